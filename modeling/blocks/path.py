"""The block path end to end: a fusion run in, a :class:`ModelRun` out.

The steps of the DEM-blocks paper, each in the module named after it:
:mod:`.supports` (section 2), :mod:`.library` (3.1), :mod:`.energy` (3.2, eq. 1-5),
:mod:`.rjmcmc` (3.3, eq. 6 and the annealing), :mod:`.block_meshes` (the meshes). This
module reads, runs a task per building (:func:`building_task`) and times them.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio.features
import shapely
from scipy import ndimage as ndi
from shapely.geometry import Polygon, mapping
from shapely.ops import unary_union

from modeling.shared.footprint_priors import crowns_over_the_edge, rasterize_on
from modeling.shared.in_blocks import (
    BlockRasters,
    SegmentClaims,
    block_engine,
    blocks_lines,
    blocks_record,
    each_block,
    kept_buildings,
    plan_blocks,
)
from modeling.shared.opened_parts import (
    building_segments,
    mid_wall_region,
    unseen_at_level,
    unseen_rim_filled,
)
from modeling.shared.raster_ground import vertex_colours
from modeling.shared.roof_envelope import BuildingMesh, RoofFace, building_solid, face_planes
from modeling.shared.roof_model import closed_roof_model
from workbench.engine import BUILDINGS_IN_FLIGHT, Engine, ThreadEngine
from workbench.errors import InputError
from workbench.fusion_run import (
    building_cells,
    checked_fusion_run,
    class_map,
    hidden_ceiling,
    read_fusion_run,
    tree_cells,
)
from workbench.grid_blocks import Block as GridBlock
from workbench.meshes import is_watertight
from workbench.model_run import Building, ModelRun, Surface
from workbench.raster import Grid
from workbench.records import StageTimer, run_speed

from .block_meshes import block_faces
from .energy import STEP_M
from .library import RIDGED, Block, block_heights
from .options import BlocksOptions
from .preview import blocks_preview
from .rjmcmc import Pair, SupportData, anneal
from .supports import (
    Support,
    automatic_supports,
    carried_polygon,
    gap_supports,
    junction_sides,
    junction_strips,
    neighbour_pairs,
    support_cells,
    supports_from_file,
)

FUSION_RASTERS = ("ortho", "dsm", "dtm", "class_prob")
_MIN_CELLS = 10  # a support with fewer cells of DSM carries no block
_OVERLAP_M = 0.02
_MESH_FRAMES = 3  # frames tried for the envelope before the supports are grown
#: the truth's roof types of the library's forms (the rest are their own)
_ROOF_TYPE = {"half-hipped": "hipped", "gambrel": "mansard"}


@dataclass
class BlocksInputs:
    """What every building's task reads."""

    grid: Grid
    dsm: np.ndarray  # (H, W) metres, NaN unknown: the fusion's whole DSM
    dtm: np.ndarray
    # (H, W) bool, the cells the fusion classes tree rather than building (None: no
    # crowns): out of the likelihood, not of the outline (a roof's steep slopes can be)
    crowns: np.ndarray | None
    boxes: np.ndarray  # (q + 1, 4) r0, r1, c0, c1 of each building with a margin
    segments: np.ndarray | None = None  # (H, W) int: the buildings (automatic supports)
    given: list = field(default_factory=list)  # per building its supports from a file
    # (H, W) metres over the cells no view saw (fusion.hidden_ceiling), None without one
    ceiling: np.ndarray | None = None


@dataclass
class BuildingResult:
    """A task's answer: the building or why it was skipped, and what the preview draws."""

    key: int
    building: Building | None = None
    skipped: str | None = None
    supports: list = field(default_factory=list)  # GeoJSON-like polygons
    forms: list = field(default_factory=list)
    trace: list = field(default_factory=list)


