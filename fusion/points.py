"""LiDAR point clouds (LAS/LAZ via laspy, PLY via Open3D) rasterised into the ortho products.

DSM: the highest return per cell, read at the cell's centre on the triangulation of those
returns (a return may lie half a cell from the centre it stands for); ortho: the colour
(or intensity) of that return; classes: the LAS classification of that return, ASPRS
codes mapped to ours; DTM: the ground class where the file has one, the progressive
morphological filter otherwise. Lengths are in the CRS's units (US survey feet stay
feet); the ground filter's metric parameters are converted.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rasterio.crs import CRS

from workbench.errors import InputError
from workbench.raster import Grid, parse_crs
from workbench.records import StageTimer

from .classifier import load_classifier
from .ground import dtm_from_dsm
from .interpolate import push_pull_fill, small_holes
from .options import FusionOptions
from .raster_forest import FEATURES as RASTER_FEATURES
from .raster_forest import classify_rasters, synthetic_raster_forest
from .scene_fusion import FILLED, HOLE_CELLS, FusionResult, check_memory

log = logging.getLogger(__name__)

# ASPRS LAS classification -> workbench class (1 ground, 2 grass, 3 tree, 4 building)
ASPRS_TO_CLASS = {2: 1, 3: 2, 4: 3, 5: 3, 6: 4, 9: 1, 11: 1}
ASPRS_NOISE = (7, 18)


@dataclass
class PointCloud:
    """Points and what they carry; xyz in the CRS's units."""

    xyz: np.ndarray  # (N, 3) float64
    rgb: np.ndarray | None  # (N, 3) uint8
    intensity: np.ndarray | None  # (N,) float
    classification: np.ndarray | None  # (N,) uint8, ASPRS codes
    crs: CRS | None
    source: str


def _las_crs(las, path) -> CRS | None:
    for vlr in las.header.vlrs:
        wkt = getattr(vlr, "string", None)
        if type(vlr).__name__ == "WktCoordinateSystemVlr" and wkt:
            return parse_crs(wkt, path=path, field="WKT VLR")
    for vlr in las.header.vlrs:
        keys = getattr(vlr, "geo_keys", None)
        if keys:
            for k in keys:
                if k.id == 3072 and k.value_offset not in (0, 32767):  # ProjectedCSTypeGeoKey
                    return parse_crs(f"EPSG:{k.value_offset}", path=path, field="GeoKeys")
    return None


def read_points(path: str | os.PathLike, crs: str | None = None) -> PointCloud:
    """Read a LAS, LAZ or PLY cloud.

    Parameters
    ----------
    path : path
    crs : str, optional
        EPSG code or WKT for a cloud that carries none (overrides nothing else).

    Raises
    ------
    InputError
        Missing or corrupt file, unknown CRS.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(path, None, "point cloud not found")
    suffix = path.suffix.lower()
    given = parse_crs(crs, path="--crs", field="crs") if crs else None
    if suffix in (".las", ".laz"):
        import laspy

        try:
            las = laspy.read(path)
        except Exception as exc:  # noqa: BLE001 - laspy raises many types for bad files
            raise InputError(path, None, f"not a readable LAS/LAZ file ({exc})") from None
        xyz = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
        names = set(las.point_format.dimension_names)
        rgb = None
        if {"red", "green", "blue"} <= names:
            rgb16 = np.column_stack([las.red, las.green, las.blue]).astype(np.float64)
            scale = 257.0 if rgb16.max() > 255 else 1.0
            rgb = np.clip(np.round(rgb16 / scale), 0, 255).astype(np.uint8)
        intensity = np.asarray(las.intensity, np.float64) if "intensity" in names else None
        cls = np.asarray(las.classification, np.uint8) if "classification" in names else None
        file_crs = _las_crs(las, path)
        if file_crs is None and given is None:
            raise InputError(path, "crs", "the file names no CRS; pass --crs")
        return PointCloud(xyz, rgb, intensity, cls, given or file_crs, str(path))
    if suffix == ".ply":
        import open3d as o3d

        pc = o3d.io.read_point_cloud(str(path))
        if len(pc.points) == 0:
            raise InputError(path, None, "no points (or not a readable PLY file)")
        rgb = (np.asarray(pc.colors) * 255).round().astype(np.uint8) if pc.has_colors() else None
        return PointCloud(np.asarray(pc.points, np.float64), rgb, None, None, given, str(path))
    raise InputError(path, None, "expected a .las, .laz or .ply point cloud")


def default_gsd(xyz: np.ndarray) -> float:
    """Cell size for a cloud: its mean point spacing over its bounding box, rounded.

    Cells without a return of their own are read on the triangulation of their
    neighbours' (:func:`top_surface_at_centres`), so the cell need not be coarser than the
    spacing to be filled; a coarser one costs accuracy at every outline.
    """
    span = np.ptp(xyz[:, :2], axis=0)
    spacing = float(np.sqrt(max(span[0] * span[1], 1e-9) / len(xyz)))
    return float(np.round(spacing, 2 if spacing < 1 else 1)) or spacing


def _top_per_cell(cells: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Index of the highest point of every occupied cell."""
    order = np.lexsort((z, cells))
    last = np.ones(len(order), bool)
    last[:-1] = cells[order][1:] != cells[order][:-1]
    return order[last]


