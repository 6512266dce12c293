"""The fusion steps as plain functions, on hand-computed cases."""

import cv2
import numpy as np
import pytest

from fusion.classifier import elevation_consistent, elevation_prior
from fusion.crowns import crown_sightings, crown_tops, sightings_clear_of_buildings
from fusion.geometry_cues import UNKNOWN, cue_columns, plane_residual, window_cells
from fusion.ground import dtm_from_dsm
from fusion.interpolate import fill_small_holes, push_pull_fill, small_holes
from fusion.observations import (
    OBSERVE_MARGIN,
    behind_occlusions,
    close_neighbours,
    depth_jumps,
    depth_outliers,
    grid_window,
    height_weights,
    near_side,
    nearest_depth,
    normal_z_image,
    normals_from_near_side,
    observe,
    visibility_groups,
)
from fusion.points import top_surface_at_cells
from fusion.scene_fusion import (
    ObservationCache,
    elevation_image,
    isolated_spikes,
    tile_shape,
    top_surface_votes,
)
from fusion.sigma_points import N_FEATURES, feature_cues, sigma_points
from workbench.camera import Camera, look_at_rotation
from workbench.raster import Grid
from workbench.robust import (
    group_count,
    group_mean,
    group_median,
    group_weighted_median,
    group_weighted_quantile,
    vector_median,
)


def test_group_median_and_mean():
    cells = np.array([0, 0, 0, 2, 2, 2, 2, 3])
    vals = np.array([5.0, 1.0, 100.0, 4.0, 1.0, 3.0, 2.0, 7.0])
    med = group_median(cells, vals, 5)
    np.testing.assert_array_equal(med[[0, 2, 3]], [5.0, 2.5, 7.0])
    assert np.isnan(med[1]) and np.isnan(med[4])
    np.testing.assert_allclose(group_mean(cells, vals, 5)[[0, 2, 3]], [106 / 3, 2.5, 7.0])
    np.testing.assert_array_equal(group_count(cells, 5), [3, 0, 4, 1, 0])
    np.testing.assert_array_equal(
        group_median(cells, vals.astype(int), 5)[[0, 2, 3]], med[[0, 2, 3]]
    )


def test_cell_layout_medians_are_numpy_s_over_every_count_and_block():
    from workbench.robust import CellLayout

    rng = np.random.default_rng(4)
    sizes = [1, 2, 3, 4, 5, 8, 9, 17, 100, 1000]  # each power-of-two bucket's edges
    cells = np.repeat(np.arange(len(sizes)) * 2, sizes)  # odd cells empty
    rng.shuffle(cells)
    values = rng.normal(size=(3, len(cells))).round(2)  # ties too
    layout = CellLayout.of(cells, 2 * len(sizes))
    layout.BLOCK = 8  # a few cells per block: the blocks' seams are crossed
    med = layout.medians(values[:, layout.order])
    for k in range(len(sizes)):
        np.testing.assert_array_equal(med[:, 2 * k], np.median(values[:, cells == 2 * k], 1))
    assert np.isnan(med[:, 1::2]).all()


def test_vector_median_is_the_definition_cell_by_cell():
    rng = np.random.default_rng(5)
    cells = rng.integers(0, 30, 600)
    v = rng.integers(0, 4, (600, 3)).astype(np.uint8) * 60  # few colours: equal scores
    out = vector_median(cells, v, 32, n_projections=5, seed=3)
    dirs = np.random.default_rng(3).normal(size=(5, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for cell in range(32):
        obs = np.flatnonzero(cells == cell)
        if not len(obs):
            assert (out[cell] == 0).all()
            continue
        proj = v[obs].astype(np.float64) @ dirs.T
        dev = np.abs(proj - np.median(proj, axis=0))
        score = (dev / (np.median(dev, axis=0) + 1e-6)).max(axis=1)
        # the least score; among equal ones the cell's first observation
        np.testing.assert_array_equal(out[cell], v[obs[np.argmin(score)]])


def test_group_weighted_median_by_hand_and_with_equal_weights():
    cells = np.array([0, 0, 0, 2, 2, 2, 2, 3])
    vals = np.array([5.0, 1.0, 100.0, 4.0, 1.0, 3.0, 2.0, 7.0])
    # cell 0: 1 (w 1), 5 (w 1), 100 (w 3): half of 5 is reached at 100
    # cell 2: 1, 2, 3, 4 with w 3, 1, 1, 1: half of 6 reached exactly at 1 -> (1 + 2) / 2
    w = np.array([1.0, 1.0, 3.0, 1.0, 3.0, 1.0, 1.0, 2.0])
    med = group_weighted_median(cells, vals, w, 5)
    np.testing.assert_array_equal(med[[0, 2, 3]], [100.0, 1.5, 7.0])
    assert np.isnan(med[1]) and np.isnan(med[4])
    rng = np.random.default_rng(1)
    c, v = rng.integers(0, 40, 2000), rng.normal(size=2000).round(1)  # many ties
    np.testing.assert_array_equal(
        group_weighted_median(c, v, np.ones(2000), 45), group_median(c, v, 45)
    )


def test_group_weighted_quantile_is_its_definition_on_runs_of_every_length():
    """Cell by cell, sorted by value: the first whose cumulative weight reaches q of the
    total (within 1e-9), or its mean with the next where it reaches it exactly."""
    rng = np.random.default_rng(7)
    lengths = [1, 2, 3, 5, 8, 13, 64, 65, 200]
    cells = np.repeat(np.arange(len(lengths)) * 2, lengths)  # odd cells stay empty
    rng.shuffle(cells)
    vals = rng.integers(0, 6, len(cells)).astype(np.float64)  # ties within every cell
    w = rng.integers(1, 4, len(cells)).astype(np.float64)  # exact targets happen
    qs = (0.1, 0.25, 0.5, 0.7, 0.9)
    got = group_weighted_quantile(cells, vals, w, 2 * len(lengths), qs)
    for k, q in enumerate(qs):
        for cell in range(2 * len(lengths)):
            mine = cells == cell
            if not mine.any():
                assert np.isnan(got[k, cell])
                continue
            order = np.lexsort((vals[mine], np.zeros(mine.sum())))
            v, cum = vals[mine][order], np.cumsum(w[mine][order])
            target = q * cum[-1]
            i = int(np.argmax(cum >= target - 1e-9 * target))
            exact = abs(cum[i] - target) <= 1e-9 * target and i + 1 < len(v)
            assert got[k, cell] == (0.5 * (v[i] + v[i + 1]) if exact else v[i])


def test_tiles_cut_the_grid_evenly_and_tile_of_finds_them(tmp_path):
    def grid(h, w):
        return Grid.from_bounds(0.0, 0.0, w * 0.5, h * 0.5, 0.5)

    # at most 512 cells a side, as few tiles as that allows, sides differing by one at most
    assert tile_shape(grid(800, 800), 512) == (400, 400)
    assert tile_shape(grid(512, 1000), 512) == (512, 500)
    assert tile_shape(grid(513, 300), 512) == (257, 300)
    cache = ObservationCache(tmp_path, grid(513, 1030), 512)
    assert [t[2:] for t in cache.tiles] == [(257, 344)] * 2 + [(257, 342)] + [(256, 344)] * 2 + [
        (256, 342)
    ]
    r, c = np.meshgrid(np.arange(513), np.arange(1030), indexing="ij")
    owner = cache.tile_of(r, c)
    for t, (r0, c0, h, w) in enumerate(cache.tiles):
        assert (owner[r0 : r0 + h, c0 : c0 + w] == t).all()
        assert (owner == t).sum() == h * w


def test_cell_then_value_order_is_lexsort_s_for_float32_and_float64():
    from workbench.robust import _order_by_cell_then_value

    rng = np.random.default_rng(3)
    cells = rng.integers(0, 50, 5000)
    # negative values, both zeros (which must tie), infinities and many exact ties
    vals = rng.normal(0, 3, 5000).round(1)
    vals[rng.random(5000) < 0.05] = -0.0
    vals[:2] = [np.inf, -np.inf]
    for dtype in (np.float32, np.float64):
        v = vals.astype(dtype)
        np.testing.assert_array_equal(_order_by_cell_then_value(cells, v), np.lexsort((v, cells)))


def test_group_weighted_quantile_by_hand():
    cells = np.array([0, 0, 0, 0, 2, 2])
    vals = np.array([4.0, 1.0, 3.0, 2.0, 10.0, 20.0])
    w = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 3.0])
    # cell 0: 1, 2, 3, 4 of weight 1: 0.7 of 4 (2.8) is reached at 3; 0.5 exactly at 2
    # cell 2: 10 (w 1), 20 (w 3): 0.2 of 4 is reached at 10, 0.7 at 20
    q7 = group_weighted_quantile(cells, vals, w, 3, 0.7)
    np.testing.assert_array_equal(q7[[0, 2]], [3.0, 20.0])
    assert np.isnan(q7[1])
    assert group_weighted_quantile(cells, vals, w, 3, 0.2)[2] == 10.0
    np.testing.assert_array_equal(
        group_weighted_quantile(cells, vals, w, 3, 0.5), group_weighted_median(cells, vals, w, 3)
    )
    assert group_weighted_quantile(cells, vals, w, 3, 0.5)[0] == 2.5  # the tie, as a median
    # several quantiles from one sort: the same as one by one
    both = group_weighted_quantile(cells, vals, w, 3, (0.5, 0.7))
    assert both.shape == (2, 3)
    np.testing.assert_array_equal(both[0][[0, 2]], [2.5, 20.0])
    np.testing.assert_array_equal(both[1], q7)
    assert group_weighted_quantile(cells[:0], vals[:0], w[:0], 3, (0.5, 0.7)).shape == (2, 3)