def run_blocks(
    fusion_dir: Path,
    options: BlocksOptions | None = None,
    *,
    supports: Path | None = None,
    engine: Engine | None = None,
) -> ModelRun:
    """The DEM-blocks path on the DSM of ``workbench fusion``.

    Parameters
    ----------
    fusion_dir : path
        A fusion run folder (ortho, dsm, dtm, class_prob; its class.tif, when it has
        one, says where crowns are), from images or points.
    options : BlocksOptions
        With ``block_m``, the grid is modelled block by block (:func:`model_block`).
    supports : path, optional
        2D supports (convex quadrilaterals or triangles, any vector file GDAL reads);
        default: extracted from the DSM and the building class.
    engine : Engine, optional
        Runs the buildings' tasks (default: this process, one after another).
    """
    options = options or BlocksOptions()
    engine = engine or ThreadEngine(1)
    timer = StageTimer()
    t_start = time.perf_counter()
    plan = plan_blocks(fusion_dir, options.block_m, options.block_margin_m, engine)
    grid, blocks, claims, rasters = plan.grid, plan.blocks, plan.claims, plan.rasters
    results, wide, crs, iterations, warm_s = [], 0, None, 0, 0.0
    for b in each_block(blocks):
        found, cut, crs = model_block(fusion_dir, b, claims, rasters, options, supports,
                                      block_engine(engine, blocks, b), timer)  # fmt: skip
        iterations += sum(x.building.record["iterations"] for x in found if x.building)
        warm_s += sum(x.building.record["annealing_seconds"]
                      - x.building.record["zero_temperature"]["seconds"]
                      for x in found if x.building)  # fmt: skip
        plan.keep_buildings(kept_buildings(found))
        results += found
        wide += cut
    if not claims.count and supports is None:
        raise InputError(Path(fusion_dir) / "class_prob.tif", None, "no building cells of "
                         "at least --min-area: nothing to model")  # fmt: skip
    buildings = plan.buildings
    skipped = [{"building": str(x.key), "reason": x.skipped} for x in results if x.skipped]
    with timer.stage("preview"):
        layers, on = rasters.preview_layers()
        rgb = layers["rgb"]
        preview = blocks_preview(rgb, on, results, buildings)
    seconds = time.perf_counter() - t_start
    record = {"supports_from": "file" if supports is not None else
              "automatic (footprint priors of the height regions)"}  # fmt: skip
    if len(blocks) > 1:
        record["blocks"] = blocks_record(blocks, plan.side_m, options.block_margin_m, wide)
    return ModelRun(
        "blocks", options, buildings, crs=crs, grid=grid, **rasters.model_rasters(),
        ground=rasters.ground(), preview=preview, stages=timer.stages,
        inputs={"fusion": str(Path(fusion_dir).absolute()),
                "supports": str(Path(supports).absolute()) if supports else None,
                "grid": {"width": grid.width, "height": grid.height, "gsd": grid.gsd}},
        counts={"candidates": claims.count, "skipped": len(skipped)},
        record={
            **record,
            "skipped": skipped,
            **engine.describe(),
            # the annealing's own, not its end at zero temperature
            "iterations_per_second": round(iterations / max(warm_s, 1e-9), 1),
            **run_speed(seconds, len(buildings), grid.width * grid.height),
        },
    )  # fmt: skip


