"""The voxel path end to end: a scene and its footprints in, a :class:`ModelRun` out.

The steps of the paper, each in the module named after it: :mod:`.proxy` (section 4:
voxelisation, photo-consistency, height clustering, the proxy mesh),
:mod:`.surface_graph` (5.1-5.2: the surface graph and its cuts), :mod:`.texture_atlas`,
:mod:`.ground_texture` (5.3-5.4: the ground and ring cuts); :mod:`.building` runs them
for one building, :mod:`.inputs` reads what they need. This module orders and times them.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Iterable
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import rasterio.features
from scipy.spatial import cKDTree
from shapely.geometry import mapping

from workbench.engine import Engine, TaskStore, ThreadEngine
from workbench.model_run import (
    Building,
    BuildingsOnDisk,
    ModelRun,
    Surface,
    Texture,
    TexturedPieces,
)
from workbench.raster import Grid, WindowedRaster, decimated_cells
from workbench.records import StageTimer, peak_memory_mb
from workbench.scene import Scene

from .building import Proxy, building_proxy, texture_building
from .building import Texture as BuildingTexture
from .ground_texture import (
    GroundTexture,
    RingSamples,
    ground_cut,
    ground_mesh,
    ground_mesh_step,
    ground_record,
    ring_cut,
    ring_samples,
)
from .ground_tiles import CUT, HEIGHTS, GroundTiles, PaintedGround
from .inputs import VoxelInputs, neighbour_scene, read_inputs
from .occluders import Occluders
from .options import VoxelOptions
from .preview import voxel_preview

log = logging.getLogger(__name__)

_WALL_FOOT_M = 1.0  # wall texels this close above the ground continue onto it (ring cut)
_COMMON = ("id", "base_z", "faces")  # proxy record keys model.json's common keys replace


def run_voxel(
    scene_dir: Path,
    options: VoxelOptions | None = None,
    *,
    footprints: Path | None = None,
    fusion_dir: Path | None = None,
    engine: Engine | None = None,
) -> ModelRun:
    """The voxel path (Garcia-Dorado, Demir & Aliaga 2013) on a scene's images.

    Parameters
    ----------
    scene_dir : path
        A scene (scene.json) with calibrated views.
    options : VoxelOptions
    footprints : path, optional
        GeoJSON footprints with a height (default: the scene's; else the fusion's
        building regions).
    fusion_dir : path, optional
        A fusion run: its DTM is the ground, its nDSM marks ground columns and places
        flat roofs (see the options).
    engine : Engine, optional
        Runs the buildings' tasks (:mod:`workbench.engine`); its store keeps finished
        buildings for ``--resume``. Default: this process, one building at a time (the
        command starts a Dask cluster of ``options.workers`` processes).
    """
    options = options or VoxelOptions()
    engine = engine or ThreadEngine(1)  # the views' image cache is one per process
    with proxy_shelf(engine) as shelf:
        return _run(scene_dir, options, footprints, fusion_dir, engine, shelf)


@contextmanager
def proxy_shelf(engine: Engine):
    """Where a run's proxies and wall feet wait between its stages: a folder of the
    engine's task store (kept for ``--resume``; every worker must see it), else a
    temporary one. A city's do not fit in the command: some 100 KB a proxy and 16 KB a
    wall foot on `small`, some 8 GB for a 100 km² city's 67,000 buildings."""
    if engine.store is not None:
        yield TaskStore(engine.store.scratch("shelf"))
        return
    with tempfile.TemporaryDirectory(prefix="voxel-shelf-") as d:
        yield TaskStore(d)


