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

import numpy as np

from workbench.errors import InputError
from workbench.raster import Grid
from workbench.records import StageTimer

from .ground import LOWEST_BUILDING_M, dtm_from_dsm
from .interpolate import fill_small_holes, push_pull_fill, small_holes
from .options import FusionOptions
from .point_classes import LOW_M, UNCLASSIFIED, classify_returns
from .point_clouds import cloud_files, read_clouds
from .scene_fusion import FILLED, HOLE_CELLS, FusionResult, check_memory

log = logging.getLogger(__name__)

# ASPRS LAS classification -> workbench class (1 ground, 2 grass, 3 tree, 4 building)
ASPRS_TO_CLASS = {2: 1, 3: 2, 4: 3, 5: 3, 6: 4, 9: 1, 11: 1}
ASPRS_NOISE = (7, 18)


RETURNS_PER_CELL = 1.0  # the default cell holds this many returns on average


def default_gsd(xyz: np.ndarray, returns_per_cell: float = RETURNS_PER_CELL) -> float:
    """Cell size for a cloud: the cell that holds ``returns_per_cell`` returns on average.

    The density is counted over the ground the cloud covers (coarse cells of twice the
    mean spacing that hold a return), not its bounding box, so that water and the corners
    of a tile do not coarsen the cell. At one return per cell about a third of the cells
    hold none (Poisson; rows of them between scan lines): :func:`top_surface_raster` fills
    those inside the coverage. Measured against coarser cells that hold two or three
    returns (``benchmarks/terrace.py``, the AHN3 clouds), the finer cell with its gaps
    filled models roofs better: docs/fusion.md gives the figures.

    Returns
    -------
    float, in the units of ``xyz``, rounded to two significant digits.
    """
    lo = xyz[:, :2].min(axis=0)
    span = np.maximum(np.ptp(xyz[:, :2], axis=0), 1e-9)
    coarse = 2.0 * float(np.sqrt(span[0] * span[1] / len(xyz)))
    ij = np.floor((xyz[:, :2] - lo) / coarse).astype(np.int64)
    occupied = len(np.unique(ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]))
    density = len(xyz) / (occupied * coarse * coarse)
    gsd = float(np.sqrt(returns_per_cell / density))
    return float(f"{gsd:.2g}")


