"""`workbench compare`: score runs against the same truth into metrics.json and a report."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from .atomic import atomic_output_dir
from .cityjson_check import lod_meshes
from .errors import InputError, WorkbenchError
from .evaluate import (
    Evaluation,
    EvaluationOptions,
    RunLayers,
    evaluate,
    picture_stride,
    stacked_meshes,
    truth_overview,
)
from .imageio import write_rgb
from .meshes import concatenate_meshes, raster_mesh, read_mesh, sample_surface, triangle_areas
from .pictures import colorize_classes, colorize_error, colorize_height
from .raycast import raycasting_scene, unsigned_distance
from .render import render_mesh, viewpoints
from .report import report_html, summary_text
from .runs import Run, load_run
from .truth import Truth

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1


def compare_runs(
    folders: list[Path],
    truth: Truth,
    out: Path,
    *,
    names: list[str] | None = None,
    options: EvaluationOptions | None = None,
    overwrite: bool = False,
    mesh: Path | None = None,
) -> dict:
    """Score every run folder against ``truth`` and write ``out/metrics.json``,
    ``out/report.html`` and ``out/figures/*.png``. With ``mesh`` (the surface mesh the
    runs were made from), each model run's levels of detail in model.city.json are scored
    by their RMS distance to it and their triangles (the LOD paper's Table 1).

    Returns
    -------
    The metrics.json document.
    """
    options = options or EvaluationOptions()
    if names is not None and len(names) != len(folders):
        raise WorkbenchError(f"--names: {len(names)} names for {len(folders)} runs")
    names = names or _default_names(folders)
    if len(set(names)) != len(names):
        raise WorkbenchError(f"--names: run names must differ, got {names}")
    runs = [load_run(f, n) for f, n in zip(folders, names, strict=True)]
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        evaluations, run_figures = {}, {}
        # the maps of the report: every few cells of a city's grid (a few MB each)
        overview = truth_overview(truth, picture_stride(truth.grid), options.window_cells)
        reference = _reference_surface(overview)
        for run in runs:
            t0 = time.perf_counter()
            e = evaluations[run.name] = evaluate(run, truth, options)
            run_figures[run.name] = run_pictures(e.overview, overview, reference, options)
            e.overview = None
            log.info("scored %s in %.1f s", run.name, time.perf_counter() - t0)
        if mesh is not None:
            scene = raycasting_scene(*read_mesh(mesh))
            for run in runs:
                lods = lod_accuracy(run, scene, options.seed)
                if lods:
                    evaluations[run.name].metrics["lods"] = lods
        doc = {
            "schema_version": SCHEMA_VERSION,
            "truth": {"grid": _grid_info(truth), "sources": truth.sources},
            "options": vars(options),
            "runs": {n: e.metrics for n, e in evaluations.items()},
            "per_building": {n: e.buildings for n, e in evaluations.items()},
            "run_folders": {r.name: str(r.folder.absolute()) for r in runs},
        }
        (tmp / "metrics.json").write_text(json.dumps(doc, indent=1))
        truth_figures = truth_pictures(overview)
        renders = _renders(runs, evaluations, truth, overview, options)
        (tmp / "figures").mkdir()
        named = [("truth", truth_figures), ("render", renders)]
        named += [(f"run_{n}", items) for n, items in run_figures.items()]
        for key, items in named:
            for img, caption in items:
                write_rgb(tmp / "figures" / f"{_slug(key)}-{_slug(caption)}.png", img)
        page = report_html(
            runs=doc["runs"],
            buildings=doc["per_building"],
            truth_info={"grid": _grid_info(truth), **truth.sources},
            truth_figures=truth_figures,
            renders=renders,
            run_figures=run_figures,
            max_error_m=options.max_error_m,
        )
        (tmp / "report.html").write_text(page)
    return doc


def lod_accuracy(run: Run, scene, seed: int = 0, spacing_m: float = 0.5) -> dict:
    """{lod: {"rms_to_mesh_m", "mean_to_mesh_m", "triangles"}} of a model run's
    model.city.json: the distance from points spread over each level's surfaces (one per
    ``spacing_m`` squared, at most 200,000) to the input mesh ``scene`` (a RayScene). The
    solids' ground surfaces are left out: a surface mesh has no floor under a building, so
    they would count their distance to its walls; the triangles are the whole model's."""
    path = run.folder / "model.city.json"
    if run.kind != "model" or not path.exists():
        return {}
    rng = np.random.default_rng(seed)
    out = {}
    doc = json.loads(path.read_text())
    whole = lod_meshes(doc)
    for lod, (V, T) in sorted(lod_meshes(doc, skip=("GroundSurface",)).items()):
        area = float(triangle_areas(V, T).sum())
        n = int(min(200_000, max(1000, area / spacing_m**2)))
        points, _ = sample_surface(V, T, n, rng)
        d = unsigned_distance(scene, points)
        out[lod] = {
            "rms_to_mesh_m": round(float(np.sqrt(np.mean(d**2))), 4),
            "mean_to_mesh_m": round(float(d.mean()), 4),
            "triangles": int(len(whole[lod][1])),
        }
    return out


def summary(doc: dict) -> str:
    """The terminal table of a metrics.json document."""
    return summary_text(doc["runs"])


def _default_names(folders: list[Path]) -> list[str]:
    names = [Path(f).name for f in folders]
    if len(set(names)) == len(names):
        return names
    return [f"{n}-{i + 1}" for i, n in enumerate(names)]


def _grid_info(truth: Truth) -> dict:
    g = truth.grid
    return {"xmin": g.xmin, "ymax": g.ymax, "gsd": g.gsd, "width": g.width, "height": g.height}


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text.lower()).strip("_")[:40]


Figures = list[tuple[np.ndarray, str]]


def truth_pictures(truth: Truth) -> Figures:
    """Pictures of the truth (its :func:`~workbench.evaluate.truth_overview`): its ortho,
    classes and DSM where it has them."""
    out = []
    if truth.ortho is not None:
        out.append((truth.ortho, "true ortho"))
    if truth.cls is not None:
        out.append((colorize_classes(truth.cls), "true classes"))
    if truth.dsm is not None:
        out.append((colorize_height(truth.dsm), "true DSM"))
    return out


def run_pictures(
    layers: RunLayers, truth: Truth, reference: np.ndarray | None, options: EvaluationOptions
) -> Figures:
    """Pictures of one run on the grid (its and the truth's overviews): its footprints
    against the truth's, its height error against ``reference``
    (:func:`_reference_surface`), its classes."""
    items = []
    if truth.building_ids is not None:
        items.append((footprint_map(layers.building_ids > 0, truth.building_ids > 0),
                      "footprints"))  # fmt: skip
    if reference is not None:
        on = (layers.building_ids > 0) | (truth.building_ids > 0)
        err = np.where(on, np.abs(layers.surface - reference), np.nan)
        items.append((colorize_error(err, options.max_error_m), "height error"))
    if layers.cls is not None:
        items.append((colorize_classes(layers.cls), "classes"))
    return items


def _reference_surface(truth: Truth) -> np.ndarray | None:
    """The true buildings over the true ground: what a model of buildings should match."""
    if truth.building_surface is None or truth.dtm is None:
        return None
    return np.where(truth.building_ids > 0, truth.building_surface, truth.dtm)


def footprint_map(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: true positives green, false positives red, false negatives blue,
    the rest white."""
    img = np.full(pred.shape + (3,), 255, np.uint8)
    img[pred & true] = (40, 170, 40)
    img[pred & ~true] = (220, 40, 40)
    img[~pred & true] = (40, 80, 230)
    return img


def _renders(
    runs: list[Run],
    evaluations: dict[str, Evaluation],
    truth,
    overview: Truth,
    options: EvaluationOptions,
) -> list[tuple[np.ndarray, str]]:
    models = [r for r in runs if r.kind == "model" and r.buildings]
    if not models:
        return []
    if truth.mesh is not None:
        z = truth.mesh.vertices[:, 2]
    else:
        z = np.concatenate([b.vertices[:, 2] for r in models for b in r.buildings])
    cams = viewpoints(truth.grid.bounds, (float(z.min()), float(z.max())))
    step = max(1, round(8 * truth.grid.gsd / overview.grid.gsd))  # a ground vertex every 8 cells
    ground = raster_mesh(overview.dtm, overview.grid, step) if overview.dtm is not None else None

    def picture(vertices, triangles, cam, colors=None):
        if ground is not None:  # the same pale ground under every model
            colors = np.full((len(triangles), 3), 200, np.uint8) if colors is None else colors
            pale = np.full((len(ground[1]), 3), 235, np.uint8)
            vertices, triangles, _ = concatenate_meshes([(vertices, triangles), ground])
            colors = np.concatenate([colors, pale])
        return render_mesh(vertices, triangles, cam, colors)

    out = []
    if truth.mesh is not None:
        for view, cam in cams.items():
            img = picture(truth.mesh.vertices, truth.mesh.triangles, cam)
            out.append((img, f"true buildings, {view}"))
    for run in models:
        vertices, triangles, _ = stacked_meshes(run)
        err = evaluations[run.name].face_error
        for view, cam in cams.items():
            out.append((picture(vertices, triangles, cam), f"{run.name}, {view}"))
        if err is not None:
            colors = colorize_error(err, options.max_error_m)
            for view, cam in cams.items():
                img = picture(vertices, triangles, cam, colors)
                out.append((img, f"{run.name}, error, {view}"))
    return out


def check_truth_args(args) -> None:
    """One of --truth or the --truth-* files must be given."""
    loose = [args.truth_dsm, args.truth_footprints, args.truth_class, args.truth_dtm]
    if args.truth is None and all(x is None for x in loose):
        raise WorkbenchError("compare: give --truth SCENE or at least one --truth-* file")
    if args.truth is not None and any(x is not None for x in loose):
        raise WorkbenchError("compare: --truth SCENE and --truth-* files exclude each other")
    for path in [args.truth, *loose]:
        if path is not None and not Path(path).exists():
            raise InputError(path, None, "no such file or folder")