def _run(scene_dir, options, footprints, fusion_dir, engine, shelf) -> ModelRun:
    timer = StageTimer()
    t_start = time.perf_counter()
    with timer.stage("read"):
        inputs = read_inputs(scene_dir, options, footprints, fusion_dir)
        shared = engine.share(inputs)
        ids = [f.id for f, _, _ in inputs.buildings]
    with timer.stage("proxies"):
        proxies = build_proxies(inputs, options, shelf, engine, shared, ids)
    with timer.stage("textures"):
        occluders = engine.share(proxy_occluders(proxies, inputs))
        big = max(range(len(proxies)), key=lambda i: proxies[i].columns) if proxies else -1
        items = [(p, i == big) for i, p in enumerate(proxies)]
        # a building whose texture task fails is left out; its proxy still hides the
        # ground behind it
        textured = engine.map(texture_task, items, shared, options, occluders, shelf,
                              stage="textures", keys=[p.id for p in proxies],
                              on_failure=lambda item, why: (None, None))  # fmt: skip
        buildings, done, costs, shown = kept_textured(textured, engine)
    with timer.stage("ground"):
        ground = texture_ground(inputs, proxies, done, options, engine, shared, occluders,
                                shelf)  # fmt: skip
    with timer.stage("preview"):
        shown_proxy = shelf.load("proxy", proxies[big].id) if proxies else None
        preview = voxel_preview(shown_proxy, shown, buildings, ground)
    return ModelRun(
        "voxel", options, buildings, crs=inputs.scene.crs,
        grid=ground.grid if ground is not None else None,
        dtm=ground.dtm if ground is not None else None,
        raster_files={"dtm": ground.dtm_file} if ground and ground.dtm_file else {},
        ground=ground.surface if ground is not None else None, preview=preview,
        stages=timer.stages,
        inputs={
            "scene": str(Path(scene_dir).resolve()), "footprints": inputs.footprint_source,
            "fusion": str(Path(fusion_dir).resolve()) if fusion_dir else None,
            "ground_model": inputs.ground.source,
        },
        counts={"skipped": len(inputs.skipped), "footprints": inputs.footprint_count},
        record={
            "skipped": inputs.skipped, "ground": ground.record if ground is not None else None,
            "texture": texture_summary(costs),
            **engine.describe(),
            "seconds_per_building": round((time.perf_counter() - t_start) / max(len(proxies), 1),
                                          3),
            "peak_memory_mb": round(peak_memory_mb(), 1),
        },
    )  # fmt: skip


@dataclass(frozen=True)
class ProxyEntry:
    """What the command keeps of a proxy, which waits on the run's shelf.

    Attributes
    ----------
    id : str
    box : (6,) tuple
        Its mesh's bounds (xmin, ymin, zmin, xmax, ymax, zmax), world metres.
    outline : (4,) tuple
        Its outline's bounds (xmin, ymin, xmax, ymax), world metres.
    columns : int
        Its voxel columns (the preview shows the largest proxy).
    """

    id: str
    box: tuple
    outline: tuple
    columns: int


def build_proxies(
    inputs: VoxelInputs,
    options: VoxelOptions,
    shelf: TaskStore,
    engine: Engine | None = None,
    shared=None,
    ids: list[str] | None = None,
) -> list[ProxyEntry]:
    """Section 4 for every usable footprint (a task each), each with the initial proxies
    of its neighbours as occlusion masks; footprints without a consistent roof are
    skipped. ``shared`` is the engine's handle on ``inputs``; the proxies go on ``shelf``
    (stage "proxy", their meshes "mesh"), the command keeps their entries."""
    engine = engine or ThreadEngine(1)
    ids = ids if ids is not None else [f.id for f, _, _ in inputs.buildings]
    shared = shared if shared is not None else inputs
    entries: list[ProxyEntry] = []
    tasks = engine.map(proxy_task, range(len(ids)), shared, options, shelf, stage="proxies",
                       keys=ids, on_failure=lambda j, why: why)  # fmt: skip
    for j, e in enumerate(tasks):
        if isinstance(e, str):  # the task failed
            inputs.skipped.append({"id": ids[j], "reason": e})
            continue
        if e is None:
            inputs.skipped.append({"id": ids[j], "reason": "no photo-consistent roof"})
            log.warning("footprint %s: no photo-consistent roof, skipped", ids[j])
            continue
        entries.append(e)
    return entries


