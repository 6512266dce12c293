"""Train the raster forest the fusion uses on clouds without training labels.

Run once (``make setup`` does): ``python -m data_samples.raster_forest [FILE]``. It
generates the ``tiny`` synthetic city for seeds 0 and 1 (deterministic), pools their
true rasters to 0.25, 0.5 and 1 m cells, and fits a random forest on
:func:`fusion.raster_forest.raster_features`; the fusion reads it from
:func:`fusion.raster_forest.cache_path`.
"""

from __future__ import annotations

import logging
import sys
import tempfile
from pathlib import Path

import numpy as np

from fusion.classifier import CLASSES, save_classifier, train_forest
from fusion.ground import dtm_from_dsm
from fusion.raster_forest import FEATURES, N_FEATURES, cache_path, raster_features
from workbench.raster import read_raster

from .generate import generate_sample

log = logging.getLogger(__name__)


def train_raster_forest(path: str | Path | None = None, *, seed: int = 0) -> Path:
    """Train the forest and save it to ``path`` (default: the fusion's cache); return it."""
    path = path or cache_path()
    log.info("training the raster forest on the synthetic city (once)")
    with tempfile.TemporaryDirectory() as tmp:
        X, y = [], []
        for s in (0, 1):
            scene = Path(tmp) / f"city{s}"
            generate_sample(scene, "tiny", s)
            dsm, grid, _ = read_raster(scene / "truth" / "dsm.tif")
            ortho = np.moveaxis(read_raster(scene / "truth" / "ortho.tif")[0], 0, -1)
            truth = read_raster(scene / "truth" / "class.tif")[0][0]
            for f in (1, 2, 4):  # 0.25, 0.5 and 1 m cells: LiDAR rasters come in all sizes
                d, o, t = _pool(dsm[0], ortho, truth, f)
                dtm, _ = dtm_from_dsm(d, grid.gsd * f)
                X.append(raster_features(d, dtm, o, grid.gsd * f).reshape(-1, N_FEATURES))
                y.append(t.ravel())
    X, y = np.concatenate(X), np.concatenate(y)
    rng = np.random.default_rng(seed)
    keep = np.concatenate(
        [
            rng.choice(np.flatnonzero(y == k), min(15000, int((y == k).sum())), replace=False)
            for k in CLASSES
            if (y == k).any()
        ]
    )
    forest = train_forest(X[keep], y[keep], n_trees=16, max_depth=14, seed=seed)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_classifier(
        path,
        forest,
        features=FEATURES,
        meta={"trained_on": "synthetic city tiny, seeds 0 and 1", "seed": seed},
    )
    return path


def _pool(dsm, ortho, truth, f: int):
    """Coarser rasters as a cloud would give them: highest point, mean colour, top class."""
    if f == 1:
        return dsm, ortho, truth
    H, W = (dsm.shape[0] // f) * f, (dsm.shape[1] // f) * f
    d = dsm[:H, :W].reshape(H // f, f, W // f, f)
    top = d.reshape(H // f, f, W // f, f).transpose(0, 2, 1, 3).reshape(H // f, W // f, f * f)
    arg = np.argmax(top, axis=-1)
    t = (
        truth[:H, :W]
        .reshape(H // f, f, W // f, f)
        .transpose(0, 2, 1, 3)
        .reshape(H // f, W // f, -1)
    )
    cls = np.take_along_axis(t, arg[..., None], axis=-1)[..., 0]
    o = ortho[:H, :W].reshape(H // f, f, W // f, f, 3).mean(axis=(1, 3)).astype(np.uint8)
    return top.max(axis=-1), o, cls


def main(argv: list[str]) -> int:
    """``[FILE] [--force]``: train into FILE (default the cache) unless it exists."""
    files = [a for a in argv if a != "--force"]
    path = Path(files[0]) if files else cache_path()
    if path.exists() and "--force" not in argv:
        return 0
    print(f"raster forest: training on the synthetic city into {path} ...", flush=True)
    train_raster_forest(path)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
