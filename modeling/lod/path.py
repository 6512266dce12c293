"""The LOD path end to end: rasters of a fusion (from a mesh, best) in, a ModelRun out.

Each paper step is a function of its own module: :func:`.tree_probability.tree_probability`
(section 4.1), :func:`.labelling.mrf_labelling` (section 4.2), :func:`.facades.facade_directions`
(5.1), :func:`.segments.detect_segments` and :func:`.segments.regularise_segments` (5.2),
:func:`.shapes.roof_directions` and :func:`.shapes.roof_planes` (5.3),
:func:`.arrangement.arrangement_faces` and :func:`.arrangement.label_faces` (5.4), and the
LOD generation here (:func:`lod_models`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from fusion.planar_objects import COUNTS as PLANAR_COUNTS
from fusion.planar_objects import planar_roof_cells
from modeling.shared.in_blocks import (
    BlockPlan,
    block_engine,
    blocks_lines,
    blocks_record,
    each_block,
    plan_blocks,
)
from modeling.shared.opened_parts import (
    half_eaves,
    mid_wall_region,
    touching,
    unseen_at_level,
)
from modeling.shared.raster_ground import dtm_across_holes, vertex_colours
from modeling.shared.roof_model import closed_roof_model
from workbench.engine import BUILDINGS_IN_FLIGHT, Engine, ThreadEngine
from workbench.errors import InputError, WorkbenchError
from workbench.fusion_run import ONE_CELL, checked_fusion_run, read_fusion_run
from workbench.grid_blocks import Block
from workbench.ground_grass_colours import fit_flat_colours, ground_factor
from workbench.model_run import Building, ModelRun
from workbench.pictures import colorize_classes, contact_sheet
from workbench.raster import BUILDING, GRASS, GROUND, TREE, Grid, raster_header, read_raster
from workbench.records import StageTimer, run_speed
from workbench.texture_seams import rgb_to_lab

from .arrangement import arrangement_faces, label_faces
from .eaves import faces_to_eaves
from .facades import facade_directions, wall_normals
from .labelling import (
    bridged_cracks,
    eroded_rim,
    fill_from_below,
    fill_holes,
    mrf_labelling,
    open_close,
)
from .options import LodOptions
from .segments import (
    detect_segments,
    direction_maps,
    outline_segments,
    regularise_segments,
)
from .shapes import roof_directions, roof_planes, z_symmetric
from .tree_probability import (
    FEATURE_MARGIN,
    N_FEATURES,
    feature_bands,
    fit_tree_classifier,
    stroke_sample,
    tree_probability,
)

log = logging.getLogger(__name__)

FUSION_RASTERS = ("ortho", "dsm", "dtm", "class_prob")
SIMPLIFY_CELLS = 2.25  # the super-pixel path's simplification of face outlines
MARGIN_CELLS = 4
STROKE_ROWS = 1024  # rows of strokes the input check reads at a time


@dataclass
class LodInputs:
    """What every building's task reads (:func:`building_lod`): a block's rasters, its
    building regions and their boxes, shared once with every worker."""

    grid: Grid
    rgb: np.ndarray
    dsm: np.ndarray
    filled: np.ndarray  # the DSM's holes filled for the outlines (labelling.fill_holes)
    dtm: np.ndarray
    normal: np.ndarray | None
    parts: np.ndarray  # (h, w) int32 building regions 1..n, 0 elsewhere
    boxes: list  # region k's (rows, cols) slices at k - 1 (ndimage.find_objects)


def run_lod(
    fusion_dir: str | Path,
    options: LodOptions | None = None,
    labels: str | Path | None = None,
    *,
    engine: Engine | None = None,
) -> ModelRun:
    """The LOD paper on a fusion run: MRF labelling, regular roof planes, segment
    arrangements, LOD0/1/2.

    A grid larger than ``options.block_m`` (by default 4096 cells a side) is modelled
    block by block (:func:`lod_block`), each labelled over its outer cells and each
    building modelled by one block (:mod:`modeling.shared.in_blocks`). What is learned
    from the strokes is learned once, over the whole grid (:func:`learn_from_strokes`),
    and the colour contrast is normalised by the whole grid's mean: a block's tree
    probability and colour weights are those of one grid. Its ground heights and its
    labelling are its own, which differ from one grid's near the blocks' edges.

    Parameters
    ----------
    fusion_dir : path
        A fusion run (ortho, dsm, dtm, class_prob; normal.tif when fused from a mesh).
    options : LodOptions
    labels : path, optional
        Training strokes (class codes 1-4, 0 unlabelled) for the tree classifier.
    engine : Engine, optional
        Runs the buildings' tasks (default: this process, one after another). With a task
        store and several blocks, the run's own rasters are written block by block to the
        store's folder, not held whole.
    """
    options = options or LodOptions()
    _check_levels(options)
    engine = engine or ThreadEngine(1)
    timer = StageTimer()
    t_start = time.perf_counter()
    plan = plan_blocks(fusion_dir, options.block_m, options.block_margin_m, engine)
    grid, blocks = plan.grid, plan.blocks
    with timer.stage("tree probability"):
        learned = learn_from_strokes(fusion_dir, labels, grid, blocks, options)
    mean_d2 = None
    if len(blocks) > 1 and options.colour_contrast:
        with timer.stage("labelling"):
            mean_d2 = whole_grid_colour_difference(fusion_dir, grid, blocks)
    done = []
    for b in each_block(blocks):
        done.append(lod_block(fusion_dir, b, plan, options, learned, mean_d2,
                              block_engine(engine, blocks, b), timer))  # fmt: skip
    buildings = plan.buildings
    with timer.stage("preview"):
        layers, _ = plan.rasters.preview_layers()
        preview = lod_preview(layers["rgb"], layers["classes"], layers["planes"])
    seconds = time.perf_counter() - t_start
    cells = {name: sum(d["cells"][name] for d in done) for name in done[0]["cells"]}
    trace = done[0]["trace"] if len(done) == 1 else [d["trace"] for d in done]
    counts = {key: sum(d["counts"][key] for d in done) for key in done[0]["counts"]}
    record = {
        "skipped": [s for d in done for s in d["skipped"]],
        "labelling": {"tree_probability": learned.source, "flat_colours": learned.colours,
                      "mean_ground_m": trace, "cells": cells},
        **engine.describe(),
        **run_speed(seconds, len(buildings), grid.width * grid.height),
    }  # fmt: skip
    if len(blocks) > 1:
        record["blocks"] = blocks_record(blocks, plan.side_m, options.block_margin_m,
                                         sum(d["cut"] for d in done))  # fmt: skip
    return ModelRun(
        "lod", options, buildings, crs=done[0]["crs"], grid=grid,
        **plan.rasters.model_rasters(), ground=plan.rasters.ground(),
        preview=preview, stages=timer.stages,
        inputs={"fusion": str(Path(fusion_dir).absolute()),
                "grid": {"width": grid.width, "height": grid.height, "gsd": grid.gsd},
                "labels": str(Path(labels).absolute()) if labels else None,
                "normal_map": "normal.tif" if done[0]["normal_map"] else "from the DSM"},
        counts=counts, record=record,
    )  # fmt: skip


def check_inputs(fusion_dir: Path, options: LodOptions, labels: Path | None = None) -> None:
    """Read what :func:`run_lod` refuses, before a command starts its workers: the levels
    asked for, the fusion run's rasters (on one cell), its normal map's grid and the
    strokes' codes (a band of rows at a time; one line, with no worker's shutdown noise
    after it)."""
    _check_levels(options)
    grid = checked_fusion_run(fusion_dir, FUSION_RASTERS, classes=False).grid
    _normal_map(Path(fusion_dir), grid, ONE_CELL)
    if labels is not None:
        for r in range(0, grid.height, STROKE_ROWS):
            _strokes(labels, grid, (slice(r, min(r + STROKE_ROWS, grid.height)),
                                    slice(0, grid.width)))  # fmt: skip


def _check_levels(options: LodOptions) -> None:
    if not {"1", "2"} & set(options.lod):
        raise WorkbenchError("--lod: give 1 or 2 as well: every building needs a closed mesh "
                             "(LOD0 is its footprint)")  # fmt: skip


@dataclass
class Learned:
    """What the strokes teach, once for the whole grid: the tree classifier (None: the
    fusion's grass and tree probabilities), the ground and grass colours (None: not
    used), and their records."""

    tree: object
    source: str
    flat: object
    colours: dict


def learn_from_strokes(fusion_dir, labels, grid: Grid, blocks: list[Block],
                       options: LodOptions) -> Learned:  # fmt: skip
    """The tree classifier (eq. 1) and the ground and grass colours, trained on the
    strokes of the whole grid, read block by block: the strokes' cells in the grid's
    order, drawn as over one grid (:func:`~.tree_probability.stroke_sample`), and their
    features, each computed over the inner cells of the block that holds it and the
    features' reach around them (``FEATURE_MARGIN``): the values are one grid's."""
    if labels is None:
        return Learned(None, "the fusion's grass and tree probabilities (no --labels)", None,
                       {"used": False, "reason": "no --labels"})  # fmt: skip
    cells, codes = [], []  # the stroke cells, whole-grid flat index, block after block
    for b in blocks:
        inner = _strokes(labels, grid, b.inner)
        r, c = np.nonzero(inner)
        cells.append((r + b.inner[0].start) * grid.width + c + b.inner[1].start)
        codes.append(inner[r, c])
    cells, codes = np.concatenate(cells), np.concatenate(codes)
    order = np.argsort(cells, kind="stable")  # the whole grid's row-major order
    cells, codes = cells[order], codes[order]
    sample = stroke_sample(cells, options.seed)
    flat_cells = (np.flatnonzero(np.isin(codes, (GROUND, GRASS))) if options.flat_colours
                  else np.zeros(0, np.int64))  # fmt: skip
    X = np.zeros((len(sample), N_FEATURES), np.float32)
    rgb = np.zeros((len(flat_cells), 3), np.uint8)
    for b in blocks:
        in_x, in_rgb = _in_inner(sample, b, grid), _in_inner(cells[flat_cells], b, grid)
        if not (in_x.any() or in_rgb.any()):
            continue
        # the inner cells and the features' reach around them: one grid's values
        window = tuple(slice(max(i.start - FEATURE_MARGIN, 0), min(i.stop + FEATURE_MARGIN, n))
                       for i, n in zip(b.inner, grid.shape, strict=True))  # fmt: skip
        ortho = read_fusion_run(fusion_dir, ("ortho",), window).rgb
        r, c = _window_cells(cells[flat_cells][in_rgb], window, grid)
        rgb[in_rgb] = ortho[r, c]
        r, c = _window_cells(sample[in_x], window, grid)
        rows_x = np.flatnonzero(in_x)
        for rows, F in feature_bands(ortho, rows=r):
            sel = (r >= rows.start) & (r < rows.stop)
            X[rows_x[sel]] = F[r[sel] - rows.start, c[sel]]
    picked = np.searchsorted(cells, sample)
    tree = fit_tree_classifier(X, codes[picked], options.boost_rounds, options.seed)
    source = f"AdaBoost of {options.boost_rounds} stumps on {labels}'s strokes"
    flat_model, colours = None, {"used": False, "reason": "--no-flat-colours"}
    if options.flat_colours:
        flat_model, colours = fit_flat_colours(rgb, codes[flat_cells], options.seed)
    return Learned(tree, source, flat_model, colours)


def _in_inner(flat: np.ndarray, block: Block, grid: Grid) -> np.ndarray:
    """(N,) whether each cell (whole-grid flat index) lies in ``block``'s inner cells."""
    r, c = np.divmod(flat, grid.width)
    (rows, cols) = block.inner
    return (r >= rows.start) & (r < rows.stop) & (c >= cols.start) & (c < cols.stop)


