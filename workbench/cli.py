"""The ``workbench`` command line: parses, calls the library, reports.

The only module that knows every part: the fusion, every modeling path (from the
registry in :mod:`modeling`), the sample generator and the comparison. Every expected
failure is one line on stderr and exit code 2; an unexpected one is one line and exit
code 1 (``-v`` shows the traceback).
"""

from __future__ import annotations

import argparse
import errno
import json
import logging
import sys
import time
import traceback
from pathlib import Path

from . import __version__
from .errors import WorkbenchError
from .options import add_option_arguments, number, options_from_args

log = logging.getLogger("workbench")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="workbench",
        description="Reconstruct cities in 3D from aerial images, DSMs and LiDAR, "
        "and compare methods on the same metrics.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in (
        _add_sample, _add_validate, _add_import_colmap, _add_import_odm, _add_fusion,
        _add_mesh, _add_model, _add_compare, _add_demo,
    ):  # fmt: skip
        add(sub)
    return parser


def _add_sample(sub) -> None:
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
    p.add_argument(
        "--seed", type=number("non_negative", int), default=0, help="random seed (default 0)"
    )
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
    p.add_argument(
        "--true-depth",
        action="store_true",
        help="depth maps are the renderer's true depth: no noise, outliers, holes or "
        "rounded edges (what the fusion reaches with a perfect matcher)",
    )
    p.add_argument(
        "--origin", type=float, nargs=2, metavar=("E", "N"),
        help="write the city centred there (metres), as real data lies far from its CRS's "
        "zero; for example 500000 5700000 with --crs EPSG:32631",
    )  # fmt: skip
    p.add_argument("--crs", help="with --origin: the CRS to name (EPSG code or WKT)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_sample)


def _add_validate(sub) -> None:
    p = sub.add_parser(
        "validate",
        help="check a scene and print a summary",
        description="Validate SCENE (scene.json and every file it names) and summarise it.",
    )
    p.add_argument("scene", type=Path, metavar="SCENE", help="scene folder or scene.json")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_validate)


def _add_import_colmap(sub) -> None:
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


def _add_import_odm(sub) -> None:
    p = sub.add_parser(
        "import-odm",
        help="convert an OpenDroneMap (OpenSfM) project into a scene",
        description="Convert an ODM project (opensfm/reconstruction.json: perspective, "
        "Brown and fisheye cameras in a topocentric frame; images/; odm_dem/dsm.tif and, "
        "if present, odm_dem/dtm.tif and odm_georeferencing/odm_georeferenced_model.laz) "
        "into a scene in the DSM's projected CRS. `workbench fusion` on it projects every "
        "view onto the DSM to fuse colour and classes.",
    )
    p.add_argument("project", type=Path, metavar="PROJECT_DIR", help="the ODM project folder")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="SCENE", help="scene folder")
    p.add_argument("--crs", help="the scene's projected CRS (default: the DSM's)")
    p.add_argument(
        "--training-labels", type=Path, metavar="FILE",
        help="strokes (label raster, codes 1-4) for the fusion's per-view classifier",
    )  # fmt: skip
    p.add_argument(
        "--copy-images", action="store_true",
        help="copy the images into the scene (default: refer to them; fisheye images are "
        "always resampled into it)",
    )  # fmt: skip
    p.add_argument("--overwrite", action="store_true", help="replace SCENE if it exists")
    p.set_defaults(func=cmd_import_odm)


