"""The super-pixel path end to end: a fusion run in, a :class:`ModelRun` out.

The steps of the paper, each in the module named after it: :mod:`.quickshift` (4.1),
:mod:`.aggregation`, :mod:`.class_crf` (4.2), :mod:`.buildings`,
:mod:`.plane_hypotheses` (5.1), :mod:`.prototypes` (5.2), :mod:`.prototype_crf` (5.2),
:mod:`.rooftop` (5.3), the last four one building at a time as tasks
(:mod:`.building_tasks`). This module only reads, orders the steps and times them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from modeling.shared.in_blocks import (
    BlockPlan,
    block_engine,
    blocks_lines,
    blocks_record,
    each_block,
    model_blocks,
    plan_blocks,
)
from modeling.shared.raster_ground import vertex_colours
from workbench import metrics
from workbench.engine import BUILDINGS_IN_FLIGHT, Engine, ThreadEngine
from workbench.errors import InputError, WorkbenchError
from workbench.fusion_run import (
    FusionRun,
    checked_fusion_run,
    class_map,
    hidden_ceiling,
    read_fusion_run,
)
from workbench.grid_blocks import Block
from workbench.model_run import Building, ModelRun
from workbench.parallel import default_workers
from workbench.raster import BUILDING, Grid, class_codes, read_raster
from workbench.records import StageTimer, run_speed

from .aggregation import SuperpixelGraph, superpixel_graph
from .building_tasks import ROOF_STEPS, building_shares, model_building_roofs, no_roofs
from .buildings import split_buildings
from .class_crf import (
    choose_omega_class,
    fit_geometry,
    geometry_factors,
    refine_classes,
    stroke_classes,
)
from .options import SuperpixelOptions
from .plane_hypotheses import SuperpixelPoints, superpixel_points
from .preview import superpixel_preview
from .quickshift import quickshift_superpixels, relief_image

FUSION_RASTERS = ("ortho", "dsm", "dtm", "class_prob")


def run_superpixel(
    fusion_dir: Path,
    options: SuperpixelOptions | None = None,
    *,
    truth: Path | None = None,
    engine: Engine | None = None,
) -> ModelRun:
    """The super-pixel path on the rasters of ``workbench fusion``.

    Parameters
    ----------
    fusion_dir : path
        A fusion run folder (ortho, dsm, dtm, class_prob, class).
    options : SuperpixelOptions
        With ``block_m``, the grid is modelled block by block (:func:`model_block`).
    truth : path, optional
        A scene with truth/: the paper's Table 1 rows go into the record.
    engine : Engine, optional
        Runs the buildings' tasks (default: this process, one after another).
    """
    options = options or SuperpixelOptions()
    engine = engine or ThreadEngine(1)
    timer = StageTimer()
    t_start = time.perf_counter()
    plan = plan_blocks(fusion_dir, options.block_m, options.block_margin_m, engine)
    grid, blocks = plan.grid, plan.blocks
    learned, learning = None, {}
    if len(blocks) > 1:
        refuse_in_blocks(truth)
        learned, learning = learn_in_blocks(fusion_dir, blocks, options, timer)
    done: list[BlockModel] = []
    for b in each_block(blocks):
        first = sum(d.superpixels for d in done)  # the super-pixels' numbers on the whole grid
        done.append(model_block(fusion_dir, b, plan, options, first, truth, learned,
                                block_engine(engine, blocks, b), timer))  # fmt: skip
    buildings = plan.buildings
    with timer.stage("preview"):
        layers, on = plan.rasters.preview_layers()
        preview = superpixel_preview(layers["rgb"], layers["labels"], layers["classes"],
                                     layers["faces"], buildings, on,
                                     min(d.ground_z for d in done))  # fmt: skip
    elapsed = time.perf_counter() - t_start
    seconds = {step: sum(d.seconds[step] for d in done) for step in ROOF_STEPS}
    record = {
        "superpixels": sum(d.superpixels for d in done), **done[0].crf_choices, **learning,
        # the tasks' own time in each step, summed over the buildings and the workers
        "roof_steps_s": {step: round(sec, 3) for step, sec in seconds.items()},
        **engine.describe(),
        **run_speed(elapsed, len(buildings), grid.width * grid.height),
    }  # fmt: skip
    if len(blocks) > 1:
        record["blocks"] = blocks_record(blocks, plan.side_m, options.block_margin_m,
                                         sum(d.cut for d in done))  # fmt: skip
    if truth is not None:
        record["classification_table"] = done[0].classification_table
    return ModelRun(
        "superpixel", options, buildings, crs=done[0].crs, grid=grid,
        **plan.rasters.model_rasters(), ground=plan.rasters.ground(),
        preview=preview, stages=timer.stages, parameters=done[0].decided, record=record,
        inputs={"fusion": str(Path(fusion_dir).absolute()),
                "grid": {"width": grid.width, "height": grid.height, "gsd": grid.gsd}},
    )  # fmt: skip


@dataclass
class BlockModel:
    """What :func:`model_block` gives beside its rasters and its buildings: its
    super-pixels, the seconds its buildings' tasks spent in each of ``ROOF_STEPS``, the
    class CRF's choices, the options it decided, its CRS, how many buildings wider than
    the margin it modelled from the part it holds, its lowest ground (for the preview's
    view) and, with a truth, the paper's Table 1."""

    superpixels: int
    seconds: dict
    crf_choices: dict
    decided: dict
    crs: object
    cut: int
    ground_z: float
    classification_table: dict | None = None


