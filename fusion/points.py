"""LiDAR point clouds (read by :mod:`.point_clouds`) rasterised into the ortho products.

DSM: the highest return per cell, read at the cell's centre on the triangulation of those
returns (a return may lie half a cell from the centre it stands for), and empty cells
inside the coverage filled the same way; ortho: the colour (or intensity) of that return;
classes: its LAS classification, ASPRS codes mapped to ours, or for unclassified returns
the class their geometry and echoes give (:mod:`.point_classes`); DTM: the ground class
where the file has one, the progressive morphological filter otherwise. Lengths are in the
CRS's units (US survey feet stay feet); metric parameters are converted.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from workbench.engine import Engine, ThreadEngine
from workbench.grid_blocks import Block, auto_block_size, block_layout
from workbench.raster import Grid, class_codes
from workbench.records import StageTimer, peak_memory_mb

from .cloud_survey import (
    RETURNS_PER_CELL,
    Survey,
    cell_holding,
    covered_area,
    spilled_survey,
)
from .ground import LARGEST_WINDOW_M, LOWEST_BUILDING_M, dtm_from_dsm
from .interpolate import fill_small_holes, push_pull_fill, small_holes
from .options import FusionOptions
from .point_classes import LOW_M, UNCLASSIFIED, classify_returns
from .point_clouds import PointCloud
from .scene_fusion import FILLED, HOLE_CELLS, FusionResult, check_memory, workers_in_memory

log = logging.getLogger(__name__)

# ASPRS LAS classification -> workbench class (1 ground, 2 grass, 3 tree, 4 building)
ASPRS_TO_CLASS = {2: 1, 3: 2, 4: 3, 5: 3, 6: 4, 9: 1, 11: 1}


def default_gsd(xyz: np.ndarray, returns_per_cell: float = RETURNS_PER_CELL) -> float:
    """Cell size for a cloud: the cell that holds ``returns_per_cell`` returns on average.

    The density is counted over the ground the cloud covers (:func:`covered_area`), not
    its bounding box, so that water and the corners of a tile do not coarsen the cell. At
    one return per cell about a third of the cells hold none (Poisson; rows of them
    between scan lines): :func:`top_surface_raster` fills those inside the coverage.
    Measured against coarser cells that hold two or three returns
    (``benchmarks/terrace.py``, the AHN3 clouds), the finer cell with its gaps filled
    models roofs better: docs/fusion.md gives the figures. A survey of many tiles sums
    their returns and covered areas (:meth:`Survey.default_gsd`).

    Returns
    -------
    float, in the units of ``xyz``, rounded to two significant digits.
    """
    return cell_holding(returns_per_cell, len(xyz) / covered_area(xyz[:, :2]))


def _top_per_cell(cells: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Index of the highest point of every occupied cell."""
    order = np.lexsort((z, cells))
    last = np.ones(len(order), bool)
    last[:-1] = cells[order][1:] != cells[order][:-1]
    return order[last]


