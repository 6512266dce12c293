"""``make bench``: wall time, throughput and peak memory per stage.

Each measurement runs in a fresh child process, which reports its own peak resident
memory (``peak_memory_mb``: the rusage of a child counts the size of the parent it was
forked from). Medians over ``--repeat`` runs; this machine is noisy.

Measured: sample generation (tiny, small), workbench compare, fusion of small, the
super-pixel, parametric, blocks and voxel paths on small (with the voxel paper's robustness
experiment), the TSDF mesh of small's views, its orthogonal sampling and the LOD path on
it, what a noise-free sensor would score on small's height metrics
(benchmarks/height_floor.py), what the super-pixel path's class CRF can reach
(benchmarks/crf_ceiling.py), the 50 AHN3 building clouds (benchmarks/ahn3.py), and
terraced blocks from LiDAR tiles, the super-pixel path on one building region of ~30,000
cells (benchmarks/terrace.py).

Then every registered path on ``small`` seeds 0-5 (:mod:`seeds`): the defaults were chosen
on seeds 0-2, seeds 3-5 are held out. Everything printed is also written to
``docs/benchmarks.md``, with the commit it measured.

``--preset city`` runs instead the 1 km² city and small end to end, command by command
(:mod:`city`), the city's fusion and its super-pixel, parametric and block paths also in
blocks of 250 m (each against small's one grid), and writes ``docs/benchmarks-city.md``.

Usage: python benchmarks/run.py [--presets tiny small] [--repeat 3] [--out bench_out]
       [--seeds 0 1 2 3 4 5] [--doc docs/benchmarks.md] [--preset small|city]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from city import BLOCK_PATHS, city_run, print_city
from crf_ceiling import crf_ceiling, print_ceiling
from height_floor import height_floor
from seeds import HELD_OUT, TUNED, run_seed, tables

CHILD = r"""
import json, sys
from data_samples.generate import generate_sample
meta = generate_sample(sys.argv[1], sys.argv[2], int(sys.argv[3]), overwrite=True)
print(json.dumps({"timing": meta["timing"], "counts": meta["counts"],
                  "image_size": meta["preset"]["image_size"],
                  "quality": {k: meta[k] for k in ("calibration_error_px_rms",
                              "depth_maps_median_over_views", "gis_footprints", "coverage",
                              "training_label_fraction")}}))
"""


_REPORT_PEAK = "\nfrom workbench.records import peak_memory_mb\nprint(peak_memory_mb())\n"


def run_child(code: str, *args: str) -> tuple[dict, float, float]:
    """Run ``code`` in a child Python; return its JSON output (its last line), wall
    seconds, and its peak RSS in MiB."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", code + _REPORT_PEAK, *args], stdout=subprocess.PIPE, text=True
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"benchmark child failed ({proc.returncode}): {' '.join(args)}")
    *_, result, peak = proc.stdout.strip().splitlines()
    return json.loads(result), wall, float(peak)


def bench_sample(preset: str, repeat: int, work: Path) -> dict:
    runs = []
    for i in range(repeat):
        res, wall, rss = run_child(CHILD, str(work / f"{preset}_{i}"), preset, "0")
        runs.append((res, wall, rss))
    stages = runs[0][0]["timing"].keys()
    med = {s: statistics.median(r[0]["timing"][s] for r in runs) for s in stages}
    counts = runs[0][0]["counts"]
    w, h = runs[0][0]["image_size"]
    pixels = counts["views"] * w * h
    return {
        "preset": preset,
        "repeat": repeat,
        "stage_median_s": med,
        "process_wall_median_s": statistics.median(r[1] for r in runs),
        "peak_memory_mib": max(r[2] for r in runs),
        "views": counts["views"],
        "buildings": counts["buildings"],
        "triangles": counts["triangles"],
        "views_per_s": counts["views"] / med["views"],
        "rendered_mpx_per_s": pixels / med["views"] / 1e6,
        "spread_total_s": [round(r[0]["timing"]["total"], 2) for r in runs],
        "quality": runs[0][0]["quality"],
    }


FUSION_CHILD = r"""
import json, sys
from fusion.options import FusionOptions
from fusion.run import run_fusion
workers = int(sys.argv[3]) if len(sys.argv) > 3 else None
r = run_fusion(sys.argv[2], FusionOptions(workers=workers), scene=sys.argv[1],
               truth=sys.argv[1], overwrite=True)
print(json.dumps({k: r.get(k) for k in ("stages", "observations", "observations_per_s",
                                        "classification_mpx_per_s", "quality", "grid",
                                        "workers", "engine", "worker_peak_memory_mb")}))
"""

READ_CHILD = r"""
import json, sys, time
from workbench.scene import load_scene
s = load_scene(sys.argv[1])
t = time.perf_counter()
n = 0
for v in s.views:
    n += v.read_image().size + v.read_depth().size
print(json.dumps({"read_s": time.perf_counter() - t, "values": n}))
"""


def stage_medians(runs: list[tuple[dict, float, float]]) -> dict:
    """Median wall time of every stage over child runs that report ``stages``."""
    first = runs[0][0]["stages"]
    return {k: statistics.median(r[0]["stages"][k]["wall_s"] for r in runs) for k in first}


