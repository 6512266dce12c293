"""CityJSON 2.0 of a model run (``model.city.json``), the same for every modeling path.

Each building is a ``Building`` city object with three geometries:

- LOD0: its footprint at its base height (``MultiSurface``);
- LOD1.2: the footprint extruded to the height that keeps the model's volume (``Solid``);
- the path's mesh at the path's level of detail (2.2 with roof planes, 1.3 for flat
  multi-level tops), after any other level the path makes (the LOD path's 1.3), each
  mesh's coplanar triangles merged into planar polygons with semantic
  surfaces: ``RoofSurface`` (with slope and azimuth), ``WallSurface``, ``GroundSurface``
  and ``OuterCeilingSurface`` (a downward face above the base).

A mesh in several closed parts is a ``MultiSolid``. Vertices are integers under the
file's ``transform`` (millimetres from a whole-metre origin), listed building after
building and shared between a building's geometries (not between buildings: the file is
written one building at a time); the CRS, where it has an EPSG code, is the metadata's
``referenceSystem``.
"""

from __future__ import annotations

import io
import json
import logging
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from .mesh_faces import planar_faces, weld
from .raycast import cast, raycasting_scene

log = logging.getLogger(__name__)

VERSION = "2.0"
SCALE_M = 0.001  # the transform's scale: vertices to the millimetre
WALL_SLOPE = math.sin(math.radians(10.0))  # |n_z| below this: a wall
MERGE_M = 0.005  # vertices closer than this are one (see mesh_faces.weld)
MIN_AREA_M2 = 0.01  # footprint holes and parts smaller than this are slivers
BASE_TOLERANCE_M = 0.05  # a downward face this close to the base is the ground surface
# spooled texts (city objects, vertices, model.json's buildings) go to disk beyond this
SPOOL_BYTES = 2**23


def city_model(run, dsm: np.ndarray | None = None) -> dict:
    """The CityJSON document of ``run`` (a :class:`~workbench.model_run.ModelRun`).

    Parameters
    ----------
    run : ModelRun
    dsm : (H, W) float, optional
        The heights the path modelled, on ``run.grid`` (metres, NaN unknown): each
        building's ``rmse_m`` attribute is the RMS of the model's roof minus them over
        the footprint's cells (null without).

    Returns
    -------
    dict, ready for ``json.dump``.
    """
    text = io.StringIO()
    _write_run(text, run, dsm)
    return json.loads(text.getvalue())


def write_city_model(path, run, dsm: np.ndarray | None = None) -> None:
    """Write :func:`city_model` of ``run`` to ``path`` (compact JSON, one line), one
    building in memory at a time."""
    with open(path, "w") as f:
        _write_run(f, run, dsm, scratch=Path(path).parent)


def _write_run(f, run, dsm, scratch=None) -> None:
    writer = CityModelWriter(f, run.method, run.crs, city_origin(run.buildings), scratch)
    for b in run.buildings:
        writer.add(b, rms_to_heights(b, dsm, run.grid))
    writer.finish()


def city_origin(buildings) -> np.ndarray:
    """(3,) the file's origin: the whole metres below every building's vertices."""
    lows = [b.mesh.vertices.min(axis=0) for b in buildings if len(b.mesh.vertices)]
    return np.floor(np.min(lows, axis=0)) if lows else np.zeros(3)


