"""Ground truth, sampled onto one evaluation grid: a scene's ``truth/`` or loose files."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rasterio.features import rasterize

from .errors import InputError
from .footprints import read_footprints
from .meshio import read_ply
from .raster import Grid, check_class_codes, read_raster
from .raycast import raycasting_scene, vertical_hits
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
    """The truth rasters that exist (dsm, dtm, ortho (H, W, 3), class), on ``grid``."""
    folder = truth_folder(scene_or_truth)
    out = {}
    for name in ("dsm", "dtm", "ortho", "class", "building_id"):
        path = folder / f"{name}.tif"
        if path.exists():
            data, src, _ = read_raster(path, as_float=name in ("dsm", "dtm"))
            if name == "class":
                check_class_codes(data, path, "truth class")
            data = sample_to_grid(data, src, grid)
            out[name] = np.moveaxis(data, 0, -1) if name == "ortho" else data[0]
    return out


def training_mask(scene, grid: Grid) -> np.ndarray | None:
    """(H, W) bool the cells of ``grid`` under ``scene``'s training strokes, on which the
    classes are not scored (a classifier trained on them is right there by construction);
    None when the scene has none."""
    strokes = scene.training_labels if scene is not None else None
    if strokes is None or not Path(strokes).exists():
        return None
    data, src, _ = read_raster(strokes, field="training labels")
    return sample_to_grid(data, src, grid)[0] > 0


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


def load_scene_truth(scene_or_truth: str | Path) -> Truth:
    """The full truth of a synthetic scene, on the grid of its ``truth/dsm.tif``."""
    folder = truth_folder(scene_or_truth)
    _, grid, crs = read_raster(folder / "dsm.tif", field="truth dsm")
    r = truth_rasters(folder, grid)
    truth = Truth(grid, crs, dsm=r["dsm"], dtm=r.get("dtm"), cls=r.get("class"))
    truth.ortho = r.get("ortho")
    truth.sources = {k: str(folder / f"{k}.tif") for k in r}
    scene = truth_scene(scene_or_truth, folder)
    if scene is not None:
        truth.views = scene.views
        truth.training = training_mask(scene, grid)
        if truth.training is not None:
            truth.sources["training"] = str(scene.training_labels)
    mesh_path = folder / "mesh.ply"
    if mesh_path.exists():
        vertices, triangles, props = read_ply(mesh_path)
        if "building_id" not in props:
            raise InputError(mesh_path, "building_id", "the truth mesh has no per-face building id")
        keep = props["building_id"] > 0
        truth.mesh = TruthMesh(vertices, triangles[keep], props["building_id"][keep])
        truth.building_ids, truth.building_surface, truth.roof_normals = top_down(
            truth.mesh.vertices, truth.mesh.triangles, truth.mesh.building, grid
        )
        truth.sources["mesh"] = str(mesh_path)
    elif "building_id" in r:
        truth.building_ids = r["building_id"].astype(np.int64)
        truth.building_surface = np.where(truth.building_ids > 0, truth.dsm, np.nan)
    path = folder / "buildings.json"
    if path.exists():
        try:
            records = json.loads(path.read_text())["buildings"]
            truth.buildings = {int(b["id"]): b for b in records}
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise InputError(path, "buildings", f"unreadable ({exc})") from None
        truth.sources["buildings"] = str(path)
    return truth


def load_file_truth(
    *,
    dsm: Path | None = None,
    dtm: Path | None = None,
    footprints: Path | None = None,
    cls: Path | None = None,
    grid: Grid | None = None,
    crs=None,
) -> Truth:
    """Truth from loose files, for real data. The grid is the DSM's, else the class
    raster's, else ``grid``; footprints are burnt into it with their feature ids."""
    rasters = {}
    for name, path in (("dsm", dsm), ("class", cls), ("dtm", dtm)):
        if path is not None:
            heights = name in ("dsm", "dtm")
            data, src, src_crs = read_raster(path, field=f"truth {name}", as_float=heights)
            if name == "class":
                check_class_codes(data, path, "truth class")
            rasters[name] = (data, src, src_crs, path)
    for name in ("dsm", "class"):
        if name in rasters:
            _, grid, crs, _ = rasters[name]
            break
    if grid is None:
        raise InputError(footprints or Path("."), None, "a truth raster or a run grid is needed")
    truth = Truth(grid, crs)
    for name, (data, src, _, path) in rasters.items():
        band = sample_to_grid(data, src, grid)[0]
        if name == "class":
            truth.cls = band.astype(np.uint8)
        else:
            setattr(truth, name, band.astype(np.float64))
        truth.sources[name] = str(path)
    if footprints is not None:
        items = read_footprints(footprints, crs=crs, extent=grid.bounds)
        shapes = [(f.polygon, i) for i, f in enumerate(items, start=1)]
        truth.building_ids = rasterize(
            shapes, out_shape=grid.shape, transform=grid.transform, fill=0, dtype="int32"
        ).astype(np.int64)
        truth.sources["footprints"] = str(footprints)
        if truth.dsm is not None:
            truth.building_surface = np.where(truth.building_ids > 0, truth.dsm, np.nan)
    return truth


def top_down(
    vertices: np.ndarray, triangles: np.ndarray, building: np.ndarray, grid: Grid
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Buildings seen straight down at every cell centre of ``grid``.

    Parameters
    ----------
    vertices : (V, 3) float
    triangles : (T, 3) int
    building : (T,) int
        Building id of each triangle (> 0).

    Returns
    -------
    ids : (H, W) int64, 0 where no building
    surface : (H, W) float64 height of the top surface, NaN where no building
    normals : (H, W, 3) float64 unit normal of that surface (facing up), NaN where none
    """
    H, W = grid.shape
    if not len(triangles):
        return np.zeros((H, W), np.int64), np.full((H, W), np.nan), np.full((H, W, 3), np.nan)
    # Open3D casts in float32: work relative to the grid centre, as projected
    # coordinates of real data are too large for centimetres in float32
    xmin, ymin, xmax, ymax = grid.bounds
    origin = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0])
    local = vertices - origin
    shifted = Grid(grid.xmin - origin[0], grid.ymax - origin[1], grid.gsd, W, H)
    hits = vertical_hits(
        raycasting_scene(local, triangles), shifted, float(local[:, 2].max()) + 10.0
    )
    hit = hits.tri >= 0
    ids = np.where(hit, building[np.where(hit, hits.tri, 0)], 0).reshape(H, W).astype(np.int64)
    surface = hits.points[:, 2].reshape(H, W)
    normals = np.where(hit[:, None], hits.normals, np.nan).reshape(H, W, 3)
    return ids, surface, normals