def proxy_task(j: int, inputs: VoxelInputs, options: VoxelOptions,
               shelf: TaskStore) -> ProxyEntry | None:  # fmt: skip
    """Task: section 4 for the ``j``-th usable footprint; its proxy and mesh go on
    ``shelf``, its entry comes back (None for an empty proxy)."""
    f, base, h = inputs.buildings[j]
    occluders = neighbour_scene(j, inputs, options)
    p = building_proxy(
        f.id, f.polygon, h, base, inputs.cameras, inputs.images, options, occluders,
        inputs.fused_ndsm,
    )  # fmt: skip
    if p.empty:
        return None
    p.record["height_source"] = f.properties.get("_height_source", "GIS")
    p.record["gis_footprint"] = mapping(f.polygon)
    shelf.save("proxy", p.id, p)
    shelf.save("mesh", p.id, (p.vertices, p.triangles))
    lo, hi = p.vertices.min(axis=0), p.vertices.max(axis=0)
    return ProxyEntry(p.id, (*lo, *hi), p.outline.bounds, int(p.columns.sum()))


def proxy_occluders(proxies: list[ProxyEntry], inputs: VoxelInputs) -> Occluders:
    """The proxies' boxes, to pick a window's occluders among their meshes (in the
    origin of the initial proxies' scenes)."""
    boxes = np.array([e.box for e in proxies], float).reshape(-1, 6)
    return replace(inputs.prisms, ids=[e.id for e in proxies], boxes=boxes[:, [0, 1, 3, 4]],
                   tops=boxes[:, 5])  # fmt: skip


# metres the rays' origins may stand above their surface (hidden_from lifts them 5 cm)
_LIFT_M = 0.1


def occluders_near(occluders: Occluders, shelf: TaskStore, cameras: list, lo, hi):
    """The ray-casting scene of the proxies that can hide a point of the box ``lo`` to
    ``hi`` ((3,) world metres) from a view that frames it (None if none can)."""
    near = occluders.around(cameras, lo, (hi[0], hi[1], hi[2] + _LIFT_M))
    return occluders.scene([shelf.load("mesh", occluders.ids[i]) for i in near])


@dataclass
class WallFoot:
    """Where a building's walls meet the ground, for the ring cut: its outline, and the
    positions (N, 2) world metres and views (N,) of its textured wall texels less than
    ``_WALL_FOOT_M`` above its base."""

    outline: object
    xy: np.ndarray
    views: np.ndarray


BUILDINGS_PER_BATCH = 32  # textured buildings pickled together when kept on disk


def kept_textured(textured: Iterable, engine: Engine):
    """The texture tasks' results as they come: the buildings (on disk in the engine's
    task store when it has one, a batch at a time: a city's atlases are gigabytes),
    whether each was textured (its wall foot is then on the shelf; not if its task
    failed), their seam costs, and the preview building's texture (None without one)."""
    store = engine.store
    buildings = BuildingsOnDisk(store.folder / "buildings") if store is not None else []
    done, costs, shown, batch = [], [], None, []
    for b, t in textured:
        done.append(b is not None)
        if b is None:  # its task failed (the engine's failures say why)
            continue
        costs.append({k: b.record[k] for k in SEAM_COSTS})
        shown = t if t is not None else shown
        batch.append(b)
        if len(batch) == BUILDINGS_PER_BATCH:
            buildings.extend(batch)
            batch = []
    buildings.extend(batch)
    return buildings, done, costs, shown


def texture_task(item: tuple, inputs: VoxelInputs, options: VoxelOptions,
                 occluders: Occluders, shelf: TaskStore):  # fmt: skip
    """Task: sections 5.1-5.2 for the proxy of entry ``item[0]``: the building of the
    run and its whole texture if ``item[1]`` (the preview's building), else None; its
    wall foot goes on ``shelf`` (stage "foot")."""
    e, keep = item
    p = shelf.load("proxy", e.id)
    near = occluders_near(occluders, shelf, inputs.cameras, e.box[:3], e.box[3:])
    t = texture_building(p, inputs.cameras, inputs.images, options, near)
    g = t.graph
    low = (np.abs(g.normals[:, 2]) < 0.5) & (g.positions[:, 2] < p.frame.base_z + _WALL_FOOT_M)
    low &= t.stitched.labels >= 0
    shelf.save("foot", p.id, WallFoot(p.outline, g.positions[low, :2],
                                      t.views[t.stitched.labels[low]]))  # fmt: skip
    return voxel_building(p, t), t if keep else None


