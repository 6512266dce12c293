"""A closed building mesh from the upper envelope of its roof faces.

Overlapping wings (L, T, U and courtyard buildings, stepped tiers) each bring
their own planar roof faces. The visible roof is their upper envelope: the faces'
outlines and the lines where two faces' planes cross are noded into a planar
arrangement; in each cell of it one face is on top. Cells become roof triangles,
height jumps between neighbouring cells become vertical walls, and a bottom
closes the solid. The result is watertight and consistently oriented (outward
normals), with vertical edges split wherever walls meet at different heights.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

from workbench.meshes import unpaired_edges

GRID = 1e-4  # metres: coordinates are snapped to this grid so that vertices match exactly
_EPS = 1e-3  # metres: offset used to probe the cell across an edge
_MIN_FACE_M2 = 1e-4  # a face smaller than this is a sliver of the clipping
_TICK = 0.01  # metres: half the piece of line that nodes an edge where two planes cross


@dataclass
class RoofFace:
    """A planar roof face: a convex polygon and its plane z = p[0] x + p[1] y + p[2]."""

    xy: np.ndarray  # (n, 2) world polygon, counter-clockwise
    plane: np.ndarray  # (3,)


@dataclass
class BuildingMesh:
    """Triangles of one building.

    Attributes
    ----------
    vertices : (V, 3) float64
    triangles : (T, 3) int64, counter-clockwise seen from outside
    part : (T,) uint8
        0 = roof, 1 = wall, 2 = bottom.
    axis : (T, 2) float64
        Texture axis: the downslope direction on roofs, the wall direction on walls.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    part: np.ndarray
    axis: np.ndarray


def clip_convex(poly: np.ndarray, a: float, b: float, c: float) -> np.ndarray:
    """The part of convex polygon ``poly`` ((n, 2), counter-clockwise) where
    a u + b v + c <= 0 (Sutherland-Hodgman against one half-plane)."""
    if not len(poly):
        return poly
    out = []
    f = poly @ np.array([a, b]) + c
    n = len(poly)
    for i in range(n):
        j = (i + 1) % n
        if f[i] <= 0:
            out.append(poly[i])
        if (f[i] < 0 < f[j]) or (f[j] < 0 < f[i]):
            s = f[i] / (f[i] - f[j])
            out.append(poly[i] + s * (poly[j] - poly[i]))
    return np.array(out) if out else np.zeros((0, 2))


def lowest_plane_faces(
    outline: np.ndarray, planes: np.ndarray, theta: float, origin: np.ndarray
) -> list[RoofFace]:
    """The faces of a roof that is the minimum of affine functions: for each plane, the
    part of ``outline`` where it is the lowest, in world coordinates.

    Parameters
    ----------
    outline : (n, 2) float
        A convex polygon, counter-clockwise, in a frame rotated by ``theta`` (radians
        from east) about ``origin`` ((2,) world metres).
    planes : (P, 3) float
        z = a u + b v + c of that frame.
    """
    c, s = np.cos(theta), np.sin(theta)
    out = []
    for k, p in enumerate(planes):
        region = outline
        for j, q in enumerate(planes):
            if j != k:
                region = clip_convex(region, *(p - q))  # p <= q
        if polygon_area(region) < _MIN_FACE_M2:
            continue
        xy = np.column_stack([origin[0] + c * region[:, 0] - s * region[:, 1],
                              origin[1] + s * region[:, 0] + c * region[:, 1]])  # fmt: skip
        # z = a u + b v + c with u = c(x - ox) + s(y - oy), v = -s(x - ox) + c(y - oy)
        ax, ay = p[0] * c - p[1] * s, p[0] * s + p[1] * c
        out.append(RoofFace(xy, np.array([ax, ay, p[2] - ax * origin[0] - ay * origin[1]])))
    return out


