"""Score one run against the truth: every metric of metrics.json, per building, with maps.

A run is first seen on the truth's grid (:class:`RunOnGrid`): its surface, its buildings
and, for models, the roof normals, all by casting vertical rays through its meshes. The
metrics are then the same plain functions of :mod:`workbench.metrics` for every method.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from . import metrics
from .errors import InputError
from .meshes import concatenate_meshes, is_watertight, sample_surface, triangle_areas
from .raster import Grid, check_class_codes, raster_header
from .raycast import raycasting_scene, unsigned_distance
from .runs import Run
from .texture_seams import SceneImages, read_textured_building, recomputed_seam_costs
from .tiled_regions import TiledRegions
from .truth import TopDown, Truth, TruthSource, read_on_grid

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
    window_cells : the grid is scored in windows of this many cells a side, so that
        memory follows the window, not the grid (the figures do not depend on it).
    """

    tolerance_m: float = 1.0
    min_object_area_m2: float = 5.0
    samples_per_m2: float = 4.0
    max_samples: int = 400_000
    max_error_m: float = 2.0
    seed: int = 0
    window_cells: int = 512


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
    overview: the run's surface, building ids and classes at every
    :func:`picture_stride`-th cell of the grid, for the report's maps; face_error: (T,)
    distance of each model face's centre to the true buildings, metres, in the order of
    the run's buildings (models with a true mesh only)."""

    metrics: dict
    buildings: list[dict]
    overview: RunLayers
    face_error: np.ndarray | None = None


class RunOnGrid:
    """A run seen on the cells of the evaluation grid, a window at a time (see
    :class:`RunLayers`): its rasters are read and its meshes cast only where asked.

    Parameters
    ----------
    run : Run
    grid, crs
        The evaluation grid and the truth's CRS (a raster of the run in another is
        refused).
    options : EvaluationOptions
        ``min_object_area_m2`` and ``window_cells``: a fusion run's buildings are the
        regions of its building class (:class:`~workbench.tiled_regions.TiledRegions`
        over the tiles of ``window_cells``), found by a first pass over those tiles.
    """

    def __init__(self, run: Run, grid: Grid, crs, options: EvaluationOptions):
        self.run, self.grid = run, grid
        self.cls_path = run.raster("class")
        self.headers = {}
        for name in ("class", "dsm", "ortho", "dtm"):
            path = run.raster(name)
            if path is not None:
                src, _, own = raster_header(path, name)
                if own is not None and crs is not None and own != crs:
                    raise InputError(path, "crs", f"{own} differs from the truth's CRS")
                self.headers[path] = src
        self.regions = self.top_down = None
        if run.kind == "fusion":
            min_cells = options.min_object_area_m2 / grid.gsd**2
            self.regions = TiledRegions(grid.tiles(options.window_cells), self._building_mask,
                                        min_cells)  # fmt: skip
        else:
            vertices, triangles, owner = stacked_meshes(run)
            self.top_down = TopDown(vertices, triangles, owner, grid)

    def _read(self, path, rows: slice, cols: slice, band: int | None = 0) -> np.ndarray:
        data = read_on_grid(path, self.grid.window(rows, cols), header=self.headers[path])
        return data if band is None else data[band]

    def _classes(self, rows: slice, cols: slice) -> np.ndarray | None:
        if self.cls_path is None:
            return None
        return check_class_codes(self._read(self.cls_path, rows, cols), self.cls_path, "class")

    def _building_mask(self, rows: slice, cols: slice, cls: np.ndarray | None = None):
        cls = self._classes(rows, cols) if cls is None else cls
        if cls is None:
            return np.zeros((rows.stop - rows.start, cols.stop - cols.start), bool)
        return cls == 4

    def layers(self, rows: slice, cols: slice, ground: np.ndarray | None,
               with_ids: bool = True) -> RunLayers:  # fmt: skip
        """The run on the cells ``rows`` x ``cols``; ``ground`` is the truth's DTM there
        (a model's ground where it has none of its own). A fusion run's building ids
        (``with_ids``) are known on the tiles of ``window_cells`` only; elsewhere pass
        ``with_ids=False`` and they are None."""
        cls = self._classes(rows, cols)
        shape = (rows.stop - rows.start, cols.stop - cols.start)
        if self.run.kind == "fusion":
            dsm = self._read(self.run.raster("dsm"), rows, cols).astype(np.float64)
            ortho = None
            if self.run.raster("ortho"):
                ortho = np.moveaxis(self._read(self.run.raster("ortho"), rows, cols, None), 0, -1)
            ids = None
            if with_ids:
                ids = self.regions(rows, cols, self._building_mask(rows, cols, cls))
            bs = np.where(ids > 0, dsm, np.nan) if ids is not None else None
            return RunLayers(dsm, ids, bs, cls=cls, ortho=ortho, dsm=dsm)
        ids, building_surface, normals = self.top_down.window(rows, cols)
        ground = np.full(shape, np.nan) if ground is None else ground
        if self.run.raster("dtm"):
            # the run's own ground; where it has none, the truth's, so that a building cell
            # the model misses is always scored (a hole in its ground must not hide it)
            own = self._read(self.run.raster("dtm"), rows, cols).astype(np.float64)
            ground = np.where(np.isfinite(own), own, ground)
        surface = np.where(ids > 0, building_surface, ground)
        return RunLayers(surface, ids, building_surface, normals=normals, cls=cls)


