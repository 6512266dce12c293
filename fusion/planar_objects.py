"""Objects the class map calls tree that are planar roofs (not in the paper).

Colour calls a moss-green or copper-green roof a tree, and the class CRF spreads the
call over the whole roof. The per-cell geometric cues (:mod:`fusion.geometry_cues`) do
not overrule it: over a metre or two a crown's surface can be as smooth as a roof. Over
a whole object they differ: a roof is a few planes, a crown is not. An object the class
map calls tree, standing a storey above the DTM, holds a roof where a few planes found
by sequential RANSAC explain most of its cells to within twice the DSM's noise, the
noise measured on the run's own ground. The share is taken over the object's cells
within :data:`NEAR_M` of the planes' largest connected part, and that part is the roof:
a crown that touches the roof is the same tree object, and counted whole it hid a
pyramid roof (dev seed 12: 0.68 of the object, 0.83 of the roof and its rim).

What is left of an object once its roof is taken out is an object of its own, tested
again (:data:`PASSES`): where the DSM rounds a ridge off both planes, the faces make two
parts, and the second face, a wing's shaded side, stayed tree (dev seed 16).

On the fusion runs of ``small`` seeds 0-2 and 6-14 (12 cities, 471 tree objects of
20 m² or more that are crowns) the planes explain at most 0.63 of a crown's cells.
Taken as objects, the 322 roofs of those cities score 0.59-1.0, 7 of them under 0.7:
such a roof, if colour called it tree, stays tree.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.morphology import disk

from workbench.planes import point_plane_distances, sequential_planes
from workbench.raster import BUILDING, GROUND, TREE

from .geometry_cues import WINDOWS_M, plane_residual, window_cells

STOREY_M = 2.5  # lower objects are hedges and shrubs whatever their shape
MIN_AREA_M2 = 20.0  # a smaller crown is nearly planar in pieces: planes explain up to 0.7
NOISE_FACTOR = 2.0  # inlier distance: this many times the DSM's noise
MIN_EXPLAINED = 0.7  # share of the object's cells on its planes
PLANE_SHARE = 0.1  # each plane takes at least this share of the object's cells
MAX_PLANES = 6  # a cross-gabled roof has 4 to 6
MAX_TILT_DEG = 75.0  # steeper is a wall (a mansard's lower faces are 60-70 degrees)
MAX_POINTS = 4000  # a larger object is tested on a sample: RANSAC holds (points, 300)
NEAR_M = 1.0  # the object's cells this near the roof are its rim: the walls' blur
PASSES = 3  # what is left of objects after their roofs, tested again (a shaded face)


def dsm_noise(dsm: np.ndarray, classes: np.ndarray, gsd: float) -> float:
    """The DSM's noise, metres: the median RMS residual of the least-squares plane in the
    ~1.25 m window around each cell classed ground (ground is locally planar wherever it
    slopes), NaN without such cells."""
    residual = plane_residual(dsm, window_cells(WINDOWS_M[0], gsd))
    on_ground = (classes == GROUND) & np.isfinite(residual)
    return float(np.median(residual[on_ground])) if on_ground.any() else float("nan")


def planar_tree_objects(
    classes: np.ndarray, dsm: np.ndarray, ndsm: np.ndarray, gsd: float, seed: int = 0
) -> tuple[np.ndarray, int]:
    """Cells of the objects classed tree whose planes make them roofs.

    Parameters
    ----------
    classes : (H, W) uint8
        Class codes (:data:`workbench.raster.CLASS_CODES`).
    dsm, ndsm : (H, W) float
        Heights and heights above the DTM, metres, NaN unknown.
    gsd : float
        Cell size, metres.
    seed : int
        Seed of the RANSAC draws and of the sample of a large object.

    Returns
    -------
    roof : (H, W) bool
        The cells on the planes of every planar object, with the gaps between them
        inside the object closed (a vent, a seam between two faces).
    objects : int
        How many roofs were found: an object's and, over :data:`PASSES`, those in what
        was left of it.
    """
    roof = np.zeros(classes.shape, bool)
    tolerance = NOISE_FACTOR * dsm_noise(dsm, classes, gsd)
    if not np.isfinite(tolerance):
        return roof, 0
    with np.errstate(invalid="ignore"):
        tall_tree = (classes == TREE) & (ndsm > STOREY_M) & np.isfinite(dsm)
    min_cells = MIN_AREA_M2 / gsd**2
    rng = np.random.default_rng(seed)
    found = 0
    candidates = tall_tree
    for _round in range(PASSES):
        labels, _ = ndimage.label(candidates)
        new = np.zeros(classes.shape, bool)
        for k, window in enumerate(ndimage.find_objects(labels), 1):
            inside = labels[window] == k
            if inside.sum() < min_cells:
                continue
            on_planes = object_planes(inside, dsm[window], gsd, tolerance, rng, seed)
            if on_planes is not None:
                new[window] |= on_planes
                found += 1
        if not new.any():
            break
        roof |= new
        # what is left of an object whose roof was taken out is an object of its own
        candidates = np.isin(labels, np.unique(labels[new])) & ~roof
    return roof, found


def object_planes(
    inside: np.ndarray, dsm: np.ndarray, gsd: float, tolerance: float, rng, seed: int
) -> np.ndarray | None:
    """(h, w) bool the roof of one object, else None: the largest connected part of the
    cells on its planes (gaps of a cell closed, holes under :data:`MIN_AREA_M2` filled:
    a vent, a seam; not a crown over the roof), where the planes explain at
    least :data:`MIN_EXPLAINED` of the object's cells within :data:`NEAR_M` of it and
    the part covers at least :data:`MIN_AREA_M2`.

    Parameters
    ----------
    inside : (h, w) bool
        The object's cells in its bounding window.
    dsm : (h, w) float
        Heights over that window, metres.
    tolerance : float
        RANSAC inlier distance, metres.
    """
    r, c = np.nonzero(inside)
    points = np.column_stack([c * gsd, -r * gsd, dsm[r, c]]).astype(np.float64)
    points -= points.mean(axis=0)  # near a local origin: heights of tens of metres
    sample = points
    if len(points) > MAX_POINTS:
        sample = points[rng.choice(len(points), MAX_POINTS, replace=False)]
    planes = sequential_planes(
        sample, tolerance, int(np.ceil(PLANE_SHARE * len(sample))), MAX_PLANES, MAX_TILT_DEG,
        seed,
    )  # fmt: skip
    if len(planes) == 0:
        return None
    on_plane = (point_plane_distances(planes, points).reshape(len(points), -1) < tolerance).any(1)
    on = np.zeros(inside.shape, bool)
    on[r[on_plane], c[on_plane]] = True
    # padded: unpadded, the closing's erosion takes the object's cells on its window's
    # border off the part (a tight window: its whole outline)
    closed = ndimage.binary_closing(np.pad(on, 1), np.ones((3, 3), bool))[1:-1, 1:-1]
    part = largest_component(closed & inside)
    if part.sum() < MIN_AREA_M2 / gsd**2:
        return None
    near = ndimage.binary_dilation(part, disk(round(NEAR_M / gsd))) & inside
    if (on & part).sum() < MIN_EXPLAINED * near.sum():
        return None
    holes, _ = ndimage.label(ndimage.binary_fill_holes(part) & ~part)
    small = np.flatnonzero(np.bincount(holes.ravel()) < MIN_AREA_M2 / gsd**2)
    return (part | (np.isin(holes, small) & (holes > 0))) & inside


def largest_component(mask: np.ndarray) -> np.ndarray:
    """(h, w) bool the largest 8-connected component of ``mask`` (empty if it is)."""
    labels, n = ndimage.label(mask, np.ones((3, 3), bool))
    if n == 0:
        return mask.copy()
    return labels == np.bincount(labels.ravel())[1:].argmax() + 1


def relabel_planar_objects(
    classes: np.ndarray, class_prob: np.ndarray, roof: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The class map and probabilities with ``roof`` cells made building.

    The probabilities of building and of each cell's most probable class trade places,
    so that building is the most probable class there and every confidence is kept.

    Parameters
    ----------
    classes : (H, W) uint8
    class_prob : (4, H, W) float
        Probabilities of ground, grass, tree and building; NaN unseen.
    roof : (H, W) bool

    Returns
    -------
    New arrays; the inputs are left as they were.
    """
    classes = np.where(roof, BUILDING, classes).astype(classes.dtype)
    class_prob = class_prob.copy()
    r, c = np.nonzero(roof)
    p = class_prob[:, r, c]
    top = np.nan_to_num(p, nan=-1.0).argmax(axis=0)
    cols = np.arange(len(r))
    building = p[BUILDING - 1].copy()
    p[BUILDING - 1] = p[top, cols]
    p[top, cols] = building
    class_prob[:, r, c] = p
    return classes, class_prob
