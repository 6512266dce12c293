"""A surface mesh (an MVS tool's, or `workbench mesh`'s) sampled into the ortho products:
the LOD paper's orthogonal grid sampling (section 4).

One vertical ray is cast from above through every cell centre; the first surface it hits
gives the cell its colour (the vertex colours or the texture at the hit), its height and
its normal: ``ortho.tif``, ``dsm.tif`` and ``normal.tif``. The DTM follows from the DSM
by the progressive morphological filter, and the classes from the forest for label-free
rasters, as for a cloud without classes; every modeling path then runs on the result.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from workbench.engine import Engine, ThreadEngine, full_disk_named
from workbench.errors import InputError
from workbench.grid_blocks import block_layout
from workbench.progress import progress
from workbench.raster import Grid, WindowedRaster, class_codes, parse_crs
from workbench.raycast import cast, local_origin, raycasting_scene
from workbench.records import StageTimer

from .ground import LARGEST_WINDOW_M, dtm_from_dsm
from .interpolate import fill_small_holes, small_holes
from .mesh_source import PlySurface, open_ply_surface
from .options import FusionOptions
from .planar_objects import COUNTS as PLANAR_COUNTS
from .planar_objects import planar_roofs_classed_tree
from .raster_forest import classify_rasters, synthetic_raster_forest
from .scene_fusion import FILLED, HOLE_CELLS, FusionResult, check_memory, workers_in_memory

log = logging.getLogger(__name__)

NON_MANIFOLD_SHARE = 0.001  # more non-manifold edges than this: not a surface
TRIANGLES_PER_CHUNK = 1 << 20  # triangles read at once (flat memory on a city's mesh)
BUCKET_BUFFER_BYTES = 64 << 20  # the tiles' lists of triangles past this go to disk
SAMPLING_TILE_CELLS = 256  # cells a side of a tile cast against its own scene
CRS_COMMENT = "crs "  # a PLY header line "comment crs <EPSG:... or WKT>"


@dataclass
class SurfaceMesh:
    """A triangle mesh to sample.

    Attributes
    ----------
    path : Path
    vertices : (V, 3) float64, world
    triangles : (T, 3) int64
    colors : (V, 3) uint8 or None
    uvs : (T, 3, 2) float or None
        Texture coordinates of each triangle's corners (u right, v up).
    textures : list of (h, w, 3) uint8
    material : (T,) int or None
        Which texture each triangle takes.
    crs : rasterio CRS or None
    """

    path: Path
    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray | None
    uvs: np.ndarray | None
    textures: list
    material: np.ndarray | None
    crs: object

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def has_colours(self) -> bool:
        return self.colors is not None

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @property
    def lo(self) -> np.ndarray:
        """(3,) the vertices' least x, y and z."""
        return self.vertices.min(axis=0)

    @property
    def hi(self) -> np.ndarray:
        """(3,) the vertices' greatest x, y and z."""
        return self.vertices.max(axis=0)

    def positions(self, sel) -> np.ndarray:
        """(N, 3) float64 positions of the vertices ``sel`` (as :class:`PlySurface`)."""
        return np.asarray(self.vertices[sel], np.float64)

    def faces(self, sel) -> np.ndarray:
        """(N, 3) int64 vertex indices of the triangles ``sel``."""
        return np.asarray(self.triangles[sel], np.int64)

    def vertex_data(self, sel) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 3) float64 positions and (N, 3) uint8 colours (None without colours) of
        the vertices ``sel``."""
        return self.positions(sel), None if self.colors is None else self.colors[sel]


def open_surface_mesh(path, crs: str | None = None) -> SurfaceMesh | PlySurface:
    """A surface mesh to sample: a binary PLY of triangles read a part at a time
    (:class:`~fusion.mesh_source.PlySurface`), anything else read whole
    (:func:`read_surface_mesh`); its vertices checked, its CRS found and checked.

    Raises
    ------
    InputError
        As :func:`read_surface_mesh`; faces are checked as they are sampled.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "no such mesh file")
    mesh = open_ply_surface(path)
    if mesh is None:
        return read_surface_mesh(path, crs)
    if not mesh.n_triangles:
        raise InputError(path, "faces", "no triangles: a surface mesh is needed")
    mesh.check_vertices()
    mesh.crs = _checked_crs(path, crs, mesh.lo, mesh.hi)
    return mesh