def test_crown_tops_raise_tree_edges_but_not_beside_buildings():
    """A crown whose edge cells the fusion read low and called grass, and a building whose
    ground cells beside its wall have high upper quantiles (facade points): only the
    crown's cells, and those next to it, take the upper quantile."""
    classes = np.full((12, 20), 2)
    classes[3:8, 2:6] = 3  # tree
    classes[3:8, 13:18] = 4  # building
    dsm = np.where(classes >= 3, 8.0, 0.0)
    dsm[3:8, 6] = 1.0  # the crown's east edge: ground under it mixed in, read low
    upper = dsm + 0.2
    upper[3:8, 6] = 7.5
    upper[3:8, 12] = 6.0  # beside the wall: roof-edge points in the ground cells
    out, raised = crown_tops(dsm, upper, classes, gsd=0.25)
    np.testing.assert_array_equal(out[3:8, 6], 7.5)
    np.testing.assert_array_equal(out[3:8, 12], 0.0)
    np.testing.assert_allclose(out[3:8, 3], 8.2, rtol=1e-6)  # inside the crown too (float32)
    assert not raised[:, 8:].any() and not raised[10:].any()  # more than 0.5 m from the tree
    assert raised[3:8, 2:7].all()


def test_sightings_beside_a_building_take_back_their_median():
    """Ground cells at a wall's foot that the sightings raised to heights between the
    ground and the eaves (wall and ramp points called tree) take back their median, within
    0.75 m (3 cells of 0.25 m) of the building; a crown's rim keeps its sightings."""
    classes = np.full((10, 30), 2)
    classes[2:8, 20:26] = 4  # building, eaves at 9 m
    classes[2:8, 2:7] = 3  # crown, 8 m
    median = np.where(classes >= 3, np.where(classes == 4, 9.0, 8.0), 0.0)
    sighted = np.zeros(classes.shape, bool)
    sighted[2:8, 7] = True  # the crown's rim, read on the ground beneath it
    sighted[2:8, 14:20] = True  # west of the wall: 6 cells, 1.5 m to 0.25 m from it
    dsm = np.where(sighted, 5.0, median)
    out, cleared = sightings_clear_of_buildings(dsm, median, sighted, classes, gsd=0.25)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(cleared[2:8, 17:20], True)  # 0.25 to 0.75 m from the wall
    np.testing.assert_array_equal(out[2:8, 17:20], 0.0)
    np.testing.assert_array_equal(out[2:8, 14:17], 5.0)  # 1 m and more: kept
    np.testing.assert_array_equal(out[2:8, 7], 5.0)  # the crown's rim: kept
    assert cleared.sum() == 18
    np.testing.assert_array_equal(out[~sighted], median[~sighted])


def test_height_weights_are_the_squared_cosine_from_the_vertical():
    center = np.array([0.0, 0.0, 100.0])
    xyz = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0 * 3**0.5, 0.0]])
    np.testing.assert_allclose(height_weights(center, xyz), [1.0, 0.5, 0.25], rtol=1e-6)


def test_vector_median_rejects_outliers_and_returns_an_observed_colour():
    rng = np.random.default_rng(0)
    grey = np.array([120, 120, 120])
    obs = np.clip(grey + rng.normal(0, 4, (9, 3)), 0, 255).astype(np.uint8)
    obs[:3] = [[255, 0, 0], [245, 10, 5], [250, 5, 10]]  # a red car seen by three views
    cells = np.zeros(9, np.int64)
    vm = vector_median(cells, obs, 1, seed=1)[0]
    assert any((vm == o).all() for o in obs)  # one of the observations, not a new colour
    assert np.abs(vm.astype(int) - grey).max() <= 12
    mean = obs.astype(float).mean(axis=0)
    assert np.abs(mean - grey).max() > 30  # the mean is pulled by the outliers


def test_vector_median_several_cells_and_empty_cells():
    cells = np.array([1, 1, 1, 3])
    v = np.array([[10, 10, 10], [12, 11, 10], [200, 0, 0], [5, 6, 7]], np.uint8)
    out = vector_median(cells, v, 4)
    assert (out[0] == 0).all() and (out[2] == 0).all()
    assert tuple(out[3]) == (5, 6, 7)
    assert tuple(out[1]) in {(10, 10, 10), (12, 11, 10)}


def test_sigma_points_match_a_direct_computation():
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 255, (40, 50, 3), dtype=np.uint8)
    elev = rng.normal(3, 1, (40, 50)).astype(np.float32)
    cues = feature_cues(rgb, elev)
    assert cues.shape == (40, 50, 6)
    f = sigma_points(cues, 11)
    assert f.shape == (40, 50, N_FEATURES) and N_FEATURES == 78
    y, x = 20, 25
    P = cues[y - 5 : y + 6, x - 5 : x + 6].reshape(-1, 6).astype(np.float64)
    mu, S = P.mean(0), np.cov(P.T, bias=True)
    L = np.linalg.cholesky(S + np.eye(6) * 1e-6 * np.trace(S) / 6)
    a = np.sqrt(12)
    ref = np.concatenate([mu[None], mu + a * L.T, mu - a * L.T]).ravel()
    np.testing.assert_allclose(f[y, x], ref, rtol=1e-4, atol=1e-3)


def test_sigma_points_of_some_pixels_are_the_rows_of_the_whole_image():
    rng = np.random.default_rng(3)
    cues = feature_cues(
        rng.integers(0, 255, (90, 100, 3), dtype=np.uint8), rng.normal(3, 1, (90, 100))
    )
    whole = sigma_points(cues).reshape(-1, N_FEATURES)
    pixels = np.sort(rng.choice(90 * 100, 5000, replace=False))  # more than one chunk
    out = np.full((len(pixels), N_FEATURES + 2), 7.0, np.float32)
    assert sigma_points(cues, pixels=pixels, out=out) is out
    np.testing.assert_array_equal(out[:, :N_FEATURES], whole[pixels])
    assert (out[:, N_FEATURES:] == 7.0).all()  # the caller's columns untouched


def test_sigma_points_of_a_flat_patch_collapse_to_the_mean():
    cues = np.ones((30, 30, 6), np.float32) * np.arange(1, 7, dtype=np.float32)
    f = sigma_points(cues).reshape(30, 30, 13, 6)
    np.testing.assert_allclose(f[15, 15], np.tile(np.arange(1, 7), (13, 1)), atol=1e-2)


def test_push_pull_fills_a_plane_exactly_enough():
    y, x = np.mgrid[0:64, 0:64]
    plane = 0.1 * x + 0.05 * y + 3
    valid = np.ones_like(plane, bool)
    valid[20:30, 20:34] = False
    filled = push_pull_fill(np.where(valid, plane, np.nan), valid)
    np.testing.assert_array_equal(filled[valid], plane[valid])
    assert np.abs(filled - plane).max() < 0.5


@pytest.mark.parametrize("shape", [(256, 192), (250, 187)])
def test_small_holes_filled_in_windows_as_over_the_whole_raster(shape):
    """Each hole's window gives the whole raster's push-pull values exactly, whether or
    not the raster's sides are multiples of the window's blocks: every level steps up by
    a factor of two, cut at the raster's end (before, a level of odd size was stretched
    and the whole raster's fill was off the surface: mean error 0.73 against 0.35)."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]]
    smooth = 40 + 30 * np.sin(x / 9.0) * np.cos(y / 13.0)
    field = smooth + rng.normal(0, 5, shape)  # noise: the fills must agree, not be near
    rgb = np.clip(np.stack([field, field[::-1], 255 - field], axis=-1), 0, 255).astype(np.uint8)
    missing = rng.random(shape) < 0.03  # mostly single cells
    missing[0, :] = True  # a border hole, and a large one, are not filled
    missing[100:110, 50:70] = True
    holes = small_holes(missing, 9)
    valid = ~missing
    assert holes.sum() > 500 and not holes[100:110, 50:70].any() and not holes[0].any()
    dsm = np.where(valid, field, np.nan).astype(np.float32)
    got = fill_small_holes(dsm, valid, holes, 9)
    want = np.where(holes, push_pull_fill(dsm, valid), dsm).astype(np.float32)
    got_rgb = fill_small_holes(rgb, valid, holes, 9)
    assert got.dtype == np.float32 and got_rgb.dtype == np.uint8
    np.testing.assert_array_equal(np.isnan(got), missing & ~holes)
    np.testing.assert_array_equal(got[~holes], dsm[~holes])  # only the holes change
    np.testing.assert_array_equal(got_rgb[~holes], rgb[~holes])
    want_rgb = [np.round(push_pull_fill(rgb[..., k].astype(float), valid)) for k in range(3)]
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_rgb[holes], np.stack(want_rgb, axis=-1)[holes])


def test_push_pull_levels_double_without_stretching():
    """A plane sampled on every other row and column of a raster of odd sides, with a
    hole of 60 x 80 cells: each level's cells sit over the cells they average, so the
    hole is filled near the plane. With each level resized to the odd size below it, the
    levels were stretched (measured in the hole: median error 8.6, largest 18.8, against
    1.04 and 2.5 now; the plane rises 0.5 a cell)."""
    y, x = np.mgrid[0:301, 0:257]
    plane = 0.5 * x + 0.25 * y
    hole = np.zeros(plane.shape, bool)
    hole[100:160, 90:170] = True
    valid = (x % 2 == 0) & (y % 2 == 0) & ~hole
    error = np.abs(push_pull_fill(plane, valid) - plane)[hole]
    assert np.median(error) < 1.2 and error.max() < 3.0


def test_a_block_fills_and_grounds_as_the_whole_grid_given_its_origin():
    """Given a block's first cell in the grid, the push-pull levels and the DTM's coarse
    cells are the whole grid's: a block's DTM is the whole grid's, byte for byte, where
    its margin holds what that depends on (the ground filter's largest window and the
    fill's reach under a building)."""
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:240, 0:200] * 0.5  # metres, 0.5 m cells
    dsm = 10 + 0.03 * x + 0.02 * y + rng.normal(0, 0.05, x.shape)
    for _ in range(25):  # houses up to 8 m wide, 4 to 9 m high
        r, c, h, w = rng.integers(0, 220), rng.integers(0, 180), *rng.integers(6, 17, 2)
        dsm[r : r + h, c : c + w] += rng.uniform(4, 9)
    dsm[rng.random(x.shape) < 0.3] = np.nan  # scan-line gaps
    rows, cols = slice(37, 203), slice(45, 163)  # odd: on neither the coarse nor the levels
    inner = (slice(40, -40), slice(40, -40))  # 20 m: the 10 m window, a house's width
    kw = dict(max_window=10.0, coarse=1.0)
    whole = dtm_from_dsm(dsm, 0.5, **kw)[0]
    block = dtm_from_dsm(dsm[rows, cols], 0.5, origin=(37, 45), **kw)[0]
    np.testing.assert_array_equal(block[inner], whole[rows, cols][inner])
    shifted = dtm_from_dsm(dsm[rows, cols], 0.5, **kw)[0]
    assert not np.array_equal(shifted[inner], whole[rows, cols][inner])  # without it
    valid = np.isfinite(dsm)
    filled = push_pull_fill(dsm, valid)[rows, cols]
    part = push_pull_fill(dsm[rows, cols], valid[rows, cols], origin=(37, 45))
    np.testing.assert_array_equal(part[inner], filled[inner])


