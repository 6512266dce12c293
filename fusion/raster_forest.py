"""Class probabilities from rasters alone, for clouds (or scenes) without training labels.

A random forest on per-cell cues a LiDAR raster has: height above ground, slope,
roughness and curvature of the surface, brightness and greenness of the colour or
intensity. It is trained on the synthetic city's rasters by
``python -m data_samples.raster_forest`` (``make setup`` runs it once) and read here
from the cache; ``--classifier FILE`` replaces it.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from workbench.errors import InputError

from .classifier import load_classifier, predict_proba

FEATURES = "raster_ndsm_slope_rough_curv_bright_green_v3"
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


def synthetic_raster_forest():
    """The forest trained on the synthetic city's rasters, from the cache.

    ``python -m data_samples.raster_forest`` trains it (``make setup`` does, once).

    Raises
    ------
    InputError
        Naming the cache file, when it is missing or unreadable.
    """
    path = cache_path()
    if not path.exists():
        raise InputError(
            path, None, "the raster forest is not trained: run `make setup` or "
            "`python -m data_samples.raster_forest` (or pass --classifier FILE)",
        )  # fmt: skip
    return load_classifier(path, features=FEATURES)[0]


def classify_rasters(forest, dsm, dtm, rgb, cell_m: float, unit: float = 1.0) -> np.ndarray:
    """(4, H, W) class probabilities (NaN where the DSM is unknown)."""
    f = raster_features(dsm, dtm, rgb, cell_m, unit)
    H, W = dsm.shape
    prob = predict_proba(forest, f.reshape(-1, N_FEATURES)).T.reshape(4, H, W)
    prob[:, ~np.isfinite(dsm)] = np.nan
    return prob
