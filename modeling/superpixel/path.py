"""The super-pixel path end to end: a fusion run in, a :class:`ModelRun` out.

The steps of the paper, each in the module named after it: :mod:`.quickshift` (4.1),
:mod:`.aggregation`, :mod:`.class_crf` (4.2), :mod:`.buildings`,
:mod:`.plane_hypotheses` (5.1), :mod:`.prototypes` (5.2), :mod:`.prototype_crf` (5.2),
:mod:`.rooftop` (5.3). This module only reads, orders the steps and times them.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from modeling.shared.raster_ground import ground_surface, vertex_colours
from workbench import metrics
from workbench.errors import InputError
from workbench.fusion_run import FusionRun, read_fusion_run
from workbench.model_run import Building, ModelRun, stage_record
from workbench.parallel import default_workers
from workbench.progress import progress
from workbench.raster import BUILDING, Grid, class_codes, read_raster
from workbench.records import StageTimer

from .aggregation import SuperpixelGraph, superpixel_graph
from .buildings import split_buildings
from .class_crf import choose_omega_class, geometry_factor, refine_classes, stroke_classes
from .options import SuperpixelOptions
from .plane_hypotheses import SuperpixelPoints, plane_hypotheses, superpixel_points
from .preview import superpixel_preview
from .prototype_crf import edges_within, label_prototypes, refit_planes
from .prototypes import roof_prototypes
from .quickshift import quickshift_superpixels, relief_image
from .rooftop import model_building, observed_faces

FUSION_RASTERS = ("ortho", "dsm", "dtm", "class_prob")
BUILDING_STEPS = ("plane_hypotheses", "prototypes", "prototype_crf", "roof_modeling")


def run_superpixel(
    fusion_dir: Path, options: SuperpixelOptions | None = None, *, truth: Path | None = None
) -> ModelRun:
    """The super-pixel path on the rasters of ``workbench fusion``.

    Parameters
    ----------
    fusion_dir : path
        A fusion run folder (ortho, dsm, dtm, class_prob, class).
    options : SuperpixelOptions
    truth : path, optional
        A scene with truth/: the paper's Table 1 rows go into the record.
    """
    options = options or SuperpixelOptions()
    timer = StageTimer()
    with timer.stage("read"):
        fusion = read_fusion_run(fusion_dir, FUSION_RASTERS)
        dsm, dtm, grid = fusion.band("dsm"), fusion.band("dtm"), fusion.grid
        decided = decide_defaults(options, fusion.from_points)
    with timer.stage("superpixels"):
        image = relief_image(dsm, grid.gsd) if decided["segment_on"] == "relief" else fusion.rgb
        labels = quickshift_superpixels(
            image, options.sigma, options.tau, options.ratio, seed=options.seed,
            workers=options.workers or default_workers(), height=dsm,
            height_weight=decided["height_weight"],
        )  # fmt: skip
    with timer.stage("aggregation"):
        graph = superpixel_graph(labels, fusion.rgb, fusion.rasters["class_prob"], dsm)
    with timer.stage("class_crf"):
        sp_class, crf_choices = class_crf(graph, labels, fusion, options)
        unseen = ~(np.nan_to_num(fusion.rasters["class_prob"]).sum(axis=0) > 0)
        crf_class = np.where(unseen, 0, sp_class[labels]).astype(np.uint8)
    with timer.stage("buildings"):
        opening = 0.0 if options.all_building else options.opening_m
        owner = split_buildings(
            sp_class == BUILDING, labels, grid.gsd, opening, options.min_area_m2
        )
        pts = superpixel_points(labels, dsm, grid)
    buildings, faces, seconds = model_buildings(
        graph, labels, owner, pts, dsm, dtm, grid, options, decided["edge_reach_m"]
    )
    timer.stages.update({name: stage_record(sec) for name, sec in seconds.items()})
    for b in buildings:
        b.mesh.vertex_colors = vertex_colours(b.mesh.vertices, fusion.rgb, grid)
    with timer.stage("preview"):
        preview = superpixel_preview(fusion.rgb, labels, crf_class, faces, buildings, grid, dtm)
    record = {"superpixels": graph.n, **crf_choices}
    if truth is not None:
        sp_argmax = np.where(unseen, 0, graph.class_sum.argmax(axis=1)[labels] + 1)
        # the paper's pixel column: each cell's most probable class (the fusion's class.tif
        # has its own CRF on the cells)
        record["classification_table"] = classification_table(
            truth, grid, class_codes(fusion.rasters["class_prob"]), sp_argmax.astype(np.uint8),
            crf_class,
        )  # fmt: skip
    return ModelRun(
        "superpixel", options, buildings, crs=fusion.crs, grid=grid, dtm=dtm, dsm=dsm,
        ground=ground_surface(dtm, fusion.rgb, grid),
        rasters={"class": (crf_class, 0), "superpixels": (labels.astype(np.int32), None)},
        preview=preview, stages=timer.stages, parameters=decided, record=record,
        inputs={"fusion": str(Path(fusion_dir).absolute()),
                "grid": {"width": grid.width, "height": grid.height, "gsd": grid.gsd}},
    )  # fmt: skip


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
    graph: SuperpixelGraph, labels: np.ndarray, fusion: FusionRun, options: SuperpixelOptions
) -> tuple[np.ndarray, dict]:
    """(N,) class of each super-pixel, and how its parameters were chosen: with
    ``omega_class`` auto, the omega; with ``geometry_unary``, the plane residuals'
    factors learned on the training strokes (:func:`~.class_crf.geometry_factor`)."""
    if options.all_building:
        return np.where(np.isfinite(graph.height_median), BUILDING, 1), {}
    omega, record, geometry = options.omega_class, {}, None
    strokes = None
    if omega is None or options.geometry_unary:
        strokes = training_strokes(fusion, required=omega is None)
    if options.geometry_unary:
        if strokes is None:
            record["geometry"] = {"used": False, "reason": "no training strokes"}
        else:
            geometry, record["geometry"] = geometry_factor(
                graph, stroke_classes(labels, strokes, graph.n)
            )
    if omega is None:
        record["omega_class_choice"] = choose_omega_class(graph, labels, strokes, geometry)
        omega = record["omega_class_choice"]["omega"]
    return refine_classes(graph, omega, geometry), record


def model_buildings(
    graph: SuperpixelGraph,
    labels: np.ndarray,
    owner: np.ndarray,
    pts: SuperpixelPoints,
    dsm: np.ndarray,
    dtm: np.ndarray,
    grid: Grid,
    options: SuperpixelOptions,
    edge_reach_m: float,
) -> tuple[list[Building], np.ndarray, dict]:
    """Sections 5.1-5.3 building by building.

    Returns
    -------
    buildings, (H, W) int32 prototype face of every building cell (1000 * building +
    face), and the seconds spent in each of ``BUILDING_STEPS``.
    """
    neighbours = adjacency_lists(graph.edges)
    cell_building = owner[labels]
    boxes = building_boxes(cell_building, int(owner.max()))
    members_of = np.split(np.argsort(owner, kind="stable"), np.cumsum(np.bincount(owner)))
    inner_edges = edges_within(graph.edges, owner)
    reach = int(round(edge_reach_m / grid.gsd))
    faces = np.zeros(labels.shape, np.int32)
    seconds = dict.fromkeys(BUILDING_STEPS, 0.0)
    out: list[Building] = []
    for b in progress(range(1, int(owner.max()) + 1), "modeling buildings"):
        r0, r1, c0, c1 = boxes[b]
        window = (slice(r0, r1), slice(c0, c1))
        crop_grid = Grid(grid.xmin + c0 * grid.gsd, grid.ymax - r0 * grid.gsd, grid.gsd,
                         c1 - c0, r1 - r0)  # fmt: skip
        timed = _timed(seconds)
        members = members_of[b]
        hyps = timed("plane_hypotheses", plane_hypotheses, members, pts, neighbours, options)
        protos, anchors = timed("prototypes", _prototypes, hyps, members, graph, neighbours,
                                options)  # fmt: skip
        if not len(protos):
            continue
        assign = timed("prototype_crf", label_prototypes, members, protos, pts, graph, options,
                       anchors, inner_edges[b])  # fmt: skip
        protos = timed("prototype_crf", refit_planes, members, assign, protos, pts, options)
        sp_face = np.zeros(graph.n, np.int32)
        sp_face[members] = assign + 1
        crop = np.where(cell_building[window] == b, sp_face[labels[window]], 0)
        crop = observed_faces(crop, np.isfinite(dsm[window]), reach)
        parts = timed("roof_modeling", model_building, crop, crop_grid, protos, dtm[window],
                      options)  # fmt: skip
        faces[window][crop > 0] = crop[crop > 0] + 1000 * b
        counts = {"superpixels": len(members), "hypotheses": len(hyps),
                  "prototypes": len(protos)}  # fmt: skip
        for k, part in enumerate(parts):
            part.id = f"{b}" if k == 0 else f"{b}-{k}"
            part.record.update(counts)
            out.append(part)
    return out, faces, seconds


def adjacency_lists(edges: np.ndarray) -> dict[int, list[int]]:
    """{node: its neighbours} on the ``edges`` (E, 2), each node's neighbours in the order
    of the edges that name it; only nodes with an edge appear."""
    if not len(edges):
        return {}
    node = np.r_[edges[:, 0], edges[:, 1]]
    other = np.r_[edges[:, 1], edges[:, 0]]
    order = np.lexsort((np.tile(np.arange(len(edges)), 2), node))
    node, other = node[order], other[order]
    starts = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
    lists = np.split(other, starts[1:])
    return dict(zip(node[starts].tolist(), (part.tolist() for part in lists), strict=True))


def _timed(seconds: dict):
    def call(step: str, fn, *args):
        t0 = time.perf_counter()
        result = fn(*args)
        seconds[step] += time.perf_counter() - t0
        return result

    return call


def _prototypes(hyps, members, graph: SuperpixelGraph, neighbours, options):
    """Section 5.2's prototypes and their anchors, or with no plane anywhere one flat roof
    at the median, anchored nowhere (allowed everywhere)."""
    if hyps:
        return roof_prototypes(hyps, neighbours, options)
    z = np.nanmedian(graph.height_median[members])
    flat = np.array([[0.0, 0.0, 1.0, -z]]) if np.isfinite(z) else np.empty((0, 4))
    return flat, None


def building_boxes(cell_building: np.ndarray, n: int) -> np.ndarray:
    """(n + 1, 4) row and column bounds (r0, r1, c0, c1), one cell of margin, of each
    building 1..n in a raster of building ids (row 0 unused)."""
    H, W = cell_building.shape
    rr, cc = np.nonzero(cell_building)
    bb = cell_building[rr, cc]
    lo_r, lo_c = np.full(n + 1, H), np.full(n + 1, W)
    hi_r, hi_c = np.full(n + 1, -1), np.full(n + 1, -1)
    np.minimum.at(lo_r, bb, rr)
    np.minimum.at(lo_c, bb, cc)
    np.maximum.at(hi_r, bb, rr)
    np.maximum.at(hi_c, bb, cc)
    return np.stack(
        [np.maximum(lo_r - 1, 0), np.minimum(hi_r + 2, H), np.maximum(lo_c - 1, 0),
         np.minimum(hi_c + 2, W)], axis=1
    )  # fmt: skip


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


def summary_lines(record: dict) -> list[str]:
    """What ``workbench model superpixel`` prints beside the counts."""
    lines = [f"  {record['superpixels']} super-pixels"]
    table = record.get("classification_table")
    if table:
        rows = ", ".join(f"{k} {v['overall_accuracy']:.3f}" for k, v in table.items())
        lines.append(f"  overall accuracy (Table 1): {rows}")
    return lines
