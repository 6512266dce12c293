"""The fusion's class CRF against its weight omega, on the tuning seeds only.

For each fusion run (``workbench fusion SCENE --truth SCENE``, as ``benchmarks/seeds.py``
makes them), the class CRF of :mod:`fusion.class_crf` is solved again on the run's
``class_prob.tif``, ``ortho.tif`` and ``dsm.tif`` for each omega, and scored against the
truth off the training strokes, as ``workbench compare`` scores a fusion. omega 0 is each
cell's most probable class (the paper). The run's DSM is the one after the crown tops
(which read the CRF's tree class), so a row may differ from a fresh fusion's by a few
cells; omega was chosen from these rows on seeds 0-2, and this script refuses to look at
the held-out seeds 3-5.

Usage: python benchmarks/class_crf_omega.py [--runs bench_out/seeds] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from fusion.class_crf import contrast_class_crf
from workbench import metrics
from workbench.fusion_run import read_fusion_run
from workbench.truth import training_cells, truth_rasters

OMEGAS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
TUNING = (0, 1, 2)


def omega_scores(fusion_dir: Path, scene: Path, omegas=OMEGAS) -> dict:
    """{omega: (overall accuracy, building / other accuracy, seconds)} of one fusion run."""
    run = read_fusion_run(fusion_dir, ("ortho", "dsm", "class_prob"))
    prob, dsm = run.rasters["class_prob"], run.band("dsm")
    truth = truth_rasters(scene, run.grid)["class"]
    strokes = training_cells(scene, run.grid)
    out = {}
    for omega in omegas:
        t0 = time.perf_counter()
        classes = contrast_class_crf(prob, run.rgb, dsm, omega)
        seconds = time.perf_counter() - t0
        c = metrics.classification(classes, truth, exclude=strokes)
        out[omega] = (c["overall_accuracy"], c["building_accuracy"], seconds)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("bench_out") / "seeds")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(TUNING))
    args = ap.parse_args()
    if set(args.seeds) - set(TUNING):
        raise SystemExit("class_crf_omega: omega is chosen on the tuning seeds 0-2 only")
    rows = {s: omega_scores(args.runs / f"fusion{s}", args.runs / f"scene{s}") for s in args.seeds}
    print("| omega | " + " | ".join(f"seed {s}" for s in args.seeds) + " | median |")
    print("|---" * (len(args.seeds) + 2) + "|")
    for omega in OMEGAS:
        acc = [rows[s][omega][0] for s in args.seeds]
        cells = " | ".join(f"{rows[s][omega][0]:.4f} ({rows[s][omega][1]:.4f})" for s in args.seeds)
        print(f"| {omega:g} | {cells} | {np.median(acc):.4f} |")
    secs = [rows[s][8.0][2] for s in args.seeds]
    print(f"\noverall accuracy (building / other); omega 8 took {np.median(secs):.1f} s per seed")


if __name__ == "__main__":
    main()