def read_surface_mesh(path, crs: str | None = None) -> SurfaceMesh:
    """Read a surface mesh (PLY, OBJ with its MTL and textures, anything Open3D reads) and
    check that it is one.

    Parameters
    ----------
    path : path
    crs : str, optional
        Its CRS (EPSG code or WKT); default: a ``comment crs`` line of a PLY header, as
        ``workbench mesh`` writes.

    Raises
    ------
    InputError
        No such file; no triangles; vertices that are not finite; more than 0.1 % of the
        edges shared by more than two triangles; coordinates outside the CRS's area of
        use. A mesh without a CRS is read, with a warning.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "no such mesh file")
    mesh = o3d.io.read_triangle_mesh(os.fspath(path), enable_post_processing=True,
                                     print_progress=False)  # fmt: skip
    # copies, so that Open3D's own arrays (a city mesh's: gigabytes) go with ``mesh``
    V = np.array(mesh.vertices, np.float64)
    T = np.array(mesh.triangles, np.int64)
    colors = None
    if mesh.has_vertex_colors():
        colors = np.empty((len(V), 3), np.uint8)
        for s in range(0, len(V), TRIANGLES_PER_CHUNK):  # no float temporaries of all
            c = np.asarray(mesh.vertex_colors)[s : s + TRIANGLES_PER_CHUNK]
            colors[s : s + len(c)] = np.clip(c * 255 + 0.5, 0, 255)
    uvs, textures, material = None, [], None
    if mesh.has_triangle_uvs() and mesh.has_textures():
        uvs = np.array(mesh.triangle_uvs, np.float64).reshape(-1, 3, 2)
        textures = [np.array(t)[..., :3] for t in mesh.textures]
        material = np.zeros(len(T), np.int64)
        if mesh.has_triangle_material_ids():
            material = np.array(mesh.triangle_material_ids, np.int64)
    del mesh
    if not len(T):
        raise InputError(path, "faces", "no triangles: a surface mesh is needed")
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        raise InputError(path, "vertices", f"{int(bad.sum())} vertices are not finite (NaN)")
    crs_obj = _checked_crs(path, crs, V.min(axis=0), V.max(axis=0))
    return SurfaceMesh(path, V, T, colors, uvs, textures, material, crs_obj)


def _checked_crs(path: Path, crs: str | None, lo: np.ndarray, hi: np.ndarray):
    """The mesh's CRS (given, else its PLY header's), checked against its box."""
    text = crs or ply_crs(path)
    crs_obj = parse_crs(text, path=path) if text else None
    if crs_obj is None:
        log.warning("%s: no CRS (give --crs): the rasters are written without one", path)
    else:
        check_in_area_of_use(path, lo, hi, crs_obj)
    return crs_obj


def ply_crs(path: Path) -> str | None:
    """The CRS a PLY header names in a ``comment crs ...`` line, if any."""
    if path.suffix.lower() != ".ply":
        return None
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").strip()
            if line == "end_header":
                return None
            if line.startswith("comment " + CRS_COMMENT):
                return line[len("comment " + CRS_COMMENT) :].strip()
    return None


def check_in_area_of_use(path: Path, lo: np.ndarray, hi: np.ndarray, crs) -> None:
    """Refuse a mesh whose bounding box (``lo``, ``hi``: its least and greatest x and y)
    lies wholly outside its CRS's area of use (a mesh in a local frame, or given the
    wrong CRS)."""
    from pyproj import CRS as ProjCRS
    from pyproj import Transformer

    epsg = crs.to_epsg()
    proj = ProjCRS.from_epsg(epsg) if epsg else ProjCRS.from_user_input(crs.to_wkt())
    area = proj.area_of_use
    if area is None or not proj.is_projected:
        return
    to_crs = Transformer.from_crs("EPSG:4326", proj, always_xy=True)
    x0, y0, x1, y1 = to_crs.transform_bounds(area.west, area.south, area.east, area.north)
    if hi[0] < x0 or lo[0] > x1 or hi[1] < y0 or lo[1] > y1:
        raise InputError(path, "vertices", f"x {lo[0]:.0f}..{hi[0]:.0f}, y {lo[1]:.0f}.."
                         f"{hi[1]:.0f} lie outside {crs.to_string()}'s area of use "
                         f"({x0:.0f}..{x1:.0f}, {y0:.0f}..{y1:.0f}): a local frame, or "
                         "another CRS?")  # fmt: skip


def default_gsd(mesh: SurfaceMesh | PlySurface) -> float:
    """The median edge length of the mesh's triangles (a sample of some 200,000, read a
    chunk at a time), to two significant digits: a cell per vertex, about."""
    step = max(1, mesh.n_triangles // 200_000)
    chunk = TRIANGLES_PER_CHUNK // step * step or step
    sample = np.concatenate([mesh.faces(slice(s, s + chunk, step))
                             for s in range(0, mesh.n_triangles, chunk)])  # fmt: skip
    used, inverse = np.unique(sample[:, :2], return_inverse=True)
    ends = mesh.positions(used)[inverse.reshape(-1, 2)]
    edges = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    gsd = float(np.median(edges[edges > 0])) if (edges > 0).any() else 1.0
    return float(f"{gsd:.2g}")


def orthogonal_sampling(
    mesh: SurfaceMesh | PlySurface, grid: Grid, tile: int = SAMPLING_TILE_CELLS,
    scratch: str | os.PathLike | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Cast a vertical ray down through every cell centre; keep the first hit
    (:func:`sampled_tiles` put together).

    Returns
    -------
    ortho : (H, W, 3) uint8
        The hit's colour (texture, else vertex colours interpolated, else grey); 0 where
        no hit.
    dsm : (H, W) float32
        The hit's height, metres, NaN where the ray missed.
    normal : (3, H, W) float32
        The unit normal at the hit (vertex normals interpolated), turned up (n_z >= 0),
        NaN where missed.
    """
    ortho = np.zeros((*grid.shape, 3), np.uint8)
    dsm = np.full(grid.shape, np.nan, np.float32)
    normal = np.full((3, *grid.shape), np.nan, np.float32)
    for rows, cols, o, d, n in sampled_tiles(mesh, grid, tile, scratch):
        ortho[rows, cols], dsm[rows, cols], normal[:, rows, cols] = o, d, n
    return ortho, dsm, normal


