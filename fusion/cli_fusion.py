"""The ``workbench fusion`` command: options in, products and fusion.json out."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from workbench.atomic import atomic_output_dir
from workbench.metrics import classification, colour_mae, height_errors
from workbench.scene import load_scene
from workbench.truth import truth_rasters

from .classifier import save_classifier
from .outputs import write_fusion
from .raster_forest import classify_rasters, synthetic_raster_forest
from .scene_fusion import FEATURES, FusionOptions, fuse_views


def fusion_arguments(**given) -> SimpleNamespace:
    """The arguments of ``workbench fusion`` with the command line's defaults, for callers
    that run it from Python (the demo, the benchmarks); ``given`` overrides them."""
    defaults = dict(
        scene=None, points=None, out=None, gsd=None, bounds=None, crs=None, truth=None,
        classifier=None, save_classifier=None, raster_prior=False, label_split=1.0, seed=0,
        workers=None, overwrite=False,
    )  # fmt: skip
    unknown = set(given) - set(defaults)
    if unknown:
        raise TypeError(f"unknown fusion arguments: {sorted(unknown)}")
    return SimpleNamespace(**{**defaults, **given})


def run_fusion(args) -> dict:
    """Run fusion for parsed CLI arguments; return the fusion.json record."""
    t0 = time.perf_counter()
    opts = FusionOptions(
        gsd=args.gsd,
        bounds=tuple(args.bounds) if args.bounds else None,
        seed=args.seed,
        classifier=args.classifier,
        raster_prior=args.raster_prior,
        label_split=args.label_split,
        workers=args.workers,
    )
    if args.points is not None:
        from .points import fuse_points

        result, crs, inputs = fuse_points(args.points, opts, crs=args.crs)
    else:
        scene = load_scene(args.scene)
        result = fuse_views(scene, opts)
        crs = scene.crs
        inputs = {"scene": str(scene.scene_json), "views": len(scene.views)}
    g = result.grid
    record = {
        "inputs": inputs,
        "parameters": {
            k: (str(v) if v is not None and not isinstance(v, int | float | tuple) else v)
            for k, v in vars(opts).items()
        },
        "grid": {
            "xmin": g.xmin,
            "ymax": g.ymax,
            "gsd": g.gsd,
            "width": g.width,
            "height": g.height,
            "crs": crs.to_string() if crs else None,
        },
        **result.record,
        "stages_total_s": round(time.perf_counter() - t0, 3),
    }
    if args.truth is not None:
        record["quality"] = fusion_quality(result, args.truth)
    with atomic_output_dir(args.out, overwrite=args.overwrite) as tmp:
        write_fusion(tmp, result, crs, record)
        if args.save_classifier is not None and result.forest is not None:
            save_classifier(
                args.save_classifier,
                result.forest,
                features=FEATURES,
                meta={"trained_on": record["inputs"], "seed": args.seed},
            )
    return record


def fusion_quality(result, truth_scene) -> dict:
    """Scores of the fused products against the truth, with the median-vs-mean ablation."""
    t = truth_rasters(truth_scene, result.grid)
    q = {}
    if "dsm" in t:
        q["dsm"] = height_errors(result.dsm, t["dsm"])
        if "dsm_mean" in result.ablation:  # views only: a cloud has one height per cell
            q["dsm_mean_fusion"] = height_errors(result.ablation["dsm_mean"], t["dsm"])
    if "dtm" in t:
        q["dtm"] = height_errors(result.dtm, t["dtm"])
    if "ortho" in t:
        seen = result.count != 0
        q["ortho_mae"] = colour_mae(result.ortho, t["ortho"], seen)
        if "ortho_mean" in result.ablation:
            mean = result.ablation["ortho_mean"]
            ok = seen & np.isfinite(mean[..., 0])
            q["ortho_mae_mean_fusion"] = colour_mae(np.round(mean), t["ortho"], ok)
    if "class" in t and np.isfinite(result.class_prob).any():
        q["classification"] = classification(result.classes, t["class"])
        # what the label-free raster forest alone would give, for comparison
        g = result.grid
        raster = classify_rasters(
            synthetic_raster_forest(), result.dsm, result.dtm, result.ortho, g.gsd
        )
        seen = np.isfinite(raster[0])
        alone = np.where(seen, np.argmax(np.nan_to_num(raster), axis=0) + 1, 0)
        q["classification_raster_forest_alone"] = classification(alone, t["class"])
    return q