def top_surface_at_cells(
    xyz: np.ndarray,
    grid: Grid,
    cells: np.ndarray,
    fallback: np.ndarray,
    max_slope_deg: float = 70.0,
    chunk: int = 1 << 20,
) -> np.ndarray:
    """Heights at the centres of ``grid``'s cells ``cells`` of the surface through the
    highest returns ``xyz`` (K, 3), one per occupied cell.

    Each centre takes the height of the Delaunay triangle of the returns (scipy) that holds
    it. A return sits anywhere in its cell: on a 40-degree roof, taking its height for the
    centre's errs by up to 0.4 cell sizes. Where the triangle is steeper than
    ``max_slope_deg`` (it spans a wall or a crown's edge) or no triangle holds the centre
    (the hull's rim), the centre keeps ``fallback``, so that edges stay sharp.

    The centres are found by scanning each triangle row by row, not by locating each
    centre in the triangulation: scipy's ``find_simplex`` first computes and keeps a
    barycentric transform of every triangle (LAPACK, 48 bytes a triangle), which took a
    block of the city's LiDAR from 2.2 to 3.1 GiB. A centre on an edge two triangles share
    takes the gentle one's height (their heights agree along the edge), then the one it
    lies deeper in.

    Parameters
    ----------
    cells : (M,) int, flat indices of the cells wanted
    fallback : (M,) float, height of the return that stands for each cell (its own
        cell's, or the nearest)
    chunk : triangles scanned at once (bounds the memory)

    Returns
    -------
    (M,) float heights, in the units of ``xyz``.
    """
    from scipy.spatial import Delaunay, QhullError

    fallback = np.asarray(fallback, np.float64)
    out = fallback.copy()
    if len(xyz) < 3 or not len(cells):
        return out
    origin = xyz[:, :2].min(axis=0)  # qhull's precision is relative to the coordinates
    try:
        simplices = Delaunay(xyz[:, :2] - origin).simplices
    except QhullError:  # all returns on a line
        return out
    slot = np.full(grid.width * grid.height, -1, np.int64)
    slot[cells] = np.arange(len(cells))
    score = np.full(len(cells), -np.inf)
    cos_max = np.cos(np.radians(max_slope_deg))
    for k in range(0, len(simplices), chunk):
        corners = xyz[simplices[k : k + chunk]]  # (n, 3, 3)
        # corners in cell units, centres at whole numbers (col, row)
        u = (corners[..., 0] - grid.xmin) / grid.gsd - 0.5
        v = (grid.ymax - corners[..., 1]) / grid.gsd - 0.5
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        gentle = np.abs(normal[:, 2]) >= cos_max * np.linalg.norm(normal, axis=1)
        tri, col, row = _centres_in_triangles(u, v, grid.width, grid.height)
        at = slot[row * grid.width + col]
        wanted = at >= 0
        tri, col, row, at = tri[wanted], col[wanted], row[wanted], at[wanted]
        w = _barycentric(u[tri], v[tri], col, row)
        depth = w.min(axis=1)
        inside = depth >= -1e-9
        tri, at, w, depth = tri[inside], at[inside], w[inside], depth[inside]
        preference = depth + 2.0 * gentle[tri]  # gentle first, then deeper inside
        order = np.lexsort((preference, at))
        last = np.r_[at[order][1:] != at[order][:-1], True]
        best = order[last]
        best = best[preference[best] > score[at[best]]]
        score[at[best]] = preference[best]
        height = np.einsum("mk,mk->m", w[best], corners[tri[best], :, 2])
        out[at[best]] = np.where(gentle[tri[best]], height, fallback[at[best]])
    return out


_SLACK = 1e-3  # cells added to a triangle's span on each side for its candidate centres


def _centres_in_triangles(u: np.ndarray, v: np.ndarray, width: int, height: int):
    """The cell centres (whole ``col``, ``row``) in or on each triangle (corners ``u``,
    ``v``, (n, 3) in cell units) on a grid of ``width`` x ``height``, row by row along
    the triangle's span (scan conversion): (triangle, col, row), each (P,) int64.

    Not the triangles' boxes: a triangle across a void (a lake, a dark roof) is long and
    thin, and its box can hold millions of cells it does not; the triangles of a
    triangulation tile its hull, so their centres are about the hull's cells."""
    # candidates a little wide: the barycentric test decides, and its tolerance, in parts
    # of a triangle's altitudes, reaches further out of a large one than a fixed width
    r0 = np.clip(np.ceil(v.min(axis=1) - _SLACK), 0, height).astype(np.int64)
    r1 = np.clip(np.floor(v.max(axis=1) + _SLACK), -1, height - 1).astype(np.int64)
    t, step = _runs(np.maximum(r1 - r0 + 1, 0))
    row = r0[t] + step
    lo, hi = np.full(len(t), np.inf), np.full(len(t), -np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):  # where each edge crosses the row (or nearly)
        ua, va, ub, vb = u[t, a], v[t, a], u[t, b], v[t, b]
        crosses = (np.minimum(va, vb) - _SLACK <= row) & (row <= np.maximum(va, vb) + _SLACK)
        flat = va == vb  # an edge along the row: both its ends
        with np.errstate(invalid="ignore", divide="ignore"):
            x = ua + np.clip((row - va) / (vb - va), 0.0, 1.0) * (ub - ua)
        lo = np.where(crosses, np.fmin(lo, np.where(flat, np.minimum(ua, ub), x)), lo)
        hi = np.where(crosses, np.fmax(hi, np.where(flat, np.maximum(ua, ub), x)), hi)
    c0 = np.clip(np.ceil(lo - _SLACK), 0, width).astype(np.int64)
    c1 = np.clip(np.floor(hi + _SLACK), -1, width - 1).astype(np.int64)
    k, step = _runs(np.maximum(c1 - c0 + 1, 0))
    return t[k], c0[k] + step, row[k]