def model_block(
    fusion_dir: Path,
    block: Block,
    plan: BlockPlan,
    options: SuperpixelOptions,
    first_label: int,
    truth: Path | None,
    learned: dict | None,
    engine: Engine,
    timer: StageTimer,
) -> BlockModel:
    """Sections 4-5 over the outer cells of ``block``: its rasters read, its super-pixels
    (numbered from ``first_label`` in ``superpixels.tif``) and their classes (with the
    class CRF's parameters ``learned`` on another block, if given), and a task for each
    building ``plan.claims`` gives it (every one when the block is the whole grid); the
    rasters the run writes put into ``plan.rasters`` and its buildings (numbered on the
    whole grid) into ``plan.buildings``."""
    fusion, decided, labels, graph = block_superpixels(fusion_dir, block, options, timer)
    dsm, dtm, grid = fusion.band("dsm"), fusion.band("dtm"), fusion.grid
    with timer.stage("class_crf"):
        sp_class, crf_choices, _ = class_crf(graph, labels, fusion, options, learned)
        unseen = ~(np.nan_to_num(fusion.rasters["class_prob"]).sum(axis=0) > 0)
        crf_class = np.where(unseen, 0, sp_class[labels]).astype(np.uint8)
    with timer.stage("buildings"):
        opening = 0.0 if options.all_building else options.opening_m
        owner = split_buildings(
            sp_class == BUILDING, labels, grid.gsd, opening, options.min_area_m2
        )
        segments, q = owner[labels], int(owner.max())
        todo, cut = plan.claims.segments_to_model(block, segments, q, None, last=True)
        number = plan.claims.claim(block, segments, q, todo)
        pts = superpixel_points(labels, dsm, grid, wanted=number[owner] > 0)
    with timer.stage("roofs"):
        ceiling = None if options.all_building else hidden_ceiling(fusion_dir, grid,
                                                                   block.outer)  # fmt: skip
        buildings, faces, seconds = model_buildings(
            graph, owner, number, pts, dsm, dtm, grid, options, decided["edge_reach_m"], engine,
            ceiling,
        )  # fmt: skip
    for b in buildings:
        b.mesh.vertex_colors = vertex_colours(b.mesh.vertices, fusion.rgb, grid)
    plan.keep_buildings(buildings)
    table = None
    if truth is not None:
        sp_argmax = np.where(unseen, 0, graph.class_sum.argmax(axis=1)[labels] + 1)
        # the paper's pixel column: each cell's most probable class (the fusion's class.tif
        # has its own CRF on the cells)
        table = classification_table(
            truth, grid, class_codes(fusion.rasters["class_prob"]), sp_argmax.astype(np.uint8),
            crf_class,
        )  # fmt: skip
    labels = labels.astype(np.int32)
    if first_label:
        labels += first_label
    plan.rasters.keep("class", block, crf_class, 0)
    plan.rasters.keep("superpixels", block, labels)
    plan.rasters.put(block, grid, dtm=dtm, rgb=fusion.rgb, dsm=dsm, labels=labels,
                     classes=crf_class, faces=faces)  # fmt: skip
    ground_z = float(np.nanmin(dtm)) if np.isfinite(dtm).any() else np.inf
    return BlockModel(graph.n, seconds, crf_choices, decided, fusion.crs, cut,
                      ground_z, table)  # fmt: skip


