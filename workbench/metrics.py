"""Metrics shared by every method, each a plain function on arrays.

Class codes: 1 ground, 2 grass, 3 tree, 4 building; 0 is no data and never scored.
"""

from __future__ import annotations

import numpy as np

CLASS_NAMES = {1: "ground", 2: "grass", 3: "tree", 4: "building"}
JUMP_M = 1.0  # a step between neighbouring cells of the true surface that is a wall


def classification(pred: np.ndarray, truth: np.ndarray, exclude: np.ndarray | None = None) -> dict:
    """Accuracy of a class map against the truth (the super-pixel paper's Table 1).

    Parameters
    ----------
    pred, truth : (H, W) int
        Class codes; cells where either is 0 are not scored.
    exclude : (H, W) bool, optional
        Cells not scored either: the training strokes, where a classifier trained on
        them is right by construction.

    Returns
    -------
    dict with ``overall_accuracy`` (correct / scored), ``per_class_accuracy`` (per true
    class: correct / true cells of that class, for classes present in the truth),
    ``mean_class_accuracy`` (their mean), ``building_accuracy`` (building against
    everything else, the paper's two-class figure), ``confusion`` (rows truth 1-4,
    columns prediction 1-4), ``scored_cells`` and ``excluded_cells``.
    """
    return classification_scores(*class_confusion(pred, truth, exclude))