def polygon_area(poly: np.ndarray) -> float:
    """Signed area of a polygon (n, 2), positive counter-clockwise."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def face_planes(faces: list[RoofFace]) -> tuple[np.ndarray, np.ndarray]:
    """(P, 4) planes (n, d) with n_z > 0 of the faces, and (P,) their horizontal areas."""
    planes, areas = [], []
    for f in faces:
        a, b, c = f.plane
        n = np.array([-a, -b, 1.0])
        norm = np.linalg.norm(n)
        planes.append(np.r_[n / norm, -c / norm])
        areas.append(abs(polygon_area(f.xy)))
    return np.array(planes).reshape(-1, 4), np.array(areas)


def _plane_z(plane: np.ndarray, x, y):
    return plane[0] * x + plane[1] * y + plane[2]


def _top_face(faces, polys, x: float, y: float) -> int:
    """Index of the face on top at (x, y), or -1 outside every face."""
    best, best_z = -1, -np.inf
    pt = shapely.Point(x, y)
    for i, (f, p) in enumerate(zip(faces, polys, strict=True)):
        if p.covers(pt):
            z = _plane_z(f.plane, x, y)
            if z > best_z + 1e-9:
                best, best_z = i, z
    return best


def _crossing_ticks(common, d: np.ndarray) -> list:
    """Short pieces of the line where two side-by-side faces' planes are equal
    (d . (x, y, 1) = 0), one where it crosses their common edge ``common``: the wall
    between the faces changes sides there, so the edge needs a vertex. The pieces
    node the edge and, dangling, leave the faces whole."""
    ticks = []
    n = np.hypot(d[0], d[1])
    along = np.array([-d[1], d[0]]) / n
    for line in shapely.get_parts(common):
        xy = shapely.get_coordinates(line)
        f = xy @ d[:2] + d[2]
        for i in range(len(xy) - 1):
            if f[i] * f[i + 1] < 0 and min(abs(f[i]), abs(f[i + 1])) > 1e-9:
                p = xy[i] + f[i] / (f[i] - f[i + 1]) * (xy[i + 1] - xy[i])
                ticks.append(LineString([p - _TICK * along, p + _TICK * along]))
    return ticks


def _face_polygon(xy: np.ndarray):
    """A face's outline as a valid (multi)polygon: a ring that folds back on itself (a
    spike of zero width where a support's side runs back along itself, 1 km² city) loses
    the fold; any overlay with an invalid ring raises GEOS's TopologyException."""
    poly = Polygon(xy)
    if poly.is_valid:
        return poly
    return shapely.union_all(
        [g for g in shapely.get_parts(shapely.make_valid(poly)) if g.geom_type == "Polygon"]
    )


def _arrangement(faces: list[RoofFace], polys: list, snap: bool = False):
    lines = [p.boundary for p in polys]
    corners = shapely.MultiPoint(np.concatenate([f.xy for f in faces]))
    for i in range(len(faces)):
        for j in range(i + 1, len(faces)):
            inter = polys[i].intersection(polys[j])
            d = faces[i].plane - faces[j].plane
            n = np.hypot(d[0], d[1])
            if n < 1e-9 or inter.is_empty:
                continue
            if inter.area < 1e-8:  # faces side by side: node their common edge where
                lines.extend(_crossing_ticks(inter, d))  # their planes cross
                continue
            # the line d0 x + d1 y + d2 = 0, long enough to cross the overlap
            cx, cy = inter.centroid.x, inter.centroid.y
            t = (d[0] * cx + d[1] * cy + d[2]) / n**2
            px, py = cx - d[0] * t, cy - d[1] * t
            L = 2.0 * np.sqrt(inter.envelope.area) + 1.0 + np.hypot(px - cx, py - cy)
            ux, uy = -d[1] / n, d[0] / n
            seg = LineString([(px - L * ux, py - L * uy), (px + L * ux, py + L * uy)])
            cut = seg.intersection(inter)
            # a crossing along the overlap's outline, closer than the probe's reach, is
            # that outline (two wings' planes rising from one eave at h_m meet on it, a
            # rounding off): as a line of its own it would leave a sliver cell the
            # snapping grid cannot resolve, and the mesh open along it
            if (not cut.is_empty and cut.length > 1e-6
                    and not inter.boundary.buffer(_EPS).covers(cut)):  # fmt: skip
                # an end within 3 grid steps of a face's corner is that corner (a
                # hip line from a shared corner): a node of its own, a grid step away
                # once snapped, would leave a wedge too thin to be a cell
                lines.append(shapely.snap(cut, corners, 3 * GRID))
    noded = shapely.set_precision(shapely.unary_union(lines), GRID)
    noded = shapely.unary_union(noded)  # re-node after snapping
    cells = shapely.get_parts(shapely.polygonize([noded]).geoms)
    if not snap:  # every cell, however small, is roof: dropped, it leaves a hole (a
        # ridge's end a millimetre off a wing's side closes a 0.3 mm^2 triangle)
        return [orient(c, 1.0) for c in cells if c.area > 0.0]
    cells = [c for c in cells if c.area > 1e-6]  # a second try: the slivers go to the snap
    if not cells:
        return []
    # a vertex a hair off its neighbour's straight edge (a face a few centimetres wide
    # along another's side) is a node of one cell only once snapped: the other cell's
    # triangles miss it and the mesh is open along the edge. Every cell takes the
    # vertices the others have on its boundary (as a second try only: snapped cell by
    # cell, a cell can take a vertex its neighbour does not, and a closed mesh opens)
    vertices = shapely.MultiPoint(np.concatenate([shapely.get_coordinates(c) for c in cells]))
    snapped = [shapely.snap(c, vertices, GRID) for c in cells]
    return [orient(n if isinstance(n, Polygon) and n.is_valid else c, 1.0)
            for c, n in zip(cells, snapped, strict=True)]  # fmt: skip