def _add_fusion(sub) -> None:
    from fusion.options import FusionOptions

    p = sub.add_parser(
        "fusion",
        help="fuse views (or a LiDAR cloud) into ortho colour, DSM/DTM/nDSM and classes",
        description="Fuse the calibrated views of SCENE (their depth maps) into north-up "
        "rasters: ortho.tif (vector median colour), dsm.tif (median height), dtm.tif, "
        "ndsm.tif, class_prob.tif, class.tif, count.tif, plus fusion.json and preview.png. "
        "With --points, rasterise LAS/LAZ/PLY tiles (files or folders of them, merged) into "
        "the same products; with --mesh, sample a surface mesh by one vertical ray per cell "
        "(the LOD paper's orthogonal grid sampling) into them and normal.tif.",
    )
    p.add_argument("scene", type=Path, nargs="?", metavar="SCENE", help="scene folder")
    p.add_argument(
        "--points", type=Path, nargs="+", metavar="CLOUD",
        help="LAS, LAZ or PLY point clouds, or folders of them: the tiles of one survey, "
        "merged (their CRSs must agree)",
    )  # fmt: skip
    p.add_argument(
        "--mesh", type=Path, metavar="MESH",
        help="a surface mesh (PLY, OBJ with its textures, ...), e.g. from `workbench mesh` "
        "or an MVS tool",
    )  # fmt: skip
    p.add_argument("-o", "--out", type=Path, required=True, metavar="OUT", help="output folder")
    p.add_argument("--crs", help="CRS of point clouds or a mesh that carry none (EPSG or WKT)")
    p.add_argument(
        "--truth", type=Path, metavar="SCENE",
        help="score the products against SCENE/truth into fusion.json",
    )  # fmt: skip
    p.add_argument(
        "--save-classifier", type=Path, metavar="FILE",
        help="save the trained forest for another scene",
    )  # fmt: skip
    add_option_arguments(p, FusionOptions)
    _add_engine_arguments(p)
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_fusion)


def _add_mesh(sub) -> None:
    p = sub.add_parser(
        "mesh",
        help="a coloured surface mesh of a scene from its views' depth maps (TSDF)",
        description="Integrate the depth maps and images of SCENE's calibrated views into a "
        "truncated signed distance field (Open3D) and extract its surface by marching "
        "cubes: a dense, vertex-coloured mesh as an MVS tool gives, written as binary PLY "
        "(float64 positions, the CRS in a header comment) for `workbench fusion --mesh`.",
    )
    p.add_argument("scene", type=Path, metavar="SCENE", help="scene folder")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="MESH.ply")
    p.add_argument("--voxel", type=number("positive"), metavar="M",
                   help="voxel edge, metres (default: the scene's gsd, else 0.25)")  # fmt: skip
    p.add_argument("--trunc", type=number("positive"), default=4.0, metavar="VOXELS",
                   help="truncation of the signed distance, voxels (default: 4)")  # fmt: skip
    p.add_argument("--tile", type=number("positive"), metavar="M",
                   help="mesh the area in square tiles of M metres (the same mesh in less "
                   "memory; default: tiles only when one grid of the whole area would not "
                   "fit in 60%% of the memory)")  # fmt: skip
    p.add_argument("--workers", type=number("positive", int), metavar="N",
                   help="tiles meshed at once: worker processes of a local Dask cluster, each "
                   "holding a tile's voxel grid (default: every core; 1: in this process; "
                   "the mesh does not depend on it)")  # fmt: skip
    _add_engine_arguments(p)
    p.add_argument("--overwrite", action="store_true", help="replace MESH.ply if it exists")
    p.set_defaults(func=cmd_mesh)


def _add_engine_arguments(p) -> None:
    """--scheduler and --resume, for the commands whose work is tasks."""
    p.add_argument(
        "--scheduler", metavar="ADDRESS",
        help="run the tasks on this Dask scheduler's workers (tcp://host:8786), which must "
        "read the inputs and OUT's folder at the same paths (default: a local cluster of "
        "--workers processes)",
    )  # fmt: skip
    p.add_argument(
        "--resume", action="store_true",
        help="keep the tasks an interrupted run of the same command finished (in "
        ".OUT.partial beside OUT) and do only the others",
    )  # fmt: skip


def _add_model(sub) -> None:
    from modeling import PATHS

    p = sub.add_parser(
        "model",
        help="model buildings: " + ", ".join(PATHS),
        description="Building modeling paths. Each writes the same run folder "
        "(buildings/, scene.ply|.obj, ground, dtm.tif, model.json, preview.png) that "
        "`workbench compare` scores; the flags of each path are its options.",
    )
    paths = p.add_subparsers(dest="path", metavar="PATH", required=True)
    for spec in PATHS.values():
        q = paths.add_parser(spec.name, help=spec.help, description=spec.description)
        for item in spec.inputs:
            if item.flag is None:
                q.add_argument(item.name, type=Path, metavar=item.metavar, help=item.help)
            else:
                q.add_argument(item.flag, dest=item.name, type=Path, metavar=item.metavar,
                               help=item.help)  # fmt: skip
        q.add_argument("-o", "--out", type=Path, required=True, metavar="OUT",
                       help="output folder")  # fmt: skip
        add_option_arguments(q, spec.options)
        if spec.tasks:
            _add_engine_arguments(q)
        q.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
        q.set_defaults(func=cmd_model, spec=spec)