def sampled_tiles(
    mesh: SurfaceMesh | PlySurface, grid: Grid, tile: int = SAMPLING_TILE_CELLS,
    scratch: str | os.PathLike | None = None,
):  # fmt: skip
    """Cast a vertical ray down through every cell centre, a tile at a time; keep the
    first hit.

    The grid is cast in tiles of ``tile`` cells a side, each against a ray-casting scene
    of the triangles over it alone: the scene of a city's whole mesh (38 M triangles)
    took some 10 GB. A first pass puts every triangle in the tiles its box reaches
    (:func:`tile_buckets`), so that a tile reads only its own triangles, and a mesh read
    a part at a time (:class:`PlySurface`) is never whole in memory. A vertical ray can
    only hit a triangle whose bounding box holds it, and every scene shares one local
    origin, so the hits are the whole mesh's (a ray right on an edge may take the other
    of its two triangles: the same point, to rounding).

    A hit's normal is interpolated from the vertex normals, each the sum of its
    triangles' (:func:`vertex_normals`): a tile's triangles reach as far past it as the
    longest triangle, so that every triangle of a vertex it hits is among them; the
    vertices of triangles longer than a quarter of a tile take the sums of a pass over
    the whole mesh. The sums run over the triangles in the file's order whatever the
    tiles, so the normals do not depend on them. Each tile also counts its edges (those
    whose midpoint it holds) shared by more than two triangles: a mesh with more than
    :data:`NON_MANIFOLD_SHARE` of such edges over the grid is not a surface.

    Parameters
    ----------
    mesh : SurfaceMesh or PlySurface
    grid : Grid
    tile : int
        Cells a side of a tile.
    scratch : path, optional
        Folder for the tiles' lists of triangles when they outgrow memory (default: the
        system's temporary folder).

    Yields
    ------
    rows, cols : slices of the tile in the grid
    ortho : (h, w, 3) uint8, dsm : (h, w) float32, normal : (3, h, w) float32
        As :func:`orthogonal_sampling`'s, on the tile.

    Raises
    ------
    InputError
        A face's vertex index out of range; too many non-manifold edges (after the last
        tile).
    """
    origin = local_origin(np.stack([mesh.lo, mesh.hi]))
    tiles = grid.tiles(tile)
    top = float(mesh.hi[2]) + 10.0
    bad_edges = edges = 0
    with tile_buckets(mesh, grid, tile, origin, scratch) as buckets:
        for k, (rows, cols) in enumerate(progress(tiles, "fusion: sampling the mesh's tiles")):
            part = grid.window(rows, cols)
            ortho = np.zeros((*part.shape, 3), np.uint8)
            dsm = np.full(part.shape, np.nan, np.float32)
            normal = np.full((3, *part.shape), np.nan, np.float32)
            idx = buckets.take(k)
            if len(idx):
                T = mesh.faces(idx)
                used, corners = np.unique(T, return_inverse=True)
                corners = corners.reshape(-1, 3)
                P, colours = mesh.vertex_data(used)
                b, e = non_manifold_edges(T, P[corners], part.bounds)
                bad_edges, edges = bad_edges + b, edges + e
                lo, hi = _boxes(P[corners] - origin)
                x0, y0, x1, y1 = np.subtract(part.bounds, np.tile(origin[:2], 2))
                reach = np.flatnonzero((hi[:, 0] >= x0) & (lo[:, 0] <= x1)
                                       & (hi[:, 1] >= y0) & (lo[:, 1] <= y1))  # fmt: skip
            if len(idx) and len(reach):
                scene = raycasting_scene(P, corners[reach], origin)
                X, Y = part.cell_centers()
                origins = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, top)])
                hits = cast(scene, origins, np.tile([0.0, 0.0, -1.0], (X.size, 1)))
                del scene
                hit = (hits.tri >= 0).reshape(part.shape)
                tri, bary = reach[hits.tri[hit.ravel()]], hits.bary[hit.ravel()]
                dsm[hit] = hits.points[hit.ravel(), 2]
                n = vertex_normals(P - origin, corners)
                long = np.isin(used, buckets.long_vertices)
                n[long] = buckets.long_normals[np.searchsorted(buckets.long_vertices, used[long])]
                normal[:, hit] = hit_normals(n[corners[tri]], bary).T
                ortho[hit] = hit_colours(mesh, idx[tri], corners[tri], colours, bary)
            yield rows, cols, ortho, dsm, normal
    share = bad_edges / max(edges, 1)
    if share > NON_MANIFOLD_SHARE:
        raise InputError(mesh.path, "faces", f"{share:.1%} of the edges are shared by more "
                         "than two triangles: not a surface")  # fmt: skip


