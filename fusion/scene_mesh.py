"""A coloured surface mesh of a scene from its calibrated views and depth maps: what a
user's MVS tool gives (dense, noisy, its corners rounded), for the LOD path and as an
export.

Each view's depth map and image are integrated into a truncated signed distance field
(Open3D's voxel block grid, hashed blocks of 8³ voxels), and marching cubes extracts its
zero level. Depth pixels that land outside the scene's bounds are left out: oblique views
see the terrain hundreds of metres beyond the area of interest, and every block they
touch costs memory. Open3D works in float32: the views are moved to a local origin (the
bounds' centre, to the kilometre) and the mesh moved back in float64.
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import open3d as o3d
import open3d.core as o3c

from workbench.engine import Engine, ThreadEngine, engine_for, full_disk_named
from workbench.errors import InputError, WorkbenchError
from workbench.progress import progress
from workbench.scene import Scene

from .scene_fusion import physical_memory

log = logging.getLogger(__name__)

BLOCK_VOXELS = 8  # voxels along a block's side
BLOCK_BYTES = BLOCK_VOXELS**3 * 5 * 4  # tsdf, weight and colour (3) as float32
BLOCKS_PER_COLUMN = 8  # measured on `small`: ground, roofs, walls and noise
# the hash map's growth and the extraction, over the blocks themselves: on `small` seed 0,
# 74,248 blocks (725 MiB) peaked at 2.55 GiB in all, which 8 blocks a column and this
# factor put at 2.7 GiB
PEAK_FACTOR = 3.5
# Open3D crashed (SIGSEGV, twice) in the first of 4 tiles of the 1 km² city, about
# 250,000 blocks each; 16 tiles of 250 m (0.4 m voxels, about 51,000 blocks each by the
# estimate) ran, as does `small`'s one grid of 74,000 blocks: tiles made by default hold
# no more than this
TILE_BLOCKS = 60_000
# Open3D's error when a view's depth touches no voxel block
NO_BLOCK_TOUCHED = "No block is touched"


@dataclass
class SceneMesh:
    """A coloured triangle mesh in world metres.

    Attributes
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int64, counter-clockwise seen from outside (the camera's side)
    colors : (V, 3) uint8
    record : dict
        Voxel size, truncation, views, blocks, times.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray
    record: dict


def integrate_views(
    scene: Scene,
    voxel_m: float | None = None,
    trunc_voxels: float = 4.0,
    bounds: tuple[float, float, float, float] | None = None,
    min_weight: float = 1.0,
    max_memory_fraction: float = 0.6,
    tile_m: float | None = None,
) -> SceneMesh:
    """TSDF integration of every view's depth map and colour, then marching cubes.

    An area whose voxel blocks would not fit in memory is meshed in square tiles, one
    after another (:func:`mesh_tiles`): each tile's grid holds the blocks within one
    block of the tile, every view integrates into them what it integrates there in one
    grid of the whole area, and the tile keeps the triangles whose centroid lies in it.
    A voxel's signed distance depends only on the views' depths along its rays, so the
    tiles' triangles are the whole grid's, and the mesh the same surface (tested); it
    comes tile after tile (:func:`tile_pieces`), where one grid's is in
    :func:`welded`'s order. :func:`write_views_mesh` writes the tiles to a PLY as they
    come, in memory that does not grow with the area.

    Parameters
    ----------
    scene : Scene
        Calibrated views with depth maps (z-depth, metres, NaN unknown).
    voxel_m : float, optional
        Voxel edge, metres (default: the scene's gsd, else 0.25).
    trunc_voxels : float
        Truncation of the signed distance, in voxels.
    bounds : (xmin, ymin, xmax, ymax), optional
        Area meshed (default: the scene's bounds; else all the views see).
    min_weight : float
        Voxels seen by fewer views' worth of weight are left out of the surface.
    max_memory_fraction : float
        The blocks of one grid may take this much of the machine's memory; a larger area
        is meshed in tiles (with bounds only).
    tile_m : float, optional
        Tile side, metres (rounded up to whole blocks); default: one grid when it fits,
        else the largest tile whose grid takes at most half that memory and about
        ``TILE_BLOCKS`` blocks.

    Raises
    ------
    InputError
        A view has no depth map.
    WorkbenchError
        A tile of one block would not fit in memory at this voxel size, or the depth
        maps give no surface.
    """
    plan = _plan(scene, voxel_m, trunc_voxels, bounds, min_weight, max_memory_fraction, tile_m)
    if plan.tiles is None:
        grid = _integrate(scene.views, None, plan.voxel_m, trunc_voxels, plan.bounds,
                          plan.origin, plan.blocks, "mesh: integrating views")  # fmt: skip
        mesh = grid.extract_triangle_mesh(weight_threshold=min_weight).to_legacy()
        n_blocks = int(grid.hashmap().size())
        del grid
        vertices, colors, triangles = welded(
            mesh.vertices, mesh.triangles, _uint8_colours(np.asarray(mesh.vertex_colors))
        )
        vertices = vertices + plan.origin
    else:
        plan, blocks = planned_tiles(scene.views, plan)
        pieces = list(tile_pieces(scene.views, plan, blocks))
        vertices = np.concatenate([p.vertices for p in pieces])
        triangles = np.concatenate([p.triangles for p in pieces])
        colors = np.concatenate([p.colours for p in pieces])
        n_blocks = sum(p.blocks for p in pieces)
    record = plan.record(len(scene.views), n_blocks, len(vertices), len(triangles))
    if not len(triangles):
        raise WorkbenchError("mesh: the views' depth maps gave no surface inside the bounds")
    return SceneMesh(vertices, triangles, colors, record)


def _defaults(function) -> dict:
    return {k: p.default for k, p in inspect.signature(function).parameters.items()
            if p.default is not inspect.Parameter.empty}  # fmt: skip


def write_views_mesh(path, scene: Scene, *, workers: int | None = None,
                     scheduler: str | None = None, resume: bool = False,
                     **mesh_options) -> dict:  # fmt: skip
    """:func:`integrate_views` (``mesh_options``: its keyword arguments) written to
    ``path`` (:func:`write_scene_mesh`'s PLY, the scene's CRS in its header), whole or
    not at all. A tiled mesh is written tile after tile, one tile's triangles in memory
    at a time; its tiles are tasks of an engine (:mod:`workbench.engine`: ``workers``
    processes of a local cluster, by default one per core, or ``scheduler``'s), each
    kept in ``path``'s partial folder as it finishes, so that a run started again with
    ``resume`` meshes only the tiles not finished. Returns the mesh's record."""
    from workbench.meshio import PlyWriter

    o = {**_defaults(integrate_views), **mesh_options}
    plan = _plan(scene, o["voxel_m"], o["trunc_voxels"], o["bounds"], o["min_weight"],
                 o["max_memory_fraction"], o["tile_m"])  # fmt: skip
    if plan.tiles is None:
        if scheduler is not None or resume:
            log.warning("--scheduler and --resume apply to a mesh in tiles; this one is one "
                        "grid, meshed in this process")  # fmt: skip
        mesh = integrate_views(scene, **mesh_options)
        write_scene_mesh(path, mesh, scene.crs)
        return mesh.record
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # the tiles as planned (their side follows this machine's memory by default): a run
    # resumed elsewhere must cut the area as the interrupted one did
    parameters = {k: o[k] for k in MESH_SIGNATURE}
    parameters["tiles"] = [[float(x) for x in core] for core, _ in plan.tiles]
    signature = {"inputs": {"scene": str(Path(scene.scene_json).absolute())},
                 "parameters": parameters}  # fmt: skip
    n_blocks = 0
    with (
        engine_for(path, signature, workers=workers, scheduler=scheduler, resume=resume,
                   preload=("fusion.scene_mesh",)) as engine,
        full_disk_named(path),
        PlyWriter(path, colours=True, comments=_crs_comments(scene.crs)) as ply,
    ):  # fmt: skip
        plan, blocks = planned_tiles(scene.views, plan, engine)
        for piece in tile_pieces(scene.views, plan, blocks, engine):
            ply.add_vertices(piece.vertices, piece.colours)
            ply.add_triangles(piece.triangles)
            n_blocks += piece.blocks
        if not ply.n_triangles:
            raise WorkbenchError("mesh: the views' depth maps gave no surface inside the bounds")
        described = engine.describe()  # the workers' peak memory, while they live
    return {**plan.record(len(scene.views), n_blocks, ply.n_vertices, ply.n_triangles),
            **described}  # fmt: skip


# what an interrupted mesh must share with its resumption, beside the scene
MESH_SIGNATURE = ("voxel_m", "trunc_voxels", "bounds", "min_weight", "max_memory_fraction",
                  "tile_m")  # fmt: skip


@dataclass
class MeshPlan:
    """How an area is meshed: voxel edge (m), truncation (voxels), bounds, the local
    origin (world metres), the tiles (None: one grid), the blocks one grid is made for,
    the weight threshold and the memory limit (bytes)."""

    voxel_m: float
    trunc_voxels: float
    bounds: tuple | None
    origin: np.ndarray
    tiles: list | None
    blocks: int
    min_weight: float
    limit: float
    fit_tiles: bool = False  # the tiles sized by default: made to hold TILE_BLOCKS at most

    def record(self, views: int, blocks: int, vertices: int, triangles: int) -> dict:
        return {
            "voxel_m": self.voxel_m, "trunc_m": round(self.trunc_voxels * self.voxel_m, 4),
            "bounds": list(self.bounds) if self.bounds is not None else None,
            "views": views, "blocks": blocks, "tiles": len(self.tiles) if self.tiles else 1,
            "vertices": vertices, "triangles": triangles,
        }  # fmt: skip


def _plan(scene, voxel_m, trunc_voxels, bounds, min_weight, max_memory_fraction,
          tile_m) -> MeshPlan:  # fmt: skip
    voxel_m = float(voxel_m or scene.gsd or 0.25)
    bounds = bounds or scene.bounds
    for v in scene.views:
        if v.depth_path is None:
            raise InputError(v.image_path, "depth", "mesh: every view needs a depth map")
    limit = max_memory_fraction * physical_memory()
    if bounds is None:
        centre = np.mean([v.camera.center for v in scene.views], axis=0) * [1, 1, 0]
        tiles, blocks = None, 100_000
    else:
        centre = np.array([(bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2, 0.0])
        need = grid_bytes(bounds, voxel_m)
        if tile_m is None and need <= limit:
            tiles = None
        else:
            # half the limit a tile: Open3D's extraction and the tile's triangles on top
            side = tile_m or min(fitting_tile_m(voxel_m, limit / 2), largest_tile_m(voxel_m))
            tiles = mesh_tiles(bounds, voxel_m, side)
            need = grid_bytes(tiles[0][1], voxel_m)
        if need > limit:
            raise WorkbenchError(
                f"mesh: --voxel {voxel_m:g} over {bounds} needs about {need / 2**30:.1f} GiB"
                f"{' a tile' if tiles else ''}, more than {max_memory_fraction:.0%} of this "
                f"machine's {physical_memory() / 2**30:.0f} GiB; use a larger --voxel"
                f"{' or a smaller --tile' if tiles else ''}"
            )
        blocks = int(grid_columns(bounds, voxel_m) * BLOCKS_PER_COLUMN) + 1000
    origin = np.round(centre / 1000.0) * 1000.0
    return MeshPlan(voxel_m, trunc_voxels, bounds, origin, tiles, blocks, min_weight, limit,
                    fit_tiles=tiles is not None and tile_m is None)  # fmt: skip


def _uint8_colours(colors: np.ndarray) -> np.ndarray:
    return np.clip(colors * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _crs_comments(crs) -> list[str] | None:
    from workbench.model_run import crs_text

    return [f"crs {crs_text(crs)}"] if crs is not None else None


def grid_columns(bounds, voxel_m: float) -> float:
    """Columns of voxel blocks over ``bounds`` (xmin, ymin, xmax, ymax)."""
    return (bounds[2] - bounds[0]) * (bounds[3] - bounds[1]) / (BLOCK_VOXELS * voxel_m) ** 2


def grid_bytes(bounds, voxel_m: float) -> float:
    """Estimated peak bytes of a voxel block grid over ``bounds``."""
    return grid_columns(bounds, voxel_m) * BLOCKS_PER_COLUMN * BLOCK_BYTES * PEAK_FACTOR


def fitting_tile_m(voxel_m: float, limit: float) -> float:
    """The side of the largest square tile (with its margin of a block each side) whose
    grid's estimate stays under ``limit`` bytes, metres."""
    block_m = BLOCK_VOXELS * voxel_m
    side = np.sqrt(limit / grid_bytes((0.0, 0.0, 1.0, 1.0), voxel_m)) - 2 * block_m
    return max(block_m, side)


def largest_tile_m(voxel_m: float) -> float:
    """The side of a tile of about ``TILE_BLOCKS`` blocks, metres."""
    return np.sqrt(TILE_BLOCKS / BLOCKS_PER_COLUMN) * BLOCK_VOXELS * voxel_m


def mesh_tiles(bounds, voxel_m: float, tile_m: float) -> list[tuple[tuple, tuple]]:
    """Square tiles of ``tile_m`` (rounded up to whole blocks) over ``bounds``: per tile
    (core, grown). The core is the area whose triangles the tile keeps, half-open (xmin,
    ymin, xmax, ymax), the outer rows and columns running on to infinity (the surface
    reaches a little past the bounds); grown is the tile within the bounds widened by a
    block, so that every cube of the core has its neighbours."""
    block_m = BLOCK_VOXELS * voxel_m
    side = np.ceil(tile_m / block_m) * block_m
    xs = np.arange(bounds[0], bounds[2], side)
    ys = np.arange(bounds[1], bounds[3], side)
    tiles = []
    for j, y0 in enumerate(ys):
        for i, x0 in enumerate(xs):
            core = (-np.inf if i == 0 else x0, -np.inf if j == 0 else y0,
                    np.inf if i == len(xs) - 1 else x0 + side,
                    np.inf if j == len(ys) - 1 else y0 + side)  # fmt: skip
            grown = (x0 - block_m, y0 - block_m, min(x0 + side, bounds[2]) + block_m,
                     min(y0 + side, bounds[3]) + block_m)  # fmt: skip
            tiles.append((tuple(float(c) for c in core), tuple(float(g) for g in grown)))
    return tiles


def _new_grid(voxel_m: float, blocks: int):
    return o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=voxel_m,
        block_resolution=BLOCK_VOXELS,
        block_count=blocks,
        device=o3c.Device("CPU:0"),
    )


def _integrate(views, box, voxel_m, trunc_voxels, bounds, origin, blocks, desc):
    """A grid of ``views`` integrated, into the blocks within ``box`` (block indices of
    the local frame, inclusive: x0, y0, x1, y1) only when given. ``views`` is a list of
    views, or of (view, footprint) pairs, the footprint the box of the blocks the view
    allocates (:func:`view_blocks`): a view whose footprint misses ``box`` is not read."""
    grid = _new_grid(voxel_m, blocks)
    for item in progress(views, desc):
        view, foot = item if isinstance(item, tuple) else (item, None)
        if foot is not None and not _overlap(foot, box):
            continue
        seen = _view_depth_blocks(grid, view, bounds, origin, trunc_voxels)
        if seen is None:
            continue
        d_img, K, E, far, coords = seen
        if box is not None:
            xy = coords.numpy()[:, :2]
            inside = np.all((xy >= box[:2]) & (xy <= box[2:]), axis=1)
            if not inside.any():
                continue
            coords = o3c.Tensor(np.ascontiguousarray(coords.numpy()[inside]))
        image = undistorted_image(view).astype(np.float32) / 255.0
        K = nearest_pixel_intrinsics(K)
        grid.integrate(coords, d_img, o3d.t.geometry.Image(o3c.Tensor(image)), K, K, E, 1.0,
                       far, trunc_voxel_multiplier=trunc_voxels)  # fmt: skip
    return grid


def nearest_pixel_intrinsics(K: o3c.Tensor) -> o3c.Tensor:
    """The (3, 3) intrinsics to hand Open3D's ``VoxelBlockGrid.integrate`` for a
    camera's ``K`` (OpenCV's: a pixel's centre at its integer coordinates): the
    principal point half a pixel further along both image axes.

    ``integrate`` projects a voxel with ``K`` and then reads the depth and colour of
    the pixel at the projection's integer part, truncated (isl-org/Open3D#7580): the
    pixel up to a whole one before the nearest, on average half a pixel. Every surface
    came out moved half a pixel's footprint along the image's axes. Five blocks seen by
    nadir views, pixels of 0.0625 m at their roofs: walls 0.065-0.077 m east on average,
    0.002-0.006 m with this (tested). On ``small`` seed 0 the mesh's walls facing east
    stood 0.7 of a cell (median) out and its heights 0.064 m low on flat ground; with
    this 0.0 cells and 0.002 m, and the DSM sampled from it 0.035 m off the truth
    (median) where it was 0.076 m. Moved by half a pixel, the truncation takes the
    nearest pixel."""
    shifted = K.numpy().copy()
    shifted[:2, 2] += 0.5
    return o3c.Tensor(shifted, o3c.float64)


def _view_depth_blocks(grid, view, bounds, origin: np.ndarray, trunc_voxels: float):
    """A view's depth inside ``bounds`` as Open3D takes it: (depth image, intrinsics,
    local extrinsics, far plane, the blocks it allocates in ``grid``'s lattice, a (N, 3)
    tensor; computing them inserts nothing), or None when it sees nothing there."""
    depth = in_bounds(undistorted_depth(view), view.camera, bounds)
    if not (depth > 0).any():
        return None
    d_img = o3d.t.geometry.Image(o3c.Tensor(depth))
    K = o3c.Tensor(view.camera.K, o3c.float64)
    E = o3c.Tensor(local_extrinsic(view.camera, origin), o3c.float64)
    far = float(depth.max()) + 1.0
    try:
        coords = grid.compute_unique_block_coordinates(
            d_img, K, E, 1.0, far, trunc_voxel_multiplier=trunc_voxels
        )
    except RuntimeError as e:
        # Open3D aborts when a view's depth touches no block, as when its pixels inside
        # the bounds are a few on the image's border (small seed 0's v002_E, meshed over
        # a part of the scene: one pixel, in its second column)
        if NO_BLOCK_TOUCHED in str(e):
            return None
        raise
    return d_img, K, E, far, coords


def _overlap(a, b) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


KEY_BITS = 21  # bits of each block index in a block's key: +-1 million blocks
KEY_BATCH = 32  # views whose blocks' keys are joined to the others' at once


def block_keys(coords: np.ndarray) -> np.ndarray:
    """(N,) int64 key of each block's (N, 3) indices, ordered as (x, y, z)."""
    c = coords.astype(np.int64) + (1 << (KEY_BITS - 1))
    return (c[:, 0] << (2 * KEY_BITS)) | (c[:, 1] << KEY_BITS) | c[:, 2]


def key_xy(keys: np.ndarray) -> np.ndarray:
    """(N, 2) x and y block indices of ``keys``."""
    mask = (1 << KEY_BITS) - 1
    x = (keys >> (2 * KEY_BITS)) - (1 << (KEY_BITS - 1))
    y = ((keys >> KEY_BITS) & mask) - (1 << (KEY_BITS - 1))
    return np.column_stack([x, y])


class ViewBlocks(NamedTuple):
    """What :func:`view_blocks` found: per view the box of its blocks (or None) and the
    sorted keys of every view's blocks."""

    boxes: list
    keys: np.ndarray


def view_blocks(views, bounds, voxel_m, trunc_voxels, origin) -> ViewBlocks:
    """The blocks the views allocate (a first pass over their depth maps, no grid): per
    view the box of its blocks' x and y indices (x0, y0, x1, y1; None for a view that
    sees nothing inside ``bounds``), and the sorted keys of every view's blocks."""
    scratch = _new_grid(voxel_m, 1)  # for its lattice only
    boxes, keys, batch = [], np.zeros(0, np.int64), []
    for view in progress(views, "mesh: the views' blocks"):
        seen = _view_depth_blocks(scratch, view, bounds, origin, trunc_voxels)
        if seen is None:
            boxes.append(None)
            continue
        coords = seen[-1].numpy()
        boxes.append((*coords[:, :2].min(axis=0), *coords[:, :2].max(axis=0)))
        batch.append(block_keys(coords))
        if len(batch) == KEY_BATCH:  # one sort per batch, not per view (116 of 128 s)
            keys, batch = np.unique(np.concatenate([keys, *batch])), []
    return ViewBlocks(boxes, np.unique(np.concatenate([keys, *batch])))


class TilePiece(NamedTuple):
    """What a tile adds to the mesh: the vertices it is the first to use ((N, 3) float64
    world metres, sorted by x, then y, then z; (N, 3) uint8 colours), its triangles
    ((T, 3) int64 on the indices of the whole mesh's vertices, each started at its
    lowest index and sorted) and the voxel blocks it integrated."""

    vertices: np.ndarray
    colours: np.ndarray
    triangles: np.ndarray
    blocks: int


def tile_box(core, grown, origin: np.ndarray, voxel_m: float, xy: np.ndarray) -> tuple:
    """The block indices (x0, y0, x1, y1, inclusive) of a tile of :func:`mesh_tiles`: its
    grown window's, and on its outer sides every block a view allocates past the bounds
    (``xy``: (N, 2) the blocks' x and y indices)."""
    block_m = BLOCK_VOXELS * voxel_m
    lo = np.floor((np.array(grown[:2]) - origin[:2]) / block_m).astype(np.int64)
    hi = np.floor((np.array(grown[2:]) - origin[:2]) / block_m).astype(np.int64)
    if len(xy):
        lo = np.where(np.isinf(core[:2]), np.minimum(lo, xy.min(axis=0)), lo)
        hi = np.where(np.isinf(core[2:]), np.maximum(hi, xy.max(axis=0)), hi)
    return (*lo, *hi)


def tile_block_count(box: tuple, xy: np.ndarray) -> int:
    """How many of the blocks ``xy`` ((N, 2) x and y indices) lie in ``box``."""
    return int(np.all((xy >= box[:2]) & (xy <= box[2:]), axis=1).sum())


def fitted_tiles(plan: MeshPlan, keys: np.ndarray, max_blocks: int = TILE_BLOCKS) -> list:
    """The plan's tiles made smaller until none holds more than ``max_blocks`` of the
    views' blocks (``keys``): their side was set from blocks per column measured on
    `small` (8), and a city's tiles held up to 113,000 blocks (11 a column, more in its
    dense parts), twice the memory meant."""
    xy = key_xy(keys)
    block_m = BLOCK_VOXELS * plan.voxel_m
    tiles = plan.tiles
    side = tiles[0][1][2] - tiles[0][1][0] - 2 * block_m  # the first tile's core
    while True:
        most = max(tile_block_count(tile_box(*t, plan.origin, plan.voxel_m, xy), xy)
                   for t in tiles)  # fmt: skip
        if most <= max_blocks or side <= 4 * block_m:
            return tiles
        side = max(4 * block_m, np.floor(side * np.sqrt(max_blocks / most) / block_m) * block_m)
        tiles = mesh_tiles(plan.bounds, plan.voxel_m, side)


def planned_tiles(views, plan: MeshPlan,
                  engine: Engine | None = None) -> tuple[MeshPlan, ViewBlocks]:  # fmt: skip
    """The views' blocks (:func:`view_blocks`; kept in ``engine``'s task store, when it
    has one, for a resumed run) and the plan with its tiles made to hold at most
    ``TILE_BLOCKS`` of them when it sized them itself (:func:`fitted_tiles`)."""
    store = engine.store if engine is not None else None
    if store is not None and store.has("view_blocks", "all"):
        blocks = store.load("view_blocks", "all")
    else:
        blocks = view_blocks(views, plan.bounds, plan.voxel_m, plan.trunc_voxels, plan.origin)
        if store is not None:
            store.save("view_blocks", "all", blocks)
    if plan.fit_tiles:
        plan = dataclasses.replace(plan, tiles=fitted_tiles(plan, blocks.keys))
    return plan, blocks


@dataclass
class TileContext:
    """What every tile's task reads (:func:`tile_mesh`): the views with the boxes of their
    blocks (views that see nothing dropped), the plan and every block's x and y indices."""

    footed: list
    plan: MeshPlan
    xy: np.ndarray


class TileMesh(NamedTuple):
    """A tile's surface, its triangles whose centre lies in its core: (N, 3) float64
    vertices in the plan's local frame, (N, 3) float colours (0-1), (T, 3) int64
    triangles on them, and the voxel blocks the tile integrated."""

    vertices: np.ndarray
    colours: np.ndarray
    triangles: np.ndarray
    blocks: int


def tile_mesh(k: int, ctx: TileContext) -> TileMesh:
    """Task: tile ``k`` of ``ctx.plan`` integrated from the views whose blocks reach it,
    its surface extracted by marching cubes and cut to its core."""
    plan = ctx.plan
    core, grown = plan.tiles[k]
    box = tile_box(core, grown, plan.origin, plan.voxel_m, ctx.xy)
    desc = f"mesh: tile {k + 1} of {len(plan.tiles)}"
    grid = _integrate(ctx.footed, box, plan.voxel_m, plan.trunc_voxels, plan.bounds,
                      plan.origin, tile_block_count(box, ctx.xy) + 1000, desc)  # fmt: skip
    held = int(grid.hashmap().size())
    mesh = grid.extract_triangle_mesh(weight_threshold=plan.min_weight).to_legacy()
    del grid
    V = np.asarray(mesh.vertices, np.float64)
    T = np.asarray(mesh.triangles, np.int64)
    if not len(T):
        return TileMesh(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), np.int64), held)
    c = (V[T].mean(axis=1) + plan.origin)[:, :2]
    keep = ((c[:, 0] >= core[0]) & (c[:, 0] < core[2])
            & (c[:, 1] >= core[1]) & (c[:, 1] < core[3]))  # fmt: skip
    used, T = np.unique(T[keep], return_inverse=True)
    return TileMesh(V[used], np.asarray(mesh.vertex_colors)[used], T.reshape(-1, 3), held)


