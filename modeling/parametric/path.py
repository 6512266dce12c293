"""The parametric path end to end: a fusion run in, a :class:`ModelRun` out.

The steps of the variational paper, each in the module named after it:
:mod:`.segmentation` (eq. 1 and 8), :mod:`modeling.shared.footprint_priors` (eq. 2-4,
shared with the block path's supports),
:mod:`.roof_geometry` (eq. 5, 6, 11, 12), :mod:`.part_meshes` (the meshes). This module
reads, runs a task per segment (:func:`building_task`) and times them.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio.features
import shapely
from scipy import ndimage
from shapely.geometry import mapping, shape
from shapely.ops import unary_union

from modeling.shared.footprint_priors import (
    Prior,
    compete_priors,
    crowns_over_the_edge,
    decompose_outline,
    label_count,
    rasterize_on,
    segment_frame,
    union_outline,
)
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
    opened_parts,
    unseen_at_level,
    unseen_rim_filled,
)
from modeling.shared.raster_ground import vertex_colours
from modeling.shared.roof_envelope import building_solid, face_planes
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
from workbench.grid_blocks import Block
from workbench.meshes import is_watertight
from workbench.model_run import Building, ModelRun, Surface
from workbench.raster import BUILDING, Grid
from workbench.records import StageTimer, run_speed

from .options import ParametricOptions
from .part_meshes import wing_faces
from .preview import parametric_preview
from .roof_geometry import (
    RoofFit,
    exact_heights,
    fit_roof,
    flat_fit,
    robust_cost,
    roof_type,
    side_distances,
    wing_samples,
)
from .segmentation import heaviside, level_set_segmentation, signed_distance

log = logging.getLogger(__name__)

FUSION_RASTERS = ("ortho", "dsm", "dtm", "class_prob")
_MAX_PARTS = 4  # priors per segment: the first and the parts its labelling leaves
_MAX_TIERS = 3  # tiers stacked on a building (a multi-level building's levels)
_TIER_RMS = 3.0  # a tier's roof fit leaves at most this many robust scales of RMS
_MESHED = (
    "as fitted",
    "planes on the wings' sides",
    "flat wings (the planes' mesh was not closed)",
)
_LOGIT_CLIP = 0.01  # the building probability's source is its log-odds, clipped here


@dataclass
class ParametricInputs:
    """What every segment's task reads: the rasters on the fusion's grid, the segments."""

    grid: Grid
    dsm: np.ndarray
    dtm: np.ndarray
    rgb: np.ndarray
    segments: np.ndarray
    boxes: np.ndarray  # (q + 1, 4) r0, r1, c0, c1 of each segment with its margin
    # (H, W) bool: the cells the fusion calls tree (:func:`~workbench.fusion_run.tree_cells`:
    # its class map's, the Potts model's answer, which the probabilities cell by cell are
    # not); None: every segment is a building (--all-building)
    tree: np.ndarray | None = None
    # (H, W) bool: the cells the fusion calls building (None with --all-building)
    building: np.ndarray | None = None
    # (H, W) metres over the cells no view saw (fusion.hidden_ceiling), None without one
    ceiling: np.ndarray | None = None


@dataclass
class Wing:
    """A rectangle of a part, in its prior's frame, with its fitted roof."""

    rect: np.ndarray
    fit: RoofFit
    roof_type: str
    tier: bool = False
    hidden: tuple = (False, False, False, False)  # sides under the building's other wings

    def record(self) -> dict:
        return {
            "rect_m": [round(float(v), 3) for v in self.rect],
            "h_main_z": round(self.fit.z_main, 3),
            "omega_deg": [round(float(v), 2) for v in np.degrees(self.fit.omega)],
            "cap_m": None if self.fit.cap is None else round(self.fit.cap, 3),
            "offset_m": [round(float(v), 3) for v in self.fit.offset],
            "roof_type": self.roof_type,
            "rms_m": round(self.fit.rms, 3),
            "energy_3d": round(self.fit.cost, 5),
            "evaluations": self.fit.evaluations,
            "tier": self.tier,
            "hidden_sides": [bool(h) for h in self.hidden],
        }


@dataclass
class SegmentResult:
    """A task's answer: the building, or why the segment was skipped; the priors' outlines
    for the preview and the next round's pull (eq. 8)."""

    segment: int
    building: Building | None = None
    skipped: str | None = None
    outlines: list = field(default_factory=list)


def run_parametric(
    fusion_dir: Path,
    options: ParametricOptions | None = None,
    *,
    footprints: Path | None = None,
    engine: Engine | None = None,
) -> ModelRun:
    """The parametric path (Karantzas & Paragios) on the rasters of ``workbench fusion``.

    Parameters
    ----------
    fusion_dir : path
        A fusion run folder (ortho, dsm, dtm, class_prob).
    options : ParametricOptions
        With ``block_m``, the grid is modelled block by block (:func:`model_block`).
    footprints : path, optional
        Building outlines (GeoJSON or any vector file GDAL reads) that initialise the
        level set instead of the fusion's building probability.
    engine : Engine, optional
        Runs the segments' tasks (default: this process, one after another).
    """
    options = options or ParametricOptions()
    engine = engine or ThreadEngine(1)
    timer = StageTimer()
    t_start = time.perf_counter()
    plan = plan_blocks(fusion_dir, options.block_m, options.block_margin_m, engine)
    grid, blocks, claims, rasters = plan.grid, plan.blocks, plan.claims, plan.rasters
    done: list[BlockModel] = []
    for b in each_block(blocks):
        on = block_engine(engine, blocks, b)
        done.append(model_block(fusion_dir, b, claims, rasters, options, footprints, on, timer))
        plan.keep_buildings(kept_buildings(done[-1].results))
    results = [x for d in done for x in d.results]
    buildings = plan.buildings
    skipped = [{"segment": x.segment, "reason": x.skipped} for x in results if x.skipped]
    with timer.stage("preview"):
        outlines = [o for x in results for o in x.outlines]
        layers, on = rasters.preview_layers()
        rgb, mask = layers["rgb"], layers.get("mask")
        preview = parametric_preview(rgb, on, mask, outlines, buildings,
                                     [o for d in done for o in d.skipped_outlines])  # fmt: skip
    seconds = time.perf_counter() - t_start
    rounds = done[0].rounds if len(done) == 1 else summed_rounds([d.rounds for d in done])
    segmentation = {"initialised_from": done[0].init_source, "rounds": rounds}
    if len(blocks) > 1:
        segmentation["blocks"] = blocks_record(blocks, plan.side_m, options.block_margin_m,
                                               sum(d.cut for d in done))  # fmt: skip
    return ModelRun(
        "parametric", options, buildings, crs=done[0].crs, grid=grid,
        **rasters.model_rasters(claims), ground=rasters.ground(), preview=preview,
        stages=timer.stages,
        inputs={"fusion": str(Path(fusion_dir).absolute()),
                "footprints": str(Path(footprints).absolute()) if footprints else None,
                "grid": {"width": grid.width, "height": grid.height, "gsd": grid.gsd}},
        counts={"segments": claims.count, "skipped": len(skipped)},
        record={
            "segmentation": segmentation,
            "skipped": skipped,
            **engine.describe(),
            **run_speed(seconds, len(buildings), grid.width * grid.height),
        },
    )  # fmt: skip