def texture_ground(
    inputs: VoxelInputs, proxies: list[ProxyEntry], done: list[bool], options: VoxelOptions,
    engine: Engine, shared, occluders, shelf: TaskStore,
) -> TexturedGround | None:  # fmt: skip
    """Sections 5.3-5.4: the ground cut with the proxies masked out, a task per tile of
    ``GROUND_TILE`` texels, then the ring cut around each building in a window around it;
    returns the textured ground (None without proxies). ``shared`` and ``occluders`` are
    the engine's handles on the inputs and on the proxies' boxes.

    The tiles wait on ``shelf``. The ring cuts' samples of the views are tasks; the cuts
    themselves paint the ground here, building after building, since neighbouring rings
    overlap."""
    if not proxies:
        return None
    grid = ground_grid(inputs.scene, proxies, options.ground_gsd_m)
    tiles = GroundTiles(grid, ground_tile_size(grid.gsd), shelf)
    items = [(k, grid.window(*t)) for k, t in enumerate(tiles.tiles)]
    counts = engine.map(ground_tile_task, items, shared, options, occluders, shelf,
                        stage="ground")  # fmt: skip
    record = ground_record(grid, list(counts))
    windows, keys = [], []
    for e, textured in zip(proxies, done, strict=True):
        window = ring_window(grid, e.outline, options.ring_m) if textured else None
        if window is not None:
            windows.append(window)
            keys.append(e.id)
    samples = engine.map(ring_task, list(zip(windows, keys, strict=True)), shared, options,
                         occluders, tiles, stage="ring cuts", keys=keys)  # fmt: skip
    painted = PaintedGround(tiles)
    ring_texels = from_building = 0
    for window, s in zip(windows, samples, strict=True):
        image = painted.read(*window)
        r = ring_cut(GroundTexture(grid.window(*window), None, image), s, options.ring_m)
        painted.paint(*window, image)
        ring_texels += r["ring_texels"]
        from_building += r["from_building"]
    record["ring_texels"], record["ring_from_building"] = ring_texels, from_building
    folder = engine.store.scratch("ground") if engine.store is not None else None
    return textured_ground(tiles, painted, record, folder, inputs.scene.crs)


def ring_task(item: tuple, inputs: VoxelInputs, options: VoxelOptions, occluders: Occluders,
              tiles: GroundTiles) -> RingSamples:  # fmt: skip
    """Task: the building side of one ring cut, ``item`` = (the building's window of the
    ground grid, rows and columns; the building's id: its wall foot is on the shelf)."""
    window, key = item
    grid, z = tiles.grid.window(*window), tiles.read(HEIGHTS, *window)
    foot = tiles.shelf.load("foot", key)
    return ring_samples(grid, z, *ring_inputs(grid, foot), inputs.cameras, inputs.images,
                        window_occluders(occluders, tiles.shelf, inputs.cameras, grid, z),
                        options.ring_m)  # fmt: skip


def window_occluders(occluders: Occluders, shelf: TaskStore, cameras: list, grid: Grid,
                     z: np.ndarray):  # fmt: skip
    """The scene of the proxies that can hide a texel of ``grid`` at heights ``z`` (the
    ground's, NaN unknown: then every proxy) from a view that frames it."""
    x0, y0, x1, y1 = grid.bounds
    if not np.isfinite(z).any():
        lo, hi = (x0, y0, -np.inf), (x1, y1, np.inf)
    else:
        lo, hi = (x0, y0, float(np.nanmin(z))), (x1, y1, float(np.nanmax(z)))
    return occluders_near(occluders, shelf, cameras, lo, hi)


GROUND_TILE = 512  # texels per side of a ground tile: 256 m at 0.5 m


def ground_tile_size(gsd: float) -> int:
    """Texels per side of a ground tile: about ``GROUND_TILE``, a whole number of the
    ground mesh's quads (so that the tiles' meshes meet at shared vertices)."""
    step = ground_mesh_step(gsd)
    return step * max(1, round(GROUND_TILE / step))


