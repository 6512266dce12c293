"""The ground and vertex colours of a path that models from fused rasters: the DTM as a
mesh, and the ortho's colour under each vertex."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from workbench.meshes import raster_mesh
from workbench.model_run import Surface
from workbench.raster import Grid

GROUND_CELL_M = 2.0  # the ground mesh's cells, metres


def vertex_colours(vertices: np.ndarray, rgb: np.ndarray, grid: Grid) -> np.ndarray:
    """(V, 3) uint8 ortho colour under each vertex."""
    r, c = grid.cell_index(vertices[:, 0], vertices[:, 1], clip=True)
    return rgb[r, c]


def dtm_across_holes(dtm: np.ndarray) -> np.ndarray:
    """(H, W) the DTM with each unknown cell given its nearest known cell's height.

    A fusion leaves its DTM unknown where its DSM is (``dtm.tif``'s NaN nodata): a mesh's
    holes lie over the ground and roofs beside tall walls that no view saw. Measured
    against an unknown ground, a cell whose height was filled in stands at no height at
    all; the terrain itself goes on under the hole. All unknown: returned as it is.
    """
    unknown = ~np.isfinite(dtm)
    if not unknown.any() or unknown.all():
        return dtm
    idx = ndi.distance_transform_edt(unknown, return_distances=False, return_indices=True)
    return dtm[tuple(idx)]


def ground_surface(
    dtm: np.ndarray, rgb: np.ndarray, grid: Grid, fill: float | None = None
) -> Surface | None:
    """The DTM as a mesh of :data:`GROUND_CELL_M` cells, coloured by the ortho; unknown
    heights take ``fill`` (default: the known ones' median)."""
    ground = raster_mesh(dtm, grid, step=max(1, round(GROUND_CELL_M / grid.gsd)), fill=fill)
    if ground is None:
        return None
    return Surface(*ground, vertex_colors=vertex_colours(ground[0], rgb, grid))
