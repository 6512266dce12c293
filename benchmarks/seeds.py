"""Quality of every path on seeds it was tuned on and seeds it never saw.

For each seed of the ``small`` city: ``workbench sample``, ``workbench fusion --truth``,
``workbench model NAME`` for every registered path (on the fusion run, as a user runs
it), the voxel path without the fusion run (photo-consistency alone, as in its paper),
``workbench mesh`` and ``workbench fusion --mesh`` (the paths of ``MESH_PATHS``, the LOD
path, run on that mesh's fusion, with the scene's training strokes), ``workbench compare``
of them all against the truth, with ``--mesh`` (every LoD's distance to the mesh).
Defaults were chosen on seeds 0-2; seeds 3-5 are held out: no choice may look at them.
The table gives each seed and the median of each group.

Usage: python benchmarks/seeds.py [--seeds 0 1 2 3 4 5] [--out bench_out/seeds]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

from modeling import PATHS

TUNED, HELD_OUT = (0, 1, 2), (3, 4, 5)
PHOTO_ALONE = "voxel_photo_alone"
MESH_FUSION = "fusion_mesh"
MESH_PATHS = ("lod",)  # run on the mesh's fusion, as their paper has it
ROOF_TYPES = ("flat", "shed", "gable", "hipped", "pyramid", "mansard", "multi-level")
ROWS = {
    "fusion": (
        ("dsm.rmse_m", "DSM RMSE (m)", 2),
        ("dsm.rmse_off_jumps_m", "DSM RMSE off height jumps (m)", 2),
        ("dsm.valid_fraction", "DSM cells known (share of the truth's)", 3),
        ("classification.overall_accuracy", "classes, overall accuracy", 3),
        ("classification.building_accuracy", "classes, building / other", 3),
        ("footprint_2d.quality", "footprint 2D quality", 3),
        ("buildings.missed_over_50m2", "true buildings of 50 m² or more missed", 0),
        ("cost.wall_s", "wall time (s)", 0),
        ("cost.peak_memory_mb", "peak memory (MiB)", 0),
    ),
    "model": (
        ("classification.overall_accuracy", "classes, overall accuracy", 3),
        ("classification.building_accuracy", "classes, building / other", 3),
        ("footprint_2d.quality", "footprint 2D quality", 3),
        ("buildings.missed_over_50m2", "true buildings of 50 m² or more missed", 0),
        ("volume_3d.quality", "volume 3D quality (same altitude)", 3),
        ("volume_3d_tolerant.quality", "... within 1 m", 3),
        ("height.rmse_m", "height RMSE on buildings (m)", 2),
        ("height.rmse_off_jumps_m", "... off height jumps (m)", 2),
        ("height.rmse_on_both_off_jumps_m", "... where both have a building, off jumps (m)", 2),
        ("height.missed_share_off_jumps", "... share of it on building cells the run misses", 2),
        ("buildings.height_error_pct_median", "building height error, median (%)", 1),
        ("buildings.height_error_pct_mean", "building height error, mean (%)", 1),
        *(
            (f"buildings.height_error_pct_by_roof_type.{t}.mean", f"... mean, {t} roofs (%)", 1)
            for t in ROOF_TYPES
        ),
        ("buildings.roof_type_accuracy", "roof types as the truth's", 2),
        ("roofs.plane_angle_median_deg", "roof plane angle, median (deg)", 1),
        ("complexity.watertight_fraction", "watertight fraction", 2),
        ("regularity.edges_within_2deg", "outline edges within 2 deg of the facades", 2),
        ("regularity.pairs_within_2deg", "roof-plane pairs within 2 deg of symmetric", 2),
        *(
            (f"lods.{lod}.rms_to_mesh_m", f"LoD {lod}: RMS to the mesh (m)", 2)
            for lod in ("0", "1.2", "1.3", "2.2")
        ),
        *(
            (f"lods.{lod}.triangles", f"LoD {lod}: triangles", 0)
            for lod in ("0", "1.2", "1.3", "2.2")
        ),
        ("texture.seam_cost", "seam cost, graph cut", 2),
        ("texture.seam_cost_projective", "seam cost, projective", 2),
        ("cost.wall_s", "wall time (s)", 1),
        ("cost.peak_memory_mb", "peak memory (MiB)", 0),
    ),
}


def _cli(*args) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "workbench.cli", *map(str, args)], capture_output=True, text=True
    )
    if proc.returncode != 0:
        raise SystemExit(f"failed: workbench {' '.join(map(str, args))}\n{proc.stderr}")


def run_seed(seed: int, work: Path, preset: str = "small") -> dict:
    """Every path on one seed; returns {run name: its metrics} and the commands' times."""
    scene, fusion = work / f"scene{seed}", work / f"fusion{seed}"
    seconds = {}
    t0 = time.perf_counter()
    if not (scene / "scene.json").exists():
        _cli("sample", scene, "--preset", preset, "--seed", seed, "--overwrite")
    seconds["sample"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    _cli("fusion", scene, "-o", fusion, "--truth", scene, "--overwrite")
    seconds["fusion"] = time.perf_counter() - t0
    mesh, mesh_fusion = work / f"mesh{seed}" / "mesh.ply", work / f"meshfusion{seed}"
    t0 = time.perf_counter()
    _cli("mesh", scene, "-o", mesh, "--overwrite")
    seconds["mesh"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    doc = json.loads((scene / "scene.json").read_text())
    _cli("fusion", "--mesh", mesh, "-o", mesh_fusion, "--gsd", doc["gsd"], "--bounds",
         *doc["bounds"], "--truth", scene, "--overwrite")  # fmt: skip
    seconds[MESH_FUSION] = time.perf_counter() - t0
    runs = [fusion, mesh_fusion]
    for name, spec in PATHS.items():
        out = work / f"{name}{seed}"
        t0 = time.perf_counter()
        given = {"scene_dir": scene, "fusion_dir": fusion, "truth": scene}
        if name in MESH_PATHS:
            given.update(fusion_dir=mesh_fusion, labels=scene / "training" / "labels.tif")
        _cli("model", name, *spec.arguments(given), "-o", out, "--overwrite")
        seconds[name] = time.perf_counter() - t0
        runs.append(out)
    # the voxel path as its paper has it: the views and GIS footprints, no fusion run
    out = work / f"{PHOTO_ALONE}{seed}"
    t0 = time.perf_counter()
    _cli("model", "voxel", scene, "-o", out, "--overwrite")
    seconds[PHOTO_ALONE] = time.perf_counter() - t0
    runs.append(out)
    report = work / f"report{seed}"
    names = ["fusion", MESH_FUSION, *PATHS, PHOTO_ALONE]
    _cli("compare", *runs, "--truth", scene, "-o", report, "--names", *names, "--mesh", mesh,
         "--overwrite")  # fmt: skip
    metrics = json.loads((report / "metrics.json").read_text())["runs"]
    return {"metrics": metrics, "command_s": seconds}


def _get(d: dict, dotted: str):
    for key in _keys(dotted):
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def _keys(dotted: str) -> list[str]:
    """The keys of a dotted path; a LoD ("1.2") after "lods" is one key."""
    parts = dotted.split(".")
    if parts[0] == "lods" and len(parts) > 2 and parts[2].isdigit():
        parts = [parts[0], f"{parts[1]}.{parts[2]}", *parts[3:]]
    return parts


def _median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def tables(results: dict[int, dict]) -> str:
    """Markdown: one table per run, a column per seed and the two groups' medians."""
    seeds = sorted(results)
    lines = []
    for name in ["fusion", MESH_FUSION, *PATHS, PHOTO_ALONE]:
        if not any(name in results[s]["metrics"] for s in seeds):
            continue
        kind = "fusion" if name in ("fusion", MESH_FUSION) else "model"
        tuned = [s for s in seeds if s in TUNED]
        held = [s for s in seeds if s in HELD_OUT]
        head = [f"seed {s}" for s in seeds]
        head += ["median 0-2"] * bool(tuned) + ["median 3-5 (held out)"] * bool(held)
        lines += [f"\n`{name}`\n", "| metric | " + " | ".join(head) + " |",
                  "|---|" + "---|" * len(head)]  # fmt: skip
        for key, label, digits in ROWS[kind]:
            per = {s: _get(results[s]["metrics"].get(name, {}), key) for s in seeds}
            if all(v is None for v in per.values()):
                continue
            cells = [per[s] for s in seeds]
            if tuned:
                cells.append(_median([per[s] for s in tuned]))
            if held:
                cells.append(_median([per[s] for s in held]))
            text = ["-" if v is None else f"{v:.{digits}f}" for v in cells]
            lines.append(f"| {label} | " + " | ".join(text) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[*TUNED, *HELD_OUT])
    ap.add_argument("--out", type=Path, default=Path("bench_out") / "seeds")
    ap.add_argument("--preset", default="small", help="sample preset (tiny for a quick look)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for seed in args.seeds:
        print(f"seed {seed}: sample, fusion, mesh, {', '.join(PATHS)}, compare ...", flush=True)
        results[seed] = run_seed(seed, args.out, args.preset)
        times = ", ".join(f"{k} {v:.0f} s" for k, v in results[seed]["command_s"].items())
        print(f"  {times}", flush=True)
    (args.out / "seeds.json").write_text(json.dumps(results, indent=1) + "\n")
    print(tables(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
