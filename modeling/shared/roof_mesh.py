"""Rooftop modeling (the super-pixel paper, section 5.3): roof faces from the prototype
labels, straightened, lifted to their planes, walled down to the ground, closed.

The faces of a building form a planar coverage: polygons that share their boundaries
vertex for vertex. Every roof vertex is lifted vertically onto its face's plane; where two
faces meet at different heights, or a face meets the outside, a vertical wall fills the
gap, split at every height any face has at its ends, so that the mesh is closed and every
edge has exactly two triangles.
"""

from __future__ import annotations

import cv2
import numpy as np
import rasterio.features
import shapely
from shapely.geometry import Polygon, shape
from shapely.geometry.polygon import orient

from workbench.planes import plane_heights
from workbench.raster import Grid

from .outline_regularity import regularise_outline

_EPS = 1e-7  # metres, on coordinates
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)  # 4-neighbourhood
_Z_EPS = 0.02  # metres: heights this close at a vertex are one level (one vertex)


def face_polygons(
    faces: np.ndarray,
    grid: Grid,
    tolerance: float,
    min_face_m2: float = 2.0,
    regularise_deg: float = 0.0,
) -> tuple[list[Polygon], list[int]]:
    """Polygons of the labelled faces, simplified together so that shared boundaries
    stay shared (a topology-preserving simplification of the coverage).

    Parameters
    ----------
    faces : (H, W) int
        Face label of every cell, 0 outside the building.
    grid : Grid
    tolerance : float
        Simplification tolerance, metres.
    min_face_m2 : float
        Connected face regions smaller than this join the neighbouring face they share
        most boundary with: slivers carry no plane worth a polygon.
    regularise_deg : float
        Outline sides this close to the building's dominant directions are put on them
        (:func:`~modeling.shared.outline_regularity.regularise_outline`, no vertex moving more
        than twice ``tolerance``); 0 leaves the outline as simplified.

    Returns
    -------
    polygons, face label of each
    """
    min_cells = max(1, int(round(min_face_m2 / grid.gsd**2)))
    faces = untangle_diagonals(merge_small_regions(faces, min_cells))
    polys, labels = [], []
    for geom, value in rasterio.features.shapes(
        faces.astype(np.int32), mask=faces > 0, transform=grid.transform, connectivity=4
    ):
        polys.append(shape(geom))
        labels.append(int(value))
    if not polys:
        return [], []
    simple = shapely.coverage_simplify(vertex_matched(polys, grid.gsd * 1e-3), tolerance)
    parts, out_labels = [], []
    for p, lab in zip(simple, labels, strict=True):
        p = shapely.make_valid(p) if not p.is_valid else p
        for part in getattr(p, "geoms", [p]):
            if isinstance(part, Polygon) and part.area > 1e-6:
                parts.append(part)
                out_labels.append(lab)
    parts = regularise_outline(parts, regularise_deg, max_shift=2 * tolerance)
    return [orient(_fill_small_holes(p, parts, 4 * grid.gsd**2), 1.0) for p in parts], out_labels


def vertex_matched(polys: list[Polygon], tolerance: float) -> np.ndarray:
    """The polygons with every vertex of the others that lies on one of their edges
    inserted into that edge (GEOS snapping), as an object array.

    Polygonising a label raster leaves no vertex on a straight edge where two other
    faces meet it (a T-junction). GEOS's coverage simplification needs the shared
    edges to match vertex for vertex; without it, a building with one such junction was
    left unsimplified (a staircase of 1,464 triangles instead of 186) or not closed.
    """
    rings = [r for p in polys for r in (p.exterior, *p.interiors)]
    points = shapely.points(np.concatenate([np.asarray(r.coords) for r in rings]))
    # only the vertices within the tolerance of a polygon can snap to it: a spatial index
    # keeps a terrace of thousands of faces linear, not quadratic
    which, near = shapely.STRtree(points).query(polys, predicate="dwithin", distance=tolerance)
    order = np.argsort(which, kind="stable")
    which, near = which[order], near[order]
    starts = np.searchsorted(which, np.arange(len(polys) + 1))
    return np.array(
        [
            shapely.snap(p, shapely.multipoints(points[near[starts[k] : starts[k + 1]]]), tolerance)
            for k, p in enumerate(polys)
        ],
        dtype=object,
    )


