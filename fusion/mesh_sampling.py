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
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from workbench.errors import InputError
from workbench.raster import Grid, class_codes, parse_crs
from workbench.raycast import cast, local_origin, raycasting_scene
from workbench.records import StageTimer

from .ground import dtm_from_dsm
from .interpolate import fill_small_holes, small_holes
from .options import FusionOptions
from .planar_objects import COUNTS as PLANAR_COUNTS
from .planar_objects import planar_roofs_classed_tree
from .raster_forest import classify_rasters, synthetic_raster_forest
from .scene_fusion import FILLED, HOLE_CELLS, FusionResult, check_memory

log = logging.getLogger(__name__)

NON_MANIFOLD_SHARE = 0.001  # more non-manifold edges than this: not a surface
TRIANGLES_PER_CHUNK = 1 << 20  # triangles boxed at once (flat memory on a city's mesh)
SAMPLING_TILE_CELLS = 1024  # cells a side of a tile cast against its own scene
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
    normals : (V, 3) float or None
        Unit vertex normals (computed when first needed).
    """

    path: Path
    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray | None
    uvs: np.ndarray | None
    textures: list
    material: np.ndarray | None
    crs: object
    normals: np.ndarray | None = None


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
    share = non_manifold_share(T)
    if share > NON_MANIFOLD_SHARE:
        raise InputError(path, "faces", f"{share:.1%} of the edges are shared by more than "
                         "two triangles: not a surface")  # fmt: skip
    text = crs or ply_crs(path)
    crs_obj = parse_crs(text, path=path) if text else None
    if crs_obj is None:
        log.warning("%s: no CRS (give --crs): the rasters are written without one", path)
    else:
        check_in_area_of_use(path, V, crs_obj)
    return SurfaceMesh(path, V, T, colors, uvs, textures, material, crs_obj)


def non_manifold_share(triangles: np.ndarray) -> float:
    """Share of the undirected edges used by more than two triangles."""
    n, t = int(triangles.max()) + 1, len(triangles)
    key = np.empty(3 * t, np.int64)  # one int64 an edge, sorted in place (a city's: 113 M)
    for k, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        lo = np.minimum(triangles[:, a], triangles[:, b])
        key[k * t : (k + 1) * t] = lo * n + np.maximum(triangles[:, a], triangles[:, b])
    key.sort()
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    return float((counts > 2).sum() / max(len(counts), 1))


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


def check_in_area_of_use(path: Path, vertices: np.ndarray, crs) -> None:
    """Refuse a mesh whose bounding box lies wholly outside its CRS's area of use (a mesh
    in a local frame, or given the wrong CRS)."""
    from pyproj import CRS as ProjCRS
    from pyproj import Transformer

    epsg = crs.to_epsg()
    proj = ProjCRS.from_epsg(epsg) if epsg else ProjCRS.from_user_input(crs.to_wkt())
    area = proj.area_of_use
    if area is None or not proj.is_projected:
        return
    to_crs = Transformer.from_crs("EPSG:4326", proj, always_xy=True)
    x0, y0, x1, y1 = to_crs.transform_bounds(area.west, area.south, area.east, area.north)
    lo, hi = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
    if hi[0] < x0 or lo[0] > x1 or hi[1] < y0 or lo[1] > y1:
        raise InputError(path, "vertices", f"x {lo[0]:.0f}..{hi[0]:.0f}, y {lo[1]:.0f}.."
                         f"{hi[1]:.0f} lie outside {crs.to_string()}'s area of use "
                         f"({x0:.0f}..{x1:.0f}, {y0:.0f}..{y1:.0f}): a local frame, or "
                         "another CRS?")  # fmt: skip


def default_gsd(mesh: SurfaceMesh) -> float:
    """The median edge length of the mesh's triangles, to two significant digits: a cell
    per vertex, about."""
    V, T = mesh.vertices, mesh.triangles
    sample = T[:: max(1, len(T) // 200_000)]
    edges = np.linalg.norm(V[sample[:, 1]] - V[sample[:, 0]], axis=1)
    gsd = float(np.median(edges[edges > 0])) if (edges > 0).any() else 1.0
    return float(f"{gsd:.2g}")


def orthogonal_sampling(
    mesh: SurfaceMesh, grid: Grid, tile: int = SAMPLING_TILE_CELLS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast a vertical ray down through every cell centre; keep the first hit.

    The grid is cast in tiles of ``tile`` cells a side, each against a ray-casting scene
    of the triangles over it alone: the scene of a city's whole mesh (38 M triangles)
    took some 10 GB. A vertical ray can only hit a triangle whose bounding box holds it,
    and every scene shares one local origin, so the hits are the whole mesh's (a ray
    right on an edge may take the other of its two triangles: the same point, to
    rounding; on `small`'s meshes every product was the same byte for byte).

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
    origin = local_origin(mesh.vertices)
    lo, hi = triangle_boxes(mesh, origin)
    top = float(mesh.vertices[:, 2].max()) + 10.0
    ortho = np.zeros((*grid.shape, 3), np.uint8)
    dsm = np.full(grid.shape, np.nan, np.float32)
    normal = np.full((3, *grid.shape), np.nan, np.float32)
    for rows, cols in grid.tiles(tile):
        part = grid.window(rows, cols)
        x0, y0, x1, y1 = part.bounds
        x0, x1, y0, y1 = x0 - origin[0], x1 - origin[0], y0 - origin[1], y1 - origin[1]
        over = np.flatnonzero((hi[:, 0] >= x0) & (lo[:, 0] <= x1)
                              & (hi[:, 1] >= y0) & (lo[:, 1] <= y1))  # fmt: skip
        if not len(over):
            continue
        used, corners = np.unique(mesh.triangles[over], return_inverse=True)
        scene = raycasting_scene(mesh.vertices[used], corners.reshape(-1, 3), origin)
        X, Y = part.cell_centers()
        origins = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, top)])
        hits = cast(scene, origins, np.tile([0.0, 0.0, -1.0], (X.size, 1)))
        del scene
        hit = (hits.tri >= 0).reshape(part.shape)
        tri, bary = over[hits.tri[hit.ravel()]], hits.bary[hit.ravel()]
        dsm[rows, cols][hit] = hits.points[hit.ravel(), 2]
        normal[:, rows, cols][:, hit] = hit_normals(mesh, tri, bary).T
        ortho[rows, cols][hit] = hit_colours(mesh, tri, bary)
    return ortho, dsm, normal


def triangle_boxes(mesh: SurfaceMesh, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle's xy bounding box relative to ``origin``: lo, hi (T, 2) float32,
    rounded outwards (a box holds its triangle whatever float32 does to it)."""
    n = len(mesh.triangles)
    lo, hi = np.empty((n, 2), np.float32), np.empty((n, 2), np.float32)
    for s in range(0, n, TRIANGLES_PER_CHUNK):  # the corners of a chunk at a time
        xy = mesh.vertices[mesh.triangles[s : s + TRIANGLES_PER_CHUNK], :2] - origin[:2]
        lo[s : s + len(xy)] = np.nextafter(xy.min(axis=1).astype(np.float32), -np.inf)
        hi[s : s + len(xy)] = np.nextafter(xy.max(axis=1).astype(np.float32), np.inf)
    return lo, hi


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals at the vertices: the area-weighted mean of their triangles'.

    The faces' normals are made a chunk of triangles at a time (a city mesh's at once
    took gigabytes), and summed in the same order as at once."""
    V, T = vertices - vertices.mean(axis=0), triangles
    n = np.zeros_like(V)
    for k in range(3):
        for s in range(0, len(T), TRIANGLES_PER_CHUNK):
            t = T[s : s + TRIANGLES_PER_CHUNK]
            face = np.cross(V[t[:, 1]] - V[t[:, 0]], V[t[:, 2]] - V[t[:, 0]])  # twice the area
            np.add.at(n, t[:, k], face)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n


def hit_normals(mesh: SurfaceMesh, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals at hits, interpolated from the vertex normals (the smooth
    shading of the mesh: a marching-cubes surface's own facets tilt by tens of degrees
    on flat ground), turned up."""
    if mesh.normals is None:
        mesh.normals = vertex_normals(mesh.vertices, mesh.triangles)
    w = np.column_stack([1.0 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]])
    n = np.einsum("nk,nkj->nj", w, mesh.normals[mesh.triangles[tri]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return np.where(n[:, 2:] < 0, -n, n)


def hit_colours(mesh: SurfaceMesh, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colour at hits on triangles ``tri`` (N,) with barycentric (u, v)."""
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
    if mesh.colors is not None:
        c = np.einsum("nk,nkj->nj", w, mesh.colors[mesh.triangles[tri]].astype(np.float64))
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
    with timer.stage("read"):
        mesh = read_surface_mesh(path, crs)
    gsd = opts.gsd or default_gsd(mesh)
    grid = Grid.covering(mesh.vertices[:, :2], gsd, opts.bounds)
    if min(grid.width, grid.height) < 3:
        raise InputError(mesh.path, None, f"a {grid.width} x {grid.height} grid at --gsd "
                         f"{gsd:g}: give a finer --gsd for a mesh this small")  # fmt: skip
    check_memory(grid, opts, 1)
    with timer.stage("sampling"):
        ortho, dsm, normal = orthogonal_sampling(mesh, grid)
        hit = np.isfinite(dsm)
        holes = small_holes(~hit, HOLE_CELLS)
        dsm = fill_small_holes(dsm, hit, holes, HOLE_CELLS)
    with timer.stage("ground"):
        dtm, _ = dtm_from_dsm(dsm, grid.gsd)
        dtm = np.where(np.isfinite(dsm), np.minimum(dtm, dsm), np.nan).astype(np.float32)
        ndsm = (dsm - dtm).astype(np.float32)
    with timer.stage("classes"):
        prob = classify_rasters(synthetic_raster_forest(), dsm, dtm, ortho, grid.gsd)
    class_map = None
    planar = dict.fromkeys(PLANAR_COUNTS, 0)
    if opts.planar_objects:
        with timer.stage("planar_objects"):
            class_map, prob, planar = planar_roofs_classed_tree(
                class_codes(prob), prob, dsm, ndsm, grid.gsd, opts.seed
            )
    count = hit.astype(np.int16)
    count[holes] = FILLED
    inputs = {
        "mesh": str(mesh.path.absolute()),
        "vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
        "crs": mesh.crs.to_string() if mesh.crs is not None else None,
        "colour": "texture" if mesh.uvs is not None else
                  "vertex colours" if mesh.colors is not None else "none (grey)",
    }  # fmt: skip
    record = {
        "mode": "mesh",
        "dtm_source": "progressive morphological filter",
        "class_source": "a forest trained on the synthetic city's rasters (nDSM, slope, "
        "roughness, curvature, brightness, greenness): no training labels"
        + ("; objects classed tree made building where planes explain most of their cells "
           "and roof faces joined to crowns where they continue a building "
           "(fusion.planar_objects)" if opts.planar_objects else ""),
        **planar,
        "missed_cells": int((~hit).sum()), "filled_cells": int(holes.sum()),
        "seconds_per_million_triangles": round(
            (time.perf_counter() - t0) / max(len(mesh.triangles) / 1e6, 1e-6), 2),
        "stages": timer.stages,
    }  # fmt: skip
    result = FusionResult(grid, ortho, dsm, dtm, ndsm, prob, count, {}, record, None, normal,
                          class_map=class_map)  # fmt: skip
    return result, mesh.crs, inputs
