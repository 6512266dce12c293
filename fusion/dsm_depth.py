"""Depth maps ray-cast from a DSM (Open3D RaycastingScene).

Used twice: for a scene with a DSM and no depth maps (a true orthophoto: every
pixel's depth, hence its visibility, comes from the DSM surface), and to give pixels
without a matched depth (textureless shadows) their elevation cue.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from workbench.camera import Camera
from workbench.raster import Grid
from workbench.raycast import cast, raycasting_scene

from .interpolate import push_pull_fill

TILE_QUADS = 256  # quads a side of a tile of the surface that depth_at casts against
# a surface's tiles kept at once, the least recently used dropped: the whole 1 km² city at
# 0.4 m (100 tiles), whose views each need 40 tiles (median): with 16 kept, every view
# rebuilt most of its own (4 s a view)
TILE_BUDGET_MB = 1024
BYTES_PER_QUAD = 160  # a quad's two triangles in Open3D's scene, BVH built: 146 in a tile


class DsmSurface:
    """A DSM as a triangle surface for ray casting.

    Coordinates are shifted to a local origin (the grid's centre) so that float32 ray
    casting keeps millimetres on projected coordinates of millions of metres.

    :meth:`depth_map` casts against the whole surface (built once, kept). :meth:`depth_at`
    casts against tiles of ``tile`` x ``tile`` quads, each built when a ray first may meet
    it and kept while the tiles fit in ``budget_mb`` (least recently used dropped first):
    the same triangles, so the same depths, in a memory bounded whatever the area (a
    whole 1 km² surface at 0.4 m, 974 MiB once cast against, fits; beyond, the tiles
    a view does not need go first).

    Parameters
    ----------
    dsm : (H, W) float
        Heights, NaN where unknown (filled by interpolation for the surface).
    grid : Grid
    tile : int
        Quads a side of a tile.
    budget_mb : float
        Memory the kept tiles may take (at :data:`BYTES_PER_QUAD`).
    """

    def __init__(self, dsm: np.ndarray, grid: Grid, tile: int = TILE_QUADS,
                 budget_mb: float = TILE_BUDGET_MB):  # fmt: skip
        filled = push_pull_fill(dsm, np.isfinite(dsm))
        x0, y0, x1, y1 = grid.bounds
        origin = np.array([(x0 + x1) / 2, (y0 + y1) / 2, float(np.nanmedian(filled))])
        self._setup(filled, grid, origin, (float(filled.min()), float(filled.max())), tile,
                    budget_mb)  # fmt: skip

    @classmethod
    def of_filled(cls, filled: np.ndarray | Path, grid: Grid, origin: np.ndarray,
                  z_range: tuple, tile: int = TILE_QUADS,
                  budget_mb: float = TILE_BUDGET_MB):  # fmt: skip
        """The surface of another's ``filled`` heights (or the ``.npy`` file of them: then
        only the tiles :meth:`depth_at` casts against are read), ``origin`` and
        ``z_range``."""
        surface = cls.__new__(cls)
        surface._setup(filled, grid, origin, z_range, tile, budget_mb)
        return surface

    def _setup(self, filled, grid, origin, z_range, tile, budget_mb):
        self.filled, self.grid, self.origin, self.z_range = filled, grid, origin, z_range
        self.tile, self.budget_mb = tile, budget_mb
        self._scene = None
        self._tiles: OrderedDict = OrderedDict()  # (tile row, tile column) -> scene
        self._lock = threading.Lock()  # threads of one process share the tiles

    def __getstate__(self):  # the ray-casting scenes are rebuilt where they are used
        return {k: v for k, v in self.__dict__.items() if k not in ("_scene", "_tiles", "_lock")}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._scene, self._tiles, self._lock = None, OrderedDict(), threading.Lock()

    @property
    def scene(self):
        """The Open3D scene of the whole surface, built on first use."""
        if self._scene is None:
            self._scene = self._build(slice(0, self.grid.height), slice(0, self.grid.width))
        return self._scene

    def _build(self, rows: slice, cols: slice):
        """The scene of the cells ``rows`` x ``cols``: a vertex at each cell centre, two
        triangles between four."""
        x, _ = self.grid.cell_center(0, np.arange(cols.start, cols.stop))
        _, y = self.grid.cell_center(np.arange(rows.start, rows.stop), 0)
        X, Y = np.meshgrid(x, y)
        if isinstance(self.filled, Path):  # mapped for this window only
            filled = np.array(np.load(self.filled, mmap_mode="r")[rows, cols], np.float64)
        else:
            filled = np.asarray(self.filled[rows, cols], np.float64)
        verts = np.column_stack([X.ravel(), Y.ravel(), filled.ravel()]) - self.origin
        H, W = filled.shape
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
        t = cast(self.scene, origin - self.origin, dirs).t
        return np.where(np.isfinite(t), t, np.nan).astype(np.float32).reshape(h, w)

    def depth_at(self, camera: Camera, pixels: np.ndarray) -> np.ndarray:
        """(N,) float32 z-depth of the surface seen by the flat ``pixels`` (row * width +
        col), NaN where the ray misses: :meth:`depth_map`'s at those pixels, the nearest
        hit among the tiles in the window of cells the rays can meet
        (:func:`ray_window`)."""
        origin, dirs = camera.pixel_grid_rays()
        dirs = dirs[pixels]
        out = np.full(len(dirs), np.nan, np.float32)
        window = ray_window(origin, dirs, self.grid, self.z_range)
        if window is None:
            return out
        rows, cols, rays = window
        t = np.full(int(rays.sum()), np.inf)
        for key in self._tiles_over(rows, cols):
            np.minimum(t, cast(self._tile_scene(key), origin - self.origin, dirs[rays]).t, out=t)
        out[rays] = np.where(np.isfinite(t), t, np.nan)
        return out

    def _tiles_over(self, rows: slice, cols: slice) -> list[tuple[int, int]]:
        """The tiles holding the quads between the cells ``rows`` x ``cols``."""
        if rows.stop - rows.start < 2 or cols.stop - cols.start < 2:
            return []
        t = self.tile
        return [(a, b) for a in range(rows.start // t, (rows.stop - 2) // t + 1)
                for b in range(cols.start // t, (cols.stop - 2) // t + 1)]  # fmt: skip

    def _tile_scene(self, key: tuple[int, int]):
        """Tile ``key``'s scene (its quads, with the cells on their far side), built or
        kept; tiles beyond the budget dropped, the least recently used first."""
        with self._lock:
            if key in self._tiles:
                self._tiles.move_to_end(key)
                return self._tiles[key]
            t, (H, W) = self.tile, self.grid.shape
            rows = slice(key[0] * t, min((key[0] + 1) * t, H - 1) + 1)
            cols = slice(key[1] * t, min((key[1] + 1) * t, W - 1) + 1)
            scene = self._build(rows, cols)
            self._tiles[key] = scene
            quads = t * t * len(self._tiles)  # at most: edge tiles are smaller
            while len(self._tiles) > 1 and quads * BYTES_PER_QUAD > self.budget_mb * 2**20:
                self._tiles.popitem(last=False)
                quads -= t * t
            return scene


def ray_window(
    origin: np.ndarray, dirs: np.ndarray, grid: Grid, z_range: tuple
) -> tuple[slice, slice, np.ndarray] | None:
    """The cells of ``grid`` where rays can first meet a surface of heights in
    ``z_range``, and the rays that can meet it.

    From above the surface, a ray meets it between its crossings of the highest and the
    lowest heights, and the segment between them lies in their bounding box; a ray that
    does not go down never meets it. The box grows by a cell, for the triangles between
    cell centres. From within the heights' range a ray may meet it anywhere: the whole
    grid.

    Parameters
    ----------
    origin : (3,) float, the rays' origin, world metres
    dirs : (N, 3) float
    grid : Grid
    z_range : (lowest, highest) heights of the surface, metres

    Returns
    -------
    (rows, cols, rays) : slices of the window of cells and the (N,) bool rays that can
        meet the surface, or None where none can.
    """
    lo, hi = z_range
    if origin[2] <= hi:
        return slice(0, grid.height), slice(0, grid.width), np.ones(len(dirs), bool)
    rays = dirs[:, 2] < 0
    if not rays.any():
        return None
    d = dirs[rays]
    ends = np.concatenate([origin + d * ((z - origin[2]) / d[:, 2])[:, None] for z in (hi, lo)])
    r, c = grid.cell_index(ends[:, 0], ends[:, 1], clip=True)
    rows = slice(max(int(r.min()) - 1, 0), min(int(r.max()) + 2, grid.height))
    cols = slice(max(int(c.min()) - 1, 0), min(int(c.max()) + 2, grid.width))
    return rows, cols, rays
