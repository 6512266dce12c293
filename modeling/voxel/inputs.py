"""What the voxel path reads: the scene and its views, the footprints (GIS, or the
fusion's building regions), each footprint's ground height and over-estimated height,
and the ground model."""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio.features
import shapely
from shapely.geometry import Polygon, box, mapping

from modeling.shared.roof_mesh import extrude_faces
from workbench.errors import InputError
from workbench.footprints import Footprint, read_footprints
from workbench.fusion_run import checked_fusion_run
from workbench.raster import BUILDING, TREE, Grid, RasterWindows, raster_header
from workbench.raycast import local_origin
from workbench.regions import mask_regions
from workbench.scene import Scene, load_scene

from .occluders import Occluders
from .options import VoxelOptions
from .view_images import ViewImages

log = logging.getLogger(__name__)


@dataclass
class VoxelInputs:
    """What the voxel path reads: the scene, its views, the usable footprints (each with
    its ground height and over-estimated height) and the ground model."""

    scene: Scene
    cameras: list
    images: ViewImages
    ground: Ground
    buildings: list  # (Footprint, base_z, height)
    skipped: list[dict]
    footprint_source: str
    footprint_count: int
    fused_ndsm: tuple | None = None  # (FusedRoofs, grid) of the fusion run, if any
    prisms: Occluders | None = None  # the usable footprints' initial proxies

    def initial_proxy(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``j``-th usable footprint's initial proxy, its prism to its over-estimated
        height ((V, 3), (T, 3)); the last :data:`PRISMS_KEPT` made are kept (per copy of
        the inputs: a worker's)."""
        kept = self.__dict__.setdefault("_prisms", OrderedDict())
        if j in kept:
            kept.move_to_end(j)
            return kept[j]
        f, base, h = self.buildings[j]
        kept[j] = prism(f.polygon, base, h)
        if len(kept) > PRISMS_KEPT:
            kept.popitem(last=False)
        return kept[j]

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("_prisms", None)
        return state


# initial proxies a worker keeps (about 1 KB each): the footprints' tasks go in their
# file's order, and a footprint's neighbours are mostly those of the ones before it: on
# the `city` preset, one worker of two had made 95.6 % of the prisms its tasks needed
# already with 256 kept, 97.6 % with 1024
PRISMS_KEPT = 512


def read_inputs(
    scene_dir: Path,
    options: VoxelOptions,
    footprints: Path | None = None,
    fusion_dir: Path | None = None,
) -> VoxelInputs:
    """Read and check the scene, footprints and ground; skip unusable footprints with a
    warning that names them."""
    scene = load_scene(scene_dir)
    cameras = [v.camera for v in scene.views]
    images = ViewImages(scene.views, features=options.consistency)
    fusion = _read_fusion(fusion_dir) if fusion_dir else None
    items, source = _footprints(scene, footprints, fusion)
    ground = _ground_model(scene, fusion, options.ground_z)
    kept, skipped = _usable(items, cameras, ground, options.default_height_m)
    fused_ndsm = (FusedRoofs(fusion["ndsm"], fusion["class"]), fusion["grid"]) if fusion else None
    return VoxelInputs(
        scene, cameras, images, ground, kept, skipped, source, len(items), fused_ndsm,
        prism_occluders(kept),
    )  # fmt: skip


def check_inputs(
    scene_dir: Path,
    options: VoxelOptions,
    footprints: Path | None = None,
    fusion_dir: Path | None = None,
) -> None:
    """Read what :func:`read_inputs` refuses, before a command starts its workers: the
    scene, the fusion run and the footprints (a file missing the scene's extent is one
    line, with no worker's shutdown noise after it)."""
    scene = load_scene(scene_dir)
    fusion = _read_fusion(fusion_dir) if fusion_dir else None
    _footprints(scene, footprints, fusion)


def roof_heights(ndsm: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """(H, W) the nDSM where the fusion did not see a tree, metres, NaN elsewhere: a crown
    hanging over a roof is no part of it, and would tilt a roof plane fitted through it
    (`tiny`'s hipped house stood 35 % too high)."""
    return np.where(classes == TREE, np.nan, ndsm)


class FusedRoofs:
    """A fusion run's nDSM where it saw no tree (:func:`roof_heights`), read a window at
    a time: ``roofs[rows, cols]`` (a city's whole grid is gigabytes per worker)."""

    def __init__(self, ndsm: RasterWindows, classes: RasterWindows):
        self.ndsm, self.classes = ndsm, classes

    @property
    def shape(self) -> tuple[int, int]:
        return self.ndsm.shape

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        return roof_heights(self.ndsm[key], self.classes[key])


FUSION_RASTERS = ("dtm", "class", "ndsm")


def _read_fusion(folder: Path) -> dict:
    """The fusion run's grid and CRS, and its DTM, classes and nDSM as
    :class:`~workbench.raster.RasterWindows` (checked to be there on one grid; absolute
    paths, for workers started elsewhere)."""
    folder = Path(folder).absolute()
    run = checked_fusion_run(folder, FUSION_RASTERS, classes=False)
    windows = {name: RasterWindows(folder / f"{name}.tif", run.grid) for name in FUSION_RASTERS}
    return {**windows, "grid": run.grid, "crs": run.crs}


def _footprints(
    scene: Scene, path: Path | None, fusion: dict | None
) -> tuple[list[Footprint], str]:
    path = path or scene.footprints
    if path is not None:
        return read_footprints(path, crs=scene.crs, extent=scene.bounds), str(path)
    if fusion is None:
        raise InputError(
            scene.scene_json, "footprints", "no footprints: pass --footprints or --fusion"
        )
    return footprints_from_fusion(fusion), "fusion building mask"


def footprints_from_fusion(fusion: dict, min_area_m2: float = 20.0) -> list[Footprint]:
    """Footprints from a fusion run's building class: one per connected region, its
    height 1.5 times its 99th-percentile nDSM (over-estimated, as GIS heights are). The
    class is polygonised a strip of rows at a time (:func:`workbench.regions.mask_regions`),
    each region's nDSM read in its window."""
    grid: Grid = fusion["grid"]
    out = []
    regions = mask_regions(lambda rows: fusion["class"][rows, 0 : grid.width] == BUILDING, grid)
    for region in regions:
        # on a canonical ring (no collinear corners, a fixed start): a region put
        # together from strips simplifies as the whole mask's does
        poly = shapely.normalize(region.simplify(0)).simplify(grid.gsd)
        if poly.area < min_area_m2:
            continue
        # its cells, in the window of its bounds (on cell edges)
        x0, y0, x1, y1 = region.bounds
        rows = slice(round((grid.ymax - y1) / grid.gsd), round((grid.ymax - y0) / grid.gsd))
        cols = slice(round((x0 - grid.xmin) / grid.gsd), round((x1 - grid.xmin) / grid.gsd))
        w = grid.window(rows, cols)
        inside = rasterio.features.geometry_mask([mapping(region)], w.shape, w.transform,
                                                 invert=True)  # fmt: skip
        z = fusion["ndsm"][rows, cols][inside]
        h = np.nanpercentile(z, 99) if np.isfinite(z).any() else np.nan
        if not np.isfinite(h) or h <= 0:
            continue
        fid = str(len(out) + 1)
        out.append(Footprint(fid, poly, float(1.5 * h), {"_height_source": "fusion nDSM x 1.5"}))
    return out


class Ground:
    """Ground height: the fusion's DTM, the scene's DTM (either read a window at a time),
    or a flat plane.

    Parameters
    ----------
    source : str
        What the ground is, for the record.
    z : RasterWindows or (H, W) float array, optional
        Ground heights on ``grid``, metres, NaN unknown (None: the flat plane).
    grid : Grid, optional
    flat : float, optional
        The flat plane's height, metres.
    """

    def __init__(self, source: str, z=None, grid: Grid | None = None, flat: float | None = None):
        self.source, self.z, self.grid, self.flat = source, z, grid, flat

    def under(self, polygon: Polygon) -> float:
        """Median ground height under a footprint (every cell it touches), metres; off the
        raster or where it is unknown, the nearest known ground's."""
        if self.z is None:
            return float(self.flat)
        window = self.grid.window_of(polygon.bounds, pad=1)
        vals = np.zeros(0)
        if window is not None:
            g = self.grid.window(*window)
            inside = rasterio.features.geometry_mask(
                [mapping(polygon)], g.shape, g.transform, invert=True, all_touched=True
            )
            vals = self.z[window][inside]
            vals = vals[np.isfinite(vals)]
        if not len(vals):
            c = polygon.centroid
            r, cc = self.grid.cell_index(np.array([c.x]), np.array([c.y]), clip=True)
            return self._nearest_known(int(r[0]), int(cc[0]))
        return float(np.median(vals))

    def __call__(self, grid: Grid) -> np.ndarray:
        """Ground height at the cell centres of ``grid``, metres (unknown cells filled)."""
        if self.z is None:
            return np.full(grid.shape, float(self.flat))
        X, Y = grid.cell_centers()
        r, c = self.grid.cell_index(X.ravel(), Y.ravel(), clip=True)
        r0, c0 = r.min(), c.min()
        z = self.z[r0 : r.max() + 1, c0 : c.max() + 1][r - r0, c - c0].reshape(grid.shape)
        if np.isfinite(z).all():
            return z
        # unknown cells take the known ground's median on the grid, or (a tile of a city
        # under one large building) the nearest known ground's height
        fill = np.nanmedian(z) if np.isfinite(z).any() else self.under(box(*grid.bounds))
        return np.where(np.isfinite(z), z, fill)

    def _nearest_known(self, r: int, c: int, radius: int = 64) -> float:
        """The known height nearest to cell (r, c) (first in row-major order among the
        nearest), searched in windows growing until one holds it."""
        g = self.grid
        while True:
            rows = slice(max(r - radius, 0), min(r + radius + 1, g.height))
            cols = slice(max(c - radius, 0), min(c + radius + 1, g.width))
            z = self.z[rows, cols]
            known = np.argwhere(np.isfinite(z))
            everything = rows == slice(0, g.height) and cols == slice(0, g.width)
            if len(known):
                d = np.hypot(known[:, 0] + rows.start - r, known[:, 1] + cols.start - c)
                j = np.argmin(d)
                # every cell as near lies in the window: the whole raster's nearest
                if d[j] <= radius or everything:
                    return float(z[tuple(known[j])])
            elif everything:
                raise InputError(getattr(self.z, "path", None), None, "no known ground height")
            radius *= 4


def _ground_model(scene: Scene, fusion: dict | None, ground_z: float | None) -> Ground:
    if fusion is not None:
        return Ground("fusion DTM", fusion["dtm"], fusion["grid"])
    if scene.dtm is not None:
        grid, _, _ = raster_header(scene.dtm, field="dtm")
        return Ground("scene DTM", RasterWindows(scene.dtm, grid, as_float=True), grid)
    if ground_z is not None:
        return Ground("flat plane (--ground-z)", flat=ground_z)
    z = flat_ground_from_depth(scene)
    if z is None:
        raise InputError(
            scene.scene_json,
            "dtm",
            "no ground: pass --fusion or --ground-z, or give the scene a dtm",
        )
    return Ground("flat plane (depth maps)", flat=z)


def flat_ground_from_depth(scene: Scene, step: int = 8) -> float | None:
    """A flat ground plane from the most downward-looking views' depth maps: the median
    of the lowest fifth of the points they see, metres. None without depth maps."""
    heights = []
    for view in scene.views:
        if view.depth_path is None or -view.camera.viewing_direction[2] < 0.95:
            continue
        depth = view.read_depth()[::step, ::step]
        origin, dirs = view.camera.pixel_grid_rays(step)
        z = origin[2] + depth.ravel() * dirs[:, 2]
        heights.append(z[np.isfinite(z)])
    if not heights:
        return None
    z = np.concatenate(heights)
    return float(np.median(z[z <= np.quantile(z, 0.2)]))


def _usable(items, cameras, ground: Ground, default_height: float):
    """The footprints to model, each with its ground height and height, and those
    skipped with why (a self-intersecting polygon; a centroid fewer than two views
    frame), both in the footprints' order."""
    polys = [
        None if not f.polygon.is_valid
        else f.polygon if isinstance(f.polygon, Polygon)
        else max(f.polygon.geoms, key=lambda g: g.area)
        for f in items
    ]  # fmt: skip
    bases = [None if p is None else ground.under(p) for p in polys]
    centres = np.array([[*p.centroid.coords[0], b] for p, b in zip(polys, bases, strict=True)
                        if p is not None]).reshape(-1, 3)  # fmt: skip
    seen = iter(views_framing(cameras, centres))
    kept, skipped = [], []
    for f, poly, base in zip(items, polys, bases, strict=True):
        if poly is None:
            log.warning("footprint %s: self-intersecting polygon, skipped", f.id)
            skipped.append({"id": f.id, "reason": "self-intersecting polygon"})
            continue
        if f.height is None:
            f.properties["_height_source"] = "zonal default"
        h = f.height if f.height is not None else default_height
        n = next(seen)
        if n < 2:
            log.warning("footprint %s: outside the images (seen by %d views), skipped", f.id, n)
            skipped.append({"id": f.id, "reason": f"seen by {n} views"})
            continue
        kept.append((Footprint(f.id, poly, h, f.properties), base, h))
    return kept, skipped


def views_framing(cameras, points: np.ndarray) -> np.ndarray:
    """(N,) int: how many of the cameras frame each of the ``points`` (N, 3) world metres
    (in front of the camera, inside its image). A camera at a time over every point: a
    footprint at a time took 7 s of the city's read (495 views, 672 footprints)."""
    seen = np.zeros(len(points), int)
    for cam in cameras:
        uv, _ = cam.project(points)
        with np.errstate(invalid="ignore"):  # NaN behind the camera: not framed
            seen += ((uv[:, 0] >= 0) & (uv[:, 0] < cam.width)
                     & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height))  # fmt: skip
    return seen


def prism(polygon: Polygon, base: float, height: float):
    return extrude_faces([polygon], [np.array([0.0, 0.0, 1.0, -(base + height)])], base)


def prism_occluders(kept) -> Occluders:
    """The boxes of the usable footprints' initial proxies (``kept``: (Footprint, base,
    height)), in one origin for every scene of them."""
    boxes = np.array([f.polygon.bounds for f, _, _ in kept], float).reshape(-1, 4)
    tops = np.array([base + h for _, base, h in kept], float)
    lo = np.column_stack([boxes[:, :2], [base for _, base, _ in kept]]).reshape(-1, 3)
    hi = np.column_stack([boxes[:, 2:], tops])
    origin = local_origin(np.vstack([lo, hi]))
    return Occluders([f.id for f, _, _ in kept], boxes, tops, origin)


def neighbour_scene(j: int, inputs: VoxelInputs, options: VoxelOptions):
    """The ray-casting scene of the initial proxies of the other buildings that can hide
    a voxel of the ``j``-th usable footprint (its columns lie within ``grow_m`` of it,
    its voxels' centres from its ground to a voxel above its height) from a view that
    frames it (None if none can)."""
    f, base, h = inputs.buildings[j]
    x0, y0, x1, y1 = f.polygon.bounds
    g = options.grow_m
    lo, hi = (x0 - g, y0 - g, base), (x1 + g, y1 + g, base + h + options.voxel_m)
    near = inputs.prisms.around(inputs.cameras, lo, hi)
    return inputs.prisms.scene([inputs.initial_proxy(i) for i in near if i != j])
