"""Meshes (step 4): each wing's roof planes clipped to its rectangle, the wings of a
building joined by the upper envelope of their roofs, walls down to the ground.

A wing's roof is the minimum of affine functions of (u, v) (eq. 5's planes with vertical
ends dropped, and a cap), so the region where each plane is the lowest is the wing's
rectangle clipped by half-planes: a convex polygon. The wings of a building overlap
(an L's corner) and stand on one another (a tier); the envelope mesher
(:func:`modeling.shared.roof_envelope.building_mesh`) nodes their faces into one closed,
outward-oriented solid.
"""

from __future__ import annotations

import numpy as np
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

from modeling.shared.roof_envelope import BuildingMesh, RoofFace, building_mesh
from workbench.meshes import unpaired_edges

from .roof_geometry import RoofFit

_MIN_FACE_M2 = 1e-4


def wing_planes(wing: np.ndarray, fit: RoofFit) -> list[np.ndarray]:
    """The wing's roof as affine functions z = a u + b v + c of its frame: (3,) each."""
    u0, u1, v0, v1 = wing
    t = fit.snapped()
    z = fit.z_main
    du, dv = fit.offset
    sides = (np.array([1.0, 0.0, du - u0]), np.array([0.0, 1.0, dv - v0]),
             np.array([-1.0, 0.0, u1 - du]), np.array([0.0, -1.0, v1 - dv]))  # fmt: skip
    planes = [tk * side + np.array([0.0, 0.0, z])
              for tk, side in zip(t, sides, strict=True) if np.isfinite(tk)]  # fmt: skip
    if fit.cap is not None or not planes:
        planes.append(np.array([0.0, 0.0, z + (fit.cap or 0.0)]))
    return planes


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


def _area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def wing_faces(wing: np.ndarray, fit: RoofFit, theta: float, origin: np.ndarray) -> list[RoofFace]:
    """The wing's roof faces in world coordinates: for each plane, the part of the
    rectangle where it is the lowest."""
    u0, u1, v0, v1 = wing
    rect = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], dtype=np.float64)
    planes = wing_planes(wing, fit)
    c, s = np.cos(theta), np.sin(theta)
    out = []
    for k, p in enumerate(planes):
        region = rect
        for j, q in enumerate(planes):
            if j != k:
                region = clip_convex(region, *(p - q))  # p <= q
        if _area(region) < _MIN_FACE_M2:
            continue
        xy = np.column_stack([origin[0] + c * region[:, 0] - s * region[:, 1],
                              origin[1] + s * region[:, 0] + c * region[:, 1]])  # fmt: skip
        # z = a u + b v + c with u = c(x - ox) + s(y - oy), v = -s(x - ox) + c(y - oy)
        ax, ay = p[0] * c - p[1] * s, p[0] * s + p[1] * c
        out.append(RoofFace(xy, np.array([ax, ay, p[2] - ax * origin[0] - ay * origin[1]])))
    return out


def building_solid(
    wing_faces_: list[list[RoofFace]], base_z: float, theta: float, origin: np.ndarray
) -> BuildingMesh:
    """One closed mesh of a building's wings (each a list of faces, world metres), down to
    ``base_z``: the upper envelope of every face.

    The envelope is meshed in the main prior's frame (``theta``, ``origin``), where the
    wings' sides are axis-aligned and their shared corners exactly equal, and turned back:
    rotated, they would be snapped to the mesher's grid apart. Where an edge is still
    left unpaired, each wing keeps the part of its outline no earlier wing covers, so
    that no faces overlap."""
    local = [[_to_frame(f, theta, origin) for f in faces] for faces in wing_faces_]
    mesh = building_mesh([f for faces in local for f in faces], base_z)
    if len(unpaired_edges(mesh.triangles)):
        mesh = building_mesh(_exclusive(local), base_z)
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
    """Each wing's faces less what earlier wings cover."""
    taken, parts = None, []
    for faces in wing_faces_:
        outline = unary_union([Polygon(f.xy) for f in faces])
        for f in faces:
            region = Polygon(f.xy) if taken is None else Polygon(f.xy).difference(taken)
            for g in getattr(region, "geoms", [region]):
                if isinstance(g, Polygon) and g.area > _MIN_FACE_M2:
                    xy = np.asarray(orient(g, 1.0).exterior.coords)[:-1]
                    parts.append(RoofFace(xy, f.plane))
        taken = outline if taken is None else taken.union(outline)
    return parts


def face_planes(faces: list[RoofFace]) -> tuple[np.ndarray, np.ndarray]:
    """(P, 4) planes (n, d) with n_z > 0 of the faces, and (P,) their horizontal areas."""
    planes, areas = [], []
    for f in faces:
        a, b, c = f.plane
        n = np.array([-a, -b, 1.0])
        norm = np.linalg.norm(n)
        planes.append(np.r_[n / norm, -c / norm])
        areas.append(abs(_area(f.xy)))
    return np.array(planes).reshape(-1, 4), np.array(areas)