class CityModelWriter:
    """model.city.json written building by building, so that no more than one building
    is held: its city objects and its vertices are kept in two spooled files (on disk
    in ``scratch`` once large) until :meth:`finish` puts the document together.

    Parameters
    ----------
    f : text file
        Where the document goes.
    method : str
        The path's name (city objects are ``METHOD-ID``).
    crs : rasterio CRS or None
    origin : (3,) float
        The transform's translation (:func:`city_origin`): whole metres at or below
        every vertex.
    scratch : path, optional
        The spooled files' folder (default: the system's).
    """

    def __init__(self, f, method: str, crs, origin: np.ndarray, scratch=None):
        self.f, self.method, self.crs, self.origin = f, method, crs, np.asarray(origin)
        spool = {"max_size": SPOOL_BYTES, "mode": "w+", "dir": scratch}
        self.objects = tempfile.SpooledTemporaryFile(**spool)
        self.vertices = tempfile.SpooledTemporaryFile(**spool)
        self.count = 0  # vertices written
        self.low = np.full(3, np.iinfo(np.int64).max)
        self.high = np.full(3, np.iinfo(np.int64).min)

    def add(self, b, rms_m: float | None) -> None:
        """Building ``b`` (a :class:`~workbench.model_run.Building`), with its RMS to the
        heights (:func:`rms_to_heights`)."""
        pool = _VertexPool(self.origin)
        obj = _building_object(b, pool, rms_m)
        cells, inverse = pool.finish()
        for g in obj["geometry"]:
            g["boundaries"] = _remap(g["boundaries"], inverse + self.count)
        sep = "," if self.objects.tell() else ""
        self.objects.write(sep + json.dumps(f"{self.method}-{b.id}") + ":"
                           + json.dumps(obj, separators=(",", ":")))  # fmt: skip
        if len(cells):
            sep = "," if self.count else ""
            self.vertices.write(sep + json.dumps(cells.tolist(), separators=(",", ":"))[1:-1])
            self.low = np.minimum(self.low, cells.min(axis=0))
            self.high = np.maximum(self.high, cells.max(axis=0))
        self.count += len(cells)

    def finish(self) -> None:
        """Write the document: its header, then the city objects and the vertices."""
        metadata = {"title": f"{self.method} model (city-workbench)"}
        epsg = self.crs.to_epsg() if self.crs is not None else None
        if epsg:
            metadata["referenceSystem"] = f"https://www.opengis.net/def/crs/EPSG/0/{epsg}"
        elif self.crs is not None:
            log.warning("model.city.json: the CRS has no EPSG code; referenceSystem left "
                        "out (model.json holds its WKT)")  # fmt: skip
        if self.count:
            extent = np.concatenate([self.low * SCALE_M + self.origin,
                                     self.high * SCALE_M + self.origin])  # fmt: skip
            metadata["geographicalExtent"] = [round(float(v), 3) for v in extent]
        head = {
            "type": "CityJSON",
            "version": VERSION,
            "transform": {"scale": [SCALE_M] * 3, "translate": self.origin.tolist()},
            "metadata": metadata,
        }
        self.f.write(json.dumps(head, separators=(",", ":"))[:-1] + ',"CityObjects":{')
        for spool, tail in ((self.objects, '},"vertices":['), (self.vertices, "]}")):
            spool.seek(0)
            shutil.copyfileobj(spool, self.f)
            spool.close()
            self.f.write(tail)


class _VertexPool:
    """Vertices in the file's integer steps; equal ones are merged when finished."""

    def __init__(self, origin: np.ndarray):
        self.origin = origin
        self.chunks: list[np.ndarray] = []
        self.size = 0

    def cells(self, points: np.ndarray) -> np.ndarray:
        return np.round((np.asarray(points, np.float64) - self.origin) / SCALE_M).astype(np.int64)

    def add(self, cells: np.ndarray) -> int:
        """Add (k, 3) integer vertices; return the index of the first."""
        first = self.size
        self.chunks.append(np.asarray(cells, np.int64).reshape(-1, 3))
        self.size += len(self.chunks[-1])
        return first

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """The distinct vertices, and the index among them of each one added."""
        if not self.chunks:
            return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
        unique, inverse = np.unique(np.concatenate(self.chunks), axis=0, return_inverse=True)
        return unique, inverse.reshape(-1)


def _remap(boundaries, inverse: np.ndarray):
    if isinstance(boundaries, np.ndarray):
        return inverse[boundaries].tolist()
    return [_remap(b, inverse) for b in boundaries]


def _building_object(b, pool: _VertexPool, rms_m: float | None) -> dict:
    cells, tri, _ = weld(b.mesh.vertices - pool.origin, b.mesh.triangles, SCALE_M, MERGE_M)
    first = pool.add(cells)
    local = cells * SCALE_M
    footprint = _polygons(b.footprint)
    volume = _volume(local, tri)
    bottom = _bottom_area(local, tri) or sum(p.area for p in footprint)
    top_z = b.base_z + volume / bottom if bottom > 0 else b.ridge_z
    # the mean height of a solid is under its top, but for the millimetres the welded
    # vertices were rounded by (a flat roof's block: 1 mm over its ridge)
    top_z = min(top_z, b.ridge_z)
    geometry = []
    if footprint and np.isfinite(b.base_z):
        geometry.append(_footprint_surface(footprint, b.base_z, pool))
        if np.isfinite(top_z) and top_z > b.base_z:
            geometry.append(_prism(footprint, b.base_z, top_z, pool))
    base_local = b.base_z - pool.origin[2] if np.isfinite(b.base_z) else local[:, 2].min()
    for lod, mesh in sorted(b.lods.items()):
        c, t, _ = weld(mesh.vertices - pool.origin, mesh.triangles, SCALE_M, MERGE_M)
        if len(t):
            geometry.append(_mesh_solid(c * SCALE_M, t, pool.add(c), lod, base_local))
    if len(tri):
        geometry.append(_mesh_solid(local, tri, first, b.lod, base_local))
    return {
        "type": "Building",
        "attributes": _attributes(b, top_z, rms_m),
        "geometry": geometry,
    }


