"""Filling gaps in rasters: push-pull interpolation and small-hole filling."""

from __future__ import annotations

import cv2
import numpy as np


def push_pull_fill(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill invalid cells by pyramid (push-pull) interpolation of the valid ones.

    Parameters
    ----------
    values : (H, W) float
    valid : (H, W) bool

    Returns
    -------
    (H, W) float64 equal to ``values`` where valid, smoothly interpolated elsewhere
    (NaN everywhere only if nothing is valid).
    """
    v = np.where(valid, values, 0.0).astype(np.float64)
    w = valid.astype(np.float64)
    if not w.any():
        return np.full(values.shape, np.nan)
    levels = []
    while True:
        levels.append((v, w))
        if min(v.shape) <= 2 or (w > 0).all():
            break
        h2, w2 = (v.shape[0] + 1) // 2, (v.shape[1] + 1) // 2
        vp = np.pad(v * w, ((0, 2 * h2 - v.shape[0]), (0, 2 * w2 - v.shape[1])))
        wp = np.pad(w, ((0, 2 * h2 - w.shape[0]), (0, 2 * w2 - w.shape[1])))
        ws = wp.reshape(h2, 2, w2, 2).sum(axis=(1, 3))
        vs = vp.reshape(h2, 2, w2, 2).sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            v = np.where(ws > 0, vs / ws, 0.0)
        w = np.minimum(ws, 1.0)
    filled, _ = levels[-1]
    for v, w in reversed(levels[:-1]):
        up = cv2.resize(filled, (v.shape[1], v.shape[0]), interpolation=cv2.INTER_LINEAR)
        filled = w * v + (1 - w) * up
    out = filled
    out[valid] = values[valid]
    return out


def small_holes(missing: np.ndarray, max_cells: int) -> np.ndarray:
    """(H, W) bool: the connected parts of ``missing`` of at most ``max_cells`` cells
    that do not touch the raster's border."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(missing.astype(np.uint8), connectivity=8)
    area = stats[:, cv2.CC_STAT_AREA]
    x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    w, h = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    H, W = missing.shape
    inner = (x > 0) & (y > 0) & (x + w < W) & (y + h < H)
    keep = (area <= max_cells) & inner
    keep[0] = False
    return keep[labels] & missing