def _add_compare(sub) -> None:
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
        "--mesh", type=Path, metavar="MESH",
        help="the surface mesh the runs were made from: each run's levels of detail are "
        "scored by their RMS distance to it and their triangles (the LOD paper's Table 1)",
    )  # fmt: skip
    p.add_argument(
        "--tolerance",
        type=number("positive"),
        default=1.0,
        metavar="METRES",
        help="vertical tolerance of the 3D completeness and correctness (default 1)",
    )
    p.add_argument(
        "--max-error",
        type=number("positive"),
        default=2.0,
        metavar="METRES",
        help="the red end of the error colour maps (default 2)",
    )
    p.add_argument(
        "--seed", type=number("non_negative", int), default=0, help="seed of surface samples"
    )
    p.add_argument("--overwrite", action="store_true", help="replace REPORT if it exists")
    p.set_defaults(func=cmd_compare)


def _add_demo(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job on the tiny sample city",
        description="Generate the tiny sample city, fuse its views, model its buildings with "
        "the super-pixel path and with the voxel path (PLY and OBJ), score the three runs "
        "against the truth with `compare` and write the report.",
    )
    p.add_argument("-o", "--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--seed", type=number("non_negative", int), default=0,
                   help="random seed (default 0)")  # fmt: skip
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=cmd_demo)


def cmd_sample(args) -> int:
    from data_samples.generate import generate_sample
    from data_samples.presets import PRESETS, TRUE_DEPTH

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
    if args.true_depth:
        if args.depth_noise is not None:
            raise WorkbenchError("--depth-noise: not with --true-depth (its depth has no noise)")
        overrides.update(TRUE_DEPTH)
    if overrides:
        preset = preset.with_overrides(**overrides)
    if args.crs and not args.origin:
        raise WorkbenchError("--crs: give --origin E N with it")
    from .raster import parse_crs

    crs = parse_crs(args.crs, path="--crs", field="crs") if args.crs else None
    meta = generate_sample(
        args.out, preset, args.seed, overwrite=args.overwrite, origin=args.origin, crs=crs
    )
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


def cmd_import_odm(args) -> int:
    from .odm import import_odm

    path = import_odm(
        args.project, args.out, crs=args.crs, training_labels=args.training_labels,
        copy_images=args.copy_images, overwrite=args.overwrite,
    )  # fmt: skip
    print(f"wrote {path}")
    return 0


def cmd_fusion(args) -> int:
    from fusion.options import FusionOptions
    from fusion.run import run_fusion

    record = run_fusion(
        args.out, options_from_args(FusionOptions, args), scene=args.scene, points=args.points,
        mesh=args.mesh, crs=args.crs, truth=args.truth, save_classifier_to=args.save_classifier,
        overwrite=args.overwrite, command=args.command_line, scheduler=args.scheduler,
        resume=args.resume,
    )  # fmt: skip
    print(fusion_summary(record, args.out))
    return 0


def cmd_mesh(args) -> int:
    from fusion.scene_mesh import write_views_mesh
    from workbench.scene import load_scene

    out = args.out
    if out.suffix.lower() != ".ply":
        raise WorkbenchError(f"{out}: the mesh is written as PLY (name it .ply)")
    if out.exists() and not args.overwrite:
        raise WorkbenchError(f"{out}: exists (give --overwrite to replace it)")
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    r = write_views_mesh(out, scene, workers=args.workers, scheduler=args.scheduler,
                         resume=args.resume, voxel_m=args.voxel, trunc_voxels=args.trunc,
                         tile_m=args.tile)  # fmt: skip
    print(
        f"wrote {out}: {r['triangles']:,} triangles, {r['vertices']:,} vertices from "
        f"{r['views']} views at {r['voxel_m']:g} m voxels"
        f"{', ' + str(r['tiles']) + ' tiles' if r['tiles'] > 1 else ''}, "
        f"{time.perf_counter() - t0:.1f} s"
    )
    if r.get("worker_peak_memory_mb"):
        peaks = ", ".join(f"{p:.0f}" for p in r["worker_peak_memory_mb"])
        print(f"  tiles meshed by {r['workers']} Dask workers; their peak memory {peaks} MiB")
    return 0