def merge_small_regions(faces: np.ndarray, min_cells: int) -> np.ndarray:
    """Give every 4-connected region of one face label smaller than ``min_cells`` the
    label of the neighbouring face it shares most cell edges with (0 stays 0)."""
    from scipy.ndimage import find_objects
    from skimage.measure import label as connected_regions

    out = faces.copy()
    regions = connected_regions(faces, background=0, connectivity=1)
    sizes = np.bincount(regions.ravel())
    small = np.flatnonzero(sizes < min_cells)
    small = small[small > 0]
    face_of = np.zeros(len(sizes), faces.dtype)
    face_of[regions.ravel()] = faces.ravel()
    boxes = find_objects(regions)
    H, W = faces.shape
    # by face label, then raster order: each region looks at the labels left by the last
    for k in small[np.lexsort((small, face_of[small]))]:
        rows, cols = boxes[k - 1]
        window = (
            slice(max(rows.start - 1, 0), min(rows.stop + 1, H)),
            slice(max(cols.start - 1, 0), min(cols.stop + 1, W)),
        )
        _absorb(out[window], regions[window] == k)  # a view: relabels ``out`` in place
    return out


def merge_smallest_face(
    faces: np.ndarray,
    among: np.ndarray | None = None,
    planes: np.ndarray | None = None,
    grid: Grid | None = None,
    within: np.ndarray | None = None,
) -> np.ndarray:
    """Give the cells of the smallest face label (of those in ``among``, when any of them
    is present; only its cells in ``within`` (H, W) bool when given) to a neighbouring
    face: with ``planes`` (P, 4) on ``grid``, the one whose plane lies nearest the face's
    own over those cells (a face across a ridge would lift them above the roof), else
    the one it shares most cell edges with."""
    labels, counts = np.unique(faces[faces > 0], return_counts=True)
    pick = np.isin(labels, among) if among is not None else np.zeros(len(labels), bool)
    if pick.any():
        labels, counts = labels[pick], counts[pick]
    out = faces.copy()
    region = faces == labels[np.argmin(counts)]
    if within is not None and (region & within).any():
        region &= within
    if planes is None or grid is None:
        _absorb(out, region)
        return out
    ring = (cv2.dilate(region.astype(np.uint8), _CROSS) > 0) & ~region & (faces > 0)
    others = np.unique(faces[ring])
    others = others[others != faces[region][0]]
    if not len(others):
        return out
    X, Y = grid.cell_centers()
    x, y = X[region], Y[region]
    own = plane_heights(planes[faces[region][0] - 1], x, y)
    cost = [np.mean(np.abs(plane_heights(planes[q - 1], x, y) - own)) for q in others]
    out[region] = others[int(np.argmin(cost))]
    return out


def _absorb(faces: np.ndarray, region: np.ndarray) -> None:
    """Relabel ``region`` (one label) in place with the other face label most common
    among its 4-neighbours, if it has any."""
    label = faces[region][0]
    ring = cv2.dilate(region.astype(np.uint8), _CROSS) > 0
    around = faces[ring & ~region]
    around = around[(around > 0) & (around != label)]
    if len(around):
        faces[region] = np.bincount(around).argmax()


def untangle_diagonals(faces: np.ndarray) -> np.ndarray:
    """Remove 2 x 2 blocks where one label touches itself only across a corner.

    Such a corner would be shared by two polygons of one face (or two stretches of the
    outline), and the solid would pinch there: not a manifold. The corner is bridged by
    giving one of the two other cells the touching label (outside cells join the
    building rather than the reverse).
    """
    f = np.pad(faces, 1).copy()
    for _ in range(f.size):
        a, b, c, d = f[:-1, :-1], f[:-1, 1:], f[1:, :-1], f[1:, 1:]
        main = (a == d) & (b != a) & (c != a)  # a and d touch at the corner
        anti = (b == c) & (a != b) & (d != b)
        if not (main.any() or anti.any()):
            break
        r, k = np.nonzero(main | anti)
        r, k = r[0], k[0]  # one at a time: a fix can create or remove others nearby
        if main[r, k]:
            if f[r, k] != 0:
                f[r, k + 1] = f[r, k]  # the top-right cell joins the face
            else:
                f[r, k] = f[r, k + 1]  # an outside corner: fill it from a neighbour
        elif f[r, k + 1] != 0:
            f[r, k] = f[r, k + 1]
        else:
            f[r, k + 1] = f[r, k]
    return f[1:-1, 1:-1]