def _window_cells(flat: np.ndarray, window: tuple[slice, slice],
                  grid: Grid) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Rows and columns in ``window`` of cells given by their whole-grid flat index."""
    r, c = np.divmod(flat, grid.width)
    return r - window[0].start, c - window[1].start


def whole_grid_colour_difference(fusion_dir, grid: Grid, blocks: list[Block]) -> float:
    """The labelling's colour normalisation, <|Lab_i - Lab_j|^2> over every pair of
    4-neighbours of the whole grid (:func:`~.labelling.mean_colour_difference`), read
    block by block: each pair counted in the block whose inner cells hold its first
    cell (each window one row and column longer, where the grid goes on)."""
    total, pairs = 0.0, grid.height * (grid.width - 1) + (grid.height - 1) * grid.width
    for b in blocks:
        (r0, r1), (c0, c1) = ((s.start, s.stop) for s in b.inner)
        window = (slice(r0, min(r1 + 1, grid.height)), slice(c0, min(c1 + 1, grid.width)))
        lab = rgb_to_lab(read_fusion_run(fusion_dir, ("ortho",), window).rgb).astype(np.float64)
        h, w = r1 - r0, c1 - c0
        total += float(np.sum((lab[:h, 1:] - lab[:h, :-1]) ** 2))
        total += float(np.sum((lab[1:, :w] - lab[:-1, :w]) ** 2))
    return total / max(pairs, 1)


def lod_block(fusion_dir, block: Block, plan: BlockPlan, options: LodOptions, learned: Learned,
              mean_d2: float | None, engine: Engine, timer: StageTimer) -> dict:  # fmt: skip
    """Sections 4-5 over the outer cells of ``block``: the tree probability, the MRF
    labelling, and the LOD models of the buildings ``plan.claims`` gives it (every one
    when the block is the whole grid), each a task of ``engine`` (:func:`building_lod`),
    put into ``plan``; returns the block's record
    (cells of each class in its inner cells, the labelling's trace, skipped regions,
    counts)."""
    with timer.stage("read"):
        fusion = read_fusion_run(fusion_dir, FUSION_RASTERS, block.outer)
        grid = fusion.grid
        dsm, dtm, rgb = fusion.band("dsm"), fusion.band("dtm"), fusion.rgb
        normal = _normal_map(Path(fusion_dir), plan.grid, block.outer)
    with timer.stage("tree probability"):
        if learned.tree is not None:
            t = tree_probability(learned.tree, rgb, engine)
        else:
            prob = fusion.rasters["class_prob"]
            t = np.nan_to_num(prob[GRASS - 1] + prob[TREE - 1], nan=0.5)
    with timer.stage("labelling"):
        cells = max(1, round(options.ground_block_m / grid.gsd))
        # the ground goes on under the mesh's holes, where filled heights stand on it
        ground = dtm_across_holes(dtm)
        # the mesh's cracks across roofs closed first, for the labelling and the outlines
        bridged = bridged_cracks(dsm, ground, options.h_trunc, grid.gsd)
        filled = fill_from_below(bridged)
        factor = ground_factor(learned.flat, rgb) if learned.flat is not None else None
        classes, _, trace = mrf_labelling(filled, t, options.h_trunc, options.mu,
                                          options.ground_iterations, cells,
                                          rgb if options.colour_contrast else None,
                                          factor, mean_d2=mean_d2)  # fmt: skip
        planar = dict.fromkeys(PLANAR_COUNTS, 0)
        if options.planar_objects:
            # green roofs the strokes' colours call tree, as in the fusion's class map;
            # the inlier distance from the noise of the roofs, not of the ground: a
            # mesh's marching cubes facet its sloped faces (seed 1: 0.043 m on cells
            # labelled building, 0.031 m on ground; 0.049 and 0.046 m in the views'
            # fusion), and a 28 m^2 cross-gabled corner of a roof the colours called
            # tree missed its planes by that much (height RMSE off the jumps 1.30 ->
            # 0.76 m; seeds 0 and 2 the same)
            roofs, planar = planar_roof_cells(classes, dsm, dsm - ground, grid.gsd,
                                              options.seed, noise_on=BUILDING)  # fmt: skip
            classes = np.where(roofs, BUILDING, classes).astype(classes.dtype)
        radius = round(options.opening_m / grid.gsd)
        building = open_close(classes == BUILDING, radius)
        parts, n = ndi.label(building)
        sizes = np.bincount(parts.ravel(), minlength=n + 1) * grid.gsd**2
        todo, cut = plan.claims.segments_to_model(block, parts, n, None, last=True)
        todo = [k for k in todo if sizes[k] >= options.min_area_m2]
        number = plan.claims.claim(block, parts, n, todo)
        outline_heights = fill_holes(bridged, ground, options.h_trunc, from_below=filled)
        # the roofs' last rows the mesh lost into the holes beyond them
        rim = eroded_rim(bridged, ground, building, options.h_trunc, grid.gsd)
        outline_heights[rim] = filled[rim]
    inputs = LodInputs(grid, rgb, dsm, outline_heights, ground, normal, parts.astype(np.int32),
                       ndi.find_objects(parts))  # fmt: skip
    buildings, skipped, painted = [], [], np.zeros(grid.shape, np.int64)
    first = len(plan.buildings)  # the buildings of the blocks before
    with timer.stage("buildings"):
        done = engine.map(building_lod, todo, engine.share(inputs), options, stage="buildings",
                          keys=[str(k) for k in todo],
                          in_flight=BUILDINGS_IN_FLIGHT * engine.workers,
                          on_failure=lambda k, why: (why, None, (None, None)))  # fmt: skip
        for k, (b, plane_raster, (rows, cols)) in zip(todo, done, strict=True):
            if isinstance(b, str):
                skipped.append({"region": int(number[k]), "reason": b})
            else:
                b.id = str(first + len(buildings) + 1)
                b.mesh.vertex_colors = vertex_colours(b.mesh.vertices, rgb, grid)
                buildings.append(b)
                inside = plane_raster > 0
                painted[rows, cols][inside] = plane_raster[inside] + 1000 * int(b.id)
    plan.keep_buildings(buildings)
    plan.rasters.keep("class", block, classes, 0)
    plan.rasters.keep("tree_probability", block, t.astype(np.float32))
    plan.rasters.put(block, grid, dtm=dtm, rgb=rgb, dsm=dsm, classes=classes, planes=painted)
    inner = classes[block.inside]
    return {
        "cells": {name: int((inner == c).sum()) for c, name in
                  ((1, "ground"), (2, "grass"), (3, "tree"), (4, "building"))},
        "trace": trace, "skipped": skipped, "cut": cut, "crs": fusion.crs,
        "normal_map": normal is not None,
        "counts": {"candidates": len(todo), "skipped": len(skipped), **planar},
    }  # fmt: skip


def building_lod(
    k: int, inputs: LodInputs, options: LodOptions
) -> tuple[Building | str, np.ndarray, tuple[slice, slice]]:
    """Task: sections 5.1-5.4 and the LOD generation for the building region ``k`` of
    ``inputs.parts``; returns the building (or why there is none), its cells' plane
    index + 1 and its window (rows, columns of the block)."""
    t0 = time.perf_counter()
    g, parts, box = inputs.grid, inputs.parts, inputs.boxes[k - 1]
    H, W = parts.shape
    r0, r1 = max(box[0].start - MARGIN_CELLS, 0), min(box[0].stop + MARGIN_CELLS, H)
    c0, c1 = max(box[1].start - MARGIN_CELLS, 0), min(box[1].stop + MARGIN_CELLS, W)
    win = (slice(r0, r1), slice(c0, c1))
    crop = g.window(*win)
    dsm, dtm = inputs.dsm[r0:r1, c0:c1], inputs.dtm[r0:r1, c0:c1]
    seg = parts[r0:r1, c0:c1]
    # the outline where the mesh's rounded walls stand at mid-height
    filled = inputs.filled[r0:r1, c0:c1]
    others = (seg > 0) & (seg != k)
    mask = mid_wall_region(seg == k, filled - dtm, others, g.gsd, options.outline_reach_m)
    hidden, level = unseen_in_outline(mask, dsm, dtm, others)
    mask |= hidden
    if mask.sum() * g.gsd**2 < options.min_area_m2:
        return "under --min-area at its walls' mid-height", np.zeros(mask.shape, np.int64), win
    normal = _normals(inputs.normal, dsm, g.gsd, win)
    X, Y = crop.cell_centers()
    points = np.dstack([X, Y, dsm])
    # 5.1 facade directions
    theta, share = facade_directions(wall_normals(normal, dsm, g.gsd, _ring(mask)),
                                     options.angle_threshold, seed=options.seed + k)  # fmt: skip
    # 5.3 roof directions and planes, on the seen cells
    cells = mask & np.isfinite(dsm) & np.isfinite(normal).all(axis=0)
    min_count = max(int(options.min_plane_m2 / g.gsd**2), 4)
    dirs = roof_directions(normal[:, cells].T, theta, options.angle_threshold, min_count,
                           seed=options.seed + k)  # fmt: skip
    planes = roof_planes(points[cells], normal[:, cells].T, dirs, options.angle_threshold,
                         options.plane_inlier_m, min_count)  # fmt: skip
    if not len(planes):
        z = np.nanmedian(dsm[mask]) if np.isfinite(dsm[mask]).any() else np.nan
        if not np.isfinite(z):
            return "no height in the DSM", np.zeros(mask.shape, np.int64), win
        planes = np.array([[0.0, 0.0, 1.0, -z]])
    # the sloped faces the mesh lost into a hole, down to the eaves
    run_on, run_level = faces_to_eaves(mask, points, normal, planes, others,
                                       options.angle_threshold, options.plane_inlier_m,
                                       g.gsd)  # fmt: skip
    mask |= run_on
    hidden |= run_on
    level = np.where(run_on, run_level, level)
    # the faces over the hidden parts are labelled at their level, planes fit seen cells
    faces_points = np.dstack([X, Y, np.where(hidden, level, dsm)])
    # 5.2 line segments from four sources, regularised
    near = ndi.binary_dilation(mask, iterations=2)
    sources = {
        "ortho": detect_segments(inputs.rgb[r0:r1, c0:c1].mean(axis=2)),
        "height": detect_segments(np.where(near, dsm, np.nan)),
        **{f"normal_{i}": detect_segments(np.where(near, m, np.nan))
           for i, m in enumerate(direction_maps(normal, theta))},
        "outline": outline_segments(mask),
    }  # fmt: skip
    found = {name: _inside(s, near) for name, s in sources.items()}
    segs, regular = regularise_segments(
        np.concatenate(list(found.values())), theta, options.angle_threshold,
        options.collinear_m / g.gsd, 1.0 / g.gsd,
    )  # fmt: skip
    faces = arrangement_faces(mask, segs, 1.0 / g.gsd)
    # 5.4 faces labelled with planes
    face_plane = label_faces(faces, faces_points, planes, options.beta, g.gsd,
                             hidden & ~np.isfinite(dsm))  # fmt: skip
    plane_raster = np.where(faces > 0, face_plane[np.maximum(faces, 1) - 1] + 1, 0)
    b = lod_models(plane_raster, crop, planes, dsm, dtm, mask, options)
    if b is None:
        return "no face gives a polygon", plane_raster, win
    b.record.update({
        "facade_direction_deg": round(float(np.degrees(theta)), 2),
        "facade_inlier_share": round(share, 3),
        "segments": {name: int(len(s)) for name, s in found.items()},
        "segments_regularised": int(regular.sum()), "segments_kept": int(len(segs)),
        "arrangement_faces": int(faces.max()), "roof_directions": len(dirs),
        "planes_detected": int(len(planes)),
        "cells_run_on_to_eaves": int(run_on.sum()),
        "symmetric_pairs": _symmetric_pairs(planes),
        "seconds": round(time.perf_counter() - t0, 3),
    })  # fmt: skip
    return b, plane_raster, win


def unseen_in_outline(mask, dsm, dtm, others) -> tuple[np.ndarray, np.ndarray]:
    """The building's parts the mesh has no surface for, to join its outline: (h, w) bool
    the unknown cells within the least rectangle of its cells with a height that reach
    those cells through unknown ones, in groups that border the seen ground for at most
    a tenth, not another building's (``others``), as the other paths take them in
    (:func:`~modeling.shared.opened_parts.unseen_parts`), with the roof cells the mesh
    saw around ``mask``; and (h, w) metres ``dsm`` with the unknown ones at their level,
    the lowest of the building's heights around them
    (:func:`~modeling.shared.opened_parts.lowest_around`: what no view saw lies below
    what hid it).

    A mesh from depth maps has no surface where no view saw one: a lower tier behind a
    taller part, and cracks across a roof near its far edge (on ``small`` seed 0, the
    mesh's unknown cells that the views' fusion knows are nearly twice as common on the
    rows and columns where its 2 m voxel blocks meet). :func:`~.labelling.fill_holes`
    gives a hole that reaches the ground anywhere the ground's height, and the outline
    cut a notch there. The arrangement's faces over such cells are labelled with the
    plane nearest their level (:func:`~.arrangement.label_faces`); the planes are fitted
    to the seen cells only.

    A mesh keeps no rays, so nothing bounds what stands on a cell it has no surface
    for: every such cell is given the ceiling a views fusion gives a column no view sees
    through, the highest surface around (:mod:`fusion.hidden_ceiling`), and the
    rectangle's candidates are all kept. A lower tier along a tower's outer side at the
    survey's edge, where every view looks from one side, has the building on one side
    only: taking in only the cells between the building's cells
    (:func:`~modeling.shared.opened_parts.unseen_between`) left out the 33 m tier of
    seed 1's 40 m tower (height RMSE off the jumps 3.31 -> 1.30 m; 2D quality 0.923 ->
    0.932). A views fusion's ceiling (``ceiling.tif``) is not read: the cells it lets in
    beside the walls joined the outlines at the roofs' level (seed 0's views fusion: 2D
    quality 0.928 without it, 0.915 with it, against 0.923 with neither).

    The rectangle spans every roof cell the mesh saw within two cells of ``mask``,
    above half the eaves (:func:`~modeling.shared.opened_parts.half_eaves`): a mesh
    rounds a wall's top off, and keeps a few cells of the roof's last rows, which the
    outline's majority filter drops (:func:`~modeling.shared.opened_parts.mid_wall_region`);
    the rectangle then stopped a row or two inside the wall, on seed 0's 48 m tower
    along its whole north side (off the jumps 1.61 -> 1.12 m, seed 2 0.85 -> 0.72 m;
    2D quality -0.002, +0.002). Those cells join the outline too.
    dsm : (h, w) metres, NaN unknown; dtm : (h, w) metres, known everywhere."""
    known = np.isfinite(dsm)
    ndsm = dsm - dtm
    near = ndi.binary_dilation(mask, iterations=2) & ~others
    with np.errstate(invalid="ignore"):  # NaN compares False: unknown, not roof
        roof = near & known & (ndsm > half_eaves(ndsm, mask))
    # the roof cells that share a side with the outline's cells (a cell met at a
    # corner only makes a face the model cannot close)
    region = (mask & known) | touching(roof & ~mask, mask, sides_only=True)
    ceiling = np.where(known, np.nan, dsm[known].max() if known.any() else np.nan)
    # no margin under it (it bounds nothing) and no reach past the rectangle (the
    # ground beside a wall is as unknown: nothing in the mesh says where the wall
    # stands in it); a group another building's cells cut off from this one's stays out
    hidden, level = unseen_at_level(region, dsm, dtm, ceiling, 0, 0.0, exclude=others)
    return touching(hidden, region) | (region & ~mask), level


def lod_models(
    plane_raster: np.ndarray,
    crop: Grid,
    planes: np.ndarray,
    dsm: np.ndarray,
    dtm: np.ndarray,
    mask: np.ndarray,
    options: LodOptions,
) -> Building | None:
    """LOD generation: LOD2 each face on its roof plane, LOD1 each face at its plane's
    mean height over it (the paper's Fig. 9), LOD0 the outline (written by the run's
    CityJSON). The building carries the highest asked for as its mesh and the LOD1 model
    in ``lods`` when both are asked for."""
    g = dtm[mask]
    base = float(np.nanmin(g)) if np.isfinite(g).any() else np.inf
    simplify = SIMPLIFY_CELLS * crop.gsd
    X, Y = crop.cell_centers()
    lod2 = lod1 = None
    if "2" in options.lod:
        lod2 = closed_roof_model(plane_raster, crop, planes, base, simplify,
                                 options.angle_threshold)  # fmt: skip
    if "1" in options.lod:
        flat = np.zeros_like(planes)
        flat[:, 2] = 1.0
        for p in range(len(planes)):
            sel = plane_raster == p + 1
            z = -(planes[p, 0] * X[sel] + planes[p, 1] * Y[sel] + planes[p, 3]) / planes[p, 2]
            flat[p, 3] = -float(z.mean()) if sel.any() else -planes[p, 3]
        lod1 = closed_roof_model(plane_raster, crop, flat, base, simplify,
                                 options.angle_threshold)  # fmt: skip
        if lod1 is not None:
            lod1.lod = "1.3"
    main = lod2 or lod1
    if main is None:
        return None
    if lod2 is not None and lod1 is not None:
        main.lods["1.3"] = lod1.mesh
    return main


def summary_lines(record: dict, buildings=()) -> list[str]:
    lab = record.get("labelling", {})
    cells = lab.get("cells", {})
    total = max(sum(cells.values()), 1)
    shares = ", ".join(f"{k} {v / total:.0%}" for k, v in cells.items())
    colours = lab.get("flat_colours", {})
    counts = record.get("counts", {})
    trace = lab.get("mean_ground_m")
    if record.get("blocks") and trace:  # one trace a block: their mean by iteration
        trace = [round(float(z), 3) for z in np.mean(trace, axis=0)]
        trace = f"{trace} m (the blocks' mean)"
    else:
        trace = f"{trace} m"
    return [*blocks_lines(record.get("blocks")),
            f"  labelling: {shares}; ground height by iteration {trace}",
            f"  tree probability: {lab.get('tree_probability')}",
            "  ground and grass by colour: " + ("yes" if colours.get("used") else
                                                f"no ({colours.get('reason')})")
            + f"; tree objects made building: {counts.get('planar_objects_made_building', 0)} "
            f"planar, {counts.get('roof_faces_made_building', 0)} roof faces"]  # fmt: skip


def lod_preview(rgb: np.ndarray, classes: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Ortho, MRF labelling and the buildings' faces coloured by roof plane, side by
    side (``planes``: a distinct id per building and plane, 0 elsewhere)."""
    palette = np.random.default_rng(0).integers(40, 230, (int(planes.max()) + 1, 3))
    palette[0] = 255
    return contact_sheet([[(rgb, "ortho"), (colorize_classes(classes), "MRF labelling"),
                           (palette[planes].astype(np.uint8), "roof planes")]],
                         height=360)  # fmt: skip


