"""The ceiling over the cells no view saw: the lowest height at which some view sees
through a cell's column, past it, to a surface beyond.

A cell stays unknown when every view's ray to it meets something first: the tall part
of a building hides its lower tier, or the ground behind its wall. What stands in such
a cell stands below every ray that passes over it, or that ray would have stopped there
(the free space a depth map carves, as volumetric fusions use it). Below the lowest
such ray the cell could hold anything; above it, nothing. A modeling path that puts a
hidden part into a building's outline asks the ceiling whether the part's level fits
under it (:func:`modeling.shared.opened_parts.unseen_parts`): a lower tier hidden
behind a taller one does (the rays pass over the taller part's edge and above the tier);
the ground beyond a wall, at the wall's height, does not (the rays that saw the ground
further out passed through that height).

On ``small`` seeds 0-2, 95-97.5 % of the hidden cells of buildings have a ceiling at or
above their true height (sampled every grid cell's size), and the rest lie on the
outline's edge; beside a wall it errs high by about the ramp's pixels no view trusts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.camera import Camera
from workbench.engine import Engine
from workbench.raster import Grid

from .observations import screened_depth

CHUNK_SAMPLES = 1 << 21  # heights tested at once in a view: 50 MB of float64 work arrays


@dataclass(frozen=True)
class HiddenColumns:
    """The columns to test: the unknown cells' centres (``x``, ``y``, metres, (n,)), the
    height each column starts at (``bottom``, (n,) metres: the ground under it) and the
    height none needs to be tested above (``top``: the highest surface of the grid), and
    the step between tested heights (metres); ``limit`` ((n,) metres, optional): the
    height each column needs no test above (:mod:`fusion.free_space`), columns in its
    order test fewer heights."""

    x: np.ndarray
    y: np.ndarray
    bottom: np.ndarray
    top: float
    step: float
    limit: np.ndarray | None = None


def trusted_depth(depth: np.ndarray) -> np.ndarray:
    """(H, W) float32 ``depth`` with NaN where a ray cannot be trusted to have passed
    everything nearer than its depth: gross matching errors (:func:`depth_outliers`)
    and the ramps dense matching draws across depth jumps (:func:`depth_jumps`, but not
    a jump's nearer surface, :func:`near_side`), whose depth floats between the two
    surfaces."""
    depth, jumps, side = screened_depth(depth)
    return np.where(jumps & (side == 0), np.float32(np.nan), depth).astype(np.float32)


def column_ceilings(
    camera: Camera,
    depth: np.ndarray,
    columns: HiddenColumns,
    tolerance: float,
    seen: np.ndarray | None = None,
) -> np.ndarray:
    """(n,) float32, for each column, the lowest of its tested heights that the view
    sees past: the point projects onto a pixel whose depth lies more than ``tolerance``
    metres beyond the point's; +inf where the view sees past none of them. The tested
    heights are the multiples of ``step`` from the one below the column's ``bottom`` up
    to ``top`` (and to the column's ``limit`` where given): the same whatever the other
    columns, so that a block of the grid gives a column what the whole grid gives it.

    Parameters
    ----------
    camera : Camera
    depth : (H, W) float32
        The view's z-depth, metres, NaN unknown or untrusted (:func:`trusted_depth`).
    columns : HiddenColumns
    tolerance : float
        Depth band behind a point within which the pixel's surface may be the point's
        own, metres (the fusion's visibility tolerance).
    seen : (n,) bool, optional
        :func:`columns_in_view` of the camera and columns, if the caller has it.
    """
    n = len(columns.x)
    out = np.full(n, np.inf, np.float32)
    if n == 0:
        return out
    H, W = depth.shape
    step = columns.step
    heights = _tested_heights(columns)
    low = float(heights[0])
    cam0 = _lowest_in_camera(camera, columns, low)  # (n, 3) camera frame
    up = camera.R[:, 2]  # a metre up, in the camera frame
    if seen is None:
        seen = _in_view(camera, cam0, cam0 + (columns.top - low) * up)
    flat_depth = depth.ravel()
    rise = heights - low
    rows = max(1, CHUNK_SAMPLES // len(heights))
    for a in range(0, n, rows):
        idx = np.flatnonzero(seen[a : a + rows]) + a
        if not len(idx):
            continue
        # the heights below every column's bottom are never tested, nor above every limit
        j0 = int(np.searchsorted(heights, (columns.bottom[idx] - step).min(), "left"))
        j1 = len(heights)
        if columns.limit is not None:
            j1 = int(np.searchsorted(heights, columns.limit[idx].max(), "right"))
        if j1 <= j0:
            continue
        tested = heights[j0:j1]
        pc = [cam0[idx, k][:, None] + rise[None, j0:j1] * up[k] for k in range(3)]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = camera.project_camera_frame(pc[0], pc[1], pc[2])
        u, v = np.rint(u), np.rint(v)
        inside = (pc[2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        pixel = np.where(inside, v * W + u, 0).astype(np.int64)
        observed = flat_depth[pixel]
        with np.errstate(invalid="ignore"):  # NaN depths compare False
            past = inside & (observed > pc[2] + tolerance)
        past &= tested[None, :] >= columns.bottom[idx, None] - step
        if columns.limit is not None:
            past &= tested[None, :] <= columns.limit[idx, None]
        first = past.argmax(axis=1)
        any_past = past[np.arange(len(idx)), first]
        out[idx] = np.where(any_past, tested[first], np.inf)
    return out


def _tested_heights(columns: HiddenColumns) -> np.ndarray:
    """The heights :func:`column_ceilings` tests, metres: the multiples of the step from
    the one below the lowest bottom up to the top."""
    step = columns.step
    heights = np.arange(np.floor(columns.bottom.min() / step), np.floor(columns.top / step) + 1)
    return heights * step


def _lowest_in_camera(camera: Camera, columns: HiddenColumns, low: float) -> np.ndarray:
    """(n, 3) the columns' points at height ``low`` in the camera frame, metres."""
    # positions relative to the camera: the world's projected metres lose a float32's
    # precision, and x_cam = R (X - C) needs no translation after
    base = np.column_stack([columns.x, columns.y, np.full(len(columns.x), low)]) - camera.center
    return base @ camera.R.T


def columns_in_view(camera: Camera, columns: HiddenColumns) -> np.ndarray:
    """(n,) bool: the columns whose tested heights may project into the image
    (:func:`_in_view`, conservatively); :func:`column_ceilings` tests no other, so a
    view with none needs no depth map read."""
    if len(columns.x) == 0:
        return np.zeros(0, bool)
    low = float(_tested_heights(columns)[0])
    cam0 = _lowest_in_camera(camera, columns, low)
    return _in_view(camera, cam0, cam0 + (columns.top - low) * camera.R[:, 2])


def _in_view(camera: Camera, bottom: np.ndarray, top: np.ndarray) -> np.ndarray:
    """(n,) bool: the columns from ``bottom`` to ``top`` ((n, 3) camera frame) whose
    image's bounding box meets the image, in front of the camera (conservatively)."""
    ends = []
    for p in (bottom, top):
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = camera.project_camera_frame(p[:, 0], p[:, 1], p[:, 2])
        ends.append((u, v, p[:, 2] > 0))
    (u0, v0, f0), (u1, v1, f1) = ends
    with np.errstate(invalid="ignore"):
        across = (np.fmax(u0, u1) >= -1) & (np.fmin(u0, u1) <= camera.width)
        down = (np.fmax(v0, v1) >= -1) & (np.fmin(v0, v1) <= camera.height)
    return f0 & f1 & across & down


def view_ceilings(i: int, views: list, columns: HiddenColumns, tolerance: float) -> np.ndarray:
    """Task: :func:`column_ceilings` of view ``i``."""
    v = views[i]
    seen = columns_in_view(v.camera, columns)
    if not seen.any():  # no column in the image: nothing to read
        return np.full(len(columns.x), np.inf, np.float32)
    return column_ceilings(v.camera, trusted_depth(v.read_depth()), columns, tolerance, seen)


def hidden_columns(hidden: np.ndarray, ground: np.ndarray, dsm: np.ndarray,
                   grid: Grid) -> HiddenColumns:  # fmt: skip
    """The :class:`HiddenColumns` of the ``hidden`` cells ((H, W) bool) of ``grid``: from
    ``ground`` ((H, W) metres, defined everywhere) up to the highest known cell of
    ``dsm`` ((H, W) metres, NaN unknown), every ``grid.gsd`` metres."""
    r, c = np.nonzero(hidden)
    known = dsm[np.isfinite(dsm)]
    bottom = ground[r, c].astype(np.float64)
    top = float(known.max()) if len(known) else float(bottom.max(initial=0.0))
    return HiddenColumns(grid.xmin + (c + 0.5) * grid.gsd, grid.ymax - (r + 0.5) * grid.gsd,
                         bottom, max(top, float(bottom.max(initial=top))), grid.gsd)  # fmt: skip


def hidden_ceilings(engine: Engine, shared_views, n_views: int, grid: Grid, dsm: np.ndarray,
                    ground: np.ndarray, tolerance: float) -> np.ndarray:  # fmt: skip
    """(H, W) float32 the ceiling of each cell ``dsm`` leaves unknown (NaN): the lowest
    height at which a view sees through its column (a view's task each, the lowest over
    them); the highest surface of the grid where no view sees through it; NaN on the
    known cells.

    Parameters
    ----------
    engine : Engine
    shared_views : the engine's handle on the views (each with ``camera`` and
        ``read_depth()``)
    n_views : int
    grid : Grid
    dsm : (H, W) float, metres, NaN unknown
    ground : (H, W) float, metres, defined everywhere (the fusion's filled DTM)
    tolerance : float
        The fusion's visibility tolerance, metres.
    """
    hidden, columns = hidden_columns_of(dsm, ground, grid)
    ceiling = np.full(len(columns.x), np.float32(columns.top), np.float32)
    if len(columns.x):
        shared_columns = engine.share(columns)  # a city's are megabytes: sent once
        for seen in engine.map(view_ceilings, range(n_views), shared_views, shared_columns,
                               tolerance, stage="ceiling"):  # fmt: skip
            np.minimum(ceiling, seen, out=ceiling)
    return ceiling_raster(hidden, ceiling)


def hidden_columns_of(dsm: np.ndarray, ground: np.ndarray,
                      grid: Grid) -> tuple[np.ndarray, HiddenColumns]:  # fmt: skip
    """The cells ``dsm`` leaves unknown ((H, W) bool) and their :func:`hidden_columns`
    (none when there are none)."""
    hidden = ~np.isfinite(dsm)
    if not hidden.any():
        none = np.zeros(0)
        return hidden, HiddenColumns(none, none, none, 0.0, grid.gsd)
    return hidden, hidden_columns(hidden, ground, dsm, grid)


def ceiling_raster(hidden: np.ndarray, ceiling: np.ndarray) -> np.ndarray:
    """(H, W) float32 ``ceiling`` ((n,) per hidden cell, in row-major order) on the
    ``hidden`` cells ((H, W) bool), NaN elsewhere."""
    out = np.full(hidden.shape, np.nan, np.float32)
    out[hidden] = ceiling
    return out