@dataclass
class BlockModel:
    """What :func:`model_block` gives beside its rasters: the results of the segments the
    block models (numbered on the whole grid), how its rounds went, its CRS, how many of
    its segments wider than the margin it modelled from the part it holds, and the
    outlines of those left to the data term (for the preview)."""

    results: list
    rounds: list
    init_source: str
    crs: object
    cut: int
    skipped_outlines: list


def model_block(
    fusion_dir: Path,
    block: Block,
    claims: SegmentClaims,
    rasters: BlockRasters,
    options: ParametricOptions,
    footprints: Path | None,
    engine: Engine,
    timer: StageTimer,
) -> BlockModel:
    """Eq. 1-8 over the outer cells of ``block``: its rasters read, the level set's rounds,
    and each segment's task, for the segments ``claims`` gives it in the last round
    (every one when the block is the whole grid); the rasters the run writes put into
    ``rasters``."""
    with timer.stage("read"):
        fusion = read_fusion_run(fusion_dir, FUSION_RASTERS, block.outer)
        grid = fusion.grid
        dsm, dtm, rgb = fusion.band("dsm"), fusion.band("dtm"), fusion.rgb
        if options.all_building:
            init, init_source = np.isfinite(dsm), "every cell with a height (--all-building)"
        else:
            init, init_source = initial_region(fusion, footprints, claims.whole)
        sources = region_sources(fusion, options)
        prob = fusion.rasters["class_prob"]
        tree = building = ceiling = None
        if not options.all_building:
            classes = class_map(fusion_dir, grid, block.outer)
            tree, building = tree_cells(classes, prob), building_cells(classes, prob)
            ceiling = hidden_ceiling(fusion_dir, grid, block.outer)
    pull = None
    results: list[SegmentResult] = []
    rounds = []
    n_rounds = 1 if options.all_building else options.rounds
    for r in range(n_rounds):
        with timer.stage("segmentation" if r == 0 else f"segmentation_{r + 1}"):
            prior, weight = pull if pull is not None else (None, 0.0)
            if options.all_building:
                mask, opening = init, 0.0
            else:
                mask = level_set_segmentation(
                    sources, init, length_weight=options.length_weight,
                    iterations=options.level_set_iterations, prior=prior, prior_weight=weight,
                )  # fmt: skip
                opening = options.opening_m
            segments = building_segments(mask, grid.gsd, opening, options.min_area_m2)
            q = int(segments.max())
            boxes = segment_boxes(segments, q)
            last = r + 1 == n_rounds
            todo, cut = claims.segments_to_model(block, segments, q, boxes, last)
            inputs = ParametricInputs(grid, dsm, dtm, rgb, segments, boxes, tree, building,
                                      ceiling)  # fmt: skip
        with timer.stage("priors_and_roofs" if r == 0 else f"priors_and_roofs_{r + 1}"):
            shared = engine.share(inputs)
            results = list(engine.map(
                building_task, todo, shared, options, stage=f"segments_{r + 1}",
                keys=[str(i) for i in todo], in_flight=BUILDINGS_IN_FLIGHT * engine.workers,
                on_failure=lambda i, why: SegmentResult(i, skipped=why),
            ))  # fmt: skip
        k, nu = label_count(q)
        rounds.append({"segments": len(todo), "labels_k": k, "regions_nu": nu,
                       "buildings": sum(x.building is not None for x in results)})  # fmt: skip
        if not last:
            pull = prior_pull(results, grid, options)
            init = mask
    for x in results:
        if x.building is not None:
            x.building.mesh.vertex_colors = vertex_colours(x.building.mesh.vertices, rgb, grid)
    skipped = skipped_outlines(results, segments, grid)
    number = claims.claim(block, segments, q, todo)
    for x in results:  # numbered on the whole grid
        x.segment = int(number[x.segment])
        if x.building is not None:
            x.building.id = str(x.segment)
    rasters.put(block, grid, dtm=dtm, rgb=rgb, mask=mask, dsm=dsm)
    return BlockModel(results, rounds, init_source, fusion.crs, cut, skipped)


def summed_rounds(per_block: list[list[dict]]) -> list[dict]:
    """The blocks' rounds as one: segments and buildings summed, the largest labelling."""
    return [
        {"segments": sum(r["segments"] for r in rs), "labels_k": max(r["labels_k"] for r in rs),
         "regions_nu": max(r["regions_nu"] for r in rs),
         "buildings": sum(r["buildings"] for r in rs)}
        for rs in zip(*per_block, strict=True)
    ]  # fmt: skip


