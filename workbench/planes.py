"""Planes by RANSAC: the super-pixel paper's roof-plane hypotheses (section 5.1), the
voxel path's pitched roofs and the fusion's test of planar objects.

A plane is (n, d) with unit normal n (n_z > 0) and n . X + d = 0, world metres.
"""

from __future__ import annotations

import numpy as np


def plane_heights(plane: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of ``plane`` (4,) = (nx, ny, nz, d) above points (x, y), metres."""
    nx, ny, nz, d = plane
    return -(nx * x + ny * y + d) / nz


def point_plane_distances(planes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unsigned distances of ``points`` (N, 3) to ``planes``: (N,) for one plane (4,),
    (N, P) for several (P, 4)."""
    planes = np.asarray(planes)
    return np.abs(points @ planes[..., :3].T + planes[..., 3])


def ransac_plane(
    points: np.ndarray,
    threshold: float = 0.15,
    iterations: int = 200,
    max_tilt_deg: float = 80.0,
    seed: int = 0,
) -> np.ndarray | None:
    """The plane with most inliers among ``points`` (N, 3) by RANSAC, refined by total
    least squares (the inliers' principal axes).

    All ``iterations`` samples of three points are drawn and scored at once, and ties go
    to the first: the result depends on ``seed`` alone. (Open3D's ``segment_plane`` scores
    its samples in parallel and, on the small point sets of super-pixels, breaks ties by
    thread timing, so its planes change from run to run.)

    Returns (4,) plane with n_z > 0, or None for fewer than 6 points or a plane steeper
    than ``max_tilt_deg`` (a wall or a tree, not a roof).
    """
    if len(points) < 6:
        return None
    centre = points.mean(axis=0)
    local = points - centre
    rng = np.random.default_rng(seed)
    a, b, c = (local[rng.integers(0, len(local), iterations)] for _ in range(3))
    u, v = b - a, c - a  # their cross product, written out: np.cross costs more on (200, 3)
    normals = u[:, [1, 2, 0]] * v[:, [2, 0, 1]] - u[:, [2, 0, 1]] * v[:, [1, 2, 0]]
    length = np.sqrt(np.sum(normals * normals, axis=1))
    ok = length > 1e-12
    if not ok.any():
        return None
    normals = normals[ok] / length[ok, None]
    offsets = -np.sum(normals * a[ok], axis=1)
    distance = local @ normals.T  # (N, samples), in place: the largest arrays of the path
    distance += offsets
    np.abs(distance, out=distance)
    inlier = distance < threshold
    inl = local[inlier[:, np.argmax(np.count_nonzero(inlier, axis=0))]]
    if len(inl) < 3:
        return None
    mean = inl.mean(axis=0)
    normal = np.linalg.svd(inl - mean, full_matrices=False)[2][-1]
    if normal[2] < 0:
        normal = -normal
    if normal[2] < np.cos(np.radians(max_tilt_deg)):
        return None
    return np.r_[normal, -normal @ (mean + centre)]


def sequential_planes(
    points: np.ndarray,
    tolerance: float,
    min_points: int,
    max_planes: int,
    max_tilt_deg: float,
    seed: int,
) -> np.ndarray:
    """Planes of a point set by sequential RANSAC: the plane with most inliers within
    ``tolerance`` metres, its inliers removed, again, while a plane gathers at least
    ``min_points`` of the points left and no more than ``max_planes`` are found.

    Parameters
    ----------
    points : (N, 3) float
        Metres, near a local origin.
    max_tilt_deg : float
        Steeper planes are walls or trees, not roofs: the search stops at one.
    seed : int
        The k-th plane's RANSAC draws with ``seed + k``.

    Returns
    -------
    (P, 4) planes, P <= ``max_planes``. A point within ``tolerance`` of any of them was
    one of their inliers.
    """
    planes = []
    left = np.asarray(points, np.float64)
    while len(left) >= max(min_points, 6) and len(planes) < max_planes:
        plane = ransac_plane(
            left, tolerance, iterations=300, max_tilt_deg=max_tilt_deg, seed=seed + len(planes)
        )
        if plane is None:
            break
        inlier = point_plane_distances(plane, left) < tolerance
        if inlier.sum() < min_points:
            break
        planes.append(plane)
        left = left[~inlier]
    return np.array(planes).reshape(-1, 4)
