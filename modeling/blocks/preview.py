"""The block path's preview: the supports on the ortho coloured by their block's form,
the energy of every building's annealing against its iterations, and the models."""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

from workbench.model_run import Building
from workbench.pictures import contact_sheet
from workbench.raster import Grid
from workbench.render import render_buildings

FORM_COLOURS = {
    "flat": (150, 150, 150), "shed": (230, 160, 60), "gable": (220, 60, 60),
    "hipped": (60, 120, 220), "half-hipped": (40, 200, 200), "pyramid": (160, 60, 200),
    "mansard": (60, 180, 90), "gambrel": (240, 220, 40), "semi-elliptic": (120, 80, 40),
}  # fmt: skip
_PLOT = 360  # pixels: the side of the energy plot


def _ring_pixels(ring, grid: Grid) -> np.ndarray:
    xy = np.asarray(ring, np.float64)
    px = np.column_stack([(xy[:, 0] - grid.xmin) / grid.gsd, (grid.ymax - xy[:, 1]) / grid.gsd])
    return np.round(px).astype(np.int32)


def energy_plot(traces: list[list]) -> np.ndarray:
    """(360, 360, 3) uint8: each building's energy over its annealing, normalised by its
    initial value, against the share of its iterations done (log energy, 1e-2 to 1)."""
    img = np.full((_PLOT, _PLOT, 3), 255, np.uint8)
    m = 24
    cv2.rectangle(img, (m, 8), (_PLOT - 8, _PLOT - m), (0, 0, 0), 1)
    w, h = _PLOT - 8 - m, _PLOT - m - 8
    for k, trace in enumerate(traces):
        t = np.asarray(trace, np.float64)
        if len(t) < 2 or t[0, 2] <= 0:
            continue
        x = m + w * t[:, 0] / max(t[-1, 0], 1)
        e = np.clip(t[:, 2] / t[0, 2], 1e-2, 1.0)
        y = 8 + h * (-np.log10(e) / 2.0)
        colour = tuple(int(c) for c in cv2.applyColorMap(np.uint8([[37 * k % 256]]),
                                                         cv2.COLORMAP_TURBO)[0, 0])  # fmt: skip
        cv2.polylines(img, [np.column_stack([x, y]).round().astype(np.int32)], False, colour, 1,
                      cv2.LINE_AA)  # fmt: skip
    font = cv2.FONT_HERSHEY_SIMPLEX
    # on the right: the contact sheet's title covers the top left
    cv2.putText(img, "U / U0 = 1", (_PLOT - 80, 20), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "0.01", (_PLOT - 40, _PLOT - m - 4), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "iterations ->", (_PLOT // 2 - 30, _PLOT - 8), font, 0.35, (0, 0, 0), 1,
                cv2.LINE_AA)  # fmt: skip
    return img


def blocks_preview(rgb: np.ndarray, grid: Grid, results: list, buildings: Iterable[Building]):
    """(h, w, 3) uint8 contact sheet: the supports filled with their block's form colour
    over the ortho (skipped buildings' supports none), the annealing energies, the
    models."""
    over = rgb.copy()
    fill = rgb.copy()
    for x in results:
        for geom, form in zip(x.supports, x.forms, strict=True):
            pts = _ring_pixels(geom["coordinates"][0], grid)
            cv2.fillPoly(fill, [pts], FORM_COLOURS.get(form, (0, 0, 0)))
    over = cv2.addWeighted(over, 0.4, fill, 0.6, 0.0)
    for x in results:
        for geom in x.supports:
            cv2.polylines(over, [_ring_pixels(geom["coordinates"][0], grid)], True,
                          (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
    row = [(over, "supports and block forms"),
           (energy_plot([x.trace for x in results if x.trace]), "annealing energy")]  # fmt: skip
    models = render_buildings(buildings, grid.bounds)
    if models is not None:
        row.append((models, "models"))
    return contact_sheet([row], height=360)