def _top_per_cell(cells: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Index of the highest point of every occupied cell."""
    order = np.lexsort((z, cells))
    last = np.ones(len(order), bool)
    last[:-1] = cells[order][1:] != cells[order][:-1]
    return order[last]


def top_surface_at_centres(
    xyz: np.ndarray,
    centres: np.ndarray,
    fallback: np.ndarray | None = None,
    max_slope_deg: float = 70.0,
) -> np.ndarray:
    """Heights at ``centres`` (M, 2) of the surface through the highest returns ``xyz``
    (K, 3), one per occupied cell.

    Each centre takes the height of the Delaunay triangle of the returns (scipy) that holds
    it. A return sits anywhere in its cell: on a 40-degree roof, taking its height for the
    centre's errs by up to 0.4 cell sizes. Where the triangle is steeper than
    ``max_slope_deg`` (it spans a wall or a crown's edge) or no triangle holds the centre
    (the hull's rim), the centre keeps ``fallback``, so that edges stay sharp.

    Parameters
    ----------
    fallback : (M,) float, optional
        Height of the return that stands for each centre (its own cell's, or the nearest);
        by default ``xyz[:, 2]`` (M = K, the i-th return lying in the i-th centre's cell).

    Returns
    -------
    (M,) float heights, in the units of ``xyz``.
    """
    from scipy.spatial import Delaunay, QhullError

    out = (xyz[:, 2] if fallback is None else fallback).astype(np.float64).copy()
    if len(xyz) < 3:
        return out
    origin = xyz[:, :2].min(axis=0)  # qhull's precision is relative to the coordinates
    try:
        tri = Delaunay(xyz[:, :2] - origin)
    except QhullError:  # all returns on a line
        return out
    local = centres - origin
    simplex = tri.find_simplex(local)
    inside = np.flatnonzero(simplex >= 0)
    s = simplex[inside]
    affine = tri.transform[s]
    b = np.einsum("mij,mj->mi", affine[:, :2], local[inside] - affine[:, 2])
    weights = np.column_stack([b, 1.0 - b.sum(axis=1)])
    corners = xyz[tri.simplices[s]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    gentle = np.abs(normal[:, 2]) >= np.cos(np.radians(max_slope_deg)) * np.linalg.norm(
        normal, axis=1
    )
    out[inside[gentle]] = np.einsum("mk,mk->m", weights[gentle], corners[gentle, :, 2])
    return out


def fuse_points(paths, opts: FusionOptions | None = None, *, crs: str | None = None):
    """Rasterise a point cloud, or tiles of one (files or folders), into a
    :class:`FusionResult`.

    Returns
    -------
    result : FusionResult
    crs : CRS or None
    inputs : dict summary of the cloud
    """
    opts = opts or FusionOptions()
    timer = StageTimer()
    with timer.stage("read"):
        cloud = read_clouds(paths, crs)
    keep = _kept_points(cloud, opts, cloud.source)
    xyz = cloud.xyz[keep]
    gsd = opts.gsd or default_gsd(xyz)
    grid = Grid.covering(xyz[:, :2], gsd, opts.bounds)
    check_memory(grid, opts, 1)
    unit = (
        cloud.crs.linear_units_factor[1]
        if cloud.crs is not None and cloud.crs.is_projected
        else 1.0
    )
    with timer.stage("rasterise"):
        r, c = grid.cell_index(xyz[:, 0], xyz[:, 1], clip=True)
        cells = r * grid.width + c
        top = _top_per_cell(cells, xyz[:, 2])
        radius = opts.fill_radius / unit if opts.fill_radius is not None else 2.0 * gsd
        dsm, count, filled, source = top_surface_raster(xyz, cells, top, grid, radius)
        # the return whose colour and class each cell takes
        at = np.flatnonzero(source >= 0)
        returns = top[source[at]]
        ortho = _ortho(cloud, keep, at, returns, grid)
    cls = cloud.classification[keep] if cloud.classification is not None else None
    with timer.stage("ground"):
        dtm, dtm_source = cloud_dtm(xyz, cells, cls, dsm, grid, unit)
        ndsm = (dsm - dtm).astype(np.float32)
    with timer.stage("classes"):
        prob, class_source = cloud_classes(
            cloud, keep, cls, at, returns, xyz, cells, dtm, grid, unit
        )
    count16 = np.minimum(count, np.iinfo(np.int16).max).astype(np.int16)
    count16[filled] = FILLED
    inputs = {
        "points": [str(f) for f in cloud_files(paths)],
        "n_points": int(len(cloud.xyz)),
        "n_points_used": int(keep.sum()),
        "crs": cloud.crs.to_string() if cloud.crs is not None else None,
        "units_per_metre": round(1.0 / unit, 6),
        "has_rgb": cloud.rgb is not None,
        "has_intensity": cloud.intensity is not None,
        "has_classification": cloud.classification is not None,
    }
    record = {
        "mode": "point cloud",
        "dtm_source": dtm_source,
        "class_source": class_source,
        "filled_cells": int(filled.sum()),
        "fill_radius": round(radius, 6),
        "stages": timer.stages,
    }
    result = FusionResult(grid, ortho, dsm, dtm, ndsm, prob, count16, {}, record, None)
    return result, cloud.crs, inputs


def _kept_points(cloud, opts: FusionOptions, path) -> np.ndarray:
    """(N,) bool: the returns that are not noise and lie inside ``opts.bounds``."""
    xyz = cloud.xyz
    keep = np.ones(len(xyz), bool)
    if cloud.classification is not None:
        keep &= ~np.isin(cloud.classification, ASPRS_NOISE)
    if opts.bounds is not None:
        x0, y0, x1, y1 = opts.bounds
        keep &= (xyz[:, 0] >= x0) & (xyz[:, 0] < x1) & (xyz[:, 1] >= y0) & (xyz[:, 1] < y1)
    if not keep.any():
        raise InputError(path, "bounds", "no points inside the bounds")
    return keep


def top_surface_raster(
    xyz: np.ndarray, cells: np.ndarray, top: np.ndarray, grid: Grid, fill_radius: float
):
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

    Returns
    -------
    dsm : (H, W) float32, NaN unknown
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
    centres = np.column_stack(grid.cell_center(*np.divmod(targets, grid.width)))
    dsm = np.full(n, np.nan)
    dsm[targets] = top_surface_at_centres(xyz[top], centres, xyz[top][source[targets], 2])
    dsm = dsm.reshape(grid.shape)
    count = np.bincount(cells, minlength=n).reshape(grid.shape)
    holes = small_holes(~np.isfinite(dsm), HOLE_CELLS)
    dsm = fill_small_holes(dsm, np.isfinite(dsm), holes, HOLE_CELLS).astype(np.float32)
    filled = (reached & ~occupied).reshape(grid.shape) | holes
    return dsm, count, filled, source


def _ortho(cloud, keep, at: np.ndarray, returns: np.ndarray, grid: Grid) -> np.ndarray:
    """(H, W, 3) uint8: at cells ``at`` (M,), the colour of their returns ``returns`` (M,),
    or its intensity as grey; black elsewhere."""
    ortho = np.zeros((grid.width * grid.height, 3), np.uint8)
    if cloud.rgb is not None:
        ortho[at] = cloud.rgb[keep][returns]
    elif cloud.intensity is not None:
        inten = cloud.intensity[keep][returns]
        hi_i = np.percentile(inten, 99) or 1.0
        ortho[at] = np.clip(inten / hi_i * 255, 0, 255).astype(np.uint8)[:, None]
    return ortho.reshape(*grid.shape, 3)


def cloud_dtm(xyz, cells, cls, dsm: np.ndarray, grid: Grid, unit: float):
    """The DTM from the ground class (its lowest return per cell, interpolated) where the
    cloud has one, else the morphological filter on the DSM; NaN where the DSM is."""
    n = grid.width * grid.height
    if cls is not None and (cls == 2).sum() > 100:
        g = cls == 2
        ground = np.full(n, np.nan)
        gtop = _top_per_cell(cells[g], -xyz[g, 2])  # the lowest ground return per cell
        ground[cells[g][gtop]] = xyz[g][gtop, 2]
        ground = ground.reshape(grid.shape)
        dtm = push_pull_fill(ground, np.isfinite(ground)).astype(np.float32)
        dtm_source = "LAS ground class (2), interpolated"
    else:
        metric = dict(
            coarse=1.0 / unit,
            max_window=80.0 / unit,
            dh0=0.5 / unit,
            dh_max=LOWEST_BUILDING_M / unit,
        )
        dtm, _ = dtm_from_dsm(dsm, grid.gsd, **metric)
        dtm_source = "progressive morphological filter"
    dtm = np.where(np.isfinite(dsm), np.minimum(dtm, dsm), np.nan).astype(np.float32)
    return dtm, dtm_source


def cloud_classes(cloud, keep, cls, at, returns, xyz, cells, dtm, grid: Grid, unit: float):
    """(4, H, W) class probabilities, one-hot: at cells ``at``, the class of their returns
    ``returns``: the ASPRS code the cloud gives, or for the returns it leaves unclassified
    (codes 0 and 1, or a cloud with no classes) the class their geometry and echoes give
    (:func:`~fusion.point_classes.classify_returns`); and a sentence on where they came from.
    Codes our classes do not hold (bridge decks, reserved codes) stay unclassified."""
    n = grid.width * grid.height
    codes = np.array(cls, np.uint8, copy=True) if cls is not None else np.zeros(len(xyz), np.uint8)
    unclassified = np.isin(codes, UNCLASSIFIED)
    # only the returns that stand for a cell need a class
    needed = np.zeros(len(xyz), bool)
    needed[returns] = True
    todo = np.flatnonzero(needed & unclassified)
    if len(todo):
        hag = xyz[:, 2] - dtm.ravel()[cells]  # ``cells``: each return's flat cell index
        echoes = cloud.number_of_returns[keep] if cloud.number_of_returns is not None else None
        rgb = cloud.rgb[keep] if cloud.rgb is not None else None
        codes[todo] = classify_returns(
            xyz, hag, todo, number_of_returns=echoes, rgb=rgb, low=LOW_M / unit
        )
    mapped = np.zeros(256, np.uint8)
    for k, v in ASPRS_TO_CLASS.items():
        mapped[k] = v
    ours = mapped[codes[returns]]
    known = ours > 0
    prob = np.full((4, n), np.nan, np.float32)
    onehot = np.zeros((4, known.sum()), np.float32)
    onehot[ours[known] - 1, np.arange(known.sum())] = 1.0
    prob[:, at[known]] = onehot
    by_geometry = float(unclassified[returns].mean()) if len(returns) else 0.0
    parts = []
    if cls is not None:
        parts.append(
            f"LAS classification (ASPRS codes mapped) for {1 - by_geometry:.1%} of the cells"
        )
    if len(todo):
        echo_note = "and echoes " if cloud.number_of_returns is not None else ""
        parts.append(
            f"their geometry {echo_note}(height above ground, neighbourhood shape) for "
            f"{by_geometry:.1%} of the cells, whose returns are unclassified"
        )
    return prob.reshape(4, *grid.shape), "; ".join(parts) or "none"