def _runs(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Runs of ``counts[i]`` items for each ``i``, laid end to end: each item's run ``i``
    and its place in it (0, 1, ...), each (sum(counts),) int64."""
    owner = np.repeat(np.arange(len(counts)), counts)
    return owner, np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)


def _barycentric(u: np.ndarray, v: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """(P, 3) barycentric coordinates of points (``px``, ``py``) in triangles with corners
    (``u``, ``v``), each (P, 3); NaN for a triangle of no area."""
    au, av = u[:, 0] - px, v[:, 0] - py
    bu, bv = u[:, 1] - px, v[:, 1] - py
    cu, cv = u[:, 2] - px, v[:, 2] - py
    w = np.column_stack([bu * cv - bv * cu, cu * av - cv * au, au * bv - av * bu])
    area = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return w / np.where(area != 0, area, np.nan)[:, None]


def fuse_points(paths, opts: FusionOptions | None = None, *, crs: str | None = None):
    """Rasterise a point cloud, or tiles of one (files or folders), into a
    :class:`FusionResult`, the whole grid at once.

    Returns
    -------
    result : FusionResult
    crs : CRS or None
    inputs : dict summary of the cloud
    """
    opts = opts or FusionOptions()
    timer = StageTimer()
    with tempfile.TemporaryDirectory(prefix=".points-scratch-") as scratch:
        with timer.stage("read"):
            survey = spilled_survey(paths, opts, crs, Path(scratch))
        grid = survey.grid(opts)
        return fuse_survey(survey, grid, opts, timer)


def fuse_survey(survey: Survey, grid: Grid, opts: FusionOptions, timer: StageTimer):
    """:func:`fuse_points` of a survey read (:func:`spilled_survey`), on its whole grid."""
    check_memory(grid, opts, 1)
    whole = (slice(0, grid.height), slice(0, grid.width))
    with timer.stage("read"):
        cloud, cells = survey.returns_in(grid, *whole)
    products, figures = cloud_products(cloud, cells, grid, survey, opts, timer)
    p = products
    record = points_record(survey, opts, figures, timer)
    result = FusionResult(grid, p["ortho"], p["dsm"], p["dtm"], p["ndsm"], p["class_prob"],
                          p["count"], {}, record, None)  # fmt: skip
    return result, survey.crs, points_inputs(survey)


def cloud_products(cloud: PointCloud, cells: np.ndarray, grid: Grid, survey: Survey,
                   opts: FusionOptions, timer: StageTimer, origin=(0, 0), zone=None):  # fmt: skip
    """The fusion's rasters from the returns of a grid or a block.

    Parameters
    ----------
    cloud : the returns (kept: no noise)
    cells : (N,) int64, each return's flat cell index in ``grid``
    grid : the grid, or a block's window of it
    survey : what the whole survey decides (the intensity drawn white, the DTM's source)
    origin : (row, col) of the block's first cell in the whole grid (small holes are
        filled on the whole grid's blocks, :func:`~fusion.interpolate.fill_small_holes`)
    zone : (rows, cols) slices, optional: the cells whose DSM is read on the
        triangulation (a block's inside and :data:`DSM_MARGIN_CELLS`); default all

    Returns
    -------
    products : {ortho, dsm, dtm, ndsm, class_prob, classes, count}
    figures : {filled_cells, fill_radius, dtm_source, cells_by_geometry, cells_classed,
        triangulated (top returns, one a cell, in ``zone``)}
    """
    xyz, unit = cloud.xyz, survey.unit
    with timer.stage("rasterise"):
        top = _top_per_cell(cells, xyz[:, 2])
        radius = opts.fill_radius / unit if opts.fill_radius is not None else 2.0 * grid.gsd
        dsm, tops, count, filled, source = top_surface_raster(xyz, cells, top, grid, radius,
                                                              origin, zone)  # fmt: skip
        # the return whose colour and class each cell takes
        at = np.flatnonzero(source >= 0)
        returns = top[source[at]]
        ortho = _ortho(cloud, at, returns, grid, survey.intensity_white)
    with timer.stage("ground"):
        dtm, dtm_source = cloud_dtm(xyz, cells, cloud.classification, dsm, tops, grid, unit,
                                    survey.ground_class, origin)  # fmt: skip
        ndsm = (dsm - dtm).astype(np.float32)
    with timer.stage("classes"):
        prob, by_geometry = cloud_classes(cloud, at, returns, cells, dtm, grid, unit)
    count16 = np.minimum(count, np.iinfo(np.int16).max).astype(np.int16)
    count16[filled] = FILLED
    products = {"ortho": ortho, "dsm": dsm, "dtm": dtm, "ndsm": ndsm, "class_prob": prob,
                "classes": class_codes(prob), "count": count16}  # fmt: skip
    triangulated = len(top) if zone is None else int(_in_zone(cells[top], grid.width, zone).sum())
    figures = {"filled_cells": int(filled.sum()), "fill_radius": round(radius, 6),
               "dtm_source": dtm_source, "cells_by_geometry": by_geometry,
               "cells_classed": len(returns), "triangulated": triangulated}  # fmt: skip
    return products, figures


def points_inputs(survey: Survey) -> dict:
    """The record's summary of the survey."""
    return {
        "points": [str(f) for f in survey.files],
        "n_points": survey.n_points,
        "n_points_used": survey.n_used,
        "crs": survey.crs.to_string() if survey.crs is not None else None,
        "units_per_metre": round(1.0 / survey.unit, 6),
        "has_rgb": "rgb" in survey.attributes,
        "has_intensity": "intensity" in survey.attributes,
        "has_classification": "classification" in survey.attributes,
    }  # fmt: skip


def points_record(survey: Survey, opts: FusionOptions, figures: dict, timer: StageTimer) -> dict:
    """The fusion record of a survey's rasterisation (``figures`` of
    :func:`cloud_products`, summed over the blocks when in blocks)."""
    return {
        "mode": "point cloud",
        "dtm_source": figures["dtm_source"],
        "class_source": class_source(
            survey, figures["cells_by_geometry"], figures["cells_classed"]
        ),
        "filled_cells": figures["filled_cells"],
        "fill_radius": figures["fill_radius"],
        **{k: figures[k] for k in ("blocks",) if k in figures},
        "peak_memory_mb": round(peak_memory_mb(), 1),
        **figures.get("engine", {}),
        "stages": timer.stages,
    }


def top_surface_raster(
    xyz: np.ndarray, cells: np.ndarray, top: np.ndarray, grid: Grid, fill_radius: float,
    origin: tuple[int, int] = (0, 0), zone: tuple[slice, slice] | None = None,
):  # fmt: skip
    """The DSM read at the cell centres on the top returns; empty cells inside the
    coverage filled, and small enclosed holes.

    An empty cell inside the cloud's coverage (the occupied cells closed by a disc of
    radius ``fill_radius``: gaps up to twice the radius wide, such as the rows between scan
    lines) is read on the same triangulation, or takes the nearest top return's height
    where the triangle spans a wall (as PDAL's ``writers.gdal`` fills by radius, but
    without growing the outline); larger voids stay empty but for holes of up to
    ``HOLE_CELLS`` cells, which are interpolated.

    Parameters
    ----------
    fill_radius : float
        In the units of ``xyz``.
    origin : (row, col) of ``grid``'s first cell in the whole grid it is a block of
    zone : (rows, cols) slices, optional: where to read the DSM on the triangulation of
        the top returns there (a block's inside and its :data:`DSM_MARGIN_CELLS`); the
        rest keeps ``tops``. Default: everywhere.

    Returns
    -------
    dsm : (H, W) float32, NaN unknown
    tops : (H, W) float32, each cell's own top return's height (or the nearest one's),
        holes filled as the DSM's
    count : (H, W) returns per cell
    filled : (H, W) bool, the cells with no return that were given a height
    source : (H * W,) int, index into ``top`` of the return whose colour and class each
        cell takes (its own top return, or the nearest one for filled cells), -1 for none
    """
    from scipy.ndimage import distance_transform_edt

    n = grid.width * grid.height
    occupied = np.zeros(n, bool)
    occupied[cells[top]] = True
    slot = np.full(n, -1, np.int64)
    slot[cells[top]] = np.arange(len(top))
    distance, (nr, nc) = distance_transform_edt(~occupied.reshape(grid.shape), return_indices=True)
    # inside the coverage only: a closing (dilation, then erosion, by the radius) fills
    # the gaps between scan lines but does not grow the cloud's outline
    near = distance * grid.gsd <= fill_radius
    reached = (distance_transform_edt(near) * grid.gsd > fill_radius).ravel() | occupied
    source = np.where(reached, slot[(nr * grid.width + nc).ravel()], -1)
    targets = np.flatnonzero(source >= 0)
    tops = np.full(n, np.nan)
    tops[targets] = xyz[top][source[targets], 2]
    dsm = tops.copy()
    read, used = targets, top
    if zone is not None:
        read = targets[_in_zone(targets, grid.width, zone)]
        used = top[_in_zone(cells[top], grid.width, zone)]
    dsm[read] = top_surface_at_cells(xyz[used], grid, read, tops[read])
    count = np.bincount(cells, minlength=n).reshape(grid.shape)
    dsm, tops = dsm.reshape(grid.shape), tops.reshape(grid.shape)
    known = np.isfinite(tops)  # the DSM's too
    holes = small_holes(~known, HOLE_CELLS)
    dsm, tops = (fill_small_holes(r, known, holes, HOLE_CELLS, origin).astype(np.float32)
                 for r in (dsm, tops))  # fmt: skip
    filled = (reached & ~occupied).reshape(grid.shape) | holes
    return dsm, tops, count, filled, source


def _in_zone(flat: np.ndarray, width: int, zone: tuple[slice, slice]) -> np.ndarray:
    """(N,) bool: the flat cells ``flat`` of a grid ``width`` wide within ``zone``."""
    r, c = np.divmod(flat, width)
    rows, cols = zone
    return (r >= rows.start) & (r < rows.stop) & (c >= cols.start) & (c < cols.stop)


def _ortho(cloud: PointCloud, at: np.ndarray, returns: np.ndarray, grid: Grid,
           white: float) -> np.ndarray:  # fmt: skip
    """(H, W, 3) uint8: at cells ``at`` (M,), the colour of their returns ``returns`` (M,),
    or their intensity as grey, ``white`` the intensity drawn white; black elsewhere."""
    ortho = np.zeros((grid.width * grid.height, 3), np.uint8)
    if cloud.rgb is not None:
        ortho[at] = cloud.rgb[returns]
    elif cloud.intensity is not None:
        grey = np.clip(cloud.intensity[returns] / white * 255, 0, 255).astype(np.uint8)
        ortho[at] = grey[:, None]
    return ortho.reshape(*grid.shape, 3)


def cloud_dtm(xyz, cells, cls, dsm: np.ndarray, tops: np.ndarray, grid: Grid, unit: float,
              ground_class: bool, origin=(0, 0)):  # fmt: skip
    """The DTM from the ground class (its lowest return per cell, interpolated) where the
    survey has one (``ground_class``) and the cloud holds ground returns, else the
    morphological filter on ``tops`` (each cell's top return); below the DSM, NaN where
    it is. ``origin``: the grid's first cell in the whole grid it is a block of.

    The filter opens ``tops``, not the DSM read at the centres: its windows (1 m and up)
    and height steps (0.5 m and up) do not see the centre's correction (a fraction of a
    cell's slope), and the DSM of a block is read on the triangulation near its inside
    only, while the filter reaches 80 m into its margins."""
    n = grid.width * grid.height
    if ground_class and cls is not None and (cls == 2).any():
        g = cls == 2
        ground = np.full(n, np.nan)
        gtop = _top_per_cell(cells[g], -xyz[g, 2])  # the lowest ground return per cell
        ground[cells[g][gtop]] = xyz[g][gtop, 2]
        ground = ground.reshape(grid.shape)
        dtm = push_pull_fill(ground, np.isfinite(ground), origin).astype(np.float32)
        dtm_source = "LAS ground class (2), interpolated"
    else:
        metric = dict(
            coarse=1.0 / unit,
            max_window=80.0 / unit,
            dh0=0.5 / unit,
            dh_max=LOWEST_BUILDING_M / unit,
        )
        dtm, _ = dtm_from_dsm(tops, grid.gsd, origin=origin, **metric)
        dtm_source = "progressive morphological filter"
    dtm = np.where(np.isfinite(dsm), np.minimum(dtm, dsm), np.nan).astype(np.float32)
    return dtm, dtm_source


def cloud_classes(cloud: PointCloud, at, returns, cells, dtm, grid: Grid, unit: float):
    """(4, H, W) class probabilities, one-hot: at cells ``at``, the class of their returns
    ``returns``: the ASPRS code the cloud gives, or for the returns it leaves unclassified
    (codes 0 and 1, or a cloud with no classes) the class their geometry and echoes give
    (:func:`~fusion.point_classes.classify_returns`); and how many cells took theirs so.
    Codes our classes do not hold (bridge decks, reserved codes) stay unclassified."""
    n = grid.width * grid.height
    xyz, cls = cloud.xyz, cloud.classification
    codes = np.array(cls, np.uint8, copy=True) if cls is not None else np.zeros(len(xyz), np.uint8)
    unclassified = np.isin(codes, UNCLASSIFIED)
    # only the returns that stand for a cell need a class
    needed = np.zeros(len(xyz), bool)
    needed[returns] = True
    todo = np.flatnonzero(needed & unclassified)
    if len(todo):
        hag = xyz[:, 2] - dtm.ravel()[cells]  # ``cells``: each return's flat cell index
        codes[todo] = classify_returns(xyz, hag, todo, number_of_returns=cloud.number_of_returns,
                                       rgb=cloud.rgb, low=LOW_M / unit)  # fmt: skip
    mapped = np.zeros(256, np.uint8)
    for k, v in ASPRS_TO_CLASS.items():
        mapped[k] = v
    ours = mapped[codes[returns]]
    known = ours > 0
    prob = np.full((4, n), np.nan, np.float32)
    onehot = np.zeros((4, known.sum()), np.float32)
    onehot[ours[known] - 1, np.arange(known.sum())] = 1.0
    prob[:, at[known]] = onehot
    return prob.reshape(4, *grid.shape), int(np.count_nonzero(unclassified[returns]))


def class_source(survey: Survey, by_geometry: int, cells: int) -> str:
    """Where the classes came from, for the record: ``by_geometry`` of the ``cells``
    classed took the class their geometry gives, the others their file's."""
    share = by_geometry / cells if cells else 0.0
    parts = []
    if "classification" in survey.attributes:
        parts.append(f"LAS classification (ASPRS codes mapped) for {1 - share:.1%} of the cells")
    if by_geometry:
        echo_note = "and echoes " if "number_of_returns" in survey.attributes else ""
        parts.append(
            f"their geometry {echo_note}(height above ground, neighbourhood shape) for "
            f"{share:.1%} of the cells, whose returns are unclassified"
        )
    return "; ".join(parts) or "none"


# returns in a block with its margins. A worker rasterising a block peaks at about 0.55 kB
# a return (the city's LiDAR: 1.6 GiB for a block of 3.0 million, 3.1 GiB before its
# DSM was triangulated near its inside only; 8.7 GiB for its 12.3 million whole), mostly
# the triangulation of the top returns (qhull)
BLOCK_RETURNS = 3_000_000
BYTES_PER_RETURN = 600
# A block's DSM is read on the triangulation this far past its inside, not over its 80 m
# margins (which only the ground filter needs): a small hole is filled from up to 57
# cells away (fill_small_holes: its 9 cells, 18 more, out to blocks of 32), and the
# triangles near the edge of those triangulated differ from the whole grid's (32 more)
DSM_MARGIN_CELLS = 96


def point_workers(opts: FusionOptions) -> int:
    """Blocks rasterised at once: ``opts.workers``, or as many as this machine has cores
    and as ``opts.max_memory_fraction`` of its memory holds blocks of
    :data:`BLOCK_RETURNS` returns."""
    return workers_in_memory(opts, BLOCK_RETURNS * BYTES_PER_RETURN)


def cloud_block_size(grid: Grid, survey: Survey, opts: FusionOptions) -> float | None:
    """The side of the blocks, in the CRS's units: ``opts.block`` (metres); by default
    none (the whole grid at once) for a survey of at most :data:`BLOCK_RETURNS` returns
    on at most :data:`~workbench.grid_blocks.AUTO_BLOCK_CELLS` cells a side, else blocks
    whose margins hold about that many returns at the survey's density."""
    if opts.block is not None:
        return opts.block / survey.unit
    cells = auto_block_size(grid, LARGEST_WINDOW_M / survey.unit)
    if survey.n_used <= BLOCK_RETURNS and cells is None:
        return None
    margin = LARGEST_WINDOW_M / survey.unit
    side = max(float(np.sqrt(BLOCK_RETURNS / survey.density)) - 2 * margin, margin)
    side = min(side, cells) if cells is not None else side
    # as few blocks along the longer side as hold that many returns, to 1 % (else a
    # grid a cell longer than three blocks would be cut in four)
    longest = max(grid.shape) * grid.gsd
    k = max(1, int(np.ceil(longest / side * 0.99)))
    return longest / k + grid.gsd


@dataclass
class CloudBlocks:
    """What every block of a survey's rasterisation needs: shared once with the workers,
    who read the returns from the spilled tiles (a folder every worker sees)."""

    survey: Survey
    grid: Grid
    opts: FusionOptions
    blocks: list[Block]


def block_products(k: int, ctx: CloudBlocks) -> tuple[dict, dict]:
    """Task: block ``k``'s products (:func:`cloud_products`) cut to its inside, and its
    figures with its returns and its stages' times."""
    b, timer = ctx.blocks[k], StageTimer()
    with timer.stage("read"):
        cloud, cells = ctx.survey.returns_in(ctx.grid, *b.outer)
    outer = ctx.grid.window(*b.outer)
    zone = tuple(slice(max(s.start - DSM_MARGIN_CELLS, 0), min(s.stop + DSM_MARGIN_CELLS, n))
                 for s, n in zip(b.inside, outer.shape, strict=True))  # fmt: skip
    products, figures = cloud_products(cloud, cells, outer, ctx.survey, ctx.opts, timer,
                                       b.origin, zone)  # fmt: skip
    inside = {k: v[(slice(None), *b.inside)] if k == "class_prob" else v[b.inside]
              for k, v in products.items()}  # fmt: skip
    figures["filled_cells"] = int(np.count_nonzero(inside["count"] == FILLED))  # not the margin's
    figures["occupied"] = int(np.count_nonzero(inside["count"] > 0))
    figures.update(returns=len(cells), stages=timer.stages)
    return {k: np.ascontiguousarray(v) for k, v in inside.items()}, figures


def fuse_points_in_blocks(survey: Survey, grid: Grid, opts: FusionOptions, timer: StageTimer,
                          write, block: float, engine: Engine | None = None) -> dict:  # fmt: skip
    """Rasterise a survey block by block: its memory follows the block, not the area.

    Each block, with its margin (the largest building's width: the ground's reach under
    a building and the morphological filter's largest window), is a task of ``engine``
    (:func:`block_products`; default: this process, one after another): it reads its
    returns from the spilled tiles (:meth:`Survey.returns_in`) and makes its products.
    ``write(block, products)`` takes their inside, in the blocks' order. With a store,
    finished blocks are kept there for ``--resume``.

    Parameters
    ----------
    block : float
        The blocks' side, in the CRS's units.

    Returns
    -------
    The record's figures, summed over the blocks' insides (the classes' counts over
    their margins too), and the tasks' stages summed into ``timer``.
    """
    engine = engine or ThreadEngine(1)
    margin = LARGEST_WINDOW_M / survey.unit
    blocks = block_layout(grid, block, margin)
    for b in blocks:  # before any work: a block too large stops at once
        check_memory(grid.window(*b.outer), opts, 1)
    shared = engine.share(CloudBlocks(survey, grid, opts, blocks))
    done = engine.map(block_products, range(len(blocks)), shared, stage="blocks",
                      keys=[str(b.index) for b in blocks], in_flight=engine.workers)  # fmt: skip
    figures = dict.fromkeys(("filled_cells", "cells_by_geometry", "cells_classed"), 0)
    returns, sources, triangulated, occupied = [], set(), 0, 0
    for b, (products, f) in zip(blocks, done, strict=True):
        write(b, products)
        for k in figures:
            figures[k] += f[k]
        returns.append(f["returns"])
        triangulated, occupied = triangulated + f["triangulated"], occupied + f["occupied"]
        sources.add(f["dtm_source"])
        figures["fill_radius"] = f["fill_radius"]
        timer.add(f["stages"])  # the tasks' stages, summed
    figures["dtm_source"] = "; ".join(sorted(sources))
    read = round(sum(returns) / survey.n_used, 3)  # the work the margins add
    figures["blocks"] = {"count": len(blocks), "side_m": round(float(block * survey.unit), 3),
                         "margin_m": LARGEST_WINDOW_M, "largest_block_returns": max(returns),
                         "returns_read_per_return": read,
                         "triangulated_per_cell": round(triangulated / max(occupied, 1), 3),
                         "dsm_margin_cells": DSM_MARGIN_CELLS}  # fmt: skip
    figures["engine"] = engine.describe()
    return figures
