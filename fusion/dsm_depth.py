"""Depth maps ray-cast from a DSM (Open3D RaycastingScene).

Used twice: for a scene with a DSM and no depth maps (a true orthophoto: every
pixel's depth, hence its visibility, comes from the DSM surface), and to give pixels
without a matched depth (textureless shadows) their elevation cue.
"""

from __future__ import annotations

import numpy as np

from workbench.camera import Camera
from workbench.raster import Grid
from workbench.raycast import cast, raycasting_scene

from .interpolate import push_pull_fill


class DsmSurface:
    """A DSM as a triangle surface for ray casting.

    Coordinates are shifted to a local origin (the grid's centre) so that float32 ray
    casting keeps millimetres on projected coordinates of millions of metres.

    Parameters
    ----------
    dsm : (H, W) float
        Heights, NaN where unknown (filled by interpolation for the surface).
    grid : Grid
    """

    def __init__(self, dsm: np.ndarray, grid: Grid):
        self.filled = push_pull_fill(dsm, np.isfinite(dsm))
        self.grid = grid
        x0, y0, x1, y1 = grid.bounds
        self.origin = np.array([(x0 + x1) / 2, (y0 + y1) / 2, float(np.nanmedian(self.filled))])
        self._scene = None

    def __getstate__(self):  # the ray-casting scene is rebuilt where it is used
        return {**self.__dict__, "_scene": None}

    @property
    def scene(self):
        """The Open3D scene of the surface, built on first use."""
        if self._scene is None:
            self._scene = self._build()
        return self._scene

    def _build(self):
        X, Y = self.grid.cell_centers()
        filled = self.filled
        verts = np.column_stack([X.ravel(), Y.ravel(), filled.ravel()]) - self.origin
        H, W = self.grid.shape
        j, i = np.meshgrid(np.arange(W - 1), np.arange(H - 1))
        v00 = (i * W + j).ravel()
        tris = np.concatenate(
            [
                np.column_stack([v00, v00 + W, v00 + 1]),
                np.column_stack([v00 + 1, v00 + W, v00 + W + 1]),
            ]
        )
        return raycasting_scene(verts, tris)

    def depth_map(self, camera: Camera, step: int = 1) -> np.ndarray:
        """(H, W) z-depth of the surface seen by every pixel, NaN where the ray misses."""
        origin, dirs = camera.pixel_grid_rays(step)
        h = len(range(0, camera.height, step))
        w = len(range(0, camera.width, step))
        return self._depths(origin, dirs).reshape(h, w)

    def depth_at(self, camera: Camera, pixels: np.ndarray) -> np.ndarray:
        """(N,) float32 z-depth of the surface seen by the flat ``pixels`` (row * width +
        col), NaN where the ray misses: :meth:`depth_map`'s at those pixels."""
        origin, dirs = camera.pixel_grid_rays()
        return self._depths(origin, dirs[pixels])

    def _depths(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        hits = cast(self.scene, origin - self.origin, dirs)
        return np.where(np.isfinite(hits.t), hits.t, np.nan).astype(np.float32)
