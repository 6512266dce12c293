"""Terraced blocks from LiDAR tiles: one building region of ~30,000 cells, in seconds.

For each seed: ``python -m data_samples.terrace`` (two rows of attached houses, 2 LAZ tiles
in UTM 31N), ``workbench fusion --points TILES`` (the defaults; a cell of three returns;
and the empty rows between scan lines left unfilled, as the stalled AHN3 run had them),
the super-pixel path, and ``workbench compare`` against the terrace's truth. Each region's
prototypes are also clustered the way the path did before (scikit-learn's dense affinity
propagation on a K x K matrix with a floor for non-adjacent pairs), on the same hypotheses,
and timed.

Usage: python benchmarks/terrace.py [--seeds 0 1 2 3 4 5] [--out bench_out/terrace]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from data_samples.terrace import write_terrace
from fusion.options import FusionOptions
from fusion.run import run_fusion
from modeling.superpixel import prototypes
from modeling.superpixel.options import SuperpixelOptions
from modeling.superpixel.path import run_superpixel
from workbench.compare import compare_runs
from workbench.model_run import write_model_run
from workbench.truth import load_scene_truth

TUNED, HELD_OUT = (0, 1, 2), (3, 4, 5)


def dense_affinity_propagation_s(similarity, n: int, preference: float) -> float:
    """Seconds scikit-learn's dense affinity propagation takes on the same problem."""
    from sklearn.cluster import AffinityPropagation

    rows, cols, s = similarity
    S = np.full((n, n), (s.min() if len(s) else 0.0) - 100.0)
    S[rows, cols] = s
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        AffinityPropagation(affinity="precomputed", preference=preference, damping=0.7,
                            max_iter=400, random_state=0).fit(S)  # fmt: skip
    return time.perf_counter() - t0


CASES = {  # name: (cell size, fill radius); None: the defaults
    "default": (None, None),
    "3 returns per cell": (0.49, None),  # the coarser cell the issue proposed, for the record
    "stripes": (None, 0.0),  # as the AHN3 block was first run: empty rows left unfilled
}


def run(seed: int, case: str, work: Path) -> dict:
    """One terrace, one case of :data:`CASES`: fusion, the super-pixel path, the
    comparison."""
    gsd, fill = CASES[case]
    sample = work / f"terrace{seed}"
    if not (sample / "terrace.json").exists():
        write_terrace(sample, seed=seed)
    tag = f"{seed}_{list(CASES).index(case)}"
    fusion, model = work / f"fusion{tag}", work / f"superpixel{tag}"
    t0 = time.perf_counter()
    run_fusion(
        fusion, FusionOptions(gsd=gsd, fill_radius=fill), points=sample / "tiles", overwrite=True
    )
    fusion_s = time.perf_counter() - t0
    clusterings = []
    original = prototypes.cluster_prototypes

    def timed(similarity, n, preference, seed=0):
        t = time.perf_counter()
        out = original(similarity, n, preference, seed)
        sparse = time.perf_counter() - t
        if n >= 200:  # the large regions only: the dense one is slow
            clusterings.append({"hypotheses": n, "pairs": len(similarity[0]), "sparse_s": sparse,
                                "dense_s": dense_affinity_propagation_s(similarity, n,
                                                                        preference)})  # fmt: skip
        return out

    prototypes.cluster_prototypes = timed
    try:
        t0 = time.perf_counter()
        result = run_superpixel(fusion, SuperpixelOptions())
        model_s = time.perf_counter() - t0
    finally:
        prototypes.cluster_prototypes = original
    write_model_run(result, model, overwrite=True)
    truth = load_scene_truth(sample / "truth")
    doc = compare_runs([model], truth, work / f"report{tag}", names=["model"], overwrite=True)
    m = doc["runs"]["model"]
    region = max(result.buildings, key=lambda b: b.record.get("superpixels", 0))
    gsd_used = result.grid.gsd
    return {
        "case": case,
        "gsd": gsd_used,
        "fusion_s": fusion_s,
        "model_s": model_s,
        "model_s_less_dense": model_s - sum(c["dense_s"] for c in clusterings),
        "stages": {k: v["wall_s"] for k, v in result.stages.items()},
        "region": {
            "cells": round(region.footprint.area / gsd_used**2),
            **{k: region.record.get(k) for k in ("superpixels", "hypotheses", "prototypes")},
        },
        "clusterings": clusterings,
        "footprint_quality": m["footprint_2d"]["quality"],
        "height_rmse_off_jumps_m": m["height"]["rmse_off_jumps_m"],
        "volume_quality": m["volume_3d"]["quality"],
    }


COLUMNS = (  # (heading, format, value of one result)
    ("prototypes: sparse (s)", ".2f", lambda r: sum(c["sparse_s"] for c in r["clusterings"])),
    ("... dense, before (s)", ".2f", lambda r: sum(c["dense_s"] for c in r["clusterings"])),
    ("model (s)", ".1f", lambda r: r["model_s_less_dense"]),
    ("fusion (s)", ".1f", lambda r: r["fusion_s"]),
    ("footprint quality", ".3f", lambda r: r["footprint_quality"]),
    ("height RMSE off jumps (m)", ".2f", lambda r: r["height_rmse_off_jumps_m"]),
)


def table(results: dict) -> str:
    """Markdown: a row per seed and case, and the medians of the two seed groups."""
    head = ["seed", "case", "cell (m)", "region: cells / super-pixels / hypotheses / prototypes"]
    head += [c[0] for c in COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for key, r in results.items():
        reg = r["region"]
        region = (
            f"{reg['cells']} / {reg['superpixels']} / {reg['hypotheses']} / {reg['prototypes']}"
        )
        cells = [key.split("_")[0], r["case"], f"{r['gsd']}", region]
        cells += [format(f(r), fmt) for _, fmt, f in COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    for name, group in (("median 0-2", TUNED), ("median 3-5 (held out)", HELD_OUT)):
        for case in CASES:
            rows = [
                r for k, r in results.items() if int(k.split("_")[0]) in group and r["case"] == case
            ]
            if rows:
                cells = [name, case, f"{rows[0]['gsd']}", ""]
                cells += [format(statistics.median(map(f, rows)), fmt) for _, fmt, f in COLUMNS]
                lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[*TUNED, *HELD_OUT])
    ap.add_argument("--out", type=Path, default=Path("bench_out") / "terrace")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for seed in args.seeds:
        for case in CASES:
            results[f"{seed}_{case}"] = run(seed, case, args.out)
            print(f"terrace seed {seed}, {case}: done", flush=True)
    (args.out / "terrace.json").write_text(json.dumps(results, indent=1) + "\n")
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
