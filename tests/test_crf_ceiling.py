"""benchmarks/crf_ceiling.py: hand-made graphs, and the tiny city's super-pixel run."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from data_samples.truth_run import truth_fusion_run
from tests.conftest import run_cli
from workbench.raster import read_raster, write_raster

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from crf_ceiling import (  # noqa: E402
    crf_ceiling,
    patch_support,
    superpixel_majority,
    wrong_patches,
)


def test_superpixel_majority_by_hand():
    labels = np.array([[0, 0, 1], [0, 2, 1]])
    truth = np.array([[2, 2, 0], [3, 4, 0]])  # super-pixel 1 has no known cell
    np.testing.assert_array_equal(superpixel_majority(labels, truth, 3), [2, 0, 4])


def test_wrong_patches_and_their_support_by_hand():
    # a row of five super-pixels; 1 and 2 both hold tree (3) and want grass (2): one patch;
    # 4 holds ground (1) and wants building (4): a patch of its own
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4]])
    boundary = np.array([4.0, 2.0, 6.0, 3.0])
    assigned = np.array([2, 3, 3, 1, 1])
    wanted = np.array([2, 2, 2, 1, 4])
    patch = wrong_patches(edges, assigned, wanted)
    np.testing.assert_array_equal(patch, [-1, 0, 0, -1, 1])
    support = patch_support(edges, boundary, assigned, wanted, patch)
    # patch 0's outer boundary: 4 cells to super-pixel 0 (grass, as it wants) and 6 to
    # super-pixel 3 (ground); the 2 cells inside the patch do not count
    # patch 1's: 3 cells to super-pixel 3 (ground, not building)
    np.testing.assert_allclose(support, [4.0 / 10.0, 0.0])


def test_a_wrong_pair_wanting_different_classes_is_two_patches():
    edges = np.array([[0, 1]])
    patch = wrong_patches(edges, np.array([3, 3]), np.array([2, 1]))
    assert patch[0] != patch[1] and min(patch) >= 0
    np.testing.assert_allclose(
        patch_support(edges, np.array([5.0]), np.array([3, 3]), np.array([2, 1]), patch),
        [0.0, 0.0],
    )


@pytest.fixture(scope="module")
def superpixel_run(tiny_scene, tmp_path_factory):
    """The path on the truth's rasters with class probabilities blurred by noise (seeded):
    per cell, and in blocks of 6 x 6 cells, so that the pixels, the super-pixels and the
    CRF disagree and some wrong super-pixels lie side by side."""
    root = tmp_path_factory.mktemp("crf_ceiling")
    fusion = truth_fusion_run(tiny_scene, root / "fusion")
    prob, grid, crs = read_raster(fusion / "class_prob.tif")
    rng = np.random.default_rng(0)
    blocks = rng.random((4, prob.shape[1] // 6 + 1, prob.shape[2] // 6 + 1))
    blocks = np.kron(blocks, np.ones((1, 6, 6)))[:, : prob.shape[1], : prob.shape[2]]
    noisy = (prob + 0.6 * rng.random(prob.shape) + 2.0 * blocks).astype(np.float32)
    noisy /= noisy.sum(axis=0)
    write_raster(fusion / "class_prob.tif", noisy, grid, crs)
    write_raster(fusion / "class.tif", (noisy.argmax(axis=0) + 1).astype(np.uint8), grid, crs)
    out = root / "model"
    proc = run_cli(
        "model", "superpixel", fusion, "-o", out, "--truth", tiny_scene, "--workers", "1"
    )
    assert proc.returncode == 0, proc.stderr
    return out, json.loads((out / "model.json").read_text()), tiny_scene


def test_ceiling_of_the_tiny_run_orders_its_rows(superpixel_run):
    out, record, scene = superpixel_run
    c = crf_ceiling(out, scene)
    table = record["classification_table"]
    # the same scorer as the run's own Table 1
    for row in ("pixel", "superpixel", "crf"):
        assert c[row] == pytest.approx(table[row]["overall_accuracy"], abs=1e-12)
    assert c["crf_by_omega"][str(float(record["parameters"]["omega_class"]))] == c["crf"]
    assert c["pixel"] < c["superpixel"] < c["superpixel_majority"]
    assert c["crf"] < c["neighbour_ceiling"] <= c["superpixel_majority"]
    assert c["mendable_cells"] <= c["wrong_cells"]
    assert sum(c["wrong_cells_by_confusion"].values()) == c["wrong_cells"]
