"""`workbench model voxel`: read a scene and its footprints, build the proxies, texture
them with surface graph cuts, write the run."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import rasterio.features
import shapely
from scipy.spatial import cKDTree
from shapely.geometry import Polygon, mapping

from workbench.atomic import atomic_output_dir
from workbench.errors import InputError
from workbench.footprints import Footprint, read_footprints
from workbench.imageio import write_rgb
from workbench.meshes import concatenate_meshes, is_watertight
from workbench.meshio import write_mtl, write_obj, write_ply
from workbench.pictures import colorize_height, contact_sheet
from workbench.progress import progress
from workbench.raster import Grid, read_raster
from workbench.raycast import cast, raycasting_scene
from workbench.records import StageTimer, peak_memory_mb
from workbench.render import viewpoints
from workbench.scene import Scene, load_scene

from .ground_texture import GroundTexture, ground_cut, ground_mesh, ring_cut
from .roof_mesh import extrude_faces
from .view_images import ViewImages
from .voxel_model import Proxy, Texture, VoxelOptions, building_proxy, texture_building

log = logging.getLogger(__name__)

_WALL_FOOT_M = 1.0  # wall texels this close above the ground continue onto it (ring cut)


def run_voxel(
    scene_dir: Path,
    out: Path,
    options: VoxelOptions,
    *,
    footprints: Path | None = None,
    fusion_dir: Path | None = None,
    ground_z: float | None = None,
    default_height: float = 35.0,
    overwrite: bool = False,
) -> dict:
    """The whole voxel path; returns the model.json record."""
    timer = StageTimer()
    t_start = time.perf_counter()
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        with timer.stage("read"):
            inputs = read_inputs(
                scene_dir, options, footprints, fusion_dir, ground_z, default_height
            )
            cameras, images = inputs.cameras, inputs.images
        with timer.stage("proxies"):
            proxies = build_proxies(inputs, options)
            images.release_blurred()
        all_proxies = concatenate_meshes([(p.vertices, p.triangles) for p in proxies])
        scene_rc = raycasting_scene(*all_proxies[:2]) if proxies else None
        with timer.stage("textures"):
            textures: list[Texture] = [
                texture_building(p, cameras, images, options, scene_rc)
                for p in progress(proxies, "surface graph cuts")
            ]
        with timer.stage("ground"):
            gtex = None
            if proxies:
                grid = _ground_grid(inputs.scene, proxies, options.ground_gsd_m)
                gz = inputs.ground(grid)
                gtex = ground_cut(grid, gz, cameras, images, scene_rc, options.overlap_m)
                rings = [
                    ring_cut(
                        gtex, *_ring_inputs(gtex, p, t), cameras, images, scene_rc, options.ring_m
                    )
                    for p, t in zip(proxies, textures, strict=True)
                ]
                gtex.record["ring_texels"] = int(sum(r["ring_texels"] for r in rings))
                gtex.record["ring_from_building"] = int(sum(r["from_building"] for r in rings))
        with timer.stage("write"):
            record = _write(tmp, proxies, textures, gtex, options)
        record.update(
            {
                "scene": str(Path(scene_dir).resolve()),
                "footprints": inputs.footprint_source,
                "fusion": str(Path(fusion_dir).resolve()) if fusion_dir else None,
                "ground_model": inputs.ground.source,
                "skipped": inputs.skipped,
            }
        )
        record["counts"]["skipped"] = len(inputs.skipped)
        record["counts"]["footprints"] = inputs.footprint_count
        record["stages"] = timer.stages
        n = max(len(proxies), 1)
        record["seconds_per_building"] = round((time.perf_counter() - t_start) / n, 3)
        record["peak_memory_mb"] = round(peak_memory_mb(), 1)
        (tmp / "model.json").write_text(json.dumps(record, indent=1))
    return record


@dataclass
class VoxelInputs:
    """What the voxel path reads: the scene, its views, the usable footprints (each with
    its ground height and over-estimated height) and the ground model."""

    scene: Scene
    cameras: list
    images: ViewImages
    ground: _Ground
    buildings: list  # (Footprint, base_z, height)
    skipped: list[dict]
    footprint_source: str
    footprint_count: int
    fused_ndsm: tuple | None = None  # (ndsm, grid) of the fusion run, if any


def read_inputs(
    scene_dir: Path,
    options: VoxelOptions,
    footprints: Path | None = None,
    fusion_dir: Path | None = None,
    ground_z: float | None = None,
    default_height: float = 35.0,
) -> VoxelInputs:
    """Read and check the scene, footprints and ground; skip unusable footprints with a
    warning that names them."""
    scene = load_scene(scene_dir)
    cameras = [v.camera for v in scene.views]
    images = ViewImages(scene.views, features=options.consistency)
    fusion = _read_fusion(fusion_dir) if fusion_dir else None
    items, source = _footprints(scene, footprints, fusion)
    ground = _ground_model(scene, fusion, ground_z)
    kept, skipped = _usable(items, cameras, ground, default_height)
    fused_ndsm = (fusion["ndsm"], fusion["grid"]) if fusion else None
    return VoxelInputs(
        scene, cameras, images, ground, kept, skipped, source, len(items), fused_ndsm
    )


def build_proxies(inputs: VoxelInputs, options: VoxelOptions) -> list[Proxy]:
    """Section 4 for every usable footprint, each with the initial proxies of its
    neighbours as occlusion masks; footprints without a consistent roof are skipped."""
    kept = inputs.buildings
    prisms = {f.id: _prism(f.polygon, base, h) for f, base, h in kept}
    proxies: list[Proxy] = []
    for f, base, h in progress(kept, "voxel proxies"):
        occluders = _neighbours(f, kept, prisms)
        p = building_proxy(
            f.id, f.polygon, h, base, inputs.cameras, inputs.images, options, occluders,
            inputs.fused_ndsm,
        )  # fmt: skip
        p.record["height_source"] = f.properties.get("_height_source", "GIS")
        p.record["gis_footprint"] = mapping(f.polygon)
        if p.empty:
            inputs.skipped.append({"id": f.id, "reason": "no photo-consistent roof"})
            log.warning("footprint %s: no photo-consistent roof, skipped", f.id)
            continue
        proxies.append(p)
    return proxies


def _read_fusion(folder: Path) -> dict:
    out = {}
    for name in ("dtm", "class", "ndsm"):
        path = Path(folder) / f"{name}.tif"
        if not path.exists():
            raise InputError(path, None, "missing: not the output folder of `workbench fusion`")
        data, grid, crs = read_raster(path)
        out[name] = data[0]
        out["grid"], out["crs"] = grid, crs
    return out


def _footprints(
    scene: Scene, path: Path | None, fusion: dict | None
) -> tuple[list[Footprint], str]:
    path = path or scene.footprints
    if path is not None:
        return read_footprints(path), str(path)
    if fusion is None:
        raise InputError(
            scene.scene_json, "footprints", "no footprints: pass --footprints or --fusion"
        )
    return footprints_from_fusion(fusion), "fusion building mask"


def footprints_from_fusion(fusion: dict, min_area_m2: float = 20.0) -> list[Footprint]:
    """Footprints from a fusion run's building class: one per connected region, its
    height 1.5 times its 99th-percentile nDSM (over-estimated, as GIS heights are)."""
    grid: Grid = fusion["grid"]
    mask = fusion["class"] == 4
    out = []
    for geom, _ in rasterio.features.shapes(
        mask.astype(np.uint8), mask=mask, transform=grid.transform, connectivity=4
    ):
        poly = shapely.geometry.shape(geom).simplify(grid.gsd)
        if poly.area < min_area_m2:
            continue
        inside = rasterio.features.geometry_mask([geom], grid.shape, grid.transform, invert=True)
        h = (
            np.nanpercentile(fusion["ndsm"][inside], 99)
            if np.isfinite(fusion["ndsm"][inside]).any()
            else np.nan
        )
        if not np.isfinite(h) or h <= 0:
            continue
        fid = str(len(out) + 1)
        out.append(Footprint(fid, poly, float(1.5 * h), {"_height_source": "fusion nDSM x 1.5"}))
    return out


class _Ground:
    """Ground height: the fusion's DTM, the scene's DTM, or a flat plane."""

    def __init__(self, source: str, z=None, grid: Grid | None = None, flat: float | None = None):
        self.source, self.z, self.grid, self.flat = source, z, grid, flat

    def under(self, polygon: Polygon) -> float:
        """Median ground height under a footprint, metres."""
        if self.z is None:
            return float(self.flat)
        inside = rasterio.features.geometry_mask(
            [mapping(polygon)], self.grid.shape, self.grid.transform, invert=True, all_touched=True
        )
        vals = self.z[inside]
        vals = vals[np.isfinite(vals)]
        if not len(vals):  # off the raster: the nearest known ground
            c = polygon.centroid
            r, cc = self.grid.cell_index(np.array([c.x]), np.array([c.y]), clip=True)
            known = np.argwhere(np.isfinite(self.z))
            j = np.argmin(np.hypot(known[:, 0] - r[0], known[:, 1] - cc[0]))
            return float(self.z[tuple(known[j])])
        return float(np.median(vals))

    def __call__(self, grid: Grid) -> np.ndarray:
        """Ground height at the cell centres of ``grid``."""
        if self.z is None:
            return np.full(grid.shape, float(self.flat))
        X, Y = grid.cell_centers()
        r, c = self.grid.cell_index(X.ravel(), Y.ravel(), clip=True)
        z = self.z[r, c].reshape(grid.shape)
        if np.isfinite(z).any():
            z = np.where(np.isfinite(z), z, np.nanmedian(z))
        return z


def _ground_model(scene: Scene, fusion: dict | None, ground_z: float | None) -> _Ground:
    if fusion is not None:
        return _Ground("fusion DTM", fusion["dtm"], fusion["grid"])
    if scene.dtm is not None:
        z, grid, _ = read_raster(scene.dtm)
        return _Ground("scene DTM", z[0], grid)
    if ground_z is not None:
        return _Ground("flat plane (--ground-z)", flat=ground_z)
    z = flat_ground_from_depth(scene)
    if z is None:
        raise InputError(
            scene.scene_json,
            "dtm",
            "no ground: pass --fusion or --ground-z, or give the scene a dtm",
        )
    return _Ground("flat plane (depth maps)", flat=z)


def flat_ground_from_depth(scene: Scene, step: int = 8) -> float | None:
    """A flat ground plane from the most downward-looking views' depth maps: the median
    of the lowest fifth of the points they see, metres. None without depth maps."""
    heights = []
    for view in scene.views:
        if view.depth_path is None or -view.camera.viewing_direction[2] < 0.95:
            continue
        depth = view.read_depth()[::step, ::step]
        origin, dirs = view.camera.pixel_grid_rays(step)
        z = origin[2] + depth.ravel() * dirs[:, 2]
        heights.append(z[np.isfinite(z)])
    if not heights:
        return None
    z = np.concatenate(heights)
    return float(np.median(z[z <= np.quantile(z, 0.2)]))


def _usable(items, cameras, ground: _Ground, default_height: float):
    kept, skipped = [], []
    for f in items:
        if not f.polygon.is_valid:
            log.warning("footprint %s: self-intersecting polygon, skipped", f.id)
            skipped.append({"id": f.id, "reason": "self-intersecting polygon"})
            continue
        poly = (
            f.polygon
            if isinstance(f.polygon, Polygon)
            else max(f.polygon.geoms, key=lambda g: g.area)
        )
        base = ground.under(poly)
        if f.height is None:
            f.properties["_height_source"] = "zonal default"
        h = f.height if f.height is not None else default_height
        c = np.array([[*poly.centroid.coords[0], base]])
        seen = 0
        for cam in cameras:
            uv, _ = cam.project(c)
            seen += bool(
                np.all(np.isfinite(uv)) and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height
            )
        if seen < 2:
            log.warning("footprint %s: outside the images (seen by %d views), skipped", f.id, seen)
            skipped.append({"id": f.id, "reason": f"seen by {seen} views"})
            continue
        kept.append((Footprint(f.id, poly, h, f.properties), base, h))
    return kept, skipped


def _prism(polygon: Polygon, base: float, height: float):
    return extrude_faces([polygon], [np.array([0.0, 0.0, 1.0, -(base + height)])], base)


def _neighbours(f: Footprint, kept, prisms):
    """The ray-casting scene of the initial proxies of the buildings near ``f``."""
    reach = 2.0 * max(h for _, _, h in kept)
    near = [
        prisms[g.id] for g, _, _ in kept if g.id != f.id and g.polygon.distance(f.polygon) <= reach
    ]
    if not near:
        return None
    V, T, _ = concatenate_meshes(near)
    return raycasting_scene(V, T)


def _ground_grid(scene: Scene, proxies: list[Proxy], gsd: float) -> Grid:
    if scene.bounds is not None:
        return Grid.from_bounds(*scene.bounds, gsd)
    xy = np.vstack([p.vertices[:, :2] for p in proxies])
    lo, hi = xy.min(axis=0) - 20.0, xy.max(axis=0) + 20.0
    return Grid.from_bounds(lo[0], lo[1], hi[0], hi[1], gsd)


def _ring_inputs(gtex: GroundTexture, proxy: Proxy, tex: Texture):
    grid = gtex.grid
    footprint = rasterio.features.geometry_mask(
        [mapping(proxy.outline)], grid.shape, grid.transform, invert=True
    )
    g = tex.graph
    low = (np.abs(g.normals[:, 2]) < 0.5) & (g.positions[:, 2] < proxy.frame.base_z + _WALL_FOOT_M)
    low &= tex.stitched.labels >= 0
    wall_view = np.full(grid.shape, -1)
    if low.any():
        X, Y = grid.cell_centers()
        _, j = cKDTree(g.positions[low, :2]).query(np.column_stack([X.ravel(), Y.ravel()]))
        wall_view = tex.stitched.labels[low][j].reshape(grid.shape)
    return footprint, wall_view


def _write(tmp: Path, proxies, textures, gtex, options: VoxelOptions) -> dict:
    bdir = tmp / "buildings"
    bdir.mkdir()
    buildings, parts, colours, runs, mtl, maps = [], [], [], [], {}, {}
    for p, t in zip(proxies, textures, strict=True):
        bid = p.id
        write_rgb(bdir / f"{bid}.png", t.image)
        write_mtl(
            bdir / f"{bid}.mtl",
            {f"building_{bid}": (255, 255, 255)},
            {f"building_{bid}": f"{bid}.png"},
        )
        write_obj(
            bdir / f"{bid}.obj",
            p.vertices,
            p.triangles,
            material=f"building_{bid}",
            mtllib=f"{bid}.mtl",
            uvs=t.uvs,
        )
        vc = _vertex_colours(p.vertices, t)
        write_ply(bdir / f"{bid}.ply", p.vertices, p.triangles, vertex_colors=vc)
        parts.append((p.vertices, p.triangles, t.uvs))
        colours.append(vc)
        runs.append((f"building_{bid}", len(p.triangles)))
        mtl[f"building_{bid}"] = (255, 255, 255)
        maps[f"building_{bid}"] = f"buildings/{bid}.png"
        rec = dict(p.record)
        rec.update(t.record)
        rec["mesh"] = f"buildings/{bid}.obj"
        rec["footprint"] = mapping(p.outline) if p.outline is not None else None
        rec["watertight"] = is_watertight(p.vertices, p.triangles)
        rec["peak_memory_mb"] = round(peak_memory_mb(), 1)
        buildings.append(rec)
    ground_record = None
    if gtex is not None:
        write_rgb(tmp / "ground.png", gtex.image)
        gm = ground_mesh(gtex)
        if gm is not None:
            gv, gt, guv = gm
            write_mtl(tmp / "ground.mtl", {"ground": (255, 255, 255)}, {"ground": "ground.png"})
            write_obj(tmp / "ground.obj", gv, gt, material="ground", mtllib="ground.mtl", uvs=guv)
            r, c = gtex.grid.cell_index(gv[:, 0], gv[:, 1], clip=True)
            parts.append((gv, gt, guv))
            colours.append(gtex.image[r, c])
            runs.append(("ground", len(gt)))
            mtl["ground"] = (255, 255, 255)
            maps["ground"] = "ground.png"
        ground_record = gtex.record
    V, T, _ = concatenate_meshes([(v, t) for v, t, _ in parts])
    uvs = np.concatenate([u for _, _, u in parts]) if parts else np.zeros((0, 3, 2))
    C = np.concatenate(colours) if colours else np.zeros((0, 3), np.uint8)
    write_mtl(tmp / "scene.mtl", mtl, maps)
    write_obj(tmp / "scene.obj", V, T, material=runs, mtllib="scene.mtl", uvs=uvs)
    write_ply(tmp / "scene.ply", V, T, vertex_colors=C)
    _preview(tmp / "preview.png", proxies, textures, gtex)
    seam, seam_p, seam_g = (
        [b[key] for b in buildings if np.isfinite(b[key])]
        for key in ("seam_cost", "seam_cost_projective", "seam_cost_greedy")
    )
    return {
        "method": "voxel",
        "parameters": asdict(options),
        "buildings": buildings,
        "ground": ground_record,
        "texture": {
            "seam_cost": round(float(np.mean(seam)), 4) if seam else None,
            "seam_cost_projective": round(float(np.mean(seam_p)), 4) if seam_p else None,
            "seam_cost_greedy": round(float(np.mean(seam_g)), 4) if seam_g else None,
        },
        "counts": {
            "buildings": len(buildings),
            "faces": int(sum(b["faces"] for b in buildings)),
            "watertight": int(sum(b["watertight"] for b in buildings)),
        },
    }


def _vertex_colours(vertices: np.ndarray, tex: Texture) -> np.ndarray:
    """Each mesh vertex takes the median colour of the texels within a voxel of it."""
    g = tex.graph
    colours = tex.colours()
    seen = tex.stitched.labels >= 0
    out = np.full((len(vertices), 3), 128, np.uint8)
    if not seen.any():
        return out
    tree = cKDTree(g.positions[seen])
    near = tree.query_ball_point(vertices, r=4 * g.texel_m)
    for i, idx in enumerate(near):  # a few dozen mesh corners per building
        if idx:
            out[i] = np.median(colours[seen][idx], axis=0)
    return out


def _preview(path: Path, proxies, textures, gtex) -> None:
    if not proxies:
        write_rgb(path, np.full((64, 64, 3), 255, np.uint8))
        return
    big = max(range(len(proxies)), key=lambda i: proxies[i].columns.sum())
    p, t = proxies[big], textures[big]
    nx, ny, nz = p.frame.shape
    var = p.variance[:, ny // 2, :].T[::-1]  # vertical slice, up is up
    var_img = colorize_height(np.log10(np.where(np.isfinite(var), var, np.nan) + 1e-6))
    horiz = p.variance[
        :,
        :,
        min(nz - 1, int(round(p.level_heights.max() / p.frame.r)) if len(p.level_heights) else 0),
    ]
    horiz_img = colorize_height(np.log10(horiz.T[::-1] + 1e-6))
    top = float(np.nanmax(p.min_height)) if np.isfinite(p.min_height).any() else 1.0
    before = _height_image(p.min_height, top)
    after = _height_image(np.concatenate([[np.nan], p.level_heights])[p.levels], top)
    row1 = [
        (_upscale(var_img), f"building {p.id}: variance, vertical slice"),
        (_upscale(horiz_img), "variance at the roof"),
        (_upscale(before), "most consistent heights"),
        (_upscale(after), "after clustering"),
    ]
    top_before = _top_labels(p, t, t.initial)
    top_after = _top_labels(p, t, t.stitched.labels)
    render = render_textured(proxies, textures, gtex)
    row2 = [
        (top_before, "roof views: best per texel"),
        (top_after, "after graph cuts"),
        (render, "textured proxies"),
    ]
    if gtex is not None:
        row2.append((gtex.image, "ground texture"))
    write_rgb(path, contact_sheet([row1, row2]))


def _upscale(img: np.ndarray, size: int = 240) -> np.ndarray:
    h, w = img.shape[:2]
    f = max(1, size // max(h, w))
    return cv2.resize(img, (w * f, h * f), interpolation=cv2.INTER_NEAREST)


def _height_image(z: np.ndarray, top: float) -> np.ndarray:
    """A column height map (nx, ny) in turbo colours from 0 to ``top`` metres, north up."""
    g = np.clip(np.nan_to_num(z.T[::-1], nan=0.0) / max(top, 1e-6) * 255, 0, 255)
    rgb = cv2.cvtColor(cv2.applyColorMap(g.astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[~np.isfinite(z.T[::-1])] = 0
    return rgb


def _top_labels(proxy: Proxy, tex: Texture, labels: np.ndarray) -> np.ndarray:
    """Roof texels coloured by view, top-down in the building's own frame."""
    g = tex.graph
    roof = (g.normals[:, 2] > 0.9) & (labels >= 0)
    palette = np.random.default_rng(0).integers(40, 255, (int(labels.max()) + 2, 3))
    if not roof.any():
        return np.full((64, 64, 3), 255, np.uint8)
    local = proxy.frame.to_local_xy(g.positions[roof, :2])
    ij = np.round((local - local.min(axis=0)) / g.texel_m).astype(int)  # texel centres
    img = np.full((ij[:, 1].max() + 1, ij[:, 0].max() + 1, 3), 255, np.uint8)
    img[ij[:, 1].max() - ij[:, 1], ij[:, 0]] = palette[labels[roof]].astype(np.uint8)
    return _upscale(img, 240)


