"""Pictures people look at: colour maps for class and height rasters, titled contact sheets."""

from __future__ import annotations

import cv2
import numpy as np

CLASS_COLORS = np.array(
    [[0, 0, 0], [150, 150, 150], [120, 220, 90], [20, 110, 30], [220, 60, 50]], np.uint8
)  # 0 nodata, 1 ground, 2 grass, 3 tree, 4 building


def colorize_classes(cls: np.ndarray) -> np.ndarray:
    """(H, W) class codes to (H, W, 3) uint8 RGB."""
    return CLASS_COLORS[np.clip(cls, 0, 4)]


def colorize_height(z: np.ndarray) -> np.ndarray:
    """(H, W) heights to (H, W, 3) uint8 RGB (turbo colour map, NaN black)."""
    ok = np.isfinite(z)
    lo, hi = np.percentile(z[ok], [1, 99]) if ok.any() else (0.0, 1.0)
    g = np.clip((np.nan_to_num(z, nan=lo) - lo) / max(hi - lo, 1e-6) * 255, 0, 255)
    rgb = cv2.cvtColor(cv2.applyColorMap(g.astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[~ok] = 0
    return rgb


def _tile(img: np.ndarray, height: int, title: str) -> np.ndarray:
    h, w = img.shape[:2]
    out = cv2.resize(img, (max(1, round(w * height / h)), height), interpolation=cv2.INTER_AREA)
    out = np.ascontiguousarray(out)
    cv2.rectangle(out, (0, 0), (8 + 9 * len(title), 22), (0, 0, 0), -1)
    cv2.putText(out, title, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def contact_sheet(rows: list[list[tuple[np.ndarray, str]]], height: int = 260) -> np.ndarray:
    """Rows of titled images, each row scaled to ``height`` pixels, left-aligned."""
    built = [np.hstack([_tile(img, height, t) for img, t in row]) for row in rows]
    width = max(r.shape[1] for r in built)
    pad = [np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in built]
    return np.vstack(pad)


def colorize_error(err: np.ndarray, max_error: float) -> np.ndarray:
    """Errors to colours as in the voxel paper's Fig. 8: green at 0, blue at half of
    ``max_error``, red at or above it; NaN white.

    Parameters
    ----------
    err : (...) float
        Non-negative errors, metres.
    max_error : float
        Metres.

    Returns
    -------
    (..., 3) uint8 RGB
    """
    s = np.clip(np.nan_to_num(err, nan=0.0) / max_error, 0.0, 1.0)[..., None]
    green, blue, red = (np.array(c, np.float64) for c in ((0, 200, 0), (0, 0, 255), (255, 0, 0)))
    low = green + (blue - green) * np.clip(2 * s, 0, 1)
    rgb = np.where(s < 0.5, low, blue + (red - blue) * np.clip(2 * s - 1, 0, 1))
    out = np.round(rgb).astype(np.uint8)
    out[~np.isfinite(err)] = 255
    return out
