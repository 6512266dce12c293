"""Volumetric building proxies (the voxel paper, section 4).

Each building is a voxel grid over its over-estimated footprint, aligned with the
footprint's dominant direction. Every voxel's colour in the views that face it gives a
photo-consistency variance (eq. 2, 3); the most consistent voxel of each column gives its
roof height; 1D k-means turns those heights into a few roof levels, morphology cleans the
height map, and the exterior surface becomes a closed low-polygon mesh.

Voxel (i, j, k) of a frame has its centre at local (x0 + (i + 0.5) r, y0 + (j + 0.5) r)
and height ``base_z + k r``: layer 0 lies on the ground, so a column whose most
consistent voxel is in layer 0 is ground.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import shapely
from scipy import ndimage
from shapely.geometry import Polygon
from sklearn.cluster import KMeans

from modeling.shared.roof_model import closed_roof_model
from workbench.camera import Camera
from workbench.model_run import Building, Surface
from workbench.raster import Grid
from workbench.raycast import occluded

from .roof_planes import RoofFaces
from .view_images import ViewImages

_CROSS = ndimage.generate_binary_structure(2, 1)
_SQUARE = np.ones((3, 3), bool)


@dataclass(frozen=True)
class VoxelFrame:
    """The voxel grid of one building.

    Attributes
    ----------
    origin : (2,) ndarray
        World x, y of the local origin, metres.
    axes : (2, 2) ndarray
        Rows: the local x and y unit vectors in world x, y.
    x0, y0 : float
        Local coordinates of the grid's corner, metres.
    r : float
        Voxel size, metres.
    shape : (nx, ny, nz)
    base_z : float
        Ground height under the building (layer 0), metres.
    """

    origin: np.ndarray
    axes: np.ndarray
    x0: float
    y0: float
    r: float
    shape: tuple[int, int, int]
    base_z: float

    def to_world_xy(self, local: np.ndarray) -> np.ndarray:
        """(N, 2) local x, y -> (N, 2) world x, y."""
        return self.origin + np.asarray(local) @ self.axes

    def to_local_xy(self, world: np.ndarray) -> np.ndarray:
        """(N, 2) world x, y -> (N, 2) local x, y."""
        return (np.asarray(world) - self.origin) @ self.axes.T

    def column_local(self) -> tuple[np.ndarray, np.ndarray]:
        """Local x, y of the column centres, each (nx, ny)."""
        nx, ny, _ = self.shape
        x = self.x0 + (np.arange(nx) + 0.5) * self.r
        y = self.y0 + (np.arange(ny) + 0.5) * self.r
        return np.meshgrid(x, y, indexing="ij")

    def column_centres(self) -> np.ndarray:
        """(nx, ny, 2) world x, y of the column centres."""
        lx, ly = self.column_local()
        nx, ny, _ = self.shape
        return self.to_world_xy(np.column_stack([lx.ravel(), ly.ravel()])).reshape(nx, ny, 2)

    def layer_z(self) -> np.ndarray:
        """(nz,) heights of the voxel centres, metres."""
        return self.base_z + np.arange(self.shape[2]) * self.r

    def voxel_centres(self, columns: np.ndarray) -> np.ndarray:
        """(M, nz, 3) world centres of the voxels of the ``columns`` (nx, ny) bool."""
        xy = self.column_centres()[columns]
        z = self.layer_z()
        m, nz = len(xy), len(z)
        return np.concatenate(
            [np.broadcast_to(xy[:, None, :], (m, nz, 2)), np.broadcast_to(z, (m, nz))[..., None]],
            axis=2,
        )


def dominant_axes(polygon: Polygon) -> np.ndarray:
    """(2, 2) local x and y unit vectors: x along the longest side of the minimum rotated
    rectangle of ``polygon``, y to its left."""
    ring = np.asarray(polygon.minimum_rotated_rectangle.exterior.coords)[:4]
    sides = np.diff(np.vstack([ring, ring[:1]]), axis=0)
    x = sides[np.argmax(np.hypot(sides[:, 0], sides[:, 1]))]
    x = x / np.hypot(*x)
    if x[0] < 0 or (x[0] == 0 and x[1] < 0):
        x = -x
    return np.array([x, [-x[1], x[0]]])


def voxelise(
    polygon: Polygon, height: float, base_z: float, r: float, grow: float
) -> tuple[VoxelFrame, np.ndarray]:
    """The voxels of the vertical extrusion of a footprint (section 4.1).

    Parameters
    ----------
    polygon : Polygon
        GIS footprint, world metres.
    height : float
        Its over-estimated height above ``base_z``, metres.
    base_z : float
        Ground height, metres.
    r : float
        Voxel size, metres.
    grow : float
        The footprint is grown by this much first, metres, so that a true outline
        displaced from the GIS one still lies inside the voxels.

    Returns
    -------
    frame : VoxelFrame
    columns : (nx, ny) bool
        Columns whose centre lies in the grown footprint.
    """
    axes = dominant_axes(polygon)
    origin = np.asarray(polygon.centroid.coords[0])
    grown = polygon.buffer(grow, join_style="mitre") if grow > 0 else polygon
    local = (np.asarray(grown.exterior.coords) - origin) @ axes.T
    lo = np.floor(local.min(axis=0) / r) * r
    hi = np.ceil(local.max(axis=0) / r) * r
    nx, ny = (np.round((hi - lo) / r).astype(int)).tolist()
    nz = int(np.ceil(height / r)) + 1
    frame = VoxelFrame(origin, axes, float(lo[0]), float(lo[1]), r, (nx, ny, nz), base_z)
    xy = frame.column_centres()
    columns = shapely.contains_xy(grown, xy[..., 0], xy[..., 1])
    return frame, columns


def ellipsoid_normals(frame: VoxelFrame, columns: np.ndarray) -> np.ndarray:
    """Initial voxel normals from the upper half-ellipsoid fitted to the building (eq. 1).

    The ellipsoid is centred on the grid's floor centre with semi-axes a, b through the
    corners of the grid's rectangle (sqrt(2) times its half-sides) and c its height.

    Returns
    -------
    (M, nz, 3) world unit normals of the voxels of ``columns``.
    """
    nx, ny, nz = frame.shape
    lx, ly = frame.column_local()
    x = (lx - (frame.x0 + nx * frame.r / 2))[columns]
    y = (ly - (frame.y0 + ny * frame.r / 2))[columns]
    z = np.arange(nz) * frame.r + frame.r / 2  # never 0: the floor's centre points up
    a = nx * frame.r / 2 * np.sqrt(2)
    b = ny * frame.r / 2 * np.sqrt(2)
    c = max(nz * frame.r, frame.r)
    m = len(x)
    n_local = np.empty((m, nz, 3))
    n_local[..., 0] = (2 * x / a**2)[:, None]
    n_local[..., 1] = (2 * y / b**2)[:, None]
    n_local[..., 2] = (2 * z / c**2)[None, :]
    n = np.empty_like(n_local)
    n[..., :2] = n_local[..., :2] @ frame.axes
    n[..., 2] = n_local[..., 2]
    return n / np.linalg.norm(n, axis=2, keepdims=True)


def projected_half_width(camera: Camera, depth: np.ndarray, r: float) -> np.ndarray:
    """s_ik: half the size of a voxel of size ``r`` projected at z-depth ``depth``, whole
    pixels (at least 1)."""
    return np.maximum(0, np.round(camera.K[0, 0] * r / (2 * depth))).astype(np.int64)


@dataclass
class PhotoConsistency:
    """Per-voxel statistics of the chroma samples.

    Attributes
    ----------
    variance : (N,) float64
        Sum over H, S chroma channels of the variance over the views, NaN when fewer
        than two views saw the voxel.
    views : (N,) int
        Number of views that saw it (s_i).
    occluded_samples : int
        Samples dropped by the occlusion masks of the neighbouring buildings.
    """

    variance: np.ndarray
    views: np.ndarray
    occluded_samples: int


def voxel_variance(
    centres: np.ndarray,
    normals: np.ndarray,
    r: float,
    cameras: list[Camera],
    images: ViewImages,
    occluders=None,
    footprint_scale: float = 1.0,
    keep: float = 1.0,
    views: list[int] | None = None,
) -> PhotoConsistency:
    """Colour samples (eq. 2) of every voxel in the views that face it, and their variance
    (the bracket of eq. 3), accumulated view by view.

    Parameters
    ----------
    centres, normals : (N, 3)
        World voxel centres, metres, and their initial unit normals.
    r : float
        Voxel size, metres.
    cameras : list of Camera
        The scene's cameras; ``images`` serves view k of ``cameras[k]``.
    occluders : workbench.raycast.RayScene, optional
        The initial proxies of the neighbouring buildings: a sample whose line of sight
        crosses them is dropped (the paper's occlusion masks).
    views : list of int, optional
        The cameras to sample (default: all); the others see none of the voxels.
    """
    n = len(centres)
    views = list(range(len(cameras))) if views is None else list(views)
    samples = None
    dropped = 0
    for j, k in enumerate(views):
        cam = cameras[k]
        to_cam = cam.center - centres
        sel = np.flatnonzero(np.einsum("ij,ij->i", to_cam, normals) > 0)
        uv, depth = cam.project(centres[sel])
        s = projected_half_width(cam, np.where(depth > 0, depth, 1.0), r * footprint_scale)
        inside = (
            (depth > 0)
            & (uv[:, 0] >= s)
            & (uv[:, 1] >= s)
            & (uv[:, 0] <= cam.width - 1 - s)
            & (uv[:, 1] <= cam.height - 1 - s)
        )
        sel, uv, s = sel[inside], uv[inside], s[inside]
        if occluders is not None and len(sel):
            hidden = occluded(occluders, centres[sel], to_cam[sel], tfar=1.0)
            dropped += int(hidden.sum())
            sel, uv, s = sel[~hidden], uv[~hidden], s[~hidden]
        if not len(sel):
            continue
        c = images.consistency_samples(k, uv, s)
        if samples is None:
            samples = np.full((n, len(views), c.shape[1]), np.nan, np.float32)
        samples[sel, j] = c
    if samples is None:
        return PhotoConsistency(np.full(n, np.nan), np.zeros(n, np.int64), dropped)
    variance, views = sample_variance(samples, keep)
    return PhotoConsistency(variance, views, dropped)


def upward_views(
    pc: PhotoConsistency,
    centres: np.ndarray,
    min_views: float,
    sample: Callable[[np.ndarray, np.ndarray], PhotoConsistency],
) -> PhotoConsistency:
    """Sample again, as if on a roof (normal straight up), the voxels that fewer than
    ``min_views`` views face by their eq. 1 normal; keep whichever saw more views.

    At a footprint's corners the half-ellipsoid's normal is near horizontal: only the
    views on that side face it, and at the edge of the flown area there are none, so a
    building there loses its corner columns. Up is what a roof voxel faces.

    Parameters
    ----------
    pc : PhotoConsistency
        :func:`voxel_variance` with the eq. 1 normals, for the N ``centres``.
    centres : (N, 3)
        World voxel centres, metres.
    min_views : float
        Fewer views than this leave a voxel unknown.
    sample : callable
        ``sample(centres, normals)``: :func:`voxel_variance` with the building's views,
        occluders and window.

    Returns
    -------
    PhotoConsistency
        ``pc`` with those voxels replaced where the upward normal found more views.
    """
    few = np.flatnonzero(pc.views < min_views)
    if not len(few):
        return pc
    up = np.zeros((len(few), 3))
    up[:, 2] = 1.0
    again = sample(centres[few], up)
    better = again.views > pc.views[few]
    variance, views = pc.variance.copy(), pc.views.copy()
    variance[few[better]] = again.variance[better]
    views[few[better]] = again.views[better]
    return PhotoConsistency(variance, views, pc.occluded_samples + again.occluded_samples)


def sample_variance(samples: np.ndarray, keep: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The bracket of eq. 3 over the views, summed over colour channels, per voxel.

    Parameters
    ----------
    samples : (N, K, C) float
        Colour of each voxel in each view, NaN where the view does not see it.
    keep : float
        Fraction of each voxel's samples kept, those nearest the per-voxel median:
        1 is the paper's plain variance; less drops views where a tree or a building
        the masks do not know hides the voxel.

    Returns
    -------
    variance : (N,) float64, NaN with fewer than two samples kept
    views : (N,) int, samples seen (s_i)
    """
    seen = np.isfinite(samples[..., 0])
    views = seen.sum(axis=1)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if keep >= 1.0:
            variance = np.nansum(np.nanvar(samples, axis=1), axis=1)
            n_kept = views
        else:
            med = view_median(samples)
            d2 = np.sum((samples - med[:, None, :]) ** 2, axis=2)
            d2 = np.sort(np.where(seen, d2, np.inf), axis=1)
            n_kept = np.maximum(np.ceil(keep * views), np.minimum(views, 2)).astype(np.int64)
            ranks = np.arange(samples.shape[1])[None, :]
            kept = np.where(ranks < n_kept[:, None], d2, 0.0)
            variance = kept.sum(axis=1) / np.maximum(n_kept, 1)
    variance = np.where(n_kept >= 2, variance, np.nan).astype(np.float64)
    return variance, views


def view_median(samples: np.ndarray) -> np.ndarray:
    """``np.nanmedian(samples, axis=1)`` for (N, K, C) samples whose channels are NaN
    together, (N, C): one sort instead of NumPy's masked-array median, which took a
    quarter of a city building's photo-consistency (the same values, to the bit)."""
    n = np.isfinite(samples[:, :, :1]).sum(axis=1)  # (N, 1) views per voxel
    ordered = np.sort(samples, axis=1)  # NaN last
    shape = (len(samples), 1, samples.shape[2])
    lo = np.broadcast_to(np.maximum(n - 1, 0)[:, None, :] // 2, shape)
    hi = np.broadcast_to(n[:, None, :] // 2, shape)
    pair = np.take_along_axis(ordered, lo, axis=1) + np.take_along_axis(ordered, hi, axis=1)
    return np.where(n > 0, pair[:, 0] / samples.dtype.type(2), np.nan)


def height_weighted_variance(
    variance: np.ndarray, layer: np.ndarray, nz: int, height_weight: float
) -> np.ndarray:
    """m_i of eq. 3: the variance weighted down with the voxel's height, so that of two
    about equally consistent voxels the higher one wins.

    The printed weight (v_z + b_z/2)/b_z grows with height, against the text ("the
    inverted building height"): we use 1 - height_weight * layer / nz.

    Parameters
    ----------
    variance : (...,) float
    layer : (...,) int
        Layer index of each voxel (0 on the ground).
    nz : int
        Number of layers.
    height_weight : float
        In [0, 1): 0 ignores height.
    """
    return variance * (1.0 - height_weight * np.asarray(layer) / max(nz, 1))


def column_minimum(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The most consistent voxel of each column (section 4.3).

    Parameters
    ----------
    m : (M, nz) float
        m_i of every voxel of M columns, NaN where unknown.

    Returns
    -------
    layer : (M,) int
        Layer of the minimum, -1 for a column without any known voxel.
    value : (M,) float
        The minimum, NaN for those columns.
    """
    known = np.isfinite(m)
    filled = np.where(known, m, np.inf)
    layer = np.argmin(filled, axis=1)
    value = filled[np.arange(len(m)), layer]
    none = ~known.any(axis=1)
    layer[none] = -1
    value[none] = np.nan
    return layer, value


def highest_tied(m: np.ndarray, layer: np.ndarray, tolerance: float = 0.05) -> np.ndarray:
    """The highest voxel of each column about as consistent as its minimum: "given an
    approximately tied variance, the vertically higher voxel is chosen" (section 4.2).

    Below a roof of uniform colour, the voxels inside the building project onto the roof
    in the steep views and onto one facade in the few oblique views that face them, and
    can beat the roof; the roof is the top of what is consistent. A voxel ties when its
    m_i exceeds the column's minimum by at most ``tolerance`` times the spread between
    the minimum and the column's median (the measure of :func:`consistent_band`).

    Parameters
    ----------
    m : (M, nz) float
        m_i (NaN unknown).
    layer : (M,) int
        Layer of each column's minimum (-1 none), :func:`column_minimum`.

    Returns
    -------
    (M,) int
        Layer of the highest tied voxel (-1 where ``layer`` is).
    """
    near = _near_layer(m, layer, tolerance)
    top = m.shape[1] - 1 - np.argmax(near[:, ::-1], axis=1)
    return np.where(layer >= 0, top, layer)


def _near_layer(m: np.ndarray, layer: np.ndarray, tolerance: float) -> np.ndarray:
    """(M, nz) bool: voxels whose m_i exceeds that of the column's voxel at ``layer`` by
    at most ``tolerance`` times the spread from it to the column's median."""
    filled = np.where(np.isfinite(m), m, np.inf)
    m0 = filled[np.arange(len(m)), np.maximum(layer, 0)]
    med = _nanmedian(np.where(np.isfinite(m), m, np.nan), axis=1)
    spread = np.where(np.isfinite(med), np.maximum(med - m0, 0), 0.0)
    return filled <= (m0 + tolerance * spread)[:, None]


def consistent_band(
    m: np.ndarray, layer: np.ndarray, tolerance: float = 0.2
) -> tuple[np.ndarray, np.ndarray]:
    """Each column's run of near-minimal voxels around a voxel of it (its minimum, or
    the highest voxel tied with it, :func:`highest_tied`).

    On a roof of uniform colour the voxels just above and below it are about as
    consistent as the roof itself, and the minimum falls anywhere in that run; the run
    reaches no further from the roof than the column's distance to the roof's edge
    (beyond it, oblique views see past the edge). A voxel is near-minimal when its m_i
    exceeds that voxel's m_i by at most ``tolerance`` times the spread between it and the
    column's median.

    Parameters
    ----------
    m : (M, nz) float
        m_i (NaN unknown).
    layer : (M,) int
        Layer of the voxel each column's run is grown from (-1 none).

    Returns
    -------
    lo, hi : (M,) int
        First and last layer of the run (-1 for columns without a minimum).
    """
    near = _near_layer(m, layer, tolerance)
    nz = m.shape[1]
    idx = np.arange(nz)[None, :]
    lo = np.where(~near & (idx < layer[:, None]), idx, -1).max(axis=1) + 1
    hi = np.where(~near & (idx > layer[:, None]), idx, nz).min(axis=1) - 1
    none = layer < 0
    lo[none] = -1
    hi[none] = -1
    return lo, hi


def consensus_levels(
    lo: np.ndarray, hi: np.ndarray, labels: np.ndarray, n_clusters: int, nz: int, merge: float = 1.5
) -> tuple[np.ndarray, np.ndarray]:
    """Refine k-means clusters of column heights into roof levels every column agrees on.

    A cluster's level is the layer that lies in the consistent runs of most of its
    columns (the edge columns, whose runs are short, pin it down); levels closer than
    ``merge`` layers merge; each column then takes the best-supported level inside its
    own run, or the level nearest its run when none is.

    Parameters
    ----------
    lo, hi : (M,) int
        Consistent runs (:func:`consistent_band`).
    labels : (M,) int
        k-means cluster of each column.
    n_clusters, nz : int

    Returns
    -------
    labels : (M,) int
        Level of each column (into ``levels``).
    levels : (L,) float
        Level heights in layers, increasing.
    """
    idx = np.arange(nz)[None, :]
    inside = (idx >= lo[:, None]) & (idx <= hi[:, None])
    found = []
    for j in range(n_clusters):
        members = labels == j
        if not members.any():
            continue
        support = inside[members].sum(axis=0)
        found.append((float(np.flatnonzero(support == support.max()).mean()), int(support.max())))
    found.sort()
    levels, weights = [], []
    for z, w in found:
        if levels and z - levels[-1] < merge:
            if w > weights[-1]:
                levels[-1], weights[-1] = z, w
            continue
        levels.append(z)
        weights.append(w)
    levels_a = np.asarray(levels)
    z_layer = np.round(levels_a).astype(int)
    in_run = (z_layer[None, :] >= lo[:, None]) & (z_layer[None, :] <= hi[:, None])
    total = inside[:, z_layer].sum(axis=0)  # support of each level over all columns
    score = np.where(in_run, total[None, :], -1)
    centre = (lo + hi) / 2.0
    nearest = np.argmin(np.abs(levels_a[None, :] - centre[:, None]), axis=1)
    out = np.where(in_run.any(axis=1), np.argmax(score, axis=1), nearest)
    return out, levels_a


def variance_outliers(value: np.ndarray, n_sigma: float = 2.0) -> np.ndarray:
    """(M,) bool: columns whose minimum variance lies more than ``n_sigma`` standard
    deviations above the mean of all columns (their roof is not photo-consistent)."""
    ok = np.isfinite(value)
    if ok.sum() < 2:
        return ~ok
    mu, sd = value[ok].mean(), value[ok].std()
    return ~ok | (value > mu + n_sigma * sd)


def fused_fine_heights(frame: VoxelFrame, ndsm: np.ndarray, grid: Grid) -> np.ndarray:
    """(nx * k, ny * k) a fusion run's nDSM at k x k points per column, one per fusion
    cell (k = r / the fusion's cell size), x along axis 0; metres, NaN where the fusion
    saw nothing or outside its grid.

    Parameters
    ----------
    frame : VoxelFrame
    ndsm : (H, W) float, or what reads its windows (``ndsm[rows, cols]``)
        Height above the ground, metres, NaN unknown, on ``grid``; only the window
        around the frame is read.
    grid : Grid
    """
    nx, ny, _ = frame.shape
    k = max(1, int(round(frame.r / grid.gsd)))
    offsets = ((np.arange(k) + 0.5) / k - 0.5) * frame.r
    ox, oy = np.meshgrid(offsets, offsets, indexing="ij")
    lx, ly = frame.column_local()
    local = np.stack([lx[..., None] + ox.ravel(), ly[..., None] + oy.ravel()], axis=-1)
    world = frame.to_world_xy(local.reshape(-1, 2))
    row, col = grid.cell_index(world[:, 0], world[:, 1])
    inside = grid.contains(row, col)
    h = np.full(len(world), np.nan)
    if inside.any():
        row, col = row[inside], col[inside]
        r0, c0 = row.min(), col.min()
        h[inside] = ndsm[r0 : row.max() + 1, c0 : col.max() + 1][row - r0, col - c0]
    return h.reshape(nx, ny, k, k).transpose(0, 2, 1, 3).reshape(nx * k, ny * k)


def fused_ground_columns(fused: np.ndarray, min_height: float) -> np.ndarray:
    """(nx, ny) bool: columns a fusion run's nDSM puts on the ground.

    Beside a roof, the air above uniform paving is photo-consistent too: the steep views
    see the same grey below it and the few oblique views that see the facade behind it
    are dropped as outliers (``keep_views``), so eq. 3 keeps such columns at roof height.
    The fused heights of the dense matching do not share that blind spot. A column is on
    the ground when its fused height is below ``min_height``; columns the fusion did not
    see (NaN) are left to the photo-consistency.

    Parameters
    ----------
    fused : (nx, ny) float
        Fused height of each column, metres (the column medians of
        :func:`fused_fine_heights`).
    min_height : float
        Metres; lower columns are ground (the path's lowest roof level).
    """
    with np.errstate(invalid="ignore"):
        return fused < min_height


def fused_flat_levels(
    levels: np.ndarray,
    level_heights: np.ndarray,
    fused: np.ndarray,
    domain: np.ndarray,
    flat: float,
    merge: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Stand each flat roof level at the median fused height of its columns, grow it over
    the empty columns beside it at that height, and merge the levels that then lie closer
    than ``merge`` (not in the paper).

    Over a roof of uniform colour the voxels a metre or two above it, and on a low roof
    the paving beside it, are about as photo-consistent as the roof itself. k-means then
    splits the noisy heights of one flat roof into two levels that straddle it (for
    heights spread evenly or normally about one value, k = 2 always removes more than 30 %
    of the k = 1 error), and parts of the roof fall to the ground level or are discarded.
    Dense matching is not blind there. A level is flat when at least half its columns'
    fused heights lie within ``flat / 2`` of their median; it then stands at that median
    and takes every empty column of ``domain`` connected to it (4-neighbours) whose fused
    height lies as close to it. A pitched level, whose median lies below its ridge, keeps
    its photo-consistent height and extent: photo-consistency still decides which levels
    there are and where they stand.

    Parameters
    ----------
    levels : (nx, ny) int
        Roof level of each column (1 = lowest), 0 empty.
    level_heights : (K,) float
        Heights of levels 1..K, metres, increasing.
    fused : (nx, ny) float
        Fused height of each column, metres, NaN unknown (the column medians of
        :func:`fused_fine_heights`).
    domain : (nx, ny) bool
        Columns that may be building.
    flat, merge : float
        Metres.

    Returns
    -------
    levels : (nx, ny) int
        The levels in use, renumbered by increasing height (0 empty).
    level_heights : (K',) float
        Their heights; merged levels take the column-weighted mean of theirs.
    """
    heights = np.array(level_heights, dtype=np.float64)
    out = levels.copy()
    known = np.isfinite(fused)
    for lev in range(1, len(heights) + 1):
        region = levels == lev
        middle = flat_median(fused[region & known], flat)
        if middle is None:
            continue
        heights[lev - 1] = middle
        with np.errstate(invalid="ignore"):
            at_height = domain & (out == 0) & (np.abs(fused - heights[lev - 1]) <= flat / 2)
        grown = ndimage.binary_propagation(region, structure=_CROSS, mask=region | at_height)
        out[grown & (out == 0)] = lev
    used, size = np.unique(out[out > 0], return_counts=True)
    if not len(used):
        return out, np.zeros(0)
    order = np.argsort(heights[used - 1], kind="stable")
    group = np.concatenate([[0], np.cumsum(np.diff(heights[used[order] - 1]) >= merge)])
    renumber = np.zeros(len(heights) + 1, np.int64)
    renumber[used[order]] = group + 1
    weight = size[order]
    merged = np.bincount(group, weight * heights[used[order] - 1]) / np.bincount(group, weight)
    return renumber[out], merged


def fused_floating_levels(
    levels: np.ndarray, level_heights: np.ndarray, fused: np.ndarray, flat: float, merge: float
) -> np.ndarray:
    """Empty the columns of each level that is not flat (:func:`flat_median`) and stands
    more than ``merge`` above nine in ten of its columns' fused heights (not in the
    paper).

    Where the views do not tell heights apart, the voxels above a roof stay as
    photo-consistent as the roof up to the grid's top, and k-means makes a level there:
    on dev seed 10 the tiers of a 46 m tower (31-46 m above its base) left a level at
    70 m, the top of the grid its GIS height (74 m) sets. No roof stands above what dense
    matching sees of it, and a pitched roof's level lies between its eaves' and its
    ridge's fused heights. The emptied columns go to the levels at their fused heights
    (:func:`fused_flat_levels`, :func:`fused_roof_columns`). A flat level is left to
    :func:`fused_flat_levels`, which stands it on its fused height (emptied, a low flat
    roof's level at the grid's top lost the columns whose fused heights the walls blur).

    Parameters
    ----------
    levels : (nx, ny) int
        Roof level of each column (1 = lowest), 0 empty.
    level_heights : (K,) float
        Heights of levels 1..K, metres.
    fused : (nx, ny) float
        Fused height of each column, metres, NaN unknown.
    flat, merge : float
        Metres.

    Returns
    -------
    (nx, ny) int levels, the floating ones' columns 0; the numbering is kept.
    """
    out = levels.copy()
    known = np.isfinite(fused)
    for lev, height in enumerate(level_heights, 1):
        region = levels == lev
        seen = fused[region & known]
        if flat_median(seen, flat) is not None:
            continue  # a flat level: fused_flat_levels stands it on its fused height
        if len(seen) and height - np.percentile(seen, 90) > merge:
            out[region] = 0
    return out


def flat_median(heights: np.ndarray, flat: float) -> float | None:
    """The median of ``heights`` (metres) when at least half of them lie within ``flat``
    / 2 of it (a flat roof's columns), else None (a pitched roof's, or none)."""
    if not len(heights):
        return None
    middle = float(np.median(heights))
    return middle if np.mean(np.abs(heights - middle) <= flat / 2) >= 0.5 else None


def fused_upper_levels(
    levels: np.ndarray,
    level_heights: np.ndarray,
    fused: np.ndarray,
    flat: float,
    merge: float,
    max_rounds: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """Stand the flat parts of a flat level that the fusion sees more than ``merge``
    above it as levels of their own, at their median fused height (not in the paper).

    c_e weighs a level's gain against the error of all the building's heights, so a
    small top tier on a large building (a wedding cake's: 30 of 400 columns) does not
    pay for a cluster and k-means folds it into the level under it; its columns then
    stand metres low. A part counts when it survives the 3 x 3 opening
    :func:`filter_levels` applies to every level and at least half its columns' fused
    heights lie within ``flat / 2`` of their median, as :func:`fused_flat_levels` asks of
    a flat level; and only on a level that is flat by the same test (a wedding cake's
    middle level, its top tier a small share of it): on a pitched one the three rows of
    columns along a gable's ridge pass it, the two beside the ridge at one height, and
    came out a flat tier. Up to ``max_rounds`` tiers deep.

    Parameters
    ----------
    levels : (nx, ny) int
        Roof level of each column (1 = lowest), 0 empty.
    level_heights : (K,) float
        Heights of levels 1..K, metres, increasing.
    fused : (nx, ny) float
        Fused height of each column, metres, NaN unknown.
    flat, merge : float
        Metres.

    Returns
    -------
    levels, level_heights : the levels renumbered by increasing height, and their heights.
    """
    out, heights = levels.copy(), list(np.asarray(level_heights, np.float64))
    known = np.isfinite(fused)
    for _ in range(max_rounds):
        added = False
        for lev in range(1, len(heights) + 1):
            region = out == lev
            if flat_median(fused[region & known], flat) is None:
                continue  # a pitched level: its ridge's rows can look flat (as wide as 3)
            with np.errstate(invalid="ignore"):
                above = region & (fused - heights[lev - 1] > merge)
            parts, n = ndimage.label(ndimage.binary_opening(above, _SQUARE), _CROSS)
            for j in range(1, n + 1):
                part = parts == j
                middle = flat_median(fused[part], flat)
                if middle is not None:
                    heights.append(middle)
                    out[part] = len(heights)
                    added = True
        if not added:
            break
    order = np.argsort(heights, kind="stable")
    renumber = np.zeros(len(heights) + 1, np.int64)
    renumber[order + 1] = np.arange(1, len(heights) + 1)
    return renumber[out], np.asarray(heights)[order]


def fused_roof_columns(
    levels: np.ndarray,
    level_heights: np.ndarray,
    fused: np.ndarray,
    domain: np.ndarray,
    min_height: float,
) -> np.ndarray:
    """Give the empty columns of ``domain`` that the fusion sees as roof, and that touch a
    level through such columns (4-neighbours), the level nearest their fused height (not
    in the paper).

    The counterpart of :func:`fused_ground_columns` for a pitched roof, which
    :func:`fused_flat_levels` leaves alone: on a low one the photo-consistent voxels of
    its lower half sink to the paving (seed 2's 5 m hipped roof kept 104 of its 237
    columns); the roof planes are then fitted to the fused heights over all of it.

    Parameters
    ----------
    levels : (nx, ny) int
        Roof level of each column, 0 empty.
    level_heights : (K,) float
        Heights of levels 1..K, metres.
    fused : (nx, ny) float
        Fused roof height of each column, metres, NaN unknown or tree.
    domain : (nx, ny) bool
        Columns that may be building.
    min_height : float
        Lower columns are ground, metres.

    Returns
    -------
    (nx, ny) int levels.
    """
    if not len(level_heights) or not (levels > 0).any():
        return levels
    with np.errstate(invalid="ignore"):
        roof = domain & (fused >= min_height)
    grown = ndimage.binary_propagation(levels > 0, structure=_CROSS, mask=(levels > 0) | roof)
    new = grown & (levels == 0)
    nearest = np.abs(fused[new][:, None] - np.asarray(level_heights)[None, :]).argmin(axis=1)
    out = levels.copy()
    out[new] = nearest + 1
    return out


def _nanmedian(a: np.ndarray, axis: int) -> np.ndarray:
    """``np.nanmedian`` that gives NaN for all-NaN slices without warning about them."""
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=axis)


def cluster_heights(
    heights: np.ndarray, cluster_error: float = 0.3, max_k: int = 6, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """1D k-means on column heights, k raised while it pays (section 4.3).

    Starting at k = 1, k grows until going to k + 1 lowers the clustering error (the
    within-cluster sum of squares) by less than the fraction ``cluster_error`` (c_e) of
    the error at k = 1. Measured against the error at k, as a literal reading of the paper
    allows, any spread-out level would keep splitting (halving a uniform run of heights
    always removes 75 % of its error): k would always reach ``max_k``.

    Parameters
    ----------
    heights : (M,) float
        Heights above ground, metres.

    Returns
    -------
    labels : (M,) int
        Cluster of each height, clusters numbered by increasing centre.
    centres : (k,) float
        Cluster means, increasing, metres.
    """
    x = np.asarray(heights, np.float64).reshape(-1, 1)
    distinct = len(np.unique(x))

    def fit(k):
        return KMeans(n_clusters=k, n_init=4, random_state=seed).fit(x)

    best = fit(1)
    total = best.inertia_
    for k in range(2, min(max_k, distinct) + 1):
        trial = fit(k)
        if best.inertia_ - trial.inertia_ < cluster_error * total:
            break
        best = trial
    order = np.argsort(best.cluster_centers_[:, 0])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[best.labels_], best.cluster_centers_[order, 0]


def filter_levels(levels: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """Clean a height map of roof levels (section 4.3).

    From the top level down, the columns at or above each level are closed (dilate,
    then erode: small gaps filled) and opened (small islands removed; an island drops
    to the level below); single empty columns take their neighbours' most common level;
    the largest 4-connected part is kept.

    Parameters
    ----------
    levels : (nx, ny) int
        Roof level of each column (1 = lowest roof), 0 empty.
    domain : (nx, ny) bool
        Columns that may be building.

    Returns
    -------
    (nx, ny) int levels.
    """
    out = levels.copy()
    for lev in range(int(out.max()), 0, -1):
        at_least = out >= lev
        closed = ndimage.binary_closing(at_least, _SQUARE, border_value=0) & domain
        kept = ndimage.binary_opening(closed, _SQUARE)
        out[kept & (out < lev)] = lev
        out[at_least & ~kept] = lev - 1
    out = _fill_single_holes(out, domain)
    parts, n = ndimage.label(out > 0, _CROSS)
    if n > 1:
        sizes = np.bincount(parts.ravel())
        sizes[0] = 0
        out[parts != np.argmax(sizes)] = 0
    return out


def _fill_single_holes(levels: np.ndarray, domain: np.ndarray) -> np.ndarray:
    padded = np.pad(levels, 1)
    neigh = np.stack(
        [padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]], axis=-1
    )
    hole = (levels == 0) & domain & (neigh > 0).all(axis=-1)
    if not hole.any():
        return levels
    out = levels.copy()
    votes = neigh[hole]
    counts = np.stack([(votes == v).sum(axis=1) for v in range(1, levels.max() + 1)], axis=1)
    out[hole] = np.argmax(counts, axis=1) + 1
    return out


def occupancy(tops: np.ndarray, r: float, nz: int) -> np.ndarray:
    """(nx, ny, nz) bool voxels at or below each column's roof (all voxels below a kept
    voxel filled). ``tops`` (nx, ny): roof height of each column, metres above the ground
    (-inf for none; :meth:`RoofFaces.column_tops`)."""
    z = np.arange(nz) * r
    return z[None, None, :] <= tops[..., None] + 1e-9


def surface_normals(occ: np.ndarray, sigma_n: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Normals of the exterior voxels (eq. 4).

    Each exterior voxel (occupied, with an empty 6-neighbour) points away from its
    occupied 26-neighbours; those raw normals are then averaged with a Gaussian of
    ``sigma_n`` voxels over the exterior voxels within 2 sigma_n.

    Parameters
    ----------
    occ : (nx, ny, nz) bool
        Occupancy; below layer 0 counts as solid ground, outside the grid as empty.

    Returns
    -------
    exterior : (nx, ny, nz) bool
    normals : (nx, ny, nz, 3) float
        Unit normals in the frame's local axes (x, y, z), zero off the exterior.
    """
    solid = np.pad(occ, 1).astype(np.float64)
    solid[:, :, 0] = 1.0
    raw = np.zeros(occ.shape + (3,))
    offsets = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1)
    for axis in range(3):
        kernel = offsets[..., axis].astype(np.float64)
        raw[..., axis] = -ndimage.correlate(solid, kernel, mode="constant")[1:-1, 1:-1, 1:-1]
    empty_neighbour = ndimage.binary_dilation(~solid.astype(bool), _cross3())[1:-1, 1:-1, 1:-1]
    exterior = occ & empty_neighbour
    length = np.linalg.norm(raw, axis=-1, keepdims=True)
    unit = np.where(length > 0, raw / np.where(length > 0, length, 1), 0.0) * exterior[..., None]
    smooth = np.stack(
        [ndimage.gaussian_filter(unit[..., a], sigma_n, truncate=2.0) for a in range(3)], -1
    )
    norm = np.linalg.norm(smooth, axis=-1, keepdims=True)
    normals = np.where(norm > 0, smooth / np.where(norm > 0, norm, 1), 0.0) * exterior[..., None]
    return exterior, normals


def _cross3() -> np.ndarray:
    return ndimage.generate_binary_structure(3, 1)


def proxy_mesh(frame: VoxelFrame, roof: RoofFaces, tolerance: float) -> Building | None:
    """The exterior surface of the proxy as a closed mesh of large polygons: every roof
    face one polygon on its plane (coplanar voxel tops merged), walls from each roof down
    to the lower neighbour or the ground
    (:func:`~modeling.shared.roof_model.closed_roof_model`).

    Parameters
    ----------
    roof : RoofFaces
        The roof's faces and planes in the frame.
    tolerance : float
        Outline simplification, metres (0 keeps the voxel staircase).

    Returns
    -------
    Building in world metres (mesh, footprint, planes, roof type, heights; id empty), or
    None for an empty proxy.
    """
    nx, ny, _ = frame.shape
    cell = frame.r / roof.k
    local = Grid(frame.x0, frame.y0 + ny * frame.r, cell, nx * roof.k, ny * roof.k)
    faces = roof.faces.T[::-1]  # rows run north in the local frame
    if not (faces > 0).any():
        return None
    model = closed_roof_model(faces, local, roof.planes, 0.0, max(tolerance, 1e-3))
    if model is None:
        return None
    return to_world(model, frame)


def to_world(model: Building, frame: VoxelFrame) -> Building:
    """A building modelled in the frame's local x, y and heights above its base, moved
    to world metres."""
    v = model.mesh.vertices.copy()
    v[:, :2] = frame.to_world_xy(v[:, :2])
    v[:, 2] += frame.base_z
    p = np.asarray(model.planes, np.float64)
    n = p[:, :2] @ frame.axes  # the normals' horizontal parts in world axes
    d = p[:, 3] - p[:, 2] * frame.base_z - n @ frame.origin
    return replace(
        model,
        mesh=Surface(v, model.mesh.triangles),
        footprint=shapely.transform(model.footprint, frame.to_world_xy),
        planes=np.column_stack([n, p[:, 2], d]),
        base_z=frame.base_z,
        eave_z=model.eave_z + frame.base_z,
        ridge_z=model.ridge_z + frame.base_z,
    )
