"""The class CRF on super-pixels (the super-pixel paper, section 4.2, eq. 2-3)."""

from __future__ import annotations

import numpy as np

from workbench.graph_cuts import alpha_expansion
from workbench.raster import BUILDING, TREE

from .aggregation import SuperpixelGraph

OMEGA_CANDIDATES = (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 12.0)
MIN_STROKE_SUPERPIXELS = 5  # per class, to learn its plane residuals from


def refine_classes(
    graph: SuperpixelGraph, omega: float, geometry: np.ndarray | None = None
) -> np.ndarray:
    """The class CRF on super-pixels (eq. 2 and 3), by alpha-expansion over the classes.

    Unary: -log of the super-pixel's aggregated (mean) class likelihood, times the
    ``geometry`` factor (N, C) when given (:func:`geometry_factor`, ours), counted once
    per cell of the super-pixel, so that it grows with the area as the pairwise term (the
    number of boundary cells) grows with the perimeter; pairwise: b / (1 + g) for
    differing labels.

    Returns
    -------
    (N,) class codes 1..C.
    """
    likelihood = graph.class_sum / np.maximum(graph.count, 1)[:, None]
    if geometry is not None:
        likelihood = likelihood * geometry
        likelihood /= np.maximum(likelihood.sum(axis=1, keepdims=True), 1e-12)
    unary = -np.log(np.clip(likelihood, 1e-6, 1.0)) * graph.count[:, None]
    return alpha_expansion(unary, graph.edges, graph.pairwise, omega) + 1


def stroke_classes(labels: np.ndarray, strokes: np.ndarray, n: int) -> np.ndarray:
    """(n,) the class of the training strokes covering most of each super-pixel (at
    least half of its cells), 0 for none."""
    out = np.zeros(n, np.int64)
    count = np.bincount(labels.ravel(), minlength=n)
    for c in np.unique(strokes[strokes > 0]):
        share = np.bincount(labels.ravel(), (strokes == c).ravel(), minlength=n)
        out[share >= 0.5 * count] = c
    return out


def geometry_factor(graph: SuperpixelGraph, stroked: np.ndarray) -> tuple[np.ndarray | None, dict]:
    """(N, C) factors on the class likelihoods from each super-pixel's plane residual
    (ours, not the paper's): a roof face is planar whatever its colour, a crown lumpy.

    The log residuals of tree and of building are modelled as normal with one spread
    pooled over both classes (as linear discriminant analysis does), each mean fitted to
    the super-pixels the training strokes mark as that class (``stroked`` (N,) from
    :func:`stroke_classes`); a super-pixel's tree and building factors are the two
    densities at its residual, normalised to sum to 2 (1 each where they agree or the
    residual is unknown). Ground and grass, both flat, keep 1. A spread of its own per
    class, fitted to the 5-8 building super-pixels the strokes mark, came out as narrow as
    0.22 and made every roof face a little rougher than those few a tree (held-out seed 3:
    15 buildings lost). None (and why) when the strokes mark fewer than
    ``MIN_STROKE_SUPERPIXELS`` of either class.

    Returns
    -------
    factors or None, and a record of the fitted means and spread.
    """
    fitted, record = fit_geometry(graph, stroked)
    return (None if fitted is None else geometry_factors(graph, *fitted)), record


def fit_geometry(graph: SuperpixelGraph, stroked: np.ndarray) -> tuple[tuple | None, dict]:
    """:func:`geometry_factor`'s fit: ({class: mean log residual}, pooled spread) or None,
    and its record."""
    r = np.log(np.maximum(graph.plane_residual, 1e-3))
    means, deviations, counts = {}, [], {}
    for c, name in ((TREE, "tree"), (BUILDING, "building")):
        v = r[(stroked == c) & np.isfinite(r)]
        if len(v) < MIN_STROKE_SUPERPIXELS:
            return None, {"used": False, "reason": f"fewer than {MIN_STROKE_SUPERPIXELS} "
                          f"{name} super-pixels under the strokes"}  # fmt: skip
        means[c], counts[c] = float(np.mean(v)), len(v)
        deviations.append(v - means[c])
    d = np.concatenate(deviations)
    sigma = max(float(np.sqrt(np.sum(d**2) / (len(d) - 2))), 0.1)
    record = {"used": True, "log_sigma": round(sigma, 3)}
    for c, name in ((TREE, "tree"), (BUILDING, "building")):
        record[name] = {"median_residual_m": round(float(np.exp(means[c])), 4),
                        "superpixels": counts[c]}  # fmt: skip
    return (means, sigma), record


def geometry_factors(graph: SuperpixelGraph, means: dict, sigma: float) -> np.ndarray:
    """(N, C) :func:`geometry_factor`'s factors from a fit (:func:`fit_geometry`), which
    may be another graph's: a grid in blocks applies one block's fit to every block."""
    r = np.log(np.maximum(graph.plane_residual, 1e-3))
    log_density = {c: -0.5 * ((r - m) / sigma) ** 2 for c, m in means.items()}
    # the two factors 2 / (1 + exp(other - own)), computed from the difference
    diff = log_density[TREE] - log_density[BUILDING]
    ok = np.isfinite(diff)
    out = np.ones((graph.n, graph.class_sum.shape[1]))
    out[ok, TREE - 1] = 2.0 / (1.0 + np.exp(-diff[ok]))
    out[ok, BUILDING - 1] = 2.0 - out[ok, TREE - 1]
    return out


def choose_omega_class(
    graph: SuperpixelGraph,
    labels: np.ndarray,
    strokes: np.ndarray,
    geometry: np.ndarray | None = None,
) -> dict:
    """Pick the class CRF's omega by its mean class accuracy on the training strokes.

    Parameters
    ----------
    graph : SuperpixelGraph
    labels : (H, W) int
        Super-pixels.
    strokes : (H, W) int
        Training labels 1..4, 0 unlabelled.

    Returns
    -------
    {"omega": best, "scores": {omega: mean class accuracy}}. The strokes also trained the
    per-view forest, so the scores favour trusting it (small omega) a little.
    """
    from workbench.metrics import classification

    scores = {}
    for omega in OMEGA_CANDIDATES:
        pred = refine_classes(graph, omega, geometry)[labels]
        c = classification(np.where(strokes > 0, pred, 0), strokes)
        scores[omega] = c.get("mean_class_accuracy", 0.0)
    best = max(scores, key=lambda w: (scores[w], -abs(np.log(w / 3.0))))  # ties: nearest 3
    return {"omega": best, "scores": scores}