def bench_fusion(scene: Path, repeat: int, work: Path) -> dict:
    runs = [run_child(FUSION_CHILD, str(scene), str(work / f"fusion_{i}")) for i in range(repeat)]
    reads = [run_child(READ_CHILD, str(scene))[0]["read_s"] for _ in range(3)]
    res = runs[0][0]
    walls = [sum(st["wall_s"] for st in r[0]["stages"].values()) for r in runs]
    stages = stage_medians(runs)
    # in this process alone, once: what the workers buy on this machine
    single, _, single_peak = run_child(FUSION_CHILD, str(scene), str(work / "fusion_w1"), "1")
    return {
        "repeat": repeat,
        "workers": res["workers"],
        "one_worker": {
            "fusion_s": sum(st["wall_s"] for st in single["stages"].values()),
            "observations_per_s": single["observations_per_s"],
            "classification_mpx_per_s": single.get("classification_mpx_per_s"),
            "peak_memory_mib": single_peak,
        },
        "stage_median_s": stages,
        "fusion_median_s": statistics.median(walls),
        "read_inputs_once_median_s": statistics.median(reads),
        "ratio_fusion_to_read": statistics.median(walls) / statistics.median(reads),
        "observations": res["observations"],
        "observations_per_s": statistics.median(r[0]["observations_per_s"] for r in runs),
        "classification_mpx_per_s": res.get("classification_mpx_per_s"),
        "peak_memory_mib": max(r[2] for r in runs),
        "engine": res.get("engine"),
        "worker_peak_memory_mib": res.get("worker_peak_memory_mb"),
        "grid": res["grid"],
        "quality": res["quality"],
    }


COMPARE_CHILD = r"""
import json, sys, time
from pathlib import Path
from data_samples.truth_run import truth_model_run
from workbench.compare import compare_runs
from workbench.truth import load_scene_truth
scene, work = Path(sys.argv[1]), Path(sys.argv[2])
runs = [truth_model_run(scene, work / "truth_run")] + [Path(p) for p in sys.argv[3:]]
t = time.perf_counter()
truth = load_scene_truth(scene)
doc = compare_runs(runs, truth, work / "report", overwrite=True)
wall = time.perf_counter() - t
g = doc["truth"]["grid"]
print(json.dumps({"wall_s": wall, "cells": g["width"] * g["height"], "runs": len(runs),
                  "buildings": len(doc["per_building"]["truth_run"]),
                  "report_mb": (work / "report" / "report.html").stat().st_size / 1e6}))
"""


def bench_compare(scene: Path, extra_runs: list[Path], repeat: int, work: Path) -> dict:
    runs = []
    for i in range(repeat):
        folder = work / f"compare_{scene.name}_{len(extra_runs)}_{i}"
        res, wall, rss = run_child(COMPARE_CHILD, str(scene), str(folder), *map(str, extra_runs))
        runs.append((res, rss))
    res = runs[0][0]
    wall = statistics.median(r[0]["wall_s"] for r in runs)
    return {
        "scene": scene.name,
        "runs": res["runs"],
        "buildings": res["buildings"],
        "cells": res["cells"],
        "wall_median_s": wall,
        "s_per_run_per_mcell": wall / res["runs"] / (res["cells"] / 1e6),
        "peak_memory_mib": max(r[1] for r in runs),
        "report_mb": res["report_mb"],
    }


def print_compare(c: dict) -> None:
    print(
        f"\nworkbench compare on {c['scene']} ({c['runs']} runs, {c['buildings']} buildings, "
        f"{c['cells'] / 1e6:.2f} M cells), median: {c['wall_median_s']:.1f} s, "
        f"{c['s_per_run_per_mcell']:.1f} s per run per M cells, peak memory "
        f"{c['peak_memory_mib']:.0f} MiB, report {c['report_mb']:.1f} MB"
    )


SUPERPIXEL_CHILD = r"""
import json, sys
from pathlib import Path
from modeling.superpixel.options import SuperpixelOptions
from modeling.superpixel.path import run_superpixel
from workbench.model_run import write_model_run
from workbench.evaluate import evaluate
from workbench.runs import load_run
from workbench.truth import load_scene_truth
from workbench.engine import start_engine
fusion, scene, out = (Path(a) for a in sys.argv[1:4])
engine = start_engine(preload=("modeling.superpixel.path",))  # as the command: every core
try:
    run = run_superpixel(fusion, SuperpixelOptions(), truth=scene, engine=engine)
finally:
    engine.close()  # before the writing, as the command does
r = write_model_run(run, out, overwrite=True)
m = evaluate(load_run(out), load_scene_truth(scene)).metrics
table1 = {k: v["overall_accuracy"] for k, v in r["classification_table"].items()}
print(json.dumps({"stages": r["stages"], "grid": r["inputs"]["grid"], "counts": r["counts"],
                  "table1": table1,
                  "metrics": {k: m[k] for k in ("footprint_2d", "height", "buildings", "roofs",
                                                 "complexity", "surface") if k in m}}))
"""


def timed_path_runs(child: str, name: str, fusion: Path, scene: Path, repeat: int,
                    work: Path) -> tuple[dict, dict]:  # fmt: skip
    """``repeat`` runs of a path's child on small: the first run's report, and the medians
    of its stages, its total and per ortho megapixel, with the peak memory."""
    runs = [run_child(child, str(fusion), str(scene), str(work / f"{name}_{i}"), name)
            for i in range(repeat)]  # fmt: skip
    res = runs[0][0]
    total = statistics.median(sum(s["wall_s"] for s in r[0]["stages"].values()) for r in runs)
    mpx = res["grid"]["width"] * res["grid"]["height"] / 1e6
    summary = {
        "repeat": repeat,
        "stage_median_s": stage_medians(runs),
        "total_median_s": total,
        "s_per_mpx": total / mpx,
        "peak_memory_mib": max(r[2] for r in runs),
    }
    if "seconds_per_building" in res:
        summary["s_per_building_median"] = statistics.median(
            r[0]["seconds_per_building"] for r in runs
        )
    return res, summary


