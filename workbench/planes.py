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
    least squares (the inliers' principal axes): :func:`ransac_planes` for one point set.

    Returns (4,) plane with n_z > 0, or None for fewer than 6 points or a plane steeper
    than ``max_tilt_deg`` (a wall or a tree, not a roof).
    """
    plane = ransac_planes([points], threshold, iterations, max_tilt_deg, seed)[0]
    return None if np.isnan(plane[0]) else plane


RANSAC_CHUNK_CELLS = 4_000_000  # (sets, points, samples) distances scored at once: 32 MB


def ransac_planes(
    point_sets: list[np.ndarray],
    threshold: float = 0.15,
    iterations: int = 200,
    max_tilt_deg: float = 80.0,
    seed: int = 0,
) -> np.ndarray:
    """:func:`ransac_plane` of each of many point sets, scored together.

    Sets of up to twice the smallest one's size are stacked (padded with points that are
    never inliers) and all their samples scored by one stacked matrix product, instead of
    a call per set. Scoring 200 samples is most of the work, so this gains little (the
    2,600 super-pixels of `small` seed 0: 0.10 against 0.12 s); stacking sets of any size
    together padded them to the largest and was slower than the calls.

    Each set draws ``iterations`` samples of three points with ``seed``, all scored at
    once, and ties go to the first sample: a set's plane depends on ``seed`` and on its
    own points alone, not on the other sets. (Open3D's ``segment_plane`` scores its
    samples in parallel and, on the small point sets of super-pixels, breaks ties by
    thread timing, so its planes change from run to run.)

    Parameters
    ----------
    point_sets : list of (N_k, 3) float
        Metres, near a local origin.
    threshold : float
        Inlier distance, metres.
    iterations : int
        Samples per set.
    max_tilt_deg : float
        Steeper planes are walls or trees, not roofs.
    seed : int

    Returns
    -------
    (S, 4) planes (nx, ny, nz, d) with n_z > 0; a row of NaN for a set with fewer than 6
    points, no three points off a line, fewer than 3 inliers or a plane steeper than
    ``max_tilt_deg``.
    """
    sizes = np.array([len(p) for p in point_sets], np.int64)
    out = np.full((len(sizes), 4), np.nan)
    draws: dict[int, np.ndarray] = {}  # sets of one size draw the same samples
    for n in np.unique(sizes[sizes >= 6]).tolist():
        rng = np.random.default_rng(seed)
        draws[n] = np.stack([rng.integers(0, n, iterations) for _ in range(3)])
    order = [k for k in np.argsort(sizes, kind="stable").tolist() if sizes[k] >= 6]
    while order:  # sets of up to twice the smallest's size together: at most half padding
        first = int(sizes[order[0]])
        count = np.searchsorted(sizes[order], 2 * first, side="right")
        count = int(max(1, min(count, RANSAC_CHUNK_CELLS // (iterations * 2 * first))))
        chunk, order = order[:count], order[count:]
        out[chunk] = _stacked_ransac([point_sets[k] for k in chunk], draws, threshold,
                                     max_tilt_deg)  # fmt: skip
    return out


def _stacked_ransac(
    point_sets: list[np.ndarray], draws: dict, threshold: float, max_tilt_deg: float
) -> np.ndarray:
    """(S, 4) planes of :func:`ransac_planes` for sets of 6 points or more, padded to the
    largest and scored by one stacked matrix product."""
    sizes = np.array([len(p) for p in point_sets], np.int64)
    S, N = len(sizes), int(sizes.max())
    real = np.arange(N) < sizes[:, None]  # (S, N)
    points = np.zeros((S, N, 3))
    points[real] = np.concatenate(point_sets)
    centre = points.sum(axis=1) / sizes[:, None]
    local = points - centre[:, None]
    local[~real] = np.nan  # padding: never an inlier, whatever the plane
    picks = np.stack([draws[n] for n in sizes.tolist()])  # (S, 3, I)
    a, b, c = (np.take_along_axis(local, picks[:, j, :, None], axis=1) for j in range(3))
    u, v = b - a, c - a  # their cross product, written out: np.cross costs more
    normals = u[..., [1, 2, 0]] * v[..., [2, 0, 1]] - u[..., [2, 0, 1]] * v[..., [1, 2, 0]]
    length = np.sqrt(np.sum(normals * normals, axis=-1))  # (S, I)
    drawn = length > 1e-12  # three points off a line
    normals = np.divide(normals, length[..., None], out=np.zeros_like(normals),
                        where=drawn[..., None])  # fmt: skip
    distance = local @ normals.transpose(0, 2, 1)  # (S, N, I): the largest arrays of the path
    distance -= np.sum(normals * a, axis=-1)[:, None, :]
    np.abs(distance, out=distance)
    inlier = distance < threshold
    votes = np.where(drawn, np.count_nonzero(inlier, axis=1), -1)
    best = np.argmax(votes, axis=1)
    inl = np.take_along_axis(inlier, best[:, None, None], axis=2)[..., 0]  # (S, N)
    counts = inl.sum(axis=1)
    mean = np.where(inl[..., None], local, 0.0).sum(axis=1) / np.maximum(counts, 1)[:, None]
    centred = np.where(inl[..., None], local - mean[:, None], 0.0)
    scatter = np.einsum("sni,snj->sij", centred, centred)
    normal = np.linalg.eigh(scatter)[1][:, :, 0]  # the inliers' least principal axis
    normal *= np.where(normal[:, 2] < 0, -1.0, 1.0)[:, None]
    planes = np.c_[normal, -np.sum(normal * (mean + centre), axis=1)]
    planes[(counts < 3) | (normal[:, 2] < np.cos(np.radians(max_tilt_deg)))] = np.nan
    return planes


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