def fusion_summary(record: dict, out: Path) -> str:
    """What ``workbench fusion`` prints: the grid, the time and the scores if any."""
    g = record["grid"]
    lines = [f"wrote {out}: {g['width']} x {g['height']} cells at {g['gsd']:g}, "
             f"{record['stages_total_s']:.1f} s"]  # fmt: skip
    q = record.get("quality", {})
    d, c = q.get("dsm", {}), q.get("classification", {})
    if d.get("rmse_m") is not None:
        off = d.get("rmse_off_jumps_m")
        off = f" ({off:.3f} m off height jumps)" if off is not None else ""
        lines.append(
            f"  DSM RMSE {d['rmse_m']:.3f} m{off}, median |e| {d['median_abs_m']:.3f} m, "
            f"valid {d['valid_fraction']:.1%}"
        )
    if c.get("overall_accuracy") is not None:
        per = ", ".join(f"{k} {v:.3f}" for k, v in c["per_class_accuracy"].items())
        lines.append(f"  classes: overall {c['overall_accuracy']:.3f} ({per})")
    if q.get("ortho_mae"):
        lines.append(f"  ortho MAE {q['ortho_mae']['mean']:.1f} / 255")
    return "\n".join(lines)


def cmd_model(args) -> int:
    from .atomic import check_output_dir
    from .model_run import write_model_run

    spec = args.spec
    check_output_dir(args.out, overwrite=args.overwrite)  # before the long work
    options = options_from_args(spec.options, args)
    positional = [getattr(args, i.name) for i in spec.inputs if i.flag is None]
    optional = {i.name: getattr(args, i.name) for i in spec.inputs if i.flag is not None}
    if not spec.tasks:
        run = spec.load()(*positional, options, **optional)
        record = write_model_run(run, args.out, overwrite=args.overwrite,
                                 command=args.command_line)  # fmt: skip
    else:
        from .engine import engine_for, run_signature

        spec.check_inputs(*positional, options, **optional)  # before the workers start
        signature = run_signature(options, {i.name: getattr(args, i.name) for i in spec.inputs})
        module = spec.run.split(":")[0]
        with engine_for(args.out, signature, workers=options.workers, scheduler=args.scheduler,
                        resume=args.resume, preload=(module,)) as engine:  # fmt: skip
            run = spec.load()(*positional, options, engine=engine, **optional)
            # the tasks are done: the workers' memory is free for the writing, and a live
            # cluster's threads slowed it (small's super-pixel model: 0.69 against 0.65 s)
            engine.close()
            record = write_model_run(run, args.out, overwrite=args.overwrite,
                                     command=args.command_line)  # fmt: skip
    print(model_summary(spec, record, args.out))
    return 0


def model_summary(spec, record: dict, out: Path) -> str:
    """What every ``workbench model`` prints: counts and total time, then the path's own
    lines (from model.json's record and, one at a time, its buildings')."""
    from .model_run import model_buildings

    c = record["counts"]
    total = sum(s["wall_s"] for s in record["stages"].values())
    lines = [
        f"wrote {out}: {c['buildings']} buildings, {c['faces']} triangles, "
        f"{c['watertight']} of {c['buildings']} watertight, {total:.1f} s"
    ]
    if c["buildings"] == 0:
        lines.append("  no buildings: the model is empty")
    failed = record.get("failed_tasks", [])
    if failed:
        stages = sorted({f["stage"] for f in failed})
        lines.append(f"  {len(failed)} task(s) failed and were left out ({', '.join(stages)}): "
                     "model.json's failed_tasks says why (-v: their tracebacks)")  # fmt: skip
    return "\n".join(lines + spec.summary_lines(record, model_buildings(out)))


