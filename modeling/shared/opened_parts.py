"""Connected parts of a mask after a morphological opening: the step that splits
neighbouring buildings joined by a thin bridge (the LOD paper, section 4.2), and a part's
outline moved to where its DSM's walls stand at mid-height, over the rim no view saw, and
the building's parts no view saw (between its known sides, or under the fusion's ceiling);
shared by the raster paths."""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage


def opened_parts(
    mask: np.ndarray, gsd: float, opening_m: float, min_area_m2: float, connectivity: int
) -> tuple[np.ndarray, np.ndarray]:
    """Label the connected parts of ``mask`` opened with a disc of radius ``opening_m``.

    Parameters
    ----------
    mask : (H, W) bool
    gsd : float
        Cell size, metres.
    opening_m : float
        Radius of the opening's disc, metres (0: no opening).
    min_area_m2 : float
        Smallest part kept.
    connectivity : int
        4 or 8.

    Returns
    -------
    parts : (H, W) int32, 0 outside the opened mask, 1..n-1 its parts
    big : (n,) bool, the parts of at least ``min_area_m2`` (False for 0)
    """
    m = mask.astype(np.uint8)
    r = int(round(opening_m / gsd))
    if r > 0:
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, disc)
    _, parts, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=connectivity)
    big = stats[:, cv2.CC_STAT_AREA] * gsd**2 >= min_area_m2
    big[0] = False
    return parts, big


def building_segments(
    mask: np.ndarray, gsd: float, opening_m: float, min_area_m2: float
) -> np.ndarray:
    """(H, W) int32 segments 1..q of the object region: opened with a disc of
    ``opening_m`` (which cuts thin bridges between neighbours), connected parts of at
    least ``min_area_m2``, renumbered; 0 elsewhere."""
    parts, big = opened_parts(mask, gsd, opening_m, min_area_m2, connectivity=4)
    new = np.zeros(len(big), np.int32)
    new[big] = np.arange(1, big.sum() + 1)
    return new[parts]


