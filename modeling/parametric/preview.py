"""The parametric path's preview: the level set and the registered priors on the ortho,
the roof types, and the models."""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np
from shapely.geometry import mapping
from skimage.segmentation import find_boundaries

from workbench.model_run import Building
from workbench.pictures import contact_sheet
from workbench.raster import Grid
from workbench.render import render_buildings

ROOF_COLOURS = {
    "flat": (150, 150, 150), "shed": (230, 160, 60), "gable": (220, 60, 60),
    "hipped": (60, 120, 220), "pyramid": (160, 60, 200), "mansard": (60, 180, 90),
    "platform": (40, 200, 200), "dissymmetric": (240, 220, 40), "multi-level": (120, 80, 40),
}  # fmt: skip


def _pixel_rings(geom: dict, grid: Grid) -> list[np.ndarray]:
    """The rings of a GeoJSON-like (Multi)Polygon as (n, 2) float column, row positions,
    exterior first."""
    polys = [geom["coordinates"]] if geom["type"] == "Polygon" else geom["coordinates"]
    out = []
    for ring in (r for poly in polys for r in poly):
        xy = np.asarray(ring, np.float64)
        out.append(np.column_stack([(xy[:, 0] - grid.xmin) / grid.gsd,
                                    (grid.ymax - xy[:, 1]) / grid.gsd]))  # fmt: skip
    return out


def _polylines(img: np.ndarray, geoms: list, grid: Grid, colour) -> None:
    for g in geoms:
        for ring in _pixel_rings(g, grid):
            pts = np.round(ring * 4).astype(np.int32)  # 2 bits of sub-pixel shift
            cv2.polylines(img, [pts], True, colour, 1, cv2.LINE_AA, shift=2)


def parametric_preview(
    rgb: np.ndarray,
    grid: Grid,
    mask: np.ndarray,
    outlines: list,
    buildings: Iterable[Building],
    skipped: list,
) -> np.ndarray:
    """(h, w, 3) uint8 contact sheet: the ortho with the level set's boundary (cyan), the
    registered priors (yellow) and the segments left to the data term (red); the roof
    types; the models.

    rgb : (H, W, 3) uint8; mask : (H, W) bool, phi > 0; outlines, skipped : GeoJSON-like
    polygons, world metres."""
    over = rgb.copy()
    over[find_boundaries(mask, mode="inner")] = (0, 255, 255)
    _polylines(over, outlines, grid, (255, 255, 0))
    _polylines(over, skipped, grid, (255, 0, 0))
    types = np.full(rgb.shape, 255, np.uint8)
    for b in buildings:
        if b.footprint is None:
            continue
        colour = ROOF_COLOURS.get(b.roof_type, (0, 0, 0))
        for i, ring in enumerate(_pixel_rings(mapping(b.footprint), grid)):
            pts = np.round(ring).astype(np.int32)
            cv2.fillPoly(types, [pts], colour if i == 0 else (255, 255, 255))
    row = [(over, "level set, priors"), (types, "roof types")]
    models = render_buildings(buildings, grid.bounds)
    if models is not None:
        row.append((models, "models"))
    return contact_sheet([row], height=360)
