"""``make bench``: wall time, throughput and peak memory per stage.

Each measurement runs in a fresh child process, so that its peak resident memory
is its own (``os.wait4``). Medians over ``--repeat`` runs; this machine is noisy.

Usage: python benchmarks/run.py [--presets tiny small] [--repeat 3] [--out bench_out]
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


def run_child(code: str, *args: str) -> tuple[dict, float, float]:
    """Run ``code`` in a child Python; return its JSON output, wall seconds, peak RSS MiB."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, text=True)
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"benchmark child failed ({status}): {' '.join(args)}")
    return json.loads(out.strip().splitlines()[-1]), wall, usage.ru_maxrss / 1024.0


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
from types import SimpleNamespace
from fusion.cli_fusion import run_fusion
args = SimpleNamespace(scene=sys.argv[1], points=None, out=sys.argv[2], gsd=None, bounds=None,
                       crs=None, truth=sys.argv[1], classifier=None, save_classifier=None,
                       raster_prior=False, seed=0, overwrite=True)
r = run_fusion(args)
print(json.dumps({k: r[k] for k in ("stages", "observations", "observations_per_s",
                                    "classification_mpx_per_s", "quality", "grid")}))
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


def bench_fusion(scene: Path, repeat: int, work: Path) -> dict:
    runs = [run_child(FUSION_CHILD, str(scene), str(work / f"fusion_{i}")) for i in range(repeat)]
    reads = [run_child(READ_CHILD, str(scene))[0]["read_s"] for _ in range(3)]
    res = runs[0][0]
    walls = [sum(st["wall_s"] for st in r[0]["stages"].values()) for r in runs]
    stages = {
        k: statistics.median(r[0]["stages"][k]["wall_s"] for r in runs) for k in res["stages"]
    }
    return {
        "repeat": repeat,
        "stage_median_s": stages,
        "fusion_median_s": statistics.median(walls),
        "read_inputs_once_median_s": statistics.median(reads),
        "ratio_fusion_to_read": statistics.median(walls) / statistics.median(reads),
        "observations": res["observations"],
        "observations_per_s": statistics.median(r[0]["observations_per_s"] for r in runs),
        "classification_mpx_per_s": res.get("classification_mpx_per_s"),
        "peak_memory_mib": max(r[2] for r in runs),
        "grid": res["grid"],
        "quality": res["quality"],
    }


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
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
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
        if "small" in args.presets and args.fusion_repeat > 0:
            scene = Path(tmp) / "small_0"
            f = bench_fusion(scene, args.fusion_repeat, Path(tmp))
            results["fusion_small"] = f
            g = f["grid"]
            print(
                f"\nworkbench fusion on small ({g['width']} x {g['height']} cells at "
                f"{g['gsd']} m), median of {f['repeat']}:"
            )
            for stage, sec in f["stage_median_s"].items():
                print(f"  {stage:<18}{sec:>8.2f} s")
            print(
                f"  total {f['fusion_median_s']:.1f} s; reading every input once "
                f"{f['read_inputs_once_median_s']:.1f} s; ratio {f['ratio_fusion_to_read']:.1f}"
            )
            print(
                f"  {f['observations_per_s'] / 1e6:.2f} M observations fused per second; "
                f"classification {f['classification_mpx_per_s']:.2f} Mpx/s per view; "
                f"peak memory {f['peak_memory_mib']:.0f} MiB"
            )
            q = f["quality"]
            print(
                f"  DSM RMSE {q['dsm']['rmse_m']:.2f} m (mean fusion "
                f"{q['dsm_mean_fusion']['rmse_m']:.2f}), median |e| "
                f"{q['dsm']['median_abs_m']:.3f} m, valid {q['dsm']['valid_fraction']:.1%}; "
                f"DTM RMSE {q['dtm']['rmse_m']:.2f} m"
            )
            c = q["classification"]
            per = ", ".join(f"{k} {v:.3f}" for k, v in c["per_class_accuracy"].items())
            mae, mae_mean = q["ortho_mae"]["mean"], q["ortho_mae_mean_fusion"]["mean"]
            print(
                f"  classes: overall {c['overall_accuracy']:.3f} ({per}); ortho MAE "
                f"{mae:.1f} (mean fusion {mae_mean:.1f})"
            )
    (args.out / "bench.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"\nwrote {args.out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
