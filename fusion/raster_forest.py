"""Class probabilities from rasters alone, for clouds (or scenes) without training labels.

A random forest on per-cell cues a LiDAR raster has: height above ground, slope,
roughness and curvature of the surface, brightness and greenness of the colour or
intensity. It is trained on the synthetic city's rasters (the ``tiny`` sample, seed
0: deterministic), on first use, and cached; ``--classifier FILE`` replaces it.
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np

from .classifier import CLASSES, load_classifier, predict_proba, save_classifier, train_forest
from .ground import dtm_from_dsm

log = logging.getLogger(__name__)

FEATURES = "raster_ndsm_slope_rough_curv_bright_green_v2"
N_FEATURES = 6


def raster_features(
    dsm: np.ndarray, dtm: np.ndarray, rgb: np.ndarray | None, cell_m: float, unit: float = 1.0
) -> np.ndarray:
    """(H, W, 6) float32 cues per cell.

    Parameters
    ----------
    dsm, dtm : (H, W) float
        Heights in the CRS's units.
    rgb : (H, W, 3) uint8 or None
        Colour (or grey intensity repeated) per cell.
    cell_m : float
        Cell size in metres.
    unit : float
        Metres per CRS unit (0.3048 for feet).

    Returns
    -------
    nDSM (m), normal z, roughness (m, 1.5 m window), |Laplacian| (1/m), brightness (0-1,
    relative to the raster's 99th percentile), greenness ((2G - R - B) / (R + G + B)).
    """
    z = np.nan_to_num(dsm * unit, nan=np.nanmedian(dsm) * unit).astype(np.float32)
    ndsm = np.nan_to_num((dsm - dtm) * unit, nan=0.0).astype(np.float32)
    gy, gx = np.gradient(z, cell_m)
    normal_z = 1.0 / np.sqrt(1.0 + gx**2 + gy**2)
    k = max(3, int(round(1.5 / cell_m)) | 1)
    mean = cv2.blur(z, (k, k))
    rough = np.sqrt(np.maximum(cv2.blur(z * z, (k, k)) - mean**2, 0.0))
    curv = cv2.blur(np.abs(cv2.Laplacian(z, cv2.CV_32F)) / cell_m**2, (k, k))
    if rgb is not None:
        c = rgb.astype(np.float32)
        grey = c.mean(axis=-1)
        bright = grey / max(float(np.percentile(grey, 99)), 1.0)
        green = (2 * c[..., 1] - c[..., 0] - c[..., 2]) / (c.sum(axis=-1) + 1.0)
    else:
        bright = np.zeros_like(z)
        green = np.zeros_like(z)
    return np.dstack([ndsm, normal_z, rough, curv, bright, green]).astype(np.float32)


def cache_path() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "city-workbench" / f"{FEATURES}.joblib"


def synthetic_raster_forest(*, seed: int = 0):
    """The forest trained on the synthetic city's rasters (cached after the first use)."""
    path = cache_path()
    if path.exists():
        try:
            return load_classifier(path, features=FEATURES)[0]
        except Exception:  # noqa: BLE001 - a stale or broken cache is rebuilt
            log.warning("rebuilding the cached raster forest %s", path)
    from data_samples.generate import generate_sample
    from workbench.raster import read_raster

    log.info("training the raster forest on the synthetic city (once)")
    with tempfile.TemporaryDirectory() as tmp:
        X, y = [], []
        for s in (0, 1):
            scene = Path(tmp) / f"city{s}"
            generate_sample(scene, "tiny", s)
            dsm, grid, _ = read_raster(scene / "truth" / "dsm.tif")
            ortho = np.moveaxis(read_raster(scene / "truth" / "ortho.tif")[0], 0, -1)
            truth = read_raster(scene / "truth" / "class.tif")[0][0]
            for f in (1, 2, 4):  # 0.25, 0.5 and 1 m cells: LiDAR rasters come in all sizes
                d, o, t = _pool(dsm[0], ortho, truth, f)
                dtm, _ = dtm_from_dsm(d, grid.gsd * f)
                X.append(raster_features(d, dtm, o, grid.gsd * f).reshape(-1, N_FEATURES))
                y.append(t.ravel())
    X, y = np.concatenate(X), np.concatenate(y)
    rng = np.random.default_rng(seed)
    keep = np.concatenate(
        [
            rng.choice(np.flatnonzero(y == k), min(15000, int((y == k).sum())), replace=False)
            for k in CLASSES
            if (y == k).any()
        ]
    )
    forest = train_forest(X[keep], y[keep], n_trees=16, max_depth=14, seed=seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_classifier(
        path,
        forest,
        features=FEATURES,
        meta={"trained_on": "synthetic city tiny, seeds 0 and 1", "seed": seed},
    )
    return forest


def _pool(dsm, ortho, truth, f: int):
    """Coarser rasters as a cloud would give them: highest point, mean colour, top class."""
    if f == 1:
        return dsm, ortho, truth
    H, W = (dsm.shape[0] // f) * f, (dsm.shape[1] // f) * f
    d = dsm[:H, :W].reshape(H // f, f, W // f, f)
    top = d.reshape(H // f, f, W // f, f).transpose(0, 2, 1, 3).reshape(H // f, W // f, f * f)
    arg = np.argmax(top, axis=-1)
    t = (
        truth[:H, :W]
        .reshape(H // f, f, W // f, f)
        .transpose(0, 2, 1, 3)
        .reshape(H // f, W // f, -1)
    )
    cls = np.take_along_axis(t, arg[..., None], axis=-1)[..., 0]
    o = ortho[:H, :W].reshape(H // f, f, W // f, f, 3).mean(axis=(1, 3)).astype(np.uint8)
    return top.max(axis=-1), o, cls


def classify_rasters(forest, dsm, dtm, rgb, cell_m: float, unit: float = 1.0) -> np.ndarray:
    """(4, H, W) class probabilities (NaN where the DSM is unknown)."""
    f = raster_features(dsm, dtm, rgb, cell_m, unit)
    H, W = dsm.shape
    prob = predict_proba(forest, f.reshape(-1, N_FEATURES)).T.reshape(4, H, W)
    prob[:, ~np.isfinite(dsm)] = np.nan
    return prob
