"""A terrain model (DTM) from a surface model (DSM) by a progressive morphological filter.

Zhang et al. (2003): grey openings with growing windows remove objects smaller than
the window; a cell stays ground while the DSM rises above the opened surface by less
than a threshold that grows with the window and the terrain slope. The filter runs
on a coarse grid (objects are metres wide, terrain is smooth), the ground cells are
interpolated into a surface, and the result is resampled to the DSM's grid.
"""

from __future__ import annotations

import cv2
import numpy as np

from workbench.options import LARGEST_BUILDING_M

from .interpolate import push_pull_fill

# Zhang et al. set the largest height threshold to the height of the lowest building: an
# object lower than it above the opened surface stays ground at every window. The opened
# surface follows the terrain on a building's uphill side, so the height that counts is
# that of its lowest wall: a storey (2.5 m) less the rise of a 5 % slope across a 10 m
# building. At 3 m, a 3.2 m garage of 15 x 9 m stood 3.0 m above the opening (dev seed
# 14) and became terrain; at 2.5 m, part of a 3.3 m T-shaped building on a slope, its
# roof 2.3-2.4 m above the ground uphill (dev seed 15), and every path lost that part.
LOWEST_BUILDING_M = 2.0
# the largest opening: about the largest building's width (a fused block's margin too,
# fusion.blocks, so that the opening sees the whole of a building the block's edge cuts)
LARGEST_WINDOW_M = LARGEST_BUILDING_M


def progressive_morphological_filter(
    dsm: np.ndarray,
    cell: float,
    *,
    max_window: float = LARGEST_WINDOW_M,
    slope: float = 0.3,
    dh0: float = 0.5,
    dh_max: float = LOWEST_BUILDING_M,
    origin=(0, 0),
) -> np.ndarray:
    """(H, W) bool mask of ground cells.

    Parameters
    ----------
    dsm : (H, W) float
        Surface heights, metres; NaN cells are never ground.
    cell : float
        Cell size, metres.
    max_window : float
        Largest window, metres: about the largest building's width.
    slope : float
        Terrain slope allowance (rise over run) for the height threshold.
    dh0, dh_max : float
        Initial and largest height thresholds, metres; ``dh_max`` below the lowest
        building's height.
    origin : (row, col) of the first cell in the whole grid ``dsm`` is a block of
    """
    valid = np.isfinite(dsm)
    surface = push_pull_fill(dsm, valid, origin).astype(np.float32)
    ground = valid.copy()
    largest = max(3, int(max_window / cell) | 1)
    windows = [w for w in (2 * 2**k + 1 for k in range(32)) if w < largest] + [largest]
    prev_w = 1
    opened = surface
    for w in windows:
        kernel = np.ones((w, w), np.uint8)
        opened = cv2.morphologyEx(opened, cv2.MORPH_OPEN, kernel)
        dh = min(dh0 + slope * (w - prev_w) * cell, dh_max)
        ground &= (surface - opened) <= dh
        prev_w = w
    return ground


def dtm_from_dsm(
    dsm: np.ndarray, gsd: float, *, coarse: float = 1.0, origin=(0, 0), **kw
) -> tuple[np.ndarray, np.ndarray]:
    """DTM and ground mask of a DSM.

    Parameters
    ----------
    dsm : (H, W) float
        Surface heights, metres, NaN where unknown.
    gsd : float
        Cell size of ``dsm``, metres.
    coarse : float
        Cell size at which the filter runs, metres (at least ``gsd``).
    origin : (row, col) of the first cell in the whole grid ``dsm`` is a block of: the
        coarse cells and the interpolation's levels are the whole grid's, so that a block
        gives the whole grid's DTM where its margin holds what that depends on
    **kw
        Passed to :func:`progressive_morphological_filter`.

    Returns
    -------
    dtm : (H, W) float32, defined everywhere the DSM's extent reaches
    ground : (H, W) bool, cells of the DSM judged ground
    """
    H, W = dsm.shape
    f = max(1, int(round(coarse / gsd)))
    r0, c0 = origin[0] % f, origin[1] % f  # the cells before the first whole coarse cell
    hc, wc = -(-(r0 + H) // f), -(-(c0 + W) // f)
    pad = np.full((hc * f, wc * f), np.nan, np.promote_types(dsm.dtype, np.float32))
    pad[r0 : r0 + H, c0 : c0 + W] = dsm
    blocks = pad.reshape(hc, f, wc, f)
    coarse_origin = (origin[0] // f, origin[1] // f)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            low = np.nanmin(
                blocks, axis=(1, 3)
            )  # the lowest return of a block is the best ground candidate
    # a 5 x 5 median removes the pits that gross depth errors leave, before the openings
    # (which follow the lowest points) can take them for terrain
    low = push_pull_fill(low, np.isfinite(low), coarse_origin).astype(np.float32)
    low = cv2.medianBlur(low, 5)
    ground_c = progressive_morphological_filter(low, gsd * f, origin=coarse_origin, **kw)
    dtm_c = push_pull_fill(low, ground_c, coarse_origin).astype(np.float32)
    dtm = cv2.resize(dtm_c, (wc * f, hc * f), interpolation=cv2.INTER_LINEAR)
    dtm = dtm[r0 : r0 + H, c0 : c0 + W]
    ground = np.isfinite(dsm) & (np.abs(dsm - dtm) < kw.get("dh0", 0.5) + 0.25)
    # refine at full resolution: interpolate the ground cells only
    dtm = push_pull_fill(dsm, ground, origin).astype(np.float32)
    np.minimum(dtm, np.where(np.isfinite(dsm), dsm, np.inf), out=dtm)
    return dtm, ground
