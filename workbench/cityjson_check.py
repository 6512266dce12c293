"""Checks of a CityJSON document's geometry that a reader does not make: the semantics
match the boundaries, and every solid is a valid solid.

A solid's shell must be (as val3dity tests it, with its default tolerances):

- **planar**: every polygon's vertices within ``PLANARITY_M`` of its plane (Newell's
  normal through the centroid);
- **closed**: every edge of its polygons used exactly twice, in opposite directions
  (which also makes it consistently oriented);
- **outward**: its signed volume positive;
- **not self-intersecting**: its polygons triangulated (constrained Delaunay, no new
  vertex) and tested pairwise by Open3D, as :func:`workbench.meshes.self_intersecting`
  (triangles within ``PLANARITY_M`` of one plane intersect only if they overlap by an
  area).
"""

from __future__ import annotations

import re
from collections import Counter

import numpy as np
import shapely
from shapely.geometry import Polygon

from .mesh_faces import newell_normal
from .meshes import self_intersecting

PLANARITY_M = 0.01
LOD = re.compile(r"^[0-3](\.[0-3])?$")
BUILDING_SURFACES = {
    "RoofSurface", "GroundSurface", "WallSurface", "ClosureSurface", "OuterCeilingSurface",
    "OuterFloorSurface", "Window", "Door",
}  # fmt: skip
DEPTH = {"MultiSurface": 3, "CompositeSurface": 3, "Solid": 4, "MultiSolid": 5,
         "CompositeSolid": 5}  # fmt: skip
REFERENCE_SYSTEM = re.compile(r"^https?://www\.opengis\.net/def/crs/\w+/[\w.]+/\w+$")


def check_city_model(doc: dict) -> list[str]:
    """Problems of ``doc`` (a CityJSON dict), one line each naming the object; [] if none.

    Structure (a strict reader such as cjio or cityjson-lib checks the rest): version 2.0,
    transform, referenceSystem as an OGC URL, each geometry's type, LoD and nesting,
    vertex indices, semantic values aligned with the surfaces; then every solid shell as
    the module says.
    """
    problems = []
    if doc.get("type") != "CityJSON" or doc.get("version") != "2.0":
        problems.append("not a CityJSON 2.0 document")
    transform = doc.get("transform", {})
    if len(transform.get("scale", [])) != 3 or len(transform.get("translate", [])) != 3:
        problems.append("transform: scale and translate need 3 numbers each")
        return problems
    ref = doc.get("metadata", {}).get("referenceSystem")
    if ref is not None and not REFERENCE_SYSTEM.match(ref):
        problems.append(f"metadata.referenceSystem: {ref!r} is not an OGC CRS URL")
    verts = np.asarray(doc.get("vertices", []), np.float64).reshape(-1, 3)
    world = verts * transform["scale"] + transform["translate"]
    for key, obj in doc.get("CityObjects", {}).items():
        for k, g in enumerate(obj.get("geometry", [])):
            where = f"{key}: geometry {k} ({g.get('type')}, LoD {g.get('lod')})"
            problems.extend(f"{where}: {p}" for p in check_geometry(g, world))
    return problems


def check_geometry(g: dict, vertices: np.ndarray) -> list[str]:
    """Problems of one geometry object whose indices refer to ``vertices`` (V, 3), metres."""
    kind = g.get("type")
    if kind not in DEPTH:
        return [f"unknown geometry type {kind!r}"]
    if not LOD.match(str(g.get("lod", ""))):
        return [f"LoD {g.get('lod')!r} is not of the form 2 or 2.2"]
    boundaries = g.get("boundaries", [])
    if _depth(boundaries) != DEPTH[kind]:
        return [f"boundaries nested {_depth(boundaries)} deep, {kind} needs {DEPTH[kind]}"]
    flat = np.asarray(_leaves(boundaries), np.int64)
    if len(flat) and (flat.min() < 0 or flat.max() >= len(vertices)):
        return ["a vertex index outside the vertex list"]
    problems = _check_semantics(g, kind)
    solids = {"Solid": [boundaries], "MultiSolid": boundaries, "CompositeSolid": boundaries}
    for s, solid in enumerate(solids.get(kind, [])):
        for h, shell in enumerate(solid):
            problems.extend(f"solid {s} shell {h}: {p}" for p in check_shell(shell, vertices))
    return problems


def check_shell(shell: list, vertices: np.ndarray) -> list[str]:
    """Problems of one solid shell: surfaces of rings of vertex indices into ``vertices``."""
    problems = []
    for f, surface in enumerate(shell):
        n = newell_normal(vertices[surface[0]])
        if not n.any():
            problems.append(f"surface {f} has no area (its corners are collinear)")
            continue
        off = _planarity(surface, vertices, n)
        if off > PLANARITY_M:
            problems.append(f"surface {f} not planar ({off * 100:.1f} cm off its plane)")
    edges = Counter()
    for surface in shell:
        for ring in surface:
            edges.update(zip(ring, ring[1:] + ring[:1], strict=True))
    unpaired = [e for e, n in edges.items() if n != 1 or edges.get(e[::-1]) != 1]
    if unpaired:
        problems.append(f"not closed: {len(unpaired)} edges not used once each way")
        return problems
    triangles = np.concatenate([_triangulate(s, vertices) for s in shell])
    local = vertices - vertices[triangles[0, 0]]
    a, b, c = (local[triangles[:, i]] for i in range(3))
    if np.einsum("ij,ij->i", a, np.cross(b, c)).sum() <= 0:
        problems.append("oriented inwards (volume not positive)")
    # its polygons are planar within PLANARITY_M: so are two triangles of one
    if self_intersecting(local, triangles, coplanar_m=PLANARITY_M):
        problems.append("self-intersecting")
    return problems