def check_inputs(
    fusion_dir: Path, options: ParametricOptions, footprints: Path | None = None
) -> None:
    """Read what :func:`run_parametric` refuses, before a command starts its workers: the
    fusion run's rasters and the footprints (one line, with no worker's shutdown noise
    after it)."""
    fusion = checked_fusion_run(fusion_dir, FUSION_RASTERS, classes=not options.all_building)
    if footprints is not None and not options.all_building:
        initial_region(fusion, footprints)


def initial_region(
    fusion, footprints: Path | None, required: bool = True
) -> tuple[np.ndarray, str]:
    """(H, W) bool initial object region: the footprints rasterised, or the cells whose
    fused building probability exceeds one half. ``required``: footprints that cover no
    cell are an error (a block of the grid may have none)."""
    grid = fusion.grid
    if footprints is None:
        p = np.nan_to_num(fusion.rasters["class_prob"][BUILDING - 1].astype(np.float64))
        return p > 0.5, "building probability"
    from workbench.footprints import read_footprints

    items = read_footprints(footprints, crs=fusion.crs, extent=grid.bounds)
    shapes = [(f.polygon, 1) for f in items]
    mask = rasterio.features.rasterize(shapes, out_shape=grid.shape, transform=grid.transform,
                                       fill=0, dtype=np.uint8)  # fmt: skip
    if required and not mask.any():
        raise InputError(footprints, None, "no footprint covers a cell of the fusion's grid")
    return mask.astype(bool), "footprints"


def region_sources(fusion, options: ParametricOptions) -> list:
    """Eq. 1's sources with their weights: the ortho's colour (weight 1), the nDSM's
    height (varrho), the building probability's log-odds (a third source). The height
    reads the unknown cells within ``options.unseen_rim_m`` of a known one at its
    height (:func:`~modeling.shared.opened_parts.unseen_rim_filled`): a roof's rim that
    no view kept is then the roof's, and its segment reaches the wall (dev fusions of
    seeds 0-2: height RMSE off the jumps 2.31, 3.49, 1.35 to 1.53, 3.46, 1.35 m)."""
    rgb = fusion.rgb.astype(np.float64)
    rgb /= 255.0  # in place: a city's RGB in float64 is 150 MiB
    dsm, dtm = fusion.band("dsm"), fusion.band("dtm")
    reach = int(round(options.unseen_rim_m / fusion.grid.gsd))
    dsm, dtm = unseen_rim_filled([dsm, dtm], np.isfinite(dsm), reach)
    ndsm = dsm - dtm
    prob = fusion.rasters["class_prob"]  # confidences are not negative: a sum > 0 is any > 0
    seen = np.isfinite(prob).all(axis=0) & (prob > 0).any(axis=0)
    p = np.clip(np.nan_to_num(prob[BUILDING - 1].astype(np.float64)), _LOGIT_CLIP, 1 - _LOGIT_CLIP)
    return [
        (rgb, rgb.sum(axis=-1) > 0, 1.0),
        (ndsm[..., None], np.isfinite(ndsm), options.height_weight),
        (np.log(p / (1 - p))[..., None], seen, options.probability_weight),
    ]


def segment_boxes(segments: np.ndarray, q: int) -> np.ndarray:
    """(q + 1, 4) row and column bounds of each segment, grown by a quarter of its size
    and 8 cells (eq. 4's domain; row 0 unused)."""
    H, W = segments.shape
    out = np.zeros((q + 1, 4), np.int64)
    rows, cols = np.nonzero(segments)
    ids = segments[rows, cols]
    for k in range(1, q + 1):
        out[k] = grown_box(rows[ids == k], cols[ids == k], (H, W))
    return out


def grown_box(rr: np.ndarray, cc: np.ndarray, shape: tuple) -> list[int]:
    """r0, r1, c0, c1 of the cells (rr, cc) grown by a quarter of their size and 8 cells
    (eq. 4's domain: the unknown label's cost is a share of it), within ``shape``."""
    mr = int(0.25 * (rr.max() - rr.min())) + 8
    mc = int(0.25 * (cc.max() - cc.min())) + 8
    return [max(rr.min() - mr, 0), min(rr.max() + mr + 1, shape[0]),
            max(cc.min() - mc, 0), min(cc.max() + mc + 1, shape[1])]  # fmt: skip