def check_tile_memory(plan: MeshPlan, xy: np.ndarray, at_once: int) -> None:
    """Refuse, before any tile is meshed, a plan whose largest tile's voxel grid, times
    the ``at_once`` tiles meshed at once on this machine, would not fit in its memory."""
    for k, (core, grown) in enumerate(plan.tiles):
        count = tile_block_count(tile_box(core, grown, plan.origin, plan.voxel_m, xy), xy)
        need = count * BLOCK_BYTES * PEAK_FACTOR
        if need * at_once > plan.limit:
            fewer = f" and {at_once} at once (fewer --workers)" if at_once > 1 else ""
            raise WorkbenchError(
                f"mesh: tile {k + 1} holds {count:,} voxel blocks, about "
                f"{need / 2**30:.1f} GiB{fewer}, more than this machine allows "
                f"({plan.limit / 2**30:.1f} GiB); use a smaller --tile"
            )


def tile_pieces(views, plan: MeshPlan, blocks: ViewBlocks,
                engine: Engine | None = None) -> Iterator[TilePiece]:  # fmt: skip
    """The tiles' meshes, each a task of ``engine`` (:func:`tile_mesh`; default: this
    process, one after another), joined into one mesh in the tiles' order.

    A first pass has found every view's blocks (``blocks``, :func:`view_blocks`): each
    tile's grid is made for the blocks it will hold (Open3D's block grid does not grow
    past its ``block_count``), a view is read for a tile only when its blocks reach it,
    and the outer tiles reach as far past the bounds as any view's blocks do.

    A vertex two tiles share is the same float in both; it lies within a voxel's
    diagonal of the edge between their cores, since the triangles of marching cubes do
    not leave their cube. So each tile looks up its vertices near its core's edges
    among the earlier tiles' (by position and colour, which :func:`welded` makes one
    vertex's), and keeps its own for the tiles still to come: those of
    the row of tiles before it and of its own row, all a tile can touch, so the table
    does not grow with the area."""
    engine = engine or ThreadEngine(1)
    tiles, voxel_m, origin = plan.tiles, plan.voxel_m, plan.origin
    xy = key_xy(blocks.keys)
    check_tile_memory(plan, xy, engine.workers if engine.local else 1)
    footed = [(v, b) for v, b in zip(views, blocks.boxes, strict=True) if b is not None]
    shared = engine.share(TileContext(footed, plan, xy))
    near = 2.0 * voxel_m  # more than a cube's diagonal in x and y
    border = _BorderVertices()
    n_vertices = 0
    meshes = engine.map(tile_mesh, range(len(tiles)), shared, stage="tiles",
                        in_flight=engine.workers)  # fmt: skip
    for (core, grown), (V, colours, T, held) in zip(tiles, meshes, strict=True):
        border.start_row(grown[1])
        if not len(T):
            yield TilePiece(np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                            np.zeros((0, 3), np.int64), held)  # fmt: skip
            continue
        # welded as written: a file read back orders the same
        V, colours, T = welded(V, T, _uint8_colours(colours))
        key = _vertex_keys(V, colours)
        w = V[:, :2] + origin[:2]
        edge = np.min(np.abs(np.column_stack([w - core[:2], w - core[2:]])), axis=1) < near
        ids = np.full(len(V), -1, np.int64)
        ids[edge] = border.find(key[edge])
        new = np.flatnonzero(ids < 0)  # in welded's order
        ids[new] = n_vertices + np.arange(len(new))
        n_vertices += len(new)
        border.add(key[edge], ids[edge])
        yield TilePiece(V[new] + origin, colours[new],
                        canonical_triangles(ids[T]), held)  # fmt: skip


