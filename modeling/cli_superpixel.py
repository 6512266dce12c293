"""`workbench model superpixel`: read a fusion run, model its buildings, write the run."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
from skimage.segmentation import find_boundaries

from workbench import metrics
from workbench.atomic import atomic_output_dir
from workbench.errors import InputError
from workbench.imageio import write_rgb
from workbench.meshes import concatenate_meshes, raster_mesh
from workbench.meshio import write_mtl, write_obj, write_ply
from workbench.parallel import default_workers
from workbench.pictures import colorize_classes, contact_sheet
from workbench.progress import progress
from workbench.raster import Grid, read_raster, write_raster
from workbench.records import StageTimer, peak_memory_mb
from workbench.render import render_mesh, viewpoints

from .aggregate import superpixel_graph
from .buildings import split_buildings
from .superpixel_model import (
    BuildingModel,
    SuperpixelOptions,
    choose_omega_class,
    label_prototypes,
    model_building,
    observed_faces,
    plane_hypotheses,
    refine_classes,
    refit_planes,
    roof_prototypes,
    superpixel_points,
)
from .superpixels import quickshift_superpixels, relief_image

log = logging.getLogger(__name__)

FUSION_RASTERS = ("ortho", "dsm", "dtm", "class_prob", "class")
BUILDING = 4


def read_fusion_dir(folder: Path) -> tuple[dict[str, np.ndarray], Grid, object]:
    """The rasters of a fusion run, checked to share one grid and CRS.

    Raises
    ------
    InputError
        Naming the missing or mismatched file.
    """
    if not Path(folder).is_dir():
        raise InputError(folder, None, "no such fusion folder")
    out, grid, crs = {}, None, None
    for name in FUSION_RASTERS:
        path = Path(folder) / f"{name}.tif"
        if not path.exists():
            raise InputError(path, None, "missing: not the output folder of `workbench fusion`")
        data, g, c = read_raster(path)
        if grid is None:
            grid, crs = g, c
        elif g != grid:
            raise InputError(path, "transform", f"grid differs from {folder}/ortho.tif's")
        elif c != crs:
            raise InputError(path, "crs", f"CRS differs from {folder}/ortho.tif's")
        out[name] = data
    if out["ortho"].shape[0] != 3 or out["class_prob"].shape[0] != 4:
        raise InputError(Path(folder) / "class_prob.tif", "bands", "expected RGB and 4 classes")
    return out, grid, crs


def run_superpixel(
    fusion_dir: Path, out: Path, options: SuperpixelOptions, *, truth=None, overwrite: bool = False
) -> dict:
    """The whole path; returns the model.json record."""
    timer = StageTimer()
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        with timer.stage("read"):
            r, grid, crs = read_fusion_dir(fusion_dir)
            rgb = np.moveaxis(r["ortho"], 0, -1)
            dsm, dtm = r["dsm"][0].astype(np.float64), r["dtm"][0].astype(np.float64)
            prob, pixel_class = r["class_prob"], r["class"][0]
            from_points = _fusion_mode(fusion_dir) == "point cloud"
            edge_reach_m = options.edge_reach_m
            if edge_reach_m is None:
                edge_reach_m = 0.0 if from_points else 1.0
        with timer.stage("superpixels"):
            segment_on = options.segment_on or ("relief" if from_points else "ortho")
            image = relief_image(dsm, grid.gsd) if segment_on == "relief" else rgb
            height_weight = options.height_weight if segment_on == "ortho" else 0.0
            labels = quickshift_superpixels(
                image, options.sigma, options.tau, options.ratio, seed=options.seed,
                workers=options.workers or default_workers(), height=dsm,
                height_weight=height_weight,
            )  # fmt: skip
        with timer.stage("aggregation"):
            graph = superpixel_graph(labels, rgb, prob, dsm)
        with timer.stage("class_crf"):
            omega_choice = None
            if options.all_building:
                sp_class = np.where(np.isfinite(graph.height_median), BUILDING, 1)
            else:
                omega = options.omega_class
                if omega is None:
                    strokes = training_strokes(fusion_dir, grid)
                    omega_choice = choose_omega_class(graph, labels, strokes)
                    omega = omega_choice["omega"]
                sp_class = refine_classes(graph, omega)
            crf_class = sp_class[labels].astype(np.uint8)
            sp_argmax = (graph.class_sum.argmax(axis=1) + 1)[labels].astype(np.uint8)
            no_data = ~(np.nan_to_num(prob).sum(axis=0) > 0)
            crf_class[no_data] = 0
            sp_argmax[no_data] = 0
        with timer.stage("buildings"):
            owner = split_buildings(
                sp_class == BUILDING,
                labels,
                grid.gsd,
                0.0 if options.all_building else options.opening_m,
                options.min_area_m2,
            )
            pts = superpixel_points(labels, dsm, grid)
        neighbours: dict[int, list[int]] = {}
        for a, b in graph.edges.tolist():
            neighbours.setdefault(a, []).append(b)
            neighbours.setdefault(b, []).append(a)
        models: list[tuple[str, BuildingModel]] = []
        prototype_raster = np.zeros(labels.shape, np.int32)
        hyp_s = proto_s = crf_s = mesh_s = 0.0
        cell_building = owner[labels]
        boxes = building_boxes(cell_building, int(owner.max()))
        members_of = np.split(np.argsort(owner, kind="stable"), np.cumsum(np.bincount(owner)))
        for b in progress(range(1, int(owner.max()) + 1), "modeling buildings"):
            members = members_of[b]
            t0 = time.perf_counter()
            hyps = plane_hypotheses(members, pts, neighbours, options)
            t1 = time.perf_counter()
            if hyps:
                protos = roof_prototypes(hyps, neighbours, options)
            else:  # no plane anywhere: one flat roof at the median height
                z = np.nanmedian(graph.height_median[members])
                protos = np.array([[0.0, 0.0, 1.0, -z]]) if np.isfinite(z) else np.empty((0, 4))
            t2 = time.perf_counter()
            if not len(protos):
                continue
            assign = label_prototypes(members, protos, pts, graph, options)
            protos = refit_planes(members, assign, protos, pts, options)
            t3 = time.perf_counter()
            sp_face = np.zeros(graph.n, np.int32)
            sp_face[members] = assign + 1
            r0, r1, c0, c1 = boxes[b]
            crop = np.where(cell_building[r0:r1, c0:c1] == b, sp_face[labels[r0:r1, c0:c1]], 0)
            reach = int(round(edge_reach_m / grid.gsd))
            crop = observed_faces(crop, np.isfinite(dsm[r0:r1, c0:c1]), reach)
            crop_grid = Grid(
                grid.xmin + c0 * grid.gsd,
                grid.ymax - r0 * grid.gsd,
                grid.gsd,
                crop.shape[1],
                crop.shape[0],
            )
            parts = model_building(crop, crop_grid, protos, dtm[r0:r1, c0:c1], options)
            t4 = time.perf_counter()
            hyp_s, proto_s, crf_s, mesh_s = (
                hyp_s + t1 - t0,
                proto_s + t2 - t1,
                crf_s + t3 - t2,
                mesh_s + t4 - t3,
            )
            prototype_raster[r0:r1, c0:c1][crop > 0] = crop[crop > 0] + 1000 * b
            for k, model in enumerate(parts):
                model.record.update(
                    superpixels=len(members), hypotheses=len(hyps), prototypes=len(protos)
                )
                models.append((f"{b}" if k == 0 else f"{b}-{k}", model))
        peak = peak_memory_mb()  # the steps below interleave, building by building
        for name, sec in (
            ("plane_hypotheses", hyp_s),
            ("prototypes", proto_s),
            ("prototype_crf", crf_s),
            ("roof_modeling", mesh_s),
        ):
            timer.stages[name] = {"wall_s": round(sec, 3), "peak_memory_mb": round(peak, 1)}
        with timer.stage("write"):
            record = _write(
                tmp, models, rgb, dtm, grid, crs, crf_class, labels, prototype_raster, options
            )
        record["stages"] = timer.stages
        record["input"] = {
            "fusion": str(Path(fusion_dir).absolute()),
            "grid": {"width": grid.width, "height": grid.height, "gsd": grid.gsd},
        }
        record["superpixels"] = graph.n
        record["parameters"]["edge_reach_m"] = edge_reach_m
        record["parameters"]["segment_on"] = segment_on
        record["parameters"]["height_weight"] = height_weight
        if omega_choice is not None:
            record["omega_class_choice"] = omega_choice
        if truth is not None:
            record["classification_table"] = _table1(truth, grid, pixel_class, sp_argmax, crf_class)
        (tmp / "model.json").write_text(json.dumps(record, indent=1) + "\n")
    return record


def _fusion_mode(fusion_dir: Path) -> str | None:
    """How the fusion run was made ("depth maps", "point cloud", ...), if it says."""
    try:
        return json.loads((Path(fusion_dir) / "fusion.json").read_text()).get("mode")
    except (OSError, json.JSONDecodeError, AttributeError):
        return None


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


def training_strokes(fusion_dir: Path, grid: Grid) -> np.ndarray:
    """The training labels of the scene a fusion run came from, on ``grid``."""
    from workbench.scene import load_scene
    from workbench.truth import sample_to_grid

    record_path = Path(fusion_dir) / "fusion.json"
    try:
        scene_path = json.loads(record_path.read_text())["inputs"]["scene"]
    except (OSError, KeyError, TypeError, json.JSONDecodeError):
        raise InputError(
            record_path, "inputs.scene", "--omega-class auto needs a fusion run of a scene"
        ) from None
    scene = load_scene(scene_path, check_files=False)
    if scene.training_labels is None:
        raise InputError(scene.scene_json, "training_labels", "--omega-class auto needs them")
    data, src, _ = read_raster(scene.training_labels, field="training_labels")
    return sample_to_grid(data, src, grid)[0].astype(np.int64)


def _table1(truth_scene, grid, pixel, superpixel, crf) -> dict:
    """The super-pixel paper's Table 1 rows against the truth: pixel, super-pixel, CRF."""
    from workbench.truth import truth_rasters

    t = truth_rasters(truth_scene, grid)["class"]
    return {
        name: metrics.classification(c, t)
        for name, c in (("pixel", pixel), ("superpixel", superpixel), ("crf", crf))
    }


