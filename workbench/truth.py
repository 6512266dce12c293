"""Ground truth, sampled onto one evaluation grid: a scene's ``truth/`` or loose files."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from rasterio.features import rasterize

from .errors import InputError
from .footprints import read_footprints
from .meshio import read_ply
from .raster import Grid, check_class_codes, raster_header, read_raster
from .raycast import local_origin, raycasting_scene, vertical_hits
from .scene import load_scene


def sample_to_grid(data: np.ndarray, src: Grid, dst: Grid) -> np.ndarray:
    """Nearest-cell sampling of a (..., H, W) raster on ``src`` at the cells of ``dst``."""
    if src == dst:
        return data
    X, Y = dst.cell_centers()
    r, c = src.cell_index(X, Y)
    inside = src.contains(r, c)
    fill = np.nan if np.issubdtype(data.dtype, np.floating) else 0
    out = np.full(data.shape[:-2] + dst.shape, fill, dtype=data.dtype)
    out[..., inside] = data[..., r[inside], c[inside]]
    return out


def read_on_grid(
    path,
    grid: Grid,
    *,
    field: str | None = None,
    as_float: bool = False,
    header: Grid | None = None,
) -> np.ndarray:
    """(B, H, W) a raster sampled at the cells of ``grid`` (nearest cell; NaN, or 0 for
    integers, off the raster), reading only the part of it they fall on: ``grid`` may be
    a window of a grid far larger than memory. ``header`` is the raster's own grid when
    the caller knows it."""
    src = header if header is not None else raster_header(path, field)[0]
    corners = grid.cell_center(np.array([0, grid.height - 1]), np.array([0, grid.width - 1]))
    r, c = src.cell_index(*corners)
    r0, r1 = max(int(r.min()), 0), min(int(r.max()) + 1, src.height)
    c0, c1 = max(int(c.min()), 0), min(int(c.max()) + 1, src.width)
    if r0 >= r1 or c0 >= c1:  # the window is off the raster: read one cell for its type
        data, sub, _ = read_raster(path, field=field, as_float=as_float,
                                   window=(slice(0, 1), slice(0, 1)))  # fmt: skip
        fill = np.nan if np.issubdtype(data.dtype, np.floating) else 0
        return np.full((len(data),) + grid.shape, fill, data.dtype)
    data, sub, _ = read_raster(path, field=field, as_float=as_float,
                               window=(slice(r0, r1), slice(c0, c1)))  # fmt: skip
    return sample_to_grid(data, sub, grid)


def truth_folder(scene_or_truth: str | Path) -> Path:
    """The truth folder of a scene (folder or scene.json) or a truth folder itself."""
    p = Path(scene_or_truth)
    if (p / "dsm.tif").exists():
        return p
    scene = load_scene(p, check_files=False)
    if scene.truth is None:
        raise InputError(scene.scene_json, "truth", "the scene has no truth folder")
    return scene.truth


def truth_scene(scene_or_truth: str | Path, folder: Path):
    """The scene the truth belongs to (given as the scene, or as its ``truth/`` folder
    beside ``scene.json``), None when there is none."""
    p = Path(scene_or_truth)
    scene_path = p if p.resolve() != folder.resolve() else folder.parent
    if not (scene_path / "scene.json").exists() and scene_path.suffix != ".json":
        return None
    return load_scene(scene_path, check_files=False)


def truth_rasters(scene_or_truth: str | Path, grid: Grid) -> dict[str, np.ndarray]:
    """The truth rasters that exist (dsm, dtm, ortho (H, W, 3), class, building_id), on
    ``grid`` (:func:`truth_layer`)."""
    folder = truth_folder(scene_or_truth)
    return {name: truth_layer(name, folder / f"{name}.tif", grid) for name in TRUTH_RASTERS
            if (folder / f"{name}.tif").exists()}  # fmt: skip


def truth_layer(name: str, path: Path, grid: Grid, header: Grid | None = None) -> np.ndarray:
    """Truth raster ``name`` (of :data:`TRUTH_RASTERS`) on ``grid`` (:func:`read_on_grid`):
    heights float64 (H, W), classes checked uint8 (H, W), the ortho (H, W, 3), ids as
    they are."""
    heights = name in ("dsm", "dtm")
    data = read_on_grid(path, grid, field=f"truth {name}", as_float=heights, header=header)
    if name == "class":
        return check_class_codes(data, path, "truth class")[0].astype(np.uint8)
    if name == "ortho":
        return np.moveaxis(data, 0, -1)
    return data[0].astype(np.float64) if heights else data[0]


def training_mask(scene, grid: Grid) -> np.ndarray | None:
    """(H, W) bool the cells of ``grid`` under ``scene``'s training strokes, on which the
    classes are not scored (a classifier trained on them is right there by construction);
    None when the scene has none."""
    strokes = scene.training_labels if scene is not None else None
    if strokes is None or not Path(strokes).exists():
        return None
    return read_on_grid(strokes, grid, field="training labels")[0] > 0


def training_cells(scene_or_truth: str | Path, grid: Grid) -> np.ndarray | None:
    """:func:`training_mask` of the scene a truth belongs to (None when there is none)."""
    return training_mask(truth_scene(scene_or_truth, truth_folder(scene_or_truth)), grid)


@dataclass
class TruthMesh:
    """The true buildings' surfaces: vertices (V, 3), triangles (T, 3), and the building
    id of each triangle (T,)."""

    vertices: np.ndarray
    triangles: np.ndarray
    building: np.ndarray


@dataclass
class Truth:
    """Whatever truth exists, on the evaluation grid (rasters (H, W), metres, NaN unknown).

    Attributes
    ----------
    grid, crs
        The evaluation grid: the truth DSM's.
    dsm, dtm : top surface and bare ground, or None.
    cls : (H, W) uint8 top-surface classes 1-4 (0 unknown), or None.
    training : (H, W) bool
        Cells under the scene's training strokes, which the classes are not scored on
        (a classifier is right there by construction), or None.
    ortho : (H, W, 3) uint8, or None.
    building_ids : (H, W) int
        Building footprints, by id (0: no building), or None. From a mesh these are the
        buildings seen from above without trees, so overhung roofs count as building.
    building_surface : (H, W) float
        Height of the buildings' top surface, NaN off buildings, or None.
    roof_normals : (H, W, 3) float
        Unit normal of the roof under each building cell, or None.
    buildings : {id: record}
        Per-building facts (roof_type, height, base_z, ...) where known.
    mesh : TruthMesh or None
    views : list of View
        The scene's calibrated views (for the texture seams), empty without a scene.
    sources : {what: file}
    """

    grid: Grid
    crs: object
    dsm: np.ndarray | None = None
    dtm: np.ndarray | None = None
    cls: np.ndarray | None = None
    training: np.ndarray | None = None
    ortho: np.ndarray | None = None
    building_ids: np.ndarray | None = None
    building_surface: np.ndarray | None = None
    roof_normals: np.ndarray | None = None
    buildings: dict[int, dict] = field(default_factory=dict)
    mesh: TruthMesh | None = None
    views: list = field(default_factory=list)
    sources: dict[str, str] = field(default_factory=dict)

    def window(self, rows: slice, cols: slice) -> Truth:
        """The truth on the cells ``rows`` x ``cols`` of its grid (views of its arrays)."""
        out = replace(self, grid=self.grid.window(rows, cols))
        for name in GRID_LAYERS:
            a = getattr(self, name)
            if a is not None:
                setattr(out, name, a[rows, cols])
        return out


GRID_LAYERS = ("dsm", "dtm", "cls", "training", "ortho", "building_ids", "building_surface",
               "roof_normals")  # fmt: skip


def open_scene_truth(scene_or_truth: str | Path) -> TruthSource:
    """The full truth of a synthetic scene, on the grid of its ``truth/dsm.tif``, read a
    window at a time (:meth:`TruthSource.window`)."""
    folder = truth_folder(scene_or_truth)
    grid, _, crs = raster_header(folder / "dsm.tif", field="truth dsm")
    rasters = {name: folder / f"{name}.tif" for name in TRUTH_RASTERS
               if (folder / f"{name}.tif").exists()}  # fmt: skip
    truth = TruthSource(grid, crs, rasters)
    truth.sources = {k: str(p) for k, p in rasters.items()}
    scene = truth_scene(scene_or_truth, folder)
    if scene is not None:
        truth.views = scene.views
        if scene.training_labels is not None and Path(scene.training_labels).exists():
            truth.training = Path(scene.training_labels)
            truth.sources["training"] = str(scene.training_labels)
    mesh_path = folder / "mesh.ply"
    if mesh_path.exists():
        vertices, triangles, props = read_ply(mesh_path)
        if "building_id" not in props:
            raise InputError(mesh_path, "building_id", "the truth mesh has no per-face building id")
        keep = props["building_id"] > 0
        truth.mesh = TruthMesh(vertices, triangles[keep], props["building_id"][keep])
        truth.sources["mesh"] = str(mesh_path)
    path = folder / "buildings.json"
    if path.exists():
        try:
            records = json.loads(path.read_text())["buildings"]
            truth.buildings = {int(b["id"]): b for b in records}
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise InputError(path, "buildings", f"unreadable ({exc})") from None
        truth.sources["buildings"] = str(path)
    return truth


def load_scene_truth(scene_or_truth: str | Path) -> Truth:
    """The full truth of a synthetic scene on the grid of its ``truth/dsm.tif``, whole
    in memory (:func:`open_scene_truth` reads it a window at a time)."""
    return open_scene_truth(scene_or_truth).whole()


def open_file_truth(
    *,
    dsm: Path | None = None,
    dtm: Path | None = None,
    footprints: Path | None = None,
    cls: Path | None = None,
    grid: Grid | None = None,
    crs=None,
) -> TruthSource:
    """Truth from loose files, for real data, read a window at a time. The grid is the
    DSM's, else the class raster's, else ``grid``; footprints are burnt into it with
    their feature ids."""
    rasters, headers = {}, {}
    for name, path in (("dsm", dsm), ("class", cls), ("dtm", dtm)):
        if path is not None:
            rasters[name] = Path(path)
            headers[name] = raster_header(path, f"truth {name}")
    for name in ("dsm", "class"):
        if name in headers:
            grid, _, crs = headers[name]
            break
    if grid is None:
        raise InputError(footprints or Path("."), None, "a truth raster or a run grid is needed")
    truth = TruthSource(grid, crs, rasters)
    truth.sources = {k: str(p) for k, p in rasters.items()}
    if footprints is not None:
        items = read_footprints(footprints, crs=crs, extent=grid.bounds)
        truth.footprints = [(f.polygon, i) for i, f in enumerate(items, start=1)]
        truth.sources["footprints"] = str(footprints)
    return truth


def load_file_truth(**kwargs) -> Truth:
    """:func:`open_file_truth`'s truth whole in memory."""
    return open_file_truth(**kwargs).whole()