class _BorderVertices:
    """The vertices near the edges of the tiles written so far, by exact key, kept for
    the tiles of the current row and the row before it."""

    def __init__(self):
        self.keys, self.ids, self.rows = [], [], []
        self.row = None

    def start_row(self, row: float) -> None:
        """Enter the tile whose row starts at ``row`` (increasing): drop the rows before
        the previous one."""
        if row != self.row:
            last = self.row
            kept = [i for i, r in enumerate(self.rows) if r == last]
            self.keys = [self.keys[i] for i in kept]
            self.ids = [self.ids[i] for i in kept]
            self.rows = [self.rows[i] for i in kept]
            self.row = row

    def add(self, keys: np.ndarray, ids: np.ndarray) -> None:
        self.keys.append(keys)
        self.ids.append(ids)
        self.rows.append(self.row)

    def find(self, keys: np.ndarray) -> np.ndarray:
        """(N,) index of each key's vertex, -1 for a key not kept."""
        if not self.keys or not len(keys):
            return np.full(len(keys), -1, np.int64)
        known = np.concatenate(self.keys)
        _, inverse = np.unique(np.concatenate([known, keys]), return_inverse=True)
        inverse = inverse.reshape(-1)
        owner = np.full(inverse.max() + 1, -1, np.int64)
        owner[inverse[: len(known)]] = np.concatenate(self.ids)
        return owner[inverse[len(known) :]]