def building_mesh(faces: list[RoofFace], bottom_z: float, snap: bool = False) -> BuildingMesh:
    """Mesh the upper envelope of roof faces into a closed solid down to ``bottom_z``.

    Parameters
    ----------
    faces : list of RoofFace
        Planar roof faces of all wings, possibly overlapping.
    bottom_z : float
        Height of the bottom face (below the terrain), metres.
    snap : bool
        Every cell of the faces' arrangement takes the vertices the other cells have on
        its boundary (a second try where the mesh was open).

    Returns
    -------
    BuildingMesh
    """
    polys = [_face_polygon(f.xy) for f in faces]
    cells = _arrangement(faces, polys, snap)
    tops = []
    kept = []
    for c in cells:
        p = c.representative_point()
        k = _top_face(faces, polys, p.x, p.y)
        if k >= 0:
            kept.append(c)
            tops.append(k)
    tri_pts, tri_part, tri_axis = [], [], []
    node_z: dict[tuple, set] = defaultdict(set)

    def key(x, y):
        return (round(x / GRID), round(y / GRID))

    walls = []
    for cell, k in zip(kept, tops, strict=True):
        plane = faces[k].plane
        grad = np.array([plane[0], plane[1]])
        down = -grad / np.linalg.norm(grad) if np.linalg.norm(grad) > 1e-9 else np.array([1, 0])
        tris = shapely.get_parts(shapely.constrained_delaunay_triangles(cell))
        for t in tris:
            xy = np.asarray(t.exterior.coords)[:3]
            if _area2(xy) < 0:
                xy = xy[::-1]
            z = _plane_z(plane, xy[:, 0], xy[:, 1])
            tri_pts.append(np.column_stack([xy, z]))
            tri_part.append(0)
            tri_axis.append(down)
            bottom = np.column_stack([xy[::-1], np.full(3, bottom_z)])
            tri_pts.append(bottom)
            tri_part.append(2)
            tri_axis.append(np.array([1.0, 0.0]))
        for ring in [cell.exterior, *cell.interiors]:
            coords = np.asarray(ring.coords)
            for p0, p1 in zip(coords[:-1], coords[1:], strict=True):
                z0, z1 = _plane_z(plane, p0[0], p0[1]), _plane_z(plane, p1[0], p1[1])
                node_z[key(*p0)].add(round(z0 / GRID))
                d = p1 - p0
                length = np.hypot(*d)
                if length < 1e-9:
                    continue
                normal = np.array([d[1], -d[0]]) / length  # outward: interior is on the left
                mid = 0.5 * (p0 + p1) + _EPS * normal
                other = _top_face(faces, polys, mid[0], mid[1])
                if other < 0:
                    o0 = o1 = bottom_z
                else:
                    o0 = _plane_z(faces[other].plane, p0[0], p0[1])
                    o1 = _plane_z(faces[other].plane, p1[0], p1[1])
                walls.extend(_wall_pieces(p0, p1, z0, z1, o0, o1))
    for p0, p1, lo0, hi0, lo1, hi1 in walls:
        for p, lo, hi in ((p0, lo0, hi0), (p1, lo1, hi1)):
            node_z[key(*p)].update((round(lo / GRID), round(hi / GRID)))
    for p0, p1, lo0, hi0, lo1, hi1 in walls:
        left = _chain(node_z[key(*p0)], lo0, hi0)
        right = _chain(node_z[key(*p1)], lo1, hi1)
        d = (p1 - p0) / np.hypot(*(p1 - p0))
        for tri in _ladder(p0, left, p1, right):
            tri_pts.append(tri)
            tri_part.append(1)
            tri_axis.append(d)
    return _index(np.array(tri_pts), np.array(tri_part, np.uint8), np.array(tri_axis))