def _attributes(b, top_z: float, rms_m: float | None) -> dict:
    def metres(v):
        return round(float(v), 3) if v is not None and np.isfinite(v) else None

    return {
        "roofType": b.roof_type,
        "measuredHeight": metres(b.ridge_z - b.base_z),
        "base_z": metres(b.base_z),
        "eave_z": metres(b.eave_z),
        "ridge_z": metres(b.ridge_z),
        "lod1_z": metres(top_z),
        "rmse_m": metres(rms_m),
        "roof_planes": int(len(b.planes)),
        "faces": int(len(b.mesh.triangles)),
        "watertight": b.watertight,
    }


def _mesh_solid(local: np.ndarray, tri: np.ndarray, first: int, lod: str, base_z: float):
    """The mesh as a Solid (one closed part) or a MultiSolid, with semantic surfaces."""
    surfaces: list[dict] = []
    kinds: dict[str, int] = {}
    solids, values = [], []
    for part in _parts(tri):
        shell, shell_values = [], []
        for face in planar_faces(local, tri[part]):
            shell.append([first + r for r in face.rings])
            shell_values.append(_semantic(face, local, base_z, surfaces, kinds))
        solids.append([shell])
        values.append([shell_values])
    if len(solids) == 1:
        kind, boundaries, values = "Solid", solids[0], values[0]
    else:
        kind, boundaries = "MultiSolid", solids
    return {"type": kind, "lod": lod, "boundaries": boundaries,
            "semantics": {"surfaces": surfaces, "values": values}}  # fmt: skip


def _semantic(face, local, base_z, surfaces: list, kinds: dict) -> int:
    """The index in ``surfaces`` of ``face``'s semantic surface (roofs get their own)."""
    nz = face.normal[2]
    if nz > WALL_SLOPE:
        surfaces.append({
            "type": "RoofSurface",
            "slope_deg": round(math.degrees(math.acos(min(nz, 1.0))), 2),
            "azimuth_deg": round(math.degrees(math.atan2(face.normal[0], face.normal[1]))
                                 % 360.0, 1) if nz < 1.0 - 1e-9 else None,
        })  # fmt: skip
        return len(surfaces) - 1
    if nz >= -WALL_SLOPE:
        kind = "WallSurface"
    else:
        top = local[np.concatenate(face.rings), 2].max()
        kind = "GroundSurface" if top <= base_z + BASE_TOLERANCE_M else "OuterCeilingSurface"
    if kind not in kinds:
        surfaces.append({"type": kind})
        kinds[kind] = len(surfaces) - 1
    return kinds[kind]


def _parts(tri: np.ndarray) -> list[np.ndarray]:
    """Triangle indices of each vertex-connected part, largest first."""
    n = int(tri.max()) + 1
    rows = np.repeat(np.arange(len(tri)), 3)
    graph = coo_matrix((np.ones(rows.size), (rows, tri.ravel())), shape=(len(tri), n))
    incidence = (graph @ graph.T).tocoo()
    _, label = connected_components(incidence, directed=False)
    parts = [np.flatnonzero(label == k) for k in np.unique(label)]
    return sorted(parts, key=len, reverse=True)


def _polygons(footprint) -> list[Polygon]:
    """The footprint's polygons, counter-clockwise, valid on a grid of ``MERGE_M`` (GEOS
    snaps it and splits where an outline touches itself), without holes or parts of under
    ``MIN_AREA_M2``."""
    if footprint is None or footprint.is_empty:
        return []
    snapped = shapely.set_precision(footprint, MERGE_M)
    geoms = snapped.geoms if hasattr(snapped, "geoms") else [snapped]
    out = []
    for p in geoms:
        if isinstance(p, Polygon) and p.area >= MIN_AREA_M2:
            holes = [h for h in p.interiors if Polygon(h).area >= MIN_AREA_M2]
            out.append(orient(Polygon(p.exterior, holes), 1.0))
    return out