def model_block(
    fusion_dir: Path,
    block: GridBlock,
    claims: SegmentClaims,
    rasters: BlockRasters,
    options: BlocksOptions,
    supports: Path | None,
    engine: Engine,
    timer: StageTimer,
) -> tuple[list[BuildingResult], int, object]:
    """The supports over the outer cells of ``block`` and a task for each building
    ``claims`` gives it (every one when the block is the whole grid); the rasters the
    run writes put into ``rasters``. Returns the tasks' answers (numbered on the whole
    grid), how many buildings wider than the margin it modelled from the part it holds,
    and the rasters' CRS."""
    with timer.stage("read"):
        fusion = read_fusion_run(fusion_dir, FUSION_RASTERS, block.outer)
        grid = fusion.grid
        dsm, dtm, rgb = fusion.band("dsm"), fusion.band("dtm"), fusion.rgb
        prob = np.nan_to_num(fusion.rasters["class_prob"].astype(np.float64))
        # crowns are no roof: left out of every likelihood (the class map's where the run
        # has one: the probabilities cell by cell leave a crown over a roof ragged)
        crowns = classes = None
        if not options.all_building:
            classes = class_map(fusion_dir, grid, block.outer)
            crowns = tree_cells(classes, prob)
    with timer.stage("supports"):
        if supports is not None:
            inputs = _given_supports(supports, fusion, grid, dsm, dtm, crowns, claims.grid)
            segments = _group_cells(inputs.given, grid)
        else:
            # the cells the fusion calls building: its class map's, as for the crowns
            mask = np.isfinite(dsm)
            if not options.all_building:
                mask &= building_cells(classes, prob)
            opening = 0.0 if options.all_building else options.opening_m
            segments = building_segments(mask, grid.gsd, opening, options.min_area_m2)
            margin = int(np.ceil(options.outline_reach_m / grid.gsd)) + 4
            ceiling = None if options.all_building else hidden_ceiling(fusion_dir, grid,
                                                                       block.outer)  # fmt: skip
            inputs = BlocksInputs(grid, dsm, dtm, crowns, _boxes(segments, margin), segments,
                                  ceiling=ceiling)  # fmt: skip
        q = len(inputs.boxes) - 1
        todo, wide = claims.segments_to_model(block, segments, q, inputs.boxes, last=True)
    with timer.stage("blocks"):
        shared = engine.share(inputs)
        results = list(engine.map(
            building_task, todo, shared, options, stage="buildings", keys=[str(k) for k in todo],
            in_flight=BUILDINGS_IN_FLIGHT * engine.workers,
            on_failure=lambda k, why: BuildingResult(k, skipped=why),
        ))  # fmt: skip
    number = claims.claim(block, segments, q, todo)
    for x in results:  # numbered on the whole grid
        x.key = int(number[x.key])
        if x.building is not None:
            x.building.id = str(x.key)
            x.building.mesh.vertex_colors = vertex_colours(x.building.mesh.vertices, rgb, grid)
    rasters.put(block, grid, dtm=dtm, rgb=rgb, dsm=dsm)
    return results, wide, fusion.crs


def check_inputs(fusion_dir: Path, options: BlocksOptions, supports: Path | None = None) -> None:
    """Read what :func:`run_blocks` refuses, before a command starts its workers: the
    fusion run's rasters and the supports' file (one line, with no worker's shutdown
    noise after it)."""
    fusion = checked_fusion_run(fusion_dir, FUSION_RASTERS, classes=not options.all_building)
    if supports is not None:
        _given_supports(supports, fusion, fusion.grid, None, None, None)


def _group_cells(groups: list, grid: Grid) -> np.ndarray:
    """(H, W) int32 each group of supports' cells on ``grid``, numbered from 1."""
    shapes = [(unary_union([s.polygon for s in g]), k) for k, g in enumerate(groups, start=1)]
    if not shapes:
        return np.zeros(grid.shape, np.int32)
    return rasterio.features.rasterize(shapes, out_shape=grid.shape, transform=grid.transform,
                                       fill=0, dtype=np.int32)  # fmt: skip


def _boxes(segments: np.ndarray, margin: int) -> np.ndarray:
    """(q + 1, 4) r0, r1, c0, c1 of each segment grown by ``margin`` cells (row 0
    unused)."""
    q = int(segments.max())
    out = np.zeros((q + 1, 4), np.int64)
    H, W = segments.shape
    for k, sl in enumerate(ndi.find_objects(segments), start=1):
        if sl is not None:
            out[k] = [max(sl[0].start - margin, 0), min(sl[0].stop + margin, H),
                      max(sl[1].start - margin, 0), min(sl[1].stop + margin, W)]  # fmt: skip
    return out


