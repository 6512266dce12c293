"""The surface a view sees, sampled at the ortho cell centres.

Neighbouring pixels of a depth map span triangles: the view's surface. A vertical ray
cast down through each cell centre hits it (Open3D ray casting); the topmost hit is
the view's height of that cell. This is a point sample at the centre, as a DSM is:
a cell beside a wall takes the height of the side its centre lies on, whereas a
median of the points that land in the cell follows whichever side sent more points.

Triangles are not spanned where the surface is not seen:

- across a depth step (more than 0.6 m or 1 % of the depth between its corners), and
  within ``JUMP_REACH`` pixels of a larger discontinuity: dense matching rounds the
  step into a ramp that would bridge the occluded ground;
- on facades (all three corners on a steep surface): their noisy points lean out of
  the wall by a decimetre and would lend the roof's height to the ground beside it.

The depth map is median filtered first (5 x 5): it removes the isolated gross errors
and cuts the noise of the points that remain by about three.
"""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from workbench.camera import Camera
from workbench.raster import Grid

from .interpolate import push_pull_fill
from .observations import STEEP_NORMAL_Z, depth_jumps, normal_z_image

DEPTH_MEDIAN = 5  # pixels
JUMP_REACH = 3  # pixels, see observations.depth_jumps
STEP, STEP_REL = 0.6, 0.01  # metres and fraction of the depth: a triangle's largest depth step
STEEP_RAY_SIN = 0.8  # sine of the elevation of the rays a cell prefers (53 degrees)


def median_depth(depth: np.ndarray) -> np.ndarray:
    """(H, W) float32 depth after a 5 x 5 median, NaN where ``depth`` is NaN.

    The holes are filled from their neighbours before filtering (so that they do not
    bias the median beside them) and put back afterwards.
    """
    seen = np.isfinite(depth) & (depth > 0)
    if not seen.any():
        return np.full(depth.shape, np.nan, np.float32)
    filled = push_pull_fill(np.where(seen, depth, np.nan).astype(np.float64), seen)
    return np.where(seen, cv2.medianBlur(filled.astype(np.float32), DEPTH_MEDIAN), np.nan).astype(
        np.float32
    )


def surface_triangles(camera: Camera, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The triangles of a view's seen surface.

    Parameters
    ----------
    camera : Camera
    depth : (H, W) float
        z-depth, metres, NaN unknown (already filtered).

    Returns
    -------
    points : (H * W, 3) float32
        World point of every pixel (meaningless where the depth is NaN).
    triangles : (T, 3) int32
        Pixel indices of the kept triangles, two per 2 x 2 block of pixels.
    """
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    origin, dirs = camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()]).astype(np.float64))
    d = depth.ravel()
    points = (origin + dirs * np.nan_to_num(d)[:, None].astype(np.float64)).astype(np.float32)
    idx = np.arange(H * W, dtype=np.int32).reshape(H, W)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, e = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    triangles = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, e])])
    unseen = ~(np.isfinite(d) & (d > 0)) | depth_jumps(depth, k=JUMP_REACH).ravel()
    steep = normal_z_image(camera, depth).ravel() < STEEP_NORMAL_Z
    keep = ~np.any(unseen[triangles], axis=1) & ~np.all(steep[triangles], axis=1)
    triangles = triangles[keep]
    corners = d[triangles]
    near = corners.min(axis=1)
    keep = corners.max(axis=1) - near <= np.maximum(STEP, STEP_REL * near)
    return points, triangles[keep]


def view_surface_heights(
    camera: Camera, depth: np.ndarray, grid: Grid, window: tuple[int, int, int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The heights a view sees at the cell centres of a window of the grid.

    Parameters
    ----------
    camera : Camera
    depth : (H, W) float
        The view's z-depth map, metres, NaN unknown (raw: it is median filtered here).
    grid : Grid
    window : (row0, col0, height, width)
        The cells to sample.

    Returns
    -------
    cells : (N,) int64
        Flat cell index inside the window (row * width + col) of each hit.
    z : (N,) float32
        Height of the view's surface at the cell centre, metres.
    sin_elevation : (N,) float32
        Sine of the elevation of the ray from the hit to the camera (1 straight down).
    """
    r0, c0, h, w = window
    empty = (np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32))
    points, triangles = surface_triangles(camera, median_depth(depth))
    if len(triangles) == 0:
        return empty
    # above everything the view sees, the same for every window (identical hits)
    top = float(points[triangles.ravel(), 2].max()) + 1.0
    row, col = grid.world_to_cell(points[:, 0], points[:, 1])
    tri_row, tri_col = row[triangles], col[triangles]
    overlaps = (tri_row.max(axis=1) >= r0 - 0.5) & (tri_row.min(axis=1) <= r0 + h - 0.5)
    overlaps &= (tri_col.max(axis=1) >= c0 - 0.5) & (tri_col.min(axis=1) <= c0 + w - 0.5)
    triangles = triangles[overlaps]
    if len(triangles) == 0:
        return empty
    lo_r, hi_r = row[triangles].min(), row[triangles].max()
    lo_c, hi_c = col[triangles].min(), col[triangles].max()
    rows = np.arange(max(r0, int(np.floor(lo_r))), min(r0 + h, int(np.ceil(hi_r)) + 1))
    cols = np.arange(max(c0, int(np.floor(lo_c))), min(c0 + w, int(np.ceil(hi_c)) + 1))
    if len(rows) == 0 or len(cols) == 0:
        return empty
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(points), o3d.core.Tensor(triangles.astype(np.uint32)))
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    rays = np.zeros((rr.size, 6), np.float32)
    rays[:, 0] = grid.xmin + (cc.ravel() + 0.5) * grid.gsd
    rays[:, 1] = grid.ymax - (rr.ravel() + 0.5) * grid.gsd
    rays[:, 2] = top
    rays[:, 5] = -1.0
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    hit = np.isfinite(t_hit)
    z = (top - t_hit[hit]).astype(np.float32)
    to_camera = camera.center - np.column_stack([rays[hit, :2], z])
    sin_elevation = to_camera[:, 2] / np.linalg.norm(to_camera, axis=1)
    cells = (rr.ravel()[hit] - r0) * w + (cc.ravel()[hit] - c0)
    return cells.astype(np.int64), z, sin_elevation.astype(np.float32)


def steep_ray_preferred(cells: np.ndarray, sin_elevation: np.ndarray, n_cells: int) -> np.ndarray:
    """(N,) bool: the heights a cell fuses: those seen along steep rays (above 53
    degrees), or all of them where no steep ray reached the cell.

    A view sees a surface point, not the column above it: a low ray reaches the ground
    under a tree crown's rim, where the DSM is the crown.
    """
    steep = sin_elevation >= STEEP_RAY_SIN
    has_steep = np.bincount(cells[steep], minlength=n_cells) > 0
    return steep | ~has_steep[cells]