def _rings_2d(p: Polygon) -> list[np.ndarray]:
    """Outline (counter-clockwise) and holes of ``p`` as (k, 2) arrays, not closed."""
    return [np.asarray(r.coords)[:-1, :2] for r in (p.exterior, *p.interiors)]


def _ring_cells(pool: _VertexPool, xy: np.ndarray, z: float) -> np.ndarray:
    """Indices of a ring's vertices at height ``z``, consecutive repeats dropped."""
    cells = pool.cells(np.column_stack([xy, np.full(len(xy), z)]))
    keep = np.any(cells != np.roll(cells, 1, axis=0), axis=1)
    cells = cells[keep]
    return pool.add(cells) + np.arange(len(cells))


def _footprint_surface(footprint: list[Polygon], base_z: float, pool: _VertexPool) -> dict:
    boundaries = [[_ring_cells(pool, r, base_z) for r in _rings_2d(p)] for p in footprint]
    return {"type": "MultiSurface", "lod": "0", "boundaries": boundaries}


def _prism(footprint: list[Polygon], base_z: float, top_z: float, pool: _VertexPool) -> dict:
    """LOD1.2: each footprint polygon extruded from ``base_z`` to ``top_z``."""
    solids, values = [], []
    for p in footprint:
        rings = _rings_2d(p)
        bottom = [_ring_cells(pool, r, base_z) for r in rings]
        top = [_ring_cells(pool, r, top_z) for r in rings]
        shell = [[r[::-1] for r in bottom], top]
        for lo, hi in zip(bottom, top, strict=True):
            nxt = np.roll(np.arange(len(lo)), -1)
            shell.extend([[np.array([lo[i], lo[j], hi[j], hi[i]])] for i, j in
                          zip(range(len(lo)), nxt, strict=True)])  # fmt: skip
        solids.append([shell])
        values.append([[0, 1] + [2] * (len(shell) - 2)])
    surfaces = [{"type": "GroundSurface"}, {"type": "RoofSurface"}, {"type": "WallSurface"}]
    if len(solids) == 1:
        kind, boundaries, values = "Solid", solids[0], values[0]
    else:
        kind, boundaries = "MultiSolid", solids
    return {"type": kind, "lod": "1.2", "boundaries": boundaries,
            "semantics": {"surfaces": surfaces, "values": values}}  # fmt: skip


def _volume(V: np.ndarray, T: np.ndarray) -> float:
    """Enclosed volume (m³) of a closed outward mesh (divergence theorem)."""
    if not len(T):
        return 0.0
    a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _bottom_area(V: np.ndarray, T: np.ndarray) -> float:
    """Horizontal area (m²) of the mesh's downward faces: the area its volume stands on."""
    if not len(T):
        return 0.0
    cross = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
    down = cross[:, 2] < 0
    return float(-cross[down, 2].sum() / 2.0)


def rms_to_heights(b, dsm: np.ndarray | None, grid) -> float | None:
    """RMS (m) of the model's top minus ``dsm`` over the cells of ``b``'s footprint."""
    if dsm is None or grid is None or b.footprint is None or not len(b.mesh.triangles):
        return None
    x0, y0, x1, y1 = b.footprint.bounds
    c0, c1 = (int(np.clip(np.floor((x - grid.xmin) / grid.gsd) + k, 0, grid.width))
              for x, k in ((x0, 0), (x1, 1)))  # fmt: skip
    r0, r1 = (int(np.clip(np.floor((grid.ymax - y) / grid.gsd) + k, 0, grid.height))
              for y, k in ((y1, 0), (y0, 1)))  # fmt: skip
    if c1 <= c0 or r1 <= r0:
        return None
    X, Y = grid.window(slice(r0, r1), slice(c0, c1)).cell_centers()
    heights = dsm[r0:r1, c0:c1]
    inside = shapely.contains_xy(b.footprint, X, Y) & np.isfinite(heights)
    if not inside.any():
        return None
    top = float(b.mesh.vertices[:, 2].max()) + 1.0
    n = int(inside.sum())
    origins = np.column_stack([X[inside], Y[inside], np.full(n, top)])
    down = np.tile([0.0, 0.0, -1.0], (n, 1))
    hits = cast(raycasting_scene(b.mesh.vertices, b.mesh.triangles), origins, down)
    d = hits.points[:, 2] - heights[inside]
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d**2))) if len(d) else None