def test_a_window_fills_its_holes_as_the_whole_grid_given_its_origin():
    """A fusion in blocks fills each block's holes: given the block's first cell in the
    grid, a hole away from the block's edges is filled as over the whole grid (the
    windows about the holes fall on the grid's blocks, not the block's)."""
    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:256, 0:192]
    field = 40 + 30 * np.sin(x / 9.0) * np.cos(y / 13.0) + rng.normal(0, 5, y.shape)
    missing = rng.random(field.shape) < 0.03
    holes = small_holes(missing, 9)
    dsm = np.where(missing, np.nan, field).astype(np.float32)
    whole = fill_small_holes(dsm, ~missing, holes, 9)
    rows, cols = slice(37, 211), slice(45, 170)  # a block not on the 32-cell blocks
    part = fill_small_holes(dsm[rows, cols], ~missing[rows, cols], holes[rows, cols], 9,
                            origin=(37, 45))  # fmt: skip
    inner = (slice(50, -50), slice(50, -50))  # beyond a hole window (18 + 31 cells)
    np.testing.assert_array_equal(part[inner], whole[rows, cols][inner])
    shifted = fill_small_holes(dsm[rows, cols], ~missing[rows, cols], holes[rows, cols], 9)
    assert not np.array_equal(shifted[inner], whole[rows, cols][inner])  # without it

    # the fusion's ground step of a block fills its DSM so, given the block's origin
    from fusion.scene_fusion import FusedHeights, fused_ground

    def heights(z):  # each cell seen 10 times: none is a spike to drop
        return FusedHeights(z, z, z, np.zeros_like(z), 10 * np.isfinite(z).astype(np.int32), 0)

    grid = Grid(0.0, 256.0, 1.0, 192, 256)
    full = fused_ground(heights(dsm.copy()), grid, "depth maps", None)[0]
    block = fused_ground(heights(dsm[rows, cols].copy()), grid.window(rows, cols), "depth maps",
                         None, origin=(37, 45))[0]  # fmt: skip
    np.testing.assert_array_equal(block[inner], full[rows, cols][inner])


def test_small_holes_only_inner_and_small():
    m = np.zeros((20, 20), bool)
    m[5, 5] = True  # one cell
    m[10:14, 10:14] = True  # 16 cells
    m[0, 0:3] = True  # touches the border
    h = small_holes(m, 9)
    assert h[5, 5] and not h[10:14, 10:14].any() and not h[0, 0:3].any()


def test_dtm_removes_buildings_and_keeps_sloped_ground():
    gsd = 0.25
    y, x = np.mgrid[0:400, 0:400] * gsd
    ground = 20 + 0.03 * x + 0.01 * y
    dsm = ground.copy()
    dsm[100:180, 120:220] += 12.0  # a 20 m x 25 m building
    dsm[300:320, 50:70] += 6.0  # a tree-sized object
    dtm, is_ground = dtm_from_dsm(dsm, gsd)
    assert np.abs(dtm - ground).max() < 0.3
    assert not is_ground[100:180, 120:220].any()
    assert is_ground[350:, 300:].all()


def test_dtm_removes_a_single_storey_garage():
    """A 2.8 m garage of 15 x 9 m: above the largest threshold Zhang et al. prescribe (the
    lowest building's height), so the filter opens it away; with 3 m it stayed terrain."""
    gsd = 0.25
    y, x = np.mgrid[0:240, 0:240] * gsd
    ground = 17.0 + 0.02 * x
    dsm = ground.copy()
    dsm[100:136, 90:150] += 2.8
    dtm, is_ground = dtm_from_dsm(dsm, gsd)
    assert np.abs(dtm - ground).max() < 0.2
    assert not is_ground[100:136, 90:150].any()
    former, _ = dtm_from_dsm(dsm, gsd, dh_max=3.0)
    assert (former - ground)[100:136, 90:150].max() > 2.7  # the case: it was terrain


def test_dtm_removes_a_building_whose_uphill_wall_is_under_a_storey():
    """A 3.3 m building of 11 x 40 m across a 1 m step of the terrain (dev seed 15's
    T-shaped building): its roof stands 2.3 m above the plateau uphill, which the
    openings follow at every window; at 2.5 m, a storey, part of it stayed terrain."""
    gsd = 0.25
    y = np.mgrid[0:640, 0:640][0] * gsd
    r0, r1 = 500, 544
    ground = 18.0 - np.clip((y - r0 * gsd) / ((r1 - r0) * gsd), 0, 1)  # rows run south
    dsm = ground.copy()
    dsm[r0:r1, 200:360] = 17.0 + 3.3
    dtm, is_ground = dtm_from_dsm(dsm, gsd)
    assert np.abs(dtm - ground).max() < 0.2
    assert not is_ground[r0:r1, 200:360].any()
    former, _ = dtm_from_dsm(dsm, gsd, dh_max=2.5)
    assert (former - ground)[r0:r1, 200:360].max() > 2.0  # the case: part of it was terrain


def test_depth_jumps_flag_edges_not_slopes():
    d = np.full((40, 40), 60.0, np.float32)
    d[:, 20:] = 52.0  # an 8 m step
    d += np.linspace(0, 1.0, 40)[None, :].astype(np.float32)  # a gentle ramp elsewhere
    j = depth_jumps(d)
    assert j[:, 17:23].all() and not j[:, 3:15].any() and not j[:, 25:37].any()


def test_depth_jumps_beside_a_hole_use_the_known_side():
    # a roof at 52 m, its rounded edge 1 m lower, then an occlusion hole and the ground
    d = np.full((40, 40), 52.0, np.float32)
    d[:, 20] = 53.0
    d[:, 21:25] = np.nan
    d[:, 25:] = 60.0
    j = depth_jumps(d)
    # 3 px right of the edge is unknown; 1 m from the roof is a ramp's middle of 2 m
    assert j[5:35, 20].all()
    assert not j[5:35, 3:20].any() and not j[5:35, 25:37].any()


def test_behind_occlusions_flags_the_background_beside_a_hole_not_the_nearer_side():
    # along each row: a roof at 52 m, the 7-pixel hole matching leaves beside its edge,
    # then the background at 60 m, with a lone dropped pixel in it
    d = np.full((12, 50), 60.0, np.float32)
    d[:, :15] = 52.0
    d[:, 15:22] = np.nan
    d[:, 35] = np.nan
    flagged = behind_occlusions(d)
    # the background's 3 pixels beside the hole (the first known pixel across it is 8 m
    # nearer, over max(1 m, 3 % of 60 m)); not the roof, across whose hole lies farther
    # ground; not the background beside its lone pixel
    assert flagged[:, 22:25].all() and flagged.sum() == 3 * 12
    # the same along columns, and mirrored
    np.testing.assert_array_equal(behind_occlusions(d.T.copy()), flagged.T)
    np.testing.assert_array_equal(behind_occlusions(d[:, ::-1].copy()), flagged[:, ::-1])
    # a step of 1.5 m (under the 1.8 m threshold at 60 m) is no jump
    low = np.where(d == 52.0, np.float32(58.5), d)
    assert not behind_occlusions(low).any()
    # across a wider hole the roof counts up to 24 pixels away (the reach), not 25
    wide = d.copy()
    wide[:, 15:37] = np.nan
    assert behind_occlusions(wide)[:, 37:39].all() and behind_occlusions(wide).sum() == 2 * 12


def test_near_side_keeps_the_nearer_surface_not_its_ramp():
    # a row of a view: a roof sloping gently away (60 m + 5 cm a pixel), its edge rounded
    # by matching into a ramp (columns 13-15), then the ground at 100 m
    d = np.full((12, 30), 100.0, np.float32)
    d[:, :15] = 60 + 0.05 * np.arange(15)
    d[:, 13], d[:, 14], d[:, 15] = 60 + 0.09 * 40, 60 + 0.25 * 40, 100 - 0.25 * 40
    jumps = depth_jumps(d)
    side = near_side(d, jumps)
    assert jumps[:, 10:19].all()
    # the roof's pixels within 3 of the jump continue the roof: its side is the left
    # (NEAR_SIDES[2], np.roll by +k along the columns); the ramp and the ground do not
    assert (side[:, 10:13] == 3).all() and not side[:, 13:30].any()
    # mirrored, the roof lies to the right
    flipped = near_side(d[:, ::-1].copy(), depth_jumps(d[:, ::-1].copy()))
    assert (flipped[:, 17:20] == 4).all() and not flipped[:, 3:17].any()
    # beside a hole only one side is known: the ramp's pixel there is not placed
    h = d.copy()
    h[:, 14:] = np.nan
    assert depth_jumps(h)[:, 13].all() and not near_side(h, depth_jumps(h))[:, 13].any()
    # its normal is read 6 pixels in on that side
    nz = np.tile(np.linspace(0.0, 0.29, 30, dtype=np.float32), (12, 1))
    out = normals_from_near_side(nz, side)
    np.testing.assert_array_equal(out[:, 10:13], nz[:, 4:7])
    np.testing.assert_array_equal(out[:, 13:], nz[:, 13:])