def _area2(xy: np.ndarray) -> float:
    return (xy[1, 0] - xy[0, 0]) * (xy[2, 1] - xy[0, 1]) - (xy[2, 0] - xy[0, 0]) * (
        xy[1, 1] - xy[0, 1]
    )


def _wall_pieces(p0, p1, z0, z1, o0, o1):
    """Wall parts along edge p0-p1 where this side (z) is above the other side (o)."""
    tol = 1e-6
    d0, d1 = z0 - o0, z1 - o1
    if d0 > tol and d1 < -tol or d0 < -tol and d1 > tol:
        # a crossing within the snapping grid of an end is that end, which the
        # arrangement has already noded (splitting there would leave a sliver unpaired)
        length = np.hypot(*(p1 - p0))
        s = d0 / (d0 - d1) * length
        if s <= 2 * GRID:
            d0 = 0.0
        elif length - s <= 2 * GRID:
            d1 = 0.0
    if d0 > tol and d1 > tol:
        return [(p0, p1, o0, z0, o1, z1)]
    if d0 > tol and d1 < -tol or d0 < -tol and d1 > tol:
        s = d0 / (d0 - d1)
        pm = p0 + s * (p1 - p0)
        zm = z0 + s * (z1 - z0)
        return [(p0, pm, o0, z0, zm, zm)] if d0 > 0 else [(pm, p1, zm, zm, o1, z1)]
    if d0 > tol:
        return [(p0, p1, o0, z0, z1, z1)]
    if d1 > tol:
        return [(p0, p1, z0, z0, o1, z1)]
    return []


def _chain(zs: set, lo: float, hi: float) -> np.ndarray:
    lo_k, hi_k = round(lo / GRID), round(hi / GRID)
    ks = sorted(k for k in zs if lo_k <= k <= hi_k)
    return np.array(ks, dtype=np.float64) * GRID


def _ladder(p0, left: np.ndarray, p1, right: np.ndarray):
    """Triangulate a vertical wall between two vertical chains of heights.

    The wall's outside is to the right of p0 -> p1 (seen from above); triangles are
    counter-clockwise seen from outside.
    """
    A = [np.array([p0[0], p0[1], z]) for z in left]
    B = [np.array([p1[0], p1[1], z]) for z in right]
    i = j = 0
    out = []
    while i < len(A) - 1 or j < len(B) - 1:
        adv_a = j >= len(B) - 1 or (i < len(A) - 1 and left[i + 1] <= right[j + 1])
        if adv_a:
            tri = (A[i], B[j], A[i + 1])
            i += 1
        else:
            tri = (A[i], B[j], B[j + 1])
            j += 1
        out.append(np.array(tri))
    return out


