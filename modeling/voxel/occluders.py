"""What can hide a task's points from the views: the meshes near enough to stand between
them and a camera.

A task casts rays from its points to the centres of the views that frame them, along
lines no flatter than the steepest such sight (:func:`~workbench.camera.steepest_sight`:
the flight's geometry around the task's box), so a mesh whose top stands ``h`` above
the lowest of the points can cross them only within ``h`` x that ratio of them,
horizontally. A task's ray-casting scene holds that neighbourhood, not the city's every
mesh, and gives the same hits: a scene of some triangles of a mesh, given the whole
mesh's origin, holds them exactly as the whole mesh's scene does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from workbench.camera import steepest_sight
from workbench.meshes import concatenate_meshes
from workbench.raycast import RayScene, raycasting_scene

# metres added to every reach: rays start 5 cm off their surface (hidden_from), and a
# mesh's triangles are float32 in the scene
REACH_MARGIN_M = 1.0


@dataclass
class Occluders:
    """The boxes of a scene's meshes, to pick those that can hide a window's points.

    Attributes
    ----------
    ids : list of str
        The meshes' names (a building's id), in the boxes' order.
    boxes : (N, 4) float
        Their horizontal bounds (xmin, ymin, xmax, ymax), world metres.
    tops : (N,) float
        Their highest points, metres.
    origin : (3,) float
        The local origin of every ray-casting scene made of them, world metres.
    """

    ids: list
    boxes: np.ndarray
    tops: np.ndarray
    origin: np.ndarray

    def near(self, bounds, z_low: float, tangent: float) -> np.ndarray:
        """(M,) sorted indices of the meshes that can stand between a point inside
        ``bounds`` (xmin, ymin, xmax, ymax) no lower than ``z_low`` and a view it sees
        along a line whose horizontal-to-vertical ratio is at most ``tangent`` (inf:
        every mesh)."""
        if not len(self.ids):
            return np.zeros(0, np.int64)
        if not np.isfinite(z_low) or not np.isfinite(tangent):
            return np.arange(len(self.ids))
        reach = np.clip(self.tops - z_low, 0.0, None) * tangent + REACH_MARGIN_M
        x0, y0, x1, y1 = bounds
        r = float(reach.max())
        candidates = self._tree().query(shapely.box(x0 - r, y0 - r, x1 + r, y1 + r))
        b = self.boxes[candidates]
        dx = np.maximum(0.0, np.maximum(b[:, 0] - x1, x0 - b[:, 2]))
        dy = np.maximum(0.0, np.maximum(b[:, 1] - y1, y0 - b[:, 3]))
        return np.sort(candidates[np.hypot(dx, dy) <= reach[candidates]])

    def around(self, cameras: list, lo, hi) -> np.ndarray:
        """(M,) sorted indices of the meshes that can hide a point of the box ``lo`` to
        ``hi`` ((3,) world metres) from a camera that frames it."""
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            return np.arange(len(self.ids))
        tangent = steepest_sight(cameras, lo, hi)
        return self.near((lo[0], lo[1], hi[0], hi[1]), lo[2], tangent)

    def scene(self, meshes: list) -> RayScene | None:
        """The ray-casting scene of ``meshes`` ((V, 3), (T, 3)) in :attr:`origin` (None
        without a triangle)."""
        meshes = [m for m in meshes if len(m[1])]
        if not meshes:
            return None
        V, T, _ = concatenate_meshes(meshes)
        return raycasting_scene(V, T, self.origin)

    def _tree(self) -> shapely.STRtree:
        # built where first used (once per worker), not sent
        if getattr(self, "_strtree", None) is None:
            self._strtree = shapely.STRtree(shapely.box(*self.boxes.T))
        return self._strtree

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("_strtree", None)
        return state