def bench_superpixel(fusion: Path, scene: Path, repeat: int, work: Path) -> dict:
    res, summary = timed_path_runs(SUPERPIXEL_CHILD, "superpixel", fusion, scene, repeat, work)
    return {**summary, "counts": res["counts"], "table1": res["table1"],
            "metrics": res["metrics"]}  # fmt: skip


def print_stages(medians: dict) -> None:
    """One line per stage: its median wall time in seconds."""
    for stage, sec in medians.items():
        print(f"  {stage:<18}{sec:>8.2f} s")


def print_superpixel(sp: dict) -> None:
    print(f"\nworkbench model superpixel on small, median of {sp['repeat']}:")
    print_stages(sp["stage_median_s"])
    m, c, t = sp["metrics"], sp["counts"], sp["table1"]
    print(
        f"  total {sp['total_median_s']:.1f} s = {sp['s_per_mpx']:.1f} s per ortho megapixel; "
        f"peak memory {sp['peak_memory_mib']:.0f} MiB"
    )
    print(
        f"  Table 1 overall accuracy: pixel {t['pixel']:.3f}, super-pixel {t['superpixel']:.3f}, "
        f"CRF {t['crf']:.3f}; footprint 2D quality {m['footprint_2d']['quality']:.3f}; "
        f"height RMSE {m['height']['rmse_m']:.2f} m (MAE {m['height']['mae_m']:.2f}, "
        f"off walls {m['height']['rmse_off_jumps_m']:.2f} m)"
    )
    print(
        f"  roof plane angle median {m['roofs']['plane_angle_median_deg']:.1f} deg; building "
        f"height error median {m['buildings']['height_error_pct_median']:.1f} %; roof types "
        f"{m['buildings'].get('roof_type_accuracy', 0):.2f}; {c['watertight']} of "
        f"{c['buildings']} watertight; {m['complexity']['faces_per_building_median']:.0f} "
        f"triangles per building (median)"
    )


TASK_PATH_CHILD = r"""
import json, sys
from pathlib import Path
from modeling import PATHS
from workbench.engine import start_engine
from workbench.evaluate import evaluate
from workbench.model_run import write_model_run
from workbench.runs import load_run
from workbench.truth import load_scene_truth
fusion, scene, out = (Path(a) for a in sys.argv[1:4])
spec = PATHS[sys.argv[4]]
kwargs = {}
if spec.tasks:  # as the command: every core
    kwargs["engine"] = start_engine(preload=(spec.run.split(":")[0],))
if any(i.name == "labels" for i in spec.inputs):  # the scene's training strokes
    kwargs["labels"] = scene / "training" / "labels.tif"
try:
    run = spec.load()(fusion, spec.options(), **kwargs)
finally:
    if "engine" in kwargs:
        kwargs["engine"].close()  # before the writing, as the command does
r = write_model_run(run, out, overwrite=True)
m = evaluate(load_run(out), load_scene_truth(scene)).metrics
print(json.dumps({"stages": r["stages"], "grid": r["inputs"]["grid"], "counts": r["counts"],
                  "buildings": r["counts"]["buildings"],
                  "seconds_per_building": r["seconds_per_building"],
                  "iterations_per_second": r.get("iterations_per_second"),
                  "metrics": {k: m[k] for k in ("classification", "footprint_2d", "volume_3d",
                                                 "height", "buildings", "complexity",
                                                 "regularity") if k in m}}))
"""


MESH_CHILD = r"""
import json, sys, time
from pathlib import Path
from fusion.options import FusionOptions
from fusion.run import run_fusion
from fusion.scene_mesh import integrate_views, write_scene_mesh
from workbench.records import peak_memory_mb
from workbench.scene import load_scene
scene_dir, out = Path(sys.argv[1]), Path(sys.argv[2])
scene = load_scene(scene_dir)
t = time.perf_counter()
mesh = integrate_views(scene)
mesh_s = time.perf_counter() - t
mesh_peak = peak_memory_mb()
write_scene_mesh(out / "mesh.ply", mesh, scene.crs)
t = time.perf_counter()
r = run_fusion(out / "fusion", FusionOptions(gsd=scene.gsd, bounds=tuple(scene.bounds)),
               mesh=out / "mesh.ply", truth=scene_dir, overwrite=True)
print(json.dumps({"mesh_s": mesh_s, "mesh_peak_mib": mesh_peak, "record": mesh.record,
                  "sampling_s": time.perf_counter() - t, "stages": r["stages"],
                  "quality": r["quality"]}))
"""


