"""``workbench sample``: generate a synthetic city with full ground truth.

Deterministic for a preset and a seed: each part of the generator draws from
its own child of one :class:`numpy.random.SeedSequence`.
"""

from __future__ import annotations

import json
import logging
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import shapely
from rasterio.crs import CRS
from rasterio.features import rasterize

from workbench.atomic import atomic_output_dir
from workbench.footprints import footprints_geojson
from workbench.imageio import write_rgb
from workbench.meshio import write_ply
from workbench.pictures import colorize_classes, colorize_height, contact_sheet
from workbench.progress import progress
from workbench.raster import Grid, write_raster
from workbench.raycast import cast, vertical_hits
from workbench.scene import write_scene_json

from .depth import degrade_depth, depth_error_stats
from .gis import gis_footprint
from .layout import make_layout
from .preset_names import preset_index
from .presets import PRESETS, Preset
from .relocate import relocate_sample
from .render import Exposure, render_view, shade
from .rig import camera_rig, ground_margin, perturb_pose, reprojection_rms
from .shading import tone_map
from .strokes import paint_strokes
from .terrain import Terrain
from .world import build_world

log = logging.getLogger(__name__)

GENERATOR_VERSION = 1
# A local transverse Mercator centred on the site keeps coordinates small, so that
# float32 ray casting stays at sub-millimetre precision.
SAMPLE_CRS = CRS.from_proj4(
    "+proj=tmerc +lat_0=52.0 +lon_0=4.37 +k=1 +x_0=0 +y_0=0 +ellps=GRS80 +units=m +no_defs"
)
_STREAMS = ("terrain", "layout", "materials", "rig", "sun", "views", "gis", "strokes", "calib")