def _given_supports(
    path: Path, fusion, grid: Grid, dsm, dtm, crowns, whole: Grid | None = None
) -> BlocksInputs:
    """The supports of a vector file that reach ``grid`` (a block of the ``whole`` grid,
    by default the whole grid itself) grouped into buildings, with their boxes."""
    from workbench.footprints import read_footprints

    items = read_footprints(path, crs=fusion.crs, extent=grid.bounds)
    groups = supports_from_file(path, [f.polygon for f in items], whole or grid)
    boxes = [np.zeros(4, np.int64)]
    for group in groups:
        xmin, ymin, xmax, ymax = unary_union([s.polygon for s in group]).bounds
        r0, c0 = grid.world_to_cell(np.array([xmin]), np.array([ymax]))
        r1, c1 = grid.world_to_cell(np.array([xmax]), np.array([ymin]))
        r0, r1, c0, c1 = int(r0[0]), int(r1[0]), int(c0[0]), int(c1[0])
        boxes.append(np.array([max(r0 - 4, 0), min(r1 + 5, grid.height),
                               max(c0 - 4, 0), min(c1 + 5, grid.width)]))  # fmt: skip
    return BlocksInputs(grid, dsm, dtm, crowns, np.array(boxes), None, groups)


def building_task(k: int, inputs: BlocksInputs, options: BlocksOptions) -> BuildingResult:
    """Task: the supports, the annealing of their blocks and the mesh of building ``k``."""
    t0 = time.perf_counter()
    r0, r1, c0, c1 = inputs.boxes[k]
    g = inputs.grid
    crop = g.window(slice(r0, r1), slice(c0, c1))
    whole, dtm = inputs.dsm[r0:r1, c0:c1], inputs.dtm[r0:r1, c0:c1]
    dsm = whole if inputs.crowns is None else np.where(inputs.crowns[r0:r1, c0:c1], np.nan, whole)
    seen = np.isfinite(whole)
    xs = crop.xmin + (np.arange(crop.width) + 0.5) * g.gsd
    ys = crop.ymax - (np.arange(crop.height) + 0.5) * g.gsd
    min_cells = int(np.ceil(max(options.min_part_m**2, 0.5 * options.min_area_m2) / g.gsd**2))
    unseen = np.zeros(whole.shape, bool)  # the parts no view saw the outline takes in
    if inputs.segments is not None:
        seg = inputs.segments[r0:r1, c0:c1]
        # the outline and its parts where the whole DSM's walls and steps stand: a
        # mansard's steep lower slopes, often classed tree, are the building's all the same
        if options.all_building:  # a cloud of one building: no ground to find walls against
            mask = seg == k
        else:
            reach = int(round(options.unseen_rim_m / g.gsd))
            rim_dsm, rim_dtm = unseen_rim_filled([whole, dtm], seen, reach)
            others = (seg > 0) & (seg != k)
            mask = mid_wall_region(seg == k, rim_dsm - rim_dtm, others, g.gsd,
                                   options.outline_reach_m)  # fmt: skip
            # the supports' steps on the filled heights too: a NaN reads as the lowest
            whole = rim_dsm
            region = mask & np.isfinite(whole)
            ceiling = None if inputs.ceiling is None else inputs.ceiling[r0:r1, c0:c1]
            unseen, whole = unseen_at_level(region, whole, rim_dtm, ceiling,
                                            int(round(options.outline_reach_m / g.gsd)),
                                            g.gsd)  # fmt: skip
            mask |= unseen
            if unseen.any():  # and the walls beside them: a lower tier's cells some view saw
                mask |= mid_wall_region((seg == k) | unseen, whole - rim_dtm, others, g.gsd,
                                        options.outline_reach_m)  # fmt: skip
        mask &= np.isfinite(whole)
        # the crowns over its edge hide whether the roof goes on under them
        under_crowns = None
        if inputs.crowns is not None and not options.all_building:
            crowns = inputs.crowns[r0:r1, c0:c1] & ~((seg > 0) & (seg != k))
            under_crowns = crowns_over_the_edge(mask, crowns, inputs.dsm[r0:r1, c0:c1], g.gsd)
        found = automatic_supports(mask, whole, xs, ys, crop, options.min_part_m, min_cells,
                                   options.step_m, dtm, under_crowns, unseen)  # fmt: skip
        supports, regions, off_level = found.supports, found.regions, found.off_level
        tiers = found.tiers
    else:
        supports = inputs.given[k - 1]
        mask = rasterize_on(unary_union([s.polygon for s in supports]), crop) & np.isfinite(dsm)
        regions, off_level = np.zeros(mask.shape, np.int32), np.zeros(mask.shape, bool)
        tiers = []
    # crowns are no roof: their cells stay out of the likelihood; so do the parts no view
    # saw, but for a support that is mostly such a part (a lower tier behind the upper
    # one from every view): it is fitted to the level they were given, or it had no block
    observed = np.isfinite(dsm)
    dsm = np.where(unseen, whole, dsm)
    cells = [c & unseen if (c & unseen).sum() > 0.5 * c.sum() else c & observed
             for c in support_cells(supports, mask, regions, crop)]  # fmt: skip
    # the walls blur the DSM next to them: those cells (from the known cells' edge: a
    # filled rim is no roof), and the small levels joined to a region, are left out of the
    # likelihood
    clear = ndi.distance_transform_edt(mask & ~off_level & seen) * g.gsd > options.wall_blur_m
    cells = [c & clear if (c & clear).sum() >= _MIN_CELLS else c for c in cells]
    kept = [i for i, c in enumerate(cells) if c.sum() >= _MIN_CELLS]
    if not kept:
        return BuildingResult(k, skipped="no 2D support with a DSM: the outline fits no "
                              f"rectangle of {options.min_part_m} m or more")  # fmt: skip
    supports, cells = [supports[i] for i in kept], [cells[i] for i in kept]
    ends = junction_sides(supports)
    pairs = [Pair(i, j, e) for i, j, e in neighbour_pairs(supports)]
    X, Y = np.meshgrid(xs, ys)
    data = []
    for s, c, e in zip(supports, cells, ends, strict=True):
        u, v = s.frame.to_frame(X[c], Y[c])
        data.append(SupportData(s.frame, e, u, v, dsm[c]))
    strips = junction_strips(supports, ends)
    for (i, side), (j, strip) in strips.items():
        u, v = supports[i].frame.to_frame(X[cells[j]], Y[cells[j]])
        on = np.flatnonzero((u >= strip[0]) & (u <= strip[1]) & (v >= strip[2]) & (v <= strip[3]))
        data[i].strips[side] = (j, on, u[on], v[on])
    t_anneal = time.perf_counter()
    result = anneal(data, pairs, alpha=options.alpha, beta=options.beta,
                    form_cost=options.form_cost,
                    iterations=options.iterations * len(supports),
                    seed=[options.seed, k])  # fmt: skip
    anneal_s = time.perf_counter() - t_anneal
    blocks = result.blocks
    # the lower tiers narrower than a support, each a flat block at its tier's level; the
    # gaps between the supports too narrow for one, each a flat block at the level of the
    # DSM in it: left open, each is a slot down to the ground
    gaps = list(tiers)
    if inputs.segments is not None:
        gaps += gap_supports(supports + gaps, mask, crop, options.min_part_m)
    gap_blocks = [Block("flat", 0, False, (gap.level if gap.is_tier else
                                           _gap_level(gap, whole, crop, blocks),))
                  for gap in gaps]  # fmt: skip
    all_supports, all_ends = supports + gaps, ends + [(False,) * 4] * len(gaps)
    ground = dtm[mask & np.isfinite(dtm)]
    roof_low = min(min(float(d.z.min()) for d in data), min(b.gutter for b in blocks))
    base_z = min(float(np.min(ground)) if len(ground) else roof_low - 3.0, roof_low - 0.5)
    how, meshed, faces, solid, closed = closed_solid(blocks + gap_blocks, all_supports, all_ends,
                                                     base_z, strips, crop)  # fmt: skip
    planes, areas = face_planes([f for fs in faces for f in fs])
    residual = np.concatenate([d.heights(b) - d.z for d, b in zip(data, blocks, strict=True)])
    warnings = []
    if result.adjustment_from is None:
        warnings.append(f"the annealing did not reach its adjustment stage (fewer than 5 % "
                        f"of uniform and data-driven proposals accepted) in "
                        f"{result.iterations} iterations: the blocks may be far from the "
                        "optimum; give more --iterations")  # fmt: skip
    record = {
        "supports": [
            dict(s.record(), block=b.record(), junction_sides=[bool(x) for x in e])
            for s, b, e in zip(supports, blocks, ends, strict=True)
        ]
        + [
            dict(s.record(), block=b.record(), gap=True, tier=s.is_tier)
            for s, b in zip(gaps, gap_blocks, strict=True)
        ],
        "neighbours": [[p.i, p.j] for p in pairs],
        "face_blocks": face_blocks(solid, all_supports, meshed, all_ends),
        "meshed": how,
        "energy": round(result.energy, 4),
        "likelihood": round(float(sum(result.likelihoods)), 4),
        "prior": round(result.prior, 4),
        "rms_m": round(float(np.sqrt(np.mean(residual**2))), 3),
        "iterations": result.iterations,
        "adjustment_stage_from": result.adjustment_from,
        "temperature": {"initial": round(result.t_start, 6), "final": round(result.t_end, 8)},
        "zero_temperature": {
            "evaluations": result.zero_temperature_evaluations,
            "forms_switched": result.forms_switched,
            "seconds": round(result.zero_temperature_seconds, 3),
        },
        "proposed": result.proposed,
        "accepted": result.accepted,
        "acceptance_rate": {
            k: round(result.accepted[k] / max(result.proposed[k], 1), 4) for k in result.proposed
        },  # fmt: skip
        "energy_trace": [list(t) for t in result.trace],
        "warnings": warnings,
        "annealing_seconds": round(anneal_s, 3),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    outline = unary_union([s.polygon for s in all_supports])
    building = Building(
        str(k), Surface(solid.vertices, solid.triangles),
        "1.3" if all(b.form == "flat" for b in meshed) else "2.2", footprint=outline,
        roof_type=building_roof_type(meshed, [s.polygon.area for s in all_supports]),
        planes=planes, plane_areas=areas, base_z=base_z,
        eave_z=min(b.gutter for b in blocks), ridge_z=float(solid.vertices[:, 2].max()),
        watertight=closed, record=record,
    )  # fmt: skip
    return BuildingResult(k, building, supports=[mapping(s.polygon) for s in all_supports],
                          forms=[b.form for b in blocks + gap_blocks],
                          trace=result.trace)  # fmt: skip


def _gap_level(gap: Support, dsm: np.ndarray, grid: Grid, blocks: list[Block]) -> float:
    """A gap's flat level: the median of ``dsm`` ((h, w) on ``grid``, metres) on its
    cells; where it has none, the lowest block's gutter."""
    z = dsm[rasterize_on(gap.polygon, grid) & np.isfinite(dsm)]
    return float(np.median(z)) if len(z) else min(b.gutter for b in blocks)


def closed_solid(blocks: list[Block], supports: list[Support], ends, base_z: float,
                 strips: dict | None = None, grid: Grid | None = None):  # fmt: skip
    """The building's mesh: every block's faces on its support (grown over the strips
    its ridge carries its roof on), their upper envelope down to ``base_z``
    (:func:`modeling.shared.roof_envelope.building_solid`), meshed in a support's frame,
    where its sides are axis-aligned.

    Faces that meet a hair off a common edge (supports cut from different priors or
    read from a file, a carried roof crossing a neighbour's ridge) can leave that
    envelope open. It is then meshed in the next support's frame; then without the
    carried roofs; then with every support grown by ``_OVERLAP_M``, so that neighbours
    overlap and the upper roof covers the seam. Given the building's ``grid``, the
    blocks' own faces are then meshed from the raster of their supports
    (:func:`raster_solid`, as the raster paths mesh their roofs: closed by
    construction, the roofs' planes kept, the outline in cells). Then every block flat at
    its median height (a closed LOD1 block rather than an open LOD2 shell), and those
    flat blocks from the raster. Returns how it was meshed, the blocks as meshed, the
    faces, the mesh and whether it is closed."""
    carried = []
    for i, (b, s) in enumerate(zip(blocks, supports, strict=True)):
        mine = [st for (k, side), (_, st) in (strips or {}).items()
                if k == i and b.form in RIDGED and side % 2 == b.along]  # fmt: skip
        carried.append(dataclasses.replace(s, polygon=carried_polygon(s, mine)) if mine else s)

    def attempts():  # made only when the ones before did not close
        yield "", blocks, carried, False
        yield ", roofs not carried over junctions", blocks, supports, False
        yield f", supports grown by {_OVERLAP_M} m", blocks, [
            dataclasses.replace(s, polygon=s.polygon.buffer(_OVERLAP_M, join_style="mitre"))
            for s in supports], False  # fmt: skip
        yield ", meshed from the raster of its supports", blocks, supports, True
        flat = [flat_block(b, s, e) for b, s, e in zip(blocks, supports, ends, strict=True)]
        yield ", every block flat at its median height", flat, supports, False
        yield (", every block flat at its median height, meshed from the raster of its "
               "supports", flat, supports, True)  # fmt: skip

    for note, bs, ss, from_raster in attempts():
        if from_raster and grid is None:
            continue
        faces = [block_faces(b, s, e) for b, s, e in zip(bs, ss, ends, strict=True)]
        if from_raster:
            raster = raster_solid(faces, base_z, grid)
            if raster is not None and is_watertight(raster.vertices, raster.triangles):
                return note.removeprefix(", "), bs, faces, raster, True
            continue
        for k, s in enumerate(supports[:_MESH_FRAMES]):
            solid = building_solid(faces, base_z, s.frame.theta, np.asarray(s.frame.origin))
            if is_watertight(solid.vertices, solid.triangles):
                return f"in the frame of support {k}{note}", bs, faces, solid, True
    return "not closed", blocks, faces, solid, False


def raster_solid(faces: list[list[RoofFace]], base_z: float, grid: Grid) -> BuildingMesh | None:
    """Roof faces meshed from their raster on ``grid``: a cell takes the face highest over
    its centre among those whose polygon covers it; by the mesher of the raster paths
    (:func:`modeling.shared.roof_model.closed_roof_model`, closed by construction).

    Supports of a building's tiers, each regularised to its own direction, cross at
    slivers a few centimetres wide whose envelope is no manifold (six towers of the
    1 km² city); on the cells they vanish. ``faces``: a list per block, as
    :func:`~.block_meshes.block_faces` gives them. None when no cell is covered."""
    labels = np.zeros(grid.shape, np.int64)
    top = np.full(grid.shape, -np.inf)
    X, Y = grid.cell_centers()
    planes = []
    for face in (f for fs in faces for f in fs):
        a, b, c = face.plane
        z = a * X + b * Y + c
        higher = rasterize_on(Polygon(face.xy), grid) & (z > top)
        planes.append([-a, -b, 1.0, -c])  # a x + b y + c z + d = 0
        labels[higher], top[higher] = len(planes), z[higher]
    if not labels.any():
        return None
    model = closed_roof_model(labels, grid, np.array(planes), base_z, grid.gsd)
    if model is None:
        return None
    V, T = model.mesh.vertices, model.mesh.triangles
    n = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    nz = n[:, 2] / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    part = np.where(nz > 0.5, 0, np.where(nz < -0.5, 2, 1)).astype(np.uint8)
    return BuildingMesh(V, T, part, np.zeros((len(T), 2)))


def flat_block(block: Block, support: Support, ends) -> Block:
    """The block flat at the median of its roof's heights over a 20 x 20 lattice of its
    support's rectangle."""
    u0, u1, v0, v1 = support.frame.rect
    t = (np.arange(20) + 0.5) / 20
    U, V = np.meshgrid(u0 + t * (u1 - u0), v0 + t * (v1 - v0))
    z = block_heights(block, U.ravel(), V.ravel(), support.frame, ends)
    return Block("flat", 0, False, (float(np.median(z)),))


def face_blocks(solid, supports: list[Support], blocks: list[Block], ends) -> list[int]:
    """Per triangle of the mesh, the index of the block whose roof it is (-1: a wall or
    the floor): the support under its centre whose block's height there is closest."""
    V, T = solid.vertices, solid.triangles
    centre = V[T].mean(axis=1)
    out = np.full(len(T), -1)
    roof = np.flatnonzero(solid.part == 0)
    best = np.full(len(roof), np.inf)
    x, y, z = centre[roof, 0], centre[roof, 1], centre[roof, 2]
    for i, (s, b, e) in enumerate(zip(supports, blocks, ends, strict=True)):
        inside = shapely.contains_xy(s.polygon.buffer(1e-3), x, y)
        if not inside.any():
            continue
        u, v = s.frame.to_frame(x[inside], y[inside])
        d = np.abs(block_heights(b, u, v, s.frame, e) - z[inside])
        idx = np.flatnonzero(inside)
        better = d < best[idx]
        best[idx[better]] = d[better]
        out[roof[idx[better]]] = i
    return out.tolist()


def building_roof_type(blocks: list[Block], areas: list[float]) -> str:
    """One label per building, as the truth has: multi-level when its blocks are flat at
    more than one level (a step of more than :data:`STEP_M`), else the roof type of the
    forms covering the most area (half-hipped counted hipped, gambrel mansard)."""
    if all(b.form == "flat" for b in blocks):
        levels = [b.gutter for b in blocks]
        return "multi-level" if max(levels) - min(levels) > STEP_M else "flat"
    votes: dict[str, float] = {}
    for b, a in zip(blocks, areas, strict=True):
        if b.form == "flat" and len(blocks) > 1:
            continue  # a flat wing beside pitched ones: the pitched roof names the building
        t = _ROOF_TYPE.get(b.form, b.form)
        votes[t] = votes.get(t, 0.0) + a
    return max(votes, key=votes.get)


def summary_lines(record: dict, buildings=()) -> list[str]:
    """What ``workbench model blocks`` prints beside the counts (``buildings``: model.json's
    building records, read once)."""
    forms: dict[str, int] = {}
    warned = switched = gaps = tiers = 0
    for b in buildings:
        for s in b["supports"]:
            if s.get("tier"):
                tiers += 1
            elif s.get("gap"):
                gaps += 1
            else:
                forms[s["block"]["form"]] = forms.get(s["block"]["form"], 0) + 1
        warned += bool(b["warnings"])
        switched += b["zero_temperature"]["forms_switched"]
    return [
        f"  supports: {record['supports_from']}; {sum(forms.values())} blocks, "
        f"{record['iterations_per_second']:.0f} iterations/s, "
        f"{record['seconds_per_building']} s per building",
        "  blocks: " + ", ".join(f"{k} {v}" for k, v in sorted(forms.items()))
        + f" ({switched} changed form at zero temperature); flat: {tiers} lower tiers and "
        f"{gaps} gaps between supports too narrow for a support",
        *([f"  {warned} buildings did not converge (see warnings in model.json)"]
          if warned else []),
        *blocks_lines(record.get("blocks")),
    ]  # fmt: skip