def test_observe_trusts_a_roof_beside_its_rounded_edge():
    """The oblique view of a 10 m block, its depth rounded at the edges and noisy as the
    sample's matching (`data_samples.depth.degrade_depth`): the pixels within 3 of the
    roof's edges that continue the roof are trusted, on the roof's height; nothing of
    the ramps is."""
    import fusion.observations as observations
    from data_samples.depth import degrade_depth

    cam, _ = _oblique_view_of_a_block()
    _, dirs = cam.pixel_grid_rays()
    with np.errstate(divide="ignore"):
        ground, roof = -cam.center[2] / dirs[:, 2], (10.0 - cam.center[2]) / dirs[:, 2]
    hit = cam.center[:2] + roof[:, None] * dirs[:, :2]
    on_roof = (np.abs(hit[:, 0]) < 8) & (np.abs(hit[:, 1] - 5) < 6) & (roof > 0)
    true = np.where(on_roof, roof, ground).reshape(cam.height, cam.width)
    true[true <= 0] = np.nan
    flat = np.full(true.shape, 128, np.uint8)
    rng = np.random.default_rng(0)
    depth = degrade_depth(true, flat, np.ones(true.shape, bool), rng, sigma=0.05,
                          reference_depth=80.0, outliers=0.0)  # fmt: skip
    grid = Grid.from_bounds(-15.0, -10.0, 15.0, 20.0, 0.25)
    now = observe(cam, depth, grid)
    import unittest.mock

    with unittest.mock.patch.object(observations, "near_side",
                                    lambda d, j: np.zeros(d.shape, np.int8)):  # fmt: skip
        before = observe(cam, depth, grid)
    np.testing.assert_array_equal(now.pixels, before.pixels)
    new = now.top_surface & ~before.top_surface
    x, y, z = now.xyz[new].T
    on = (np.abs(x) < 8) & (np.abs(y - 5) < 6)
    assert on.sum() > 120  # measured: 163 (of 4312 trusted before)
    assert np.abs(z[on] - 10).max() < 0.15  # measured: 0.093 m
    assert not (z[~on] > 1).any()  # nothing trusted floats beside the block
    # the roof now seen at its rim hides the few points of the ground beyond the edge
    # that landed under it (measured: 4)
    lost = before.top_surface & ~now.top_surface
    x, y, z = now.xyz[lost].T
    assert lost.sum() < 10 and ((np.abs(x) < 8) & (np.abs(y - 5) < 6) & (z < 0.5)).all()


def test_close_neighbours_and_isolated_spikes_by_hand():
    """A 3 x 4 height field: a spike at (1, 1), an unknown cell at (0, 3), and a roof
    edge (5 m) along the last column."""
    h = np.array([[0.0, 0.2, 0.0, np.nan], [0.1, 9.0, 0.4, 5.0], [0.0, 0.0, 0.8, 5.2]])
    near = close_neighbours(h, 1.0)
    # (0, 0): (0, 1) and (1, 0) within 1 m, the spike not; (1, 2): (0, 1), (0, 2),
    # (2, 1) and (2, 2), not the spike, the unknown cell or the roof's two cells
    assert near[0, 0] == 2 and near[1, 1] == 0 and near[1, 2] == 4 and near[2, 2] == 2
    assert near[1, 3] == 1 and near[2, 3] == 1  # the roof's edge: only each other
    count = np.full(h.shape, 3)
    count[1:, 3] = 5  # seen often enough to be trusted
    spikes = isolated_spikes(h, count)
    assert spikes[1, 1] and spikes.sum() == 1
    count[2, 3] = 4  # thinly seen: the roof's lone corner counts as a spike too
    assert isolated_spikes(h, count)[2, 3]


def test_depth_outliers_are_isolated_pixels_not_corners_or_rims():
    d = np.full((30, 30), 100.0, np.float32)
    d[5:15, 5:15] = 90.0  # a roof: its corner pixels have 3 neighbours on it
    d[20, 20:22] = 95.0  # a 2-pixel bar (a pole, a branch): each has one neighbour
    d[22:, 25:] = np.nan
    spikes = [(2, 25), (10, 10), (21, 24), (25, 2)]  # the third beside the hole
    for r, c in spikes:
        d[r, c] *= 1.25
    flagged = {tuple(map(int, rc)) for rc in np.argwhere(depth_outliers(d))}
    assert flagged == set(spikes) | {(20, 20), (20, 21)}
    assert not depth_outliers(d, support=1)[20, 20:22].any()


