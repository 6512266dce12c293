"""Metrics shared by every method, each a plain function on arrays.

Class codes: 1 ground, 2 grass, 3 tree, 4 building; 0 is no data and never scored.
"""

from __future__ import annotations

import numpy as np

CLASS_NAMES = {1: "ground", 2: "grass", 3: "tree", 4: "building"}


def classification(pred: np.ndarray, truth: np.ndarray) -> dict:
    """Accuracy of a class map against the truth (the super-pixel paper's Table 1).

    Parameters
    ----------
    pred, truth : (H, W) int
        Class codes; cells where either is 0 are not scored.

    Returns
    -------
    dict with ``overall_accuracy`` (correct / scored), ``per_class_accuracy`` (per true
    class: correct / true cells of that class, for classes present in the truth),
    ``mean_class_accuracy`` (their mean), ``confusion`` (rows truth 1-4, columns
    prediction 1-4) and ``scored_cells``.
    """
    m = (pred > 0) & (truth > 0)
    p, t = pred[m].astype(int), truth[m].astype(int)
    conf = np.zeros((4, 4), np.int64)
    np.add.at(conf, (t - 1, np.clip(p, 1, 4) - 1), 1)
    out = {"scored_cells": int(m.sum())}
    if not m.any():
        return out
    out["overall_accuracy"] = float(np.trace(conf) / conf.sum())
    per = {CLASS_NAMES[k + 1]: float(conf[k, k] / conf[k].sum()) for k in range(4) if conf[k].sum()}
    out["per_class_accuracy"] = per
    out["mean_class_accuracy"] = float(np.mean(list(per.values())))
    out["confusion"] = conf.tolist()
    return out


def height_errors(model: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Errors of a height raster against the truth, metres.

    Parameters
    ----------
    model, truth : (H, W) float
        Heights, NaN where unknown.
    mask : (H, W) bool, optional
        Cells to score (default: every cell where the truth is known).

    Returns
    -------
    dict with ``rmse_m``, ``mae_m``, ``median_abs_m`` over cells where both are known,
    and ``valid_fraction``: share of the scored cells where the model is known.
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
    return out


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