def block_superpixels(
    fusion_dir: Path, block: Block, options: SuperpixelOptions, timer: StageTimer
) -> tuple[FusionRun, dict, np.ndarray, SuperpixelGraph]:
    """Section 4.1 over the outer cells of ``block``: its rasters, the options its fusion
    decides, its super-pixels (H, W) and their graph."""
    with timer.stage("read"):
        fusion = read_fusion_run(fusion_dir, FUSION_RASTERS, block.outer)
        dsm, grid = fusion.band("dsm"), fusion.grid
        decided = decide_defaults(options, fusion.from_points)
    with timer.stage("superpixels"):
        image = relief_image(dsm, grid.gsd) if decided["segment_on"] == "relief" else fusion.rgb
        labels = quickshift_superpixels(
            image, options.sigma, options.tau, options.ratio, seed=options.seed,
            workers=options.workers or default_workers(), height=dsm,
            height_weight=decided["height_weight"],
        )  # fmt: skip
    with timer.stage("aggregation"):
        graph = superpixel_graph(labels, fusion.rgb, fusion.rasters["class_prob"], dsm,
                                 residuals=options.geometry_unary,
                                 classes=class_map(fusion_dir, grid, block.outer))  # fmt: skip
    return fusion, decided, labels, graph


def learn_in_blocks(
    fusion_dir: Path, blocks: list[Block], options: SuperpixelOptions, timer: StageTimer
) -> tuple[dict | None, dict]:
    """The class CRF's parameters a run in blocks learns on the training strokes
    (``--omega-class auto``, ``--geometry-unary``), once for every block: on the block
    whose inner cells the strokes cover most, as one grid learns them. Returns them (None
    when there is nothing to learn) and their record."""
    if options.all_building or (options.omega_class is not None and not options.geometry_unary):
        return None, {}
    with timer.stage("learning"):  # its block's super-pixels are timed in their stages
        counts = []
        for b in blocks:
            strokes = training_strokes(read_fusion_run(fusion_dir, ("dsm",), b.outer),
                                       required=options.omega_class is None)  # fmt: skip
            counts.append(0 if strokes is None else int((strokes[b.inside] > 0).sum()))
        best = blocks[int(np.argmax(counts))]
    fusion, _, labels, graph = block_superpixels(fusion_dir, best, options, timer)
    with timer.stage("learning"):
        _, record, learned = class_crf(graph, labels, fusion, options)
    record["learned_on_block"] = {"index": best.index, "stroke_cells": max(counts)}
    return learned, record


def check_inputs(fusion_dir: Path, options: SuperpixelOptions, truth: Path | None = None) -> None:
    """Read what :func:`run_superpixel` refuses, before a command starts its workers: the
    fusion run's rasters, the training strokes ``--omega-class auto`` needs and a
    ``--truth`` a run in blocks cannot take (one line, with no worker's shutdown noise
    after it)."""
    fusion = checked_fusion_run(fusion_dir, FUSION_RASTERS, classes=True)
    if len(model_blocks(fusion.grid, options.block_m, options.block_margin_m)[0]) > 1:
        refuse_in_blocks(truth)
    if options.omega_class is None and not options.all_building:
        training_strokes(fusion, required=True)


def refuse_in_blocks(truth: Path | None) -> None:
    """What a run in blocks cannot do: score the whole grid's classes against a truth."""
    if truth is not None:
        raise WorkbenchError("--truth: not with --block; score the run's class.tif with "
                             "`workbench compare --truth` instead")  # fmt: skip


def decide_defaults(options: SuperpixelOptions, from_points: bool) -> dict:
    """The options left to the run (None) decided by what the fusion was made from."""
    segment_on = options.segment_on or ("relief" if from_points else "ortho")
    edge_reach_m = options.edge_reach_m
    if edge_reach_m is None:  # clouds see the eaves from above; views leave them unseen
        edge_reach_m = 0.0 if from_points else 1.0
    return {
        "segment_on": segment_on,
        "height_weight": options.height_weight if segment_on == "ortho" else 0.0,
        "edge_reach_m": edge_reach_m,
    }


def class_crf(
    graph: SuperpixelGraph,
    labels: np.ndarray,
    fusion: FusionRun,
    options: SuperpixelOptions,
    learned: dict | None = None,
) -> tuple[np.ndarray, dict, dict]:
    """(N,) class of each super-pixel, how its parameters were chosen (with
    ``omega_class`` auto, the omega; with ``geometry_unary``, the plane residuals' fit on
    the training strokes, :func:`~.class_crf.fit_geometry`), and the parameters
    themselves ({"omega", "geometry_fit"}). With ``learned`` (another block's), those
    are used as they are."""
    if options.all_building:
        return np.where(np.isfinite(graph.height_median), BUILDING, 1), {}, {}
    if learned is not None:
        fit = learned["geometry_fit"]
        geometry = None if fit is None else geometry_factors(graph, *fit)
        return refine_classes(graph, learned["omega"], geometry), {}, learned
    omega, record, geometry, fit = options.omega_class, {}, None, None
    strokes = None
    if omega is None or options.geometry_unary:
        strokes = training_strokes(fusion, required=omega is None)
    if options.geometry_unary:
        if strokes is None:
            record["geometry"] = {"used": False, "reason": "no training strokes"}
        else:
            fit, record["geometry"] = fit_geometry(graph, stroke_classes(labels, strokes, graph.n))
            geometry = None if fit is None else geometry_factors(graph, *fit)
    if omega is None:
        record["omega_class_choice"] = choose_omega_class(graph, labels, strokes, geometry)
        omega = record["omega_class_choice"]["omega"]
    return refine_classes(graph, omega, geometry), record, {"omega": omega, "geometry_fit": fit}


