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

A roof's face can also join a crown instead: the shaded, steep faces of a mansard roof
beside a tree read as tree, and the class CRF joins them to the crown, one object whose
planes explain too little of it. :func:`roof_faces_beside_buildings` takes such faces
out of the objects: a plane's cells that are dense, share an edge with the building
class, and continue its heights across that edge. On the fusion runs of ``small`` seeds
0-2 and 6-10 it took 5 parts, each at least 0.99 on a true roof, and no crown; the
heights carried on along 0.63-1.0 of the faces' edges, 0-0.23 of the other parts'.
The heights are compared off the foot of a wall up to a higher tier: a lower tier
classed tree and joined to a crown met its own tier along less than half its edge (dev
seed 2: 0.47), the rest at the upper tier's wall. A mesh rounds that wall's top over a
cell or two, which the building class takes: the foot is where the building neighbours
rise past the face's own rise and the building within :data:`NEAR_M` (the walls' blur)
stands a storey above. There the edge is the face's too, for its length: a moss-green
ring around a tower on ``small`` seed 0's mesh met its own ring along 4 of its 23 edge
cells, the other 19 at the tower's rounded wall (0.37 of the LOD path's squared error
off the jumps on that seed).

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
DRAWS = 3  # sequential RANSAC decompositions tried on an object before it is no roof
FACE_MIN_M2 = 5.0  # a roof face beside a building: a hipped end of a small house is larger
MAX_FACES = 12  # planes sought per object: a crown's come first, a face's after them
FACE_DENSITY = MIN_EXPLAINED  # share of a face's cells on its plane (a crown's: speckles)
FACE_EDGE_M = 4.0  # the edge a face shares with the building class
FACE_CONTINUES = 0.5  # share of that edge where the heights carry on across it
COUNTS = ("planar_objects_made_building", "roof_faces_made_building")  # in fusion.json


def dsm_noise(dsm: np.ndarray, classes: np.ndarray, gsd: float, on: int = GROUND) -> float:
    """The DSM's noise, metres: the median RMS residual of the least-squares plane in the
    ~1.25 m window around each cell of class ``on`` (ground, by default: locally planar
    wherever it slopes), NaN without such cells."""
    residual = plane_residual(dsm, window_cells(WINDOWS_M[0], gsd))
    on_class = (classes == on) & np.isfinite(residual)
    return float(np.median(residual[on_class])) if on_class.any() else float("nan")


def inlier_tolerance(dsm: np.ndarray, classes: np.ndarray, gsd: float,
                     on: int = GROUND) -> float:  # fmt: skip
    """The planes' inlier distance, metres: :data:`NOISE_FACTOR` times
    :func:`dsm_noise` on class ``on``, else on the ground (NaN without either)."""
    noise = dsm_noise(dsm, classes, gsd, on)
    if not np.isfinite(noise) and on != GROUND:
        noise = dsm_noise(dsm, classes, gsd)
    return NOISE_FACTOR * noise


def tall_trees(classes: np.ndarray, dsm: np.ndarray, ndsm: np.ndarray) -> np.ndarray:
    """(H, W) bool cells classed tree, known, more than :data:`STOREY_M` above the DTM."""
    with np.errstate(invalid="ignore"):
        return (classes == TREE) & (ndsm > STOREY_M) & np.isfinite(dsm)


