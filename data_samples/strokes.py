"""Sparse training labels painted as brush strokes, as a person would paint them."""

from __future__ import annotations

import cv2
import numpy as np

CLASSES = (1, 2, 3, 4)


def paint_strokes(
    truth: np.ndarray, gsd: float, rng: np.random.Generator, coverage: float = 0.02
) -> np.ndarray:
    """Brush strokes inside the regions of each class.

    Parameters
    ----------
    truth : (H, W) uint8
        True class map (codes 1-4).
    gsd : float
        Cell size, metres (brushes are 0.6 to 1.5 m wide, strokes 2 to 6 m per segment).
    rng : numpy.random.Generator
    coverage : float
        Fraction of the grid to label, shared equally among the classes present.

    Returns
    -------
    (H, W) uint8 labels, 0 where unlabelled.
    """
    H, W = truth.shape
    labels = np.zeros((H, W), np.uint8)
    present = [c for c in CLASSES if (truth == c).sum() > 50]
    if not present:
        return labels
    quota = coverage * H * W / len(present)
    for c in present:
        region = (truth == c).astype(np.uint8)
        painted = 0
        for _ in range(400):
            if painted >= quota:
                break
            r = max(1, int(round(rng.uniform(0.3, 0.75) / gsd)))
            inside = cv2.erode(region, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
            ys, xs = np.nonzero(inside)
            if len(xs) == 0:
                break
            k = rng.integers(len(xs))
            pts = [np.array([xs[k], ys[k]], float)]
            heading = rng.uniform(0, 2 * np.pi)
            for _ in range(int(rng.integers(2, 7))):
                heading += rng.normal(0, 0.6)
                step = rng.uniform(2.0, 6.0) / gsd
                pts.append(pts[-1] + step * np.array([np.cos(heading), np.sin(heading)]))
            canvas = np.zeros((H, W), np.uint8)
            poly = np.round(np.array(pts)).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(canvas, [poly], False, 1, thickness=2 * r + 1)
            stroke = (canvas > 0) & (region > 0) & (labels == 0)
            # a careful painter lifts the brush at the region's edge
            n, comp = cv2.connectedComponents(stroke.astype(np.uint8))
            if n > 1:
                keep = comp == comp[ys[k], xs[k]]
                stroke &= keep
            labels[stroke] = c
            painted += int(stroke.sum())
    return labels
