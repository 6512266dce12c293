"""2D supports (the DEM-blocks paper, section 2): per building a set of connected,
non-overlapping quadrilaterals, each the ground plan of one block.

Automatic extraction: the building's cells split where the DSM steps by more than a
storey (:func:`height_regions`: a block's roof has no step, so a multi-level building's
tiers are supports of their own), each region's outline decomposed into rectangles by the
footprint priors in competition (:func:`modeling.shared.footprint_priors.decompose_outline`:
rectangle, L, T, U and courtyard registered to the region, the parts they leave
decomposed in turn), and each prior's arms cut where they overlap
(:func:`connected_rectangles`), so that an L is two rectangles sharing an edge. This is
the deterministic rectangle decomposition the issue allows in place of Ortner's marked
point process: the priors are fitted to the outline by least squares, not drawn, and
their arms meet on common edges by construction. A tier narrower than a support (a
podium's ring round a tower) is what the outline of the building's part at or above its
level holds beyond those regions' supports (:func:`tier_supports`); a gap between
supports narrower than one is closed (:func:`gap_supports`); both carry flat blocks.

``--supports FILE``: the quadrilaterals (or triangles) of a vector file, the paper's
interactive mode; supports that touch form one building.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from modeling.shared.footprint_priors import Prior, decompose_outline, rasterize_on
from workbench.errors import InputError
from workbench.raster import Grid

from .library import Frame

_FAMILIES = ("rect", "L", "T", "U", "courtyard")
_MAX_PARTS = 4  # priors per height region
_EDGE_TOLERANCE = 0.1  # metres: sides this close are one common edge
_MIN_EDGE_M = 1.0  # a common edge shorter than this makes no neighbours
_STEP_DISTANCE_M = 0.5  # the step is measured between cells this far apart
_MIN_TIER_CELLS = 10  # a piece of the outline with fewer cells of a tier is no tier


@dataclass
class Support:
    """A 2D support: its polygon (world metres), the frame of its bounding rectangle,
    the height region it was cut from (supports of one region may be junctions) and, for
    a lower tier's, the tier's level (metres)."""

    polygon: Polygon
    frame: Frame
    region: int = 0
    level: float = float("nan")

    @property
    def is_tier(self) -> bool:
        """A lower tier's flat piece (:func:`tier_supports`), which has its level."""
        return bool(np.isfinite(self.level))

    def record(self) -> dict:
        return {
            "polygon_m": [
                [round(float(x), 3), round(float(y), 3)]
                for x, y in self.polygon.exterior.coords[:-1]
            ],  # fmt: skip
            "rotation_deg": round(float(np.degrees(self.frame.theta)), 3),
        }