def stacked_meshes(run: Run) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All building meshes of a model run as one, with each triangle's 1-based owner."""
    return concatenate_meshes([(b.vertices, b.triangles) for b in run.buildings])


def evaluate(run: Run, truth: Truth | TruthSource,
             options: EvaluationOptions | None = None) -> Evaluation:  # fmt: skip
    """Every metric the truth and the run allow; groups without data are left out.

    The grid is scored a window of ``options.window_cells`` at a time (the truth and the
    run read there only), the buildings a group at a time, so that memory follows the
    window, not the grid: the figures are the same whatever the window.
    """
    options = options or EvaluationOptions()
    on_grid = RunOnGrid(run, truth.grid, truth.crs, options)
    scores = GridScores(run, truth.grid, picture_stride(truth.grid), options.tolerance_m)
    for rows, cols in truth.grid.tiles(options.window_cells):
        scores.add(truth, rows, cols, on_grid)
    m: dict = {"method": run.method, "kind": run.kind, **scores.metrics()}
    rows = per_building(run, truth, on_grid, scores, options)
    m["buildings"] = building_summary(rows)
    face_error = None
    if run.kind == "model":
        if truth.mesh is not None and run.buildings:
            m["surface"], face_error = surface_metrics(run, truth, options)
        m["complexity"] = metrics.complexity(
            [len(b.triangles) for b in run.buildings],
            [is_watertight(b.vertices, b.triangles) for b in run.buildings],
        )
        m["regularity"] = {
            **metrics.outline_regularity([_footprint(b) for b in run.buildings]),
            **metrics.symmetric_plane_pairs(
                [[p["normal"] for p in b.record.get("planes") or []] for b in run.buildings]
            ),
        }
        texture = texture_costs(run, truth)
        if texture:
            m["texture"] = texture
    c = metrics.cost(run.record.get("stages", {}))
    if c:
        m["cost"] = c
    m = _drop_empty({k: m[k] for k in METRIC_ORDER if k in m})
    return Evaluation(m, rows, scores.overview, face_error)


METRIC_ORDER = ("method", "kind", "classification", "footprint_2d", "volume_3d",
                "volume_3d_tolerant", "height", "buildings", "surface", "complexity", "roofs",
                "regularity", "texture", "dsm", "ortho", "cost")  # fmt: skip

PICTURE_CELLS = 2048  # the longest side of the report's maps