def mid_wall_region(
    segment: np.ndarray, ndsm: np.ndarray, others: np.ndarray, gsd: float, reach_m: float
) -> np.ndarray:
    """(h, w) bool the building's cells as its DSM draws them: the cells within
    ``reach_m`` of ``segment`` (and not of ``others``) standing above the ground by more
    than half its eaves' height (the 10th percentile of its nDSM), connected to it.

    The building class's edge wanders by a cell or two where the classifier is unsure;
    a DSM blurs a wall over a cell or two too, and its mid-height is where the wall
    stands. ndsm : (h, w) metres, NaN unknown."""
    r = max(1, int(round(reach_m / gsd)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    near = cv2.dilate(segment.astype(np.uint8), disc).astype(bool) & ~others
    high = near & (np.nan_to_num(ndsm, nan=-np.inf) > half_eaves(ndsm, segment))
    # the majority of each 3 x 3: a DSM's noise leaves single cells in and out of the
    # edge, whose staircase would outweigh the sides in the outline's direction
    high = cv2.medianBlur(high.astype(np.uint8) * 255, 3) > 0
    labels, _ = ndimage.label(high)
    keep = np.unique(labels[segment & high])
    return np.isin(labels, keep[keep > 0])


def half_eaves(ndsm: np.ndarray, cells: np.ndarray) -> float:
    """Half the eaves' height of the building on ``cells`` ((h, w) bool): half the 10th
    percentile of its nDSM (``ndsm``, metres, NaN unknown), 0 where it has none. A wall
    stands where its DSM passes this."""
    z = ndsm[cells]
    z = z[np.isfinite(z)]
    return 0.5 * float(np.percentile(z, 10)) if len(z) else 0.0


def unseen_rim_filled(
    heights: list[np.ndarray], known: np.ndarray, reach_cells: int
) -> list[np.ndarray]:
    """Each of ``heights`` ((h, w) float, metres) with its unknown cells within
    ``reach_cells`` of a known one (``known``: (h, w) bool) given that cell's value (the
    nearest, ties as :func:`scipy.ndimage.distance_transform_edt` breaks them).

    A fusion of depth maps leaves each roof's outermost cells unknown: every view drops
    the pixels of a depth jump's ramp, about two on the roof's side (0.24-0.4 m on
    ``small``'s roofs), so no view keeps the roof up to its wall, and an outline drawn
    on the known cells alone lies a cell inside the true one. Filled, the cells beside a
    roof take its height and those beside the ground the ground's, so that where the
    wall stands at mid-height (:func:`mid_wall_region`) the outline may reach them; the
    fits still use the known cells only."""
    if reach_cells <= 0 or known.all() or not known.any():
        return [h.copy() for h in heights]
    dist, (ri, ci) = ndimage.distance_transform_edt(~known, return_indices=True)
    near = ~known & (dist <= reach_cells)
    return [np.where(near, h[ri, ci], h) for h in heights]


def unseen_parts(
    region: np.ndarray,
    dsm: np.ndarray,
    dtm: np.ndarray,
    ceiling: np.ndarray | None = None,
    reach: int = 0,
) -> np.ndarray:
    """(h, w) bool the cells that may be the building's parts no view saw, for the caller
    to give a level and then to keep those under the ceiling (:func:`under_ceiling`).

    Where the fusion gives a ceiling over an unknown cell (``ceiling``, (h, w) metres,
    NaN where it has none: :mod:`fusion.hidden_ceiling`), the views' geometry decides: a
    candidate is any unknown cell within the building's least rectangle (its two
    directions, as :func:`unseen_between` takes them) that reaches the building's known
    cells (``region``) through unknown ones, in groups that border the seen ground for
    at most a tenth and not at both ends (:func:`off_the_ground`); such a part may
    carry on ``reach`` cells past the rectangle (the outline's reach: a fusion keeps no
    roof up to its wall, and the rectangle of the known cells stops short of it). A
    lower tier along the building's outer side, hidden behind its upper part, has the
    building on one side only, and :func:`unseen_between` left it out: on ``small``
    seed 1 a quarter of a 72-79 m tower. Elsewhere (a cloud's fusion, a run from
    another tool) the candidates are :func:`unseen_between`'s.

    dsm, dtm : (h, w) float, metres, NaN unknown."""
    between = unseen_between(region, dsm, dtm)
    if ceiling is None or region.sum() < 3:
        return between
    frame = BuildingFrame(region)
    open_ = ~np.isfinite(dsm) & np.isfinite(ceiling)
    inside = frame.rectangle() & open_
    grown = frame.rectangle(reach) & open_
    # the ground beside a wall whose ramp the views dropped is as unknown as a hidden
    # tier, and a ray grazing the roof's edge passes over it: its group borders the
    # ground the views saw beyond, a hidden tier's the building and the ground it hides
    within = off_the_ground(touching(inside, region), region, dsm, dtm)
    # past the rectangle only to carry on such a part
    return between | touching(grown, within)


# the margin under the fusion's ceiling a hidden part's level keeps, in cells of the grid
# (:func:`under_ceiling` says why)
CEILING_MARGIN_CELLS = 2


def under_ceiling(
    cells: np.ndarray,
    heights: np.ndarray,
    ceiling: np.ndarray | None,
    region: np.ndarray,
    margin: float,
) -> np.ndarray:
    """(h, w) bool those of ``cells`` whose level (``heights``, (h, w) metres) stays
    ``margin`` metres under the fusion's ceiling (``ceiling``, NaN or None: no ceiling,
    it fits), and that still reach ``region`` through such cells.

    Every view's ray over a hidden cell passed above what stands there: a part whose
    level rises above the lowest of them would have stopped it. Behind a taller part the
    rays pass above a lower tier; beyond the building's wall the rays that saw the
    ground further out pass below the roof's level. Beside a wall the ceiling errs
    high: no view trusts the three pixels of the jump's ramp (0.5 m over a ray-cast
    depth map's exact answer beside a tower), so the rays grazing a roof's edge pass
    over the ground beyond it higher than they are. The callers' margin is
    :data:`CEILING_MARGIN_CELLS` cells (0.5 m on ``small``, about those pixels'
    footprint). On the dev fusions of seeds
    0-2 and 6, against none: block path 2D quality 0.956, 0.940, 0.946, 0.937 -> 0.959,
    0.945, 0.948, 0.943, height RMSE off the jumps 0.36, 0.25, 0.32, 0.48 -> 0.41, 0.25,
    0.36, 0.48 m; with 1 m, 0.53 and 0.50 m on seeds 0 and 2 and the parametric path's
    1.00 m on seed 2 (0.72 at 0.5 m): of the hidden cells of buildings on seeds 0-2,
    89, 84 and 66 % have a ceiling 0.5 m or more above their true height, 47, 55 and
    20 % 1 m."""
    if ceiling is None:
        return cells
    with np.errstate(invalid="ignore"):  # NaN compares False: no ceiling, it fits
        fits = cells & ~(heights > ceiling - margin)
    return touching(fits, region)


def unseen_at_level(
    region: np.ndarray,
    dsm: np.ndarray,
    dtm: np.ndarray,
    ceiling: np.ndarray | None,
    reach: int,
    gsd: float,
    exclude: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The building's parts no view saw that its outline takes in, and their level:
    (h, w) bool the cells of :func:`unseen_parts` (not of ``exclude``, another
    building's) whose level, the lowest of the building's heights around them
    (:func:`lowest_around`), stays :data:`CEILING_MARGIN_CELLS` cells of ``gsd`` metres
    under the fusion's ``ceiling`` (:func:`under_ceiling`); and (h, w) metres ``dsm``
    with those cells at that level (a new array). The raster paths' one sequence of
    these steps; the super-pixel path gives a part the level of a roof face instead
    (:func:`~modeling.superpixel.rooftop.with_unseen_parts`).

    region : (h, w) bool, the building's cells with a height. dsm, dtm : (h, w) float,
    metres, NaN unknown. ceiling : (h, w) metres, NaN where the fusion gives none, or
    None. reach : cells past the building's least rectangle (:func:`unseen_parts`)."""
    hidden = unseen_parts(region, dsm, dtm, ceiling, reach)
    if exclude is not None:
        hidden &= ~exclude
    level = lowest_around(dsm, region, hidden)
    kept = under_ceiling(hidden, level, ceiling, region, CEILING_MARGIN_CELLS * gsd)
    dropped = hidden & ~kept
    level[dropped] = dsm[dropped]
    return kept, level


def touching(cells: np.ndarray, region: np.ndarray, sides_only: bool = False) -> np.ndarray:
    """(h, w) bool the 8-connected groups of ``cells`` that touch ``region`` (both
    (h, w) bool); with ``sides_only``, the 4-connected groups that share a side with it."""
    link = None if sides_only else np.ones((3, 3))  # None: scipy's cross, the sides
    groups, n = ndimage.label(cells, link)
    if n == 0:
        return cells.copy()
    near = ndimage.binary_dilation(region, link)
    keep = np.zeros(n + 1, bool)
    keep[groups[near]] = True
    keep[0] = False
    return keep[groups]


class BuildingFrame:
    """A building's cells (``region``, (h, w) bool, at least 3) turned into the frame of
    their least rectangle (:func:`cv2.minAreaRect`): its sides along the frame's rows
    and columns. ``framed`` is the region in that frame."""

    def __init__(self, region: np.ndarray):
        h, w = self.shape = region.shape
        self.region = region
        pts = np.argwhere(region)[:, ::-1].astype(np.float32)
        (cx, cy), _, angle = cv2.minAreaRect(pts)
        self.side = int(np.ceil(np.hypot(h, w))) + 2
        self.turn = cv2.getRotationMatrix2D((cx, cy), angle, 1.0)  # into the frame
        self.turn[:, 2] += (self.side / 2 - cx, self.side / 2 - cy)
        self.framed = self.to_frame(region)

    def to_frame(self, mask: np.ndarray) -> np.ndarray:
        return cv2.warpAffine(mask.astype(np.uint8), self.turn, (self.side, self.side),
                              flags=cv2.INTER_NEAREST) > 0  # fmt: skip

    def back(self, framed: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """A mask in the frame, back on the building's (h, w) cells."""
        h, w = shape
        return cv2.warpAffine(framed.astype(np.uint8), self.turn, (w, h),
                              flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0  # fmt: skip

    def between(self) -> np.ndarray:
        """The frame's cells with the region on both sides along a row or a column."""
        out = np.zeros(self.framed.shape, bool)
        for axis in (0, 1):
            ahead = np.maximum.accumulate(self.framed, axis=axis)
            behind = np.flip(np.maximum.accumulate(np.flip(self.framed, axis), axis=axis), axis)
            out |= ahead & behind
        return out

    def rectangle(self, grow: int = 0) -> np.ndarray:
        """(h, w) bool the building's cells within its least rectangle, and ``grow``
        cells more on every side: those whose centres, turned into the frame, lie within
        the range of the region's along both of its sides. Taken from the cells' own
        coordinates, not resampled into the frame and back: a nearest cell each way
        dropped a side's last column where the frame's centre fell between cells (every
        rectangle turned by 90 degrees)."""
        rows, cols = np.indices(self.shape, dtype=np.float64)
        out = np.ones(self.shape, bool)
        for a, b, t in self.turn:  # the frame's columns, then its rows
            along = a * cols + b * rows + t
            inner = along[self.region]
            out &= (along >= inner.min() - grow - 1e-6) & (along <= inner.max() + grow + 1e-6)
        return out


def unseen_between(region: np.ndarray, dsm: np.ndarray, dtm: np.ndarray) -> np.ndarray:
    """(h, w) bool the building's parts no view saw: the unknown cells (``dsm`` NaN) that
    have cells of ``region`` ((h, w) bool, a building's cells with a height) on both
    sides along one of the building's two directions (its least rectangle's sides,
    :func:`cv2.minAreaRect`), in groups that do not border the ground, nor the ground
    at both ends (a passage between two parts, :func:`off_the_ground`). What they are
    given is the caller's (:func:`nearest_of`: the nearest cell's height or roof face).

    Where every view looks at a roof from one side (at the edge of a survey), the
    building's upper parts hide its lower tier, and the fusion knows nothing there: an
    outline on the known cells stops at the tall part, a notch cut into the building
    between its known sides. Hidden ground beside a wall, or in an L's inner corner,
    has the building on one side only along each direction; in a U's courtyard it has
    it on two, but borders the courtyard's ground the views saw: a group whose known
    neighbours stand at the ground (below half the building's eaves, as in
    :func:`mid_wall_region`) for more than a tenth is left out.

    Whatever else stands between the cell and the building's sides is not asked: a
    lower tier often holds a few cells some view saw, and asking that the nearest seen
    cells be the building's lost more hidden tiers than it kept out hidden ground (dev
    fusions of seeds 0-2 and 6-14: block path off the jumps worse on 7 seeds, 1.06 ->
    1.68 m on seed 0; a super-pixel roof better on one seed).

    dsm, dtm : (h, w) float, metres, NaN unknown."""
    unknown = ~np.isfinite(dsm)
    none = np.zeros(region.shape, bool)
    if region.sum() < 3 or not unknown.any():
        return none
    frame = BuildingFrame(region)
    back = frame.back(frame.between() & ~frame.framed, region.shape)
    return off_the_ground(back & unknown, region, dsm, dtm)


def off_the_ground(
    cells: np.ndarray, region: np.ndarray, dsm: np.ndarray, dtm: np.ndarray
) -> np.ndarray:
    """(h, w) bool the 8-connected groups of ``cells`` (unknown cells, (h, w) bool) of
    whose known neighbours at most a tenth stand at the ground (below half the eaves of
    the building on ``region``, as in :func:`mid_wall_region`): not the ground beside a
    wall that the views lost with the wall's ramp, nor a courtyard's hidden strip.

    Nor a group whose ground neighbours lie in two places apart (since 2026-12-07): a
    strip between two of the region's parts that the ground closes at both ends is a
    passage between them (an alley between a tower and a lower building one labelled
    region holds; on ``small`` seed 0's mesh, 4 m wide and 30 m long, its two ends were
    under a tenth of its ring), where a hidden tier between a tower and its podium's
    outer part ends on the podium."""
    out = np.zeros(cells.shape, bool)
    groups, n = ndimage.label(cells, structure=np.ones((3, 3)))
    if n == 0:
        return out
    ndsm = dsm - dtm
    known = np.isfinite(ndsm) & ~region
    ground = known & (ndsm < half_eaves(ndsm, region))
    for j, box in enumerate(ndimage.find_objects(groups), start=1):
        grown = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        group = groups[grown] == j
        ring = ndimage.binary_dilation(group, structure=np.ones((3, 3))) & ~group
        at_ground = ground[grown] & ring
        if at_ground.sum() > 0.1 * (ring & (known | region)[grown]).sum():
            continue
        if _ends_at_the_ground(group, at_ground):
            continue
        out[grown] |= group
    return out


def _ends_at_the_ground(group: np.ndarray, at_ground: np.ndarray) -> bool:
    """Whether the ground the ``group`` of cells borders (``at_ground``, both (h, w)
    bool) lies in two places or more, each as long as half the group's width (its cells
    over its length, the length from their spread along their main axis): a strip's two
    ends, not the ground a notch's corners touch diagonally."""
    pieces, n = ndimage.label(at_ground, structure=np.ones((3, 3)))
    if n < 2:
        return False
    pts = np.argwhere(group).astype(np.float64)
    length = np.sqrt(12.0 * np.linalg.eigvalsh(np.cov(pts.T)).max()) if len(pts) > 2 else 1.0
    width = len(pts) / max(length, 1.0)
    sizes = np.bincount(pieces.ravel())[1:]
    return int((sizes >= width / 2).sum()) >= 2


def lowest_around(heights: np.ndarray, region: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """``heights`` ((h, w) float, metres) with each group of ``cells`` ((h, w) bool,
    8-connected) given the lowest level of the cells of ``region`` ((h, w) bool) within
    two cells of it: the 10th percentile of their heights (the nearest cell's where none
    is so near). What the views could not see lies below what hid it."""
    out = nearest_of(heights, region, cells)
    for near, group, ring in groups_and_rings(cells, region):
        z = heights[near][ring]
        z = z[np.isfinite(z)]
        if len(z):
            out[near][group] = np.percentile(z, 10)
    return out


def groups_and_rings(cells: np.ndarray, around: np.ndarray, reach: int = 2):
    """Each 8-connected group of ``cells`` ((h, w) bool) as (window, group, ring): the
    slices of a window round it, the group's cells and the cells of ``around`` ((h, w)
    bool) within ``reach`` cells of it, both (h', w') bool in the window."""
    groups, _ = ndimage.label(cells, np.ones((3, 3)))
    for j, box in enumerate(ndimage.find_objects(groups), start=1):
        near = tuple(slice(max(b.start - reach, 0), b.stop + reach) for b in box)
        group = groups[near] == j
        ring = ndimage.binary_dilation(group, np.ones((3, 3)), iterations=reach)
        yield near, group, ring & around[near]


def nearest_of(values: np.ndarray, region: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """``values`` ((h, w), any dtype) with each of ``cells`` ((h, w) bool) given the value
    of the nearest cell of ``region`` ((h, w) bool; ties as
    :func:`scipy.ndimage.distance_transform_edt` breaks them); a new array."""
    if not cells.any() or not region.any():
        return values.copy()
    _, (ri, ci) = ndimage.distance_transform_edt(~region, return_indices=True)
    return np.where(cells, values[ri, ci], values)
