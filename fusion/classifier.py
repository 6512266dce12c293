"""The per-view random forest: training, saving and loading.

Saved classifiers are pickles (joblib): load only files you trust, as with any
scikit-learn model.
"""

from __future__ import annotations

import os
from pathlib import Path

import joblib
import numpy as np
from sklearn.ensemble import RandomForestClassifier

from workbench.errors import InputError

CLASSES = (1, 2, 3, 4)  # ground, grass, tree, building
CLASS_NAMES = ("ground", "grass", "tree", "building")
FORMAT = "city-workbench-forest"
RAISED = (3, 4)  # the classes that stand above the terrain: tree, building


def elevation_consistent(labels: np.ndarray, elevation: np.ndarray, split: float) -> np.ndarray:
    """(N,) bool: whether each label agrees with the elevation of what it labels.

    Trees and buildings stand above the terrain, ground and grass lie on it. A stroke
    drawn on the ortho and projected into a view can land on the other kind of surface
    (the ground seen past a crown's edge, an overhanging crown above a road); such
    pixels teach the forest that dark ground is tree.

    Parameters
    ----------
    labels : (N,) int
        Class codes 1-4 (0 unlabelled, kept as it is).
    elevation : (N,) float
        Mean elevation above the DTM of each labelled pixel's patch, metres.
    split : float
        Height separating the terrain classes from the raised ones, metres.
    """
    raised = np.isin(labels, RAISED)
    with np.errstate(invalid="ignore"):
        return (labels == 0) | np.where(raised, elevation >= split, elevation < split)


def elevation_prior(
    class_prob: np.ndarray,
    ndsm: np.ndarray,
    split: float,
    *,
    damping: float = 0.01,
    copy: bool = True,
) -> np.ndarray:
    """Class probabilities with the classes the fused nDSM contradicts damped.

    Where the surface lies on the terrain (nDSM below ``split / 2``) it is no tree and
    no building; where it stands well above it (more than ``split + 2`` metres, beyond
    the spill of roof edges onto the street) it is neither ground nor grass. Without
    this, a shadowed road that no stroke labelled goes to whichever dark class the
    forest's random splits favour (tree with one seed, ground with another). The
    damping is soft: a class every view is sure of survives it.

    Parameters
    ----------
    class_prob : (4, H, W) float
        Probabilities of ground, grass, tree, building; NaN where unseen.
    ndsm : (H, W) float
        Fused height above the DTM, metres; NaN unknown (left as it is).
    split : float
        Height separating the terrain classes from the raised ones, metres.
    damping : float
        Factor on a contradicted class's probability.
    copy : bool
        False: ``class_prob`` is damped in place when it is float32 (a city's is 100 MB).

    Returns
    -------
    (4, H, W) float32 probabilities, renormalised.
    """
    out = np.array(class_prob, np.float32) if copy else np.asarray(class_prob, np.float32)
    with np.errstate(invalid="ignore"):
        on_terrain = np.where(ndsm < split / 2, damping, 1.0)
        well_above = np.where(ndsm > split + 2.0, damping, 1.0)
    for k in range(len(out)):  # band by band: no (4, H, W) float64 temporary
        out[k] *= on_terrain if k + 1 in RAISED else well_above
    with np.errstate(invalid="ignore", divide="ignore"):
        out /= out.sum(axis=0, keepdims=True)
    return out


def train_forest(
    X: np.ndarray,
    y: np.ndarray,
    *,
    n_trees: int = 8,
    max_depth: int = 14,
    seed: int = 0,
    n_jobs: int | None = None,
) -> RandomForestClassifier:
    """Train the random forest of the paper (8 trees, depth 14 by default).

    Parameters
    ----------
    X : (N, F) float
        Feature vectors.
    y : (N,) int
        Class codes 1-4.
    seed : int
        Seed of the forest's bootstrap and feature choices.
    n_jobs : int, optional
        Parallel jobs (default: all cores).
    """
    forest = RandomForestClassifier(
        n_estimators=n_trees,
        max_depth=max_depth,
        random_state=seed,
        n_jobs=n_jobs if n_jobs is not None else os.cpu_count(),
        class_weight="balanced",
    )
    forest.fit(X, y)
    return forest


def predict_proba(forest: RandomForestClassifier, X: np.ndarray) -> np.ndarray:
    """(N, 4) probabilities of classes 1-4 (zero for classes the forest never saw)."""
    out = np.zeros((len(X), len(CLASSES)), np.float32)
    if len(X) == 0:
        return out
    p = forest.predict_proba(X)
    for j, c in enumerate(forest.classes_):
        out[:, CLASSES.index(int(c))] = p[:, j]
    return out


def save_classifier(path: str | os.PathLike, forest, *, features: str, meta: dict) -> None:
    """Save a forest with what it needs to be reused: its feature set and provenance."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    joblib.dump(
        {"format": FORMAT, "version": 1, "features": features, "meta": meta, "forest": forest}, tmp
    )
    os.replace(tmp, path)


def load_classifier(path: str | os.PathLike, *, features: str):
    """Load a forest saved by :func:`save_classifier`; check its feature set.

    Returns
    -------
    forest, meta
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, None, "classifier file not found")
    try:
        doc = joblib.load(path)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a bad file
        raise InputError(path, None, f"not a saved classifier ({type(exc).__name__})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(path, "format", "not a city-workbench classifier")
    if doc.get("features") != features:
        raise InputError(
            path, "features", f"trained on {doc.get('features')!r} features, {features!r} needed"
        )
    return doc["forest"], doc.get("meta", {})