def bench_mesh(scene: Path, repeat: int, work: Path) -> dict:
    """``workbench mesh`` and ``workbench fusion --mesh`` on small: medians of their
    times, seconds per million triangles, peak memory, the sampled rasters' quality."""
    runs = [run_child(MESH_CHILD, str(scene), str(work / f"mesh_{i}")) for i in range(repeat)]
    res = runs[0][0]
    mesh_s = statistics.median(r[0]["mesh_s"] for r in runs)
    sampling_s = statistics.median(r[0]["sampling_s"] for r in runs)
    tri = res["record"]["triangles"]
    return {"repeat": repeat, "mesh_median_s": mesh_s, "sampling_median_s": sampling_s,
            "triangles": tri, "views": res["record"]["views"],
            "mesh_s_per_million_triangles": mesh_s / (tri / 1e6),
            "sampling_s_per_million_triangles": sampling_s / (tri / 1e6),
            "mesh_peak_memory_mib": max(r[0]["mesh_peak_mib"] for r in runs),
            "peak_memory_mib": max(r[2] for r in runs), "quality": res["quality"]}  # fmt: skip


def print_mesh(m: dict) -> None:
    q = m["quality"]
    print(f"\nworkbench mesh and fusion --mesh on small, median of {m['repeat']}:")
    print(
        f"  TSDF mesh of {m['views']} views: {m['mesh_median_s']:.1f} s, {m['triangles']:,} "
        f"triangles ({m['mesh_s_per_million_triangles']:.1f} s per million), peak memory "
        f"{m['mesh_peak_memory_mib']:.0f} MiB"
    )
    print(
        f"  orthogonal sampling and products: {m['sampling_median_s']:.1f} s "
        f"({m['sampling_s_per_million_triangles']:.1f} s per million triangles); DSM RMSE "
        f"{q['dsm']['rmse_m']:.2f} m ({q['dsm']['rmse_off_jumps_m']:.2f} off height jumps), "
        f"valid {q['dsm']['valid_fraction']:.1%}; classes "
        f"{q['classification']['overall_accuracy']:.3f}"
    )


def bench_task_path(name: str, fusion: Path, scene: Path, repeat: int, work: Path) -> dict:
    """A path timed on small as its command runs it (parametric, blocks: a task per
    building on every core; lod: with the scene's training strokes)."""
    res, summary = timed_path_runs(TASK_PATH_CHILD, name, fusion, scene, repeat, work)
    return {**summary, "buildings": res["buildings"], "metrics": res["metrics"],
            "iterations_per_second": res["iterations_per_second"]}  # fmt: skip


def print_task_path(name: str, p: dict) -> None:
    print(f"\nworkbench model {name} on small, median of {p['repeat']}:")
    print_stages(p["stage_median_s"])
    m = p["metrics"]
    print(
        f"  total {p['total_median_s']:.1f} s = {p['s_per_building_median']:.2f} s per building "
        f"({p['buildings']} buildings), {p['s_per_mpx']:.1f} s per ortho megapixel; peak "
        f"memory {p['peak_memory_mib']:.0f} MiB"
        + (f"; {p['iterations_per_second']:.0f} RJMCMC iterations per second"
           if p.get("iterations_per_second") else "")
    )  # fmt: skip
    print(
        f"  footprint 2D quality {m['footprint_2d']['quality']:.3f}, volume 3D quality "
        f"{m['volume_3d']['quality']:.3f}; roof types "
        f"{m['buildings'].get('roof_type_accuracy', 0):.2f}; building height error mean "
        f"{m['buildings']['height_error_pct_mean']:.1f} %; watertight "
        f"{m['complexity']['watertight_fraction']:.0%}"
    )


VOXEL_CHILD = r"""
import json, sys
from pathlib import Path
from modeling.voxel.options import VoxelOptions
from modeling.voxel.path import run_voxel
from workbench.model_run import write_model_run
from workbench.evaluate import evaluate
from workbench.runs import load_run
from workbench.truth import load_scene_truth
scene, fusion, out = (Path(a) for a in sys.argv[1:4])
variant = sys.argv[4] if len(sys.argv) > 4 else ""
options = VoxelOptions(fusion_flat_roofs=variant != "photo", pitched_roofs=variant != "levels")
from workbench.engine import start_engine
engine = start_engine(preload=("modeling.voxel.path",))  # as the command: every core
try:
    run = run_voxel(scene, options, fusion_dir=fusion, engine=engine)
finally:
    engine.close()  # before the writing, as the command does
r = write_model_run(run, out, overwrite=True)
truth = load_scene_truth(scene)
ev = evaluate(load_run(out), truth)
m = ev.metrics
rows = [{k: b.get(k) for k in ("roof_type_true", "height_error_pct")} for b in ev.buildings]
# the input as a model: the GIS footprints extruded to their over-estimated heights
from modeling.voxel.inputs import prism, read_inputs
from workbench.meshio import write_ply
inputs = read_inputs(scene, VoxelOptions(), fusion_dir=fusion)
gis = out.parent / (out.name + "_gis")
(gis / "buildings").mkdir(parents=True, exist_ok=True)
for f, base, h in inputs.buildings:
    write_ply(gis / "buildings" / f"{f.id}.ply", *prism(f.polygon, base, h))
(gis / "model.json").write_text(json.dumps({"method": "gis", "buildings": [
    {"id": f.id} for f, _, _ in inputs.buildings]}))
g = evaluate(load_run(gis), truth).metrics
gis_metrics = {"footprint_2d": g["footprint_2d"], "buildings": g["buildings"]}
print(json.dumps({"stages": r["stages"], "counts": r["counts"], "texture": r["texture"],
                  "seconds_per_building": r["seconds_per_building"], "ground": r["ground"],
                  "rows": rows, "gis": gis_metrics,
                  "metrics": {k: m[k] for k in ("footprint_2d", "volume_3d", "height",
                                                 "buildings", "complexity", "surface",
                                                 "texture") if k in m}}))
"""