def generate_sample(
    out: str | Path,
    preset: str | Preset = "tiny",
    seed: int = 0,
    *,
    overwrite: bool = False,
    origin: tuple[float, float] | None = None,
    crs: CRS | None = None,
) -> dict:
    """Generate a synthetic city scene with ground truth into ``out``.

    Parameters
    ----------
    out : path
        Output scene folder (written atomically).
    preset : str or Preset
        ``tiny``, ``small``, ``city`` or a customised :class:`Preset`.
    seed : int
        Seed of every random choice.
    overwrite : bool
        Replace ``out`` if it exists.
    origin : (E, N), optional
        Write the city there, metres, labelled ``crs`` (:mod:`data_samples.relocate`): the
        same city far from its CRS's zero, as real data is.
    crs : CRS, optional
        With ``origin``: the CRS to name (default: the sample's own).

    Returns
    -------
    dict
        The content of ``sample.json`` plus ``timing`` (seconds per stage).
    """
    p = PRESETS[preset] if isinstance(preset, str) else preset
    if not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    streams = np.random.SeedSequence([seed, preset_index(p.name)]).spawn(len(_STREAMS))
    rng = {name: np.random.default_rng(s) for name, s in zip(_STREAMS, streams, strict=True)}
    timing = {}
    t0 = time.perf_counter()

    terrain = Terrain.random(rng["terrain"], p.terrain_slope, p.terrain_relief)
    layout = make_layout(p, rng["layout"])
    ground_z = float(terrain.height(0.0, 0.0))
    cams = camera_rig(p, ground_z, rng["rig"])
    half = p.size / 2
    margin = ground_margin([c for _, c in cams], ground_z, 4.0 * p.flying_height, half)
    world = build_world(layout, terrain, margin, rng["materials"])
    scene = world.raycasting_scene()
    sun = _sun_direction(rng["sun"])
    timing["world"] = time.perf_counter() - t0
    log.info(
        "world: %d buildings, %d trees, %d triangles",
        len(layout.buildings),
        len(layout.trees),
        len(world.triangles),
    )

    grid = Grid.from_bounds(-half, -half, half, half, p.gsd)
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        t = time.perf_counter()
        truth = _truth_rasters(world, scene, grid, sun)
        (tmp / "truth").mkdir()
        for name, arr in truth.items():
            write_raster(
                tmp / "truth" / f"{name}.tif",
                arr,
                grid,
                SAMPLE_CRS,
                nodata=0 if name in ("class", "building_id") else None,
            )
        timing["truth_rasters"] = time.perf_counter() - t

        t = time.perf_counter()
        views, calib, shown, depth_quality = _render_views(tmp, world, scene, cams, sun, p, rng)
        timing["views"] = time.perf_counter() - t

        t = time.perf_counter()
        buildings = _buildings_json(layout, world)
        _write_json(
            tmp / "truth" / "buildings.json", {"crs": "see scene.json", "buildings": buildings}
        )
        gis = _gis(layout, buildings, rng["gis"])
        _write_json(tmp / "footprints_gis.geojson", footprints_geojson(gis, SAMPLE_CRS))
        truth_fp = [
            {
                "id": b["id"],
                "polygon": spec.footprint,
                "properties": {"height": b["height"], "roof_type": b["roof_type"]},
            }
            for b, spec in zip(buildings, layout.buildings, strict=True)
        ]
        _write_json(tmp / "truth" / "footprints.geojson", footprints_geojson(truth_fp, SAMPLE_CRS))
        (tmp / "training").mkdir()
        labels = paint_strokes(truth["class"], p.gsd, rng["strokes"])
        write_raster(tmp / "training" / "labels.tif", labels, grid, SAMPLE_CRS, nodata=0)
        write_ply(
            tmp / "truth" / "mesh.ply",
            world.vertices,
            world.triangles,
            face_properties={"class": world.cls, "building_id": world.building},
        )
        _write_json(
            tmp / "truth" / "cameras.json",
            {"note": "true poses used for rendering", "cameras": calib["true"]},
        )
        timing["truth_files"] = time.perf_counter() - t

        write_scene_json(
            tmp,
            crs=SAMPLE_CRS,
            views=views,
            bounds=list(grid.bounds),
            gsd=p.gsd,
            footprints="footprints_gis.geojson",
            training_labels="training/labels.tif",
            truth="truth",
        )
        meta = {
            "generator": "city-workbench synthetic city",
            "generator_version": GENERATOR_VERSION,
            "preset": p.to_dict(),
            "seed": seed,
            "terrain": terrain.to_dict(),
            "sun_direction": np.round(sun, 6).tolist(),
            "counts": {
                "buildings": len(layout.buildings),
                "trees": len(layout.trees),
                "views": len(views),
                "triangles": int(len(world.triangles)),
                "roof_types": _count(b["roof_type"] for b in buildings),
                "shapes": _count(b["shape"] for b in buildings),
            },
            "calibration_error_px_rms": round(float(np.sqrt(np.mean(np.square(calib["rms"])))), 4),
            "depth_maps_median_over_views": depth_quality,
            "gis_footprints": _gis_stats(gis, layout),
            "class_fractions": {
                n: round(float(np.mean(truth["class"] == c)), 4)
                for c, n in ((1, "ground"), (2, "grass"), (3, "tree"), (4, "building"))
            },
            "training_label_fraction": round(float(np.mean(labels > 0)), 4),
            "coverage": _coverage(cams, truth["dsm"], grid, p),
        }
        _write_json(tmp / "sample.json", meta)
        sheet = _preview(shown, truth, labels, gis, grid)
        write_rgb(tmp / "preview.png", sheet)
        if origin is not None:
            relocate_sample(tmp, origin, crs or SAMPLE_CRS)
    timing["total"] = time.perf_counter() - t0
    meta["timing"] = timing
    return meta


def _sun_direction(rng) -> np.ndarray:
    elev = np.radians(rng.uniform(38.0, 55.0))
    az = np.radians(rng.uniform(110.0, 250.0))  # from the south-east to the south-west
    return np.array([np.sin(az) * np.cos(elev), np.cos(az) * np.cos(elev), np.sin(elev)])


def _truth_rasters(world, scene, grid: Grid, sun) -> dict:
    z_top = float(world.vertices[:, 2].max() + 10.0)
    hits = vertical_hits(scene, grid, z_top)
    hit = hits.tri >= 0
    dsm = np.where(hit, hits.points[:, 2], np.nan).astype(np.float32).reshape(grid.shape)
    tri = np.where(hit, hits.tri, 0)
    cls = np.where(hit, world.cls[tri], 0).astype(np.uint8).reshape(grid.shape)
    bid = np.where(hit, world.building[tri], 0).astype(np.int32).reshape(grid.shape)
    rad, _ = shade(world, scene, hits, sun)
    ortho = np.round(tone_map(rad)).astype(np.uint8).reshape(*grid.shape, 3)
    ground = world.raycasting_scene(mask=world.cls <= 2)
    g = vertical_hits(ground, grid, z_top)
    dtm = np.where(g.tri >= 0, g.points[:, 2], np.nan).astype(np.float32).reshape(grid.shape)
    return {
        "ortho": np.moveaxis(ortho, -1, 0),
        "dsm": dsm,
        "dtm": dtm,
        "class": cls,
        "building_id": bid,
    }