def building_task(k: int, inputs: ParametricInputs, options: ParametricOptions) -> SegmentResult:
    """Task: eq. 2-6 and the mesh for segment ``k``."""
    t0 = time.perf_counter()
    r0, r1, c0, c1 = inputs.boxes[k]
    g = inputs.grid
    crop = g.window(slice(r0, r1), slice(c0, c1))
    mask = inputs.segments[r0:r1, c0:c1] == k
    dsm, dtm = inputs.dsm[r0:r1, c0:c1], inputs.dtm[r0:r1, c0:c1]
    xs = crop.xmin + (np.arange(crop.width) + 0.5) * g.gsd
    ys = crop.ymax - (np.arange(crop.height) + 0.5) * g.gsd
    min_cells = int(np.ceil(max(options.min_part_m**2, 0.5 * options.min_area_m2) / g.gsd**2))
    # a segment of --all-building is a building: no unknown-object label for it
    lambda_ = np.inf if options.all_building else options.lambda_
    crowns = np.zeros(mask.shape, bool)
    found = overruled = None
    if inputs.tree is not None:
        tree = inputs.tree[r0:r1, c0:c1]
        if _classed(mask, tree):  # eq. 4's unknown label, on the classes
            # unless its roof is planar: then the classes took a roof for a tree by its
            # colour (a green roof), and say nothing of crowns on it either
            found, overruled = planar_roof(mask, dsm, dtm, xs, ys, crop, options, min_cells,
                                           lambda_)  # fmt: skip
            if found is None:
                return SegmentResult(k, skipped="a tree: the fusion classes most of it tree "
                                                "and no planar roof fits it")  # fmt: skip
        else:  # crowns from the class map: the probabilities' cell by cell are ragged, and
            # a crown over a roof that they left out was fitted as an upper tier
            crowns = tree_crowns(mask, tree, crop.gsd, options, min_cells)
    unknown = crowns  # left to the data term (eq. 4): out of the segment and of the fits
    unknown_overruled = None
    # the building's parts no view saw (between its known sides, or where their lowest
    # level fits under the fusion's ceiling): in its outline, not in the fits (their
    # DSM is NaN); a cloud of one building has no hidden parts, its
    # unknown cells are off the building (AHN3 clouds: median RMS 0.486 -> 0.515 m)
    hidden = np.zeros(mask.shape, bool)
    if not options.all_building:
        region = mask & ~unknown & np.isfinite(dsm)
        ceiling = None if inputs.ceiling is None else inputs.ceiling[r0:r1, c0:c1]
        reach = int(round(options.outline_reach_m / g.gsd))
        hidden, _ = unseen_at_level(region, dsm, dtm, ceiling, reach, g.gsd,
                                    exclude=inputs.segments[r0:r1, c0:c1] != 0)  # fmt: skip
    known, known_dsm = (mask & ~unknown) | hidden, np.where(unknown, np.nan, dsm)
    others = (inputs.segments[r0:r1, c0:c1] > 0) & ~mask
    # the crowns over its edge, the segment's own among them: what they hide is neither
    # roof nor ground to the priors
    under_crowns = None
    if inputs.tree is not None and not options.all_building:
        under_crowns = crowns_over_the_edge(known, inputs.tree[r0:r1, c0:c1] & ~others, dsm,
                                            crop.gsd)  # fmt: skip
    if found is None:
        found = segment_roofs(known, known_dsm, dtm, xs, ys, crop, options, min_cells, lambda_,
                              under_crowns)  # fmt: skip
        building = None if inputs.building is None else inputs.building[r0:r1, c0:c1]
        if isinstance(found, str) and building is not None and _classed(mask, building):
            found, known = outline_at_the_walls(found, known, known_dsm, dtm, others, xs, ys,
                                                crop, options, min_cells, lambda_,
                                                under_crowns)  # fmt: skip
            if isinstance(found, str):
                found, unknown_overruled = building_all_the_same(
                    found, known, known_dsm, dtm, xs, ys, crop, options, min_cells, under_crowns
                )
    if not isinstance(found, str):
        more = unknown_objects(dsm, mask & ~unknown, found.heights, crop.gsd, options, min_cells)
        if more.any():  # the segment without them, again
            again = segment_roofs((mask & ~(unknown | more)) | hidden,
                                  np.where(unknown | more, np.nan, dsm),
                                  dtm, xs, ys, crop, options, min_cells, lambda_,
                                  under_crowns)  # fmt: skip
            if not isinstance(again, str):
                found, unknown = again, unknown | more
    if isinstance(found, str):
        return SegmentResult(k, skipped=found)
    priors, wings, inside, heights = found.priors, found.wings, found.inside, found.heights
    X, Y = np.meshgrid(xs, ys)
    # a floor under every roof cell: a cloud of roofs alone has its DTM on the roofs
    roof_low = min(min(w.fit.z_main for w, _ in wings), float(np.nanmin(heights)))
    base_z = min(found.base_z, roof_low - 0.5)
    meshed, how, faces, solid = closed_solid(wings, base_z, priors[0])
    if meshed is not wings:  # rebuilt: the heights and the roof type as meshed
        wings, heights = meshed, model_heights(meshed, X, Y)
    planes, areas = face_planes(faces)
    record = {
        "family": priors[0].family,
        "parts": [p.record() for p in priors],
        "wings": [w.record() for w, _ in wings],
        "energies_2d": found.energies,
        "energy_2d": round(float(sum(p.energy for p in priors)), 5),
        "energy_3d_rms_m": round(float(_rms(heights - dsm, inside & ~unknown)), 3),
        "unknown_object_m2": round(float(unknown.sum()) * crop.gsd**2, 2),
        "tree_class_overruled": overruled is not None,
        "unknown_label_overruled": unknown_overruled is not None,
        "meshed": how,
        "iterations": int(sum(p.evaluations for p in priors) + sum(w.fit.evaluations
                                                                  for w, _ in wings)),
        "seconds": round(time.perf_counter() - t0, 3),
    }  # fmt: skip
    building = Building(
        str(k), Surface(solid.vertices, solid.triangles), "2.2", footprint=found.outline,
        roof_type=building_roof_type([w for w, _ in wings], options.tier_step_m),
        planes=planes, plane_areas=areas, base_z=base_z,
        eave_z=min(w.fit.z_main for w, _ in wings),
        ridge_z=float(solid.vertices[:, 2].max()), record=record,
    )  # fmt: skip
    return SegmentResult(k, building, outlines=[mapping(p.polygon()) for p in priors])


@dataclass
class SegmentRoofs:
    """Eq. 2-6's answer for one segment: its priors and their eq. 4 energies, their
    outline (and the cells it covers), the wings' roofs, the model's heights on the
    segment's crop (NaN off the outline) and the lowest ground under it, metres."""

    priors: list
    energies: dict
    outline: object
    inside: np.ndarray
    wings: list
    heights: np.ndarray
    base_z: float


def segment_roofs(mask, dsm, dtm, xs, ys, crop: Grid, options, min_cells, lambda_,
                  under_crowns=None):  # fmt: skip
    """Eq. 2-6 on one segment's cells (``mask``; ``dsm`` NaN where it is not to be
    fitted): a :class:`SegmentRoofs`, or why the segment is skipped (str).
    ``under_crowns`` : (h, w) bool, optional, cells off the segment whose footprint
    crowns hide (:func:`crowns_over_the_edge`): the priors' registration leaves them
    out, and the roofs are not fitted to them."""
    priors, energies = decompose_outline(mask, xs, ys, crop, options.families,
                                         options.min_part_m, lambda_, options.rho, min_cells,
                                         _MAX_PARTS, lambda_label=options.lambda_,
                                         hidden=under_crowns)  # fmt: skip
    if under_crowns is not None:
        dsm = np.where(under_crowns, np.nan, dsm)
    if not priors:
        return (f"unknown object: no footprint prior explains it (eq. 4 energies "
                f"{energies})")  # fmt: skip
    X, Y = np.meshgrid(xs, ys)
    outline = union_outline(priors)
    inside = rasterize_on(outline, crop)
    if not np.isfinite(dsm[inside]).any():
        return "the registered prior covers no cell with a height"
    ground = dtm[inside & np.isfinite(dtm)]
    base_z = float(np.min(ground)) if len(ground) else float(np.nanmin(dsm[inside]) - 3.0)
    ground_z = float(np.median(ground)) if len(ground) else base_z
    if options.all_building:  # a cloud of roofs alone has its DTM on its lowest roof
        ground_z = -np.inf
    wings = roof_wings(priors, X, Y, dsm, inside, crop, options, min_cells, ground_z)
    if not wings:
        return "no DSM height on the registered prior"
    return SegmentRoofs(priors, energies, outline, inside, wings, model_heights(wings, X, Y),
                        base_z)  # fmt: skip