def cmd_compare(args) -> int:
    from .compare import check_truth_args, compare_runs, summary
    from .evaluate import EvaluationOptions
    from .runs import load_run
    from .truth import open_file_truth, open_scene_truth

    check_truth_args(args)
    if args.truth is not None:
        truth = open_scene_truth(args.truth)
    else:
        first = load_run(args.runs[0])
        grid = crs = None
        if first.raster("dsm") or first.raster("class"):
            from .raster import raster_header

            grid, _, crs = raster_header(first.raster("dsm") or first.raster("class"))
        truth = open_file_truth(
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
        args.runs,
        truth,
        args.out,
        names=args.names,
        options=options,
        overwrite=args.overwrite,
        mesh=args.mesh,
    )
    print(summary(doc))
    print(f"report: {args.out / 'report.html'}")
    return 0


def cmd_demo(args) -> int:
    from data_samples.generate import generate_sample
    from fusion.options import FusionOptions
    from fusion.run import run_fusion
    from fusion.scene_mesh import integrate_views, write_scene_mesh
    from modeling import PATHS
    from modeling.blocks.options import BlocksOptions
    from modeling.blocks.path import run_blocks
    from modeling.lod.path import run_lod
    from modeling.parametric.path import run_parametric
    from modeling.superpixel.options import SuperpixelOptions
    from modeling.superpixel.path import run_superpixel
    from modeling.voxel.options import VoxelOptions
    from modeling.voxel.path import run_voxel

    from .atomic import check_output_dir
    from .compare import compare_runs, summary
    from .model_run import write_model_run
    from .scene import load_scene
    from .truth import open_scene_truth

    t0 = time.perf_counter()
    scene_dir, fusion_dir, report_dir = args.out / "scene", args.out / "fusion", args.out / "report"
    superpixel_dir, voxel_dir = args.out / "superpixel", args.out / "voxel"
    parametric_dir, blocks_dir = args.out / "parametric", args.out / "blocks"
    mesh_path, mesh_fusion_dir, lod_dir = (args.out / "mesh.ply", args.out / "mesh_fusion",
                                           args.out / "lod")  # fmt: skip
    check_output_dir(args.out, overwrite=args.overwrite)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"1/8 generating the tiny sample city (seed {args.seed}) ...", flush=True)
    meta = generate_sample(scene_dir, "tiny", args.seed, overwrite=True)
    c = meta["counts"]
    roofs = ", ".join(f"{n} {kind}" for kind, n in c["roof_types"].items())
    print(f"    {c['buildings']} buildings ({roofs}), {c['trees']} trees, {c['views']} views "
          f"with depth maps, calibration error {meta['calibration_error_px_rms']:.2f} px RMS, "
          f"in {meta['timing']['total']:.1f} s")  # fmt: skip
    print("2/8 fusing the views into ortho, DSM/DTM/nDSM and classes ...", flush=True)
    command = args.command_line
    record = run_fusion(fusion_dir, scene=scene_dir, truth=scene_dir, overwrite=True,
                        command=command)  # fmt: skip
    print("    " + fusion_summary(record, fusion_dir).replace("\n", "\n  "))
    q = record["quality"]
    print(
        f"      mean fusion instead of the median: DSM RMSE {q['dsm_mean_fusion']['rmse_m']:.2f} "
        f"m, ortho MAE {q['ortho_mae_mean_fusion']['mean']:.1f}"
    )
    print("3/8 super-pixel modeling: Quickshift, class CRF, roof prototypes, LOD2 ...", flush=True)
    run = run_superpixel(fusion_dir, SuperpixelOptions(seed=args.seed), truth=scene_dir)
    sp = write_model_run(run, superpixel_dir, overwrite=True, command=command)
    print("    " + model_summary(PATHS["superpixel"], sp, superpixel_dir).replace("\n", "\n  "))
    print("4/8 voxel modeling: photo-consistency proxies, surface graph cut textures ...",
          flush=True)  # fmt: skip
    run = run_voxel(scene_dir, VoxelOptions(seed=args.seed), fusion_dir=fusion_dir)
    vx = write_model_run(run, voxel_dir, overwrite=True, command=command)
    print("    " + model_summary(PATHS["voxel"], vx, voxel_dir).replace("\n", "\n  "))
    print("5/8 parametric modeling: level set, footprint priors, five-parameter roofs ...",
          flush=True)  # fmt: skip
    pm = write_model_run(run_parametric(fusion_dir), parametric_dir, overwrite=True,
                         command=command)  # fmt: skip
    print("    " + model_summary(PATHS["parametric"], pm, parametric_dir).replace("\n", "\n  "))
    print("6/8 block modeling: 2D supports, library of 3D blocks, RJMCMC ...", flush=True)
    bk = write_model_run(run_blocks(fusion_dir, BlocksOptions(seed=args.seed)), blocks_dir,
                         overwrite=True, command=command)  # fmt: skip
    print("    " + model_summary(PATHS["blocks"], bk, blocks_dir).replace("\n", "\n  "))
    print("7/8 LOD modeling from the views' mesh: TSDF mesh, orthogonal sampling, MRF "
          "labelling, regular roof planes, LOD0/1/2 ...", flush=True)  # fmt: skip
    scene = load_scene(scene_dir)
    mesh = integrate_views(scene)
    write_scene_mesh(mesh_path, mesh, scene.crs)
    run_fusion(mesh_fusion_dir, mesh=mesh_path, overwrite=True, command=command,
               options=FusionOptions(gsd=scene.gsd, bounds=tuple(scene.bounds)))  # fmt: skip
    ld = write_model_run(run_lod(mesh_fusion_dir, labels=scene_dir / "training" / "labels.tif"),
                         lod_dir, overwrite=True, command=command)  # fmt: skip
    print(
        f"    mesh {mesh.record['triangles']:,} triangles; "
        + model_summary(PATHS["lod"], ld, lod_dir).replace("\n", "\n  ")
    )
    print("8/8 scoring the runs against the truth ...", flush=True)
    doc = compare_runs(
        [fusion_dir, superpixel_dir, voxel_dir, parametric_dir, blocks_dir, lod_dir],
        open_scene_truth(scene_dir), report_dir,
        names=["fusion", "superpixel", "voxel", "parametric", "blocks", "lod"], overwrite=True,
    )  # fmt: skip
    print()
    print(summary(doc))
    print(f"  models:         {superpixel_dir / 'scene.obj'}, {voxel_dir / 'scene.obj'} (textured)")
    for name, folder in (("scene", scene_dir), ("fusion", fusion_dir), ("voxel", voxel_dir)):
        print(f"  {name + ' preview:':<15} {folder / 'preview.png'}")
    print(f"  report:         {report_dir / 'report.html'}")
    print(f"demo finished in {time.perf_counter() - t0:.1f} s")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    args.command_line = ["workbench", *map(str, argv)]
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.verbose:  # our own debug messages, not every library's
        for name in ("workbench", "fusion", "modeling", "data_samples"):
            logging.getLogger(name).setLevel(logging.DEBUG)
    if getattr(args, "resume", False):  # say what is kept
        for name in ("workbench.engine", "fusion.blocks"):
            logging.getLogger(name).setLevel(logging.INFO)
    try:
        return args.func(args)
    except WorkbenchError as exc:
        print(f"workbench: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"workbench: interrupted{_kept(args)}", file=sys.stderr)
        return 130
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            return _internal_error(exc, args)
        # a file the command itself was writing (a task's result says so already); the
        # output is written atomically, so nothing of it is left
        print(f"workbench: error: {exc.filename or 'a file'}: disk full{_kept(args)}",
              file=sys.stderr)  # fmt: skip
        return 2
    except Exception as exc:  # noqa: BLE001 - never a bare traceback from the CLI
        return _internal_error(exc, args)


def _internal_error(exc: Exception, args) -> int:
    """The one line of an error the workbench did not foresee; 1."""
    if args.verbose:
        traceback.print_exc()
    msg = str(exc).splitlines()[0] if str(exc) else ""
    print(
        f"workbench: internal error: {type(exc).__name__}: {msg} (run with -v for the traceback)",
        file=sys.stderr,
    )
    return 1


def _kept(args) -> str:
    """What an interrupted command kept for --resume, if anything."""
    from .engine import partial_folder

    out = getattr(args, "out", None)
    if out is None or not partial_folder(out).exists():
        return ""
    return f"; the finished tasks are kept in {partial_folder(out)}: run again with --resume"


if __name__ == "__main__":
    sys.exit(main())
