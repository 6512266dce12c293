"""Where a run's height error lies against the survey's viewpoints.

A building standing beyond the outermost viewpoints along x or y has an outer side that
no camera looks at: no view stands beyond it looking back, so its outer wall and the
ground behind it are hidden (the oblique views look away from them). A TSDF mesh of the
views keeps no surface there, and a path modelling from a mesh knows less of those
buildings than one modelling from the views' fusion, whose rays still say where space is
free. This script splits the height RMSE off the truth's height jumps (as `workbench
compare` scores it) between the true buildings wholly inside the rectangle of the
viewpoints (the cameras' centres) and those reaching beyond it.

Usage: python benchmarks/survey_edge.py SCENE RUN [RUN ...] [--json FILE]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from workbench import metrics
from workbench.evaluate import EvaluationOptions, RunOnGrid
from workbench.raster import Grid
from workbench.runs import load_run
from workbench.scene import load_scene
from workbench.truth import Truth, load_scene_truth


def beyond_viewpoints(truth: Truth, centres: np.ndarray) -> np.ndarray:
    """(H, W) bool: the cells of the true buildings with a cell outside the rectangle of
    the viewpoints ``centres`` ((N, 3) metres, world frame)."""
    X, Y = truth.grid.cell_centers()
    (x0, y0), (x1, y1) = centres[:, :2].min(axis=0), centres[:, :2].max(axis=0)
    outside = ~((X >= x0) & (X <= x1) & (Y >= y0) & (Y <= y1))
    ids = truth.building_ids
    reaching = np.unique(ids[outside & (ids > 0)])
    return np.isin(ids, reaching[reaching > 0])


def edge_split(truth: Truth, beyond: np.ndarray, surface: np.ndarray) -> dict:
    """Height RMSE off the truth's jumps (:func:`workbench.metrics.height_errors`, as
    `compare` scores it) over every true building cell, over the buildings inside the
    viewpoints and over those beyond them; the share of the squared error beyond.
    ``surface`` is the model's (H, W) height, the ground where it has none."""
    tb = truth.building_surface
    on = truth.building_ids > 0
    jumps = metrics.height_jumps(tb)
    scored = on & np.isfinite(tb) & ~jumps

    def rmse(mask):
        return metrics.height_errors(surface, tb, mask, jumps).get("rmse_off_jumps_m")

    return {
        "rmse_off_jumps_m": rmse(on),
        "inside_rmse_off_jumps_m": rmse(on & ~beyond),
        "beyond_rmse_off_jumps_m": rmse(on & beyond),
        "beyond_share_of_square": metrics.error_share_off_jumps(surface, tb, on, beyond, jumps),
        "cells_inside": int((scored & ~beyond).sum()),
        "cells_beyond": int((scored & beyond).sum()),
    }


def run_surface(run_dir: str, grid: Grid, truth: Truth) -> np.ndarray:
    """A run folder's modelled surface on the truth's grid, as `compare` reads it."""
    layers = RunOnGrid(load_run(run_dir), grid, truth.crs, EvaluationOptions())
    return layers.layers(slice(0, grid.shape[0]), slice(0, grid.shape[1]), truth.dtm).surface


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--json", help="write the figures there too")
    args = ap.parse_args(argv)
    truth = load_scene_truth(args.scene)
    scene = load_scene(args.scene, check_files=False)
    beyond = beyond_viewpoints(truth, np.array([v.camera.center for v in scene.views]))
    ids = truth.building_ids
    n_beyond = len(np.unique(ids[beyond]))
    print(f"{args.scene}: {len(np.unique(ids[ids > 0]))} buildings, {n_beyond} reaching beyond "
          f"the viewpoints")  # fmt: skip
    out = {}
    for r in args.runs:
        out[r] = f = edge_split(truth, beyond, run_surface(r, truth.grid, truth))
        print(f"  {r}: off the jumps {f['rmse_off_jumps_m']:.3f} m; buildings inside "
              f"{f['inside_rmse_off_jumps_m']:.3f} m, beyond {f['beyond_rmse_off_jumps_m']:.3f} "
              f"m ({f['beyond_share_of_square']:.2f} of the squared error)")  # fmt: skip
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