def _fill_small_holes(poly: Polygon, others: list[Polygon], min_area: float) -> Polygon:
    """Fill holes below ``min_area`` that no other face fills: slivers left by the
    simplification, which would pinch the solid where they touch the outline."""
    keep = []
    for ring in poly.interiors:
        hole = Polygon(ring)
        filled = any(o is not poly and o.representative_point().within(hole) for o in others)
        if hole.area >= min_area or filled:
            keep.append(ring)
    return Polygon(poly.exterior, keep) if len(keep) != len(poly.interiors) else poly


def extrude_faces(
    polygons: list[Polygon], planes: list[np.ndarray], base_z: float
) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-oriented mesh of roof faces on their planes over a flat floor.

    Parameters
    ----------
    polygons : list of Polygon
        A coverage (shared boundaries, no overlaps), world metres.
    planes : list of (4,) arrays
        The plane of each polygon's roof.
    base_z : float
        Height of the floor, metres (below every roof).

    Returns
    -------
    vertices : (V, 3) float64
    triangles : (T, 3) int64, counter-clockwise seen from outside
    """

    def roof(f: int, x, y):
        return plane_heights(planes[f], x, y)

    rings, xy = _noded_rings(polygons)
    rings = _split_crossings(rings, xy, roof)
    xy = np.asarray(xy)
    keys = _vertex_keys(xy)
    z_of = [roof(f, xy[:, 0], xy[:, 1]) for f in range(len(planes))]  # (F, V2)
    owner = _edge_owners(rings)
    lows, heights = _levels(rings, z_of, base_z, len(xy))
    verts: dict[tuple[int, int], int] = {}

    def level(v: int, z: float) -> int:
        return int(np.searchsorted(lows[v], z + _Z_EPS, side="right")) - 1

    def vid(v: int, li: int) -> int:
        if (v, li) not in verts:
            verts[(v, li)] = len(verts)
        return verts[(v, li)]

    tris = []
    floor = _outline_polygons(owner, xy)
    for f, face in enumerate(rings):
        poly = Polygon(xy[face[0]], [xy[r] for r in face[1:]])
        for t in _triangulate(poly, keys):
            tris.append([vid(v, level(v, z_of[f][v])) for v in t])  # roof, up
            if floor is None:
                tris.append([vid(v, 0) for v in t[::-1]])  # floor under each face, down
        for ring in face:
            for a, b in zip(ring, np.roll(ring, -1), strict=True):
                g = owner.get((b, a))
                low_a = 0 if g is None else level(a, z_of[g][a])
                low_b = 0 if g is None else level(b, z_of[g][b])
                high_a, high_b = level(a, z_of[f][a]), level(b, z_of[f][b])
                if high_a < low_a or high_b < low_b:
                    continue  # the other face is higher: its wall
                if high_a == low_a and high_b == low_b:
                    continue  # the faces meet without a step
                chain_a = np.arange(low_a, high_a + 1)
                chain_b = np.arange(low_b, high_b + 1)
                for tri in _strip(chain_a, chain_b, heights[a], heights[b]):
                    tris.append([vid(a if side == 0 else b, li) for side, li in tri])
    for poly in floor or []:
        tris.extend([vid(v, 0) for v in t[::-1]] for t in _triangulate(poly, keys))
    vertices = np.zeros((len(verts), 3))
    for (v, li), i in verts.items():
        vertices[i] = (xy[v, 0], xy[v, 1], heights[v][li])
    return vertices, np.asarray(tris, np.int64).reshape(-1, 3)


def _edge_owners(rings) -> dict[tuple[int, int], int]:
    """The face of every directed ring edge (a, b); faces run counter-clockwise, so a
    shared edge appears once each way and an outline edge once."""
    owner = {}
    for f, face in enumerate(rings):
        for ring in face:
            for a, b in zip(ring, np.roll(ring, -1), strict=True):
                owner[(int(a), int(b))] = f
    return owner


def _outline_polygons(owner: dict, xy: np.ndarray) -> list[Polygon] | None:
    """The building's outline as polygons over the shared vertex table: the rings of
    the face edges (``owner``, :func:`_edge_owners`) no other face runs back along.
    The floor is triangulated over these alone, with no vertex inside, instead of once
    under every face: fewer triangles, the same solid. None where the outline touches
    itself at a vertex (the walk would be ambiguous); the floor then follows the faces."""
    nxt: dict[int, int] = {}
    for a, b in owner:
        if (b, a) not in owner:
            if a in nxt:
                return None
            nxt[a] = b
    loops = []
    while nxt:
        start = next(iter(nxt))
        loop = [start]
        while (v := nxt.pop(loop[-1], None)) is not None and v != start:
            loop.append(v)
        if v != start or len(loop) < 3:
            return None
        loops.append(Polygon(xy[loop]))
    shells = [p for p in loops if p.exterior.is_ccw]
    holes = [p for p in loops if not p.exterior.is_ccw]
    out = []
    for shell in shells:
        inner = [h.exterior for h in holes if shell.contains(h.representative_point())]
        out.append(Polygon(shell.exterior, inner))
    if sum(len(p.interiors) for p in out) != len(holes) or not all(p.is_valid for p in out):
        return None
    return out


def _noded_rings(polygons: list[Polygon]) -> tuple[list[list[np.ndarray]], list]:
    """Rings as vertex-id arrays over one shared vertex table, every vertex of any ring
    lying on another ring's edge inserted there (no T-junctions)."""
    coords = []
    for p in polygons:
        for r in [p.exterior, *p.interiors]:
            coords.append(np.asarray(r.coords)[:-1])
    allxy = np.concatenate(coords) if coords else np.empty((0, 2))
    keys = np.round(allxy / _EPS / 10).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    xy = [tuple(allxy[i]) for i in first]
    table = np.asarray(xy)
    tree = shapely.STRtree(shapely.points(table))
    rings, k = [], 0
    for p in polygons:
        face = []
        for r in [p.exterior, *p.interiors]:
            m = len(r.coords) - 1
            ids = inverse.ravel()[k : k + m]
            k += m
            near = np.sort(tree.query(shapely.box(*r.bounds).buffer(10 * _EPS)))
            face.append(_insert_on_edges(ids, table, near))
        rings.append(face)
    return rings, xy


