"""RANSAC roof-plane hypotheses per super-pixel (the super-pixel paper, section 5.1).

A plane is (n, d) with unit normal n (n_z > 0) and n . X + d = 0, world metres.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d


def plane_heights(plane: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of ``plane`` (4,) = (nx, ny, nz, d) above points (x, y), metres."""
    nx, ny, nz, d = plane
    return -(nx * x + ny * y + d) / nz


def point_plane_distances(plane: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) unsigned distances of ``points`` (N, 3) to ``plane`` (4,)."""
    return np.abs(points @ plane[:3] + plane[3])


def ransac_plane(
    points: np.ndarray,
    threshold: float = 0.15,
    iterations: int = 200,
    max_tilt_deg: float = 80.0,
) -> np.ndarray | None:
    """The plane with most inliers among ``points`` (N, 3), by Open3D's RANSAC, refined
    by total least squares (the inliers' principal axes) on its inliers.

    Returns (4,) plane with n_z > 0, or None for fewer than 6 points or a plane steeper
    than ``max_tilt_deg`` (a wall or a tree, not a roof).
    """
    if len(points) < 6:
        return None
    centre = points.mean(axis=0)  # Open3D fits in float32-friendly local coordinates
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - centre))
    model, inliers = pcd.segment_plane(threshold, 3, iterations)
    plane = np.asarray(model, np.float64)
    inl = points[np.asarray(inliers, dtype=np.int64)] - centre
    if len(inl) >= 3:
        mean = inl.mean(axis=0)
        normal = np.linalg.svd(inl - mean, full_matrices=False)[2][-1]
        plane = np.r_[normal, -normal @ mean]
    n = np.linalg.norm(plane[:3])
    if not np.isfinite(plane).all() or n == 0:
        return None
    plane = plane / n
    if plane[2] < 0:
        plane = -plane
    if plane[2] < np.cos(np.radians(max_tilt_deg)):
        return None
    plane[3] -= plane[:3] @ centre  # back to world coordinates
    return plane
