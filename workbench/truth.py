"""Ground truth of a scene (``truth/``), sampled onto any run's grid."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .raster import Grid, read_raster
from .scene import load_scene


def sample_to_grid(data: np.ndarray, src: Grid, dst: Grid) -> np.ndarray:
    """Nearest-cell sampling of a (..., H, W) raster on ``src`` at the cells of ``dst``."""
    if src == dst:
        return data
    X, Y = dst.cell_centers()
    r, c = src.cell_index(X, Y)
    inside = src.contains(r, c)
    fill = np.nan if np.issubdtype(data.dtype, np.floating) else 0
    out = np.full(data.shape[:-2] + dst.shape, fill, dtype=data.dtype)
    out[..., inside] = data[..., r[inside], c[inside]]
    return out


def truth_folder(scene_or_truth: str | Path) -> Path:
    """The truth folder of a scene (folder or scene.json) or a truth folder itself."""
    p = Path(scene_or_truth)
    if (p / "dsm.tif").exists():
        return p
    scene = load_scene(p, check_files=False)
    if scene.truth is None:
        raise InputError(scene.scene_json, "truth", "the scene has no truth folder")
    return scene.truth


def truth_rasters(scene_or_truth: str | Path, grid: Grid) -> dict[str, np.ndarray]:
    """The truth rasters that exist (dsm, dtm, ortho (H, W, 3), class), on ``grid``."""
    folder = truth_folder(scene_or_truth)
    out = {}
    for name in ("dsm", "dtm", "ortho", "class", "building_id"):
        path = folder / f"{name}.tif"
        if path.exists():
            data, src, _ = read_raster(path)
            data = sample_to_grid(data, src, grid)
            out[name] = np.moveaxis(data, 0, -1) if name == "ortho" else data[0]
    return out