class TileBuckets:
    """Which triangles (indices, ascending) reach each tile, kept in memory up to
    ``buffer_bytes`` and past that appended to a file a tile in a temporary folder.

    Attributes
    ----------
    long_vertices : (L,) int64
        Sorted vertices of the triangles longer than the tiles' margin.
    long_normals : (L, 3) float64
        Their unit normals over the whole mesh.
    """

    def __init__(self, n_tiles: int, scratch=None, buffer_bytes: int | None = None):
        self.parts: list[list[np.ndarray]] = [[] for _ in range(n_tiles)]
        self.scratch, self.held = scratch, 0
        self.buffer_bytes = BUCKET_BUFFER_BYTES if buffer_bytes is None else buffer_bytes
        self.folder: Path | None = None
        self.long_vertices = np.zeros(0, np.int64)
        self.long_normals = np.zeros((0, 3))

    def add(self, tile_ids: np.ndarray, triangles: np.ndarray) -> None:
        """Put ``triangles`` (N,) in the tiles ``tile_ids`` (N,); within a call and from
        one call to the next the triangles come in ascending order."""
        order = np.argsort(tile_ids, kind="stable")
        tile_ids, triangles = tile_ids[order], triangles[order]
        starts = np.flatnonzero(np.r_[True, tile_ids[1:] != tile_ids[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(tile_ids)], strict=True):
            self.parts[tile_ids[a]].append(triangles[a:b])
        self.held += triangles.nbytes
        if self.held > self.buffer_bytes:
            self._spill()

    def _spill(self) -> None:
        if self.folder is None:
            self.folder = Path(tempfile.mkdtemp(prefix="mesh-tiles-", dir=self.scratch))
        for k, parts in enumerate(self.parts):
            if parts:
                path = self.folder / f"{k}.i8"
                with full_disk_named(path), open(path, "ab") as f:
                    for p in parts:
                        f.write(p.astype("<i8").tobytes())
                self.parts[k] = []
        self.held = 0

    def take(self, k: int) -> np.ndarray:
        """(N,) int64 the triangles of tile ``k``, ascending (given once)."""
        parts = self.parts[k]
        self.parts[k] = []
        if self.folder is not None and (self.folder / f"{k}.i8").exists():
            parts = [np.fromfile(self.folder / f"{k}.i8", "<i8"), *parts]
            (self.folder / f"{k}.i8").unlink()
        return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)

    def __enter__(self) -> TileBuckets:
        return self

    def __exit__(self, *exc) -> None:
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)


