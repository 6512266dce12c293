"""A fusion run end to end: options in, products and fusion.json out."""

from __future__ import annotations

import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from workbench.atomic import atomic_output_dir, check_output_dir
from workbench.engine import engine_for, run_signature
from workbench.errors import WorkbenchError
from workbench.metrics import classification, colour_mae, height_errors
from workbench.options import options_record
from workbench.raster import class_codes
from workbench.records import StageTimer, provenance
from workbench.scene import load_scene
from workbench.truth import truth_rasters

from .blocks import block_size, check_disk, fuse_in_blocks, planned_grid
from .classifier import save_classifier
from .options import FusionOptions
from .outputs import FusionWindows, read_fusion, write_fusion, write_record
from .raster_forest import classify_rasters, synthetic_raster_forest
from .scene_fusion import check_height_source, feature_set, fuse_views

log = logging.getLogger(__name__)


def run_fusion(
    out: Path,
    options: FusionOptions | None = None,
    *,
    scene: Path | None = None,
    points: Path | list[Path] | None = None,
    mesh: Path | None = None,
    crs: str | None = None,
    truth: Path | None = None,
    save_classifier_to: Path | None = None,
    overwrite: bool = False,
    command: list[str] | None = None,
    scheduler: str | None = None,
    resume: bool = False,
) -> dict:
    """Fuse a scene's views (or a point cloud) and write the run folder ``out``.

    Parameters
    ----------
    out : path
        The run folder (written atomically).
    options : FusionOptions
    scene, points, mesh : path, or paths for ``points``
        Exactly one: a scene folder, LAS/LAZ/PLY clouds (tiles, or folders of them), or a
        surface mesh (sampled by vertical rays, :mod:`fusion.mesh_sampling`).
    crs : str, optional
        CRS of clouds or a mesh that carry none (EPSG code or WKT).
    truth : path, optional
        A scene with truth/: the products' scores go into fusion.json.
    save_classifier_to : path, optional
        Where to save the trained per-view forest.
    command : list of str, optional
        The command line that asked for the run, for its record.
    scheduler : str, optional
        A Dask scheduler's address: its workers run the views' and tiles' tasks
        (default: a local cluster of ``options.workers`` processes, or this process for 1).
    resume : bool
        Keep the tasks an interrupted run of the same fusion finished.

    Returns
    -------
    The fusion.json record.
    """
    if sum(x is not None for x in (scene, points, mesh)) != 1:
        raise WorkbenchError("fusion: give one of SCENE, --points CLOUD and --mesh MESH")
    check_output_dir(out, overwrite=overwrite)  # before the long work
    options = options or FusionOptions()
    t0 = time.perf_counter()
    if mesh is not None:
        return _fuse_mesh(out, mesh, crs, options, truth, overwrite, command, t0, scheduler,
                          resume)  # fmt: skip
    if points is not None:
        return _fuse_points(out, points, crs, options, truth, overwrite, command, t0,
                            scheduler, resume)  # fmt: skip
    loaded = load_scene(scene)
    check_height_source(loaded)  # before the workers start: bad input stops at once
    inputs = {"scene": str(loaded.scene_json), "views": len(loaded.views)}
    signature = run_signature(options, {"scene": scene})
    grid = planned_grid(loaded, options)
    block_m = block_size(grid, options)
    if block_m is not None:
        check_disk(grid, Path(out).absolute().parent)
    with engine_for(out, signature, workers=options.workers, scheduler=scheduler,
                    resume=resume, preload=("fusion.scene_fusion",)) as engine:  # fmt: skip
        if block_m is not None:
            return _fuse_blocks(out, loaded, grid, block_m, engine, inputs, options, truth,
                                save_classifier_to, overwrite, command, t0)  # fmt: skip
        result = fuse_views(loaded, options, engine)
        return _write(out, result, loaded.crs, inputs, options, truth, save_classifier_to,
                      overwrite, command, t0)  # fmt: skip


def _record(grid, crs, inputs, options, figures: dict, command, t0) -> dict:
    """The run's record: what made it, its grid, the fusion's own figures."""
    g = grid
    return {
        "provenance": provenance(command),
        "inputs": inputs,
        "parameters": options_record(options),
        "grid": {
            "xmin": g.xmin, "ymax": g.ymax, "gsd": g.gsd, "width": g.width, "height": g.height,
            "crs": crs.to_string() if crs else None,
        },
        **figures,
        "stages_total_s": round(time.perf_counter() - t0, 3),
    }  # fmt: skip


def _write(out, result, crs, inputs, options, truth, save_classifier_to, overwrite, command, t0):
    """The run's record (scored against ``truth`` if given), and the run folder written
    atomically; returns the record."""
    record = _record(result.grid, crs, inputs, options, result.record, command, t0)
    if truth is not None:
        record["quality"] = fusion_quality(result, truth)
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        write_fusion(tmp, result, crs, record)
        _save_forest(save_classifier_to, result.forest, record, options)
    return record


def _save_forest(path, forest, record: dict, options: FusionOptions) -> None:
    if path is not None and forest is not None:
        save_classifier(path, forest, features=feature_set(options),
                        meta={"trained_on": record["inputs"], "seed": options.seed})  # fmt: skip


def _fuse_blocks(out, scene, grid, block_m, engine, inputs, options, truth, save_classifier_to,
                 overwrite, command, t0):  # fmt: skip
    """The fusion block by block (:mod:`fusion.blocks`), its rasters written window by
    window into the run folder, which appears atomically; returns the record. Scoring
    against ``truth`` reads the whole rasters back."""
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        windows = FusionWindows(tmp, grid, scene.crs, ceiling=True)
        try:
            grid, figures, forest = fuse_in_blocks(scene, options, engine, windows, block_m)
        except BaseException:
            windows.discard()
            raise
        record = _record(grid, scene.crs, inputs, options, figures, command, t0)
        _close_windows(tmp, windows, record, truth)
        _save_forest(save_classifier_to, forest, record, options)
    return record