def height_regions(
    mask: np.ndarray,
    dsm: np.ndarray,
    gsd: float,
    step_m: float,
    min_cells: int,
    tiers: bool = True,
    min_width: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(h, w) int regions 1..n of ``mask`` that no height step crosses, 0 elsewhere;
    (h, w) bool the cells off their region's level: its steps and the small levels
    joined to it; and (h, w) bool the cells of the lower tiers too small for a region.

    A height step is a jump of more than ``step_m`` in the DSM (3 x 3 median) between
    cells ``_STEP_DISTANCE_M`` apart along a row or column (a wall; a roof of 70 degrees
    rises 1.4 m over that distance). Its cells are the two of each sharp edge within the
    jump's span (neighbours more than half a step apart): the wall's own pair, not every
    cell within the step's distance of it on both sides, which took a metre-wide strip
    of a lower tier along a tower (four cells) for steps alone and gave it to the tower.
    Levels smaller than ``min_cells`` and the step cells join the region nearest to
    them, for the outline. A small level lies beyond a step from the one it joins: a
    level too small for a block of its own (the strip of a lower tier along a tower's
    wall), whose cells no block of the region it joins should fit.

    But a small level, or one narrower than ``min_width`` cells (twice the largest
    distance of its cells to its edge: narrower than a support), that is flat and more
    than ``step_m`` below a wider region beside it
    (across the wall's steps) is a tier of its own, narrower than a support (a podium's
    ring 1.5 m wide round a tower, a middle tier's between the podium and the tower): it
    joins no region, nor do the step cells nearest it, so that the tower's supports stop
    at the tower's wall. Flat: the plane fitted to it rises less than half a step over a
    step's distance (a mansard's 70-degree lower slope, split by the steps its noise
    makes, rises nearly a whole one; a DSM's blur at a ring's walls tilts its plane by
    far less). Its cells (0 in the regions) are the third output, the step cells it
    took left out. ``tiers=False``: such levels, and the narrow ones, join a region as
    the other small ones."""
    z = ndimage.median_filter(np.where(np.isfinite(dsm), dsm, np.nanmin(dsm)), size=3)
    k = max(1, int(round(_STEP_DISTANCE_M / gsd)))
    step = np.zeros(mask.shape, bool)
    for axis in (0, 1):
        jump = np.abs(_shifted(z, k, axis)) > step_m  # (i, i + k)
        sharp = np.abs(_shifted(z, 1, axis)) > step_m / 2  # (c, c + 1)
        # the edge (c, c + 1) lies within a jump's span when one starts at c + 1 - k .. c
        spanned = np.zeros(sharp.shape, bool)
        for d in range(k):  # c = i + d for the jump (i, i + k)
            spanned[_along(axis, d, d + jump.shape[axis])] |= jump
        edge = sharp & spanned
        step[_along(axis, 0, -1)] |= edge
        step[_along(axis, 1, None)] |= edge
    labels, n = ndimage.label(mask & ~step)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= min_cells
    keep[0] = False
    if not keep.any():
        return mask.astype(np.int32), step & mask, np.zeros(mask.shape, bool)
    lower = np.zeros(0, int)
    wide = keep.copy()
    if min_width > 1:  # twice the largest distance of a level's cells to its edge
        inner = ndimage.distance_transform_edt(np.pad(labels > 0, 1))[1:-1, 1:-1]
        widest = np.concatenate([[0.0], ndimage.maximum(inner, labels, np.arange(1, n + 1))])
        wide &= 2 * widest >= min_width
    if not tiers:  # a narrow level joins a region as the small ones do
        keep = wide
    elif wide.any():
        rank = np.zeros(n + 1, np.int32)
        rank[wide] = np.arange(1, int(wide.sum()) + 1)
        lower = _lower_tiers(labels, wide, rank[labels], z, gsd, step_m, 2 * k + 1)
        keep[lower] = False  # a narrow level is a region of its own unless a lower tier
    m = int(keep.sum())
    new = np.zeros(n + 1, np.int32)
    new[keep] = np.arange(1, m + 1)
    kept = new[labels]
    new[lower] = m + 1 + np.arange(len(lower))
    levels = new[labels]
    # every other cell of the mask to the nearest kept region or lower tier
    _, (ri, ci) = ndimage.distance_transform_edt(levels == 0, return_indices=True)
    nearest = np.where(mask, levels[ri, ci], 0)
    regions = np.where(nearest > m, 0, nearest).astype(np.int32)
    return regions, mask & (kept == 0), (levels > m) & mask


def _lower_tiers(
    labels: np.ndarray,
    keep: np.ndarray,
    kept: np.ndarray,
    z: np.ndarray,
    gsd: float,
    step_m: float,
    reach: int,
) -> np.ndarray:
    """The labels of :func:`height_regions`' small levels that are lower tiers: flat
    (the plane fitted to their heights ``z``, metres on cells of ``gsd`` m, rises less
    than half of ``step_m`` over ``_STEP_DISTANCE_M``) and with a median more than
    ``step_m`` below the highest kept region (``kept``, regions 1..m) within ``reach``
    cells of them (the wall between them and their cells on a step)."""
    small = np.flatnonzero(~keep[1:]) + 1
    if not len(small):
        return small
    level = np.concatenate([[-np.inf], ndimage.median(z, kept, np.arange(1, int(kept.max()) + 1))])
    boxes = ndimage.find_objects(labels)
    out = []
    for j in small:
        box = tuple(slice(max(b.start - reach, 0), b.stop + reach) for b in boxes[j - 1])
        own = labels[box] == j
        near = ndimage.binary_dilation(own, iterations=reach)
        r, c = np.nonzero(own)
        zj = z[box][own]
        if len(zj) < 3 or np.median(zj) >= level[kept[box][near]].max() - step_m:
            continue
        a = np.column_stack([(c - c.mean()) * gsd, (r - r.mean()) * gsd, np.ones(len(zj))])
        (gx, gy, _), *_ = np.linalg.lstsq(a, zj, rcond=None)
        if np.hypot(gx, gy) * _STEP_DISTANCE_M < step_m / 2:
            out.append(j)
    return np.asarray(out, int)


def _along(axis: int, start: int, stop: int | None) -> tuple[slice, slice]:
    """The index of ``start:stop`` along ``axis`` of a 2-D array, everything along the
    other."""
    index = [slice(None)] * 2
    index[axis] = slice(start, stop)
    return tuple(index)


def _shifted(z: np.ndarray, k: int, axis: int) -> np.ndarray:
    return z[_along(axis, k, None)] - z[_along(axis, 0, -k)]


def connected_rectangles(prior: Prior) -> list[np.ndarray]:
    """(4,) rectangles u0, u1, v0, v1 of the prior's frame: its arms, each less the
    earlier ones, so that they do not overlap and meet on common edges."""
    taken = None
    out = []
    for wing in prior.wings():
        r = box(wing[0], wing[2], wing[1], wing[3])
        rest = r if taken is None else r.difference(taken)
        if rest.area > 1e-6:
            u0, v0, u1, v1 = rest.bounds
            if rest.area >= 0.98 * (u1 - u0) * (v1 - v0):  # still a rectangle
                out.append(np.array([u0, u1, v0, v1]))
        taken = r if taken is None else taken.union(r)
    return out


@dataclass
class FoundSupports:
    """What :func:`automatic_supports` finds in one building."""

    supports: list[Support]  # the regions' rectangles, each a block of the annealing
    tiers: list[Support]  # the lower tiers narrower than a support: flat, not annealed
    regions: np.ndarray  # (h, w) int, :func:`height_regions`
    off_level: np.ndarray  # (h, w) bool


def automatic_supports(
    mask: np.ndarray,
    dsm: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    grid: Grid,
    min_part_m: float,
    min_cells: int,
    step_m: float,
    dtm: np.ndarray | None = None,
    hidden: np.ndarray | None = None,
    unseen: np.ndarray | None = None,
) -> FoundSupports:
    """The supports of one building: its height regions, each decomposed into the
    rectangles of its footprint priors, and its lower tiers too narrow for a support
    (:func:`tier_supports`).

    mask : (h, w) bool the building's cells on ``grid``; dsm, dtm : (h, w) metres (a
    tier stands more than ``step_m`` above the DTM: lower, it is ground the outline took
    in); xs : (w,), ys : (h,) cell centres. When the tiers give no support, the supports
    are those of the regions their cells join (:func:`height_regions`, ``tiers=False``):
    the tower's cover the ring at its own height rather than leave a slot. ``hidden``
    (h, w) bool, optional: cells off the building whose footprint no view shows (the
    crowns over its edge, :func:`~modeling.shared.footprint_priors.crowns_over_the_edge`),
    which the regions' priors neither pay for covering nor for leaving out. ``unseen``
    (h, w) bool, optional: the building's cells no view saw, at the level they were
    given (:func:`~modeling.shared.opened_parts.unseen_at_level`), which the tiers'
    priors neither pay for covering nor for leaving out (:func:`tier_supports`). A
    tier's cell over an unknown DTM stays a tier's: no view saw the ground beside it."""
    narrowest = max(int(min_part_m / grid.gsd), 1)
    # the levels narrower than a support as tiers; where no tier comes of them, as regions
    # of their own (a LiDAR house's annex under 3 m wide whose ground the cloud lacks); at
    # last joined to the regions beside them
    for split, min_width in dict.fromkeys([(True, narrowest), (True, 1), (False, narrowest)]):
        regions, off_level, tier_cells = height_regions(
            mask, dsm, grid.gsd, step_m, min_cells, split, min_width
        )
        if dtm is not None:
            with np.errstate(invalid="ignore"):  # an unknown ground does not say ground
                tier_cells &= ~(dsm - dtm <= step_m)
        supports = [
            Support(poly, frame, r)
            for r in range(1, int(regions.max()) + 1)
            for poly, frame in _prior_rectangles(
                regions == r, xs, ys, grid, min_part_m, min_cells, hidden
            )
        ]
        if not (mask & (regions == 0)).any():
            return FoundSupports(supports, [], regions, off_level)
        tiers = tier_supports(supports, mask, tier_cells, regions, dsm, xs, ys, grid,
                              min_part_m, min_cells, step_m, unseen)  # fmt: skip
        if tiers:
            return FoundSupports(supports, tiers, regions, off_level)
    return FoundSupports(supports, [], regions, off_level)


def _prior_rectangles(
    mask: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    grid: Grid,
    min_part_m: float,
    min_cells: int,
    hidden: np.ndarray | None = None,
) -> list[tuple[Polygon, Frame]]:
    """The rectangles of the footprint priors decomposed from ``mask``'s outline, each a
    polygon (world metres) and its prior's frame, those of ``min_cells`` cells or more
    (``hidden``: :func:`~modeling.shared.footprint_priors.decompose_outline`'s)."""
    priors, _ = decompose_outline(mask, xs, ys, grid, _FAMILIES, min_part_m, np.inf, 1.0,
                                  min_cells, _MAX_PARTS, lambda_label=0.95,
                                  hidden=hidden)  # fmt: skip
    out = []
    for p in priors:
        for rect in connected_rectangles(p):
            frame = Frame(float(p.theta), (float(p.origin[0]), float(p.origin[1])),
                          tuple(float(v) for v in rect))  # fmt: skip
            poly = p.frame_polygon(rect)
            if poly.area >= min_cells * grid.gsd**2:
                out.append((poly, frame))
    return out


def tier_supports(
    supports: list[Support],
    mask: np.ndarray,
    tiers: np.ndarray,
    regions: np.ndarray,
    dsm: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    grid: Grid,
    min_part_m: float,
    min_cells: int,
    step_m: float,
    unseen: np.ndarray | None = None,
) -> list[Support]:
    """Supports for the lower tiers narrower than a support (``tiers``, (h, w) bool on
    ``grid``, :func:`height_regions`), level by level: the pieces of the outline of the
    building's part at or above a tier's level (its area, the cells of ``mask`` in no
    region, with the higher regions' cells; the rectangles of its footprint priors)
    that the higher regions' ``supports`` leave uncovered, each at least a cell wide and
    with ``_MIN_TIER_CELLS`` or more on that tier. Tiers within ``step_m`` of one another
    are one level (``dsm``, metres: their cells' medians).

    Without them a tower's supports stop at its wall and the podium's ring round it is a
    slot down to the ground; a prior of the podium's own cells has no arm as narrow as
    the ring (``min_part_m``). The building's outline has: the ring is what its
    rectangle holds beyond the tower's. A middle tier between a podium and a tower is
    the same ring on the outline of the part above the podium; its block, higher than
    the podium's (whose courtyard arms, ``min_part_m`` wide at least, may reach under
    it), stands on them in the envelope.

    ``unseen`` (h, w) bool, optional: the building's cells no view saw. They were given
    the lowest level around them, so a tier hidden behind the tower in part has an
    outline with a bite out of it, and its L prior would leave the bite at the podium's
    level. They are hidden from the priors (``decompose_outline``'s ``hidden``): the
    tier's rectangle is what its seen cells draw (on dev seeds 9 and 11, 0.39 and 0.62
    of the squared error off the jumps was such a corner)."""
    if not supports or tiers.sum() < _MIN_TIER_CELLS:
        return []
    area = mask & (regions == 0)
    parts, n = ndimage.label(area)
    part_level = np.full(n + 1, np.nan)
    for p in range(1, n + 1):
        z = dsm[(parts == p) & tiers]
        part_level[p] = np.median(z) if len(z) else np.nan
    # parts within a step of one another are one level; a part with no tier cell (a wall's
    # steps) goes with the level whose tier cells are nearest
    group = np.zeros(n + 1, int)
    levels: list[float] = []
    for p in np.argsort(part_level):  # NaN last
        if not np.isfinite(part_level[p]):
            break
        if not levels or part_level[p] > levels[-1] + step_m:
            levels.append(part_level[p])
        group[p] = len(levels)
    grouped = group[parts]
    _, (ri, ci) = ndimage.distance_transform_edt(grouped == 0, return_indices=True)
    grouped = np.where(area, grouped[ri, ci], 0)
    ids = np.arange(1, int(regions.max()) + 1)
    region_level = np.concatenate([[np.nan], ndimage.median(dsm, regions, ids)])
    out = []
    for g, low in enumerate(levels, start=1):
        own = grouped == g
        level = float(np.median(dsm[own & tiers]))
        higher = region_level[regions] > low - step_m
        above = [s.polygon for s in supports if region_level[s.region] > low - step_m]
        hidden = None if unseen is None else unseen & ~(own | higher)
        rects = _prior_rectangles(own | higher, xs, ys, grid, min_part_m, min_cells, hidden)
        outer = unary_union([poly for poly, _ in rects])
        for piece in _without_holes(outer.difference(unary_union(above)) if above else outer):
            if piece.buffer(-grid.gsd / 2, join_style="mitre").is_empty:
                continue
            if (rasterize_on(piece, grid) & tiers & own).sum() >= _MIN_TIER_CELLS:
                out.append(Support(piece, rectangle_frame(piece), 0, level))
    return out


def gap_supports(supports: list[Support], mask: np.ndarray, grid: Grid,
                 width_m: float) -> list[Support]:  # fmt: skip
    """Supports for the building's gaps between its supports narrower than ``width_m``:
    the pieces of the supports' union closed by ``width_m / 2`` (square joins, so that a
    rectilinear outline keeps its corners) that the union leaves uncovered, each over
    the centre of a cell or more and at least half on the building's cells ``mask``
    ((h, w) on ``grid``).

    No footprint prior has an arm narrower than ``width_m`` (the strip of a tier between a
    tower's wall and the podium's edge, a leftover part of an outline), and the solid of
    the blocks is their upper envelope down to the ground: such a strip would be a slot
    through the building, as deep as the building is tall. So would a sliver between two
    supports cut from different priors, a hair apart, where it passes over a row or a
    column of cell centres (dev seed 10: a 0.1 m sliver along a 62 m tower's wall, 0.87
    of the seed's squared error off the jumps). One that covers no cell centre is left:
    no raster shows it, and the mesh keeps a crack a few centimetres wide."""
    if not supports:
        return []
    union = unary_union([s.polygon for s in supports])
    d = width_m / 2
    closed = union.buffer(d, join_style="mitre").buffer(-d, join_style="mitre")
    out = []
    for piece in _without_holes(closed.difference(union)):
        cells = rasterize_on(piece, grid)
        if cells.any() and (cells & mask).sum() >= 0.5 * cells.sum():
            out.append(Support(piece, rectangle_frame(piece), 0))
    return out


def _without_holes(geom) -> list[Polygon]:
    """The polygons of ``geom``, each with holes cut in two along the row through its
    first hole's centre (a gap all round a tower is a ring; a support has no hole)."""
    out = []
    for piece in getattr(geom, "geoms", [geom]):
        if not isinstance(piece, Polygon) or piece.is_empty:
            continue
        if not piece.interiors:
            out.append(piece)
            continue
        x0, y0, x1, y1 = piece.bounds
        y = Polygon(piece.interiors[0]).centroid.y
        for half in (box(x0, y0, x1, y), box(x0, y, x1, y1)):
            out += _without_holes(piece.intersection(half))
    return out


def support_cells(supports: list[Support], mask: np.ndarray, regions: np.ndarray,
                  grid: Grid) -> list[np.ndarray]:  # fmt: skip
    """(h, w) bool cells of each support: the building's cells of its region (any
    region, for supports read from a file) whose centre it covers and no earlier
    support took."""
    taken = np.zeros(mask.shape, bool)
    out = []
    for s in supports:
        cells = rasterize_on(s.polygon, grid) & mask & ~taken
        if s.region:
            cells &= regions == s.region
        taken |= cells
        out.append(cells)
    return out


def junction_sides(supports: list[Support]) -> list[tuple[bool, bool, bool, bool]]:
    """Per support, whether each side of its rectangle (u0, v0, u1, v1) is a junction:
    at least half of it a common edge with supports of the same height region."""
    out = []
    for i, s in enumerate(supports):
        others = [t.polygon for j, t in enumerate(supports) if j != i and t.region == s.region]
        near = unary_union(others).buffer(_EDGE_TOLERANCE) if others else None
        u0, u1, v0, v1 = s.frame.rect
        corners = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
        sides = []
        for a, b in ((3, 0), (0, 1), (1, 2), (2, 3)):  # u0, v0, u1, v1
            xa, ya = s.frame.to_world(np.array(corners[a][0]), np.array(corners[a][1]))
            xb, yb = s.frame.to_world(np.array(corners[b][0]), np.array(corners[b][1]))
            side = shapely.LineString([(float(xa), float(ya)), (float(xb), float(yb))])
            shared = 0.0 if near is None else side.intersection(near).length
            sides.append(shared >= 0.5 * side.length)
        out.append(tuple(sides))
    return out


def junction_strips(supports: list[Support], ends: list) -> dict:
    """{(i, side): (j, strip)}: for each junction side of each automatic support, the
    neighbour j across it and the rectangle (u0, u1, v0, v1 of i's frame) over which a
    ridge running into that side carries its roof on: i's width, half of j's depth (up to
    where an L's valleys meet the other arm's ridge)."""
    out = {}
    for i, s in enumerate(supports):
        if not s.region:
            continue
        u0, u1, v0, v1 = s.frame.rect
        for side in range(4):
            if not ends[i][side]:
                continue
            best, j_best = 0.0, None
            for j, t in enumerate(supports):
                if j != i and t.region == s.region:
                    shared = t.polygon.buffer(_EDGE_TOLERANCE).intersection(s.polygon).area
                    if shared > best:
                        best, j_best = shared, j
            if j_best is None:
                continue
            xy = np.asarray(supports[j_best].polygon.exterior.coords)
            u, v = s.frame.to_frame(xy[:, 0], xy[:, 1])
            if side == 0:
                strip = (u0 - 0.5 * (u0 - u.min()), u0, v0, v1)
            elif side == 2:
                strip = (u1, u1 + 0.5 * (u.max() - u1), v0, v1)
            elif side == 1:
                strip = (u0, u1, v0 - 0.5 * (v0 - v.min()), v0)
            else:
                strip = (u0, u1, v1, v1 + 0.5 * (v.max() - v1))
            out[(i, side)] = (j_best, np.array(strip))
    return out


def carried_polygon(support: Support, strips: list[np.ndarray]) -> Polygon:
    """The support's rectangle grown over the strips its ridge carries its roof on."""
    u0, u1, v0, v1 = support.frame.rect
    for s in strips:
        u0, u1, v0, v1 = min(u0, s[0]), max(u1, s[1]), min(v0, s[2]), max(v1, s[3])
    x, y = support.frame.to_world(np.array([u0, u1, u1, u0]), np.array([v0, v0, v1, v1]))
    return Polygon(np.column_stack([x, y]))


def neighbour_pairs(supports: list[Support]) -> list[tuple[int, int, np.ndarray]]:
    """(i, j, unit vector of the common edge) for supports with a common edge of at
    least ``_MIN_EDGE_M``."""
    out = []
    for i in range(len(supports)):
        for j in range(i + 1, len(supports)):
            a, b = supports[i].polygon, supports[j].polygon
            common = a.boundary.intersection(b.buffer(_EDGE_TOLERANCE))
            if common.length < _MIN_EDGE_M:
                continue
            pts = np.asarray(shapely.get_coordinates(common))
            d = pts[np.argmax(((pts - pts[0]) ** 2).sum(axis=1))] - pts[0]
            out.append((i, j, d / max(np.hypot(*d), 1e-9)))
    return out


def supports_from_file(path, polygons: list[Polygon], grid: Grid) -> list[list[Support]]:
    """The supports of a vector file, grouped into buildings (supports that touch).

    Raises
    ------
    InputError
        Naming the file and the feature: a support that is not a quadrilateral or a
        triangle, lies outside the grid, or overlaps another."""
    xmin, ymin, xmax, ymax = grid.bounds
    extent = box(xmin, ymin, xmax, ymax)
    supports = []
    for k, poly in enumerate(polygons):
        field = f"features[{k}]"
        if not isinstance(poly, Polygon) or poly.is_empty:
            raise InputError(path, field, "not a polygon: a 2D support is a quadrilateral")
        ring = shapely.simplify(poly, grid.gsd * 1e-3).exterior
        n = len(ring.coords) - 1
        if n not in (3, 4) or poly.convex_hull.area > poly.area * 1.001:
            raise InputError(path, field, f"a polygon of {n} corners: a 2D support is a convex "
                             "quadrilateral or triangle")  # fmt: skip
        if not extent.contains(poly):
            raise InputError(path, field, "outside the fusion's grid")
        supports.append(Support(poly, rectangle_frame(poly), 0))
    polys = [s.polygon for s in supports]
    # a spatial index keeps a city's file linear, not quadratic, in its supports
    first, second = shapely.STRtree(polys).query(polys, predicate="intersects")
    for i, j in sorted(zip(first.tolist(), second.tolist(), strict=True)):
        if i >= j:
            continue
        overlap = polys[i].intersection(polys[j]).area
        if overlap > 0.01 * min(polys[i].area, polys[j].area):
            raise InputError(path, f"features[{j}]", f"overlaps features[{i}] by "
                             f"{overlap:.1f} m²: supports must not overlap")  # fmt: skip
    supports = snapped_together(supports)
    groups = unary_union([s.polygon.buffer(_EDGE_TOLERANCE) for s in supports])
    groups = list(getattr(groups, "geoms", [groups]))
    points = [s.polygon.representative_point() for s in supports]
    which, group = shapely.STRtree(groups).query(points, predicate="within")
    buildings = [[] for _ in groups]
    for k, g in sorted(zip(which.tolist(), group.tolist(), strict=True)):
        buildings[g].append(supports[k])
    return buildings


def snapped_together(supports: list[Support]) -> list[Support]:
    """The supports with every vertex within ``_EDGE_TOLERANCE`` of another support's
    boundary moved onto it (GEOS snapping, in order): supports drawn by hand or rounded
    in a file meet a millimetre apart, and the mesh of their common edge needs them to
    meet exactly."""
    out = list(supports)
    # only supports this near can reach within the tolerance once snapped themselves
    first, second = shapely.STRtree([s.polygon for s in supports]).query(
        [s.polygon for s in supports], predicate="dwithin", distance=2 * _EDGE_TOLERANCE
    )
    near = [sorted(second[(first == i) & (second != i)].tolist()) for i in range(len(out))]
    for i, s in enumerate(out):
        others = [out[j].polygon for j in near[i]]
        if others:
            snapped = shapely.snap(s.polygon, unary_union(others).boundary, _EDGE_TOLERANCE)
            if isinstance(snapped, Polygon) and snapped.is_valid:
                out[i] = Support(snapped, s.frame, s.region)
    return out


def rectangle_frame(poly: Polygon) -> Frame:
    """The frame of a polygon's minimum rotated rectangle, u along its longer side."""
    rect = np.asarray(poly.minimum_rotated_rectangle.exterior.coords)[:4]
    e1, e2 = rect[1] - rect[0], rect[2] - rect[1]
    axis = e1 if np.hypot(*e1) >= np.hypot(*e2) else e2
    theta = float(np.arctan2(axis[1], axis[0]))
    c = np.asarray(poly.centroid.coords[0])
    frame = Frame(theta, (float(c[0]), float(c[1])), (0.0, 0.0, 0.0, 0.0))
    u, v = frame.to_frame(rect[:, 0], rect[:, 1])
    return Frame(theta, frame.origin, (float(u.min()), float(u.max()), float(v.min()),
                                       float(v.max())))  # fmt: skip
