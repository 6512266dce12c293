"""Score one run against the truth: every metric of metrics.json, per building, with maps.

A run is first seen on the truth's grid (:func:`run_layers`): its surface, its buildings
and, for models, the roof normals, all by casting vertical rays through its meshes. The
metrics are then the same plain functions of :mod:`workbench.metrics` for every method.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from . import metrics
from .errors import InputError
from .meshes import concatenate_meshes, is_watertight, sample_surface, triangle_areas
from .raster import check_class_codes, read_raster
from .raycast import raycasting_scene, unsigned_distance
from .runs import Run
from .texture_seams import SceneImages, read_textured_building, recomputed_seam_costs
from .truth import Truth, sample_to_grid, top_down

DSM_KEYS = ("rmse_m", "rmse_off_jumps_m", "median_abs_m", "valid_fraction")


@dataclass
class EvaluationOptions:
    """Parameters of the evaluation.

    Attributes
    ----------
    tolerance_m : vertical tolerance of ``volume_3d_tolerant``, metres (``volume_3d`` is
        the paper's: voxels at the same altitude, no tolerance).
    min_object_area_m2 : smallest connected building region of a raster run that counts
        as a building object.
    samples_per_m2 : surface samples per square metre for the surface distances
        (at most ``max_samples`` per surface).
    max_error_m : the red end of the error colour maps, metres.
    seed : seed of the surface samples.
    """

    tolerance_m: float = 1.0
    min_object_area_m2: float = 5.0
    samples_per_m2: float = 4.0
    max_samples: int = 400_000
    max_error_m: float = 2.0
    seed: int = 0


@dataclass
class RunLayers:
    """A run seen on the evaluation grid ((H, W) arrays, metres, NaN unknown).

    Attributes
    ----------
    surface : the run's surface: its DSM, or its buildings over its ground.
    building_ids : 1-based building index (into ``run.buildings`` for models, connected
        regions of the class map for fusion runs), 0 off buildings.
    building_surface : ``surface`` on building cells, NaN elsewhere.
    normals : (H, W, 3) roof normals of model runs, else None.
    cls, ortho, dsm : the run's rasters where it has them, else None.
    """

    surface: np.ndarray
    building_ids: np.ndarray
    building_surface: np.ndarray
    normals: np.ndarray | None = None
    cls: np.ndarray | None = None
    ortho: np.ndarray | None = None
    dsm: np.ndarray | None = None


@dataclass
class Evaluation:
    """metrics: the run's entry in metrics.json; buildings: one row per true building;
    layers: the run on the grid (None once ``compare`` has drawn it); face_error: (T,)
    distance of each model face's centre to the true buildings, metres, in the order of
    the run's buildings (models with a true mesh only)."""

    metrics: dict
    buildings: list[dict]
    layers: RunLayers | None
    face_error: np.ndarray | None = None


def _on_grid(path, truth: Truth, band: int | None = 0) -> np.ndarray:
    data, src, crs = read_raster(path)
    if crs is not None and truth.crs is not None and crs != truth.crs:
        raise InputError(path, "crs", f"{crs} differs from the truth's CRS")
    data = sample_to_grid(data, src, truth.grid)
    return data if band is None else data[band]


def run_layers(run: Run, truth: Truth, options: EvaluationOptions) -> RunLayers:
    """The run on the truth's grid (see :class:`RunLayers`)."""
    path = run.raster("class")
    cls = check_class_codes(_on_grid(path, truth), path, "class") if path else None
    if run.kind == "fusion":
        dsm = _on_grid(run.raster("dsm"), truth).astype(np.float64)
        ortho = None
        if run.raster("ortho"):
            ortho = np.moveaxis(_on_grid(run.raster("ortho"), truth, band=None), 0, -1)
        mask = cls == 4 if cls is not None else np.zeros(truth.grid.shape, bool)
        ids = building_regions(mask, options.min_object_area_m2 / truth.grid.gsd**2)
        return RunLayers(dsm, ids, np.where(ids > 0, dsm, np.nan), cls=cls, ortho=ortho, dsm=dsm)
    vertices, triangles, owner = stacked_meshes(run)
    ids, building_surface, normals = top_down(vertices, triangles, owner, truth.grid)
    ground = truth.dtm if truth.dtm is not None else np.full(truth.grid.shape, np.nan)
    if run.raster("dtm"):
        # the run's own ground; where it has none, the truth's, so that a building cell
        # the model misses is always scored (a hole in its ground must not hide it)
        own = _on_grid(run.raster("dtm"), truth).astype(np.float64)
        ground = np.where(np.isfinite(own), own, ground)
    surface = np.where(ids > 0, building_surface, ground)
    return RunLayers(surface, ids, building_surface, normals=normals, cls=cls)


def stacked_meshes(run: Run) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All building meshes of a model run as one, with each triangle's 1-based owner."""
    return concatenate_meshes([(b.vertices, b.triangles) for b in run.buildings])


def building_regions(mask: np.ndarray, min_cells: float) -> np.ndarray:
    """(H, W) int64 ids of the 8-connected regions of ``mask`` with at least ``min_cells``
    cells, 0 elsewhere."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, np.int64)
    big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= min_cells)
    big = big[big > 0]
    keep[big] = np.arange(1, len(big) + 1)
    return keep[labels]


def evaluate(run: Run, truth: Truth, options: EvaluationOptions | None = None) -> Evaluation:
    """Every metric the truth and the run allow; groups without data are left out."""
    options = options or EvaluationOptions()
    layers = run_layers(run, truth, options)
    m: dict = {"method": run.method, "kind": run.kind}
    if layers.cls is not None and truth.cls is not None:
        c = metrics.classification(layers.cls, truth.cls, exclude=truth.training)
        if "overall_accuracy" in c:
            m["classification"] = c
    t_ids = truth.building_ids
    if t_ids is not None:
        f = metrics.footprint_2d(layers.building_ids > 0, t_ids > 0)
        f["objects"] = metrics.building_objects(t_ids, layers.building_ids)
        m["footprint_2d"] = f
    t_surface = truth.building_surface
    if t_surface is not None and truth.dtm is not None:
        pred_h, true_h = layers.building_surface - truth.dtm, t_surface - truth.dtm
        m["volume_3d"] = metrics.volume_3d(pred_h, true_h)
        m["volume_3d_tolerant"] = metrics.volume_3d(pred_h, true_h, options.tolerance_m)
    if t_surface is not None:
        jumps = metrics.height_jumps(t_surface)
        h = metrics.height_errors(layers.surface, t_surface, mask=t_ids > 0, jumps=jumps)
        if "rmse_m" in h:
            m["height"] = h
            # the roofs' own error: where both the run and the truth have a building
            # (the DEM-blocks paper's altimetric RMSE), the outlines' misses apart
            roofs = metrics.height_errors(layers.surface, t_surface,
                                          mask=(t_ids > 0) & (layers.building_ids > 0),
                                          jumps=jumps)  # fmt: skip
            if "rmse_m" in roofs:
                h["rmse_on_both_m"] = roofs["rmse_m"]
                h["rmse_on_both_off_jumps_m"] = roofs["rmse_off_jumps_m"]
            share = metrics.error_share_off_jumps(layers.surface, t_surface, t_ids > 0,
                                                  layers.building_ids == 0, jumps)  # fmt: skip
            if share is not None:
                h["missed_share_off_jumps"] = share
    rows = per_building(run, truth, layers)
    m["buildings"] = building_summary(rows)
    face_error = None
    if run.kind == "model":
        if truth.mesh is not None and run.buildings:
            m["surface"], face_error = surface_metrics(run, truth, options)
        m["complexity"] = metrics.complexity(
            [len(b.triangles) for b in run.buildings],
            [is_watertight(b.vertices, b.triangles) for b in run.buildings],
        )
        if layers.normals is not None and truth.roof_normals is not None:
            both = np.isfinite(layers.normals[..., 2]) & np.isfinite(truth.roof_normals[..., 2])
            if both.any():
                ang = metrics.plane_angles_deg(layers.normals[both], truth.roof_normals[both])
                m["roofs"] = {
                    "plane_angle_median_deg": float(np.median(ang)),
                    "cells": int(both.sum()),
                }
        m["regularity"] = {
            **metrics.outline_regularity([_footprint(b) for b in run.buildings]),
            **metrics.symmetric_plane_pairs(
                [[p["normal"] for p in b.record.get("planes") or []] for b in run.buildings]
            ),
        }
        texture = texture_costs(run, truth)
        if texture:
            m["texture"] = texture
    if run.kind == "fusion":
        if truth.dsm is not None:
            d = metrics.height_errors(layers.dsm, truth.dsm)
            m["dsm"] = {k: d[k] for k in DSM_KEYS if k in d}
        if layers.ortho is not None and truth.ortho is not None:
            both = (layers.ortho.sum(-1) > 0) & np.isfinite(layers.dsm)
            o = metrics.colour_mae(layers.ortho, truth.ortho, both)
            if o:
                m["ortho"] = {"mae": o["mean"], "per_channel": [o["r"], o["g"], o["b"]]}
    c = metrics.cost(run.record.get("stages", {}))
    if c:
        m["cost"] = c
    return Evaluation(_drop_empty(m), rows, layers, face_error)


def per_building(run: Run, truth: Truth, layers: RunLayers) -> list[dict]:
    """One row per true building: its truth, the model building covering most of it,
    and the errors over its cells."""
    t_ids = truth.building_ids
    if t_ids is None:
        return []
    ground = truth.dtm
    true_h = model_h = {}
    if ground is not None and truth.building_surface is not None:
        true_h = metrics.building_heights(truth.building_surface, ground, t_ids)
        model_h = metrics.building_heights(layers.surface, ground, t_ids)
    err_pct = metrics.height_error_pct(model_h, true_h)
    rows = []
    for k, window in building_windows(t_ids):
        cells = t_ids[window] == k
        row = {"id": k, "area_m2": float(cells.sum() * truth.grid.gsd**2)}
        rec = truth.buildings.get(k, {})
        if "roof_type" in rec:
            row["roof_type_true"] = rec["roof_type"]
            also = metrics.indistinguishable_roof_types(
                rec["roof_type"], rec.get("wings", []), truth.grid.gsd
            ) - {rec["roof_type"]}
            if also:
                row["roof_type_true_also"] = sorted(also)
        if k in true_h:
            row["height_true_m"] = true_h[k]
            row["height_model_m"] = model_h.get(k, 0.0)
            row["height_error_pct"] = err_pct[k]
        covered = layers.building_ids[window][cells]
        row["covered_fraction"] = float(np.mean(covered > 0))
        if truth.building_surface is not None:
            e = layers.surface[window][cells] - truth.building_surface[window][cells]
            e = e[np.isfinite(e)]
            if len(e):
                row["rmse_m"] = float(np.sqrt(np.mean(e**2)))
        if run.kind == "model" and (covered > 0).any():
            j = int(np.bincount(covered[covered > 0]).argmax())
            b = run.buildings[j - 1]
            row["model_id"] = b.id
            row["faces"] = len(b.triangles)
            for key in ("roof_type", "seam_cost", "seam_cost_projective"):
                if key in b.record:
                    row[key] = b.record[key]
            if layers.normals is not None and truth.roof_normals is not None:
                model_n, true_n = layers.normals[window], truth.roof_normals[window]
                both = cells & np.isfinite(model_n[..., 2]) & np.isfinite(true_n[..., 2])
                if both.any():
                    ang = metrics.plane_angles_deg(model_n[both], true_n[both])
                    row["plane_angle_median_deg"] = float(np.median(ang))
        rows.append(row)
    return rows


def building_windows(ids: np.ndarray):
    """Each building id > 0 of ``ids`` (H, W) in increasing order, with the rows and
    columns (two slices) of its bounding box: a building's cells are then looked for in its
    box, not over the whole grid (a city's grid holds thousands of buildings)."""
    labels, index = np.unique(ids, return_inverse=True)
    shift = int(labels[0] != 0)  # index 0 is find_objects' background: the id 0 only
    for i, window in enumerate(ndimage.find_objects(index.reshape(ids.shape) + shift)):
        k = int(labels[i + 1 - shift])
        if k > 0 and window is not None:
            yield k, window


def building_summary(rows: list[dict], min_area_m2: float = 50.0) -> dict:
    """The ``buildings`` group: true buildings of at least ``min_area_m2`` that less than
    half of is building in the run (``missed_over_50m2``), median and mean |height error|
    in percent, overall and per true roof type, and roof-type accuracy over the true
    buildings a model building covers (with ``roof_types_unresolvable``: how many of them
    the grid cannot tell from another type, which counts too)."""
    out = {}
    big = [r for r in rows if r["area_m2"] >= min_area_m2]
    if big:
        out["missed_over_50m2"] = sum(r["covered_fraction"] < 0.5 for r in big)
    err = [r["height_error_pct"] for r in rows if "height_error_pct" in r]
    if err:
        s = metrics.height_error_summary(err)
        out["height_error_pct_median"] = s["median"]
        out["height_error_pct_mean"] = s["mean"]
        groups: dict[str, list[float]] = {}
        for r in rows:
            if "height_error_pct" in r and "roof_type_true" in r:
                groups.setdefault(r["roof_type_true"], []).append(r["height_error_pct"])
        if groups:
            out["height_error_pct_by_roof_type"] = {
                k: metrics.height_error_summary(v) for k, v in sorted(groups.items())
            }
    typed = [r for r in rows if "roof_type" in r and "roof_type_true" in r]
    if typed:
        acc = metrics.roof_type_accuracy(
            [r["roof_type"] for r in typed],
            [r["roof_type_true"] for r in typed],
            [{r["roof_type_true"], *r.get("roof_type_true_also", [])} for r in typed],
        )
        out["roof_type_accuracy"] = acc["roof_type_accuracy"]
        out["roof_type_confusion"] = acc["confusion"]
        out["roof_types_unresolvable"] = sum("roof_type_true_also" in r for r in typed)
    return out


def surface_metrics(run: Run, truth: Truth, options: EvaluationOptions) -> tuple[dict, np.ndarray]:
    """Mean and maximum (Hausdorff) distances between the run's building meshes and the
    true buildings, and the distance of each model face's centre to the truth (for the
    error renders)."""
    rng = np.random.default_rng(options.seed)
    vertices, triangles, _ = stacked_meshes(run)
    origin = truth.mesh.vertices.mean(axis=0)  # float32 ray casting near the origin
    model = (vertices - origin, triangles)
    true = (truth.mesh.vertices - origin, truth.mesh.triangles)
    samples = []
    for v, t in (model, true):
        n = int(
            min(options.max_samples, max(1000, triangle_areas(v, t).sum() * options.samples_per_m2))
        )
        samples.append(sample_surface(v, t, n, rng)[0])
    true_scene = raycasting_scene(*true)
    d_model = unsigned_distance(true_scene, samples[0])
    d_true = unsigned_distance(raycasting_scene(*model), samples[1])
    out = metrics.surface_distances(samples[0], d_model, samples[1], d_true)
    centres = model[0][model[1]].mean(axis=1)
    return out, unsigned_distance(true_scene, centres)


def texture_costs(run: Run, truth: Truth) -> dict:
    """The ``texture`` group: the seam costs recomputed from the run's textured meshes
    and the scene's views (:func:`~workbench.texture_seams.recomputed_seam_costs`), with
    the run's own figures under ``reported``; without views to measure with, the run's
    own figures (``seam_cost``, ``seam_cost_projective``, ``seam_cost_greedy``: its
    record's, else the mean over its buildings) and ``source: "run"``."""
    rec = run.record.get("texture", {})
    reported = {}
    for key in ("seam_cost", "seam_cost_projective", "seam_cost_greedy"):
        if isinstance(rec, dict) and key in rec:
            reported[key] = float(rec[key])
        else:
            vals = [float(b.record[key]) for b in run.buildings if key in b.record]
            if vals:
                reported[key] = float(np.mean(vals))
    files = _obj_files(run)
    textured = (t for t in map(read_textured_building, files) if t is not None)
    measured = {}
    if files and truth.views:  # read one building at a time: a city's atlases are many
        vertices, triangles, _ = stacked_meshes(run)
        measured = recomputed_seam_costs(
            textured, [v.camera for v in truth.views], SceneImages(truth.views),
            raycasting_scene(vertices, triangles),
        )  # fmt: skip
    if not measured:
        return {**reported, "source": "run"} if reported else {}
    return {**measured, "source": "recomputed", "reported": reported}


def _obj_files(run: Run) -> list:
    return [p for b in run.buildings if (p := run.folder / "buildings" / f"{b.id}.obj").exists()]


def _drop_empty(d: dict) -> dict:
    return {k: v for k, v in d.items() if not (isinstance(v, dict) and not v)}


def _footprint(b):
    """A model building's footprint (model.json's GeoJSON), None without one."""
    from shapely.geometry import shape

    fp = b.record.get("footprint")
    return shape(fp) if fp else None