def planar_tree_objects(
    classes: np.ndarray,
    dsm: np.ndarray,
    ndsm: np.ndarray,
    gsd: float,
    seed: int = 0,
    tolerance: float | None = None,
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
    tolerance : float, optional
        RANSAC inlier distance, metres; :func:`inlier_tolerance` by default.

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
    tolerance = inlier_tolerance(dsm, classes, gsd) if tolerance is None else tolerance
    if not np.isfinite(tolerance):
        return roof, 0
    tall_tree = tall_trees(classes, dsm, ndsm)
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

    Sequential RANSAC is greedy: its first plane, the one with most inliers, can bridge
    two faces of a small roof, and the faces' remains then fall short of a plane's
    share. Up to :data:`DRAWS` decompositions, each with its own draws, are tried; the
    first that makes a roof is kept (dev seed 8's moss-green hipped L of 121 m^2: its
    first draw explained 0.66 of it with a plane across two faces, 6 of the next 7
    draws 0.70-0.76).

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
    for draw in range(DRAWS):  # the k-th plane of a draw uses seed + k: draws apart
        planes = sequential_planes(
            sample, tolerance, int(np.ceil(PLANE_SHARE * len(sample))), MAX_PLANES,
            MAX_TILT_DEG, seed + draw * MAX_PLANES,
        )  # fmt: skip
        roof = _planes_roof(planes, points, r, c, inside, gsd, tolerance)
        if roof is not None:
            return roof
    return None


def _planes_roof(planes, points, r, c, inside, gsd: float, tolerance: float):
    """:func:`object_planes`' roof on the given planes, else None."""
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


def roof_faces_beside_buildings(
    classes: np.ndarray,
    dsm: np.ndarray,
    ndsm: np.ndarray,
    gsd: float,
    seed: int = 0,
    tolerance: float | None = None,
) -> tuple[np.ndarray, int]:
    """Cells of the objects classed tree that are faces of a building's roof.

    In each object classed tree, a storey above the DTM and touching the building
    class, sequential RANSAC seeks up to :data:`MAX_FACES` planes of at least
    :data:`FACE_MIN_M2` each (at most :data:`MAX_TILT_DEG` steep, inliers within twice
    the DSM's noise, as :func:`planar_tree_objects`). Each cell goes to the first plane
    it lies on; the cells of one plane, gaps of a cell closed, make parts. A part is a
    face of the roof beside it when all three hold:

    - at least :data:`FACE_DENSITY` of its cells lie on the plane: a crown's surface
      crosses a plane in rings and speckles;
    - it shares an edge of at least :data:`FACE_EDGE_M` with cells classed building: a
      face meets the rest of its roof along a ridge, a hip or a break of slope, or a
      lower tier its upper tier's wall;
    - along at least :data:`FACE_CONTINUES` of that edge the heights carry on: a cell of
      the part and its building neighbour differ by at most the plane's own rise over
      the diagonal of a cell, plus the inlier distance. A crown beside a roof stands
      above it or falls away from it. The edge's cells at a wall's foot (their building
      neighbours all rise past that, and the building within :data:`NEAR_M` of them
      stands :data:`STOREY_M` or more above them) are left out of this share, and one
      cell at least must be left for it.

    Faces found make the building class larger; faces beyond them are sought again,
    up to :data:`PASSES` times.

    Parameters
    ----------
    classes : (H, W) uint8
        Class codes, with :func:`planar_tree_objects`' roofs made building.
    dsm, ndsm : (H, W) float
        Heights and heights above the DTM, metres, NaN unknown.
    gsd : float
        Cell size, metres.
    seed : int
        Seed of the RANSAC draws.
    tolerance : float, optional
        RANSAC inlier distance, metres; :func:`inlier_tolerance` by default.

    Returns
    -------
    faces : (H, W) bool
    found : int
        How many connected parts were made building (faces that meet count once).
    """
    faces = np.zeros(classes.shape, bool)
    tolerance = inlier_tolerance(dsm, classes, gsd) if tolerance is None else tolerance
    if not np.isfinite(tolerance):
        return faces, 0
    tall_tree = tall_trees(classes, dsm, ndsm)
    building = classes == BUILDING
    found = 0
    eight = np.ones((3, 3), bool)
    reach = 1 + round(NEAR_M / gsd)
    near_new = None  # after the first pass: the last pass's faces and their neighbours
    for _round in range(PASSES):
        near_building = ndimage.binary_dilation(building, eight)
        labels, _ = ndimage.label(tall_tree & ~faces)
        new = np.zeros(classes.shape, bool)
        for k, window in enumerate(ndimage.find_objects(labels), 1):
            # one cell around, and the walls' blur for the wall's foot
            window = tuple(slice(max(s.start - reach, 0), s.stop + reach) for s in window)
            inside = labels[window] == k
            if inside.sum() < FACE_MIN_M2 / gsd**2 or not (inside & near_building[window]).any():
                continue
            # an object no new face touches has the cells and building neighbours it
            # had in the pass before, where it gave none: the same draws give none again
            if near_new is not None and not (inside & near_new[window]).any():
                continue
            part = object_faces(inside, dsm[window], building[window], near_building[window],
                                gsd, tolerance, seed)  # fmt: skip
            new[window] |= part
            found += int(ndimage.label(part, eight)[1])
        if not new.any():
            break
        faces |= new
        building |= new
        near_new = ndimage.binary_dilation(new, eight)
    return faces, found


def object_faces(
    inside: np.ndarray,
    dsm: np.ndarray,
    building: np.ndarray,
    near_building: np.ndarray,
    gsd: float,
    tolerance: float,
    seed: int,
) -> np.ndarray:
    """(h, w) bool the parts of one object that are faces of the roof beside it (see
    :func:`roof_faces_beside_buildings`); ``building`` the cells classed building in the
    object's window, ``near_building`` those and their 8 neighbours, ``tolerance`` the
    inlier distance in metres."""
    r, c = np.nonzero(inside)
    points = np.column_stack([c * gsd, -r * gsd, dsm[r, c]]).astype(np.float64)
    points -= points.mean(axis=0)  # near a local origin: heights of tens of metres
    min_cells = int(np.ceil(FACE_MIN_M2 / gsd**2))
    planes = sequential_planes(points, tolerance, min_cells, MAX_FACES, MAX_TILT_DEG, seed)
    faces = np.zeros(inside.shape, bool)
    if len(planes) == 0:
        return faces
    on = point_plane_distances(planes, points).reshape(len(points), -1) < tolerance
    first = np.where(on.any(axis=1), on.argmax(axis=1), -1)
    step_to_building = _step_to_building(dsm, building)
    # a cell at the foot of a wall up to a higher tier says nothing of whether the face
    # goes on: its building neighbours rise past the face's rise (a mesh rounds the
    # wall's top over a cell or two, which the building class takes) and the building
    # within the walls' blur stands a storey above it
    rise_to_building = _rise_to_building(dsm, building)
    tier_above = _building_within(dsm, building, round(NEAR_M / gsd)) - dsm > STOREY_M
    eight = np.ones((3, 3), bool)
    for p, plane in enumerate(planes):
        cells = np.zeros(inside.shape, bool)
        cells[r[first == p], c[first == p]] = True
        closed = ndimage.binary_closing(np.pad(cells, 1), eight)[1:-1, 1:-1] & inside
        parts, _ = ndimage.label(closed, eight)
        # a cell of the face and its building neighbour: the plane's rise over a
        # cell's diagonal apart, and the inliers' tolerance
        rise = gsd * np.sqrt(2) * np.hypot(plane[0], plane[1]) / abs(plane[2]) + tolerance
        for q, where in enumerate(ndimage.find_objects(parts), 1):
            part = parts[where] == q
            if part.sum() < min_cells or (cells[where] & part).sum() < FACE_DENSITY * part.sum():
                continue
            contact = part & near_building[where]
            if contact.sum() < FACE_EDGE_M / gsd:
                continue
            foot = (rise_to_building[where] > rise) & tier_above[where]
            edge = contact & ~foot
            if not edge.any():
                continue
            if (step_to_building[where][edge] <= rise).mean() >= FACE_CONTINUES:
                faces[where] |= part
    return faces


def _step_to_building(dsm: np.ndarray, building: np.ndarray) -> np.ndarray:
    """(h, w) float the smallest absolute height difference, metres, between each cell
    and its 8 neighbours classed building; inf without such a neighbour."""
    return _nearest_building_neighbour(np.abs, dsm, building)


def _rise_to_building(dsm: np.ndarray, building: np.ndarray) -> np.ndarray:
    """(h, w) float the smallest height, metres, by which each cell's 8 neighbours
    classed building stand above it (negative: one lies below); inf without such a
    neighbour."""
    return _nearest_building_neighbour(lambda diff: diff, dsm, building)


def _building_within(dsm: np.ndarray, building: np.ndarray, radius: int) -> np.ndarray:
    """(h, w) float the highest height, metres, of the cells classed building within
    ``radius`` cells of each cell; -inf where there is none."""
    heights = np.where(building & np.isfinite(dsm), dsm, -np.inf)
    return ndimage.maximum_filter(heights, footprint=disk(radius), mode="constant", cval=-np.inf)


def _nearest_building_neighbour(measure, dsm: np.ndarray, building: np.ndarray) -> np.ndarray:
    """(h, w) float the smallest ``measure(neighbour's height - cell's height)`` over
    each cell's 8 neighbours classed building with a height; inf without one."""
    h, w = dsm.shape
    z = np.pad(dsm, 1, constant_values=np.nan)
    b = np.pad(building, 1)
    out = np.full((h, w), np.inf)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0:
                continue
            nz = z[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
            nb = b[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
            with np.errstate(invalid="ignore"):
                diff = measure(nz - dsm)
            out = np.fmin(out, np.where(nb & np.isfinite(diff), diff, np.inf))
    return out


def largest_component(mask: np.ndarray) -> np.ndarray:
    """(h, w) bool the largest 8-connected component of ``mask`` (empty if it is)."""
    labels, n = ndimage.label(mask, np.ones((3, 3), bool))
    if n == 0:
        return mask.copy()
    return labels == np.bincount(labels.ravel())[1:].argmax() + 1


def planar_roof_cells(
    classes: np.ndarray,
    dsm: np.ndarray,
    ndsm: np.ndarray,
    gsd: float,
    seed: int = 0,
    noise_on: int = GROUND,
) -> tuple[np.ndarray, dict]:
    """(H, W) bool the cells classed tree that are roofs: whole objects
    (:func:`planar_tree_objects`), then faces joined to a crown
    (:func:`roof_faces_beside_buildings`); and how many of each were found, by the
    names in :data:`COUNTS`. The LOD path tests its MRF labelling with it too, the
    noise measured on the roofs (``noise_on``, a class code; ground by default)."""
    # the noise is measured on a class neither step relabels (tree cells become building)
    tolerance = inlier_tolerance(dsm, classes, gsd, noise_on)
    roof, objects = planar_tree_objects(classes, dsm, ndsm, gsd, seed, tolerance)
    with_roofs = np.where(roof, BUILDING, classes).astype(classes.dtype)
    faces, found = roof_faces_beside_buildings(with_roofs, dsm, ndsm, gsd, seed, tolerance)
    return roof | faces, dict(zip(COUNTS, (objects, found), strict=True))


def planar_roofs_classed_tree(
    classes: np.ndarray,
    class_prob: np.ndarray,
    dsm: np.ndarray,
    ndsm: np.ndarray,
    gsd: float,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The class map and probabilities with the roofs colour called tree made building
    (:func:`planar_roof_cells`).

    Returns
    -------
    classes, class_prob
        New arrays (see :func:`relabel_planar_objects`).
    counts : dict
        How many of each were made building, by the names in :data:`COUNTS`.
    """
    cells, counts = planar_roof_cells(classes, dsm, ndsm, gsd, seed)
    # one relabelling of both: each copies the probabilities (100 MB on the 1 km² city)
    classes, class_prob = relabel_planar_objects(classes, class_prob, cells)
    return classes, class_prob, counts


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
