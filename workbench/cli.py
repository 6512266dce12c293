"""The ``workbench`` command line: parses, calls the library, reports.

Every expected failure is one line on stderr and exit code 2; an unexpected one
is one line and exit code 1 (``-v`` shows the traceback).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import traceback
from pathlib import Path

from . import __version__
from .errors import WorkbenchError

log = logging.getLogger("workbench")


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return v


def _non_negative_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative number, got {text}")
    return v


def _omega(text: str) -> float | None:
    return None if text == "auto" else _positive_float(text)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text}")
    return v


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="workbench",
        description="Reconstruct cities in 3D from aerial images, DSMs and LiDAR, "
        "and compare methods on the same metrics.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser(
        "sample",
        help="generate a synthetic city with full ground truth",
        description="Generate a synthetic city scene (images, depth maps, GIS footprints, "
        "training labels) with full ground truth in OUT/truth. Deterministic for a preset "
        "and a seed.",
    )
    p.add_argument("out", type=Path, metavar="OUT", help="output scene folder")
    p.add_argument(
        "--preset",
        choices=["tiny", "small", "city"],
        default="tiny",
        help="tiny: 64 m, ~6 buildings, 20 views of 640x480 (seconds); "
        "small: 200 m, ~30 buildings, 45 views of 1024x768 (the benchmark); "
        "city: 1 km, ~500 buildings, 495 views (minutes). Default: tiny",
    )
    p.add_argument("--seed", type=_non_negative_int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--calibration-error",
        type=float,
        metavar="PX",
        default=None,
        help="RMS reprojection error of the written poses against the true ones, "
        "pixels (default 0.5)",
    )
    p.add_argument(
        "--depth-noise",
        type=float,
        metavar="METRES",
        default=None,
        help="depth-map noise sigma at the flying height, metres (default 0.15)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_sample)

    p = sub.add_parser(
        "validate",
        help="check a scene and print a summary",
        description="Validate SCENE (scene.json and every file it names) and summarise it.",
    )
    p.add_argument("scene", type=Path, metavar="SCENE", help="scene folder or scene.json")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser(
        "import-colmap",
        help="convert a COLMAP text model into a scene",
        description="Convert a geo-registered COLMAP text model (cameras.txt, images.txt; "
        "PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV cameras) into a scene. "
        "Principal points move by half a pixel (COLMAP's pixel centres are at +0.5).",
    )
    p.add_argument(
        "model", type=Path, metavar="MODEL_DIR", help="folder with cameras.txt, images.txt"
    )
    p.add_argument("images", type=Path, metavar="IMAGES_DIR", help="folder with the images")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="SCENE", help="scene folder")
    p.add_argument(
        "--crs",
        required=True,
        help="EPSG code or WKT of the model's frame (projected metres, z up)",
    )
    p.add_argument(
        "--depth-dir",
        type=Path,
        metavar="DIR",
        help="COLMAP stereo/depth_maps folder (NAME.geometric.bin)",
    )
    p.add_argument(
        "--copy-images",
        action="store_true",
        help="copy the images into the scene (default: refer to them)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace SCENE if it exists")
    p.set_defaults(func=cmd_import_colmap)

    p = sub.add_parser(
        "fusion",
        help="fuse views (or a LiDAR cloud) into ortho colour, DSM/DTM/nDSM and classes",
        description="Fuse the calibrated views of SCENE (their depth maps) into north-up "
        "rasters: ortho.tif (vector median colour), dsm.tif (median height), dtm.tif, "
        "ndsm.tif, class_prob.tif, class.tif, count.tif, plus fusion.json and preview.png. "
        "With --points, rasterise a LAS/LAZ/PLY cloud into the same products.",
    )
    p.add_argument("scene", type=Path, nargs="?", metavar="SCENE", help="scene folder")
    p.add_argument("--points", type=Path, metavar="CLOUD", help="LAS, LAZ or PLY point cloud")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="OUT", help="output folder")
    p.add_argument(
        "--gsd",
        type=_positive_float,
        metavar="METRES",
        help="cell size in the CRS's units (default: the scene's gsd, else the "
        "nadir view's; for clouds, the point spacing)",
    )
    p.add_argument(
        "--bounds",
        type=float,
        nargs=4,
        metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
        help="area to fuse, world units (default: the scene's bounds)",
    )
    p.add_argument("--crs", help="CRS of a point cloud that carries none (EPSG code or WKT)")
    p.add_argument(
        "--truth",
        type=Path,
        metavar="SCENE",
        help="score the products against SCENE/truth into fusion.json",
    )
    p.add_argument(
        "--classifier",
        type=Path,
        metavar="FILE",
        help="reuse a saved forest instead of training one",
    )
    p.add_argument(
        "--raster-prior",
        action="store_true",
        help="multiply the views' class probabilities by those of a forest on the fused "
        "rasters (nDSM, slope, roughness, colour), trained on the synthetic city; not in the "
        "paper, off by default",
    )
    p.add_argument(
        "--save-classifier",
        type=Path,
        metavar="FILE",
        help="save the trained forest for another scene",
    )
    p.add_argument(
        "--label-split",
        type=_non_negative_float,
        default=1.0,
        metavar="METRES",
        help="training pixels labelled tree or building must stand at least this high above "
        "the DTM, ground or grass below it; others are dropped (default 1)",
    )
    p.add_argument(
        "--workers",
        type=_positive_int,
        metavar="N",
        help="views processed at once, in threads (default: every core; the products do "
        "not depend on it)",
    )
    p.add_argument("--seed", type=_non_negative_int, default=0, help="random seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_fusion)

    p = sub.add_parser(
        "model",
        help="model buildings from a fusion run (superpixel) or from images (voxel)",
        description="Building modeling paths. Each writes a model run folder that "
        "`workbench compare` scores.",
    )
    paths = p.add_subparsers(dest="path", metavar="PATH", required=True)
    q = paths.add_parser(
        "superpixel",
        help="Quickshift super-pixels, class CRF, RANSAC roof prototypes, LOD2 meshes",
        description="The super-pixel path (Kluckner & Bischof 2010) on the rasters of "
        "`workbench fusion`: Quickshift super-pixels on the ortho, a class CRF on them, "
        "RANSAC plane hypotheses clustered into roof prototypes by affinity propagation, a "
        "prototype CRF, and roof polygons lifted to their planes with walls to the DTM. "
        "Writes buildings/<id>.ply|.obj, scene.ply|.obj, class.tif, model.json, preview.png.",
    )
    q.add_argument("fusion", type=Path, metavar="FUSION_DIR", help="output of workbench fusion")
    q.add_argument("-o", "--out", type=Path, required=True, metavar="OUT", help="output folder")
    q.add_argument(
        "--omega-class",
        type=_omega,
        default=3.0,
        help="weight of the class CRF's pairwise term (default 3), or auto: the best of "
        "0.25-12 on the scene's training strokes",
    )
    q.add_argument(
        "--omega-roof",
        type=_positive_float,
        default=5.0,
        help="weight of the prototype CRF's pairwise term (default 5)",
    )
    q.add_argument(
        "--quickshift-sigma",
        type=_positive_float,
        default=2.0,
        help="Quickshift kernel width, pixels (default 2)",
    )
    q.add_argument(
        "--quickshift-tau",
        type=_positive_float,
        default=8.0,
        help="Quickshift largest link distance, pixels (default 8)",
    )
    q.add_argument(
        "--segment-on",
        choices=("ortho", "relief"),
        default=None,
        help="what Quickshift segments: the ortho (the paper) or the DSM's surface normals "
        "(default: the relief for point-cloud fusions, whose ortho is one grey level per "
        "cell; the ortho otherwise)",
    )
    q.add_argument(
        "--height-weight",
        type=_non_negative_float,
        default=10.0,
        metavar="LAB_PER_M",
        help="Lab units per metre of the DSM's height segmented beside the ortho's colour, so "
        "that super-pixels do not straddle walls (default 10; 0: the colour alone, as the "
        "paper does; not used on the relief)",
    )
    q.add_argument(
        "--workers",
        type=_positive_int,
        metavar="N",
        help="Quickshift tiles segmented at once, in threads (default: every core; the "
        "labels do not depend on it)",
    )
    q.add_argument(
        "--min-area",
        type=_positive_float,
        default=20.0,
        metavar="M2",
        help="smallest building kept, square metres (default 20)",
    )
    q.add_argument(
        "--simplify",
        type=_positive_float,
        default=None,
        metavar="METRES",
        help="tolerance of the roof polygon simplification (default: two cells)",
    )
    q.add_argument(
        "--regularise",
        type=_non_negative_float,
        default=0.0,
        metavar="DEG",
        help="put outline sides this close to the building's dominant directions on them, and "
        "square their corners (default 0: the outline as simplified)",
    )
    q.add_argument(
        "--truth",
        type=Path,
        metavar="SCENE",
        help="record the paper's Table 1 rows (pixel, super-pixel, CRF) against "
        "SCENE/truth in model.json",
    )
    q.add_argument(
        "--edge-reach",
        type=_non_negative_float,
        default=None,
        metavar="METRES",
        help="unseen cells of a building this close to its seen cells stay in it (default: "
        "1 for fused views, whose occlusions leave building edges unseen; 0 for clouds)",
    )
    q.add_argument(
        "--all-building",
        action="store_true",
        help="every cell with a height is building (clouds of single buildings, such as "
        "City3D's building instances, have no ground to classify against)",
    )
    q.add_argument("--seed", type=_non_negative_int, default=0, help="random seed (default 0)")
    q.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    q.set_defaults(func=cmd_model_superpixel)

    q = paths.add_parser(
        "voxel",
        help="photo-consistency voxel proxies from GIS footprints, graph-cut texture atlases",
        description="The voxel path (Garcia-Dorado, Demir & Aliaga 2013) on a scene's images: "
        "each footprint's over-estimated extrusion is voxelised, carved to the heights its "
        "views agree on, clustered into roof levels and meshed; surface graph cuts stitch the "
        "views into one texture atlas per building, and a ground cut with the proxies masked "
        "out textures the ground. Writes buildings/<id>.obj|.mtl|.png|.ply, ground.obj, "
        "scene.obj|.ply, model.json, preview.png.",
    )
    q.add_argument("scene", type=Path, metavar="SCENE", help="scene folder (scene.json)")
    q.add_argument("-o", "--out", type=Path, required=True, metavar="OUT", help="output folder")
    q.add_argument(
        "--footprints",
        type=Path,
        metavar="FILE",
        help="GeoJSON footprints with a height property (default: the scene's footprints)",
    )
    q.add_argument(
        "--fusion",
        type=Path,
        metavar="FUSION_DIR",
        help="a fusion run: its DTM is the ground, its nDSM marks ground columns and "
        "places and grows flat roofs, its building mask stands in for missing footprints "
        "(default: a flat ground plane)",
    )
    q.add_argument(
        "--no-fusion-ground",
        dest="fusion_ground",
        action="store_false",
        help="keep the columns the --fusion nDSM puts on the ground: photo-consistency "
        "alone decides the proxies' extent, as in the paper",
    )
    q.add_argument(
        "--no-fusion-flat-roofs",
        dest="fusion_flat_roofs",
        action="store_false",
        help="keep the photo-consistent height and extent of flat roofs instead of "
        "placing and growing them on the --fusion nDSM, as in the paper",
    )
    q.add_argument(
        "--voxel",
        type=_positive_float,
        default=1.0,
        metavar="METRES",
        help="voxel size r (default 1)",
    )
    q.add_argument(
        "--subdivisions",
        type=_positive_int,
        default=4,
        metavar="S",
        help="texels per voxel side on the surface graph (default 4)",
    )
    q.add_argument(
        "--cluster-error",
        type=_positive_float,
        default=0.3,
        metavar="CE",
        help="k-means stops when one more cluster lowers the error by less than this (default 0.3)",
    )
    q.add_argument(
        "--overlap",
        type=_positive_float,
        default=4.0,
        metavar="METRES",
        help="width of the band where a graph cut may move a seam (default 4)",
    )
    q.add_argument(
        "--refine-sweeps",
        type=_non_negative_int,
        default=2,
        metavar="N",
        help="passes of expansion moves over the whole surface after the greedy cuts "
        "(default 2; 0: the paper's greedy cuts alone)",
    )
    q.add_argument(
        "--facing-weight",
        type=_non_negative_float,
        default=10.0,
        metavar="LAB",
        help="what the refinement charges for a worse-facing view, Lab units per unit "
        "cosine (default 10)",
    )
    q.add_argument(
        "--ring",
        type=_positive_float,
        default=4.0,
        metavar="METRES",
        help="width of the building-ground ring cut (default 4)",
    )
    q.add_argument(
        "--grow",
        type=_non_negative_float,
        default=1.5,
        metavar="METRES",
        help="grow the GIS footprints by this much before voxelising (default 1.5)",
    )
    q.add_argument(
        "--consistency",
        choices=("lab", "hs"),
        default="lab",
        help="colour of the photo-consistency: CIE Lab (default, measured better on the "
        "sample city) or the paper's HSL hue and saturation",
    )
    q.add_argument(
        "--default-height",
        type=_positive_float,
        default=35.0,
        metavar="METRES",
        help="height of footprints without one (the paper's zonal default, 35)",
    )
    q.add_argument(
        "--ground-z",
        type=float,
        default=None,
        metavar="METRES",
        help="height of the flat ground plane without --fusion or a scene DTM (default: "
        "from the depth maps of the most downward-looking views)",
    )
    q.add_argument("--seed", type=_non_negative_int, default=0, help="random seed (default 0)")
    q.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    q.set_defaults(func=cmd_model_voxel)

    p = sub.add_parser(
        "compare",
        help="score runs against the same truth: metrics.json and report.html",
        description="Score fusion and model runs on the same metrics against the same "
        "truth; write REPORT/metrics.json, REPORT/report.html (one self-contained page) and "
        "REPORT/figures/, and print the side-by-side table.",
    )
    p.add_argument("runs", type=Path, nargs="+", metavar="RUN", help="fusion or model run folder")
    p.add_argument("--truth", type=Path, metavar="SCENE", help="a scene with truth/")
    p.add_argument("--truth-dsm", type=Path, metavar="FILE", help="true DSM GeoTIFF (real data)")
    p.add_argument("--truth-dtm", type=Path, metavar="FILE", help="true DTM GeoTIFF (real data)")
    p.add_argument("--truth-footprints", type=Path, metavar="FILE", help="true footprints GeoJSON")
    p.add_argument("--truth-class", type=Path, metavar="FILE", help="true class GeoTIFF (1-4)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="REPORT", help="report folder")
    p.add_argument("--names", nargs="+", metavar="NAME", help="run names (default: folder names)")
    p.add_argument(
        "--tolerance",
        type=_positive_float,
        default=1.0,
        metavar="METRES",
        help="vertical tolerance of the 3D completeness and correctness (default 1)",
    )
    p.add_argument(
        "--max-error",
        type=_positive_float,
        default=2.0,
        metavar="METRES",
        help="the red end of the error colour maps (default 2)",
    )
    p.add_argument("--seed", type=_non_negative_int, default=0, help="seed of surface samples")
    p.add_argument("--overwrite", action="store_true", help="replace REPORT if it exists")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser(
        "demo",
        help="run the main job on the tiny sample city",
        description="Generate the tiny sample city, fuse its views, model its buildings with "
        "the super-pixel path and with the voxel path (PLY and OBJ), score the three runs "
        "against the truth with `compare` and write the report.",
    )
    p.add_argument("-o", "--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--seed", type=_non_negative_int, default=0, help="random seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_demo)
    return parser


def cmd_sample(args) -> int:
    from data_samples.generate import generate_sample
    from data_samples.presets import PRESETS

    preset = PRESETS[args.preset]
    overrides = {}
    if args.calibration_error is not None:
        if args.calibration_error < 0:
            raise WorkbenchError("--calibration-error: must be >= 0 pixels")
        overrides["calibration_error_px"] = args.calibration_error
    if args.depth_noise is not None:
        if args.depth_noise < 0:
            raise WorkbenchError("--depth-noise: must be >= 0 metres")
        overrides["depth_sigma"] = args.depth_noise
    if overrides:
        preset = preset.with_overrides(**overrides)
    meta = generate_sample(args.out, preset, args.seed, overwrite=args.overwrite)
    c = meta["counts"]
    print(
        f"wrote {args.out}: {c['buildings']} buildings, {c['trees']} trees, {c['views']} views, "
        f"{c['triangles']} triangles in {meta['timing']['total']:.1f} s"
    )
    print(
        f"  calibration error {meta['calibration_error_px_rms']:.2f} px RMS; "
        f"preview: {args.out / 'preview.png'}"
    )
    return 0


def scene_summary(scene) -> dict:
    views = scene.views
    return {
        "scene": str(scene.scene_json),
        "crs": scene.crs.to_string() if scene.crs.to_epsg() else scene.crs.to_wkt()[:80] + "...",
        "views": len(views),
        "views_with_depth": sum(v.depth_path is not None for v in views),
        "image_sizes": sorted({f"{v.camera.width}x{v.camera.height}" for v in views}),
        "bounds": scene.bounds,
        "gsd": scene.gsd,
        **{
            k: str(getattr(scene, k))
            for k in ("dsm", "dtm", "points", "footprints", "training_labels", "truth")
            if getattr(scene, k) is not None
        },
    }


def cmd_validate(args) -> int:
    from .scene import load_scene

    summary = scene_summary(load_scene(args.scene))
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print(f"{args.scene}: valid scene")
        for k, v in summary.items():
            print(f"  {k}: {v}")
    return 0


def cmd_import_colmap(args) -> int:
    from .colmap import import_colmap

    path = import_colmap(
        args.model,
        args.images,
        args.out,
        crs=args.crs,
        depth_dir=args.depth_dir,
        copy_images=args.copy_images,
        overwrite=args.overwrite,
    )
    print(f"wrote {path}")
    return 0


def cmd_fusion(args) -> int:
    from fusion.cli_fusion import run_fusion

    if (args.scene is None) == (args.points is None):
        raise WorkbenchError("fusion: give either SCENE or --points CLOUD")
    record = run_fusion(args)
    q = record.get("quality", {})
    print(
        f"wrote {args.out}: {record['grid']['width']} x {record['grid']['height']} cells "
        f"at {record['grid']['gsd']:g}, {record['stages_total_s']:.1f} s"
    )
    if q:
        d, c = q.get("dsm", {}), q.get("classification", {})
        if d.get("rmse_m") is not None:
            off = d.get("rmse_off_jumps_m")
            off = f" ({off:.3f} m off height jumps)" if off is not None else ""
            print(
                f"  DSM RMSE {d['rmse_m']:.3f} m{off}, median |e| {d['median_abs_m']:.3f} m, "
                f"valid {d['valid_fraction']:.1%}"
            )
        if c.get("overall_accuracy") is not None:
            per = ", ".join(f"{k} {v:.3f}" for k, v in c["per_class_accuracy"].items())
            print(f"  classes: overall {c['overall_accuracy']:.3f} ({per})")
        if q.get("ortho_mae"):
            print(f"  ortho MAE {q['ortho_mae']['mean']:.1f} / 255")
    return 0


def cmd_model_superpixel(args) -> int:
    from modeling.cli_superpixel import run_superpixel
    from modeling.superpixel_model import SuperpixelOptions

    options = SuperpixelOptions(
        sigma=args.quickshift_sigma,
        tau=args.quickshift_tau,
        segment_on=args.segment_on,
        height_weight=args.height_weight,
        omega_class=args.omega_class,
        omega_roof=args.omega_roof,
        min_area_m2=args.min_area,
        simplify_m=args.simplify,
        regularise_deg=args.regularise,
        all_building=args.all_building,
        edge_reach_m=args.edge_reach,
        seed=args.seed,
        workers=args.workers,
    )
    record = run_superpixel(
        args.fusion, args.out, options, truth=args.truth, overwrite=args.overwrite
    )
    c = record["counts"]
    total = sum(s["wall_s"] for k, s in record["stages"].items())
    print(
        f"wrote {args.out}: {c['buildings']} buildings, {c['faces']} triangles, "
        f"{c['watertight']} of {c['buildings']} watertight, {record['superpixels']} "
        f"super-pixels, {total:.1f} s"
    )
    table = record.get("classification_table")
    if table:
        rows = ", ".join(f"{k} {v['overall_accuracy']:.3f}" for k, v in table.items())
        print(f"  overall accuracy (Table 1): {rows}")
    if c["buildings"] == 0:
        print("  no building pixels: the model is empty")
    return 0


def cmd_model_voxel(args) -> int:
    from modeling.cli_voxel import run_voxel
    from modeling.voxel_model import VoxelOptions

    options = VoxelOptions(
        voxel_m=args.voxel,
        subdivisions=args.subdivisions,
        cluster_error=args.cluster_error,
        overlap_m=args.overlap,
        refine_sweeps=args.refine_sweeps,
        facing_weight=args.facing_weight,
        ring_m=args.ring,
        grow_m=args.grow,
        consistency=args.consistency,
        fusion_ground=args.fusion_ground,
        fusion_flat_roofs=args.fusion_flat_roofs,
        seed=args.seed,
    )
    record = run_voxel(
        args.scene,
        args.out,
        options,
        footprints=args.footprints,
        fusion_dir=args.fusion,
        ground_z=args.ground_z,
        default_height=args.default_height,
        overwrite=args.overwrite,
    )
    print(voxel_summary(record, args.out))
    return 0


def voxel_summary(record: dict, out: Path) -> str:
    """Two lines on a voxel run: counts, time, seam costs."""
    c, t = record["counts"], record["texture"]
    seams = ""
    if t.get("seam_cost") is not None:
        seams = (
            f"; seam cost {t['seam_cost']:.2f} (graph cut) vs "
            f"{t['seam_cost_projective']:.2f} (projective)"
        )
    return (
        f"wrote {out}: {c['buildings']} buildings of {c['footprints']} footprints "
        f"({c['skipped']} skipped), {c['faces']} triangles, {c['watertight']} watertight, "
        f"{record['seconds_per_building']:.2f} s per building{seams}"
    )


def cmd_compare(args) -> int:
    from .compare import check_truth_args, compare_runs, summary
    from .evaluate import EvaluationOptions
    from .runs import load_run
    from .truth import load_file_truth, load_scene_truth

    check_truth_args(args)
    if args.truth is not None:
        truth = load_scene_truth(args.truth)
    else:
        first = load_run(args.runs[0])
        grid = crs = None
        if first.raster("dsm") or first.raster("class"):
            from .raster import read_raster

            _, grid, crs = read_raster(first.raster("dsm") or first.raster("class"))
        truth = load_file_truth(
            dsm=args.truth_dsm,
            dtm=args.truth_dtm,
            footprints=args.truth_footprints,
            cls=args.truth_class,
            grid=grid,
            crs=crs,
        )
    options = EvaluationOptions(
        tolerance_m=args.tolerance, max_error_m=args.max_error, seed=args.seed
    )
    doc = compare_runs(
        args.runs, truth, args.out, names=args.names, options=options, overwrite=args.overwrite
    )
    print(summary(doc))
    print(f"report: {args.out / 'report.html'}")
    return 0


def cmd_demo(args) -> int:

    from data_samples.generate import generate_sample
    from fusion.cli_fusion import fusion_arguments, run_fusion
    from modeling.cli_superpixel import run_superpixel
    from modeling.cli_voxel import run_voxel
    from modeling.superpixel_model import SuperpixelOptions
    from modeling.voxel_model import VoxelOptions

    from .compare import compare_runs, summary
    from .scene import load_scene
    from .truth import load_scene_truth

    t0 = time.perf_counter()
    scene_dir, fusion_dir = args.out / "scene", args.out / "fusion"
    report_dir = args.out / "report"
    if args.out.exists() and not args.overwrite and any(args.out.iterdir()):
        raise WorkbenchError(f"{args.out}: output exists (pass --overwrite to replace it)")
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"1/5 generating the tiny sample city (seed {args.seed}) ...", flush=True)
    meta = generate_sample(scene_dir, "tiny", args.seed, overwrite=True)
    scene = load_scene(scene_dir)
    c = meta["counts"]
    roofs = ", ".join(f"{n} {kind}" for kind, n in c["roof_types"].items())
    print(
        f"    {c['buildings']} buildings ({roofs}), {c['trees']} trees, {len(scene.views)} "
        f"views with depth maps, in {meta['timing']['total']:.1f} s"
    )
    print(
        f"    calibration error of the written poses: {meta['calibration_error_px_rms']:.2f} px RMS"
    )
    print("2/5 fusing the views into ortho, DSM/DTM/nDSM and classes ...", flush=True)
    record = run_fusion(
        fusion_arguments(
            scene=scene_dir, out=fusion_dir, truth=scene_dir, seed=args.seed, overwrite=True
        )
    )
    q = record["quality"]
    print(
        f"    {record['stages_total_s']:.1f} s; mean fusion instead of the median: DSM RMSE "
        f"{q['dsm_mean_fusion']['rmse_m']:.2f} m (median {q['dsm']['rmse_m']:.2f} m), ortho MAE "
        f"{q['ortho_mae_mean_fusion']['mean']:.1f} (median {q['ortho_mae']['mean']:.1f})"
    )
    print("3/5 super-pixel modeling: Quickshift, class CRF, roof prototypes, LOD2 ...", flush=True)
    superpixel_dir = args.out / "superpixel"
    sp = run_superpixel(
        fusion_dir, superpixel_dir, SuperpixelOptions(seed=args.seed), truth=scene_dir,
        overwrite=True,
    )  # fmt: skip
    c = sp["counts"]
    t1 = sp["classification_table"]
    print(
        f"    {c['buildings']} buildings, {c['faces']} triangles, {c['watertight']} watertight, "
        f"{sum(s['wall_s'] for s in sp['stages'].values()):.1f} s; overall accuracy pixel "
        f"{t1['pixel']['overall_accuracy']:.3f}, super-pixel "
        f"{t1['superpixel']['overall_accuracy']:.3f}, CRF {t1['crf']['overall_accuracy']:.3f}"
    )
    print(
        "4/5 voxel modeling: photo-consistency proxies, surface graph cut textures ...", flush=True
    )
    voxel_dir = args.out / "voxel"
    vx = run_voxel(
        scene_dir, voxel_dir, VoxelOptions(seed=args.seed), fusion_dir=fusion_dir, overwrite=True
    )
    print("    " + voxel_summary(vx, voxel_dir))
    print("5/5 scoring the runs against the truth ...", flush=True)
    truth = load_scene_truth(scene_dir)
    doc = compare_runs(
        [fusion_dir, superpixel_dir, voxel_dir], truth, report_dir,
        names=["fusion", "superpixel", "voxel"], overwrite=True,
    )  # fmt: skip
    print()
    print(summary(doc))
    print(f"  models:         {superpixel_dir / 'scene.obj'}, {voxel_dir / 'scene.obj'} (textured)")
    print(f"  scene preview:  {scene_dir / 'preview.png'}")
    print(f"  fusion preview: {fusion_dir / 'preview.png'}")
    print(f"  voxel preview:  {voxel_dir / 'preview.png'}")
    print(f"  report:         {report_dir / 'report.html'}")
    print(f"demo finished in {time.perf_counter() - t0:.1f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.verbose:  # our own debug messages, not every library's
        for name in ("workbench", "fusion", "modeling", "data_samples"):
            logging.getLogger(name).setLevel(logging.DEBUG)
    try:
        return args.func(args)
    except WorkbenchError as exc:
        print(f"workbench: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("workbench: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - never a bare traceback from the CLI
        if args.verbose:
            traceback.print_exc()
        msg = str(exc).splitlines()[0] if str(exc) else ""
        print(
            f"workbench: internal error: {type(exc).__name__}: {msg} "
            "(run with -v for the traceback)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