def _normal_map(folder: Path, grid: Grid, window: tuple[slice, slice]) -> np.ndarray | None:
    """(3, h, w) float32 the fusion's normal map (a mesh's) on the cells ``window`` of
    its ``grid``, or None when it has none (as stored: a building's crop is made float64,
    :func:`_normals`, and the block's map shared with the workers is half the size)."""
    path = folder / "normal.tif"
    if not path.exists():
        return None
    g, bands, _ = raster_header(path)
    if g != grid or bands != 3:
        raise InputError(path, "transform", "not 3 bands on the fusion's grid")
    return read_raster(path, window=window)[0].astype(np.float32, copy=False)


def _normals(normal: np.ndarray | None, dsm: np.ndarray, gsd: float, win) -> np.ndarray:
    """(3, h, w) float64 unit normals of a crop: the normal map's, else the DSM's
    gradient's."""
    if normal is not None:
        return normal[(slice(None), *win)].astype(np.float64)
    gy, gx = np.gradient(dsm, gsd)
    n = np.stack([-gx, gy, np.ones_like(dsm)])  # rows run south: dz/dy = -gy
    return n / np.linalg.norm(n, axis=0)


def _strokes(path, grid: Grid, window: tuple[slice, slice]) -> np.ndarray:
    """(h, w) int64 the training strokes, codes 0-4, on the cells ``window`` of ``grid``:
    read in the window when they are on that grid, else sampled at the nearest cell of
    the strokes' cells under the window (only those read)."""
    path = Path(path)
    g, _, _ = raster_header(path, "labels")
    if g == grid:
        codes = read_raster(path, window=window)[0][0]
    else:
        X, Y = grid.window(*window).cell_centers()
        r, c = g.cell_index(X.ravel(), Y.ravel(), clip=True)
        (r0, r1), (c0, c1) = (r.min(), r.max() + 1), (c.min(), c.max() + 1)
        data = read_raster(path, window=(slice(r0, r1), slice(c0, c1)))[0]
        codes = data[0][r - r0, c - c0].reshape(X.shape)
    if codes.size and (np.nanmax(codes) > 4 or np.nanmin(codes) < 0):
        raise InputError(path, "band 1", "class codes must be 0 (unlabelled) to 4")
    return codes.astype(np.int64)


def _ring(mask: np.ndarray) -> np.ndarray:
    """The cells within two of the mask's edge, both sides (its walls)."""
    grown = ndi.binary_dilation(mask, iterations=2)
    return grown & ~ndi.binary_erosion(mask, iterations=2)


def _inside(seg: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The segments whose middle lies in ``near``."""
    if not len(seg):
        return seg
    mid = np.round((seg[:, :2] + seg[:, 2:]) / 2).astype(np.int64)
    h, w = near.shape
    ok = (mid[:, 0] >= 0) & (mid[:, 0] < w) & (mid[:, 1] >= 0) & (mid[:, 1] < h)
    ok[ok] = near[mid[ok, 1], mid[ok, 0]]
    return seg[ok]


def _symmetric_pairs(planes: np.ndarray) -> int:
    """Plane pairs whose normals are z-symmetric (to 1e-6)."""
    n = planes[:, :3]
    twin = z_symmetric(n)
    return int(sum(np.abs(n[j] - twin[i]).max() < 1e-6 for i in range(len(n))
                   for j in range(i + 1, len(n))))  # fmt: skip
