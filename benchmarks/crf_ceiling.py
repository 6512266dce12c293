"""What the class CRF of the super-pixel path can reach on a run.

The issue asks the CRF to gain 2 points of overall accuracy over the fused pixel classes.
A CRF only relabels whole super-pixels, and only towards what their neighbours say. This
script scores, against the truth and with the metric of Table 1 (``_table1``):

- the path's rows (pixel, super-pixel argmax, CRF at the run's omega) and the CRF over a
  range of omega (:data:`modeling.superpixel.class_crf.OMEGA_CANDIDATES`);
- the super-pixel majority: every super-pixel takes the true class of most of its
  cells, the most any labelling of these super-pixels can score;
- the neighbour ceiling: the CRF's labels with every wrong patch set right where most of
  its outer boundary touches neighbours that already hold its true class (a patch: wrong
  super-pixels side by side that hold one class and want one class, which a CRF can
  relabel together). A smoothing prior pulls a patch towards its neighbours' label, so it
  may mend those whatever their unary; a patch whose neighbours are mostly as wrong as
  itself it pulls the wrong way, and only a better unary (the fused probabilities) can
  mend it. This is an estimate of what any omega or pairwise weight can gain, not a
  bound: chains of patches mended one after another are not counted.

Usage: python benchmarks/crf_ceiling.py SUPERPIXEL_RUN --truth SCENE [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from modeling.superpixel.aggregation import superpixel_graph
from modeling.superpixel.class_crf import OMEGA_CANDIDATES, refine_classes
from workbench import metrics
from workbench.fusion_run import class_map, read_fusion_run
from workbench.raster import class_codes, read_raster
from workbench.truth import training_cells, truth_rasters

CLASS_NAMES = ("ground", "grass", "tree", "building")


def superpixel_majority(labels: np.ndarray, truth: np.ndarray, n: int) -> np.ndarray:
    """(n,) the true class (1..4) most of each super-pixel's cells have, 0 where none of
    its cells has one.

    Parameters
    ----------
    labels : (H, W) int super-pixels 0..n-1
    truth : (H, W) int true classes 1..4, 0 unknown
    n : int number of super-pixels
    """
    known = (truth >= 1) & (truth <= len(CLASS_NAMES))
    counts = np.zeros((n, len(CLASS_NAMES) + 1), np.int64)
    np.add.at(counts, (labels[known], truth[known]), 1)
    return np.where(counts[:, 1:].sum(axis=1) > 0, counts[:, 1:].argmax(axis=1) + 1, 0)


def wrong_patches(edges: np.ndarray, assigned: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """(n,) patch index of each wrong super-pixel, -1 for the right ones: a patch joins
    adjacent wrong super-pixels that hold the same class and want the same class, as a
    CRF may relabel them together.

    Parameters
    ----------
    edges : (E, 2) int adjacent super-pixel pairs
    assigned : (n,) int class each super-pixel holds
    wanted : (n,) int class each super-pixel should hold (0: unknown, never wrong)
    """
    n = len(assigned)
    wrong = (wanted > 0) & (assigned != wanted)
    a, b = edges[:, 0], edges[:, 1]
    same = wrong[a] & wrong[b] & (assigned[a] == assigned[b]) & (wanted[a] == wanted[b])
    graph = sparse.coo_matrix((np.ones(same.sum()), (a[same], b[same])), shape=(n, n))
    _, component = csgraph.connected_components(graph, directed=False)
    _, patch = np.unique(component[wrong], return_inverse=True)
    out = np.full(n, -1, np.int64)
    out[wrong] = patch
    return out


def patch_support(
    edges: np.ndarray,
    boundary: np.ndarray,
    assigned: np.ndarray,
    wanted: np.ndarray,
    patch: np.ndarray,
) -> np.ndarray:
    """(n_patches,) share of each patch's outer boundary whose neighbour is assigned the
    class the patch wants (0 for a patch with no neighbour).

    Parameters
    ----------
    edges : (E, 2) int adjacent super-pixel pairs
    boundary : (E,) float boundary length of each pair, cells
    assigned, wanted : (n,) int as :func:`wrong_patches`
    patch : (n,) int from :func:`wrong_patches`
    """
    n_patches = int(patch.max()) + 1
    agree = np.zeros(n_patches)
    total = np.zeros(n_patches)
    for a, b in ((edges[:, 0], edges[:, 1]), (edges[:, 1], edges[:, 0])):
        outer = (patch[a] >= 0) & (patch[a] != patch[b])
        np.add.at(total, patch[a][outer], boundary[outer])
        np.add.at(agree, patch[a][outer], boundary[outer] * (assigned[b] == wanted[a])[outer])
    return agree / np.maximum(total, 1e-12)


def crf_ceiling(run_dir: Path, scene: Path) -> dict:
    """The figures of the module docstring for one ``workbench model superpixel`` run."""
    record = json.loads((run_dir / "model.json").read_text())
    omega = record["parameters"]["omega_class"]
    fusion = read_fusion_run(record["inputs"]["fusion"], ("ortho", "dsm", "class_prob"))
    rasters, grid = fusion.rasters, fusion.grid
    prob = rasters["class_prob"]
    labels = read_raster(run_dir / "superpixels.tif")[0][0].astype(np.int64)
    labels -= labels.min()
    graph = superpixel_graph(
        labels, np.moveaxis(rasters["ortho"], 0, -1), prob, rasters["dsm"][0].astype(np.float64),
        classes=class_map(record["inputs"]["fusion"], grid),
    )  # fmt: skip
    truth = truth_rasters(scene, grid)["class"]
    strokes = training_cells(scene, grid)  # not scored, as in the run's own Table 1
    no_data = ~(np.nan_to_num(prob).sum(axis=0) > 0)

    def accuracy(classes: np.ndarray) -> float:
        raster = np.where(no_data, 0, classes).astype(np.uint8)
        return metrics.classification(raster, truth, exclude=strokes)["overall_accuracy"]

    crf = refine_classes(graph, omega)
    majority = superpixel_majority(labels, np.where(no_data, 0, truth), graph.n)
    scored = majority > 0
    patch = wrong_patches(graph.edges, crf, majority)
    wrong = patch >= 0
    support = patch_support(graph.edges, graph.boundary, crf, majority, patch)
    mendable = wrong.copy()
    mendable[wrong] = support[patch[wrong]] > 0.5
    cells = np.bincount(labels[~no_data], minlength=graph.n)
    confusions = {}
    for k in np.flatnonzero(wrong):
        key = f"{CLASS_NAMES[crf[k] - 1]} for {CLASS_NAMES[majority[k] - 1]}"
        confusions[key] = confusions.get(key, 0) + int(cells[k])
    return {
        "omega": omega,
        "pixel": accuracy(class_codes(prob)),  # the paper's pixel column: each cell's argmax
        "superpixel": accuracy((graph.class_sum.argmax(axis=1) + 1)[labels]),
        "crf": accuracy(crf[labels]),
        "crf_by_omega": {
            str(w): accuracy(refine_classes(graph, w)[labels]) for w in OMEGA_CANDIDATES
        },
        "superpixel_majority": accuracy(np.where(scored, majority, crf)[labels]),
        "neighbour_ceiling": accuracy(np.where(mendable, majority, crf)[labels]),
        "wrong_superpixels": int(wrong.sum()),
        "wrong_patches": int(patch.max()) + 1,
        "wrong_cells": int(cells[wrong].sum()),
        "mendable_cells": int(cells[mendable].sum()),
        "wrong_cells_by_confusion": dict(sorted(confusions.items(), key=lambda kv: -kv[1])),
    }


def print_ceiling(c: dict) -> None:
    by_omega = ", ".join(f"{w}: {a:.4f}" for w, a in c["crf_by_omega"].items())
    print(
        f"  class CRF ceiling (benchmarks/crf_ceiling.py): pixel {c['pixel']:.4f}, super-pixel "
        f"{c['superpixel']:.4f}, CRF {c['crf']:.4f} (omega {c['omega']:g}); over omega {by_omega}"
    )
    print(
        f"  every super-pixel its true majority {c['superpixel_majority']:.4f}; the CRF's "
        f"{c['wrong_cells']} wrong cells ({c['wrong_superpixels']} super-pixels in "
        f"{c['wrong_patches']} patches) with the patches mended whose neighbours hold their "
        f"class over half their outer boundary ({c['mendable_cells']} cells) "
        f"{c['neighbour_ceiling']:.4f}"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a `workbench model superpixel` output folder")
    ap.add_argument("--truth", type=Path, required=True, help="the sample scene")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    c = crf_ceiling(args.run, args.truth)
    print_ceiling(c)
    if args.json:
        args.json.write_text(json.dumps(c, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