def tile_buckets(mesh, grid: Grid, tile: int, origin: np.ndarray, scratch=None) -> TileBuckets:
    """The triangles of each of ``grid.tiles(tile)``, in two passes over the faces.

    The first finds the longest triangle (in x or y) up to a quarter of a tile, the
    tiles' margin; the triangles longer than that are few (a mesh of a city's roofs has
    none) and their vertices' normals are summed over the whole mesh in the second
    pass. The second puts each triangle in every tile its box, widened by the margin,
    reaches: a tile then holds every triangle around each vertex of a triangle over it.

    Raises
    ------
    InputError
        A face names a vertex the mesh does not have.
    """
    side = tile * grid.gsd
    cap = side / 4
    margin, long = 0.0, []
    for s, _, P in _face_chunks(mesh):
        lo, hi = _xy_box(P)
        extent = np.maximum(hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1])
        over = extent > cap
        long.append(s + np.flatnonzero(over))
        if (~over).any():
            margin = max(margin, float(extent[~over].max()))
    long = np.concatenate(long)
    margin += 1e-3  # float32 boxes are rounded outwards for the rays
    rows_n, cols_n = -(-grid.height // tile), -(-grid.width // tile)
    buckets = TileBuckets(rows_n * cols_n, scratch)
    long_vertices = np.unique(mesh.faces(long)) if len(long) else np.zeros(0, np.int64)
    long_sums = np.zeros((len(long_vertices), 3))
    x0, y1 = grid.xmin, grid.ymax
    try:
        for s, T, P in _face_chunks(mesh):
            lo, hi = _xy_box(P)
            lo, hi = lo - margin, hi + margin
            c0 = np.floor((lo[:, 0] - x0) / side).astype(np.int64)
            c1 = np.floor((hi[:, 0] - x0) / side).astype(np.int64)
            r0 = np.floor((y1 - hi[:, 1]) / side).astype(np.int64)
            r1 = np.floor((y1 - lo[:, 1]) / side).astype(np.int64)
            c0, r0 = np.maximum(c0, 0), np.maximum(r0, 0)
            c1, r1 = np.minimum(c1, cols_n - 1), np.minimum(r1, rows_n - 1)
            nc, nr = np.maximum(c1 - c0 + 1, 0), np.maximum(r1 - r0 + 1, 0)
            tri = np.repeat(np.arange(len(T)), nc * nr)
            step = np.arange(len(tri)) - np.repeat(np.cumsum(nc * nr) - nc * nr, nc * nr)
            rr, cc = r0[tri] + step // nc[tri], c0[tri] + step % nc[tri]
            buckets.add(rr * cols_n + cc, s + tri)
            if len(long_vertices):
                _add_face_normals(long_sums, long_vertices, T, P - origin)
    except BaseException:  # an interrupted pass leaves no lists on disk
        buckets.__exit__(None, None, None)
        raise
    buckets.long_vertices = long_vertices
    buckets.long_normals = _unit(long_sums)
    return buckets


def _face_chunks(mesh):
    """(first index, (N, 3) faces, (N, 3, 3) corner positions) a chunk of triangles at a
    time; the faces' indices checked."""
    n_v = mesh.n_vertices
    for s in range(0, mesh.n_triangles, TRIANGLES_PER_CHUNK):
        T = mesh.faces(slice(s, s + TRIANGLES_PER_CHUNK))
        if len(T) and (T.min() < 0 or T.max() >= n_v):
            raise InputError(mesh.path, "faces", f"a face names vertex {int(T.max())}; "
                             f"the mesh has {n_v} vertices")  # fmt: skip
        yield s, T, mesh.positions(T.reshape(-1)).reshape(-1, 3, 3)


def non_manifold_edges(T: np.ndarray, corners: np.ndarray, bounds) -> tuple[int, int]:
    """Edges of triangles ``T`` (N, 3 vertex indices) whose midpoint lies in ``bounds``
    (xmin, ymin, xmax, ymax; half-open), counted once each: how many are shared by more
    than two of the triangles, and how many there are. ``corners`` (N, 3, 3) are the
    triangles' positions. Every triangle on such an edge holds its midpoint in its box,
    so a tile's triangles count its edges whole."""
    a, b = T.T.reshape(-1), T[:, [1, 2, 0]].T.reshape(-1)
    xy = corners[..., :2]
    mid = (np.concatenate([xy[:, 0], xy[:, 1], xy[:, 2]])
           + np.concatenate([xy[:, 1], xy[:, 2], xy[:, 0]])) / 2  # fmt: skip
    inside = ((mid[:, 0] >= bounds[0]) & (mid[:, 0] < bounds[2])
              & (mid[:, 1] >= bounds[1]) & (mid[:, 1] < bounds[3]))  # fmt: skip
    a, b = a[inside], b[inside]
    if not len(a):
        return 0, 0
    key = np.minimum(a, b) * (int(T.max()) + 1) + np.maximum(a, b)  # one int64 an edge
    key.sort()
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    return int((counts > 2).sum()), len(counts)


def _boxes(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles' xy boxes (N, 2) float32 from their (N, 3, 3) local corners, rounded
    outwards (a box holds its triangle whatever float32 does to it)."""
    lo, hi = _xy_box(corners)
    return (np.nextafter(lo.astype(np.float32), -np.inf),
            np.nextafter(hi.astype(np.float32), np.inf))  # fmt: skip


def _xy_box(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) least and greatest x and y of triangles' (N, 3, 3) corners."""
    xy = corners[..., :2]
    lo = np.minimum(np.minimum(xy[:, 0], xy[:, 1]), xy[:, 2])
    return lo, np.maximum(np.maximum(xy[:, 0], xy[:, 1]), xy[:, 2])


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals at the vertices: the area-weighted mean of their triangles'.

    Each vertex sums its triangles' normals in the triangles' order (a triangle's three
    corners, then the next triangle's), so that the sums over any set of triangles
    holding all of a vertex's are the same floats. ``vertices`` are relative to a
    local origin; a chunk of triangles at a time (a city mesh's at once took
    gigabytes)."""
    n = np.zeros((len(vertices), 3))
    for s in range(0, len(triangles), TRIANGLES_PER_CHUNK):
        t = triangles[s : s + TRIANGLES_PER_CHUNK]
        _add_face_normals(n, None, t, vertices[t])
    return _unit(n)


def _add_face_normals(sums: np.ndarray, rows: np.ndarray | None, T: np.ndarray,
                      corners: np.ndarray) -> None:  # fmt: skip
    """Add each triangle's normal (twice its area) to ``sums`` at its corners, triangle
    after triangle; with ``rows`` (sorted vertex indices), only to those vertices, at
    their position in it."""
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    at, value = T.reshape(-1), np.repeat(face, 3, axis=0)
    if rows is not None:
        pos = np.minimum(np.searchsorted(rows, at), len(rows) - 1)
        keep = rows[pos] == at
        at, value = pos[keep], value[keep]
    np.add.at(sums, at, value)


def _unit(n: np.ndarray) -> np.ndarray:
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def hit_normals(corner_normals: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals at hits, interpolated from the (N, 3, 3) vertex normals of
    their triangles' corners (the smooth shading of the mesh: a marching-cubes
    surface's own facets tilt by tens of degrees on flat ground), turned up."""
    w = np.column_stack([1.0 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]])
    n = _unit(np.einsum("nk,nkj->nj", w, corner_normals))
    return np.where(n[:, 2:] < 0, -n, n)


def hit_colours(mesh, tri: np.ndarray, corners: np.ndarray, colours: np.ndarray | None,
                bary: np.ndarray) -> np.ndarray:  # fmt: skip
    """(N, 3) uint8 colour at hits on triangles ``tri`` (N,) of ``mesh`` with barycentric
    (u, v): its texture's, else its vertex ``colours`` ((U, 3) uint8 of the vertices the
    tile reads, which ``corners`` (N, 3) index; None: grey)."""
    w = np.column_stack([1.0 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]])
    if mesh.uvs is not None and mesh.textures:
        uv = np.einsum("nk,nkj->nj", w, mesh.uvs[tri])
        out = np.zeros((len(tri), 3), np.uint8)
        mat = mesh.material[tri]
        for k, image in enumerate(mesh.textures):
            sel = mat == k
            h, wdt = image.shape[:2]
            c = np.clip((uv[sel, 0] % 1.0) * wdt, 0, wdt - 1).astype(np.int64)
            r = np.clip((1.0 - uv[sel, 1] % 1.0) * h, 0, h - 1).astype(np.int64)
            out[sel] = image[r, c]
        return out
    if colours is not None:
        c = np.einsum("nk,nkj->nj", w, colours[corners].astype(np.float64))
        return np.clip(c + 0.5, 0, 255).astype(np.uint8)
    return np.full((len(tri), 3), 128, np.uint8)


def fuse_mesh(path, opts: FusionOptions | None = None, *, crs: str | None = None):
    """Sample a surface mesh into a :class:`FusionResult` (with ``normal``).

    Returns
    -------
    result : FusionResult
    crs : CRS or None
    inputs : dict summary of the mesh
    """
    opts = opts or FusionOptions()
    timer = StageTimer()
    t0 = time.perf_counter()
    mesh, grid = opened_mesh(path, opts, crs, timer)
    return fuse_opened_mesh(mesh, grid, opts, timer, t0)


def fuse_opened_mesh(mesh, grid: Grid, opts: FusionOptions, timer: StageTimer, t0: float):
    """:func:`fuse_mesh` of a mesh :func:`opened_mesh` opened, on its grid."""
    check_memory(grid, opts, 1)
    with timer.stage("sampling"):
        ortho, dsm, normal = orthogonal_sampling(mesh, grid)
    products, figures = surface_products(ortho, dsm, grid.gsd, opts, timer)
    record = mesh_record(mesh, opts, figures, timer, t0)
    p = products
    result = FusionResult(grid, ortho, p["dsm"], p["dtm"], p["ndsm"], p["class_prob"],
                          p["count"], {}, record, None, normal,
                          class_map=figures.pop("class_map"))  # fmt: skip
    return result, mesh.crs, mesh_inputs(mesh)


def opened_mesh(path, opts: FusionOptions, crs: str | None, timer: StageTimer):
    """The mesh (:func:`open_surface_mesh`) and the grid it is sampled on (``opts.gsd``
    and ``opts.bounds``, else the mesh's)."""
    with timer.stage("read"):
        mesh = open_surface_mesh(path, crs)
        gsd = opts.gsd or default_gsd(mesh)
    grid = Grid.covering(np.stack([mesh.lo, mesh.hi])[:, :2], gsd, opts.bounds)
    if min(grid.width, grid.height) < 3:
        raise InputError(mesh.path, None, f"a {grid.width} x {grid.height} grid at --gsd "
                         f"{gsd:g}: give a finer --gsd for a mesh this small")  # fmt: skip
    return mesh, grid


def surface_products(
    ortho: np.ndarray, dsm: np.ndarray, gsd: float, opts: FusionOptions, timer: StageTimer,
    origin: tuple[int, int] = (0, 0),
) -> tuple[dict, dict]:  # fmt: skip
    """The fusion's rasters from a sampled ortho ((h, w, 3) uint8) and DSM ((h, w)
    float32, NaN where no ray hit) of a grid or a block: small holes filled, the DTM
    (progressive morphological filter), the classes (the forest for label-free rasters),
    the planar objects. ``origin``: the (row, col) of the block's first cell in the grid.

    Returns
    -------
    products : {dsm, dtm, ndsm, class_prob, classes, count} (the names of
        :func:`~fusion.blocks.fuse_in_blocks`'s products)
    figures : the record's missed and filled cells, the planar objects' counts, and
        ``class_map`` (the planar objects' classes, None without them)
    """
    with timer.stage("sampling"):
        hit = np.isfinite(dsm)
        holes = small_holes(~hit, HOLE_CELLS)
        dsm = fill_small_holes(dsm, hit, holes, HOLE_CELLS, origin)
    with timer.stage("ground"):
        dtm, _ = dtm_from_dsm(dsm, gsd, origin=origin)
        dtm = np.where(np.isfinite(dsm), np.minimum(dtm, dsm), np.nan).astype(np.float32)
        ndsm = (dsm - dtm).astype(np.float32)
    with timer.stage("classes"):
        prob = classify_rasters(synthetic_raster_forest(), dsm, dtm, ortho, gsd)
    class_map = None
    planar = dict.fromkeys(PLANAR_COUNTS, 0)
    if opts.planar_objects:
        with timer.stage("planar_objects"):
            class_map, prob, planar = planar_roofs_classed_tree(
                class_codes(prob), prob, dsm, ndsm, gsd, opts.seed
            )
    count = hit.astype(np.int16)
    count[holes] = FILLED
    products = {"dsm": dsm, "dtm": dtm, "ndsm": ndsm, "class_prob": prob, "count": count,
                "classes": class_map if class_map is not None else class_codes(prob)}  # fmt: skip
    figures = {**planar, "missed_cells": int((~hit).sum()), "filled_cells": int(holes.sum()),
               "class_map": class_map}  # fmt: skip
    return products, figures


def mesh_inputs(mesh) -> dict:
    """The record's summary of the mesh."""
    return {
        "mesh": str(mesh.path.absolute()),
        "vertices": mesh.n_vertices, "triangles": mesh.n_triangles,
        "read": "a part at a time" if isinstance(mesh, PlySurface) else "whole (Open3D)",
        "crs": mesh.crs.to_string() if mesh.crs is not None else None,
        "colour": "texture" if mesh.uvs is not None else
                  "vertex colours" if mesh.has_colours else "none (grey)",
    }  # fmt: skip


def mesh_record(mesh, opts: FusionOptions, figures: dict, timer: StageTimer, t0: float) -> dict:
    """The fusion record of a mesh's sampling (``figures`` from
    :func:`surface_products`, summed over the blocks when in blocks)."""
    return {
        "mode": "mesh",
        "dtm_source": "progressive morphological filter",
        "class_source": "a forest trained on the synthetic city's rasters (nDSM, slope, "
        "roughness, curvature, brightness, greenness): no training labels"
        + ("; objects classed tree made building where planes explain most of their cells "
           "and roof faces joined to crowns where they continue a building "
           "(fusion.planar_objects)" if opts.planar_objects else ""),
        **{k: v for k, v in figures.items() if k != "class_map"},
        "seconds_per_million_triangles": round(
            (time.perf_counter() - t0) / max(mesh.n_triangles / 1e6, 1e-6), 2),
        "stages": timer.stages,
    }  # fmt: skip


# a block's peak while it makes its products (:func:`surface_products`), bytes a cell of its
# window: the ortho, the heights, the forest's features and the four classes' probabilities
BYTES_PER_BLOCK_CELL = 300


@dataclass
class MeshBlocks:
    """What every block of a mesh's fusion needs: shared once with the workers, who read
    the sampled ortho and DSM of the whole grid from the run's store (a folder every
    worker sees)."""

    ortho: WindowedRaster
    dsm: WindowedRaster
    grid: Grid
    opts: FusionOptions
    blocks: list


def mesh_block_products(k: int, ctx: MeshBlocks) -> tuple[dict, dict]:
    """Task: block ``k``'s products (:func:`surface_products`) over its window of the
    sampled ortho and DSM, cut to its inside; its figures with its stages' times."""
    b, timer = ctx.blocks[k], StageTimer()
    with timer.stage("read"):
        ortho = np.moveaxis(ctx.ortho.read(*b.outer), 0, -1)
        dsm = ctx.dsm.read(*b.outer)[0]
    products, f = surface_products(ortho, dsm, ctx.grid.gsd, ctx.opts, timer, b.origin)
    products["ortho"] = ortho
    # the inside of each: class_prob is (4, h, w), the others (h, w) or (h, w, 3)
    inside = {k: v[(slice(None), *b.inside)] if k == "class_prob" else v[b.inside]
              for k, v in products.items()}  # fmt: skip
    f.pop("class_map")
    f["missed_cells"] = int(np.count_nonzero(inside["count"] != 1))  # not the margin's
    f["filled_cells"] = int(np.count_nonzero(inside["count"] == FILLED))
    f["stages"] = timer.stages
    return {k: np.ascontiguousarray(v) for k, v in inside.items()}, f


def mesh_workers(grid: Grid, block_m: float, opts: FusionOptions) -> int:
    """Blocks of ``block_m`` metres made at once: ``opts.workers``, or as many as this
    machine has cores and as ``opts.max_memory_fraction`` of its memory holds, at
    :data:`BYTES_PER_BLOCK_CELL` a cell of the largest block's window."""
    windows = (grid.window(*b.outer) for b in block_layout(grid, block_m))
    cells = max(w.width * w.height for w in windows)
    return workers_in_memory(opts, cells * BYTES_PER_BLOCK_CELL)


def fuse_mesh_in_blocks(mesh, grid: Grid, opts: FusionOptions, timer: StageTimer, write,
                        normal_path: Path, block_m: float, scratch: Path,
                        engine: Engine | None = None) -> dict:  # fmt: skip
    """Sample a surface mesh block by block: its memory follows the block, not the area.

    1. The mesh is sampled tile by tile (:func:`sampled_tiles`), in this process, into
       the grid's ortho, DSM and normals, windows of rasters kept in the engine's store
       (``scratch`` without one); the normals become ``normal_path``.
    2. Each block, with its margin (the largest building's width: the ground filter's
       largest window and a building the block's edge cuts), is a task of ``engine``
       (:func:`mesh_block_products`; default: this process, one after another) that
       makes its products; ``write(block, products)`` takes their inside, in the
       blocks' order.

    With a store, a run interrupted in step 2 keeps the samples and the finished blocks
    for ``--resume``, which samples nothing again and makes only the other blocks. The
    tiles' lists of triangles go to ``scratch`` when they outgrow memory.

    Returns
    -------
    The record's figures, summed over the blocks: the missed and filled cells of their
    insides, the planar objects of their windows (an object in a margin is counted by
    every block that holds it); the blocks' stages summed into ``timer``.
    """
    engine = engine or ThreadEngine(1)
    blocks = block_layout(grid, block_m)
    for b in blocks:  # before the sampling: a block too large stops at once
        check_memory(grid.window(*b.outer), opts, 1)
    kept = engine.store.scratch("samples") if engine.store is not None else scratch
    sampled = (kept / "sampled").exists()  # by an interrupted run, for --resume
    ortho = WindowedRaster(kept / "ortho.tif", grid, None, np.uint8, 3, reopen=sampled)
    dsm = WindowedRaster(kept / "dsm.tif", grid, None, np.float32, 1, nodata=np.nan,
                         reopen=sampled)  # fmt: skip
    normal = WindowedRaster(kept / "normal.tif", grid, mesh.crs, np.float32, 3,
                            descriptions=["nx", "ny", "nz"], reopen=sampled)  # fmt: skip
    if sampled:
        log.info("fusion: the mesh's samples kept by the interrupted run")
    else:
        with timer.stage("sampling"):
            for rows, cols, o, d, n in sampled_tiles(mesh, grid, scratch=scratch):
                ortho.write(np.moveaxis(o, -1, 0), rows, cols)
                dsm.write(d, rows, cols)
                normal.write(n, rows, cols)
        (kept / "sampled").touch()
    shared = engine.share(MeshBlocks(ortho, dsm, grid, opts, blocks))
    done = engine.map(mesh_block_products, range(len(blocks)), shared, stage="blocks",
                      keys=[str(b.index) for b in blocks], in_flight=engine.workers)  # fmt: skip
    figures: dict = {}
    for b, (products, f) in zip(blocks, done, strict=True):
        write(b, products)
        timer.add(f.pop("stages"))
        for k, v in f.items():
            figures[k] = figures.get(k, 0) + v
    # the samples' mark goes first: a run stopped while the normals are copied out of
    # the store samples again rather than find their windows gone
    (kept / "sampled").unlink()
    normal.close()
    os.replace(normal.path, normal_path)
    figures["blocks"] = {"count": len(blocks), "side_m": round(float(block_m), 3),
                         "margin_m": LARGEST_WINDOW_M}  # fmt: skip
    figures["engine"] = engine.describe()
    return figures
