"""The class CRF on super-pixels (the super-pixel paper, section 4.2, eq. 2-3)."""

from __future__ import annotations

import numpy as np

from modeling.shared.graph_cuts import alpha_expansion

from .aggregation import SuperpixelGraph

OMEGA_CANDIDATES = (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 12.0)


def refine_classes(graph: SuperpixelGraph, omega: float) -> np.ndarray:
    """The class CRF on super-pixels (eq. 2 and 3), by alpha-expansion over the classes.

    Unary: -log of the super-pixel's aggregated (mean) class likelihood, counted once per
    cell of the super-pixel, so that it grows with the area as the pairwise term (the
    number of boundary cells) grows with the perimeter; pairwise: b / (1 + g) for
    differing labels.

    Returns
    -------
    (N,) class codes 1..C.
    """
    likelihood = graph.class_sum / np.maximum(graph.count, 1)[:, None]
    unary = -np.log(np.clip(likelihood, 1e-6, 1.0)) * graph.count[:, None]
    return alpha_expansion(unary, graph.edges, graph.pairwise, omega) + 1


def choose_omega_class(graph: SuperpixelGraph, labels: np.ndarray, strokes: np.ndarray) -> dict:
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
        pred = refine_classes(graph, omega)[labels]
        c = classification(np.where(strokes > 0, pred, 0), strokes)
        scores[omega] = c.get("mean_class_accuracy", 0.0)
    best = max(scores, key=lambda w: (scores[w], -abs(np.log(w / 3.0))))  # ties: nearest 3
    return {"omega": best, "scores": scores}