def _insert_on_edges(ring: np.ndarray, table: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The ring with every vertex of ``table`` (among the indices ``near``: those in its
    bounding box) that lies on one of its edges inserted there, in order."""
    out = []
    candidates = table[near]
    for a, b in zip(ring, np.roll(ring, -1), strict=True):
        out.append(a)
        pa, pb = table[a], table[b]
        d = pb - pa
        L2 = d @ d
        if L2 == 0:
            continue
        t = (candidates - pa) @ d / L2
        rel = candidates - pa
        perp = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]) / np.sqrt(L2)
        on = np.flatnonzero((t > 1e-9) & (t < 1 - 1e-9) & (perp < 10 * _EPS))
        out.extend(near[on[np.argsort(t[on])]])
    return np.asarray(out, np.int64)


def _split_crossings(rings, xy: list, roof) -> list:
    """Insert a vertex where two neighbouring faces' roofs cross along their shared
    edge, so that each wall piece has one face above the other. ``roof(f, x, y)`` is the
    height of face f. Two planes differ linearly along an edge, so an edge crosses at most
    once and one pass over the edges finds every crossing."""
    table = np.asarray(xy)
    owner = _edge_owners(rings)
    split: dict[tuple[int, int], int] = {}
    for (a, b), f in owner.items():
        g = owner.get((b, a))
        if g is None or g < f:
            continue
        da = float(roof(f, *table[a]) - roof(g, *table[a]))
        db = float(roof(f, *table[b]) - roof(g, *table[b]))
        if (da > _Z_EPS and db < -_Z_EPS) or (da < -_Z_EPS and db > _Z_EPS):
            xy.append(tuple(table[a] + da / (da - db) * (table[b] - table[a])))
            split[(a, b)] = split[(b, a)] = len(xy) - 1
    if not split:
        return rings
    out = []
    for face in rings:
        new_face = []
        for ring in face:
            walked = []
            for u, v in zip(ring, np.roll(ring, -1), strict=True):
                walked.append(u)
                if (int(u), int(v)) in split:
                    walked.append(split[(int(u), int(v))])
            new_face.append(np.asarray(walked, np.int64))
        out.append(new_face)
    return out


def _levels(rings, z_of, base_z: float, n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The distinct heights at every 2D vertex (the floor, level 0, and each face's roof
    there), heights within ``_Z_EPS`` of the next lower one merged into one level.

    Returns the lowest height of each level (for look-ups) and each level's mean height.
    """
    found: list[list[float]] = [[base_z] for _ in range(n)]
    for f, face in enumerate(rings):
        for ring in face:
            for a in ring:
                found[a].append(float(z_of[f][a]))
    lows, means = [], []
    for zs in found:
        zs = np.sort(np.asarray(zs))
        cluster = np.r_[0, np.cumsum(np.diff(zs) > _Z_EPS)]
        lows.append(zs[np.r_[True, np.diff(cluster) > 0]])
        means.append(np.bincount(cluster, weights=zs) / np.bincount(cluster))
    for m in means:
        m[0] = base_z  # the floor stays flat
    return lows, means


def _strip(chain_p: np.ndarray, chain_q: np.ndarray, z_p: np.ndarray, z_q: np.ndarray) -> list:
    """Triangles between two vertical chains of levels at the ends p (side 0) and q
    (side 1) of a wall, outward for a face to the left of p -> q; ``z_p``, ``z_q`` are the
    heights of the levels. Each triangle corner is (side, level)."""

    def t(chain, i):
        z = z_p if chain is chain_p else z_q
        span = z[chain[-1]] - z[chain[0]]
        return (z[chain[i]] - z[chain[0]]) / span if span > 0 else 1.0

    i = j = 0
    out = []
    while i < len(chain_p) - 1 or j < len(chain_q) - 1:
        step_q = i == len(chain_p) - 1 or (
            j < len(chain_q) - 1 and t(chain_q, j + 1) <= t(chain_p, i + 1)
        )
        if step_q:
            out.append([(0, chain_p[i]), (1, chain_q[j]), (1, chain_q[j + 1])])
            j += 1
        else:
            out.append([(0, chain_p[i]), (1, chain_q[j]), (0, chain_p[i + 1])])
            i += 1
    return out


def _vertex_keys(xy: np.ndarray) -> dict[tuple[int, int], int]:
    """Vertex id of every coordinate of the shared table, by its rounded key."""
    keys = np.round(np.asarray(xy) / _EPS / 10).astype(np.int64)
    return {(int(a), int(b)): i for i, (a, b) in enumerate(keys)}


def _triangulate(poly: Polygon, keys: dict[tuple[int, int], int]) -> list[list[int]]:
    """Constrained Delaunay triangles of a polygon as counter-clockwise vertex-id triples
    (no new vertices); ``keys`` from :func:`_vertex_keys`."""
    out = []
    for tri in shapely.constrained_delaunay_triangles(poly).geoms:
        c = np.asarray(tri.exterior.coords)[:3]
        ids = [keys[(int(a), int(b))] for a, b in np.round(c / _EPS / 10).astype(np.int64)]
        area = (c[1, 0] - c[0, 0]) * (c[2, 1] - c[0, 1]) - (c[2, 0] - c[0, 0]) * (c[1, 1] - c[0, 1])
        if abs(area) < 1e-12:
            continue
        out.append(ids if area > 0 else ids[::-1])
    return out
