"""Shape detection with regularity (the LOD paper, section 5.3): roof directions found by
a RANSAC whose hypotheses are snapped to the vertical planes of the facade directions and
counted with their z-symmetric twins (eq. 8), then roof planes along those directions on
the height map: parallel and z-symmetric by construction."""

from __future__ import annotations

import numpy as np

FLAT_DEG = 5.0  # a normal within this of the vertical is a flat roof's
STEEPEST_DEG = 70.0  # a surface steeper than this is a wall, not a roof


def snap_to_facades(n: np.ndarray, theta: float) -> np.ndarray:
    """(N, 3) normals moved into the nearest vertical plane through a facade direction
    (theta or theta + 90 degrees): a roof's normal lies in the plane of z and a facade's
    normal (the paper after Kelly and Wonka)."""
    n = np.atleast_2d(n)
    out = np.empty_like(n)
    for i, v in enumerate(n):
        best = None
        for a in (theta, theta + np.pi / 2):
            d = np.array([np.cos(a), np.sin(a)])
            h = (v[:2] @ d) * d
            cand = np.array([h[0], h[1], v[2]])
            dist = np.linalg.norm(cand - v)
            if best is None or dist < best[0]:
                best = (dist, cand)
        out[i] = best[1] / np.linalg.norm(best[1])
    return out


def z_symmetric(n: np.ndarray) -> np.ndarray:
    """The z-symmetric counterpart (-n_x, -n_y, n_z) of normals (N, 3)."""
    return np.asarray(n) * [-1.0, -1.0, 1.0]


def roof_directions(
    normals: np.ndarray,
    theta: float,
    angle_deg: float = 10.0,
    min_count: int = 20,
    iterations: int = 300,
    seed: int = 0,
) -> list[np.ndarray]:
    """Roof directions by RANSAC (eq. 8): a hypothesis, snapped to the facades' vertical
    planes, counts the normals within ``angle_deg`` of it or of its z-symmetric twin; the
    largest consensus is kept, its inliers removed, and again while one holds at least
    ``min_count``. The vertical (flat roofs) comes first when it holds that many. Normals
    steeper than ``STEEPEST_DEG`` are a wall's (a mesh rounds its eaves) and take no part.

    Parameters
    ----------
    normals : (N, 3) unit normals of the building's cells (n_z > 0)

    Returns
    -------
    list of (3,) unit directions (each standing for itself and its z-symmetric twin)
    """
    rng = np.random.default_rng(seed)
    cos_tol = np.cos(np.radians(angle_deg))
    left = normals[np.isfinite(normals).all(axis=1)]
    left = left[left[:, 2] >= np.cos(np.radians(STEEPEST_DEG))]  # the walls' rounded tops
    out = []
    flat = left[:, 2] >= np.cos(np.radians(FLAT_DEG))
    if flat.sum() >= min_count:
        out.append(np.array([0.0, 0.0, 1.0]))
    left = left[~(left[:, 2] >= cos_tol)]
    while len(left) >= min_count:
        hyp = snap_to_facades(left[rng.choice(len(left), min(iterations, len(left)),
                                              replace=False)], theta)  # fmt: skip
        cos_a, cos_b = left @ hyp.T, left @ z_symmetric(hyp).T
        counts = ((cos_a >= cos_tol) | (cos_b >= cos_tol)).sum(axis=0)
        k = int(np.argmax(counts))
        if counts[k] < min_count:
            break
        out.append(hyp[k])
        left = left[~((cos_a[:, k] >= cos_tol) | (cos_b[:, k] >= cos_tol))]
    return out


def roof_planes(
    points: np.ndarray,
    normals: np.ndarray,
    directions: list[np.ndarray],
    angle_deg: float,
    inlier_m: float,
    min_count: int,
) -> np.ndarray:
    """Planes along the roof directions (and their z-symmetric twins) on the height map:
    for each direction, the cells whose normal lies within ``angle_deg`` of it vote for
    the offset d = -n . X; the densest offset (a window of ``inlier_m``) gives a plane, its
    inliers leave, and again while ``min_count`` cells remain.

    Parameters
    ----------
    points : (N, 3) the building's cells as points (metres, local frame)
    normals : (N, 3) their unit normals

    Returns
    -------
    (P, 4) planes (n, d), n . X + d = 0, unit n with n_z > 0
    """
    cos_tol = np.cos(np.radians(angle_deg))
    planes = []
    taken = np.zeros(len(points), bool)
    for base in directions:
        twins = [base] if base[2] > 0.999 else [base, z_symmetric(base)]
        for n in twins:
            near = (normals @ n >= cos_tol) & ~taken
            while near.sum() >= min_count:
                d = -(points[near] @ n)
                d_sorted = np.sort(d)
                # the densest window of width 2 * inlier_m
                j = np.searchsorted(d_sorted, d_sorted + 2 * inlier_m)
                k = int(np.argmax(j - np.arange(len(d_sorted))))
                if j[k] - k < min_count:
                    break
                centre = float(np.median(d_sorted[k : j[k]]))
                plane = np.array([*n, centre])
                members = np.flatnonzero(near & on_plane(points, normals, plane, angle_deg,
                                                         inlier_m))  # fmt: skip
                planes.append(plane)
                taken[members] = True
                near[members] = False
    return np.asarray(planes, np.float64).reshape(-1, 4)


def on_plane(
    points: np.ndarray, normals: np.ndarray, plane: np.ndarray, angle_deg: float, inlier_m: float
) -> np.ndarray:
    """(N,) bool the points that :func:`roof_planes` counts on ``plane`` ((4,) n, d):
    their unit normals ((N, 3)) within ``angle_deg`` of n, and the points ((N, 3),
    metres) within ``inlier_m`` of the plane."""
    n = plane[:3]
    return (normals @ n >= np.cos(np.radians(angle_deg))) & (
        np.abs(points @ n + plane[3]) <= inlier_m
    )