def _render_views(tmp: Path, world, scene, cams, sun, p: Preset, rng):
    (tmp / "images").mkdir()
    (tmp / "depth").mkdir()
    views, true_poses, rms, shown, depth_stats = [], [], [], [], []
    side = np.linspace(-p.size / 2, p.size / 2, 25)
    X, Y = np.meshgrid(side, side)
    probe = cast(
        scene,
        np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 1e4)]),
        np.tile([0.0, 0.0, -1.0], (X.size, 1)),
    ).points
    probe = probe[np.isfinite(probe[:, 0])]
    view_seeds = rng["views"].spawn(len(cams))
    nx, ny = p.grid
    # the preview: the central nadir view, and obliques that look into the area
    preview = (
        f"v{(ny // 2) * nx + nx // 2:03d}_n",
        f"v{(ny // 2) * nx:03d}_E",
        f"v{(ny - 1) * nx + nx // 2:03d}_S",
    )
    for (name, cam), vs in progress(list(zip(cams, view_seeds, strict=True)), "rendering views"):
        vr = np.random.default_rng(vs)
        exposure = Exposure(
            gain=float(vr.uniform(0.85, 1.15)),
            balance=tuple(vr.uniform(0.95, 1.05, 3)),
            vignetting=float(vr.uniform(0.1, 0.25)),
            noise=1.5,
            blur=0.6,
        )
        r = render_view(world, scene, cam, sun, exposure, vr)
        gray = cv2.cvtColor(r.rgb, cv2.COLOR_RGB2GRAY)
        if p.depth_matching:
            depth = degrade_depth(
                r.depth,
                gray,
                r.lit,
                vr,
                sigma=p.depth_sigma,
                reference_depth=p.flying_height,
                outliers=p.depth_outliers,
                round_edges=p.depth_round_edges,
            )
        else:
            depth = r.depth.astype(np.float32)
        depth_stats.append(
            depth_error_stats(depth, r.depth, sigma=p.depth_sigma, reference_depth=p.flying_height)
        )
        write_rgb(tmp / "images" / f"{name}.png", r.rgb)
        np.save(tmp / "depth" / f"{name}.npy", depth)
        written = perturb_pose(cam, p.calibration_error_px, p.flying_height, rng["calib"], probe)
        rms.append(reprojection_rms(cam, written, probe))
        views.append(
            {
                "id": name,
                "file": f"images/{name}.png",
                **written.to_dict(),
                "depth": f"depth/{name}.npy",
            }
        )
        true_poses.append({"id": name, **cam.to_dict()})
        if name in preview:
            shown.append((r.rgb, name))
    calib = {"true": true_poses, "rms": [x for x in rms if np.isfinite(x)]}
    depth = {k: round(float(np.median([d[k] for d in depth_stats])), 4) for k in depth_stats[0]}
    return views, calib, shown, depth


def _buildings_json(layout, world) -> list[dict]:
    out = []
    for spec in layout.buildings:
        m = world.building == spec.id
        z = world.vertices[world.triangles[m & (world.cls == 4)].ravel(), 2]
        ridge = float(z.max())
        out.append(
            {
                "id": spec.id,
                "shape": spec.shape,
                "roof_type": spec.roof_type,
                "rotated": spec.rotated,
                "footprint": [
                    list(map(list, np.round(np.asarray(r.coords), 4)))
                    for r in [spec.footprint.exterior, *spec.footprint.interiors]
                ],
                "area_m2": round(spec.footprint.area, 3),
                "base_z": round(spec.base_z, 4),
                "eave_z": round(spec.base_z + spec.eave, 4),
                "ridge_z": round(ridge, 4),
                "height": round(ridge - spec.base_z, 4),
                "pitch_deg": round(spec.pitch, 3)
                if spec.roof_type not in ("flat", "multi-level")
                else 0.0,
                "wings": [
                    {
                        "center": [round(w.cx, 4), round(w.cy, 4)],
                        "half_length": round(w.a, 4),
                        "half_width": round(w.b, 4),
                        "angle_deg": round(np.degrees(w.angle), 4),
                    }
                    for w in spec.wings
                ],
                "levels": [round(spec.base_z + spec.eave, 4)]
                + [round(spec.base_z + h, 4) for _, h in spec.tiers],
                "triangles": int(m.sum()),
            }
        )
    return out