ROBUSTNESS_CHILD = r"""
import json, sys, tempfile
from pathlib import Path
from modeling.voxel.inputs import read_inputs
from modeling.voxel.path import build_proxies
from modeling.voxel.options import VoxelOptions
from modeling.voxel.robustness import robustness_experiment
from workbench.engine import TaskStore
scene, fusion = Path(sys.argv[1]), Path(sys.argv[2])
options = VoxelOptions()
inputs = read_inputs(scene, options, fusion_dir=fusion)
with tempfile.TemporaryDirectory() as folder:
    shelf = TaskStore(folder)
    proxies = [shelf.load("proxy", e.id) for e in build_proxies(inputs, options, shelf)]
print(json.dumps(robustness_experiment(proxies, inputs.cameras, inputs.images, options)))
"""


def bench_voxel(scene: Path, fusion: Path, repeat: int, work: Path) -> dict:
    runs = [
        run_child(VOXEL_CHILD, str(scene), str(fusion), str(work / f"voxel_{i}"))
        for i in range(repeat)
    ]
    res = runs[0][0]
    stages = stage_medians(runs)
    robust, _, _ = run_child(ROBUSTNESS_CHILD, str(scene), str(fusion))
    # the flat roofs' heights and extent from photo-consistency alone, as in the paper
    photo, _, _ = run_child(
        VOXEL_CHILD, str(scene), str(fusion), str(work / "voxel_photo"), "photo"
    )
    # the paper's flat levels only, without the pitched roofs' planes
    levels, _, _ = run_child(
        VOXEL_CHILD, str(scene), str(fusion), str(work / "voxel_levels"), "levels"
    )
    return {
        "repeat": repeat,
        "stage_median_s": stages,
        "s_per_building_median": statistics.median(r[0]["seconds_per_building"] for r in runs),
        "process_wall_median_s": statistics.median(r[1] for r in runs),
        "peak_memory_mib": max(r[2] for r in runs),
        "counts": res["counts"],
        "texture": res["texture"],
        "ground": res["ground"],
        "metrics": res["metrics"],
        "height_error_pct_by_truth_roof": _by_roof(res["rows"]),
        "gis_input": res["gis"],
        "robustness": robust,
        "photo_flat_roofs": {
            "height_error_pct_median": photo["metrics"]["buildings"]["height_error_pct_median"],
            "footprint_2d_quality": photo["metrics"]["footprint_2d"]["quality"],
            "height_error_pct_by_truth_roof": _by_roof(photo["rows"]),
        },
        "flat_levels_only": {
            "height_error_pct_median": levels["metrics"]["buildings"]["height_error_pct_median"],
            "height_error_pct_mean": levels["metrics"]["buildings"]["height_error_pct_mean"],
            "volume_3d_quality": levels["metrics"]["volume_3d"]["quality"],
            "height_error_pct_by_truth_roof": _by_roof(levels["rows"]),
            "texture": levels["metrics"].get("texture"),
        },
    }


def _by_roof(rows: list[dict]) -> dict:
    """Median and mean |height error| per true roof type, from the per-building rows."""
    groups: dict[str, list[float]] = {}
    for row in rows:
        if row.get("height_error_pct") is not None and row.get("roof_type_true"):
            groups.setdefault(row["roof_type_true"], []).append(abs(row["height_error_pct"]))
    return {
        k: {"median_abs_pct": statistics.median(v), "mean_abs_pct": statistics.mean(v),
            "n": len(v)}
        for k, v in groups.items()
    }  # fmt: skip


