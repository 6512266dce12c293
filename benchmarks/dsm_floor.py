"""What the fusion's DSM can reach on better depth maps: its error with each defect removed.

The sample's depth maps are made as dense matching makes them
(``data_samples/depth.py``): corners rounded across depth edges, occlusion and shadow
holes, noise growing with the square of the depth, 2 % gross outliers; the written poses
carry a 0.5 px calibration error. This script samples the same city (same seed, same
images) again with these defects removed one group at a time, runs ``workbench fusion
--truth`` on each with its default options, and reports the DSM's error as the fusion
scores it:

- ``sampled``: the sample as ``workbench sample`` makes it;
- ``no noise``: no depth noise and no outliers (rounded corners, holes and the pose
  error kept);
- ``sharp edges``: and no rounding across depth edges (the holes kept);
- ``true depth``: the renderer's true depth (no rounding, no holes either);
- ``true depth and poses``: and the true poses.

A fusion error that stays on ``true depth and poses`` is the fusion's own (its grid, its
medians, its classes); what goes away between two rows is what that defect costs.

Usage: python benchmarks/dsm_floor.py [--seeds 0 1 2 3 4 5] [--out bench_out/dsm_floor]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import rasterio
from seeds import HELD_OUT, TUNED, _cli

from data_samples.generate import generate_sample
from data_samples.presets import PRESETS, TRUE_DEPTH
from workbench.metrics import height_jumps

NO_NOISE = {"depth_sigma": 0.0, "depth_outliers": 0.0}
VARIANTS = {
    "sampled": {},
    "no noise": NO_NOISE,
    "sharp edges": {**NO_NOISE, "depth_round_edges": False},
    "true depth": TRUE_DEPTH,
    "true depth and poses": {**TRUE_DEPTH, "calibration_error_px": 0.0},
}
GROSS_M = 2.0  # a cell this far off the truth is a gross error


def gross_share(fusion: Path, scene: Path) -> dict:
    """Share of the cells off the truth's height jumps that are more than ``GROSS_M`` off,
    and their share of the squared error there."""
    with rasterio.open(fusion / "dsm.tif") as a, rasterio.open(scene / "truth" / "dsm.tif") as b:
        dsm, truth = a.read(1).astype(np.float64), b.read(1).astype(np.float64)
    off = np.isfinite(dsm) & np.isfinite(truth) & ~height_jumps(truth)
    e = dsm[off] - truth[off]
    gross = np.abs(e) > GROSS_M
    return {
        "gross_cells": float(gross.mean()),
        "gross_share_of_squared_error": float((e[gross] ** 2).sum() / max((e**2).sum(), 1e-12)),
    }


def run_variant(seed: int, name: str, work: Path, preset: str, sampled: Path | None) -> dict:
    """Sample ``seed`` with the variant's defects removed, fuse it, score the DSM.

    ``sampled``: a folder holding ``scene{seed}`` as ``benchmarks/seeds.py`` made it, read
    for the ``sampled`` variant instead of sampling it again."""
    tag = name.replace(" ", "_")
    scene, fusion = work / f"scene{seed}_{tag}", work / f"fusion{seed}_{tag}"
    if name == "sampled" and sampled is not None and (sampled / f"scene{seed}").is_dir():
        scene = sampled / f"scene{seed}"
    t0 = time.perf_counter()
    if not (scene / "scene.json").exists():
        p = PRESETS[preset].with_overrides(**VARIANTS[name])
        generate_sample(scene, p, seed, overwrite=True)
    t_sample = time.perf_counter() - t0
    t0 = time.perf_counter()
    _cli("fusion", scene, "-o", fusion, "--truth", scene, "--overwrite")
    t_fusion = time.perf_counter() - t0
    q = json.loads((fusion / "fusion.json").read_text())["quality"]
    depth = json.loads((scene / "sample.json").read_text())["depth_maps_median_over_views"]
    return {
        "dsm_rmse_m": q["dsm"]["rmse_m"],
        "dsm_rmse_off_jumps_m": q["dsm"]["rmse_off_jumps_m"],
        "overall_accuracy": q["classification"]["overall_accuracy"],
        "depth_valid_fraction": depth["valid_fraction"],
        **gross_share(fusion, scene),
        "seconds": {"sample": round(t_sample, 1), "fusion": round(t_fusion, 1)},
    }


def table(results: dict[int, dict[str, dict]]) -> str:
    """Each seed's DSM RMSE off the jumps per variant, and its gross cells' share."""
    names = list(VARIANTS)
    width = max(map(len, names)) + 2
    lines = [
        "fusion DSM RMSE off the height jumps (m); cells > 2 m off: % of the cells, % of the "
        "squared error; default options",
        " " * 19 + "".join(f"{n:>{width}}" for n in names),
    ]
    for seed, row in results.items():
        group = "tuned" if seed in TUNED else "held out" if seed in HELD_OUT else "other"
        rmse, gross = [], []
        for n in names:
            r = row.get(n)
            rmse.append(f"{r['dsm_rmse_off_jumps_m']:.3f}" if r else "-")
            gross.append(
                f"{100 * r['gross_cells']:.2f}, {100 * r['gross_share_of_squared_error']:.0f}"
                if r
                else "-"
            )
        lines.append(f"seed {seed:<2} {group:<9} m   " + "".join(f"{c:>{width}}" for c in rmse))
        lines.append(f"{'':<16} > 2 m" + "".join(f"{c:>{width}}" for c in gross))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[*TUNED, *HELD_OUT])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--out", type=Path, default=Path("bench_out") / "dsm_floor")
    ap.add_argument("--preset", default="small", help="sample preset (tiny for a quick look)")
    ap.add_argument("--sampled", type=Path, help="benchmarks/seeds.py's folder: its scenes")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    saved = args.out / "dsm_floor.json"
    results = {}
    if saved.exists():  # a run broken off goes on where it stopped (delete it to redo all)
        results = {int(k): v for k, v in json.loads(saved.read_text()).items()}
    for seed in args.seeds:
        for name in args.variants:
            if name in results.get(seed, {}):
                continue
            print(f"seed {seed}, {name}: sample, fusion ...", flush=True)
            results.setdefault(seed, {})[name] = run_variant(
                seed, name, args.out, args.preset, args.sampled
            )
            r = results[seed][name]
            print(f"  DSM RMSE off the jumps {r['dsm_rmse_off_jumps_m']:.3f} m", flush=True)
            saved.write_text(json.dumps(results, indent=1) + "\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