def _gis(layout, buildings, rng) -> list[dict]:
    out = []
    for spec, b in zip(layout.buildings, buildings, strict=True):
        poly, height, info = gis_footprint(spec.footprint, b["height"], rng)
        out.append(
            {
                "id": b["id"],
                "polygon": poly,
                "properties": {"height": height, "source": "synthetic GIS", **info},
            }
        )
    return out


def _gis_stats(gis: list[dict], layout) -> dict:
    """Medians of how far the GIS footprints are from the true ones."""
    shift = [
        g["polygon"].centroid.distance(b.footprint.centroid)
        for g, b in zip(gis, layout.buildings, strict=True)
    ]
    haus = [
        g["polygon"].hausdorff_distance(b.footprint)
        for g, b in zip(gis, layout.buildings, strict=True)
    ]
    iou = [
        g["polygon"].intersection(b.footprint).area / g["polygon"].union(b.footprint).area
        for g, b in zip(gis, layout.buildings, strict=True)
    ]
    factor = [g["properties"]["height_factor"] for g in gis]
    if not gis:
        return {}
    return {
        "centroid_shift_m": round(float(np.median(shift)), 3),
        "hausdorff_m": round(float(np.median(haus)), 3),
        "iou": round(float(np.median(iou)), 4),
        "height_factor": round(float(np.median(factor)), 3),
    }


def _coverage(cams, dsm: np.ndarray, grid: Grid, p: Preset) -> dict:
    """Overlap figures: nadir forward/side overlap, and how many views see each cell
    (ignoring occlusion)."""
    X, Y = grid.cell_centers()
    step = max(1, int(np.ceil(np.sqrt(X.size / 250_000))))  # a statistic: a sample of cells
    X, Y, Z = X[::step, ::step], Y[::step, ::step], dsm[::step, ::step]
    pts = np.column_stack([X.ravel(), Y.ravel(), np.nan_to_num(Z.ravel(), nan=0.0)])
    nadir = np.zeros(len(pts), int)
    any_view = np.zeros(len(pts), int)
    for name, cam in cams:
        uv, d = cam.project(pts)
        inside = (d > 0) & np.all((uv >= 0) & (uv <= [cam.width - 1, cam.height - 1]), axis=1)
        any_view += inside
        if name.endswith("_n"):
            nadir += inside
    w, h = p.image_size
    footprint = np.array([w, h]) * p.flying_height / p.focal_px  # nadir image on flat ground, m
    overlap = [
        round(float(1 - p.spacing[i] / footprint[i]), 4) if p.grid[i] > 1 else None for i in (0, 1)
    ]
    return {
        "nadir_overlap_x": overlap[0],
        "nadir_overlap_y": overlap[1],
        "cells_seen_by_2_nadir_views": round(float(np.mean(nadir >= 2)), 4),
        "median_views_per_cell": float(np.median(any_view)),
        "cells_seen_by_no_view": round(float(np.mean(any_view == 0)), 4),
    }


def _preview(shown, truth, labels, gis, grid: Grid) -> np.ndarray:
    ortho = np.ascontiguousarray(np.moveaxis(truth["ortho"], 0, -1))
    outlines = ortho.copy()
    polys = [g["polygon"].exterior for g in gis]
    if polys:
        mask = rasterize(
            [(shapely.buffer(p, grid.gsd), 1) for p in polys],
            out_shape=grid.shape,
            transform=grid.transform,
            fill=0,
            dtype="uint8",
        )
        outlines[mask > 0] = (255, 255, 0)
    strokes = colorize_classes(truth["class"]) // 3
    strokes[labels > 0] = colorize_classes(labels)[labels > 0]
    return contact_sheet(
        [
            list(shown),
            [
                (outlines, "true ortho + GIS footprints"),
                (colorize_classes(truth["class"]), "true classes"),
                (colorize_height(truth["dsm"]), "true DSM"),
                (strokes, "training strokes"),
            ],
        ]
    )


def _count(items) -> dict:
    return dict(sorted(Counter(items).items()))


def _write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1) + "\n")