def ground_tile_task(item: tuple, inputs: VoxelInputs, options: VoxelOptions,
                     occluders: Occluders, shelf: TaskStore) -> dict:  # fmt: skip
    """Task: the ground cut of one tile, ``item`` = (its index, its grid); its heights and
    texture go on ``shelf``, the cut's counts come back (with the views it used)."""
    k, grid = item
    z = inputs.ground(grid)
    cut = ground_cut(grid, z, inputs.cameras, inputs.images,
                     window_occluders(occluders, shelf, inputs.cameras, grid, z),
                     options.overlap_m)  # fmt: skip
    shelf.save(HEIGHTS, str(k), z)
    shelf.save(CUT, str(k), cut.image)
    return {**cut.counts, "views": sorted(int(v) for v in np.unique(cut.labels[cut.labels >= 0]))}


@dataclass
class TexturedGround:
    """The voxel path's ground, as the run writes it.

    Attributes
    ----------
    grid : Grid
    surface : Surface or TexturedPieces
        The textured mesh: one with one tile, else a piece per tile.
    dtm : (H, W) float array or None
        The ground's heights on ``grid``, metres (None when they are in ``dtm_file``).
    dtm_file : path or None
        The heights as a GeoTIFF, written a tile at a time.
    image : (h, w, 3) uint8
        The texture, decimated to at most ``PREVIEW_TEXELS`` a side (for the preview).
    record : dict
    """

    grid: Grid
    surface: Surface | TexturedPieces | None
    dtm: np.ndarray | None
    dtm_file: Path | None
    image: np.ndarray
    record: dict

    def surfaces(self) -> Iterable[Surface]:
        """The textured mesh's pieces."""
        if isinstance(self.surface, TexturedPieces):
            return self.surface
        return [self.surface] if self.surface is not None else []


PREVIEW_TEXELS = 1024


