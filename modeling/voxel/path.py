"""The voxel path end to end: a scene and its footprints in, a :class:`ModelRun` out.

The steps of the paper, each in the module named after it: :mod:`.proxy` (section 4:
voxelisation, photo-consistency, height clustering, the proxy mesh),
:mod:`.surface_graph` (5.1-5.2: the surface graph and its cuts), :mod:`.texture_atlas`,
:mod:`.ground_texture` (5.3-5.4: the ground and ring cuts); :mod:`.building` runs them
for one building, :mod:`.inputs` reads what they need. This module orders and times them.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import rasterio.features
from scipy.spatial import cKDTree
from shapely.geometry import mapping

from workbench.meshes import concatenate_meshes
from workbench.model_run import Building, ModelRun, Surface, Texture
from workbench.progress import progress
from workbench.raster import Grid
from workbench.raycast import raycasting_scene
from workbench.records import StageTimer, peak_memory_mb
from workbench.scene import Scene

from .building import Proxy, building_proxy, texture_building
from .building import Texture as BuildingTexture
from .ground_texture import GroundTexture, ground_cut, ground_mesh, ring_cut
from .inputs import VoxelInputs, neighbour_scene, prism, read_inputs
from .options import VoxelOptions
from .preview import voxel_preview

log = logging.getLogger(__name__)

_WALL_FOOT_M = 1.0  # wall texels this close above the ground continue onto it (ring cut)
_COMMON = ("id", "base_z", "faces")  # proxy record keys model.json's common keys replace


def run_voxel(
    scene_dir: Path,
    options: VoxelOptions | None = None,
    *,
    footprints: Path | None = None,
    fusion_dir: Path | None = None,
) -> ModelRun:
    """The voxel path (Garcia-Dorado, Demir & Aliaga 2013) on a scene's images.

    Parameters
    ----------
    scene_dir : path
        A scene (scene.json) with calibrated views.
    options : VoxelOptions
    footprints : path, optional
        GeoJSON footprints with a height (default: the scene's; else the fusion's
        building regions).
    fusion_dir : path, optional
        A fusion run: its DTM is the ground, its nDSM marks ground columns and places
        flat roofs (see the options).
    """
    options = options or VoxelOptions()
    timer = StageTimer()
    t_start = time.perf_counter()
    with timer.stage("read"):
        inputs = read_inputs(scene_dir, options, footprints, fusion_dir)
    with timer.stage("proxies"):
        proxies = build_proxies(inputs, options)
        inputs.images.release_blurred()
    all_proxies = concatenate_meshes([(p.vertices, p.triangles) for p in proxies])
    scene_rc = raycasting_scene(*all_proxies[:2]) if proxies else None
    with timer.stage("textures"):
        textures = [
            texture_building(p, inputs.cameras, inputs.images, options, scene_rc)
            for p in progress(proxies, "surface graph cuts")
        ]
    with timer.stage("ground"):
        gtex, ground_z = texture_ground(inputs, proxies, textures, options, scene_rc)
    with timer.stage("preview"):
        preview = voxel_preview(proxies, textures, gtex)
    buildings = [voxel_building(p, t) for p, t in zip(proxies, textures, strict=True)]
    return ModelRun(
        "voxel", options, buildings, crs=inputs.scene.crs,
        grid=gtex.grid if gtex is not None else None, dtm=ground_z,
        ground=ground_surface(gtex), preview=preview, stages=timer.stages,
        inputs={
            "scene": str(Path(scene_dir).resolve()), "footprints": inputs.footprint_source,
            "fusion": str(Path(fusion_dir).resolve()) if fusion_dir else None,
            "ground_model": inputs.ground.source,
        },
        counts={"skipped": len(inputs.skipped), "footprints": inputs.footprint_count},
        record={
            "skipped": inputs.skipped, "ground": gtex.record if gtex is not None else None,
            "texture": texture_summary(textures),
            "seconds_per_building": round((time.perf_counter() - t_start) / max(len(proxies), 1),
                                          3),
            "peak_memory_mb": round(peak_memory_mb(), 1),
        },
    )  # fmt: skip


def build_proxies(inputs: VoxelInputs, options: VoxelOptions) -> list[Proxy]:
    """Section 4 for every usable footprint, each with the initial proxies of its
    neighbours as occlusion masks; footprints without a consistent roof are skipped."""
    kept = inputs.buildings
    prisms = {f.id: prism(f.polygon, base, h) for f, base, h in kept}
    proxies: list[Proxy] = []
    for f, base, h in progress(kept, "voxel proxies"):
        occluders = neighbour_scene(f, kept, prisms)
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


def texture_ground(
    inputs: VoxelInputs, proxies: list[Proxy], textures: list, options: VoxelOptions, scene_rc
) -> tuple[GroundTexture | None, np.ndarray | None]:
    """Sections 5.3-5.4: the ground cut with the proxies masked out, then the ring cut
    around each building; returns the ground texture and the ground heights on its grid."""
    if not proxies:
        return None, None
    grid = ground_grid(inputs.scene, proxies, options.ground_gsd_m)
    gz = inputs.ground(grid)
    cams, images = inputs.cameras, inputs.images
    gtex = ground_cut(grid, gz, cams, images, scene_rc, options.overlap_m)
    rings = [
        ring_cut(gtex, *ring_inputs(gtex, p, t), cams, images, scene_rc, options.ring_m)
        for p, t in zip(proxies, textures, strict=True)
    ]
    gtex.record["ring_texels"] = int(sum(r["ring_texels"] for r in rings))
    gtex.record["ring_from_building"] = int(sum(r["from_building"] for r in rings))
    return gtex, gz


def ground_grid(scene: Scene, proxies: list[Proxy], gsd: float) -> Grid:
    """The scene's bounds at ``gsd``, else the proxies' with 20 m around them."""
    if scene.bounds is not None:
        return Grid.from_bounds(*scene.bounds, gsd)
    xy = np.vstack([p.vertices[:, :2] for p in proxies])
    lo, hi = xy.min(axis=0) - 20.0, xy.max(axis=0) + 20.0
    return Grid.from_bounds(lo[0], lo[1], hi[0], hi[1], gsd)


def ring_inputs(gtex: GroundTexture, proxy: Proxy, tex: BuildingTexture):
    """The proxy's footprint on the ground grid, and for every ground cell the view of
    the nearest low wall texel (-1 where there is none)."""
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


def voxel_building(p: Proxy, t: BuildingTexture) -> Building:
    """A proxy and its texture as a building of the run: its roof model (one horizontal
    plane per roof level, LOD 1.3 in CityJSON's terms, or pitched planes, LOD 2.2) with the
    textured mesh."""
    m = p.model
    record = {k: v for k, v in p.record.items() if k not in _COMMON}
    record.update(m.record)
    record.update(t.record)
    mesh = Surface(p.vertices, p.triangles, vertex_colours(p.vertices, t), Texture(t.image, t.uvs))
    return replace(m, id=p.id, mesh=mesh, lod="2.2" if p.roof.pitched else "1.3",
                   watertight=None, record=record)  # fmt: skip


def vertex_colours(vertices: np.ndarray, tex: BuildingTexture) -> np.ndarray:
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


def ground_surface(gtex: GroundTexture | None) -> Surface | None:
    """The textured ground mesh, coloured by its texture at the vertices."""
    gm = ground_mesh(gtex) if gtex is not None else None
    if gm is None:
        return None
    gv, gt, guv = gm
    r, c = gtex.grid.cell_index(gv[:, 0], gv[:, 1], clip=True)
    return Surface(gv, gt, gtex.image[r, c], Texture(gtex.image, guv))


def texture_summary(textures: list[BuildingTexture]) -> dict:
    """Mean seam costs over the buildings (graph cut, projective, greedy before the
    refinement)."""
    out = {}
    for key in ("seam_cost", "seam_cost_projective", "seam_cost_greedy"):
        vals = [t.record[key] for t in textures if np.isfinite(t.record[key])]
        out[key] = round(float(np.mean(vals)), 4) if vals else None
    return out


def summary_lines(record: dict) -> list[str]:
    """What ``workbench model voxel`` prints beside the counts."""
    c, t = record["counts"], record["texture"]
    lines = [
        f"  {c['footprints']} footprints ({c['skipped']} skipped), "
        f"{record['seconds_per_building']:.2f} s per building"
    ]
    if t.get("seam_cost") is not None:
        lines.append(
            f"  seam cost {t['seam_cost']:.2f} (graph cut) vs "
            f"{t['seam_cost_projective']:.2f} (projective)"
        )
    return lines
