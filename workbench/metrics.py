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
    m = (pred > 0) & (truth > 0)
    excluded = 0
    if exclude is not None:
        excluded = int(np.count_nonzero(m & exclude))
        m &= ~exclude
    p, t = pred[m].astype(int), truth[m].astype(int)
    conf = np.zeros((4, 4), np.int64)
    np.add.at(conf, (t - 1, np.clip(p, 1, 4) - 1), 1)
    out = {"scored_cells": int(m.sum()), "excluded_cells": excluded}
    if not m.any():
        return out
    out["overall_accuracy"] = float(np.trace(conf) / conf.sum())
    per = {CLASS_NAMES[k + 1]: float(conf[k, k] / conf[k].sum()) for k in range(4) if conf[k].sum()}
    out["per_class_accuracy"] = per
    out["mean_class_accuracy"] = float(np.mean(list(per.values())))
    out["building_accuracy"] = float(np.mean((p == 4) == (t == 4)))
    out["confusion"] = conf.tolist()
    return out


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
    dict with ``rmse_m``, ``mae_m``, ``median_abs_m`` over cells where both are known,
    ``valid_fraction``: share of the scored cells where the model is known, and
    ``rmse_off_jumps_m`` and ``jump_fraction``: the RMSE over the scored cells off
    :func:`height_jumps` of the truth, and the share of scored cells on them.
    """
    m = np.isfinite(truth) if mask is None else (mask & np.isfinite(truth))
    ok = m & np.isfinite(model)
    out = {"valid_fraction": float(ok.sum() / max(m.sum(), 1))}
    if ok.any():
        e = (model[ok] - truth[ok]).astype(np.float64)
        out.update(
            rmse_m=float(np.sqrt(np.mean(e**2))),
            mae_m=float(np.mean(np.abs(e))),
            median_abs_m=float(np.median(np.abs(e))),
        )
        jumps = height_jumps(truth) if jumps is None else jumps
        off = ok & ~jumps
        out["jump_fraction"] = float((ok & jumps).sum() / ok.sum())
        if off.any():
            e = (model[off] - truth[off]).astype(np.float64)
            out["rmse_off_jumps_m"] = float(np.sqrt(np.mean(e**2)))
    return out


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
    jumps = height_jumps(truth) if jumps is None else jumps
    ok = mask & np.isfinite(model) & np.isfinite(truth) & ~jumps
    e2 = np.where(ok, (np.asarray(model, np.float64) - truth) ** 2, 0.0)
    total = float(e2.sum())
    return float(e2[part].sum() / total) if total > 0 else None


def colour_mae(model: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """Mean absolute colour error per channel (0-255) over ``mask``.

    Parameters
    ----------
    model, truth : (H, W, 3) arrays
    mask : (H, W) bool
    """
    if not mask.any():
        return {}
    d = np.abs(model[mask].astype(np.float64) - truth[mask].astype(np.float64))
    per = d.mean(axis=0)
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
    out = {"tp": tp, "fp": fp, "fn": fn}
    for key, den in (
        ("completeness", tp + fn),
        ("correctness", tp + fp),
        ("quality", tp + fp + fn),
    ):
        if den:
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

    def covered(ids: np.ndarray, other: np.ndarray) -> tuple[int, int]:
        labels, inv = np.unique(ids[ids > 0], return_inverse=True)
        if not len(labels):
            return 0, 0
        size = np.bincount(inv)
        hit = np.bincount(inv, weights=other[ids > 0] > 0)
        return len(labels), int(np.count_nonzero(hit >= min_cover * size))

    n_truth, found = covered(truth_ids, pred_ids)
    n_pred, correct = covered(pred_ids, truth_ids)
    return {
        "truth_buildings": n_truth,
        "found": found,
        "model_buildings": n_pred,
        "correct": correct,
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
    out = {"vtp": vtp, "vfp": vfp, "vfn": vfn, "tolerance_m": tolerance}
    for key, den in (
        ("completeness", vtp + vfn),
        ("correctness", vtp + vfp),
        ("quality", vtp + vfp + vfn),
    ):
        if den > 0:
            out[key] = vtp / den
    return out


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
    if not m.any():
        return {}
    order = np.argsort(ids[m], kind="stable")
    sid, sh = ids[m][order], h[m][order]
    labels, start = np.unique(sid, return_index=True)
    return {
        int(k): float(np.percentile(part, percentile))
        for k, part in zip(labels, np.split(sh, start[1:]), strict=True)
    }


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