def _oblique_view_of_a_floor():
    """A 64 x 64 camera at the origin looking north and 45 degrees down, and its z-depth
    map of the plane z = -20."""
    R = look_at_rotation([0, 1, -1])
    K = np.array([[200.0, 0, 31.5], [0, 200.0, 31.5], [0, 0, 1]])
    cam = Camera(K, R, -R @ np.zeros(3), 64, 64)
    v, u = np.mgrid[0:64, 0:64]
    _, dirs = cam.pixel_rays(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    zc = (dirs @ R.T)[:, 2]  # z-depth per unit ray length
    return cam, ((-20.0 / dirs[:, 2]) * zc).reshape(64, 64).astype(np.float32)


def test_observe_does_not_trust_the_background_behind_an_occlusion(monkeypatch):
    import fusion.observations as observations

    # an oblique view of a floor, a surface 10 m nearer over columns 10-20, and the hole
    # matching leaves beside its edge (columns 21-27)
    cam, d = _oblique_view_of_a_floor()
    d[:, 10:21] -= 10.0
    d[:, 21:28] = np.nan
    grid = Grid.from_bounds(-40.0, 0.0, 40.0, 80.0, 0.5)
    rows = slice(20, 44)  # away from the rows np.roll compares across the image's edge

    def trusted(columns):
        o = observe(cam, d, grid)
        at = np.zeros((64, 64), bool)
        at.ravel()[o.pixels[o.top_surface]] = True
        return at[rows, columns]

    assert trusted(slice(10, 18)).all()
    assert not trusted(slice(28, 31)).any() and trusted(slice(31, 50)).all()
    # their rays did pass the nearer surface: what the view sees past still counts them
    from fusion.hidden_ceiling import trusted_depth

    assert np.isfinite(trusted_depth(d)[rows, 28:31]).all()
    # without the test, the hole hid the jump from the floor's 3 pixels beside it
    monkeypatch.setattr(observations, "behind_occlusions", lambda d: np.zeros(d.shape, bool))
    assert trusted(slice(28, 31)).all()


def test_normals_stay_known_beside_a_dropped_pixel():
    # removing a gross error must not leave unknown normals k pixels around it, which
    # would count as facing up
    cam, floor = _oblique_view_of_a_floor()
    floor[32, 32] = np.nan
    nz = normal_z_image(cam, floor)
    assert np.isfinite(nz[10:-10, 10:-10][np.isfinite(floor[10:-10, 10:-10])]).all()
    np.testing.assert_allclose(nz[29:36, 29:36][np.isfinite(floor[29:36, 29:36])], 1, atol=1e-3)


def test_observe_keeps_the_nearest_surface_of_a_cell():
    # a nadir camera 50 m above; two pixels see the same cell at different depths
    R = look_at_rotation([0, 0, -1])
    K = np.array([[100.0, 0, 2.0], [0, 100.0, 2.0], [0, 0, 1]])
    cam = Camera(K, R, -R @ np.array([0.0, 0.0, 50.0]), 5, 5)
    depth = np.full((5, 5), 50.0, np.float32)
    depth[2:4, 2:4] = 40.0  # a roof at z = 10 above the cell of the centre
    grid = Grid.from_bounds(-1.25, -1.25, 1.25, 1.25, 2.5)  # one 2.5 m cell for all pixels
    obs = observe(cam, depth, grid, tolerance=1.0)
    assert len(obs.cells) == 25 and (obs.cells == 0).all()
    assert obs.visible.sum() == 4
    np.testing.assert_allclose(obs.xyz[obs.visible][:, 2], 10.0, atol=1e-5)
    depth[2, 2] = 40.0 * 0.75  # a gross matching error is no observation at all
    assert len(observe(cam, depth, grid, tolerance=1.0).cells) == 24


def test_empty_groups():
    empty = np.zeros(0, np.int64)
    assert np.isnan(group_mean(empty, np.zeros(0), 3)).all()
    assert group_mean(empty, np.zeros((0, 3)), 3).shape == (3, 3)
    assert np.isnan(group_median(empty, np.zeros(0), 3)).all()
    assert (vector_median(empty, np.zeros((0, 3), np.uint8), 3) == 0).all()


def test_labels_whose_elevation_contradicts_their_class_are_dropped():
    #                  ground grass tree tree building ground unlabelled
    labels = np.array([1, 2, 3, 3, 4, 1, 0])
    elevation = np.array([0.1, 1.9, 7.0, 0.3, 2.0, 9.0, 50.0])
    keep = elevation_consistent(labels, elevation, split=2.0)
    # the tree at 0.3 m is the ground past a crown's edge, the ground at 9 m a crown above it
    np.testing.assert_array_equal(keep, [True, True, True, False, True, False, True])


def test_elevation_prior_damps_the_classes_the_ndsm_contradicts():
    # four cells: a road called tree at 0.1 m, a roof called grass at 8 m, an
    # undecided cell at 2 m, and an unseen one
    p = np.array(
        [
            [0.30, 0.10, 0.25, np.nan],  # ground
            [0.10, 0.60, 0.25, np.nan],  # grass
            [0.60, 0.10, 0.25, np.nan],  # tree
            [0.00, 0.20, 0.25, np.nan],  # building
        ]
    )[:, None, :]
    ndsm = np.array([[0.1, 8.0, 2.0, np.nan]])
    before = p.copy()
    q = elevation_prior(p, ndsm, split=1.0, damping=0.01)
    low = np.array([0.30, 0.10, 0.006, 0.0])
    np.testing.assert_allclose(q[:, 0, 0], low / low.sum(), rtol=1e-6)
    high = np.array([0.001, 0.006, 0.10, 0.20])
    np.testing.assert_allclose(q[:, 0, 1], high / high.sum(), rtol=1e-6)
    np.testing.assert_allclose(q[:, 0, 2], 0.25)  # between 0.5 and 3 m: nothing damped
    assert np.isnan(q[:, 0, 3]).all()
    assert np.argmax(q[:, 0, 0]) == 0 and np.argmax(q[:, 0, 1]) == 3
    np.testing.assert_array_equal(p, before)  # p as it was, by default
    mine = p.astype(np.float32)
    assert elevation_prior(mine, ndsm, split=1.0, damping=0.01, copy=False) is mine
    np.testing.assert_array_equal(mine, q)  # in place, the same numbers


def test_normals_face_the_camera_and_undersides_are_negative():
    # an oblique camera looking north and 45 degrees down sees a floor 20 m below it from
    # above; one looking 45 degrees up sees a ceiling 20 m above it from below
    cam, floor = _oblique_view_of_a_floor()
    nz = normal_z_image(cam, floor)
    np.testing.assert_allclose(nz[10:-10, 10:-10], 1.0, atol=1e-3)
    R_up = look_at_rotation([0, 1, 1])  # looking north-up at a ceiling z = +20
    cam_up = Camera(cam.K, R_up, -R_up @ np.zeros(3), 64, 64)
    v, u = np.mgrid[0:64, 0:64]
    _, dirs = cam_up.pixel_rays(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    ceiling = (20.0 / dirs[:, 2]) * (dirs @ R_up.T)[:, 2]
    nz = normal_z_image(cam_up, ceiling.reshape(64, 64).astype(np.float32))
    np.testing.assert_allclose(nz[10:-10, 10:-10], -1.0, atol=1e-3)


def test_a_facade_does_not_hide_the_ground_in_front_of_it():
    """One cell holds the foot of a facade and the ground in front of it; an oblique
    view sees the facade nearer than the ground, yet both are visible."""
    cells = np.array([0, 0, 0, 1, 1])
    depth = np.array([10.0, 11.0, 13.0, 20.0, 22.0])
    top = np.array([False, False, True, True, True])  # facade, facade, ground | roof, pit
    nearest = nearest_depth(cells, depth, top, 2)
    np.testing.assert_array_equal(nearest, [13.0, 13.0, 13.0, 20.0, 20.0])
    visible = depth <= nearest + 1.0
    np.testing.assert_array_equal(visible, [True, True, True, True, False])
    # a cell with only steep points keeps its nearest one
    np.testing.assert_array_equal(nearest_depth(cells[:2], depth[:2], top[:2], 1), [10.0, 10.0])


def test_at_a_walls_foot_the_roof_edge_does_not_hide_the_ground_before_the_wall():
    """Cell 0 is a wall's foot: a view facing the wall sees the ground before it (quarter
    0), the facade, and the roof's edge 8 m nearer (quarter 1). Cell 1 is a crown's
    edge with no facade: the ground seen past the crown (quarter 0) stays hidden."""
    cells = np.array([0, 0, 0, 0, 1, 1])
    quarter = np.array([0, 0, 1, 1, 1, 0])
    depth = np.array([30.0, 27.0, 22.0, 22.2, 24.0, 30.0])
    top = np.array([True, False, True, True, True, True])  # ground, facade, roof, roof
    groups, n = visibility_groups(cells, quarter, top, 2)
    assert n == 2 + 4 and groups[4] == groups[5] == 1
    assert len(set(groups[:4])) == 2 and groups[0] != groups[2] and groups[2] == groups[3]
    visible = depth <= nearest_depth(groups, depth, top, n) + 1.0
    np.testing.assert_array_equal(visible, [True, True, True, True, True, False])
    # judged per cell, the roof's edge hid the ground
    per_cell = depth <= nearest_depth(cells, depth, top, 2) + 1.0
    assert not per_cell[0]


def test_only_the_top_surface_votes_for_a_cells_colour_and_class():
    """Cell 0: a crown at 9 m whose edge an oblique view sees past, to the ground at
    0 m; cell 1: a roof 0.3 m rough; cell 2: only the ground beneath a crown and an
    unreliable point, whose top is unknown; cell 3: only unreliable points; cell 4: a
    crown's rim, its top (from crown_sightings) seen only in unreliable steep points
    above reliable ground."""
    cells = np.array([0, 0, 0, 0, 1, 1, 2, 2, 3, 4, 4, 4])
    z = np.array([9.2, 8.6, 0.1, 0.0, 6.0, 6.3, 0.2, 5.0, 1.0, 0.1, 7.9, 8.3])
    reliable = np.array([1, 1, 1, 1, 1, 1, 1, 0, 0, 1, 0, 0], bool)
    top = np.array([9.0, 6.2, np.nan, 1.0, 8.0])
    votes = top_surface_votes(cells, z, reliable, top, beneath_m=2.0)
    np.testing.assert_array_equal(votes, [1, 1, 0, 0, 1, 1, 1, 0, 1, 0, 1, 1])


def test_crown_sightings_need_enough_tree_observations_and_take_their_median():
    """Cell 0: four sightings only; cell 1: six sightings among ten ground points; cell
    2: five sightings among twenty ground points (20 %); cell 3: weighted sightings,
    and one at exactly the threshold probability, which does not count."""
    cells, z, weight, p = [], [], [], []

    def add(cell, heights, prob, w=None):
        cells.extend([cell] * len(heights))
        z.extend(heights)
        p.extend([prob] * len(heights))
        weight.extend(w if w is not None else [1.0] * len(heights))

    add(0, [8.0, 8.5, 9.0, 9.0], 0.9)
    add(0, [0.0] * 6, 0.1)
    add(1, [10.0, 8.0, 30.0, 9.5, 9.0, 8.5], 0.8)
    add(1, [0.0] * 10, 0.2)
    add(2, [7.0] * 5, 0.95)
    add(2, [0.1] * 20, 0.05)
    add(3, [9.0, 5.0, 6.0, 8.0, 7.0], 0.9, [10.0, 1.0, 1.0, 1.0, 1.0])
    add(3, [20.0], 0.67)
    cells, z, weight, p = (np.array(a) for a in (cells, z, weight, p))
    median = np.array([0.0, 0.0, 0.1, 6.9, np.nan])
    crown = crown_sightings(cells, z, weight, p, median, min_probability=0.67)
    assert np.isnan(crown[0]) and np.isnan(crown[2]) and np.isnan(crown[4])
    assert crown[1] == 9.25  # midway between the third and fourth of six equal weights
    assert crown[3] == 9.0  # the weight of 10 carries the median; 20 m is no sighting
    # a median less than 2 m below the crown is the crown's own: nothing to raise
    median[3] = 7.1
    assert np.isnan(crown_sightings(cells, z, weight, p, median, min_probability=0.67)[3])


def test_elevation_cue_ignores_an_isolated_matching_error():
    grid = Grid(xmin=0.0, ymax=10.0, gsd=1.0, width=10, height=10)
    dtm = np.full(grid.shape, 5.0)
    shape = (12, 12)
    rows, cols = np.mgrid[0:12, 0:12]
    pixels = (rows * 12 + cols).ravel()
    xyz = np.column_stack([cols.ravel() * 0.8 + 0.1, 9.9 - rows.ravel() * 0.8, np.full(144, 5.2)])
    xyz[6 * 12 + 6, 2] = 30.0  # one gross depth error in the middle of flat ground
    elev = elevation_image(pixels, xyz, shape, dtm, grid)
    np.testing.assert_allclose(elev, 0.2, atol=1e-5)


def test_top_surface_is_read_at_the_cell_centres_and_keeps_walls_sharp():
    """One return per 1 m cell, anywhere in it, on a 40-degree roof east of x = 6 and
    flat ground 5 m lower west of it."""
    rng = np.random.default_rng(3)
    cx, cy = np.meshgrid(np.arange(12) + 0.5, np.arange(8) + 0.5)
    centres = np.column_stack([cx.ravel(), cy.ravel()])
    xy = centres + rng.uniform(-0.45, 0.45, centres.shape)
    slope = np.tan(np.radians(40))

    def surface(p):
        return np.where(p[:, 0] < 6, 0.0, 5.0 + slope * (p[:, 0] - 6))

    xyz = np.column_stack([xy, surface(xy)])
    grid = Grid(0.0, 8.0, 1.0, 12, 8)  # the cell of centre (x, y): row 7.5 - y, col x - 0.5
    cells = ((7.5 - centres[:, 1]) * 12 + centres[:, 0] - 0.5).astype(int)
    z = top_surface_at_cells(xyz, grid, cells, xyz[:, 2])
    roof = (centres[:, 0] > 7) & (centres[:, 0] < 11)
    inner = roof & (centres[:, 1] > 1) & (centres[:, 1] < 7)
    np.testing.assert_allclose(z[inner], surface(centres)[inner], atol=1e-9)
    assert np.abs(surface(xy)[inner] - surface(centres)[inner]).max() > 0.2  # not so
    # beside the 5 m step the wall is not smeared into a ramp
    np.testing.assert_allclose(z[centres[:, 0] == 5.5], 0.0)
    assert z[centres[:, 0] == 6.5].min() >= 5.0


def test_top_surface_finds_the_triangles_scipy_finds():
    """Returns in most cells of a 60 x 50 grid at 0.5 m (UTM-sized coordinates) but a
    round lake, on a rough surface: every cell centre takes the height of the triangle
    scipy's ``find_simplex`` locates it in, or keeps its fallback off the hull and on the
    steep triangles."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(7)
    grid = Grid(500_000.0, 5_700_025.0, 0.5, 60, 50)
    rows, cols = np.divmod(np.arange(3000), 60)
    keep = rng.random(3000) > 0.1
    keep &= np.hypot(rows - 25, cols - 30) > 12  # a lake: long triangles across it
    x, y = grid.cell_center(rows[keep], cols[keep])
    x, y = x + rng.uniform(-0.24, 0.24, x.size), y + rng.uniform(-0.24, 0.24, y.size)
    z = 10 + rng.normal(0, 0.3, x.size) + 8.0 * (rng.random(x.size) < 0.05)  # spikes
    xyz = np.column_stack([x, y, z])
    cells = np.arange(3000)
    fallback = np.full(3000, -1.0)
    got = top_surface_at_cells(xyz, grid, cells, fallback)

    origin = xyz[:, :2].min(axis=0)
    tri = Delaunay(xyz[:, :2] - origin)
    centres = np.column_stack(grid.cell_center(rows, cols)) - origin
    s = tri.find_simplex(centres)
    want = fallback.copy()
    inside = s >= 0
    affine = tri.transform[s[inside]]
    b = np.einsum("mij,mj->mi", affine[:, :2], centres[inside] - affine[:, 2])
    w = np.column_stack([b, 1 - b.sum(axis=1)])
    corners = xyz[tri.simplices[s[inside]]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    gentle = np.abs(normal[:, 2]) >= np.cos(np.radians(70)) * np.linalg.norm(normal, axis=1)
    want[np.flatnonzero(inside)[gentle]] = np.einsum("mk,mk->m", w, corners[..., 2])[gentle]
    assert 0.05 < (want == -1).mean() < 0.5  # steep triangles and the rim keep theirs
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_a_long_thin_triangle_is_scanned_along_itself_not_its_box():
    """A sliver across a 600 x 600 cell box (as a triangle across a lake): the centres
    scanned are those in it, found by brute force over its box, not the box's 360,000."""
    from fusion.points import _barycentric, _centres_in_triangles

    u = np.array([[0.3, 599.6, 597.2], [10.5, 14.5, 12.0]])
    v = np.array([[0.2, 599.4, 599.9], [3.0, 3.0, 7.0]])  # and one with a flat edge
    t, col, row = _centres_in_triangles(u, v, 700, 700)
    for k in range(2):
        r, c = np.mgrid[0 : int(v[k].max()) + 1, 0 : int(u[k].max()) + 1]
        r, c = r.ravel(), c.ravel()
        w = _barycentric(np.tile(u[k], (len(r), 1)), np.tile(v[k], (len(r), 1)), c, r)
        inside = set(zip(r[w.min(axis=1) >= -1e-9], c[w.min(axis=1) >= -1e-9], strict=True))
        found = set(zip(row[t == k], col[t == k], strict=True))
        assert inside <= found and len(found) <= len(inside) + 2 * (np.ptp(v[k]) + 1)
    assert (t == 0).sum() < 3_000


def test_plane_residual_is_zero_on_a_roof_and_the_spread_of_a_crown():
    rows, cols = np.indices((30, 30))
    roof = 5.0 + 0.4 * cols - 0.2 * rows  # a tilted plane: no residual at any scale
    roof[3, 3] = np.nan  # unknown cells are left out of the windows
    r = plane_residual(roof, 5)
    assert np.nanmax(r) < 1e-6 and np.isnan(r).sum() == 0
    crown = np.random.default_rng(0).normal(10.0, 0.5, (30, 30))
    r = plane_residual(crown, 9)[10:20, 10:20]
    assert 0.4 < np.median(r) < 0.55  # about the bumps' spread (a plane takes a little)
    few = np.full((5, 5), np.nan)
    few[2, :4] = 1.0  # 4 known cells: no plane to judge
    assert np.isnan(plane_residual(few, 5)).all()
    assert window_cells(1.25, 0.25) == 5 and window_cells(2.25, 0.25) == 9
    assert window_cells(1.25, 1.0) == 3  # never under 3 x 3


def test_plane_residual_in_tiles_is_that_of_the_whole_grid():
    """The tiles' margins hold every window: residuals in 16-cell tiles are the whole
    grid's (to float64 rounding) at the tiles' edges too, and unknown cells stay so."""
    rng = np.random.default_rng(1)
    rows, cols = np.indices((70, 90))
    dsm = 30.0 + 0.3 * cols + rng.normal(0.0, 0.4, (70, 90)) * (rows > 35)  # plane, then bumps
    dsm[rng.random(dsm.shape) < 0.1] = np.nan
    dsm[:8, :8] = np.nan
    for size in (5, 9):
        whole, tiled = plane_residual(dsm, size, tile=1000), plane_residual(dsm, size, tile=16)
        assert np.array_equal(np.isnan(whole), np.isnan(tiled))
        np.testing.assert_allclose(tiled, whole, atol=1e-5)
        assert np.nanmax(whole[rows > 40]) > 0.2  # the bumps are seen


def test_geometric_cues_reach_each_pixel_through_its_cell():
    grid = Grid(0.0, 4.0, 1.0, 4, 4)
    cues = np.stack([np.full((4, 4), 0.1), np.full((4, 4), 0.2), np.full((4, 4), np.nan)])
    cues[0, 0, 3] = 0.9  # the north-east cell
    xyz = np.array([[3.5, 3.5, 10.0], [0.5, 0.5, 0.0]])
    out = cue_columns(cues, xyz, grid)
    assert out.shape == (2, 3) and out.dtype == np.float32
    assert out[0].tolist() == pytest.approx([0.9, 0.2, UNKNOWN])
    assert out[1].tolist() == pytest.approx([0.1, 0.2, UNKNOWN])


def _oblique_view_of_a_block(width=300, height=200, seed=0):
    """An oblique camera 60 m above flat ground with a 10 m flat-roofed block, and its
    noisy depth map with holes and gross errors."""
    R = look_at_rotation([0, 1, -1])
    K = np.array([[250.0, 0, (width - 1) / 2], [0, 250.0, (height - 1) / 2], [0, 0, 1]])
    center = np.array([0.0, -60.0, 60.0])
    cam = Camera(K, R, -R @ center, width, height)
    _, dirs = cam.pixel_grid_rays()
    with np.errstate(divide="ignore"):
        depth = -center[2] / dirs[:, 2]  # the ground, z = 0 (the rays' camera z is 1)
        roof = (10.0 - center[2]) / dirs[:, 2]
    hit = center[:2] + roof[:, None] * dirs[:, :2]
    on_roof = (np.abs(hit[:, 0]) < 8) & (np.abs(hit[:, 1] - 5) < 6) & (roof > 0)
    depth = np.where(on_roof, roof, depth).reshape(height, width)
    rng = np.random.default_rng(seed)
    depth = depth + rng.normal(0, 0.05, depth.shape)
    depth[rng.random(depth.shape) < 0.02] *= 0.7  # gross matching errors
    depth[rng.random(depth.shape) < 0.02] = np.nan  # unmatched pixels
    depth[depth <= 0] = np.nan  # above the horizon
    return cam, depth.astype(np.float32)


def test_observe_reads_only_the_window_that_sees_the_grid(monkeypatch):
    import fusion.observations as observations

    cam, depth = _oblique_view_of_a_block()
    grid = Grid.from_bounds(-15.0, -10.0, 15.0, 20.0, 0.5)
    window = grid_window(depth, cam, grid, OBSERVE_MARGIN)
    rows, cols = window
    assert 0 < (rows.stop - rows.start) * (cols.stop - cols.start) < 0.6 * depth.size
    windowed = observe(cam, depth, grid)
    assert len(windowed.cells) > 5000
    # the same observations, field for field, as from the whole image
    whole = (slice(0, depth.shape[0]), slice(0, depth.shape[1]))
    monkeypatch.setattr(observations, "grid_window", lambda *args: whole)
    everything = observe(cam, depth, grid)
    for field in ("pixels", "cells", "xyz", "depth", "visible", "normal_z", "near_jump",
                  "height_weight"):  # fmt: skip
        np.testing.assert_array_equal(getattr(windowed, field), getattr(everything, field))
    monkeypatch.undo()
    # a grid the view does not see: no window, no observation
    far = Grid.from_bounds(500.0, 500.0, 510.0, 510.0, 0.5)
    assert grid_window(depth, cam, far, 9) is None
    assert len(observe(cam, depth, far).cells) == 0


def test_view_features_of_a_window_are_those_of_the_whole_image():
    from types import SimpleNamespace

    from fusion.observations import window_pixels
    from fusion.scene_fusion import feature_margin, view_features

    cam, depth = _oblique_view_of_a_block()
    rng = np.random.default_rng(1)
    rgb = cv2.GaussianBlur(rng.integers(0, 256, depth.shape + (3,), dtype=np.uint8), (0, 0), 2)
    grid = Grid.from_bounds(-15.0, -10.0, 15.0, 20.0, 0.5)
    dtm, view = np.zeros(grid.shape), SimpleNamespace(camera=cam)
    window = grid_window(depth, cam, grid, feature_margin(11))
    feats, pixels, xyz = view_features(view, rgb, depth, dtm, grid, 11, window=window)
    all_feats, all_pixels, all_xyz = view_features(view, rgb, depth, dtm, grid, 11)
    full = window_pixels(window, pixels, depth.shape[1])
    np.testing.assert_array_equal(xyz, all_xyz[np.isin(all_pixels, full)])
    # every pixel whose point lands in the grid is in the window, with its features (the
    # patches' box filters run from another edge: the same but for rounding)
    r_all, c_all = grid.cell_index(all_xyz[:, 0], all_xyz[:, 1])
    seen = all_pixels[grid.contains(r_all, c_all)]
    assert len(seen) > 5000 and np.isin(seen, full).all()
    r, c = grid.cell_index(xyz[:, 0], xyz[:, 1])
    inside = grid.contains(r, c)
    np.testing.assert_array_equal(full[inside], seen)
    assert len(feats) == len(pixels) and len(all_feats) == len(all_pixels)
    np.testing.assert_allclose(
        feats[inside], all_feats[grid.contains(r_all, c_all)], rtol=1e-6, atol=1e-6
    )


def test_ray_window_bounds_where_rays_from_above_can_meet_the_heights():
    from fusion.dsm_depth import ray_window

    grid = Grid.from_bounds(-50.0, -50.0, 50.0, 50.0, 1.0)
    dirs = np.array([[0.1, 0.0, -1.0], [0.0, 0.0, 1.0]])
    # the first ray crosses z = 10 at x = 9 and z = 0 at x = 10 (columns 59 and 60, row
    # 50), a cell added around; the second goes up
    rows, cols, rays = ray_window(np.array([0.0, 0.0, 100.0]), dirs, grid, (0.0, 10.0))
    assert (rows, cols) == (slice(49, 52), slice(58, 62))
    assert rays.tolist() == [True, False]
    assert ray_window(np.array([0.0, 0.0, 100.0]), dirs[1:], grid, (0.0, 10.0)) is None
    # from within the heights, anywhere
    rows, cols, rays = ray_window(np.array([0.0, 0.0, 5.0]), dirs, grid, (0.0, 10.0))
    assert (rows, cols) == (slice(0, 100), slice(0, 100)) and rays.all()


def test_grid_rasters_are_read_from_their_files_at_the_cells_asked_for(tmp_path):
    from fusion.dsm_depth import DsmSurface
    from fusion.grid_rasters import GridRasters

    grid = Grid.from_bounds(-30.0, -30.0, 30.0, 30.0, 0.5)
    X, Y = grid.cell_centers()
    dsm = np.where((np.abs(X) < 8) & (np.abs(Y - 5) < 6), 10.0, 0.02 * X).astype(np.float32)
    dsm[3, 4] = np.nan
    dtm, cues = 0.02 * X, np.stack([X, Y]).astype(np.float32)
    surface = DsmSurface(dsm, grid)
    rasters = GridRasters.write(tmp_path, grid, surface, dsm=dsm, dtm=dtm, cues=cues)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "cues.npy", "dsm.npy", "dtm.npy", "filled.npy"]  # fmt: skip
    assert isinstance(rasters.read("dtm"), np.memmap) and rasters.read("none") is None
    r, c = np.array([0, 3, 119]), np.array([5, 4, 0])
    np.testing.assert_array_equal(rasters.read("dsm")[r, c], dsm[r, c])
    np.testing.assert_array_equal(rasters.read("cues")[:, r, c], cues[:, r, c])
    # a task's surface casts as the whole one does, from the mapped heights
    cam, _ = _oblique_view_of_a_block()
    pixels = np.random.default_rng(1).choice(cam.width * cam.height, 500, replace=False)
    np.testing.assert_array_equal(
        rasters.surface().depth_at(cam, pixels), surface.depth_map(cam).ravel()[pixels]
    )


def test_grid_rasters_on_a_full_disk_say_so_in_one_line(tmp_path, monkeypatch):
    import errno

    from fusion import grid_rasters
    from fusion.dsm_depth import DsmSurface
    from workbench.errors import WorkbenchError

    grid = Grid.from_bounds(0.0, 0.0, 4.0, 4.0, 1.0)

    def full(path, array):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(grid_rasters.np, "save", full)
    with pytest.raises(WorkbenchError, match=r"dsm\.npy: disk full .* --resume"):
        grid_rasters.GridRasters.write(tmp_path, grid, DsmSurface(np.zeros((4, 4)), grid),
                                       dsm=np.zeros((4, 4)))  # fmt: skip


def test_dsm_surface_depth_at_some_pixels_is_its_depth_map_there():
    from fusion.dsm_depth import BYTES_PER_QUAD, DsmSurface, ray_window

    grid = Grid.from_bounds(-30.0, -30.0, 30.0, 30.0, 0.5)
    X, Y = grid.cell_centers()
    dsm = np.where((np.abs(X) < 8) & (np.abs(Y - 5) < 6), 10.0, 0.02 * X)  # a block on a slope
    surface = DsmSurface(dsm, grid)
    cam, _ = _oblique_view_of_a_block()
    whole = surface.depth_map(cam).ravel()
    pixels = np.random.default_rng(0).choice(whole.size, 2000, replace=False)
    np.testing.assert_array_equal(surface.depth_at(cam, pixels), whole[pixels])
    # a patch of the image is cast against a window of the surface, with the same result
    patch = (np.arange(90, 110)[:, None] * cam.width + np.arange(130, 170)).ravel()
    origin, dirs = cam.pixel_grid_rays()
    rows, cols, _ = ray_window(origin, dirs[patch], grid, surface.z_range)
    assert (rows.stop - rows.start) * (cols.stop - cols.start) < 0.5 * grid.width * grid.height
    np.testing.assert_array_equal(surface.depth_at(cam, patch), whole[patch])
    # in tiles of 16 x 16 quads, four kept at most: the same depths
    budget = 4 * 16 * 16 * BYTES_PER_QUAD / 2**20
    tiled = DsmSurface(dsm, grid, tile=16, budget_mb=budget)
    np.testing.assert_array_equal(tiled.depth_at(cam, pixels), whole[pixels])
    assert len(tiled._tiles) == 4
    roof = np.isfinite(whole) & (whole < np.nanmedian(whole) - 5)
    assert roof.sum() > 1000  # the block's roof is nearer than the ground behind it


def _tower_and_tier_views():
    """A 20 m tower (x 0-10 m) with a 10 m tier along its east side (x 10-14 m), seen by
    a 45-degree oblique camera from the west on the line through the tower's top edge
    (its rays past the edge fall a metre per metre: over x they pass at 30 - x m) and
    by a nadir camera over x = 15 m; their depth maps ray-cast from the DSM."""
    from fusion.dsm_depth import DsmSurface

    grid = Grid.from_bounds(-20.0, -20.0, 40.0, 20.0, 0.25)
    X, Y = grid.cell_centers()
    dsm = np.where((X > 0) & (X < 10) & (np.abs(Y) < 10), 20.0, 0.0)
    dsm[(X > 10) & (X < 14) & (np.abs(Y) < 10)] = 10.0
    surface = DsmSurface(dsm, grid)
    K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])

    def camera(center, forward):
        R = look_at_rotation(np.asarray(forward, float))
        return Camera(K, R, -R @ np.asarray(center, float), 640, 480)

    oblique = camera([-70.0, 0.0, 100.0], [1.0, 0.0, -1.0])
    nadir = camera([15.0, 0.0, 100.0], [0.0, 0.0, -1.0])
    return grid, dsm, surface, oblique, nadir


