"""Pitched roofs on the proxies (the voxel paper's future work, section 7; ours).

The 1D k-means of section 4.3 gives every roof level one height: a gable, hipped or
pyramid roof becomes one flat slab at a height between its eaves and its ridge, or a
stack of slabs. The paper names the remedy: where the clustering leaves a high error, fit
planes. Here a proxy whose observed heights planes explain much better than its levels
(:func:`pitched_planes`) is cut into faces, each on a plane fitted by sequential RANSAC
to those heights. The heights are the fusion's, at its cells (k x k per voxel column), so
that ridges and hips follow the roof rather than the voxel staircase; each cell takes the
plane nearest its height. Otherwise the levels stay: horizontal planes at their heights.
The proxy mesh is then the closed roof model of these faces
(:func:`modeling.shared.roof_model.closed_roof_model`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from workbench.planes import plane_heights, point_plane_distances, sequential_planes

_SQUARE = np.ones((3, 3), bool)
MAX_PLANES = 8  # per roof level: a cross-gabled roof has 4 to 6
HORIZONTAL_DEG = 5.0  # planes flatter are flat roofs, put level (as roof_types.roof_type says)
MAX_TILT_DEG = 75.0  # steeper is a wall (a mansard's lower faces are 60-70 degrees)


@dataclass
class RoofFaces:
    """A proxy's roof as planar faces on a grid finer than the voxels.

    Attributes
    ----------
    faces : (nx * k, ny * k) int
        Plane index + 1 of every fine cell (k x k per voxel column, in the column's
        order: x along axis 0, y along axis 1), 0 outside the proxy.
    planes : (F, 4) float
        Planes (n, d), n . (x, y, z) + d = 0 with x, y the frame's local coordinates and
        z height above the frame's base, metres; n_z > 0.
    k : int
        Fine cells per voxel side.
    pitched : bool
        Whether the planes were fitted (else they are the flat levels').
    """

    faces: np.ndarray
    planes: np.ndarray
    k: int
    pitched: bool

    def column_tops(self, r: float, x0: float, y0: float) -> np.ndarray:
        """(nx, ny) height of the roof over each voxel column (the median of its fine
        cells), metres above the base; -inf where the column is empty."""
        h = self.fine_heights(r, x0, y0)
        shape = (self.faces.shape[0] // self.k, self.faces.shape[1] // self.k)
        tops = column_medians(np.where(np.isfinite(h), h, np.nan), shape)
        return np.where(np.isfinite(tops), tops, -np.inf)

    def fine_heights(self, r: float, x0: float, y0: float) -> np.ndarray:
        """(nx * k, ny * k) roof height of every fine cell, metres above the base (-inf
        outside)."""
        fx, fy = fine_centres(self.faces.shape, r / self.k, x0, y0)
        out = np.full(self.faces.shape, -np.inf)
        for f in range(1, len(self.planes) + 1):
            m = self.faces == f
            out[m] = plane_heights(self.planes[f - 1], fx[m], fy[m])
        return out


def column_medians(fine: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(nx, ny) median of the known values of ``fine`` (nx * k, ny * k) over each column's
    k x k cells, NaN where none is known."""
    nx, ny = shape
    k = fine.shape[0] // nx
    blocks = fine.reshape(nx, k, ny, k).transpose(0, 2, 1, 3).reshape(nx, ny, k * k)
    known = np.isfinite(blocks).any(axis=2)
    out = np.full(shape, np.nan)
    if known.any():
        out[known] = np.nanmedian(blocks[known], axis=1)
    return out


def fine_centres(shape: tuple[int, int], cell: float, x0: float, y0: float):
    """Local x, y (each ``shape``) of the centres of a grid of ``cell``-metre cells whose
    corner is (x0, y0), x along axis 0."""
    x = x0 + (np.arange(shape[0]) + 0.5) * cell
    y = y0 + (np.arange(shape[1]) + 0.5) * cell
    return np.meshgrid(x, y, indexing="ij")


def flat_planes(level_heights: np.ndarray) -> np.ndarray:
    """(K, 4) horizontal planes at the heights (K,) of roof levels 1..K."""
    h = np.asarray(level_heights, np.float64)
    return np.column_stack([np.zeros((len(h), 2)), np.ones(len(h)), -h])


def level_planes(planes: np.ndarray, points: np.ndarray, max_deg: float) -> np.ndarray:
    """``planes`` (P, 4) with those flatter than ``max_deg`` made horizontal at the median
    height of the ``points`` (N, 3) nearest to them."""
    out = planes.copy()
    if not len(planes):
        return out
    nearest = np.argmin(point_plane_distances(planes, points).reshape(len(points), -1), axis=1)
    for p in np.flatnonzero(planes[:, 2] > np.cos(np.radians(max_deg))):
        mine = points[nearest == p, 2]
        if len(mine):
            out[p] = [0.0, 0.0, 1.0, -float(np.median(mine))]
    return out


def pitched_planes(
    points: np.ndarray,
    level_error: float,
    tolerance: float,
    min_points: int,
    gain: float,
    seed: int,
) -> np.ndarray | None:
    """The roof planes of a building's columns if planes explain their heights much
    better than its flat levels do, else None.

    Parameters
    ----------
    points : (N, 3) float
        Local x, y of the building's roof columns and their observed heights above the
        base, metres.
    level_error : float
        Median absolute difference between those heights and their columns' level
        heights, metres: the error the 1D k-means leaves (a median, so that a few stray
        columns decide nothing).
    tolerance : float
        RANSAC inlier distance, metres.
    min_points : int
        Fewest columns a plane takes.
    gain : float
        The planes must bring the median absolute height error down to this fraction
        of ``level_error``, or the levels stay.

    Returns
    -------
    (P, 4) planes (those flatter than ``HORIZONTAL_DEG`` made level) or None.
    """
    if len(points) < 2 * min_points:
        return None
    planes = sequential_planes(points, tolerance, min_points, MAX_PLANES, MAX_TILT_DEG, seed)
    if len(planes) == 0:
        return None
    planes = level_planes(planes, points, HORIZONTAL_DEG)
    residual = point_plane_distances(planes, points).reshape(len(points), -1).min(axis=1)
    if np.median(residual) > gain * level_error:
        return None
    return planes


def assign_cells(
    region: np.ndarray, points_ij: np.ndarray, points: np.ndarray, planes: np.ndarray
) -> np.ndarray:
    """(H, W) plane index + 1 of every cell of ``region``: the plane nearest each
    observed cell's height, smoothed by a 3 x 3 majority, and for unobserved cells the
    plane of the nearest observed one; 0 outside the region.

    ``points_ij`` (N, 2) are the observed cells' indices, ``points`` (N, 3) their local
    x, y and heights."""
    d = point_plane_distances(planes, points).reshape(len(points), -1)
    label = np.zeros(region.shape, np.int64)
    label[points_ij[:, 0], points_ij[:, 1]] = np.argmin(d, axis=1) + 1
    votes = np.stack(
        [ndimage.convolve((label == p).astype(np.int64), _SQUARE.astype(np.int64))
         for p in range(1, len(planes) + 1)]
    )  # fmt: skip
    smooth = np.argmax(votes, axis=0) + 1
    label = np.where(label > 0, smooth, 0)
    _, (ii, jj) = ndimage.distance_transform_edt(label == 0, return_indices=True)
    return np.where(region, label[ii, jj], 0)


def refit_planes(
    labels: np.ndarray,
    points_ij: np.ndarray,
    points: np.ndarray,
    planes: np.ndarray,
    tolerance: float,
) -> np.ndarray:
    """Each plane refitted by total least squares to the observed cells inside its face
    (those whose 8 neighbours are on it too: the cells along a ridge or a hip mix both
    sides) that lie within ``tolerance`` metres of it (the fused heights blur a step of
    a multi-level roof over a metre), kept as it is where fewer than 6 are; flat planes
    stay level."""
    out = planes.copy()
    label = labels[points_ij[:, 0], points_ij[:, 1]]
    for p in range(1, len(planes) + 1):
        core = ndimage.binary_erosion(labels == p, _SQUARE)
        near = point_plane_distances(planes[p - 1], points) < tolerance
        mine = points[core[points_ij[:, 0], points_ij[:, 1]] & (label == p) & near]
        if len(mine) < 6:
            continue
        if planes[p - 1, 0] == 0 and planes[p - 1, 1] == 0:
            out[p - 1] = [0.0, 0.0, 1.0, -float(np.median(mine[:, 2]))]
            continue
        mean = mine.mean(axis=0)
        normal = np.linalg.svd(mine - mean, full_matrices=False)[2][-1]
        normal = -normal if normal[2] < 0 else normal
        out[p - 1] = np.r_[normal, -normal @ mean]
    return out


def absorb_small_regions(
    faces: np.ndarray,
    planes: np.ndarray,
    fine_h: np.ndarray,
    heights: np.ndarray,
    min_cells: int,
) -> np.ndarray:
    """Connected face regions smaller than ``min_cells`` join the neighbouring face whose
    plane lies nearest the heights observed over them (``fine_h``, NaN unknown; where
    none is known, the lowest). The mesh would otherwise join a sliver beside a ridge to
    whichever face it shares most boundary with, perhaps the one across the ridge, whose
    plane rises above the roof there.

    ``heights`` (P, H, W) are each plane's heights at every cell."""
    out = faces.copy()
    for p in range(1, len(planes) + 1):
        parts, n = ndimage.label(out == p)
        sizes = np.bincount(parts.ravel(), minlength=n + 1)
        for part in np.flatnonzero(sizes[1:] < min_cells) + 1:
            region = parts == part
            ring = ndimage.binary_dilation(region, _SQUARE) & ~region & (out > 0)
            others = np.unique(out[ring])
            others = others[others != p]
            if not len(others):
                continue
            known = region & np.isfinite(fine_h)
            if known.any():
                cost = [np.median(np.abs(heights[q - 1][known] - fine_h[known])) for q in others]
            else:
                cost = [np.mean(heights[q - 1][region]) for q in others]
            out[region] = others[int(np.argmin(cost))]
    return out


def roof_faces(
    levels: np.ndarray,
    level_heights: np.ndarray,
    fine_h: np.ndarray,
    r: float,
    x0: float,
    y0: float,
    *,
    tolerance: float,
    gain: float,
    min_points: int,
    min_height: float,
    min_region_m2: float = 2.0,
    seed: int = 0,
) -> RoofFaces:
    """The roof of one proxy: planes fitted to the heights observed over it where they
    explain them much better than the flat levels (:func:`pitched_planes`), else the
    levels.

    Parameters
    ----------
    levels : (nx, ny) int
        Filtered roof levels, 0 empty.
    level_heights : (K,) float
        Heights of levels 1..K above the base, metres.
    fine_h : (nx * k, ny * k) float
        Observed heights above the base at k x k fine cells per column (the fusion's
        nDSM; without one the middle of each column's photo-consistent run, k = 1),
        metres, NaN unknown.
    r, x0, y0 : float
        Voxel size and the grid's local corner, metres.
    tolerance, gain, seed
        See :func:`pitched_planes`.
    min_points : int
        Fewest columns a plane takes.
    min_height : float
        Cells lower than this are ground, not roof, metres.
    min_region_m2 : float
        Smaller connected parts of a face join a neighbour
        (:func:`absorb_small_regions`), square metres.
    """
    k = fine_h.shape[0] // levels.shape[0]
    flat = RoofFaces(np.kron(levels, np.ones((k, k), np.int64)), flat_planes(level_heights), k,
                     False)  # fmt: skip
    region = flat.faces > 0
    # planes are fitted to the fine cells: a column on a ridge or on the outline mixes two
    # faces, or the roof and the ground; cells below ``min_height`` are ground
    with np.errstate(invalid="ignore"):
        obs = region & (fine_h >= min_height)
    if not obs.any():
        return flat
    fx, fy = fine_centres(region.shape, r / k, x0, y0)
    points = np.column_stack([fx[obs], fy[obs], fine_h[obs]])
    level_error = float(np.median(np.abs(fine_h[obs] - level_heights[flat.faces[obs] - 1])))
    planes = pitched_planes(points, level_error, tolerance, min_points * k * k, gain, seed)
    if planes is None:
        return flat
    ij = np.argwhere(obs)
    min_region_cells = max(1, int(round(min_region_m2 / (r / k) ** 2)))
    # a face may not rise above the highest height observed nor sink below the base: a
    # steep plane through the cells beside a step of a multi-level roof would
    lo, hi = 0.0, points[:, 2].max() + tolerance
    while len(planes):
        for _ in range(2):  # RANSAC's inliers reach across ridges: refit on face cores
            faces = assign_cells(region, ij, points, planes)
            planes = refit_planes(faces, ij, points, planes, tolerance)
        faces = assign_cells(region, ij, points, planes)
        # a refit on a face's core can stand a plane on end (the cells of a wall): its
        # heights are infinite, its excess below the largest, and it is dropped below
        with np.errstate(divide="ignore", invalid="ignore"):
            heights = np.stack([plane_heights(q, fx, fy) for q in planes])
            faces = absorb_small_regions(faces, planes, fine_h, heights, min_region_cells)
            h = RoofFaces(faces, planes, k, True).fine_heights(r, x0, y0)
        # a cell nothing was seen on (the fusion's blind spot behind a high wall) whose
        # plane would rise above everything seen is past the roof's edge, not roof: a
        # shed's plane carried on over them rose 1.4 m above the highest cell seen
        faces = np.where(~obs & (h > hi), 0, faces)
        roof = RoofFaces(faces, planes, k, True)
        excess = np.maximum(h - hi, lo - h)
        # a tenth of a face may overshoot (cells a little past a ridge, on its other side)
        out_of_range = [
            np.percentile(excess[faces == p], 90) if (faces == p).any() else 0.0
            for p in range(1, len(planes) + 1)
        ]
        worst = int(np.argmax(out_of_range))
        if out_of_range[worst] <= 0:
            return capped(roof, h, hi)
        planes = np.delete(planes, worst, axis=0)
    return flat


def capped(roof: RoofFaces, heights: np.ndarray, top: float) -> RoofFaces:
    """``roof`` with the cells where their plane rises above ``top`` given to a flat face
    at ``top``.

    The tenth of a face allowed past its range (:func:`roof_faces`) is a few cells past a
    ridge on a gentle roof, but on a steep plane carried past a step of a multi-level
    roof those cells rise metres above everything seen; no roof may.

    Parameters
    ----------
    roof : RoofFaces
    heights : (nx * k, ny * k) float
        ``roof.fine_heights``, metres above the base.
    top : float
        The highest height observed over the roof plus the plane tolerance, metres.
    """
    over = (roof.faces > 0) & (heights > top)
    if not over.any():
        return roof
    planes = np.vstack([roof.planes, flat_planes(np.array([top]))])
    return RoofFaces(np.where(over, len(planes), roof.faces), planes, roof.k, roof.pitched)
