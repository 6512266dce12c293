"""Filling gaps in rasters: push-pull interpolation and small-hole filling."""

from __future__ import annotations

import cv2
import numpy as np


def push_pull_fill(values: np.ndarray, valid: np.ndarray, origin=(0, 0)) -> np.ndarray:
    """Fill invalid cells by pyramid (push-pull) interpolation of the valid ones.

    Each level's cells are the means of 2 x 2 cells of the level below, paired as the
    whole grid pairs them when ``values`` is a window of it (a block): a block then
    averages the same cells as the whole grid wherever its levels' cells lie inside it,
    and fills its holes alike.

    Parameters
    ----------
    values : (H, W) float
    valid : (H, W) bool
    origin : (row, col) of ``values``' first cell in the whole grid it is a window of

    Returns
    -------
    (H, W) float64 equal to ``values`` where valid, smoothly interpolated elsewhere
    (NaN everywhere only if nothing is valid).
    """
    if not valid.any():
        return np.full(values.shape, np.nan)
    if min(values.shape) <= 2 or valid.all():
        return np.where(valid, values, 0.0).astype(np.float64)
    # The first level's weights are 0 or 1: its block sums need only the valid values,
    # and its blend w v + (1 - w) up is the coarser level's value where not valid. So
    # the whole raster holds one float64 array (8 bytes a cell, not 64 in float64
    # values, weights, their product, paddings and the blend's terms).
    H, W = values.shape
    pad, (h2, w2), up_origin = _halving((H, W), origin)
    inside = (slice(pad[0], pad[0] + H), slice(pad[1], pad[1] + W))
    sums = np.zeros((2 * h2, 2 * w2))
    sums[inside][valid] = values[valid]
    vs = sums.reshape(h2, 2, w2, 2).sum(axis=(1, 3))
    del sums
    ws = np.zeros((2 * h2, 2 * w2), np.uint8)
    ws[inside] = valid
    ws = ws.reshape(h2, 2, w2, 2).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.where(ws > 0, vs / ws, 0.0)
    filled = _push_pull_coarse(v, np.minimum(ws, 1.0), up_origin)
    out = _doubled(filled, (H, W), pad)
    out[valid] = values[valid]
    return out


def _halving(shape: tuple[int, int], origin) -> tuple[tuple, tuple, tuple]:
    """How a level of ``shape`` whose first cell is ``origin`` in its level of the whole
    grid pairs its cells: the rows and columns it is padded with before them (1 where its
    first cell is the second of a pair), the next level's shape and origin."""
    pad = (origin[0] % 2, origin[1] % 2)
    half = ((pad[0] + shape[0] + 1) // 2, (pad[1] + shape[1] + 1) // 2)
    return pad, half, (origin[0] // 2, origin[1] // 2)


def _push_pull_coarse(v: np.ndarray, w: np.ndarray, origin=(0, 0)) -> np.ndarray:
    """The pyramid from a level of block means ``v`` and weights ``w`` (in [0, 1]) up:
    ``v`` blended with the next coarser level where ``w`` is under 1. ``origin``: the
    level's first cell in the whole grid's level (:func:`push_pull_fill`)."""
    levels = []
    while True:
        if min(v.shape) <= 2 or (w > 0).all():
            levels.append((v, w, None))
            break
        pad, (h2, w2), up_origin = _halving(v.shape, origin)
        levels.append((v, w, pad))
        vp = np.zeros((2 * h2, 2 * w2))
        wp = np.zeros((2 * h2, 2 * w2))
        inside = (slice(pad[0], pad[0] + v.shape[0]), slice(pad[1], pad[1] + v.shape[1]))
        vp[inside], wp[inside] = v * w, w
        ws = wp.reshape(h2, 2, w2, 2).sum(axis=(1, 3))
        vs = vp.reshape(h2, 2, w2, 2).sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            v = np.where(ws > 0, vs / ws, 0.0)
        w = np.minimum(ws, 1.0)
        origin = up_origin
    filled = levels[-1][0]
    for v, w, pad in reversed(levels[:-1]):
        filled = w * v + (1 - w) * _doubled(filled, v.shape, pad)
    return filled


def _doubled(coarse: np.ndarray, shape: tuple[int, int], pad=(0, 0)) -> np.ndarray:
    """The level ``coarse`` up by a factor of two (bilinear), cut to ``shape`` after the
    ``pad`` rows and columns of :func:`_halving`: each of its cells stands over the 2 x 2
    cells it was made of, wherever the raster ends. Resized to an odd ``shape`` instead,
    a level would be stretched by up to a cell of its own at the far side of the raster."""
    up = cv2.resize(coarse, (2 * coarse.shape[1], 2 * coarse.shape[0]),
                    interpolation=cv2.INTER_LINEAR)  # fmt: skip
    return up[pad[0] : pad[0] + shape[0], pad[1] : pad[1] + shape[1]]


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


def fill_small_holes(values: np.ndarray, valid: np.ndarray, holes: np.ndarray,
                     max_cells: int, origin: tuple[int, int] = (0, 0)) -> np.ndarray:  # fmt: skip
    """``values`` with each small hole filled by push-pull interpolation
    (:func:`push_pull_fill`) in a window about it, not over the whole raster.

    A hole of at most ``max_cells`` cells spans at most that many; the pyramid fills it
    from the level whose blocks are that wide, and the bilinear step up reaches one block
    further. A margin of ``2 * max_cells`` cells about the hole's box therefore holds
    what the whole raster's pyramid uses there, in a few kilobytes rather than 64 bytes
    a cell of the raster. The window's corners fall on the whole raster's blocks of that
    level (multiples of its power of two), so that its pyramid averages the same blocks
    and steps up by the same factor of two.

    Parameters
    ----------
    values : (H, W) or (H, W, C) array
    valid : (H, W) bool, the cells to interpolate from
    holes : (H, W) bool, the cells to fill (:func:`small_holes`)
    max_cells : int, the largest hole's cells
    origin : (row, col) of the raster's first cell in a larger grid it is a window of:
        the blocks are the larger grid's, so that a hole is filled as the whole grid
        fills it (a fusion in blocks)

    Returns
    -------
    a copy of ``values``, of its dtype (rounded for integers), filled at ``holes``
    """
    out = values.copy()
    n, labels, stats, _ = cv2.connectedComponentsWithStats(holes.astype(np.uint8), connectivity=8)
    margin = 2 * max_cells
    block = 1 << int(np.ceil(np.log2(margin)))
    H, W = holes.shape
    planes = out.reshape(H, W, -1)

    def aligned(start, stop, size, o):  # the margin added, out to the blocks' edges
        return slice(max((start + o - margin) // block * block - o, 0),
                     min(-(-(stop + o + margin) // block) * block - o, size))  # fmt: skip

    for k in range(1, n):
        x, y, w, h = stats[k, :4]
        rows, cols = aligned(y, y + h, H, origin[0]), aligned(x, x + w, W, origin[1])
        inside = labels[rows, cols] == k
        for c in range(planes.shape[2]):
            filled = push_pull_fill(planes[rows, cols, c], valid[rows, cols],
                                    (rows.start + origin[0], cols.start + origin[1]))  # fmt: skip
            if np.issubdtype(out.dtype, np.integer):
                filled = np.round(filled)
            planes[rows, cols, c][inside] = filled[inside]
    return out