TRUTH_RASTERS = ("dsm", "dtm", "ortho", "class", "building_id")


@dataclass
class TruthSource:
    """Whatever truth exists, on the evaluation grid, read a window at a time: a city's
    truth on its grid is gigabytes, a window of it megabytes.

    Attributes
    ----------
    grid, crs
        The evaluation grid.
    rasters : {name: path}
        The truth rasters there are, of :data:`TRUTH_RASTERS`, on any grid.
    training : path of the scene's training strokes, or None.
    mesh : TruthMesh or None
        The true buildings (their ids, top surface and roof normals on the grid are cast
        from it).
    footprints : list of (polygon, id) or None
        True footprints burnt into the grid (without a mesh).
    buildings, views, sources
        As in :class:`Truth`.
    """

    grid: Grid
    crs: object
    rasters: dict[str, Path] = field(default_factory=dict)
    training: Path | None = None
    mesh: TruthMesh | None = None
    footprints: list | None = None
    buildings: dict[int, dict] = field(default_factory=dict)
    views: list = field(default_factory=list)
    sources: dict[str, str] = field(default_factory=dict)

    def __post_init__(self):
        self._headers: dict[str, Grid] = {}
        self._top_down: TopDown | None = None

    def window(self, rows: slice, cols: slice) -> Truth:
        """The truth on the cells ``rows`` x ``cols`` of :attr:`grid` (a
        :class:`Truth` on that window's grid)."""
        g = self.grid.window(rows, cols)
        r = {name: self._read(name, path, g) for name, path in self.rasters.items()}
        t = Truth(g, self.crs, dsm=r.get("dsm"), dtm=r.get("dtm"), cls=r.get("class"),
                  ortho=r.get("ortho"), buildings=self.buildings, mesh=self.mesh,
                  views=self.views, sources=self.sources)  # fmt: skip
        if self.training is not None:
            t.training = read_on_grid(self.training, g, field="training labels")[0] > 0
        if self.mesh is not None:
            if self._top_down is None:
                m = self.mesh
                self._top_down = TopDown(m.vertices, m.triangles, m.building, self.grid)
            t.building_ids, t.building_surface, t.roof_normals = self._top_down.window(rows, cols)
        elif self.footprints:
            t.building_ids = rasterize(self.footprints, out_shape=g.shape, transform=g.transform,
                                       fill=0, dtype="int32").astype(np.int64)  # fmt: skip
        elif self.footprints is not None:  # a footprint file without footprints here
            t.building_ids = np.zeros(g.shape, np.int64)
        elif "building_id" in r:
            t.building_ids = r["building_id"].astype(np.int64)
        if t.building_ids is not None and t.building_surface is None and t.dsm is not None:
            t.building_surface = np.where(t.building_ids > 0, t.dsm, np.nan)
        return t

    def whole(self) -> Truth:
        """The truth on the whole grid, in memory."""
        return self.window(slice(0, self.grid.height), slice(0, self.grid.width))

    def _read(self, name: str, path: Path, grid: Grid) -> np.ndarray:
        if name not in self._headers:
            self._headers[name] = raster_header(path, f"truth {name}")[0]
        return truth_layer(name, path, grid, self._headers[name])