def picture_stride(grid: Grid, longest: int = PICTURE_CELLS) -> int:
    """Every how many cells the report's maps take one, so that they are at most
    ``longest`` cells a side."""
    return max(1, -(-max(grid.shape) // longest))


def overview_grid(grid: Grid, stride: int) -> Grid:
    """The grid of every ``stride``-th cell of ``grid`` (cells ``stride`` times larger)."""
    return Grid(grid.xmin, grid.ymax, grid.gsd * stride, -(-grid.width // stride),
                -(-grid.height // stride))  # fmt: skip


def strided_into(out: np.ndarray | None, a: np.ndarray, rows: slice, cols: slice, stride: int,
                 shape: tuple[int, int]) -> np.ndarray:  # fmt: skip
    """Put the window ``rows`` x ``cols`` of a grid, ``a`` ((h, w, ...)), at its place
    in ``out``, the grid's every ``stride``-th cell (of ``shape``; made, NaN or 0, when
    None); returns ``out``."""
    if out is None:
        fill = np.nan if np.issubdtype(a.dtype, np.floating) else 0
        out = np.full(shape + a.shape[2:], fill, a.dtype)
    r0, c0 = -rows.start % stride, -cols.start % stride  # the window's first cell kept
    i, j = (rows.start + r0) // stride, (cols.start + c0) // stride
    sub = a[r0::stride, c0::stride]
    out[i : i + sub.shape[0], j : j + sub.shape[1]] = sub
    return out


# the truth's layers the report draws (the ground under the renders included)
PICTURED = ("ortho", "cls", "dsm", "dtm", "building_ids", "building_surface")


def truth_overview(truth, stride: int, window_cells: int = 512) -> Truth:
    """The truth's rasters at every ``stride``-th cell (a :class:`Truth` on
    :func:`overview_grid`), read a window at a time: the report's maps of a city."""
    grid = overview_grid(truth.grid, stride)
    out = Truth(grid, truth.crs, buildings=truth.buildings, mesh=truth.mesh,
                views=truth.views, sources=truth.sources)  # fmt: skip
    for rows, cols in truth.grid.tiles(window_cells):
        t = truth.window(rows, cols)
        for name in PICTURED:
            if getattr(t, name) is not None:
                setattr(out, name, strided_into(getattr(out, name), getattr(t, name), rows, cols,
                                                stride, grid.shape))  # fmt: skip
    return out


class GridScores:
    """The sums the grid's metrics are made of, added up window by window, and the
    run's maps for the report (every ``stride``-th cell).

    Parameters
    ----------
    run : Run
    grid : Grid
        The evaluation grid.
    stride : int
        Of the maps in :attr:`overview`.
    tolerance_m : float
        Of ``volume_3d_tolerant``.
    """

    def __init__(self, run: Run, grid: Grid, stride: int, tolerance_m: float):
        self.kind, self.stride, self.tolerance = run.kind, stride, tolerance_m
        self.confusion, self.excluded, self.classes = np.zeros((4, 4), np.int64), 0, False
        self.footprint = None  # [tp, fp, fn]
        self.objects = None  # id_counts of the true ids and of the run's
        self.volume = {0: np.zeros(3), 1: np.zeros(3)}
        self.height, self.roofs = metrics.HeightErrorSums(), metrics.HeightErrorSums()
        self.dsm, self.dsm_known = metrics.HeightErrorSums(), False
        self.colour = [0, np.zeros(3)]
        self.angles = metrics.angle_median()
        self.per_true = None  # id_counts of the true ids: covered, squared error, errors
        self.covering = None  # id_counts of (true id, model id) pairs
        self.boxes: dict[int, list[int]] = {}  # true id: [row0, row1, col0, col1]
        self.has_surface = self.has_volume = False
        self.shape = overview_grid(grid, stride).shape
        self.overview = RunLayers(None, None, None)
        self.n_models = len(run.buildings) if run.kind == "model" else 0

    def add(self, truth, rows: slice, cols: slice, on_grid: RunOnGrid) -> None:
        """Score the window ``rows`` x ``cols`` of the grid."""
        H, W = truth.grid.shape
        # the truth one cell wider: its height jumps look at the cells around
        halo = (slice(max(rows.start - 1, 0), min(rows.stop + 1, H)),
                slice(max(cols.start - 1, 0), min(cols.stop + 1, W)))  # fmt: skip
        wide = truth.window(*halo)
        inner = (slice(rows.start - halo[0].start, rows.stop - halo[0].start),
                 slice(cols.start - halo[1].start, cols.stop - halo[1].start))  # fmt: skip
        t = wide.window(*inner)
        run = on_grid.layers(rows, cols, t.dtm)
        if run.cls is not None and t.cls is not None:
            conf, excluded = metrics.class_confusion(run.cls, t.cls, exclude=t.training)
            self.confusion += conf
            self.excluded += excluded
            self.classes = True
        t_ids, ids = t.building_ids, run.building_ids
        if t_ids is not None:
            self._buildings(t, run, rows, cols)
        if t.building_surface is not None and t.dtm is not None:
            pred_h, true_h = run.building_surface - t.dtm, t.building_surface - t.dtm
            self.has_volume = True
            for k, tol in ((0, 0.0), (1, self.tolerance)):
                v = metrics.volume_3d(pred_h, true_h, tol)
                self.volume[k] += [v["vtp"], v["vfp"], v["vfn"]]
        if t.building_surface is not None:
            self.has_surface = True
            jumps = metrics.height_jumps(wide.building_surface)[inner]
            self.height.add(run.surface, t.building_surface, t_ids > 0, jumps, ids == 0)
            self.roofs.add(run.surface, t.building_surface, (t_ids > 0) & (ids > 0), jumps)
        if run.normals is not None and t.roof_normals is not None:
            both = np.isfinite(run.normals[..., 2]) & np.isfinite(t.roof_normals[..., 2])
            self.angles.add(metrics.plane_angles_deg(run.normals[both], t.roof_normals[both]))
        if self.kind == "fusion" and t.dsm is not None:
            self.dsm_known = True
            self.dsm.add(run.dsm, t.dsm, None, metrics.height_jumps(wide.dsm)[inner])
            if run.ortho is not None and t.ortho is not None:
                n, sums = metrics.colour_sums(
                    run.ortho, t.ortho, (run.ortho.sum(-1) > 0) & np.isfinite(run.dsm)
                )
                self.colour[0] += n
                self.colour[1] += sums
        self._picture(run, rows, cols)

    def _buildings(self, t: Truth, run: RunLayers, rows: slice, cols: slice) -> None:
        t_ids, ids = t.building_ids, run.building_ids
        f = metrics.footprint_2d(ids > 0, t_ids > 0)
        counts = np.array([f["tp"], f["fp"], f["fn"]])
        self.footprint = counts if self.footprint is None else self.footprint + counts
        true_objects, run_objects = (
            metrics.id_counts(t_ids, ids > 0),
            metrics.id_counts(ids, t_ids > 0),
        )
        if self.objects is not None:
            true_objects = metrics.add_id_counts(self.objects[0], true_objects)
            run_objects = metrics.add_id_counts(self.objects[1], run_objects)
        self.objects = (true_objects, run_objects)
        if t.building_surface is not None:
            e = run.surface - t.building_surface
            known = np.isfinite(e)
            per = metrics.id_counts(t_ids, ids > 0, np.where(known, e, 0.0) ** 2, known)
        else:
            per = metrics.id_counts(t_ids, ids > 0)
        self.per_true = per if self.per_true is None else metrics.add_id_counts(self.per_true, per)
        if self.kind == "model":
            both = (t_ids > 0) & (ids > 0)
            pairs = metrics.id_counts(t_ids[both] * (self.n_models + 1) + ids[both])
            if self.covering is not None:
                pairs = metrics.add_id_counts(self.covering, pairs)
            self.covering = pairs
        for k, (r, c) in building_windows(t_ids):
            box = [r.start + rows.start, r.stop + rows.start, c.start + cols.start,
                   c.stop + cols.start]  # fmt: skip
            old = self.boxes.setdefault(k, box)
            old[:] = [min(old[0], box[0]), max(old[1], box[1]), min(old[2], box[2]),
                      max(old[3], box[3])]  # fmt: skip

    def _picture(self, run: RunLayers, rows: slice, cols: slice) -> None:
        for name in ("surface", "building_ids", "cls"):
            a, into = getattr(run, name), getattr(self.overview, name)
            if a is not None:
                into = strided_into(into, a, rows, cols, self.stride, self.shape)
                setattr(self.overview, name, into)

    def metrics(self) -> dict:
        """The grid's groups of metrics.json (those the data allow)."""
        m = {}
        if self.classes:
            c = metrics.classification_scores(self.confusion, self.excluded)
            if "overall_accuracy" in c:
                m["classification"] = c
        if self.footprint is not None:
            tp, fp, fn = (int(x) for x in self.footprint)
            f = {"tp": tp, "fp": fp, "fn": fn, **metrics.detection_ratios(tp, fp, fn)}
            f["objects"] = metrics.objects_from_counts(*self.objects)
            m["footprint_2d"] = f
        if self.has_volume:
            for key, k, tol in (("volume_3d", 0, 0.0), ("volume_3d_tolerant", 1, self.tolerance)):
                vtp, vfp, vfn = (float(x) for x in self.volume[k])
                m[key] = {"vtp": vtp, "vfp": vfp, "vfn": vfn, "tolerance_m": tol,
                          **metrics.detection_ratios(vtp, vfp, vfn)}  # fmt: skip
        if self.has_surface:
            h = self.height.result()
            if "rmse_m" in h:
                m["height"] = h
                # the roofs' own error: where both the run and the truth have a building
                # (the DEM-blocks paper's altimetric RMSE), the outlines' misses apart
                roofs = self.roofs.result()
                if "rmse_m" in roofs:
                    h["rmse_on_both_m"] = roofs["rmse_m"]
                    h["rmse_on_both_off_jumps_m"] = roofs["rmse_off_jumps_m"]
                share = self.height.part_share()
                if share is not None:
                    h["missed_share_off_jumps"] = share
        if self.angles.n:
            m["roofs"] = {"plane_angle_median_deg": self.angles.median(), "cells": self.angles.n}
        if self.dsm_known:
            d = self.dsm.result()
            m["dsm"] = {k: d[k] for k in DSM_KEYS if k in d}
            o = metrics.colour_scores(*self.colour)
            if o:
                m["ortho"] = {"mae": o["mean"], "per_channel": [o["r"], o["g"], o["b"]]}
        return m


def per_building(run: Run, truth, on_grid: RunOnGrid, scores: GridScores,
                 options: EvaluationOptions) -> list[dict]:  # fmt: skip
    """One row per true building: its truth, the model building covering most of it,
    and the errors over its cells.

    What adds up (its cells, how many the run covers, its squared errors) comes from
    ``scores``; its height and roof angles, which are quantiles of its cells, are read
    a group of buildings at a time, each group the box of the buildings whose box's
    centre falls in one tile of ``window_cells``.
    """
    if scores.per_true is None:
        return []
    t_ids, sums = scores.per_true
    gsd = truth.grid.gsd
    cover = _covering_model(scores) if run.kind == "model" else {}
    quantiles = {}
    for window, group in _building_groups(scores.boxes, options.window_cells):
        t = truth.window(*window)
        layers = on_grid.layers(*window, t.dtm, with_ids=False)
        quantiles.update(_building_quantiles(t, layers, group))
    rows = []
    for k, s in zip(t_ids.tolist(), sums, strict=True):
        row = {"id": k, "area_m2": float(s[0] * gsd**2)}
        rec = truth.buildings.get(k, {})
        if "roof_type" in rec:
            row["roof_type_true"] = rec["roof_type"]
            also = metrics.indistinguishable_roof_types(rec["roof_type"], rec.get("wings", []),
                                                        gsd) - {rec["roof_type"]}  # fmt: skip
            if also:
                row["roof_type_true_also"] = sorted(also)
        q = quantiles.get(k, {})
        if "height_true_m" in q:
            row["height_true_m"] = q["height_true_m"]
            row["height_model_m"] = q.get("height_model_m", 0.0)
            err = metrics.height_error_pct({k: row["height_model_m"]}, {k: row["height_true_m"]})
            if k in err:
                row["height_error_pct"] = err[k]
        row["covered_fraction"] = float(s[1] / s[0])
        if len(s) > 2 and s[3] > 0:
            row["rmse_m"] = float(np.sqrt(s[2] / s[3]))
        if k in cover:
            b = run.buildings[cover[k] - 1]
            row["model_id"] = b.id
            row["faces"] = len(b.triangles)
            for key in ("roof_type", "seam_cost", "seam_cost_projective"):
                if key in b.record:
                    row[key] = b.record[key]
            if "plane_angle_median_deg" in q:
                row["plane_angle_median_deg"] = q["plane_angle_median_deg"]
        rows.append(row)
    return rows


def _covering_model(scores: GridScores) -> dict[int, int]:
    """{true id: the model building (1-based) covering most of its cells, the first of
    equals}."""
    if scores.covering is None:
        return {}
    keys, sums = scores.covering
    n = scores.n_models + 1
    t, mdl, count = keys // n, keys % n, sums[:, 0]
    order = np.lexsort((mdl, -count, t))  # per true id: most cells first, then lowest id
    t, mdl = t[order], mdl[order]
    first = np.r_[True, t[1:] != t[:-1]]
    return dict(zip(t[first].tolist(), mdl[first].tolist(), strict=True))


def _building_groups(boxes: dict[int, list[int]], size: int):
    """((rows, cols), ids): the buildings whose box's centre is in one tile of ``size``
    cells, and the box of all their boxes."""
    groups: dict[tuple[int, int], list[int]] = {}
    for k, (r0, r1, c0, c1) in boxes.items():
        groups.setdefault((((r0 + r1) // 2) // size, ((c0 + c1) // 2) // size), []).append(k)
    for _, ids in sorted(groups.items()):
        b = np.array([boxes[k] for k in ids])
        window = (slice(int(b[:, 0].min()), int(b[:, 1].max())),
                  slice(int(b[:, 2].min()), int(b[:, 3].max())))  # fmt: skip
        yield window, ids


def _building_quantiles(t: Truth, layers: RunLayers, ids: list[int]) -> dict[int, dict]:
    """{id: {height_true_m, height_model_m, plane_angle_median_deg}} of the true
    buildings ``ids`` over their cells in the window of ``t`` (which holds them whole)."""
    group = np.where(np.isin(t.building_ids, ids), t.building_ids, 0)
    out: dict[int, dict] = {k: {} for k in ids}
    if t.dtm is not None and t.building_surface is not None:
        true_h = metrics.building_heights(t.building_surface, t.dtm, group)
        model_h = metrics.building_heights(layers.surface, t.dtm, group)
        for k, h in true_h.items():
            out[k]["height_true_m"] = h
            if k in model_h:
                out[k]["height_model_m"] = model_h[k]
    if layers.normals is not None and t.roof_normals is not None:
        known = np.isfinite(layers.normals[..., 2]) & np.isfinite(t.roof_normals[..., 2])
        both = (group > 0) & known
        ang = metrics.plane_angles_deg(layers.normals[both], t.roof_normals[both])
        for k, a in metrics.values_by_id(group[both], ang):
            out[k]["plane_angle_median_deg"] = float(np.median(a))
    return out


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