def print_voxel(v: dict, floor: dict | None = None) -> None:
    print(f"\nworkbench model voxel on small (r = 1 m, S = 4), median of {v['repeat']}:")
    print_stages(v["stage_median_s"])
    c, m, t = v["counts"], v["metrics"], v["texture"]
    print(
        f"  {v['s_per_building_median']:.2f} s per building ({c['buildings']} buildings); "
        f"peak memory {v['peak_memory_mib']:.0f} MiB"
    )
    print(
        f"  building height error median {m['buildings']['height_error_pct_median']:.1f} %, "
        f"mean {m['buildings']['height_error_pct_mean']:.1f} %; footprint 2D quality "
        f"{m['footprint_2d']['quality']:.3f}; volume 3D quality (same altitude) "
        f"{m['volume_3d']['quality']:.3f}; {c['watertight']} of {c['buildings']} watertight"
    )
    g = v["gis_input"]
    print(
        f"  the GIS input extruded: height error median "
        f"{g['buildings']['height_error_pct_median']:.1f} %, footprint 2D quality "
        f"{g['footprint_2d']['quality']:.3f}"
    )
    by = ", ".join(
        f"{k} {g['median_abs_pct']:.1f} / {g['mean_abs_pct']:.1f} % (n={g['n']})"
        for k, g in sorted(v["height_error_pct_by_truth_roof"].items())
    )
    print(f"  height error by true roof type (median / mean): {by}")
    lv = v.get("flat_levels_only")
    if lv:
        by = ", ".join(
            f"{k} {g['median_abs_pct']:.1f} / {g['mean_abs_pct']:.1f} %"
            for k, g in sorted(lv["height_error_pct_by_truth_roof"].items())
        )
        tx = lv.get("texture") or {}
        seams = (
            f"; seam cost {tx['seam_cost']:.2f} vs projective {tx['seam_cost_projective']:.2f}"
            if "seam_cost" in tx and "seam_cost_projective" in tx else ""
        )  # fmt: skip
        print(
            f"  flat levels only (--no-pitched-roofs, the paper): height error median "
            f"{lv['height_error_pct_median']:.1f} %, mean {lv['height_error_pct_mean']:.1f} % "
            f"({by}); volume 3D quality {lv['volume_3d_quality']:.3f}{seams}"
        )
    photo = v.get("photo_flat_roofs")
    if photo:
        by = ", ".join(
            f"{k} {g['median_abs_pct']:.1f} %"
            for k, g in sorted(photo["height_error_pct_by_truth_roof"].items())
        )
        print(
            f"  flat roofs as photo-consistency leaves them (--no-fusion-flat-roofs): height "
            f"error median {photo['height_error_pct_median']:.1f} % ({by}); footprint 2D "
            f"quality {photo['footprint_2d_quality']:.3f}"
        )
    for p in (floor or {}).get("voxel_proxies", []):
        print(
            f"  perfect proxies (true column heights, clustered with c_e {p['cluster_error']:g}):"
            f" height error median {p['height_error_pct_median']:.1f} %"
        )
    print(
        f"  seam cost, the run's own (eq. 5 per graph edge): graph cut {t['seam_cost']:.3f}, "
        f"projective {t['seam_cost_projective']:.3f} (ratio "
        f"{t['seam_cost'] / t['seam_cost_projective']:.2f}; greedy cuts alone "
        f"{t['seam_cost_greedy']:.3f}); ground "
        f"{v['ground']['seam_cost']:.3f} vs {v['ground']['seam_cost_projective']:.3f}"
    )
    rt = m.get("texture", {})
    if rt.get("source") == "recomputed":
        print(
            f"  seam cost recomputed by compare from the OBJ textures and the views: graph cut "
            f"{rt['seam_cost']:.3f}, projective {rt['seam_cost_projective']:.3f} (ratio "
            f"{rt['seam_cost'] / rt['seam_cost_projective']:.2f}; texture to its source view "
            f"{rt['source_lab_median']:.1f} Lab, median; {rt['points']} points)"
        )
    rb = v["robustness"]
    print(f"  robustness (Fig. 14), height noise +/- {rb['height_noise_m']:.1f} m:")
    for name, case in rb["cases"].items():
        print(
            f"    {name:<12} graph cut {case['seam_cost']:.2f}, projective "
            f"{case['seam_cost_projective']:.2f}, ratio {case['ratio']:.2f}"
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["tiny", "small"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("bench_out"))
    ap.add_argument(
        "--fusion-repeat",
        type=int,
        default=1,
        help="fusion runs on the small sample (about 3 minutes each)",
    )
    ap.add_argument(
        "--seeds", type=int, nargs="*", default=[*TUNED, *HELD_OUT],
        help="small seeds every path is scored on (none: skip; about 4 minutes each)",
    )  # fmt: skip
    ap.add_argument(
        "--doc", type=Path,
        help="the page written with everything printed (default: docs/benchmarks.md, "
        "docs/benchmarks-city.md with --preset city; none with --doc '')",
    )  # fmt: skip
    ap.add_argument(
        "--preset", choices=("small", "city"), default="small",
        help="city: the 1 km² city end to end beside small, command by command (about two "
        "hours, benchmarks/city.py), instead of everything above",
    )  # fmt: skip
    ap.add_argument(
        "--reuse-runs", action="store_true",
        help="with --preset city: take the runs already in OUT/small and OUT/city as they "
        "are (their records' times) instead of running them again",
    )  # fmt: skip
    args = ap.parse_args()
    if args.doc is None:
        args.doc = Path("docs") / ("benchmarks-city.md" if args.preset == "city" else
                                   "benchmarks.md")  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    tee = _Tee(sys.stdout)
    sys.stdout = tee
    try:
        results = run_city(args) if args.preset == "city" else run_benchmarks(args)
    finally:
        sys.stdout = tee.stream
    (args.out / "bench.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"\nwrote {args.out / 'bench.json'}")
    if str(args.doc):
        write_page(args.doc, results, tee.text(), sys.argv[1:])
        print(f"wrote {args.doc}")
    return 0


class _Tee:
    """Prints as usual and keeps a copy of what was printed."""

    def __init__(self, stream):
        self.stream, self.parts = stream, []

    def write(self, text: str) -> int:
        self.parts.append(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()

    def text(self) -> str:
        return "".join(self.parts)


def _git(*args: str) -> str:
    proc = subprocess.run(["git", *args], capture_output=True, text=True)
    return proc.stdout.strip() if proc.returncode == 0 else ""


def write_page(path: Path, results: dict, printed: str, argv: list[str]) -> None:
    """docs/benchmarks.md: the commit and machine, the seeds' tables, all that was printed."""
    commit = _git("rev-parse", "--short", "HEAD") or "unknown"
    if _git("status", "--porcelain", "--untracked-files=no"):
        commit += " with uncommitted changes"
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    lines = [
        "# Benchmarks",
        "",
        "Written by `make bench` (`benchmarks/run.py`); do not edit by hand.",
        "",
        f"- commit: `{commit}`, {time.strftime('%Y-%m-%d')}",
        f"- machine: {os.cpu_count()} cores, {memory:.0f} GiB, Python {results['python']}",
        f"- command: `{' '.join(['python benchmarks/run.py', *argv])}`",
        "",
    ]
    if results.get("seeds"):
        lines += [
            "## Quality on the tuning seeds and on held-out seeds",
            "",
            "`small` city, every path run as a user runs it (`workbench fusion SCENE --truth "
            "SCENE`, then `workbench model NAME` on that fusion run, and `voxel_photo_alone`: "
            "`workbench model voxel SCENE` without it, then `workbench compare`; "
            "`benchmarks/seeds.py`). Defaults were chosen on seeds 0-2; seeds 3-5 are held "
            "out. Wall times are of single runs beside nothing else.",
            tables(results["seeds"]),
        ]
    lines += ["## Speed, memory and quality per stage", "", "```text", printed.rstrip(), "```", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines))


CITY_BLOCK_M = 250.0  # the city's fusion in 16 blocks of at most 1025 x 1025 cells


def run_city(args) -> dict:
    """``--preset city``: small and city end to end, seed 0, command by command (the
    sample scenes already in ``args.out`` are kept)."""
    results = {"cores": os.cpu_count(), "python": sys.version.split()[0]}
    print(f"end to end on {os.cpu_count()} cores, one run of each command")
    if args.reuse_runs:
        print("(--reuse-runs: the runs already in the output folders, each timed when it ran "
              "by benchmarks/city.py; where that time was lost, the run's record's stage "
              "total, without the interpreter's start)")  # fmt: skip
    for preset in ("small", "city"):
        results[preset] = city_run(preset, 0, args.out / preset, None, reuse=True,
                                   reuse_runs=args.reuse_runs,
                                   block_m=CITY_BLOCK_M if preset == "city" else None)  # fmt: skip
        print_city(results[preset])
    small, city = results["small"], results["city"]
    for stage in ("fusion", "fusion_blocks", "superpixel", "voxel", "parametric", "blocks",
                  *(f"{n}_blocks" for n in BLOCK_PATHS), "mesh", "fusion_mesh", "lod",
                  "fusion_mesh_blocks", "lod_blocks", "fusion_points", "compare"):  # fmt: skip
        # a run in blocks against small's run of one grid, about a block's size
        a, b = small.get(stage.removesuffix("_blocks")), city.get(stage)
        if a is None or b is None:  # a record from before it was benched
            continue
        print(f"  {stage}: peak memory city / small {b['peak_mb'] / a['peak_mb']:.2f} (largest "
              "process)"
              + (f", {max(b['worker_peak_mb']) / max(a['worker_peak_mb']):.2f} (workers)"
                 if a.get("worker_peak_mb") and b.get("worker_peak_mb") else ""))  # fmt: skip
    return results


def run_benchmarks(args) -> dict:
    """Every measurement of the module docstring; prints as it goes."""
    results = {"cores": os.cpu_count(), "python": sys.version.split()[0], "sample": []}
    print(f"benchmarks on {os.cpu_count()} cores, medians of {args.repeat} runs")
    with tempfile.TemporaryDirectory(dir=args.out) as tmp:
        for preset in args.presets:
            r = bench_sample(preset, args.repeat, Path(tmp))
            results["sample"].append(r)
            print(
                f"\nworkbench sample --preset {preset}: {r['buildings']} buildings, "
                f"{r['views']} views, {r['triangles']} triangles"
            )
            print(f"  {'stage':<16}{'median s':>10}")
            for stage, s in r["stage_median_s"].items():
                print(f"  {stage:<16}{s:>10.2f}")
            print(
                f"  {'process wall':<16}{r['process_wall_median_s']:>10.2f}"
                f"   (runs: {r['spread_total_s']})"
            )
            print(
                f"  throughput: {r['views_per_s']:.2f} views/s, "
                f"{r['rendered_mpx_per_s']:.2f} Mpx/s rendered (primary + shadow ray per px)"
            )
            print(f"  peak memory: {r['peak_memory_mib']:.0f} MiB")
            q = r["quality"]
            d = q["depth_maps_median_over_views"]
            g = q["gis_footprints"]
            print(
                f"  dataset: calibration error {q['calibration_error_px_rms']:.2f} px RMS; "
                f"depth noise {d['noise_ratio']:.2f} x model, {d['outlier_fraction']:.1%} "
                f"outliers, {d['valid_fraction']:.1%} valid"
            )
            print(
                f"           GIS footprints: shift {g['centroid_shift_m']:.2f} m, IoU "
                f"{g['iou']:.2f}, heights x{g['height_factor']:.2f}; nadir overlap "
                f"{q['coverage']['nadir_overlap_x']:.0%}; training labels "
                f"{q['training_label_fraction']:.1%}"
            )
        for preset in args.presets:
            c = bench_compare(Path(tmp) / f"{preset}_0", [], args.repeat, Path(tmp))
            results[f"compare_{preset}"] = c
            print_compare(c)
        if "small" in args.presets and args.fusion_repeat > 0:
            scene = Path(tmp) / "small_0"
            f = bench_fusion(scene, args.fusion_repeat, Path(tmp))
            results["fusion_small"] = f
            g = f["grid"]
            print(
                f"\nworkbench fusion on small ({g['width']} x {g['height']} cells at "
                f"{g['gsd']} m), median of {f['repeat']}:"
            )
            print_stages(f["stage_median_s"])
            print(
                f"  total {f['fusion_median_s']:.1f} s; reading every input once "
                f"{f['read_inputs_once_median_s']:.1f} s; ratio {f['ratio_fusion_to_read']:.1f}"
            )
            one = f["one_worker"]
            wp = f.get("worker_peak_memory_mib") or []
            workers = ", ".join(f"{p:.0f}" for p in wp)
            print(
                f"  {f['observations_per_s'] / 1e6:.2f} M observations fused per second; "
                f"classification {f['classification_mpx_per_s']:.2f} Mpx/s "
                "of the views' pixels the colour pass reads (their visible observations); "
                f"peak memory {f['peak_memory_mib']:.0f} MiB in the command"
                + (f", {workers} MiB in its {len(wp)} Dask workers" if wp else "")
            )
            print(
                f"  in one process (--workers 1, one run): {one['fusion_s']:.1f} s "
                f"(x{one['fusion_s'] / f['fusion_median_s']:.2f}), "
                f"{one['observations_per_s'] / 1e6:.2f} M observations/s, classification "
                f"{one['classification_mpx_per_s']:.2f} Mpx/s, {one['peak_memory_mib']:.0f} MiB"
            )
            q = f["quality"]
            print(
                f"  DSM RMSE {q['dsm']['rmse_m']:.2f} m (mean fusion "
                f"{q['dsm_mean_fusion']['rmse_m']:.2f}), median |e| "
                f"{q['dsm']['median_abs_m']:.3f} m, valid {q['dsm']['valid_fraction']:.1%}, "
                f"off height jumps {q['dsm']['rmse_off_jumps_m']:.2f} m; "
                f"DTM RMSE {q['dtm']['rmse_m']:.2f} m"
            )
            floor = height_floor(scene)
            results["height_floor_small"] = floor
            fm, walls = floor["median_of_returns"], floor["walls_displaced"]
            print(
                f"  what a noise-free sensor scores (benchmarks/height_floor.py): the median "
                f"of {floor['returns_per_cell']} returns per cell, DSM RMSE "
                f"{fm['dsm_rmse_m']:.2f} m; a perfect model with walls 5 cm off, height RMSE "
                f"on buildings {walls['0.05']['building_rmse_m']:.2f} m"
            )
            inside = ", ".join(f"{d} m: {v['building_rmse_off_jumps_m']:.2f} m"
                               for d, v in floor["outline_inside"].items())  # fmt: skip
            print(f"  a perfect model with outlines inside the true ones by {inside} (height "
                  "RMSE on buildings off the jumps)")  # fmt: skip
            cells = floor["cells"]
            print(
                f"  cells whose true surface some view sees {cells['seen_by_a_view']:.1%}, "
                f"that some depth map observes {cells['observed_by_a_depth_map']:.1%}"
            )
            c = q["classification"]
            per = ", ".join(f"{k} {v:.3f}" for k, v in c["per_class_accuracy"].items())
            mae, mae_mean = q["ortho_mae"]["mean"], q["ortho_mae_mean_fusion"]["mean"]
            print(
                f"  classes: overall {c['overall_accuracy']:.3f} ({per}); ortho MAE "
                f"{mae:.1f} (mean fusion {mae_mean:.1f})"
            )
            sp = bench_superpixel(Path(tmp) / "fusion_0", scene, args.repeat, Path(tmp))
            results["superpixel_small"] = sp
            print_superpixel(sp)
            ceiling = crf_ceiling(Path(tmp) / "superpixel_0", scene)
            results["crf_ceiling_small"] = ceiling
            print_ceiling(ceiling)
            for name in ("parametric", "blocks"):
                pm = bench_task_path(name, Path(tmp) / "fusion_0", scene, args.repeat, Path(tmp))
                results[f"{name}_small"] = pm
                print_task_path(name, pm)
            ms = bench_mesh(scene, args.repeat, Path(tmp))
            results["mesh_small"] = ms
            print_mesh(ms)
            ld = bench_task_path("lod", Path(tmp) / "mesh_0" / "fusion", scene, args.repeat,
                                 Path(tmp))  # fmt: skip
            results["lod_small"] = ld
            print_task_path("lod", ld)
            vx = bench_voxel(scene, Path(tmp) / "fusion_0", args.repeat, Path(tmp))
            results["voxel_small"] = vx
            print_voxel(vx, floor)
            c = bench_compare(
                scene,
                [
                    Path(tmp) / f"{name}_0"
                    for name in ("fusion", "superpixel", "parametric", "blocks", "voxel", "lod")
                ],
                1,
                Path(tmp),
            )
            results["compare_small_with_fusion"] = c
            print_compare(c)
    print("\nAHN3 building clouds (benchmarks/ahn3.py):", flush=True)
    ahn3 = [sys.executable, str(Path(__file__).with_name("ahn3.py")), "--out", str(args.out)]
    proc = subprocess.run(ahn3, check=False, capture_output=True, text=True)
    print(proc.stdout.rstrip())
    print("\nterraced blocks from LiDAR tiles (benchmarks/terrace.py), seeds 0-5:", flush=True)
    terrace = [sys.executable, str(Path(__file__).with_name("terrace.py")), "--out",
               str(args.out / "terrace")]  # fmt: skip
    proc = subprocess.run(terrace, check=False, capture_output=True, text=True)
    print("\n".join(ln for ln in proc.stdout.splitlines() if ln.startswith("|")))
    if args.seeds:
        results["seeds"] = {}
        for seed in args.seeds:
            print(f"\nsmall seed {seed}: every path, scored (benchmarks/seeds.py) ...", flush=True)
            results["seeds"][seed] = run_seed(seed, args.out / "seeds")
        print(tables(results["seeds"]))
    return results


if __name__ == "__main__":
    sys.exit(main())