def top_surface_at_centres(
    xyz: np.ndarray, centres: np.ndarray, max_slope_deg: float = 70.0
) -> np.ndarray:
    """Heights at ``centres`` (M, 2) of the surface through the highest returns ``xyz``
    (M, 3), one per cell, the i-th return lying in the cell of the i-th centre.

    Each centre takes the height of the Delaunay triangle of the returns (scipy) that holds
    it. A return sits anywhere in its cell: on a 40-degree roof, taking its height for the
    centre's errs by up to 0.4 cell sizes. Where the triangle is steeper than
    ``max_slope_deg`` (it spans a wall or a crown's edge) or no triangle holds the centre
    (the hull's rim), the cell keeps its return's own height, so that edges stay sharp.

    Returns
    -------
    (M,) float heights, in the units of ``xyz``.
    """
    from scipy.spatial import Delaunay, QhullError

    z = xyz[:, 2].astype(np.float64)
    if len(xyz) < 3:
        return z
    try:
        tri = Delaunay(xyz[:, :2])
    except QhullError:  # all returns on a line
        return z
    simplex = tri.find_simplex(centres)
    inside = np.flatnonzero(simplex >= 0)
    s = simplex[inside]
    affine = tri.transform[s]
    b = np.einsum("mij,mj->mi", affine[:, :2], centres[inside] - affine[:, 2])
    weights = np.column_stack([b, 1.0 - b.sum(axis=1)])
    corners = xyz[tri.simplices[s]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    gentle = np.abs(normal[:, 2]) >= np.cos(np.radians(max_slope_deg)) * np.linalg.norm(
        normal, axis=1
    )
    out = z.copy()
    out[inside[gentle]] = np.einsum("mk,mk->m", weights[gentle], corners[gentle, :, 2])
    return out


def fuse_points(path, opts: FusionOptions | None = None, *, crs: str | None = None):
    """Rasterise a point cloud into a :class:`FusionResult`.

    Returns
    -------
    result : FusionResult
    crs : CRS or None
    inputs : dict summary of the cloud
    """
    opts = opts or FusionOptions()
    timer = StageTimer()
    with timer.stage("read"):
        cloud = read_points(path, crs)
    keep = _kept_points(cloud, opts, path)
    xyz = cloud.xyz[keep]
    gsd = opts.gsd or default_gsd(xyz)
    if opts.bounds is not None:
        grid = Grid.from_bounds(*opts.bounds, gsd)
    else:
        lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
        grid = Grid.from_bounds(lo[0], lo[1], hi[0] + 1e-6, hi[1] + 1e-6, gsd)
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
        dsm, count, holes = top_surface_raster(xyz, cells, top, grid)
        ortho = _ortho(cloud, keep, cells, top, grid)
    cls = cloud.classification[keep] if cloud.classification is not None else None
    with timer.stage("ground"):
        dtm, dtm_source = cloud_dtm(xyz, cells, cls, dsm, grid, unit)
        ndsm = (dsm - dtm).astype(np.float32)
    with timer.stage("classes"):
        prob, class_source = cloud_classes(cloud, cls, cells, top, dsm, dtm, ortho, grid, opts,
                                           unit)  # fmt: skip
    count16 = np.minimum(count, np.iinfo(np.int16).max).astype(np.int16)
    count16[holes] = FILLED
    inputs = {
        "points": cloud.source,
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
        "filled_small_holes": int(holes.sum()),
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


def top_surface_raster(xyz: np.ndarray, cells: np.ndarray, top: np.ndarray, grid: Grid):
    """The DSM read at the cell centres on the top returns, small holes filled.

    Returns
    -------
    dsm (H, W) float32, NaN unknown; count (H, W) returns per cell; holes (H, W) bool, the
    cells filled by interpolation.
    """
    n = grid.width * grid.height
    centres = np.column_stack(grid.cell_center(*np.divmod(cells[top], grid.width)))
    dsm = np.full(n, np.nan)
    dsm[cells[top]] = top_surface_at_centres(xyz[top], centres)
    dsm = dsm.reshape(grid.shape)
    count = np.bincount(cells, minlength=n).reshape(grid.shape)
    holes = small_holes(~np.isfinite(dsm), HOLE_CELLS)
    dsm = np.where(holes, push_pull_fill(dsm, np.isfinite(dsm)), dsm).astype(np.float32)
    return dsm, count, holes


def _ortho(cloud, keep, cells, top, grid: Grid) -> np.ndarray:
    """(H, W, 3) uint8: the top return's colour, or its intensity as grey, or black."""
    ortho = np.zeros((grid.width * grid.height, 3), np.uint8)
    if cloud.rgb is not None:
        ortho[cells[top]] = cloud.rgb[keep][top]
    elif cloud.intensity is not None:
        inten = cloud.intensity[keep][top]
        hi_i = np.percentile(inten, 99) or 1.0
        ortho[cells[top]] = np.clip(inten / hi_i * 255, 0, 255).astype(np.uint8)[:, None]
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
        metric = dict(coarse=1.0 / unit, max_window=80.0 / unit, dh0=0.5 / unit, dh_max=3.0 / unit)
        dtm, _ = dtm_from_dsm(dsm, grid.gsd, **metric)
        dtm_source = "progressive morphological filter"
    dtm = np.where(np.isfinite(dsm), np.minimum(dtm, dsm), np.nan).astype(np.float32)
    return dtm, dtm_source


def cloud_classes(cloud, cls, cells, top, dsm, dtm, ortho, grid: Grid, opts: FusionOptions,
                  unit: float):  # fmt: skip
    """(4, H, W) class probabilities: the top return's ASPRS class where it has one, the
    raster forest's elsewhere; and a sentence on where they came from."""
    n = grid.width * grid.height
    prob = np.full((4, n), np.nan, np.float32)
    class_source = "none: the cloud has no classification"
    if cls is not None:
        mapped = np.zeros(256, np.uint8)
        for k, v in ASPRS_TO_CLASS.items():
            mapped[k] = v
        top_cls = mapped[cls[top]]
        known = top_cls > 0
        onehot = np.zeros((4, known.sum()), np.float32)
        onehot[top_cls[known] - 1, np.arange(known.sum())] = 1.0
        prob[:, cells[top][known]] = onehot
        share = float(known.mean())
        class_source = (
            f"LAS classification (ASPRS codes mapped) for {share:.1%} of the occupied cells"
        )
    prob = prob.reshape(4, *grid.shape)
    unknown = np.isfinite(dsm) & ~np.isfinite(prob[0])
    if not unknown.any():
        return prob, class_source
    if opts.classifier is not None:
        forest = load_classifier(opts.classifier, features=RASTER_FEATURES)[0]
        origin = f"the forest in {opts.classifier}"
    else:
        forest = synthetic_raster_forest()
        origin = "a forest trained on the synthetic city's rasters"
    rgb = ortho if (cloud.rgb is not None or cloud.intensity is not None) else None
    guess = classify_rasters(forest, dsm, dtm, rgb, grid.gsd * unit, unit)
    prob[:, unknown] = guess[:, unknown]
    share = float(unknown.sum() / np.isfinite(dsm).sum())
    class_source = (
        (class_source + "; " if cloud.classification is not None else "")
        + f"{origin} (nDSM, slope, roughness, curvature, brightness, greenness) "
        f"for {share:.1%} of the cells"
    )
    return prob, class_source