def render_textured(
    proxies: list[Proxy], textures: list[Texture], gtex, width: int = 640
) -> np.ndarray:
    """Ray-cast picture of the textured proxies (and ground) from the south-west: each
    pixel's hit is looked up in its mesh's atlas through the interpolated UVs."""
    parts = [
        (p.vertices, p.triangles, t.uvs, t.image) for p, t in zip(proxies, textures, strict=True)
    ]
    gm = ground_mesh(gtex) if gtex is not None else None
    if gm is not None:
        parts.append((*gm, gtex.image))
    V, T, owner = concatenate_meshes([(v, t) for v, t, _, _ in parts])
    uvs = np.concatenate([u for _, _, u, _ in parts])
    xy = np.vstack([p.vertices[:, :2] for p in proxies])
    bounds = (*xy.min(axis=0), *xy.max(axis=0))
    cam = viewpoints(bounds, (float(V[:, 2].min()), float(V[:, 2].max())), width, width * 3 // 4)[
        "south-west"
    ]
    origin, dirs = cam.pixel_grid_rays()
    hits = cast(raycasting_scene(V, T), origin, dirs)
    img = np.full((cam.height * cam.width, 3), 255, np.uint8)
    for i, (_, _, _, atlas_img) in enumerate(parts):
        sel = np.flatnonzero((hits.tri >= 0) & (owner[np.maximum(hits.tri, 0)] == i + 1))
        if not len(sel):
            continue
        corners = uvs[hits.tri[sel]]
        b = hits.bary[sel]
        uv = (
            (1 - b[:, :1] - b[:, 1:]) * corners[:, 0]
            + b[:, :1] * corners[:, 1]
            + b[:, 1:] * corners[:, 2]
        )
        h, w = atlas_img.shape[:2]
        c = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
        r = np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1)
        img[sel] = atlas_img[r, c]
    return img.reshape(cam.height, cam.width, 3)