def class_confusion(
    pred: np.ndarray, truth: np.ndarray, exclude: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """The counts :func:`classification` is made of, which add up over the windows of a
    grid: (4, 4) int64 confusion (rows truth 1-4, columns prediction 1-4) and the number
    of excluded cells."""
    m = (pred > 0) & (truth > 0)
    excluded = 0
    if exclude is not None:
        excluded = int(np.count_nonzero(m & exclude))
        m &= ~exclude
    p, t = pred[m].astype(np.int64), truth[m].astype(np.int64)
    conf = np.bincount((t - 1) * 4 + np.clip(p, 1, 4) - 1, minlength=16).reshape(4, 4)
    return conf, excluded


def classification_scores(conf: np.ndarray, excluded: int) -> dict:
    """:func:`classification`'s figures from its counts (:func:`class_confusion`)."""
    conf = np.asarray(conf, np.int64)
    total = int(conf.sum())
    out = {"scored_cells": total, "excluded_cells": int(excluded)}
    if not total:
        return out
    out["overall_accuracy"] = float(np.trace(conf) / total)
    per = {CLASS_NAMES[k + 1]: float(conf[k, k] / conf[k].sum()) for k in range(4) if conf[k].sum()}
    out["per_class_accuracy"] = per
    out["mean_class_accuracy"] = float(np.mean(list(per.values())))
    # building against everything else: the building/building and other/other blocks
    out["building_accuracy"] = float((conf[3, 3] + conf[:3, :3].sum()) / total)
    out["confusion"] = conf.tolist()
    return out


class RoundedMedian:
    """The median of non-negative values rounded to ``step``, kept as counts: a city's
    grid has hundreds of millions of cells, whose values need not be held to find it.

    Values above ``top`` are kept as they are (they are few: errors of more than 100 m).

    Parameters
    ----------
    step, top : float
        Rounding and the largest value counted, in the values' unit.
    """

    def __init__(self, step: float, top: float):
        self.step = step
        self.counts = np.zeros(int(round(top / step)) + 1, np.int64)
        self.above: list[np.ndarray] = []

    def add(self, values: np.ndarray) -> None:
        v = np.asarray(values, np.float64).ravel()
        k = np.rint(v / self.step)
        high = k >= len(self.counts)
        if high.any():
            self.above.append(v[high])
        self.counts += np.bincount(k[~high].astype(np.int64), minlength=len(self.counts))

    @property
    def n(self) -> int:
        return int(self.counts.sum()) + sum(len(a) for a in self.above)

    def median(self) -> float | None:
        """The median (the mean of the two middle values for an even count), None
        without values."""
        n = self.n
        if not n:
            return None
        cum = np.cumsum(self.counts)
        above = np.sort(np.concatenate(self.above)) if self.above else np.zeros(0)

        def kth(i: int) -> float:
            if i < cum[-1]:
                return float(np.searchsorted(cum, i, side="right") * self.step)
            return float(above[i - cum[-1]])

        # to the rounding's digits and one more (the mean of two middles), not k * step's
        digits = int(np.ceil(-np.log10(self.step))) + 1
        return round((kth((n - 1) // 2) + kth(n // 2)) / 2, digits)


HEIGHT_ROUNDING_M = 1e-4  # medians of height errors: to a tenth of a millimetre
ANGLE_ROUNDING_DEG = 1e-3


def height_median() -> RoundedMedian:
    """A :class:`RoundedMedian` for absolute height errors in metres."""
    return RoundedMedian(HEIGHT_ROUNDING_M, 100.0)


def angle_median() -> RoundedMedian:
    """A :class:`RoundedMedian` for angles in degrees."""
    return RoundedMedian(ANGLE_ROUNDING_DEG, 180.0)


def height_jumps(truth: np.ndarray, step: float = JUMP_M) -> np.ndarray:
    """(H, W) bool: cells on either side of a jump in the true surface.

    A cell is on a jump when one of its 8 neighbours differs from it by more than
    ``step`` metres, or is unknown while it is known (the outline of a building
    surface that is NaN off buildings). The grid's border is not a jump. Slopes up to
    ``atan(step / diagonal)`` (70 degrees at 0.25 m cells and 1 m) are not jumps.
    """
    t = np.asarray(truth, dtype=np.float64)
    known = np.isfinite(t)
    p = np.pad(t, 1, mode="edge")
    pk = np.pad(known, 1, mode="edge")
    H, W = t.shape
    out = np.zeros((H, W), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == dc == 0:
                continue
            nb = p[1 + dr : 1 + dr + H, 1 + dc : 1 + dc + W]
            nk = pk[1 + dr : 1 + dr + H, 1 + dc : 1 + dc + W]
            with np.errstate(invalid="ignore"):
                out |= known & ((nk & (np.abs(nb - t) > step)) | ~nk)
    return out


def height_errors(
    model: np.ndarray,
    truth: np.ndarray,
    mask: np.ndarray | None = None,
    jumps: np.ndarray | None = None,
) -> dict:
    """Errors of a height raster against the truth, metres.

    Beside a wall the truth read at a cell centre is the wall's height away from the
    truth a few centimetres off: an outline off by 5 cm costs a perfect model more
    than 1 m of RMSE over building cells (``benchmarks/height_floor.py``). The errors
    away from the true surface's jumps are reported beside, so that the surfaces'
    accuracy and the outlines' show apart.

    Parameters
    ----------
    model, truth : (H, W) float
        Heights, NaN where unknown.
    mask : (H, W) bool, optional
        Cells to score (default: every cell where the truth is known).
    jumps : (H, W) bool, optional
        :func:`height_jumps` of ``truth``, when the caller has them already.

    Returns
    -------
    dict with ``rmse_m``, ``mae_m``, ``median_abs_m`` (to :data:`HEIGHT_ROUNDING_M`) over
    cells where both are known, ``valid_fraction``: share of the scored cells where the
    model is known, and ``rmse_off_jumps_m`` and ``jump_fraction``: the RMSE over the
    scored cells off :func:`height_jumps` of the truth, and the share of scored cells on
    them.
    """
    sums = HeightErrorSums()
    sums.add(model, truth, mask, height_jumps(truth) if jumps is None else jumps)
    return sums.result()


class HeightErrorSums:
    """:func:`height_errors` over the windows of a grid: :meth:`add` each window, then
    :meth:`result`. With ``part`` cells given to :meth:`add`, :meth:`part_share` is the
    share of the squared error off the jumps that falls on them."""

    def __init__(self):
        self.scored = self.known = self.on_jumps = self.off_jumps = 0
        self.sq = self.abs = self.sq_off = self.sq_off_part = 0.0
        self.median = height_median()

    def add(self, model: np.ndarray, truth: np.ndarray, mask: np.ndarray | None,
            jumps: np.ndarray, part: np.ndarray | None = None) -> None:  # fmt: skip
        """One window: arrays as for :func:`height_errors`, ``jumps`` required."""
        m = np.isfinite(truth) if mask is None else (mask & np.isfinite(truth))
        ok = m & np.isfinite(model)
        self.scored += int(np.count_nonzero(m))
        self.known += int(np.count_nonzero(ok))
        e = (model[ok] - truth[ok]).astype(np.float64)
        self.sq += float(np.sum(e**2))
        self.abs += float(np.sum(np.abs(e)))
        self.median.add(np.abs(e))
        self.on_jumps += int(np.count_nonzero(ok & jumps))
        off = ok & ~jumps
        self.off_jumps += int(np.count_nonzero(off))
        e2 = np.where(off, (np.asarray(model, np.float64) - truth) ** 2, 0.0)
        self.sq_off += float(e2.sum())
        if part is not None:
            self.sq_off_part += float(e2[part].sum())

    def result(self) -> dict:
        out = {"valid_fraction": float(self.known / max(self.scored, 1))}
        if self.known:
            out.update(
                rmse_m=float(np.sqrt(self.sq / self.known)),
                mae_m=float(self.abs / self.known),
                median_abs_m=self.median.median(),
                jump_fraction=float(self.on_jumps / self.known),
            )
            if self.off_jumps:
                out["rmse_off_jumps_m"] = float(np.sqrt(self.sq_off / self.off_jumps))
        return out

    def part_share(self) -> float | None:
        """Share of the squared error off the jumps on the ``part`` cells (see
        :func:`error_share_off_jumps`), None without error."""
        return float(self.sq_off_part / self.sq_off) if self.sq_off > 0 else None


def error_share_off_jumps(
    model: np.ndarray,
    truth: np.ndarray,
    mask: np.ndarray,
    part: np.ndarray,
    jumps: np.ndarray | None = None,
) -> float | None:
    """Share of the summed squared height error over the ``mask`` cells off the truth's
    jumps (:func:`height_jumps`) that falls on the ``part`` cells: for a model over the
    true building cells and ``part`` the cells it has no building on, how much of its
    ``rmse_off_jumps_m`` its outlines cost rather than its roofs. None without error.

    model, truth : (H, W) float, metres, NaN unknown; mask, part : (H, W) bool; jumps :
    (H, W) bool, :func:`height_jumps` of ``truth`` if the caller has them.
    """
    sums = HeightErrorSums()
    sums.add(model, truth, mask, height_jumps(truth) if jumps is None else jumps, part)
    return sums.part_share()


def colour_mae(model: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """Mean absolute colour error per channel (0-255) over ``mask``.

    Parameters
    ----------
    model, truth : (H, W, 3) arrays
    mask : (H, W) bool
    """
    n, sums = colour_sums(model, truth, mask)
    return colour_scores(n, sums)


def colour_sums(model: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> tuple[int, np.ndarray]:
    """The cells of ``mask`` and the (3,) sums of their absolute colour errors, which
    add up over the windows of a grid (:func:`colour_scores` makes them
    :func:`colour_mae`)."""
    d = np.abs(model[mask].astype(np.float64) - truth[mask].astype(np.float64))
    return int(len(d)), d.sum(axis=0)


def colour_scores(n: int, sums: np.ndarray) -> dict:
    """:func:`colour_mae` from :func:`colour_sums`."""
    if not n:
        return {}
    per = np.asarray(sums) / n
    return {"r": float(per[0]), "g": float(per[1]), "b": float(per[2]), "mean": float(per.mean())}


def footprint_2d(pred: np.ndarray, truth: np.ndarray) -> dict:
    """Pixel-level building detection (the variational paper, section IV.A).

    Parameters
    ----------
    pred, truth : (H, W) bool
        Building cells of the model and of the truth.

    Returns
    -------
    dict with ``completeness`` TP/(TP+FN), ``correctness`` TP/(TP+FP), ``quality``
    TP/(TP+FP+FN), and the cell counts ``tp``, ``fp``, ``fn``; a ratio whose denominator
    is 0 is absent.
    """
    tp = int(np.count_nonzero(pred & truth))
    fp = int(np.count_nonzero(pred & ~truth))
    fn = int(np.count_nonzero(~pred & truth))
    return {"tp": tp, "fp": fp, "fn": fn, **detection_ratios(tp, fp, fn)}


def detection_ratios(tp: float, fp: float, fn: float) -> dict:
    """``completeness`` TP/(TP+FN), ``correctness`` TP/(TP+FP) and ``quality``
    TP/(TP+FP+FN) of counts or volumes; a ratio whose denominator is 0 is absent (the
    counts add up over the windows of a grid, these ratios do not)."""
    out = {}
    for key, den in (("completeness", tp + fn), ("correctness", tp + fp),
                     ("quality", tp + fp + fn)):  # fmt: skip
        if den > 0:
            out[key] = tp / den
    return out


def building_objects(truth_ids: np.ndarray, pred_ids: np.ndarray, min_cover: float = 0.5) -> dict:
    """Object-level building detection.

    A true building is found when at least ``min_cover`` of its cells are model building
    cells; a model building is correct when at least ``min_cover`` of its cells are true
    building cells.

    Parameters
    ----------
    truth_ids, pred_ids : (H, W) int
        Building ids, 0 for no building.

    Returns
    -------
    dict with ``truth_buildings``, ``found``, ``model_buildings``, ``correct``.
    """

    sizes = [id_counts(ids, other > 0) for ids, other in ((truth_ids, pred_ids),
                                                          (pred_ids, truth_ids))]  # fmt: skip
    return objects_from_counts(*sizes, min_cover)


def id_counts(ids: np.ndarray, *weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ids > 0 of ``ids`` (sorted) and, for each, its cells and the sum of each of
    ``weights`` (arrays of ``ids``' shape) over them: (K,) ids and (K, 1 + len(weights))
    float64 sums, which :func:`add_id_counts` adds up over the windows of a grid."""
    m = ids > 0
    labels, inv = np.unique(ids[m], return_inverse=True)
    sums = np.zeros((len(labels), 1 + len(weights)))
    sums[:, 0] = np.bincount(inv, minlength=len(labels))
    for j, w in enumerate(weights, start=1):
        sums[:, j] = np.bincount(inv, weights=np.asarray(w)[m], minlength=len(labels))
    return labels, sums


def add_id_counts(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]):
    """Two :func:`id_counts` results as one."""
    labels, inv = np.unique(np.concatenate([a[0], b[0]]), return_inverse=True)
    sums = np.zeros((len(labels), a[1].shape[1]))
    np.add.at(sums, inv, np.concatenate([a[1], b[1]]))
    return labels, sums


def objects_from_counts(truth: tuple, pred: tuple, min_cover: float = 0.5) -> dict:
    """:func:`building_objects` from the :func:`id_counts` of the true ids weighted by
    the model's building cells and of the model's ids weighted by the true ones."""
    (t_ids, t), (p_ids, p) = truth, pred
    return {
        "truth_buildings": len(t_ids),
        "found": int(np.count_nonzero(t[:, 1] >= min_cover * t[:, 0])),
        "model_buildings": len(p_ids),
        "correct": int(np.count_nonzero(p[:, 1] >= min_cover * p[:, 0])),
    }


def volume_3d(pred_height: np.ndarray, truth_height: np.ndarray, tolerance: float = 0.0) -> dict:
    """Voxel-based 3D completeness, correctness and quality (the variational paper, IV.A).

    Every building cell is a column of voxels from the ground up to its height. The
    paper counts a voxel as true positive when model and truth both hold it at the same
    altitude: in a cell both call building, the columns agree up to the lower of the two
    heights, and the difference is false positive volume (model too high) or false
    negative volume (model too low). With a ``tolerance`` (the workbench's tolerant
    variant, ``volume_3d_tolerant``), a difference up to it counts as agreement.
    Columns of one side only are wholly false positive or false negative. Volumes are in
    cell-metres: multiply by the cell area for cubic metres.

    Parameters
    ----------
    pred_height, truth_height : (H, W) float
        Building height above the (common) ground, metres; 0 or NaN where no building.
    tolerance : float
        Vertical tolerance, metres; 0 is the paper's definition.

    Returns
    -------
    dict with ``completeness`` VTP/(VTP+VFN), ``correctness`` VTP/(VTP+VFP), ``quality``
    VTP/(VTP+VFP+VFN), the volumes ``vtp``, ``vfp``, ``vfn`` and ``tolerance_m``.
    """
    hp = np.clip(np.nan_to_num(pred_height, nan=0.0), 0.0, None).astype(np.float64)
    ht = np.clip(np.nan_to_num(truth_height, nan=0.0), 0.0, None).astype(np.float64)
    both = (hp > 0) & (ht > 0)
    excess = np.where(both, np.maximum(np.abs(hp - ht) - tolerance, 0.0), 0.0)
    vtp = float(np.sum(np.where(both, np.maximum(hp, ht) - excess, 0.0)))
    vfp = float(np.sum(np.where(both, np.where(hp > ht, excess, 0.0), hp)))
    vfn = float(np.sum(np.where(both, np.where(ht > hp, excess, 0.0), ht)))
    return {"vtp": vtp, "vfp": vfp, "vfn": vfn, "tolerance_m": tolerance,
            **detection_ratios(vtp, vfp, vfn)}  # fmt: skip


def building_heights(
    surface: np.ndarray, ground: np.ndarray, ids: np.ndarray, percentile: float = 99.0
) -> dict[int, float]:
    """Height of each building: a high percentile of surface minus ground over its cells.

    The percentile rather than the maximum keeps one outlying cell (an antenna, a noisy
    DSM spike) from setting a building's height.

    Parameters
    ----------
    surface, ground : (H, W) float
        Metres; NaN where unknown.
    ids : (H, W) int
        Building ids, 0 for none.

    Returns
    -------
    {id: height in metres} for every id with at least one known cell.
    """
    h = surface - ground
    m = (ids > 0) & np.isfinite(h)
    return {k: float(np.percentile(part, percentile)) for k, part in values_by_id(ids[m], h[m])}


def values_by_id(ids: np.ndarray, values: np.ndarray):
    """(id, its values) for each id of ``ids`` (N,), in increasing order, ``values`` (N,)
    split by them (each id's in their order)."""
    if not len(ids):
        return iter(())
    order = np.argsort(ids, kind="stable")
    labels, start = np.unique(ids[order], return_index=True)
    return zip(labels.tolist(), np.split(values[order], start[1:]), strict=True)


def height_error_summary(errors_pct: list[float]) -> dict:
    """``{"median": .., "mean": .., "n": ..}`` of the absolute height errors (percent) of a
    group of buildings: the voxel paper's Fig. 13 is a mean, a median hides the tail."""
    e = np.abs(np.asarray(errors_pct, dtype=np.float64))
    if not len(e):
        return {"n": 0}
    return {"median": float(np.median(e)), "mean": float(np.mean(e)), "n": len(e)}


def height_error_pct(model: dict[int, float], truth: dict[int, float]) -> dict[int, float]:
    """Signed error of each true building's height in percent of its true height.

    A building the model has no height for counts as height 0 (an error of -100 %).
    """
    return {k: 100.0 * (model.get(k, 0.0) - t) / t for k, t in truth.items() if t > 0}


def surface_distances(
    points_a: np.ndarray, dist_a_to_b: np.ndarray, points_b: np.ndarray, dist_b_to_a: np.ndarray
) -> dict:
    """Distances between two surfaces from point samples of both.

    Parameters
    ----------
    points_a, points_b : (N, 3), (M, 3) float
        Samples of surfaces A (the model) and B (the truth); only their counts are used.
    dist_a_to_b, dist_b_to_a : (N,), (M,) float
        Distance of each sample to the other surface, metres.

    Returns
    -------
    dict with the symmetric ``mean_distance_m`` (the mean of the two directed means),
    ``rms_distance_m`` (root of the mean of the two directed mean squares) and
    ``hausdorff_m`` (the Hausdorff distance: the larger directed maximum), plus each
    direction's ``mean_m``,
    ``rms_m``, ``max_m`` under ``model_to_truth`` and ``truth_to_model``.
    """
    if not len(points_a) or not len(points_b):
        return {}
    d = {}
    for key, e in (("model_to_truth", dist_a_to_b), ("truth_to_model", dist_b_to_a)):
        d[key] = {
            "mean_m": float(np.mean(e)),
            "rms_m": float(np.sqrt(np.mean(e**2))),
            "max_m": float(np.max(e)),
            "samples": len(e),
        }
    a, b = d["model_to_truth"], d["truth_to_model"]
    return {
        "mean_distance_m": (a["mean_m"] + b["mean_m"]) / 2,
        "rms_distance_m": float(np.sqrt((a["rms_m"] ** 2 + b["rms_m"] ** 2) / 2)),
        "hausdorff_m": max(a["max_m"], b["max_m"]),
        **d,
    }


def complexity(faces: list[int], watertight: list[bool]) -> dict:
    """Model complexity (the LOD paper's Table 1): ``faces_total``,
    ``faces_per_building_median`` and ``watertight_fraction`` over buildings."""
    if not faces:
        return {"buildings": 0}
    return {
        "buildings": len(faces),
        "faces_total": int(np.sum(faces)),
        "faces_per_building_median": float(np.median(faces)),
        "watertight_fraction": float(np.mean(watertight)),
    }


def plane_angles_deg(normals_a: np.ndarray, normals_b: np.ndarray) -> np.ndarray:
    """(N,) angle between the planes of unit normals ``normals_a`` and ``normals_b``
    ((N, 3) each), degrees in [0, 90]: a plane's two normals are the same plane."""
    c = np.abs(np.sum(normals_a * normals_b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def indistinguishable_roof_types(roof_type: str, wings: list[dict], cell_m: float) -> set[str]:
    """The labels a grid of ``cell_m`` cells cannot tell apart from a true roof's own.

    A hipped roof on one rectangle has a ridge 2 (half_length - half_width) long; shorter
    than two cells it is a point on the grid, and the roof a pyramid to every method
    (the sample city draws hipped roofs on near-square houses: ridges of 6 and 10 cm
    occur). Any other roof is its own label only.

    Parameters
    ----------
    roof_type : str
        The truth's label.
    wings : list of dict
        The truth's rectangles, each with ``half_length`` and ``half_width`` in metres.
    cell_m : float
        The evaluation grid's cell, metres.
    """
    if roof_type == "hipped" and len(wings) == 1:
        w = wings[0]
        ridge = 2.0 * abs(float(w["half_length"]) - float(w["half_width"]))
        if ridge < 2.0 * cell_m:
            return {"hipped", "pyramid"}
    return {roof_type}


def roof_type_accuracy(
    pred: list[str], truth: list[str], accepted: list[set[str]] | None = None
) -> dict:
    """Share of buildings whose roof type label matches the truth's, and the confusion
    as ``{true type: {predicted type: count}}``.

    ``accepted`` gives, per building, the labels that count as a match (by default the
    truth's own; see :func:`indistinguishable_roof_types`); the confusion keeps the truth's label.
    """
    if not truth:
        return {}
    accepted = [{t} for t in truth] if accepted is None else accepted
    conf: dict[str, dict[str, int]] = {}
    for p, t in zip(pred, truth, strict=True):
        conf.setdefault(t, {}).setdefault(p, 0)
        conf[t][p] += 1
    hits = sum(p in a for p, a in zip(pred, accepted, strict=True))
    return {"roof_type_accuracy": hits / len(truth), "confusion": conf}


def cost(stages: dict) -> dict:
    """Total wall time (s) and peak memory (MiB) from ``{stage: {wall_s, peak_memory_mb}}``."""
    if not stages:
        return {}
    out = {"wall_s": float(sum(s.get("wall_s", 0.0) for s in stages.values()))}
    mem = [s["peak_memory_mb"] for s in stages.values() if "peak_memory_mb" in s]
    if mem:
        out["peak_memory_mb"] = float(max(mem))
    return out


def outline_regularity(footprints: list, tol_deg: float = 2.0) -> dict:
    """The share of outline edges within ``tol_deg`` of their building's facade
    directions (the LOD paper's regularity), over every building.

    A building's facade direction is the length-weighted circular mean of its edges'
    directions modulo 90 degrees (its pair of orthogonal directions).

    Parameters
    ----------
    footprints : list of shapely Polygon or MultiPolygon (or None)
    """
    within = total = 0
    for fp in footprints:
        if fp is None or fp.is_empty:
            continue
        polys = fp.geoms if hasattr(fp, "geoms") else [fp]
        d = np.concatenate([np.diff(np.asarray(r.coords)[:, :2], axis=0) for p in polys
                            for r in (p.exterior, *p.interiors)])  # fmt: skip
        length = np.hypot(d[:, 0], d[:, 1])
        d, length = d[length > 1e-6], length[length > 1e-6]
        if not len(d):
            continue
        phi = np.arctan2(d[:, 1], d[:, 0])
        theta = np.angle(np.sum(length * np.exp(4j * phi))) / 4.0
        off = np.mod(phi - theta, np.pi / 2)
        off = np.degrees(np.minimum(off, np.pi / 2 - off))
        within += int((off <= tol_deg).sum())
        total += len(off)
    return {"edges_within_2deg": within / total if total else None, "edges": total}


def symmetric_plane_pairs(planes: list[np.ndarray], tol_deg: float = 2.0) -> dict:
    """The share of a building's facing roof-plane pairs (sloped planes whose downhill
    directions differ by more than 135 degrees) whose normals are z-symmetric within
    ``tol_deg``: same slope, opposite azimuth (the LOD paper's regularity).

    Parameters
    ----------
    planes : list of (P, 3) arrays, the unit normals (n_z > 0) of each building's roof
        planes
    """
    within = total = 0
    for p in planes:
        n = np.asarray(p, np.float64).reshape(-1, 3) if len(p) else np.zeros((0, 3))
        n = n[n[:, 2] < np.cos(np.radians(5.0))]  # sloped
        for i in range(len(n)):
            for j in range(i + 1, len(n)):
                h_i, h_j = n[i, :2], n[j, :2]
                cos_az = h_i @ h_j / max(np.linalg.norm(h_i) * np.linalg.norm(h_j), 1e-12)
                if cos_az > np.cos(np.radians(135.0)):
                    continue
                twin = n[j] * [-1.0, -1.0, 1.0]
                angle = np.degrees(np.arccos(np.clip(n[i] @ twin, -1.0, 1.0)))
                within += int(angle <= tol_deg)
                total += 1
    return {"pairs_within_2deg": within / total if total else None, "pairs": total}