class _RayCast:
    """A view whose depth map is ray-cast from ``surface`` (a DsmSurface)."""

    def __init__(self, surface, camera):
        self.surface, self.camera = surface, camera

    def read_depth(self):
        return self.surface.depth_map(self.camera).astype(np.float32)


def test_the_ceiling_over_a_hidden_column_is_the_lowest_ray_past_it():
    """Over the tier hidden behind the tower, and the ground beyond it, the oblique view
    sees past each column from 30 - x m up: exactly so on the ray-cast depth, half a
    metre higher once the 3 pixels beside the tower's edge are untrusted (a matched
    depth map's ramp). The nadir view sees past the tier's columns from its roof up
    (plus the 1 m tolerance) and past the ground's from the ground up; the fusion's
    ceiling is the lower of the two, and NaN on the cells some view saw."""
    from fusion.hidden_ceiling import (
        HiddenColumns,
        column_ceilings,
        hidden_ceilings,
        trusted_depth,
    )
    from workbench.engine import ThreadEngine

    grid, dsm, surface, oblique, nadir = _tower_and_tier_views()
    xs = np.array([10.5, 11.0, 12.0, 13.0, 16.0, 18.0])
    columns = HiddenColumns(xs, np.zeros_like(xs), np.zeros_like(xs), 20.0, 0.25)
    depth = surface.depth_map(oblique).astype(np.float32)
    exact = column_ceilings(oblique, depth, columns, 1.0)
    np.testing.assert_allclose(exact, 30.0 - xs, atol=1e-6)
    np.testing.assert_allclose(column_ceilings(oblique, trusted_depth(depth), columns, 1.0),
                               30.0 - xs + 0.5, atol=1e-6)  # fmt: skip
    from_above = column_ceilings(nadir, surface.depth_map(nadir).astype(np.float32), columns,
                                 1.0)  # fmt: skip
    np.testing.assert_allclose(from_above, np.where(xs < 14, 11.25, 1.25), atol=1e-6)

    X, Y = grid.cell_centers()
    unseen = dsm.copy()
    unseen[(X > 10) & (X < 20) & (np.abs(Y) < 8)] = np.nan
    views = [_RayCast(surface, oblique), _RayCast(surface, nadir)]
    ceiling = hidden_ceilings(ThreadEngine(1), views, 2, grid, unseen, np.zeros(grid.shape), 1.0)
    r, c = grid.world_to_cell(xs, np.zeros_like(xs))
    np.testing.assert_allclose(ceiling[r.astype(int), c.astype(int)], from_above)
    assert np.isnan(ceiling[np.isfinite(unseen)]).all()
    assert np.isfinite(ceiling[~np.isfinite(unseen)]).all()
    from fusion.free_space import ceilings_and_free_space

    both = ceilings_and_free_space(ThreadEngine(1), views, 2, grid, unseen, np.zeros(grid.shape),
                                   1.0)  # fmt: skip
    np.testing.assert_array_equal(both.ceiling, ceiling)  # one reading of the views for both
    alone = ceilings_and_free_space(ThreadEngine(1), views, 2, grid, unseen, np.zeros(grid.shape),
                                    1.0, free_space=False)  # fmt: skip
    np.testing.assert_array_equal(alone.ceiling, ceiling)
    assert np.isnan(alone.lowest).all() and not alone.views.any()