def _close_windows(tmp: Path, windows: FusionWindows, record: dict, truth) -> None:
    """The rasters written window by window closed with the run's record, scored against
    ``truth`` if given (which reads the whole rasters back)."""
    windows.close(record)
    if truth is not None:
        record["quality"] = fusion_quality(read_fusion(tmp), truth)
        write_record(tmp, record)


def _fuse_mesh(out, path, crs, options, truth, overwrite, command, t0, scheduler,
               resume) -> dict:  # fmt: skip
    """A mesh's fusion: whole up to 4096 cells a side (or ``--block``), else sampled in
    this process and its blocks made as tasks of the engine
    (:func:`~fusion.mesh_sampling.fuse_mesh_in_blocks`), its rasters written window by
    window into the run folder, which appears atomically; returns the record."""
    from .mesh_sampling import (
        fuse_mesh_in_blocks,
        fuse_opened_mesh,
        mesh_inputs,
        mesh_record,
        mesh_workers,
        opened_mesh,
    )

    timer = StageTimer()
    mesh, grid = opened_mesh(path, options, crs, timer)
    block_m = block_size(grid, options)
    if block_m is None:
        if scheduler is not None or resume:
            log.warning("--scheduler and --resume apply to a mesh in blocks (--block); "
                        "this one is sampled whole in this process")  # fmt: skip
        result, crs, inputs = fuse_opened_mesh(mesh, grid, options, timer, t0)
        return _write(out, result, crs, inputs, options, truth, None, overwrite, command, t0)
    parent = Path(out).absolute().parent
    check_disk(grid, parent)
    signature = run_signature(options, {"mesh": path})
    signature["crs"] = crs
    workers = mesh_workers(grid, block_m, options)
    with engine_for(out, signature, workers=workers, scheduler=scheduler, resume=resume,
                    preload=("fusion.mesh_sampling",)) as engine, \
            atomic_output_dir(out, overwrite=overwrite) as tmp, \
            tempfile.TemporaryDirectory(prefix=".mesh-scratch-",
                                        dir=parent) as scratch:  # fmt: skip
        windows = FusionWindows(tmp, grid, mesh.crs)
        try:
            figures = fuse_mesh_in_blocks(mesh, grid, options, timer, windows,
                                          tmp / "normal.tif", block_m, Path(scratch),
                                          engine)  # fmt: skip
        except BaseException:
            windows.discard()
            raise
        record = _record(grid, mesh.crs, mesh_inputs(mesh), options,
                         mesh_record(mesh, options, figures, timer, t0), command, t0)  # fmt: skip
        _close_windows(tmp, windows, record, truth)
    return record


def _fuse_points(out, paths, crs, options, truth, overwrite, command, t0, scheduler,
                 resume) -> dict:  # fmt: skip
    """A survey's fusion: its tiles read once into a scratch folder beside ``out``
    (:func:`~fusion.cloud_survey.spilled_survey`), then rasterised whole, or block by
    block as tasks of the engine (:func:`~fusion.points.fuse_points_in_blocks`) into
    windows of the run folder, which appears atomically; returns the record."""
    from .cloud_survey import spilled_survey
    from .points import (
        cloud_block_size,
        fuse_points_in_blocks,
        fuse_survey,
        point_workers,
        points_inputs,
        points_record,
    )

    timer = StageTimer()
    parent = Path(out).absolute().parent
    parent.mkdir(parents=True, exist_ok=True)  # as the output's atomic folder would
    with tempfile.TemporaryDirectory(prefix=".points-scratch-", dir=parent) as scratch:
        with timer.stage("read"):
            survey = spilled_survey(paths, options, crs, Path(scratch))
        grid = survey.grid(options)
        block = cloud_block_size(grid, survey, options)
        if block is None:
            if scheduler is not None or resume:
                log.warning("--scheduler and --resume apply to a cloud in blocks (--block); "
                            "this one is rasterised whole in this process")  # fmt: skip
            result, crs, inputs = fuse_survey(survey, grid, options, timer)
            return _write(out, result, crs, inputs, options, truth, None, overwrite, command,
                          t0)  # fmt: skip
        check_disk(grid, parent)
        signature = run_signature(options, {"points": survey.files})
        with engine_for(out, signature, workers=point_workers(options), scheduler=scheduler,
                        resume=resume, preload=("fusion.points",)) as engine, \
                atomic_output_dir(out, overwrite=overwrite) as tmp:  # fmt: skip
            windows = FusionWindows(tmp, grid, survey.crs)
            try:
                figures = fuse_points_in_blocks(survey, grid, options, timer, windows, block,
                                                engine)  # fmt: skip
            except BaseException:
                windows.discard()
                raise
            figures = points_record(survey, options, figures, timer)
            record = _record(grid, survey.crs, points_inputs(survey), options, figures, command,
                             t0)  # fmt: skip
            _close_windows(tmp, windows, record, truth)
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
        if result.class_map is not None:  # the ablation of the class CRF and planar objects
            q["classification_most_probable"] = classification(
                class_codes(result.class_prob), t["class"]
            )
        # what the label-free raster forest alone would give, for comparison
        g = result.grid
        raster = classify_rasters(
            synthetic_raster_forest(), result.dsm, result.dtm, result.ortho, g.gsd
        )
        seen = np.isfinite(raster[0])
        alone = np.where(seen, np.argmax(np.nan_to_num(raster), axis=0) + 1, 0)
        q["classification_raster_forest_alone"] = classification(alone, t["class"])
    return q
