"""The fusion's class CRF on hand-made grids: boundaries move to the colour edge or the
height jump, confident cells stay, tiles do not show."""

import numpy as np
import pytest
from scipy import ndimage

from fusion.class_crf import contrast_betas, contrast_class_crf, contrast_terms
from workbench.engine import ThreadEngine
from workbench.graph_cuts import grid_pairs

GREY, GREEN = (130, 130, 125), (80, 130, 60)


def blurred_lawn(width: int = 60, edge: int = 34, blur_from: int = 26, blur_to: int = 36):
    """Grey paving left of column ``edge``, a green lawn right of it; the confidences
    ramp from ground to grass across columns ``blur_from``-``blur_to``, so the most
    probable class changes just past their middle (32; a tie at 31 goes to ground), two
    cells before the colour edge, as patch features blur it."""
    H, W = 40, width
    ortho = np.empty((H, W, 3), np.uint8)
    ortho[:, :edge], ortho[:, edge:] = GREY, GREEN
    t = np.clip((np.arange(W) - blur_from) / (blur_to - blur_from), 0.02, 0.98)
    prob = np.zeros((4, H, W), np.float32)
    prob[0], prob[1] = 1.0 - t, t
    return prob, ortho, np.zeros((H, W), np.float32)


def test_the_boundary_moves_to_the_colour_edge():
    prob, ortho, dsm = blurred_lawn()
    argmax = contrast_class_crf(prob, ortho, dsm, omega=0.0)
    assert (argmax[:, :32] == 1).all() and (argmax[:, 32:] == 2).all()
    crf = contrast_class_crf(prob, ortho, dsm, omega=8.0)
    assert (crf[:, :34] == 1).all() and (crf[:, 34:] == 2).all()


def test_a_height_jump_is_an_edge_too():
    # a grey roof on grey paving: no colour edge, a 6 m wall at column 34
    prob, ortho, dsm = blurred_lawn()
    ortho[:] = GREY
    prob[3], prob[1] = prob[1], 0.0  # building instead of grass
    dsm[:, 34:] = 6.0
    crf = contrast_class_crf(prob, ortho, dsm, omega=8.0)
    assert (crf[:, :34] == 1).all() and (crf[:, 34:] == 4).all()


def test_small_objects_with_edges_stay_and_unseen_cells_stay_unseen():
    prob, ortho, dsm = blurred_lawn()
    # a confident 3 x 3 crown inside the paving: dark and 3 m high
    prob[:, 10:13, 10:13] = 0.0
    prob[2, 10:13, 10:13] = 1.0
    ortho[10:13, 10:13] = (40, 70, 30)
    dsm[10:13, 10:13] = 3.0
    prob[:, 20:22, :] = np.nan  # unseen rows
    crf = contrast_class_crf(prob, ortho, dsm, omega=8.0)
    assert (crf[10:13, 10:13] == 3).all()
    assert (crf[20:22] == 0).all()
    assert (crf[:20, 34:] == 2).all() and (crf[22:, 34:] == 2).all()


def test_a_patch_without_any_edge_is_smoothed_away():
    # the Potts model's price: a confident 2 x 2 patch with neither colour nor height of
    # its own costs more boundary (omega 8 x 16.5) than its cells' data (4 x 9.2)
    prob, ortho, dsm = blurred_lawn()
    prob[:, 10:12, 10:12] = 0.0
    prob[2, 10:12, 10:12] = 1.0
    assert (contrast_class_crf(prob, ortho, dsm, omega=8.0)[10:12, 10:12] == 1).all()


def test_tiles_do_not_show():
    # lawns of several sizes on paving, each with blurred confidences; tiles of 64 cells
    # cut through them
    H, W = 150, 170
    rows, cols = np.mgrid[:H, :W]
    lawn = ((rows // 37) % 2 == 0) & ((cols // 41) % 2 == 1)
    ortho = np.where(lawn[..., None], np.array(GREEN, np.uint8), np.array(GREY, np.uint8))
    t = ndimage.uniform_filter(lawn.astype(float), 7).clip(0.02, 0.98)
    prob = np.zeros((4, H, W), np.float32)
    prob[0], prob[1] = 1.0 - t, t
    dsm = np.zeros((H, W), np.float32)
    one = contrast_class_crf(prob, ortho, dsm, omega=8.0, tile=512)
    tiled = contrast_class_crf(prob, ortho, dsm, omega=8.0, tile=64)
    np.testing.assert_array_equal(one, tiled)
    np.testing.assert_array_equal(one, np.where(lawn, 2, 1))
    # the tiles as tasks of three threads: the same labels
    threads = contrast_class_crf(prob, ortho, dsm, omega=8.0, tile=64, engine=ThreadEngine(3))
    np.testing.assert_array_equal(threads, tiled)


def test_betas_are_the_inverse_mean_squared_differences():
    ortho = np.zeros((2, 3, 3), np.uint8)
    ortho[:, 1:] = 255  # a black-to-white edge: L* 0 to 100
    dsm = np.array([[0.0, 2.0, 2.0], [0.0, 2.0, 2.0]])
    seen = np.ones((2, 3), bool)
    pairs, _ = grid_pairs(seen.shape, diagonals=True)
    beta_c, beta_h = contrast_betas(ortho, dsm, seen)
    across = np.array([(a % 3 == 0) != (b % 3 == 0) for a, b in pairs])
    assert beta_h == pytest.approx(1.0 / (2.0 * 4.0 * across.mean()))
    assert beta_c == pytest.approx(1.0 / (2.0 * 100.0**2 * across.mean()), rel=1e-3)


def test_betas_in_bands_are_the_mean_over_every_pair():
    """Summed band by band, the betas are those of every seen pair of the grid at once
    (contrast_terms over grid_pairs), whatever the band's height."""
    rng = np.random.default_rng(5)
    ortho = rng.integers(0, 256, (23, 17, 3)).astype(np.uint8)
    dsm = rng.normal(10, 3, (23, 17)).astype(np.float32)
    dsm[rng.random(dsm.shape) < 0.1] = np.nan
    seen = rng.random(dsm.shape) < 0.9
    pairs, _ = grid_pairs(seen.shape, diagonals=True)
    pairs = pairs[seen.ravel()[pairs].all(axis=1)]
    dc2, dh2 = contrast_terms(ortho, dsm, pairs)
    want = 1 / (2 * dc2.mean()), 1 / (2 * np.nanmean(dh2))
    for band in (1, 2, 5, 23, 64):
        assert contrast_betas(ortho, dsm, seen, band=band) == pytest.approx(want, rel=1e-12)


def test_grid_pairs_counts():
    pairs, length = grid_pairs((3, 4))
    assert len(pairs) == 3 * 3 + 2 * 4 and (length == 1).all()
    pairs, length = grid_pairs((3, 4), diagonals=True)
    assert len(pairs) == 17 + 2 * 2 * 3
    assert np.isclose(length[17:], np.sqrt(2)).all()
    assert set(map(tuple, pairs[17:19])) == {(0, 5), (1, 6)}