class TopDown:
    """Buildings of a triangle mesh seen straight down at the cell centres of a grid, a
    window of it at a time: the same cell is the same ray whichever window holds it.

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
    building : (T,) int
        Building id of each triangle (> 0).
    grid : Grid
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, building: np.ndarray,
                 grid: Grid):  # fmt: skip
        self.grid, self.building = grid, np.asarray(building)
        self.scene = None
        if len(triangles):
            # Open3D casts in float32: the scene's origin near the grid's centre, as
            # projected coordinates of real data are too large for centimetres in float32
            xmin, ymin, xmax, ymax = grid.bounds
            centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0])
            origin = centre + local_origin(np.asarray(vertices, np.float64) - centre)
            self.scene = raycasting_scene(vertices, triangles, origin)
            self.z_top = float(np.max(vertices[:, 2])) + 10.0

    def window(self, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The buildings at the cells ``rows`` x ``cols`` of the grid.

        Returns
        -------
        ids : (h, w) int64, 0 where no building
        surface : (h, w) float64 height of the top surface, NaN where no building
        normals : (h, w, 3) float64 unit normal of that surface (facing up), NaN where none
        """
        h, w = rows.stop - rows.start, cols.stop - cols.start
        if self.scene is None:
            return np.zeros((h, w), np.int64), np.full((h, w), np.nan), np.full((h, w, 3), np.nan)
        hits = vertical_hits(self.scene, self.grid, self.z_top, (rows, cols))
        hit = hits.tri >= 0
        ids = np.where(hit, self.building[np.where(hit, hits.tri, 0)], 0)
        normals = np.where(hit[:, None], hits.normals, np.nan).reshape(h, w, 3)
        return ids.reshape(h, w).astype(np.int64), hits.points[:, 2].reshape(h, w), normals
