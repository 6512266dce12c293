"""The LOD path end to end: rasters of a fusion (from a mesh, best) in, a ModelRun out.

Each paper step is a function of its own module: :func:`.tree_probability.tree_probability`
(section 4.1), :func:`.labelling.mrf_labelling` (section 4.2), :func:`.facades.facade_directions`
(5.1), :func:`.segments.detect_segments` and :func:`.segments.regularise_segments` (5.2),
:func:`.shapes.roof_directions` and :func:`.shapes.roof_planes` (5.3),
:func:`.arrangement.arrangement_faces` and :func:`.arrangement.label_faces` (5.4), and the
LOD generation here (:func:`lod_models`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from fusion.planar_objects import COUNTS as PLANAR_COUNTS
from fusion.planar_objects import planar_roof_cells
from modeling.shared.opened_parts import mid_wall_region
from modeling.shared.raster_ground import dtm_across_holes, ground_surface, vertex_colours
from modeling.shared.roof_model import closed_roof_model
from workbench.errors import InputError, WorkbenchError
from workbench.fusion_run import read_fusion_run
from workbench.ground_grass_colours import fit_flat_colours, ground_factor
from workbench.model_run import Building, ModelRun
from workbench.pictures import colorize_classes, contact_sheet
from workbench.progress import progress
from workbench.raster import BUILDING, GRASS, GROUND, TREE, Grid, read_raster
from workbench.records import StageTimer, peak_memory_mb

from .arrangement import arrangement_faces, label_faces
from .facades import facade_directions, wall_normals
from .labelling import fill_from_below, fill_holes, mrf_labelling, open_close
from .options import LodOptions
from .segments import (
    detect_segments,
    direction_maps,
    outline_segments,
    regularise_segments,
)
from .shapes import roof_directions, roof_planes, z_symmetric
from .tree_probability import train_tree_classifier, tree_probability

log = logging.getLogger(__name__)

FUSION_RASTERS = ("ortho", "dsm", "dtm", "class_prob")
SIMPLIFY_CELLS = 2.25  # the super-pixel path's simplification of face outlines
MARGIN_CELLS = 4


@dataclass
class LodInputs:
    """What every building's step reads: the fusion's rasters on one grid."""

    grid: Grid
    rgb: np.ndarray
    dsm: np.ndarray
    filled: np.ndarray  # the DSM's holes filled for the outlines (labelling.fill_holes)
    dtm: np.ndarray
    normal: np.ndarray | None


def run_lod(
    fusion_dir: str | Path, options: LodOptions | None = None, labels: str | Path | None = None
) -> ModelRun:
    """The LOD paper on a fusion run: MRF labelling, regular roof planes, segment
    arrangements, LOD0/1/2.

    Parameters
    ----------
    fusion_dir : path
        A fusion run (ortho, dsm, dtm, class_prob; normal.tif when fused from a mesh).
    options : LodOptions
    labels : path, optional
        Training strokes (class codes 1-4, 0 unlabelled) for the tree classifier.
    """
    options = options or LodOptions()
    if not {"1", "2"} & set(options.lod):
        raise WorkbenchError("--lod: give 1 or 2 as well: every building needs a closed mesh "
                             "(LOD0 is its footprint)")  # fmt: skip
    timer = StageTimer()
    t_start = time.perf_counter()
    with timer.stage("read"):
        fusion = read_fusion_run(fusion_dir, FUSION_RASTERS)
        grid = fusion.grid
        dsm, dtm, rgb = fusion.band("dsm"), fusion.band("dtm"), fusion.rgb
        normal = _normal_map(Path(fusion_dir), grid)
        strokes = _strokes(labels, grid) if labels is not None else None
    with timer.stage("tree probability"):
        if strokes is not None:
            model = train_tree_classifier(rgb, strokes, options.boost_rounds, options.seed)
            t = tree_probability(model, rgb)
            t_source = f"AdaBoost of {options.boost_rounds} stumps on {labels}'s strokes"
        else:
            prob = fusion.rasters["class_prob"]
            t = np.nan_to_num(prob[GRASS - 1] + prob[TREE - 1], nan=0.5)
            t_source = "the fusion's grass and tree probabilities (no --labels)"
    with timer.stage("labelling"):
        block = max(1, round(options.ground_block_m / grid.gsd))
        # the ground goes on under the mesh's holes, where filled heights stand on it
        ground = dtm_across_holes(dtm)
        filled = fill_from_below(dsm)
        factor, colours = None, {"used": False, "reason": "no --labels"}
        if strokes is not None and options.flat_colours:
            on = np.isin(strokes, (GROUND, GRASS))
            model, colours = fit_flat_colours(rgb[on], strokes[on], options.seed)
            factor = ground_factor(model, rgb) if model is not None else None
        elif strokes is not None:
            colours["reason"] = "--no-flat-colours"
        classes, _, trace = mrf_labelling(filled, t, options.h_trunc, options.mu,
                                          options.ground_iterations, block,
                                          rgb if options.colour_contrast else None,
                                          factor)  # fmt: skip
        planar = dict.fromkeys(PLANAR_COUNTS, 0)
        if options.planar_objects:
            # green roofs the strokes' colours call tree, as in the fusion's class map
            roofs, planar = planar_roof_cells(classes, dsm, dsm - ground, grid.gsd, options.seed)
            classes = np.where(roofs, BUILDING, classes).astype(classes.dtype)
        radius = round(options.opening_m / grid.gsd)
        building = open_close(classes == BUILDING, radius)
        parts, n = ndi.label(building)
        sizes = np.bincount(parts.ravel(), minlength=n + 1) * grid.gsd**2
        keep = [k for k in range(1, n + 1) if sizes[k] >= options.min_area_m2]
        outline_heights = fill_holes(dsm, ground, options.h_trunc, from_below=filled)
    inputs = LodInputs(grid, rgb, dsm, outline_heights, ground, normal)
    buildings, skipped, painted = [], [], np.zeros(grid.shape, np.int64)
    with timer.stage("buildings"):
        boxes = ndi.find_objects(parts)
        for k in progress(keep, "lod: buildings"):
            b, plane_raster, (rows, cols) = building_lod(k, parts, boxes[k - 1], inputs, options)
            if isinstance(b, str):
                skipped.append({"region": int(k), "reason": b})
            else:
                b.id = str(len(buildings) + 1)
                b.mesh.vertex_colors = vertex_colours(b.mesh.vertices, rgb, grid)
                buildings.append(b)
                inside = plane_raster > 0
                painted[rows, cols][inside] = plane_raster[inside] + 1000 * len(buildings)
    with timer.stage("preview"):
        preview = lod_preview(rgb, classes, painted)
    seconds = time.perf_counter() - t_start
    return ModelRun(
        "lod", options, buildings, crs=fusion.crs, grid=grid, dtm=dtm, dsm=dsm,
        ground=ground_surface(dtm, rgb, grid), preview=preview, stages=timer.stages,
        rasters={"class": (classes, 0), "tree_probability": (t.astype(np.float32), None)},
        inputs={"fusion": str(Path(fusion_dir).absolute()),
                "grid": {"width": grid.width, "height": grid.height, "gsd": grid.gsd},
                "labels": str(Path(labels).absolute()) if labels else None,
                "normal_map": "normal.tif" if normal is not None else "from the DSM"},
        counts={"candidates": len(keep), "skipped": len(skipped), **planar},
        record={
            "skipped": skipped,
            "labelling": {"tree_probability": t_source, "flat_colours": colours,
                          "mean_ground_m": trace,
                          "cells": {name: int((classes == c).sum()) for c, name in
                                    ((1, "ground"), (2, "grass"), (3, "tree"),
                                     (4, "building"))}},
            "seconds_per_building": round(seconds / max(len(buildings), 1), 3),
            "seconds_per_megapixel": round(seconds / (grid.width * grid.height / 1e6), 3),
            "peak_memory_mb": round(peak_memory_mb(), 1),
        },
    )  # fmt: skip


def building_lod(
    k: int, parts: np.ndarray, box: tuple, inputs: LodInputs, options: LodOptions
) -> tuple[Building | str, np.ndarray, tuple[slice, slice]]:
    """Sections 5.1-5.4 and the LOD generation for the building region ``k``; returns
    the building (or why there is none), its cells' plane index + 1 and its window."""
    t0 = time.perf_counter()
    g = inputs.grid
    H, W = parts.shape
    r0, r1 = max(box[0].start - MARGIN_CELLS, 0), min(box[0].stop + MARGIN_CELLS, H)
    c0, c1 = max(box[1].start - MARGIN_CELLS, 0), min(box[1].stop + MARGIN_CELLS, W)
    win = (slice(r0, r1), slice(c0, c1))
    crop = g.window(*win)
    dsm, dtm = inputs.dsm[r0:r1, c0:c1], inputs.dtm[r0:r1, c0:c1]
    seg = parts[r0:r1, c0:c1]
    # the outline where the mesh's rounded walls stand at mid-height
    filled = inputs.filled[r0:r1, c0:c1]
    mask = mid_wall_region(seg == k, filled - dtm, (seg > 0) & (seg != k), g.gsd,
                           options.outline_reach_m)  # fmt: skip
    if mask.sum() * g.gsd**2 < options.min_area_m2:
        return "under --min-area at its walls' mid-height", np.zeros(mask.shape, np.int64), win
    normal = _normals(inputs.normal, dsm, g.gsd, win)
    X, Y = crop.cell_centers()
    points = np.dstack([X, Y, dsm])
    # 5.1 facade directions
    theta, share = facade_directions(wall_normals(normal, dsm, g.gsd, _ring(mask)),
                                     options.angle_threshold, seed=options.seed + k)  # fmt: skip
    # 5.2 line segments from four sources, regularised
    near = ndi.binary_dilation(mask, iterations=2)
    sources = {
        "ortho": detect_segments(inputs.rgb[r0:r1, c0:c1].mean(axis=2)),
        "height": detect_segments(np.where(near, dsm, np.nan)),
        **{f"normal_{i}": detect_segments(np.where(near, m, np.nan))
           for i, m in enumerate(direction_maps(normal, theta))},
        "outline": outline_segments(mask),
    }  # fmt: skip
    found = {name: _inside(s, near) for name, s in sources.items()}
    segs, regular = regularise_segments(
        np.concatenate(list(found.values())), theta, options.angle_threshold,
        options.collinear_m / g.gsd, 1.0 / g.gsd,
    )  # fmt: skip
    faces = arrangement_faces(mask, segs, 1.0 / g.gsd)
    # 5.3 roof directions and planes
    cells = mask & np.isfinite(dsm) & np.isfinite(normal).all(axis=0)
    min_count = max(int(options.min_plane_m2 / g.gsd**2), 4)
    dirs = roof_directions(normal[:, cells].T, theta, options.angle_threshold, min_count,
                           seed=options.seed + k)  # fmt: skip
    planes = roof_planes(points[cells], normal[:, cells].T, dirs, options.angle_threshold,
                         options.plane_inlier_m, min_count)  # fmt: skip
    if not len(planes):
        z = np.nanmedian(dsm[mask]) if np.isfinite(dsm[mask]).any() else np.nan
        if not np.isfinite(z):
            return "no height in the DSM", np.zeros(mask.shape, np.int64), win
        planes = np.array([[0.0, 0.0, 1.0, -z]])
    # 5.4 faces labelled with planes
    face_plane = label_faces(faces, points, planes, options.beta, g.gsd)
    plane_raster = np.where(faces > 0, face_plane[np.maximum(faces, 1) - 1] + 1, 0)
    b = lod_models(plane_raster, crop, planes, dsm, dtm, mask, options)
    if b is None:
        return "no face gives a polygon", plane_raster, win
    b.record.update({
        "facade_direction_deg": round(float(np.degrees(theta)), 2),
        "facade_inlier_share": round(share, 3),
        "segments": {name: int(len(s)) for name, s in found.items()},
        "segments_regularised": int(regular.sum()), "segments_kept": int(len(segs)),
        "arrangement_faces": int(faces.max()), "roof_directions": len(dirs),
        "planes_detected": int(len(planes)),
        "symmetric_pairs": _symmetric_pairs(planes),
        "seconds": round(time.perf_counter() - t0, 3),
    })  # fmt: skip
    return b, plane_raster, win


