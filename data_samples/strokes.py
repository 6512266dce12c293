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
        Cell size, metres (brushes are 0.5 to 1 m wide, 1 to 3 segments of 1 to 3 m).
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
        # the brush's centre stays half its width plus half a metre inside the region
        r = max(1, int(round((0.5 + 0.5) / gsd)))
        inside = cv2.erode(region, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        n, comp = cv2.connectedComponents(inside)
        if n <= 1:
            continue
        flat = comp.ravel()
        order_px = np.argsort(flat, kind="stable")
        starts = np.searchsorted(flat[order_px], np.arange(n + 1))
        # a person spreads strokes over many objects: visit the regions in turn
        order = rng.permutation(np.arange(1, n))
        painted, k = 0, 0
        for _ in range(5000):
            if painted >= quota:
                break
            cid = order[k % len(order)]
            k += 1
            members = order_px[starts[cid] : starts[cid + 1]]
            y0, x0 = np.divmod(members[rng.integers(len(members))], W)
            pts = [np.array([x0, y0], float)]
            heading = rng.uniform(0, 2 * np.pi)
            for _ in range(int(rng.integers(1, 4))):
                heading += rng.normal(0, 0.6)
                step = rng.uniform(1.0, 3.0) / gsd
                pts.append(pts[-1] + step * np.array([np.cos(heading), np.sin(heading)]))
            width = max(1, int(round(rng.uniform(0.5, 1.0) / gsd)))
            pts = np.round(np.array(pts)).astype(np.int32)
            # paint in the stroke's bounding window only
            lo = np.maximum(pts.min(axis=0) - width, 0)
            hi = np.minimum(pts.max(axis=0) + width + 1, [W, H])
            win = (slice(lo[1], hi[1]), slice(lo[0], hi[0]))
            canvas = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
            cv2.polylines(canvas, [(pts - lo).reshape(-1, 1, 2)], False, 1, thickness=width)
            stroke = (canvas > 0) & (region[win] > 0) & (labels[win] == 0)
            # a careful painter lifts the brush at the region's edge
            _, parts = cv2.connectedComponents(stroke.astype(np.uint8))
            stroke &= parts == parts[y0 - lo[1], x0 - lo[0]]
            labels[win][stroke] = c
            painted += int(stroke.sum())
    return labels