def textured_ground(tiles: GroundTiles, painted: PaintedGround, record: dict, folder,
                    crs) -> TexturedGround:  # fmt: skip
    """The textured ground mesh and the ground's heights, a tile at a time: in memory
    with one tile or without a ``folder``, else on disk in ``folder``. A tile's mesh
    reaches the first texel row and column of the tiles east and south of it, where
    their meshes start, so that the pieces meet."""
    grid = tiles.grid
    f = max(1, -(-max(grid.shape) // PREVIEW_TEXELS))  # the preview's every f-th texel
    if len(tiles.tiles) == 1:
        whole = (slice(0, grid.height), slice(0, grid.width))
        z, image = tiles.read(HEIGHTS, *whole), painted.read(*whole)
        s = ground_surface(GroundTexture(grid, z, image))
        return TexturedGround(grid, s, z, None, image[::f, ::f], record)
    pieces = TexturedPieces(folder)
    mosaic = np.zeros((-(-grid.height // f), -(-grid.width // f), 3), np.uint8)
    dtm, dtm_file = None, None
    if folder is None:
        dtm = np.empty(grid.shape, np.float32)
    else:
        dtm_file = Path(folder) / "dtm.tif"
        raster = WindowedRaster(dtm_file, grid, crs, np.float32)
    for rows, cols in tiles.tiles:
        outer = (slice(rows.start, min(rows.stop + 1, grid.height)),
                 slice(cols.start, min(cols.stop + 1, grid.width)))  # fmt: skip
        z, image = tiles.read(HEIGHTS, *outer), painted.read(*outer)
        s = ground_surface(GroundTexture(grid.window(*outer), z, image))
        if s is not None:
            pieces.add(s)
        h, w = rows.stop - rows.start, cols.stop - cols.start
        if dtm is not None:
            dtm[rows, cols] = z[:h, :w]
        else:
            raster.write(z[:h, :w].astype(np.float32), rows, cols)
        inside, at = decimated_cells(rows, cols, f, (rows.start, cols.start))
        mosaic[at] = image[inside]
    if dtm is None:
        raster.close()
    return TexturedGround(grid, pieces, dtm, dtm_file, mosaic, record)


def ring_window(grid: Grid, outline: tuple, ring_m: float) -> tuple[slice, slice] | None:
    """Rows and columns of ``grid`` around a building's outline (its bounds: xmin, ymin,
    xmax, ymax), with the ring and a texel to spare (None if it lies off the grid): every
    texel of its ring, and every footprint texel nearest to one, is inside."""
    x0, y0, x1, y1 = outline
    m = ring_m + 2 * grid.gsd
    return grid.window_of((x0 - m, y0 - m, x1 + m, y1 + m))


def ground_grid(scene: Scene, proxies: list[ProxyEntry], gsd: float) -> Grid:
    """The scene's bounds at ``gsd``, else the proxies' with 20 m around them."""
    if scene.bounds is not None:
        return Grid.from_bounds(*scene.bounds, gsd)
    boxes = np.array([e.box for e in proxies], float)
    lo, hi = boxes[:, :2].min(axis=0) - 20.0, boxes[:, 3:5].max(axis=0) + 20.0
    return Grid.from_bounds(lo[0], lo[1], hi[0], hi[1], gsd)


def ring_inputs(grid: Grid, foot: WallFoot):
    """The building's footprint on ``grid`` (a window of the ground grid), and for every
    cell the view of the nearest low wall texel (-1 where there is none)."""
    footprint = rasterio.features.geometry_mask(
        [mapping(foot.outline)], grid.shape, grid.transform, invert=True
    )
    wall_view = np.full(grid.shape, -1)
    if len(foot.xy):
        X, Y = grid.cell_centers()
        _, j = cKDTree(foot.xy).query(np.column_stack([X.ravel(), Y.ravel()]))
        wall_view = foot.views[j].reshape(grid.shape)
    return footprint, wall_view


def voxel_building(p: Proxy, t: BuildingTexture) -> Building:
    """A proxy and its texture as a building of the run: its roof model (one horizontal
    plane per roof level, LOD 1.3 in CityJSON's terms, or pitched planes, LOD 2.2) with the
    textured mesh."""
    m = p.model
    record = {k: v for k, v in p.record.items() if k not in _COMMON}
    record.update(m.record)
    record.update(t.record)
    # both stages time their steps: keep the proxy's beside the texture's
    record["times_s"] = {**p.record.get("times_s", {}), **t.record.get("times_s", {})}
    mesh = Surface(p.vertices, p.triangles, vertex_colours(p.vertices, t), Texture(t.image, t.uvs))
    return replace(m, id=p.id, mesh=mesh, lod="2.2" if p.roof.pitched else "1.3",
                   watertight=None, record=record)  # fmt: skip


def vertex_colours(vertices: np.ndarray, tex: BuildingTexture) -> np.ndarray:
    """Each mesh vertex takes the median colour of the texels within a voxel of it."""
    g = tex.graph
    colours = tex.colours()
    seen = tex.stitched.labels >= 0
    out = np.full((len(vertices), 3), 128, np.uint8)
    if not seen.any():
        return out
    tree = cKDTree(g.positions[seen])
    near = tree.query_ball_point(vertices, r=4 * g.texel_m)
    for i, idx in enumerate(near):  # a few dozen mesh corners per building
        if idx:
            out[i] = np.median(colours[seen][idx], axis=0)
    return out


def ground_surface(ground: GroundTexture) -> Surface | None:
    """The textured ground mesh, coloured by its texture at the vertices (None when the
    grid is too small)."""
    gm = ground_mesh(ground)
    if gm is None:
        return None
    gv, gt, guv = gm
    r, c = ground.grid.cell_index(gv[:, 0], gv[:, 1], clip=True)
    return Surface(gv, gt, ground.image[r, c], Texture(ground.image, guv))


SEAM_COSTS = ("seam_cost", "seam_cost_projective", "seam_cost_greedy")


def texture_summary(records: list[dict]) -> dict:
    """Mean seam costs over the buildings' records (graph cut, projective, greedy before
    the refinement)."""
    out = {}
    for key in SEAM_COSTS:
        vals = [r[key] for r in records if np.isfinite(r[key])]
        out[key] = round(float(np.mean(vals)), 4) if vals else None
    return out


def summary_lines(record: dict, buildings=()) -> list[str]:
    """What ``workbench model voxel`` prints beside the counts."""
    c, t = record["counts"], record["texture"]
    lines = [
        f"  {c['footprints']} footprints ({c['skipped']} skipped), "
        f"{record['seconds_per_building']:.2f} s per building"
    ]
    if t.get("seam_cost") is not None:
        lines.append(
            f"  seam cost {t['seam_cost']:.2f} (graph cut) vs "
            f"{t['seam_cost_projective']:.2f} (projective)"
        )
    return lines