def _classed(mask: np.ndarray, cells: np.ndarray) -> bool:
    """Whether the fusion classes more than half of the segment ``mask`` as ``cells`` (the
    same crop, bool) say."""
    return bool((mask & cells).sum() > 0.5 * mask.sum())


def outline_at_the_walls(why: str, mask, dsm, dtm, others, xs, ys, crop: Grid, options,
                         min_cells, lambda_, under_crowns=None) -> tuple:  # fmt: skip
    """A segment the fusion classes building that no prior explained better than the
    unknown label (``why``), tried again on its outline where its DSM's walls stand at
    half its eaves' height (:func:`~modeling.shared.opened_parts.mid_wall_region` within
    ``options.outline_reach_m``, not into the ``others`` segments). Returns
    (:func:`segment_roofs`' answer, the cells it was fitted on): the new outline's when a
    prior explains it, else (``why``, ``mask``).

    The level set's length term rounds a notch off an outline, and the DSM's walls keep
    it: dev seed 6 lost a 59 m² L whose segment cut its inner corner across (rectangle
    0.25 against the unknown label's 0.19); on its walls' outline the L scores 0.11."""
    if options.outline_reach_m <= 0:
        return why, mask
    walls = mid_wall_region(mask, dsm - dtm, others, crop.gsd, options.outline_reach_m)
    walls &= np.isfinite(dsm)
    if under_crowns is not None:
        under_crowns = under_crowns & ~walls
    found = segment_roofs(walls, dsm, dtm, xs, ys, crop, options, min_cells, lambda_,
                          under_crowns)  # fmt: skip
    return (why, mask) if isinstance(found, str) else (found, walls)


def building_all_the_same(why: str, mask, dsm, dtm, xs, ys, crop: Grid, options, min_cells,
                          under_crowns=None):  # fmt: skip
    """A segment the fusion classes building that no prior explained better than the
    unknown label (``why``): its best prior, fitted without that label, models it when
    the roof fitted on it is planar (a median residual under ``options.planar_m``, as a
    roof the classes call tree is kept); a crown the classes took for a building is not
    (small seed 2's, 38 m², stays out). Returns (:func:`segment_roofs`' answer, the
    residual) or (``why``, None).

    Eq. 4's unknown label stands for the objects no prior is made for; the classes and
    the roof's planarity say what this one is. Without this, a building whose segment
    the priors fit poorly is left out of the model altogether: small seed 5 lost a T
    and a U, by 0.4 and 15 % of their energy; the T's roof leaves 0.04 m and is kept,
    the rectangle over the U 0.43 m, and it stays out."""
    found, residual = planar_roof(mask, dsm, dtm, xs, ys, crop, options, min_cells, np.inf,
                                  under_crowns)  # fmt: skip
    return (why, None) if found is None else (found, residual)


def planar_roof(mask, dsm, dtm, xs, ys, crop: Grid, options, min_cells, lambda_,
                under_crowns=None) -> tuple:  # fmt: skip
    """:func:`segment_roofs` on the segment ``mask`` and the median residual its roof
    leaves there (:func:`planar_residual`), or (None, None) unless that is under
    ``options.planar_m``: a roof, not a crown."""
    found = segment_roofs(mask, dsm, dtm, xs, ys, crop, options, min_cells, lambda_,
                          under_crowns)  # fmt: skip
    residual = planar_residual(found, dsm, mask, options.tier_step_m)
    if residual is None or residual >= options.planar_m:
        return None, None
    return found, residual


def planar_residual(found, dsm: np.ndarray, mask: np.ndarray, step: float) -> float | None:
    """Median |DSM - fitted roof| over the segment's cells (``mask``) inside its outline
    and off the model's walls (:func:`_off_walls`, steps over ``step`` metres), metres,
    for :func:`segment_roofs`' answer ``found``; None when no prior or roof fits (a str).
    On seeds 0-2 a roof leaves 0.044 m (90 % under 0.088 m), a crown or a group of
    crowns at least 0.115 m (with the walls: 0.05, 0.105 and 0.12 m)."""
    if isinstance(found, str):
        return None
    r = np.abs(_off_walls(found.heights, dsm, found.inside & mask, step))
    return float(np.median(r)) if len(r) else None


def tree_crowns(mask, tree, gsd: float, options, min_cells) -> np.ndarray:
    """(h, w) bool crowns the level set took into the segment ``mask``: the cells the
    fusion classes tree (``tree``: its class map, else its probabilities), in parts wider
    than the smallest part and of at least ``min_cells``, with what they leave of the
    segment that is narrower (their rim, which the classes may give to building) or smaller.
    None when they would leave less than half the segment: a building the classes got
    wrong (a green roof) stays whole, and the roof fit decides."""
    crowns = _large_parts(mask & tree, gsd, options, min_cells)
    if not crowns.any():
        return crowns
    kept = _large_parts(mask & ~crowns, gsd, options, min_cells)
    if kept.sum() < 0.5 * mask.sum():
        return np.zeros_like(crowns)
    return mask & ~kept