class _Unread(_RayCast):
    """A view whose depth map must not be read."""

    def read_depth(self):
        raise AssertionError("the depth map of a view that sees no column was read")


def test_a_view_that_sees_no_column_reads_no_depth_map():
    """A block of a city that a view does not look at: its task gives +inf for every
    column without reading the view's depth map (a block's views are all the run's), and
    the ceilings and free space of the views that do see it are unchanged."""
    from fusion.free_space import ceilings_and_free_space, view_ceilings_and_free_space
    from fusion.hidden_ceiling import HiddenColumns, columns_in_view, view_ceilings
    from workbench.engine import ThreadEngine

    grid, dsm, surface, oblique, nadir = _tower_and_tier_views()
    K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
    R = look_at_rotation(np.array([0.0, 0.0, -1.0]))
    elsewhere = Camera(K, R, -R @ np.array([500.0, 0.0, 100.0]), 640, 480)  # 500 m east
    xs = np.array([10.5, 13.0, 18.0])
    columns = HiddenColumns(xs, np.zeros_like(xs), np.zeros_like(xs), 20.0, 0.25)
    assert not columns_in_view(elsewhere, columns).any()
    assert columns_in_view(nadir, columns).all()
    unread = [_Unread(surface, elsewhere)]
    assert np.isinf(view_ceilings(0, unread, columns, 1.0)).all()
    hidden, elevated = view_ceilings_and_free_space(0, unread, columns, columns, 1.0)
    assert np.isinf(hidden).all() and np.isinf(elevated).all()

    X, Y = grid.cell_centers()
    unseen = dsm.copy()
    unseen[(X > 10) & (X < 20) & (np.abs(Y) < 8)] = np.nan
    seeing = [_RayCast(surface, oblique), _RayCast(surface, nadir)]
    args = (grid, unseen, np.zeros(grid.shape), 1.0)
    alone = ceilings_and_free_space(ThreadEngine(1), seeing, 2, *args)
    with_it = ceilings_and_free_space(ThreadEngine(1), [*seeing, *unread], 3, *args)
    np.testing.assert_array_equal(with_it.ceiling, alone.ceiling)
    np.testing.assert_array_equal(with_it.lowest, alone.lowest)
    np.testing.assert_array_equal(with_it.views, alone.views)