def _index(tri_pts: np.ndarray, part: np.ndarray, axis: np.ndarray) -> BuildingMesh:
    """Merge triangle corners into shared vertices: same snapped xy, z within 3 GRID.

    z is clustered rather than rounded, so that two planes meeting at a ridge whose
    height falls on a rounding boundary still give one vertex.
    """
    pts = tri_pts.reshape(-1, 3)
    kx = np.round(pts[:, 0] / GRID).astype(np.int64)
    ky = np.round(pts[:, 1] / GRID).astype(np.int64)
    order = np.lexsort((pts[:, 2], ky, kx))
    new = np.ones(len(order), dtype=bool)
    new[1:] = (
        (np.diff(kx[order]) != 0) | (np.diff(ky[order]) != 0) | (np.diff(pts[order, 2]) > 3 * GRID)
    )
    cluster = np.cumsum(new) - 1
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = cluster
    first = order[new]
    verts = np.column_stack([kx[first] * GRID, ky[first] * GRID, pts[first, 2]])
    tris = inverse.reshape(-1, 3)
    ok = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
    return BuildingMesh(verts, tris[ok], part[ok], axis[ok])


def building_solid(
    wing_faces_: list[list[RoofFace]], base_z: float, theta: float, origin: np.ndarray
) -> BuildingMesh:
    """One closed mesh of a building's wings (each a list of faces, world metres), down to
    ``base_z``: the upper envelope of every face.

    The envelope is meshed in the main prior's frame (``theta``, ``origin``), where the
    wings' sides are axis-aligned and their shared corners exactly equal, and turned back:
    rotated, they would be snapped to the mesher's grid apart. Where an edge is still
    left unpaired, the arrangement's cells are snapped to each other's vertices; where
    still, each wing keeps the part of its outline no higher wing covers (so that no
    faces overlap), unsnapped, then snapped."""
    local = [[_to_frame(f, theta, origin) for f in faces] for faces in wing_faces_]

    def attempts():  # made only when the ones before did not close
        every = [f for faces in local for f in faces]
        yield every, False
        yield every, True
        exclusive = _exclusive(local)
        yield exclusive, False
        yield exclusive, True

    for faces, snap in attempts():
        mesh = building_mesh(faces, base_z, snap)
        if not len(unpaired_edges(mesh.triangles)):
            break
    c, s = np.cos(theta), np.sin(theta)
    u, v = mesh.vertices[:, 0], mesh.vertices[:, 1]
    mesh.vertices = np.column_stack([origin[0] + c * u - s * v, origin[1] + s * u + c * v,
                                     mesh.vertices[:, 2]])  # fmt: skip
    return mesh


def _to_frame(face: RoofFace, theta: float, origin: np.ndarray) -> RoofFace:
    """A world face in the frame rotated by ``theta`` about ``origin``."""
    c, s = np.cos(theta), np.sin(theta)
    dx, dy = face.xy[:, 0] - origin[0], face.xy[:, 1] - origin[1]
    uv = np.column_stack([c * dx + s * dy, -s * dx + c * dy])
    a, b, k = face.plane  # z = a x + b y + k, x = ox + c u - s v, y = oy + s u + c v
    return RoofFace(np.round(uv, 9), np.array([a * c + b * s, -a * s + b * c,
                                               k + a * origin[0] + b * origin[1]]))  # fmt: skip


def _exclusive(wing_faces_: list[list[RoofFace]]) -> list[RoofFace]:
    """Each wing's faces less what higher wings cover (the highest roof point first: a
    tier keeps its roof, the podium under it loses that part; in the given order, a
    tier listed after its podium vanished from the mesh)."""
    taken, parts = None, []
    for faces in sorted(wing_faces_, key=lambda fs: -max((_top_z(f) for f in fs), default=-np.inf)):
        # the faces' rings made valid, as the arrangement's (a fold raised GEOS's
        # TopologyException here: dev seed 6's supports widened under a crown)
        polys = [_face_polygon(f.xy) for f in faces]
        outline = unary_union(polys)
        for f, poly in zip(faces, polys, strict=True):
            region = poly if taken is None else poly.difference(taken)
            for g in getattr(region, "geoms", [region]):
                if isinstance(g, Polygon) and g.area > _MIN_FACE_M2:
                    xy = np.asarray(orient(g, 1.0).exterior.coords)[:-1]
                    parts.append(RoofFace(xy, f.plane))
        taken = outline if taken is None else taken.union(outline)
    return parts


def _top_z(face: RoofFace) -> float:
    """The face's highest corner, metres."""
    return float(np.max(_plane_z(face.plane, face.xy[:, 0], face.xy[:, 1])))