def lod_models(
    plane_raster: np.ndarray,
    crop: Grid,
    planes: np.ndarray,
    dsm: np.ndarray,
    dtm: np.ndarray,
    mask: np.ndarray,
    options: LodOptions,
) -> Building | None:
    """LOD generation: LOD2 each face on its roof plane, LOD1 each face at its plane's
    mean height over it (the paper's Fig. 9), LOD0 the outline (written by the run's
    CityJSON). The building carries the highest asked for as its mesh and the LOD1 model
    in ``lods`` when both are asked for."""
    g = dtm[mask]
    base = float(np.nanmin(g)) if np.isfinite(g).any() else np.inf
    simplify = SIMPLIFY_CELLS * crop.gsd
    X, Y = crop.cell_centers()
    lod2 = lod1 = None
    if "2" in options.lod:
        lod2 = closed_roof_model(plane_raster, crop, planes, base, simplify,
                                 options.angle_threshold)  # fmt: skip
    if "1" in options.lod:
        flat = np.zeros_like(planes)
        flat[:, 2] = 1.0
        for p in range(len(planes)):
            sel = plane_raster == p + 1
            z = -(planes[p, 0] * X[sel] + planes[p, 1] * Y[sel] + planes[p, 3]) / planes[p, 2]
            flat[p, 3] = -float(z.mean()) if sel.any() else -planes[p, 3]
        lod1 = closed_roof_model(plane_raster, crop, flat, base, simplify,
                                 options.angle_threshold)  # fmt: skip
        if lod1 is not None:
            lod1.lod = "1.3"
    main = lod2 or lod1
    if main is None:
        return None
    if lod2 is not None and lod1 is not None:
        main.lods["1.3"] = lod1.mesh
    return main