def unknown_objects(dsm, mask, heights, gsd: float, options, min_cells) -> np.ndarray:
    """(h, w) bool cells of the segment that the fitted roofs do not explain: outside
    the outline or standing more than a tier's step off the model, in parts wider than
    the smallest part and of at least ``min_cells``, taken whole, that stand apart from
    the roof beside them (:func:`_stands_apart`) and reach into the outline (none
    otherwise). A crown over or beside the roof is such an object, which
    eq. 4 leaves to the data term; the building's own tiers and wings are in the model.

    dsm, heights : (h, w) float, metres; mask : (h, w) bool, the segment."""
    # the cells the outline leaves out are unexplained too: they make the object whole
    off = ~np.isfinite(heights) | (np.abs(dsm - heights) > options.tier_step_m)
    off &= mask & np.isfinite(dsm)
    core = _large_parts(off, gsd, options, min_cells)
    labels, _ = ndimage.label(off)  # the objects whole: the opening trims them
    objects = np.unique(labels[core])
    explained = mask & np.isfinite(dsm) & ~off
    objects = [j for j in objects if j and _stands_apart(labels == j, dsm, heights, explained,
                                                         options.tier_step_m)]  # fmt: skip
    unknown = np.isin(labels, objects)
    # an object wholly outside the outline is already left to the data term
    return unknown if (unknown & np.isfinite(heights)).any() else np.zeros_like(unknown)


def _stands_apart(obj, dsm, heights, explained, step: float) -> bool:
    """Whether the unexplained object ``obj`` stands apart from the roof beside it: fewer
    than half of its cells within ``step`` metres of the model's median height over the
    explained cells it touches. A part of the roof that a wrong wing stood over (a
    segment merged with its neighbour's building, whose L put a wing across the tower's
    corner) is level with the roof beside it; a crown or a neighbour's roof is not."""
    beside = ndimage.binary_dilation(obj, np.ones((3, 3), bool)) & explained
    if not beside.any():
        return True
    level = float(np.median(heights[beside]))
    z = dsm[obj]
    z = z[np.isfinite(z)]
    return not len(z) or np.mean(np.abs(z - level) <= step) < 0.5


def _large_parts(mask, gsd: float, options, min_cells) -> np.ndarray:
    """(h, w) bool the parts of ``mask`` opened by a disc of half the smallest part's
    width and of at least ``min_cells``."""
    parts, big = opened_parts(mask, gsd, 0.5 * options.min_part_m, min_cells * gsd**2, 8)
    return big[parts]


def closed_solid(wings: list, base_z: float, main: Prior):
    """The building's mesh (:func:`part_meshes.building_solid` in ``main``'s frame) and
    its roof faces. Planes offset by a hair from a neighbouring wing's eave can leave
    slivers that the closedness check (Open3D's) rejects: the mesh is then rebuilt with
    the planes back on the wings' sides, and if still not closed, with every wing flat
    at the median height of its roof (a closed LOD1 block rather than an open LOD2
    shell). Returns the wings as meshed, how (``_MESHED``), faces, solid."""
    attempts = [(_MESHED[0], wings)]
    if any(np.any(w.fit.offset) for w, _ in wings):
        attempts.append((_MESHED[1], [(_refit(w, offset=np.zeros(4)), p) for w, p in wings]))
    attempts.append((_MESHED[2], [(_flat_wing(w), p) for w, p in wings]))
    for attempt in attempts:
        how, candidate = attempt
        per_wing = [wing_faces(w.rect, w.fit, p.theta, p.origin) for w, p in candidate]
        solid = building_solid(per_wing, base_z, main.theta, main.origin)
        if is_watertight(solid.vertices, solid.triangles):
            break
    return candidate, how, [f for wf in per_wing for f in wf], solid


def _refit(w: Wing, **changes) -> Wing:
    return dataclasses.replace(w, fit=dataclasses.replace(w.fit, **changes))


def _flat_wing(w: Wing) -> Wing:
    """The wing with a flat roof at the median height of its fitted roof (at the centres
    of a 20 x 20 lattice of its rectangle)."""
    u0, u1, v0, v1 = w.rect
    t = (np.arange(20) + 0.5) / 20
    U, V = np.meshgrid(u0 + t * (u1 - u0), v0 + t * (v1 - v0))
    h = exact_heights(side_distances(U.ravel(), V.ravel(), w.rect), w.fit)
    z = w.fit.z_main + float(np.median(h))
    flat = _refit(w, z_main=z, omega=np.zeros(4), offset=np.zeros(4), cap=None)
    return dataclasses.replace(flat, roof_type="flat")


def _frame_coords(p: Prior, X, Y):
    c, s = np.cos(p.theta), np.sin(p.theta)
    dx, dy = X - p.origin[0], Y - p.origin[1]
    return c * dx + s * dy, -s * dx + c * dy


def _in_rect(u, v, rect, pad=0.0):
    return (u >= rect[0] - pad) & (u <= rect[1] + pad) & (v >= rect[2] - pad) & (v <= rect[3] + pad)


