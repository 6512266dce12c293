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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["tiny", "small"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("bench_out"))
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
    (args.out / "bench.json").write_text(json.dumps(results, indent=1) + "\n")
    print(f"\nwrote {args.out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
