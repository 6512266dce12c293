"""Triangle meshes as arrays: reading any format Open3D reads, surface samples, closedness."""

from __future__ import annotations

import os

import numpy as np
import open3d as o3d
from shapely.geometry import Polygon

from .errors import InputError


def read_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh (PLY, OBJ, ... whatever Open3D reads), welding equal vertices.

    OBJ files split vertices along texture seams; welding makes the mesh's topology
    (closedness, orientation) that of its geometry.

    Returns
    -------
    vertices : (V, 3) float64
    triangles : (T, 3) int64
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(path, None, "no such mesh file")
    mesh = o3d.io.read_triangle_mesh(path, enable_post_processing=False, print_progress=False)
    if not mesh.has_vertices():
        raise InputError(path, "vertices", "no readable vertices (not a mesh Open3D can read)")
    mesh.remove_duplicated_vertices()
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)


def concatenate_meshes(
    meshes: list[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Many meshes as one.

    Parameters
    ----------
    meshes : list of (vertices (V_i, 3), triangles (T_i, 3))

    Returns
    -------
    vertices : (sum V_i, 3) float64
    triangles : (sum T_i, 3) int64, re-indexed
    owner : (sum T_i,) int64, the 1-based index of the mesh each triangle came from
    """
    if not meshes:
        return np.empty((0, 3)), np.empty((0, 3), np.int64), np.empty(0, np.int64)
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes])[:-1]
    vertices = np.concatenate([np.asarray(v, np.float64).reshape(-1, 3) for v, _ in meshes])
    triangles = np.concatenate(
        [
            np.asarray(t, np.int64).reshape(-1, 3) + o
            for (_, t), o in zip(meshes, offsets, strict=True)
        ]
    )
    owner = np.repeat(np.arange(1, len(meshes) + 1), [len(t) for _, t in meshes])
    return vertices, triangles, owner


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) area of each triangle, square metres."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def sample_surface(
    vertices: np.ndarray, triangles: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Points spread uniformly by area over a mesh.

    Returns
    -------
    points : (n, 3) float64
    tri : (n,) int64
        The triangle each point lies on.
    """
    area = triangle_areas(vertices, triangles)
    if n <= 0 or area.sum() <= 0:
        return np.empty((0, 3)), np.empty(0, np.int64)
    tri = rng.choice(len(triangles), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = (vertices[triangles[tri, i]] for i in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a), tri


def is_watertight(vertices: np.ndarray, triangles: np.ndarray) -> bool:
    """Closed 2-manifold without self-intersections, consistently oriented (Open3D)."""
    if not len(triangles):
        return False
    mesh = _o3d_mesh(vertices, triangles)
    return bool(
        mesh.is_edge_manifold(allow_boundary_edges=False)
        and mesh.is_vertex_manifold()
        and not self_intersecting(vertices, triangles, mesh)
        and _consistently_oriented(triangles)
        and _outward(vertices, triangles)
    )


def self_intersecting(
    vertices: np.ndarray,
    triangles: np.ndarray,
    mesh: o3d.geometry.TriangleMesh | None = None,
    coplanar_m: float = 0.0,
) -> bool:
    """Whether two triangles that share no vertex intersect (Open3D), with every pair Open3D
    reports checked again: a pair in one plane by its overlap in that plane, any other
    pair by the separating axes of two triangles.

    Open3D reports disjoint coplanar triangles as intersecting when their coordinates are
    large (isl-org/Open3D#6462: a proxy's floor in world metres), and also disjoint
    triangles of one polygon whose corners were rounded off its plane by millimetres (a
    CityJSON file's). A coplanar pair intersects only if it overlaps by an area. Its
    test of two triangles in different planes also answers yes for some that stand
    apart (isl-org/Open3D#5117; two roof triangles of an L's hips 9 mm apart): such a
    pair intersects only if no axis separates them.

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
    coplanar_m : float
        Two triangles whose corners lie this close to each other's plane, metres, are
        coplanar (besides those within a millionth of their size): the tolerance the
        vertices were rounded or checked planar to.
    """
    mesh = mesh if mesh is not None else _o3d_mesh(vertices, triangles)
    for a, b in np.asarray(mesh.get_self_intersecting_triangles()):
        ta, tb = vertices[triangles[a]], vertices[triangles[b]]
        if _coplanar(ta, tb, abs_tol=coplanar_m):
            if _overlap_area(ta, tb) > 0:
                return True
        elif not _separated(ta, tb):
            return True
    return False


def _separated(ta: np.ndarray, tb: np.ndarray) -> bool:
    """Whether an axis separates two triangles (3, 3) that are not in one plane: their
    normals and the nine cross products of their edges (the separating axis theorem for
    convex polyhedra; a touch, within a billionth of their size, is no separation)."""
    ea, eb = np.roll(ta, -1, axis=0) - ta, np.roll(tb, -1, axis=0) - tb
    axes = np.vstack([np.cross(ea[0], ea[1]), np.cross(eb[0], eb[1]),
                      np.cross(ea[:, None, :], eb[None, :, :]).reshape(9, 3)])  # fmt: skip
    norms = np.linalg.norm(axes, axis=1)
    axes = axes[norms > 1e-12 * max(float(norms.max()), 1e-300)]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    centre = ta.mean(axis=0)
    pa, pb = (ta - centre) @ axes.T, (tb - centre) @ axes.T  # (3, n_axes)
    gap = 1e-9 * float(np.ptp(np.vstack([ta, tb]), axis=0).max())
    return bool(np.any((pa.max(axis=0) < pb.min(axis=0) - gap)
                       | (pb.max(axis=0) < pa.min(axis=0) - gap)))  # fmt: skip


def _o3d_mesh(vertices: np.ndarray, triangles: np.ndarray) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(triangles).astype(np.int32)),
    )


def _coplanar(ta: np.ndarray, tb: np.ndarray, rel_tol: float = 1e-6, abs_tol: float = 0.0) -> bool:
    """Whether ``tb``'s corners lie in ``ta``'s plane, within ``rel_tol`` of their size or
    ``abs_tol`` metres."""
    n = np.cross(ta[1] - ta[0], ta[2] - ta[0])
    norm = float(np.linalg.norm(n))
    if norm == 0.0:
        return False
    size = float(np.ptp(np.vstack([ta, tb]), axis=0).max())
    return bool(np.all(np.abs((tb - ta[0]) @ (n / norm)) <= max(rel_tol * size, abs_tol)))


def _overlap_area(ta: np.ndarray, tb: np.ndarray) -> float:
    """Area of the overlap of two coplanar triangles, in the plane of their largest
    projection (relative to their size: 0 when they only touch)."""
    drop = int(np.argmax(np.abs(np.cross(ta[1] - ta[0], ta[2] - ta[0]))))
    keep = [i for i in range(3) if i != drop]
    origin = ta[0, keep]
    pa, pb = Polygon(ta[:, keep] - origin), Polygon(tb[:, keep] - origin)
    area = pa.intersection(pb).area
    return area if area > 1e-9 * max(pa.area, pb.area) else 0.0


def unpaired_edges(triangles: np.ndarray) -> np.ndarray:
    """Directed edges that break a closed, consistently oriented mesh: walked by more
    than one triangle, or with no triangle walking them back.

    Parameters
    ----------
    triangles : (T, 3) int

    Returns
    -------
    (K, 2) int vertex pairs (empty for a closed, oriented 2-manifold's edges).
    """
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    if not len(e):
        return e.reshape(0, 2)
    n = int(e.max()) + 1
    key = e[:, 0] * n + e[:, 1]
    rev = e[:, 1] * n + e[:, 0]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    bad = (counts[inverse.ravel()] > 1) | ~np.isin(rev, key)
    return e[bad]


def _consistently_oriented(triangles: np.ndarray) -> bool:
    # neighbours walk their shared edge in opposite directions
    return len(unpaired_edges(triangles)) == 0


def _outward(vertices: np.ndarray, triangles: np.ndarray) -> bool:
    # a closed mesh whose faces turn outwards encloses a positive signed volume
    a, b, c = (vertices[triangles[:, i]] - vertices.mean(axis=0) for i in range(3))
    return float(np.sum(a * np.cross(b, c))) > 0


def raster_mesh(
    z: np.ndarray, grid, step: int = 1, fill: float | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """A triangle mesh (facing up) of a height raster on ``grid`` through every ``step``-th
    cell centre; NaN heights take ``fill`` (default: the samples' median). None when fewer
    than 2 x 2 samples are known.

    Returns
    -------
    vertices : (V, 3) float64 world metres
    triangles : (T, 3) int64
    """
    zs = z[::step, ::step]
    if not np.isfinite(zs).any() or min(zs.shape) < 2:
        return None
    zs = np.where(np.isfinite(zs), zs, np.nanmedian(zs) if fill is None else fill)
    X, Y = grid.cell_centers()
    vertices = np.column_stack([X[::step, ::step].ravel(), Y[::step, ::step].ravel(), zs.ravel()])
    h, w = zs.shape
    i = np.arange(h * w).reshape(h, w)[:-1, :-1].ravel()
    triangles = np.concatenate(
        [np.column_stack([i, i + w, i + w + 1]), np.column_stack([i, i + w + 1, i + 1])]
    )
    return vertices, triangles