def fit_wings(priors, X, Y, dsm, inside, options: ParametricOptions, gsd: float,
              flat: bool | float = False) -> list:  # fmt: skip
    """Eq. 6 on every wing of every part: its cells are those of the outline inside its
    rectangle that no other wing covers (all of its cells where the others cover most),
    less the outermost ring, whose heights the walls blur. The wings share one main
    height h_m (their median), as the paper's buildings do; tiers get their own.
    ``flat`` holds every angle at 0 (a multi-level building's base), at the level of
    each wing's outer ring (True) or at the height it gives (metres)."""
    level = None if isinstance(flat, bool) else float(flat)
    fit = (
        fit_roof
        if flat is False
        else (lambda d, z, s, zm, _: flat_fit(d, z, s, zm if level is None else level))
    )
    rects = [(w, p) for p in priors for w in p.wings()]
    coords = {id(p): _frame_coords(p, X, Y) for p in priors}
    masks = [_in_rect(*coords[id(p)], w) & inside for w, p in rects]
    cells_of = []
    for i, (rect, p) in enumerate(rects):
        own = masks[i].copy()
        for j, m in enumerate(masks):
            if j != i:
                own &= ~m
        cells = own if own.sum() >= 0.5 * masks[i].sum() else masks[i]
        u, v = coords[id(p)]
        d = side_distances(u[cells], v[cells], rect)
        z = dsm[cells]
        keep = np.isfinite(z) & (d.min(axis=0) >= gsd)
        if keep.sum() < 10:
            continue
        cells_of.append((rect, p, d[:, keep], z[keep]))
    hidden, covered = under_other_wings([(rect, p) for rect, p, _, _ in cells_of])
    fits = [fit(d, z, options.robust_m, None, h)
            for (_, _, d, z), h in zip(cells_of, hidden, strict=True)]  # fmt: skip
    if len(fits) > 1:  # the paper's h_m is one per building: the wings share the median
        z_main = float(np.median([f.z_main for f in fits]))
        fits = [fit(d, z, options.robust_m, z_main, h)
                for (_, _, d, z), h in zip(cells_of, hidden, strict=True)]  # fmt: skip
    return [(Wing(rect, f, roof_type(f, rect, h, c), hidden=h), p) for (rect, p, _, _), f, h, c
            in zip(cells_of, fits, hidden, covered, strict=True)]  # fmt: skip


def under_other_wings(rects: list) -> tuple[list[tuple[bool, ...]], list[np.ndarray]]:
    """Per wing, what of it lies under the building's other wings, where the DSM shows
    their roof, not its own.

    rects : list of (rect (4,), Prior) in the prior's frame.

    Returns
    -------
    hidden : list of (4,) bool tuples
        Whether each side (u0, v0, u1, v1) does: the strip along it, half the wing's
        width deep, at least half covered. A plane rising from such a side (an L's inner
        corner) shows in the DSM over the strip's rest at most.
    covered : list of (N,) bool
        Which of its :func:`wing_samples` do.
    """
    polys = [p.frame_polygon(r) for r, p in rects]
    hidden, covered = [], []
    for i, (r, p) in enumerate(rects):
        u, v = wing_samples(r)
        others = unary_union([q for j, q in enumerate(polys) if j != i])
        if others.is_empty:
            hidden.append((False,) * 4)
            covered.append(np.zeros(u.shape, bool))
            continue
        u0, u1, v0, v1 = r
        half = 0.5 * min(u1 - u0, v1 - v0)
        strips = ([u0, u0 + half, v0, v1], [u0, u1, v0, v0 + half],
                  [u1 - half, u1, v0, v1], [u0, u1, v1 - half, v1])  # fmt: skip
        hidden.append(tuple(
            bool(s.intersection(others).area >= 0.5 * s.area)
            for s in (p.frame_polygon(np.array(b)) for b in strips)
        ))  # fmt: skip
        cos, sin = np.cos(p.theta), np.sin(p.theta)
        covered.append(shapely.contains_xy(others, p.origin[0] + cos * u - sin * v,
                                           p.origin[1] + sin * u + cos * v))  # fmt: skip
    return hidden, covered


def roof_wings(
    priors, X, Y, dsm, inside, crop: Grid, options, min_cells, ground_z, depth: int = 0
) -> list:
    """The wings' roofs with their tiers: the five-parameter roofs, or flat roofs with
    tiers stacked on them (a multi-level building, which the roofs would bridge with
    steep planes), whichever fits the DSM over the outline better (the robust cost). A
    flat base less than a tier's step above ``ground_z`` (metres) is the ground the
    outline took in, not a level of the building. A third candidate's flat base stands
    at the lowest level (:func:`_lowest_level`) where that is a tier's step below the
    outer ring's. A tier is chosen the same way, on the roof under it (``depth`` tiers
    down, at most ``_MAX_TIERS``)."""
    candidates, ring_z = [], None
    for flat in (False, True, "lowest"):
        if flat == "lowest":
            flat = _lowest_level(dsm, inside, options.tier_step_m, min_cells)
            if flat is None or ring_z is None or flat > ring_z - options.tier_step_m:
                continue
        wings = fit_wings(priors, X, Y, dsm, inside, options, crop.gsd, flat)
        if flat is True and wings:
            ring_z = min(w.fit.z_main for w, _ in wings)
        if flat is not False and any(
            w.fit.z_main < ground_z + options.tier_step_m for w, _ in wings
        ):
            continue
        if depth < _MAX_TIERS:
            wings += stack_tiers(wings, X, Y, dsm, inside, crop, options, min_cells, depth)
        if wings:
            r = (model_heights(wings, X, Y) - dsm)[inside]
            r = r[np.isfinite(r)]
            candidates.append((robust_cost(r, options.robust_m), wings))
    return min(candidates, key=lambda c: c[0])[1] if candidates else []


def _lowest_level(dsm, inside, step: float, min_cells: int) -> float | None:
    """The height of the lowest part of the outline's DSM (off its outer ring) of at least
    ``min_cells`` cells, when they stand within ``step`` metres of one another: a base
    for tiers below the outer ring's level (a low annex beside the main block, which
    tiers stacked on the ring's level cannot reach). None when there is none."""
    z = np.sort(dsm[ndimage.binary_erosion(inside)])
    z = z[np.isfinite(z)]
    if len(z) < 2 * min_cells:
        return None
    low = z[:min_cells]
    return float(np.median(low)) if low[-1] - low[0] <= step else None


def model_heights(wings, X, Y) -> np.ndarray:
    """(h, w) the model's roof height at every cell: the highest wing over it."""
    z = np.full(X.shape, -np.inf)
    for w, p in wings:
        u, v = _frame_coords(p, X, Y)
        m = _in_rect(u, v, w.rect)
        if m.any():
            h = w.fit.z_main + exact_heights(side_distances(u[m], v[m], w.rect), w.fit)
            z[m] = np.maximum(z[m], h)
    return np.where(np.isfinite(z), z, np.nan)


