"""The super-pixel path's preview: super-pixels, CRF classes, roof prototypes, models."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from skimage.segmentation import find_boundaries

from workbench.model_run import Building
from workbench.pictures import colorize_classes, contact_sheet
from workbench.raster import Grid
from workbench.render import render_buildings


def superpixel_preview(
    rgb: np.ndarray,
    labels: np.ndarray,
    classes: np.ndarray,
    faces: np.ndarray,
    buildings: Iterable[Building],
    grid: Grid,
    ground_z: float,
) -> np.ndarray:
    """(h, w, 3) uint8 contact sheet.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 ortho; labels : (H, W) super-pixels; classes : (H, W) CRF
    classes; faces : (H, W) int prototype face of every building cell (0 elsewhere);
    grid : their grid; ground_z : the lowest ground, metres (inf: none).
    """
    edges = rgb.copy()
    edges[find_boundaries(labels, mode="inner")] = (255, 255, 0)
    rng = np.random.default_rng(0)
    palette = rng.integers(60, 255, (int(faces.max()) + 1, 3)).astype(np.uint8)
    palette[0] = 0
    row = [
        (edges, "super-pixels"),
        (colorize_classes(classes), "CRF classes"),
        (palette[faces], "roof prototypes"),
    ]
    # a single-building cloud's DTM can be all NaN: its models' foot is the ground then
    models = render_buildings(buildings, grid.bounds, ground_z if np.isfinite(ground_z) else None)
    if models is not None:
        row.append((models, "models"))
    return contact_sheet([row], height=360)