def _write(
    tmp: Path, models, rgb, dtm, grid: Grid, crs, crf_class, labels, prototype_raster, options
) -> dict:
    (tmp / "buildings").mkdir()
    materials = {"wall": (170, 170, 170)}
    buildings, parts, colours = [], [], []
    for b, m in models:
        colors = _vertex_colours(m.vertices, rgb, grid)
        bid = str(b)
        write_ply(tmp / "buildings" / f"{bid}.ply", m.vertices, m.triangles, vertex_colors=colors)
        materials[f"roof_{bid}"] = tuple(int(v) for v in np.median(colors, axis=0))
        write_obj(
            tmp / "buildings" / f"{bid}.obj",
            m.vertices,
            m.triangles,
            vertex_colors=colors,
            material=f"roof_{bid}",
            mtllib="materials.mtl",
        )
        buildings.append({"id": bid, "mesh": f"buildings/{bid}.ply", **m.record})
        parts.append((m.vertices, m.triangles))
        colours.append(colors)
    write_mtl(tmp / "buildings" / "materials.mtl", materials)
    ground = raster_mesh(dtm, grid, step=max(1, round(2.0 / grid.gsd)))
    if ground is not None:
        parts.append(ground)
        colours.append(_vertex_colours(ground[0], rgb, grid))
    V, T, _ = concatenate_meshes(parts)  # empty, but valid, without buildings and ground
    Cc = np.concatenate(colours) if colours else np.empty((0, 3), np.uint8)
    write_ply(tmp / "scene.ply", V, T, vertex_colors=Cc)
    write_obj(tmp / "scene.obj", V, T, vertex_colors=Cc)
    write_raster(tmp / "class.tif", crf_class, grid, crs, nodata=0)
    write_raster(tmp / "superpixels.tif", labels.astype(np.int32), grid, crs, nodata=None)
    _preview(tmp / "preview.png", rgb, labels, crf_class, prototype_raster, models, grid, dtm)
    n = len(buildings)
    if n == 0:
        log.warning("no building pixels survived the class CRF: the model is empty")
    return {
        "method": "superpixel",
        "parameters": vars(options),
        "buildings": buildings,
        "counts": {
            "buildings": n,
            "faces": int(sum(b["faces"] for b in buildings)),
            "watertight": int(sum(b["watertight"] for b in buildings)),
        },
    }