def stack_tiers(wings, X, Y, dsm, inside, crop: Grid, options, min_cells, depth: int = 0) -> list:
    """Parts of the roof standing ``tier_step_m`` above the fitted roof over at least
    ``min_cells``: each a prior and its roof (:func:`roof_wings`: five parameters, or
    flat with tiers of its own, as a wedding cake's middle level), on top (a
    multi-level building's upper tiers), up to ``_MAX_TIERS``. X, Y : (h, w) cell
    centres of ``crop``."""
    gsd = crop.gsd
    extra: list = []
    for _ in range(_MAX_TIERS):
        above = inside & (np.nan_to_num(dsm - model_heights(wings + extra, X, Y), nan=0.0)
                          > options.tier_step_m)  # fmt: skip
        above = ndimage.binary_opening(above, iterations=max(1, int(1.0 / gsd)))
        labels, n = ndimage.label(above)
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        big = [j for j in range(1, n + 1) if sizes[j] >= min_cells]
        if not big:
            break
        before = len(extra)
        for j in big:
            part = labels == j
            r0, r1, c0, c1 = grown_box(*np.nonzero(part), part.shape)  # the tier's own domain
            p, _ = compete_priors(segment_frame(part[r0:r1, c0:c1], X[0, c0:c1], Y[r0:r1, 0],
                                                gsd), ("rect",), options.min_part_m,
                                  options.lambda_)  # fmt: skip
            if p is None:
                continue
            cells = rasterize_on(p.polygon(), crop) & inside
            below = float(np.nanmedian(model_heights(wings + extra, X, Y)[cells]))
            new = roof_wings([p], X, Y, dsm, cells, crop, options, min_cells, below, depth + 1)
            # a tier is a roof: its planes explain its cells (a crown's dome they do
            # not), its walls apart, as in the fits (the DSM blurs them)
            r = _off_walls(model_heights(new, X, Y), dsm, cells, options.tier_step_m)
            if len(r) and np.sqrt(np.mean(r**2)) <= _TIER_RMS * options.robust_m:
                extra += [(Wing(w.rect, w.fit, w.roof_type, tier=True, hidden=w.hidden), q)
                          for w, q in new]  # fmt: skip
        if len(extra) == before:  # what stands above is no roof: looking again finds it again
            break
    return extra


def _off_walls(heights, dsm, cells, step: float) -> np.ndarray:
    """(n,) residuals ``heights - dsm`` (metres, NaN-free) over ``cells`` less their
    outermost ring and the cells beside a step of more than ``step`` metres in the
    model's ``heights`` (an upper tier's walls): the cells the DSM does not blur."""
    filled = np.where(np.isfinite(heights), heights, -1e6)
    wall = ndimage.maximum_filter(filled, 3) - ndimage.minimum_filter(filled, 3) > step
    r = (heights - dsm)[ndimage.binary_erosion(cells) & ~wall]
    return r[np.isfinite(r)]


def building_roof_type(wings: list[Wing], tier_step_m: float) -> str:
    """One label per building, as the truth has: multi-level when its flat wings stand
    at more than one level, else the type that covers most of the wings that show an
    end."""
    flat = [w for w in wings if w.roof_type == "flat"]
    if len(flat) == len(wings):
        levels = sorted(w.fit.z_main + (w.fit.cap or 0.0) for w in wings)
        return "multi-level" if levels[-1] - levels[0] > tier_step_m else "flat"
    main = [w for w in wings if not w.tier] or wings
    # a wing with both ends under other wings (a U's base) shows no end: gable or hipped
    # are one to it, so the wings that show an end decide
    main = [w for w in main if sum(w.hidden) < 2] or main
    votes: dict[str, float] = {}
    for w in main:
        area = float((w.rect[1] - w.rect[0]) * (w.rect[3] - w.rect[2]))
        votes[w.roof_type] = votes.get(w.roof_type, 0.0) + area
    return max(votes, key=votes.get)


def prior_pull(results: list[SegmentResult], grid: Grid, options: ParametricOptions):
    """Eq. 8's pull for the next round: H_eps of the registered priors' signed distance,
    and mu / sigma^2 (the template variance over the grid) where a prior lies near."""
    shapes = [(shape(o), 1) for x in results for o in x.outlines]
    if not shapes:
        return None
    inside = rasterio.features.rasterize(shapes, out_shape=grid.shape, transform=grid.transform,
                                         fill=0, dtype=np.uint8).astype(bool)  # fmt: skip
    phi = signed_distance(inside)
    near = np.abs(phi) < 8
    h = heaviside(phi)
    var = max(float(np.mean(h[near] ** 2) - np.mean(h[near]) ** 2), 1e-3)
    return h, np.where(near, options.mu / var, 0.0)


def skipped_outlines(results: list[SegmentResult], segments: np.ndarray, grid: Grid) -> list:
    """Outlines of the skipped segments (the preview draws them)."""
    out = []
    for x in results:
        if x.skipped is None:
            continue
        for geom, _ in rasterio.features.shapes((segments == x.segment).astype(np.uint8),
                                                mask=segments == x.segment,
                                                transform=grid.transform):  # fmt: skip
            out.append(geom)
    return out


def _rms(e: np.ndarray, mask: np.ndarray) -> float:
    e = e[mask & np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def summary_lines(record: dict, buildings=()) -> list[str]:
    """What ``workbench model parametric`` prints beside the counts (``buildings``:
    model.json's building records, read once)."""
    rounds = record["segmentation"]["rounds"]
    types: dict[str, int] = {}
    families: dict[str, int] = {}
    for b in buildings:
        types[b["roof_type"]] = types.get(b["roof_type"], 0) + 1
        families[b["family"]] = families.get(b["family"], 0) + 1
    return [
        f"  {rounds[-1]['segments']} segments, {len(record['skipped'])} left to the data term "
        f"(unknown objects); {record['seconds_per_building']} s per building",
        "  footprint priors: " + ", ".join(f"{k} {v}" for k, v in sorted(families.items())),
        "  roof types: " + ", ".join(f"{k} {v}" for k, v in sorted(types.items())),
        *blocks_lines(record["segmentation"].get("blocks")),
    ]