def test_the_nearest_depth_around_a_pixel_is_none_beside_an_unknown_one():
    from fusion.free_space import nearest_around

    depth = np.full((7, 8), 50.0, np.float32)
    depth[2, 3] = 40.0
    depth[0, 0] = np.nan
    near = nearest_around(depth)
    assert (near[1:4, 2:5] == 40.0).all() and near[4, 5] == 50.0
    assert near[0, 0] == near[1, 1] == 0.0 and near[2, 2] == 40.0
    assert (near[:, 0] == 0).all() and (near[-1] == 0).all()  # the image's edge: unknown


def test_free_space_is_what_a_view_sees_past_below_a_cell_and_never_a_true_roof():
    """Beside the tier's east wall (x 14-15 m), a fused DSM standing 8 m on the ground
    (the wall's points seen edge-on): the nadir view sees the ground there, so the
    lowest height it sees past is the first tested one more than the 1 m tolerance
    above the ground, 1.25 m; the oblique view's rays pass above the wall's 7 m limit.
    The cells whose pixels' neighbourhoods reach the tier's edge (within 1.5 pixels,
    0.19 m, of the ray-cast surface's ramp between the cell centres) are not seen past,
    nor is any cell of the tower, the tier or the ground as fused."""
    from fusion.free_space import ceilings_and_free_space
    from workbench.engine import ThreadEngine

    grid, dsm, surface, oblique, nadir = _tower_and_tier_views()

    X, Y = grid.cell_centers()
    fused = dsm.copy()
    strip = (X > 14) & (X < 15) & (np.abs(Y) < 5)
    fused[strip] = 8.0
    views = [_RayCast(surface, oblique), _RayCast(surface, nadir)]
    space = ceilings_and_free_space(ThreadEngine(1), views, 2, grid, fused, np.zeros(grid.shape),
                                    1.0)  # fmt: skip
    free, past = space.lowest, space.views
    assert np.isnan(space.ceiling).all()  # every cell seen
    clear = strip & (X > 14.5)
    np.testing.assert_allclose(free[clear], 1.25)
    assert (past[clear] == 1).all()
    assert np.isnan(free[strip & (X < 14.25)]).all()  # pixels on the tier's edge
    assert np.isnan(free[~strip]).all() and (past[~strip] == 0).all()


def test_a_cell_seen_through_is_contradicted_unless_its_object_is_a_crown():
    """Two objects above the ground, classed building: a roof with a strip of 3 cells
    a view sees past (wall points beside it), and a crown seen past at 6 of its 9 cells
    (beneath its canopy), which is porous, and at 3 of them, which is not; a cell the
    views give tree a third of their votes is left alone, and one classed tree is never
    tested. The porous cells' tree and building votes trade places."""
    from fusion.free_space import relabel_porous, seen_through

    elevated = np.zeros((8, 12), bool)
    elevated[1:7, 1:6] = True  # the roof, 30 cells
    elevated[2:5, 8:11] = True  # the crown, 9 cells
    free = np.full(elevated.shape, np.nan)
    free[1:4, 5] = 2.0  # the strip along the roof's east side
    free[2:4, 8:11] = 3.0
    prob = np.zeros((4,) + elevated.shape)
    prob[3] = 3.0  # building
    prob[0] = 1.0
    prob[2, 3, 5] = 2.0  # a third of the votes: tree
    contradicted, porous = seen_through(free, prob, elevated)
    expected = np.zeros(elevated.shape, bool)
    expected[1:3, 5] = True
    np.testing.assert_array_equal(contradicted, expected)
    crown = np.zeros(elevated.shape, bool)
    crown[2:5, 8:11] = True
    np.testing.assert_array_equal(porous, crown)
    half = free.copy()
    half[3, 8:11] = np.nan  # 3 of its 9 cells seen past: a roof's, contradicted
    half[1, 2] = 2.0
    as_tree = prob.copy()
    as_tree[2, 1, 2] = 4.0  # the forest's tree: never tested
    contradicted, porous = seen_through(half, as_tree, elevated)
    assert not porous.any()
    assert contradicted[2, 8:11].all() and contradicted.sum() == 5 and not contradicted[1, 2]
    relabel_porous(prob, crown)
    np.testing.assert_array_equal(prob[2][crown], 3.0)
    np.testing.assert_array_equal(prob[3][crown], 0.0)
    assert (prob[3][~crown & elevated] == 3.0).all()


def test_a_cell_put_on_the_ground_takes_the_flat_class_it_was_given_most():
    """The votes of a cell the free space lowered to the ground are its wall's points':
    building (3 of 4) trades places with ground (1), or with grass where grass had more;
    the other cells are left as they were."""
    from fusion.free_space import relabel_grounded

    prob = np.zeros((4, 2, 3))
    prob[:, 0, 0] = [1.0, 0.0, 0.0, 3.0]
    prob[:, 0, 1] = [0.0, 0.5, 0.0, 3.5]
    prob[:, 1, 2] = [0.0, 0.0, 2.0, 2.0]
    grounded = np.zeros((2, 3), bool)
    grounded[0, :2] = True
    before = prob.copy()
    relabel_grounded(prob, grounded)
    np.testing.assert_array_equal(prob[:, 0, 0], [3.0, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(prob[:, 0, 1], [0.0, 3.5, 0.0, 0.5])
    np.testing.assert_array_equal(prob[:, ~grounded], before[:, ~grounded])


def test_a_walls_top_below_a_roofs_edge_keeps_a_steep_normal():
    """The tower's west wall and roof seen by the 45-degree oblique view from the west,
    ray-cast: the wall's pixels right under the roof's edge (a convex crease) have the
    wall's normal, not one mixed with the roof's, and the roof's pixels by the edge keep
    the roof's."""
    from fusion.observations import STEEP_NORMAL_Z, lift_depth

    _, _, surface, oblique, _ = _tower_and_tier_views()
    depth = _RayCast(surface, oblique).read_depth()
    nz = normal_z_image(oblique, depth)
    pixels, xyz = lift_depth(oblique, depth)
    n = nz.ravel()[pixels]
    x, z = xyz[:, 0], xyz[:, 2]
    known = np.isfinite(n)
    wall = known & (x > -0.01) & (x < 0.13) & (z > 15.0) & (z < 19.95)  # its cells
    # the roof off its north and south edges (depth jumps, which the fusion screens)
    roof = known & (x > 0.1) & (x < 9.0) & (np.abs(z - 20.0) < 0.01) & (np.abs(xyz[:, 1]) < 8)
    assert wall.sum() > 3000 and (z[wall] > 19.5).sum() > 100 and roof.sum() > 5000
    # central differences: 138 of the wall's pixels over 0.26 (up to 0.46), 588 of the
    # roof's under 0.99 (down to 0.70, by the crease and the far edge)
    assert (n[wall] < STEEP_NORMAL_Z).all()
    assert (n[roof] > 0.99).all()