def _vertex_colours(vertices: np.ndarray, rgb: np.ndarray, grid: Grid) -> np.ndarray:
    r, c = grid.cell_index(vertices[:, 0], vertices[:, 1], clip=True)
    return rgb[r, c]


def _preview(path, rgb, labels, classes, prototypes, models, grid, dtm) -> None:
    edges = rgb.copy()
    edges[find_boundaries(labels, mode="inner")] = (255, 255, 0)
    rng = np.random.default_rng(0)
    palette = rng.integers(60, 255, (int(prototypes.max()) + 1, 3)).astype(np.uint8)
    palette[0] = 0
    proto = palette[prototypes]
    row = [
        (edges, "super-pixels"),
        (colorize_classes(classes), "CRF classes"),
        (proto, "roof prototypes"),
    ]
    if models:
        V, T, _ = concatenate_meshes([(m.vertices, m.triangles) for _, m in models])
        # a single-building cloud's DTM can be all NaN: its models' foot is the ground then
        low = float(np.nanmin(dtm)) if np.isfinite(dtm).any() else float(V[:, 2].min())
        cam = viewpoints(grid.bounds, (low, float(V[:, 2].max())))["south-west"]
        row.append((render_mesh(V, T, cam, np.full((len(T), 3), 205, np.uint8)), "models"))
    write_rgb(path, contact_sheet([row], height=360))