def lod_meshes(doc: dict, skip: tuple[str, ...] = ()) -> dict:
    """Every level of detail of a CityJSON document as one triangle mesh: {lod: (vertices
    (V, 3) float64 world metres, triangles (T, 3) int64)}, its polygons triangulated
    (constrained Delaunay on their own vertices); surfaces whose semantic type is in
    ``skip`` (such as "GroundSurface") left out."""
    t = doc["transform"]
    vertices = np.asarray(doc["vertices"], np.float64).reshape(-1, 3) * t["scale"] + t["translate"]
    out: dict[str, list] = {}
    for obj in doc.get("CityObjects", {}).values():
        for g in obj.get("geometry", []):
            depth = DEPTH.get(g.get("type"))
            if depth is None:
                continue
            surfaces = _surfaces(g["boundaries"], depth - 2)
            sem = g.get("semantics")
            if sem and skip:
                kinds = [sem["surfaces"][v]["type"] if v is not None else None
                         for v in _leaves(sem["values"])]  # fmt: skip
                surfaces = [sf for sf, k in zip(surfaces, kinds, strict=True) if k not in skip]
            tris = [_triangulate(sf, vertices) for sf in surfaces]
            out.setdefault(str(g["lod"]), []).extend(tr for tr in tris if len(tr))
    return {lod: (vertices, np.concatenate(tris)) for lod, tris in out.items() if tris}


def _surfaces(boundaries: list, depth: int) -> list:
    """The surfaces (lists of rings) ``depth`` levels down a boundaries array."""
    if depth == 1:
        return list(boundaries)
    return [s for item in boundaries for s in _surfaces(item, depth - 1)]


def _check_semantics(g: dict, kind: str) -> list[str]:
    sem = g.get("semantics")
    if sem is None:
        return []
    surfaces = sem.get("surfaces", [])
    bad = sorted({s.get("type") for s in surfaces} - BUILDING_SURFACES)
    if bad:
        return [f"semantic surface types {bad} are not a building's"]
    values = sem.get("values")
    depth = DEPTH[kind] - 2  # one value per surface
    if _depth(values) != depth or len(_leaves(values)) != _count(g["boundaries"], depth):
        return ["semantics.values do not match the surfaces one for one"]
    if any(v is not None and not 0 <= v < len(surfaces) for v in _leaves(values)):
        return ["semantics.values index outside semantics.surfaces"]
    return []


def _depth(x) -> int:
    d = 0
    while isinstance(x, list):
        d += 1
        x = x[0] if x else None
    return d


def _leaves(x) -> list:
    if not isinstance(x, list):
        return [x]
    return [v for item in x for v in _leaves(item)]


def _count(x, depth: int) -> int:
    """Number of lists ``depth`` levels down (surfaces of a boundaries array)."""
    return len(x) if depth == 1 else sum(_count(item, depth - 1) for item in x)


def _planarity(surface: list, vertices: np.ndarray, n: np.ndarray) -> float:
    """The farthest of a surface's vertices from its mean point along its unit normal
    ``n``, metres."""
    P = vertices[np.concatenate(surface)]
    return float(np.abs((P - P.mean(axis=0)) @ n).max())


def _triangulate(surface: list, vertices: np.ndarray) -> np.ndarray:
    """(t, 3) vertex indices of a planar polygon with holes, on its own vertices; none for
    a polygon of no area (collinear corners), which GEOS cannot triangulate."""
    n = newell_normal(vertices[surface[0]])
    if not n.any():
        return np.zeros((0, 3), np.int64)
    drop = int(np.argmax(np.abs(n)))
    keep = [i for i in range(3) if i != drop]
    rings = [vertices[r][:, keep] for r in surface]
    index = {tuple(p): v for r, xy in zip(surface, rings, strict=True)
             for v, p in zip(r, xy.tolist(), strict=True)}  # fmt: skip
    tris = shapely.constrained_delaunay_triangles(Polygon(rings[0], rings[1:]))
    out = [[index[tuple(p)] for p in np.asarray(t.exterior.coords)[:3].tolist()]
           for t in tris.geoms]  # fmt: skip
    out = np.asarray(out, np.int64).reshape(-1, 3)
    # keep the surface's orientation: its triangles turn as its outline does
    if len(out):
        a, b, c = (vertices[out[:, i]] for i in range(3))
        flip = np.einsum("ij,j->i", np.cross(b - a, c - a), n) < 0
        out[flip] = out[flip][:, ::-1]
    return out
