"""Ray casting with Open3D's RaycastingScene, on NumPy arrays, in a local origin.

Open3D casts in float32, which resolves about 0.5 m at a UTM northing of 5.7e6 m. A
:class:`RayScene` keeps its triangles relative to a local origin (the centre of their
bounding box, to the kilometre), and :func:`cast`, :func:`occluded` and
:func:`unsigned_distance` move the rays and points given in world coordinates (float64)
there before they are made float32: results on a scene far from its CRS's origin equal
those on the same scene near it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .raster import Grid

_CHUNK = 1 << 20


@dataclass
class RayScene:
    """An Open3D ray-casting scene and the local origin its triangles are relative to.

    Attributes
    ----------
    scene : open3d.t.geometry.RaycastingScene
    origin : (3,) float64
        World coordinates of the scene's zero, metres.
    """

    scene: o3d.t.geometry.RaycastingScene
    origin: np.ndarray

    def local(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) as float32 relative to the origin."""
        return (np.asarray(points, np.float64) - self.origin).astype(np.float32)


def local_origin(vertices: np.ndarray) -> np.ndarray:
    """(3,) the centre of the bounding box of ``vertices`` (V, 3), to the kilometre (the
    sample, built around its CRS's zero, keeps zero)."""
    vertices = np.asarray(vertices, np.float64)
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2 if len(vertices) else np.zeros(3)
    return np.round(centre / 1000.0) * 1000.0


def raycasting_scene(
    vertices: np.ndarray, triangles: np.ndarray, origin: np.ndarray | None = None
) -> RayScene:
    """An Open3D ray-casting scene of one triangle mesh, in a local origin.

    Parameters
    ----------
    vertices : (V, 3) float
        World coordinates.
    triangles : (T, 3) int
    origin : (3,) float, optional
        The local origin (default :func:`local_origin`); scenes of parts of one mesh given
        the same origin hold their triangles exactly as the whole mesh's scene does.

    Returns
    -------
    RayScene whose hits' primitive ids index ``triangles``.
    """
    vertices = np.asarray(vertices, np.float64)
    origin = local_origin(vertices) if origin is None else np.asarray(origin, np.float64)
    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor((vertices - origin).astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(np.asarray(triangles, dtype=np.int32))
    scene.add_triangles(mesh)
    return RayScene(scene, origin)


@dataclass
class Hits:
    """What rays hit.

    Attributes
    ----------
    t : (N,) float64
        Ray parameter of the hit in units of the direction's length (inf for a miss);
        with camera rays of unit camera-frame z, this is the z-depth.
    tri : (N,) int64
        Triangle index, -1 for a miss.
    points : (N, 3) float64
        Hit points (NaN for a miss).
    normals : (N, 3) float64
        Unit face normals turned to face the ray origin.
    bary : (N, 2) float64
        Barycentric coordinates (u, v) of the hit in its triangle: the hit is
        ``(1 - u - v) a + u b + v c`` for corners a, b, c.
    """

    t: np.ndarray
    tri: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    bary: np.ndarray


def cast(scene: RayScene, origins: np.ndarray, dirs: np.ndarray) -> Hits:
    """Cast rays from ``origins`` ((N, 3) or (3,), world) along ``dirs`` (N, 3), in chunks."""
    dirs = np.asarray(dirs, dtype=np.float64)
    n = len(dirs)
    origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), (n, 3))
    t = np.empty(n, np.float64)
    tri = np.empty(n, np.int64)
    nrm = np.empty((n, 3), np.float64)
    bary = np.empty((n, 2), np.float64)
    for s in range(0, n, _CHUNK):
        e = min(n, s + _CHUNK)
        rays = np.hstack([scene.local(origins[s:e]), dirs[s:e].astype(np.float32)])
        ans = scene.scene.cast_rays(o3d.core.Tensor(rays))
        t[s:e] = ans["t_hit"].numpy()
        ids = ans["primitive_ids"].numpy().astype(np.int64)
        ids[~np.isfinite(t[s:e])] = -1
        tri[s:e] = ids
        nrm[s:e] = ans["primitive_normals"].numpy()
        bary[s:e] = ans["primitive_uvs"].numpy()
    hit = np.isfinite(t)
    points = np.where(hit[:, None], origins + dirs * np.where(hit, t, 0)[:, None], np.nan)
    flip = np.sum(nrm * dirs, axis=1) > 0
    nrm[flip] *= -1
    return Hits(t, tri, points, nrm, bary)


def occluded(
    scene: RayScene,
    origins: np.ndarray,
    dirs: np.ndarray,
    tfar: float = np.inf,
) -> np.ndarray:
    """(N,) bool: each ray from ``origins`` along ``dirs`` hits something before ``tfar``
    (in units of the direction's length: 1 tests the segment to ``origins + dirs``).

    ``origins`` and ``dirs`` are (N, 3) or (3,) and broadcast against each other.
    """
    origins = np.atleast_2d(np.asarray(origins, dtype=np.float64))
    dirs = np.atleast_2d(np.asarray(dirs, dtype=np.float64))
    n = max(len(origins), len(dirs))
    origins = np.broadcast_to(origins, (n, 3))
    dirs = np.broadcast_to(dirs, (n, 3))
    out = np.empty(n, bool)
    for s in range(0, n, _CHUNK):
        e = min(n, s + _CHUNK)
        rays = np.hstack([scene.local(origins[s:e]), dirs[s:e].astype(np.float32)])
        out[s:e] = scene.scene.test_occlusions(o3d.core.Tensor(rays), tfar=tfar).numpy()
    return out


def vertical_hits(scene: RayScene, grid: Grid, z_top: float,
                  window: tuple[slice, slice] | None = None) -> Hits:  # fmt: skip
    """Cast rays straight down from height ``z_top`` through every cell centre of ``grid``,
    or of its cells ``window`` (rows, cols): a cell's ray is the same whichever window
    holds it (its centre from its index in ``grid``).

    Returns
    -------
    Hits of the cells' rays in row-major cell order: the top surface.
    """
    rows, cols = window or (slice(0, grid.height), slice(0, grid.width))
    x, _ = grid.cell_center(0, np.arange(cols.start, cols.stop))
    _, y = grid.cell_center(np.arange(rows.start, rows.stop), 0)
    X, Y = np.meshgrid(x, y)
    origins = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z_top)])
    return cast(scene, origins, np.tile([0.0, 0.0, -1.0], (X.size, 1)))


def unsigned_distance(scene: RayScene, points: np.ndarray) -> np.ndarray:
    """(N,) float64 distance from each of ``points`` (N, 3, world) to the nearest triangle."""
    points = scene.local(np.asarray(points).reshape(-1, 3))
    out = np.empty(len(points), np.float64)
    for s in range(0, len(points), _CHUNK):
        q = o3d.core.Tensor(points[s : s + _CHUNK])
        out[s : s + _CHUNK] = scene.scene.compute_distance(q).numpy()
    return out