def summary_lines(record: dict, buildings=()) -> list[str]:
    lab = record.get("labelling", {})
    cells = lab.get("cells", {})
    total = max(sum(cells.values()), 1)
    shares = ", ".join(f"{k} {v / total:.0%}" for k, v in cells.items())
    colours = lab.get("flat_colours", {})
    counts = record.get("counts", {})
    return [f"  labelling: {shares}; ground height by iteration {lab.get('mean_ground_m')} m",
            f"  tree probability: {lab.get('tree_probability')}",
            "  ground and grass by colour: " + ("yes" if colours.get("used") else
                                                f"no ({colours.get('reason')})")
            + f"; tree objects made building: {counts.get('planar_objects_made_building', 0)} "
            f"planar, {counts.get('roof_faces_made_building', 0)} roof faces"]  # fmt: skip


def lod_preview(rgb: np.ndarray, classes: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Ortho, MRF labelling and the buildings' faces coloured by roof plane, side by
    side (``planes``: a distinct id per building and plane, 0 elsewhere)."""
    palette = np.random.default_rng(0).integers(40, 230, (int(planes.max()) + 1, 3))
    palette[0] = 255
    return contact_sheet([[(rgb, "ortho"), (colorize_classes(classes), "MRF labelling"),
                           (palette[planes].astype(np.uint8), "roof planes")]],
                         height=360)  # fmt: skip


def _normal_map(folder: Path, grid: Grid) -> np.ndarray | None:
    path = folder / "normal.tif"
    if not path.exists():
        return None
    data, g, _ = read_raster(path)
    if g != grid or data.shape[0] != 3:
        raise InputError(path, "transform", "not 3 bands on the fusion's grid")
    return data.astype(np.float64)


def _normals(normal: np.ndarray | None, dsm: np.ndarray, gsd: float, win) -> np.ndarray:
    """(3, h, w) unit normals of a crop: the normal map's, else the DSM's gradient's."""
    if normal is not None:
        return normal[(slice(None), *win)]
    gy, gx = np.gradient(dsm, gsd)
    n = np.stack([-gx, gy, np.ones_like(dsm)])  # rows run south: dz/dy = -gy
    return n / np.linalg.norm(n, axis=0)


def _strokes(path, grid: Grid) -> np.ndarray:
    """The training strokes on ``grid`` (nearest cell), codes 0-4."""
    data, g, _ = read_raster(path)
    codes = data[0]
    if np.nanmax(codes) > 4 or np.nanmin(codes) < 0:
        raise InputError(path, "band 1", "class codes must be 0 (unlabelled) to 4")
    if g == grid:
        return codes.astype(np.int64)
    X, Y = grid.cell_centers()
    r, c = g.cell_index(X.ravel(), Y.ravel(), clip=True)
    return codes[r, c].reshape(grid.shape).astype(np.int64)


def _ring(mask: np.ndarray) -> np.ndarray:
    """The cells within two of the mask's edge, both sides (its walls)."""
    grown = ndi.binary_dilation(mask, iterations=2)
    return grown & ~ndi.binary_erosion(mask, iterations=2)


def _inside(seg: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The segments whose middle lies in ``near``."""
    if not len(seg):
        return seg
    mid = np.round((seg[:, :2] + seg[:, 2:]) / 2).astype(np.int64)
    h, w = near.shape
    ok = (mid[:, 0] >= 0) & (mid[:, 0] < w) & (mid[:, 1] >= 0) & (mid[:, 1] < h)
    ok[ok] = near[mid[ok, 1], mid[ok, 0]]
    return seg[ok]


def _symmetric_pairs(planes: np.ndarray) -> int:
    """Plane pairs whose normals are z-symmetric (to 1e-6)."""
    n = planes[:, :3]
    twin = z_symmetric(n)
    return int(sum(np.abs(n[j] - twin[i]).max() < 1e-6 for i in range(len(n))
                   for j in range(i + 1, len(n))))  # fmt: skip