def _vertex_keys(V: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """(N,) keys equal exactly when position and colour are (48-byte rows)."""
    rows = np.ascontiguousarray(np.column_stack([V, colours]), np.float64)
    return rows.view(np.dtype((np.void, rows.itemsize * 6))).reshape(-1)


def welded(
    vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The mesh in an order of its geometry alone, its vertices at one position and of
    one colour made one.

    Open3D integrates and extracts its voxel blocks in many threads, so the same surface
    comes out with its vertices and triangles in another order from run to run (seed 5
    of `small`: 3.2 M triangles, the same sets, the files different); where two triangles
    tie for a ray, the mesh's sampling then takes one or the other, and the LOD path's
    figures moved between runs of the same code. Marching cubes also gives a few
    vertices twice at one position, where two sheets of the surface meet (185 positions
    among the city's 20.7 M vertices), most of one colour: nothing geometric orders such
    twins (their triangles' corners did not, the city's mesh from 1 and 2 workers then
    differed in 4 bytes), so they are one vertex here, as they are one point of the
    surface. A triangle two of whose corners become one has no area and is dropped.

    Vertices are sorted by position (x, then y, then z), then colour; each triangle is
    turned, keeping its winding, to start at its lowest vertex, and the triangles sorted.

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
    colours : (V, 3) uint8, optional
        The vertices' colours as written; twins of other colours stay apart.

    Returns
    -------
    vertices : (V', 3) float64
    colours : (V', 3) uint8 or None
    triangles : (T', 3) int64
    """
    rows = np.asarray(vertices, np.float64)
    if colours is not None:
        rows = np.column_stack([rows, np.asarray(colours, np.float64)])
    order = np.lexsort(rows.T[::-1])
    rows = rows[order]
    first = np.r_[True, np.any(rows[1:] != rows[:-1], axis=1)]
    vertex = np.empty(len(order), np.int64)
    vertex[order] = np.cumsum(first) - 1
    t = vertex[np.asarray(triangles, np.int64)].reshape(-1, 3)
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    used, t = np.unique(t, return_inverse=True)
    rows = rows[first][used]
    out_colours = None if colours is None else rows[:, 3:].astype(np.uint8)
    return rows[:, :3], out_colours, canonical_triangles(t.reshape(-1, 3))


def canonical_triangles(t: np.ndarray) -> np.ndarray:
    """(T, 3) triangles each turned, keeping its winding, to start at its lowest vertex,
    and sorted."""
    first = np.argmin(t, axis=1)
    t = t[np.arange(len(t))[:, None], (first[:, None] + np.arange(3)) % 3]
    return t[np.lexsort((t[:, 2], t[:, 1], t[:, 0]))]


def write_scene_mesh(path, mesh: SceneMesh, crs) -> None:
    """Write ``mesh`` as binary PLY (float64 positions, vertex colours, the CRS in a
    ``comment crs`` header line, which ``workbench fusion --mesh`` reads), whole or not
    at all: it is written beside ``path`` and moved into place."""
    from workbench.meshio import write_ply

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    write_ply(partial, mesh.vertices, mesh.triangles, vertex_colors=mesh.colors,
              comments=_crs_comments(crs))  # fmt: skip
    partial.replace(path)


def local_extrinsic(camera, origin: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera matrix of ``camera`` for points relative to ``origin``:
    x_cam = R (X_local + origin) + t."""
    E = np.eye(4)
    E[:3, :3] = camera.R
    E[:3, 3] = camera.t + camera.R @ origin
    return E


def _undistort_maps(camera):
    return cv2.initUndistortRectifyMap(camera.K, camera.distortion, None, camera.K,
                                       (camera.width, camera.height), cv2.CV_32FC1)  # fmt: skip


def undistorted_depth(view) -> np.ndarray:
    """The view's z-depth (H, W) float32 (0 unknown) through a pinhole of the same K
    (Open3D integrates without distortion)."""
    depth = np.ascontiguousarray(view.read_depth(), np.float32)
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    if view.camera.has_distortion:  # nearest: no depth between two surfaces
        depth = cv2.remap(depth, *_undistort_maps(view.camera), cv2.INTER_NEAREST)
    return np.ascontiguousarray(depth)


def undistorted_image(view) -> np.ndarray:
    """The view's image (H, W, 3) uint8 through a pinhole of the same K."""
    image = view.read_image()
    if view.camera.has_distortion:
        image = cv2.remap(image, *_undistort_maps(view.camera), cv2.INTER_LINEAR)
    return np.ascontiguousarray(image)


def in_bounds(depth: np.ndarray, camera, bounds) -> np.ndarray:
    """``depth`` (H, W) with 0 where its pixel's point lies outside ``bounds`` (world xmin,
    ymin, xmax, ymax; None keeps every pixel). ``depth`` is undistorted: its pixels are
    read through ``camera``'s pinhole."""
    if bounds is None:
        return depth
    pinhole = dataclasses.replace(camera, distortion=np.zeros(5))
    origin, dirs = pinhole.pixel_grid_rays()
    X = origin + dirs * depth.reshape(-1, 1)
    out = (
        (X[:, 0] < bounds[0])
        | (X[:, 0] > bounds[2])
        | (X[:, 1] < bounds[1])
        | (X[:, 1] > bounds[3])
    )
    return np.where(out.reshape(depth.shape), np.float32(0.0), depth)