def model_buildings(
    graph: SuperpixelGraph,
    owner: np.ndarray,
    number: np.ndarray,
    pts: SuperpixelPoints,
    dsm: np.ndarray,
    dtm: np.ndarray,
    grid: Grid,
    options: SuperpixelOptions,
    edge_reach_m: float,
    engine: Engine,
    ceiling: np.ndarray | None = None,
) -> tuple[list[Building], np.ndarray, dict]:
    """Sections 5.1-5.3, each building a task of ``engine``
    (:func:`~.building_tasks.model_building_roofs`).

    ``owner`` (N,) is each super-pixel's building 1..B (0 none); ``number`` (B + 1,)
    each building's number on the whole grid, 0 for those another block models;
    ``ceiling`` (H, W) the fusion's over the cells no view saw (None without one).

    Returns
    -------
    buildings, (H, W) int32 prototype face of every building cell (1000 * building +
    face), and the seconds the tasks spent in each of ``ROOF_STEPS``, summed.
    """
    shares = [s for s in building_shares(graph, owner, pts, dsm, dtm, grid, ceiling)
              if number[s.id]]  # fmt: skip
    for s in shares:
        s.id = int(number[s.id])
    faces = np.zeros(graph.labels.shape, np.int32)
    seconds = dict.fromkeys(ROOF_STEPS, 0.0)
    out: list[Building] = []
    done = engine.map(model_building_roofs, shares, options, edge_reach_m, stage="buildings",
                      keys=[str(s.id) for s in shares],
                      in_flight=BUILDINGS_IN_FLIGHT * engine.workers,
                      on_failure=no_roofs)  # fmt: skip
    for share, roofs in zip(shares, done, strict=True):
        r0, r1, c0, c1 = share.window
        window = faces[r0:r1, c0:c1]
        on = roofs.faces > 0
        window[on] = roofs.faces[on] + 1000 * roofs.id
        out.extend(roofs.parts)
        for step, sec in roofs.seconds.items():
            seconds[step] += sec
    return out, faces, seconds


def training_strokes(fusion: FusionRun, required: bool = True) -> np.ndarray | None:
    """The training labels of the scene a fusion run came from, on its grid; None when
    there are none and they are not ``required`` (``--omega-class auto`` needs them)."""
    from workbench.scene import load_scene
    from workbench.truth import sample_to_grid

    record_path = fusion.folder / "fusion.json"
    inputs = fusion.record.get("inputs")
    scene_path = inputs.get("scene") if isinstance(inputs, dict) else None
    if not scene_path:
        if not required:
            return None
        raise InputError(
            record_path, "inputs.scene", "--omega-class auto needs a fusion run of a scene"
        )
    scene = load_scene(scene_path, check_files=False)
    if scene.training_labels is None:
        if not required:
            return None
        raise InputError(scene.scene_json, "training_labels", "--omega-class auto needs them")
    data, src, _ = read_raster(scene.training_labels, field="training_labels")
    return sample_to_grid(data, src, fusion.grid)[0].astype(np.int64)


def classification_table(truth: Path, grid: Grid, pixel, superpixel, crf) -> dict:
    """The super-pixel paper's Table 1 rows against the truth: pixel, super-pixel, CRF,
    off the training strokes (as ``workbench compare`` scores them)."""
    from workbench.truth import training_cells, truth_rasters

    t = truth_rasters(truth, grid)["class"]
    strokes = training_cells(truth, grid)
    return {
        name: metrics.classification(c, t, exclude=strokes)
        for name, c in (("pixel", pixel), ("superpixel", superpixel), ("crf", crf))
    }


def summary_lines(record: dict, buildings=()) -> list[str]:
    """What ``workbench model superpixel`` prints beside the counts."""
    lines = [f"  {record['superpixels']} super-pixels", *blocks_lines(record.get("blocks"))]
    table = record.get("classification_table")
    if table:
        rows = ", ".join(f"{k} {v['overall_accuracy']:.3f}" for k, v in table.items())
        lines.append(f"  overall accuracy (Table 1): {rows}")
    return lines
