"""The voxel path: hand-computed cases for each step, then the command on the tiny city."""

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from shapely.geometry import Polygon, box

from data_samples.truth_run import truth_fusion_run
from modeling.voxel.building import Proxy
from modeling.voxel.inputs import roof_heights
from modeling.voxel.proxy import (
    VoxelFrame,
    cluster_heights,
    column_minimum,
    consensus_levels,
    consistent_band,
    dominant_axes,
    ellipsoid_normals,
    filter_levels,
    fused_fine_heights,
    fused_flat_levels,
    fused_floating_levels,
    fused_ground_columns,
    fused_roof_columns,
    fused_upper_levels,
    highest_tied,
    occupancy,
    proxy_mesh,
    sample_variance,
    surface_normals,
    upward_views,
    variance_outliers,
    view_median,
    voxel_variance,
    voxelise,
)
from modeling.voxel.robustness import perturbed_mesh
from modeling.voxel.roof_planes import (
    RoofFaces,
    capped,
    column_medians,
    flat_planes,
    roof_faces,
)
from modeling.voxel.surface_graph import (
    mesh_charts,
    patches,
    refine_seams,
    select_views,
    stitch_patches,
    surface_graph,
)
from modeling.voxel.texture_atlas import atlas, pack_charts
from modeling.voxel.view_images import footprint_sigma, hs_chroma
from workbench.camera import Camera, look_at_rotation
from workbench.engine import TaskStore
from workbench.meshes import is_watertight
from workbench.meshio import write_obj
from workbench.raster import Grid
from workbench.texture_seams import ViewSamples, seam_cost, seam_costs, source_views

from .conftest import run_cli


def _volume(v, t):
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6)


def test_footprint_sigma_is_opencvs_rule():
    # OpenCV: sigma = 0.3 ((ksize - 1) / 2 - 1) + 0.8 for ksize = 2 s + 1
    assert footprint_sigma(1) == pytest.approx(0.8)
    assert footprint_sigma(3) == pytest.approx(1.4)


def test_hs_chroma_drops_lightness_and_wraps_hue():
    rgb = np.array([[[255, 0, 0], [128, 0, 0], [128, 128, 128], [255, 0, 8]]], np.uint8)
    c = hs_chroma(rgb)[0]
    np.testing.assert_allclose(c[0], [1, 0], atol=1e-6)  # pure red: S = 1, H = 0
    np.testing.assert_allclose(c[1], c[0], atol=1e-6)  # darker red: same H and S
    np.testing.assert_allclose(c[2], [0, 0], atol=1e-6)  # grey: no chroma
    assert np.linalg.norm(c[3] - c[0]) < 0.05  # hue 358 degrees is next to 0


def test_voxelise_aligns_with_the_footprint_and_grows_it():
    angle = np.radians(30)
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    corners = np.array([[0, 0], [10, 0], [10, 6], [0, 6]]) @ R.T + [100, 200]
    poly = Polygon(corners)
    np.testing.assert_allclose(np.abs(dominant_axes(poly)[0]), np.abs(R[:, 0]), atol=1e-9)
    frame, columns = voxelise(poly, 12.0, 5.0, 1.0, grow=0.0)
    assert columns.sum() == 60  # 10 x 6 columns, centres inside
    assert frame.shape[2] == 13  # layers 0..12 m above the ground
    np.testing.assert_allclose(frame.layer_z()[[0, -1]], [5.0, 17.0])
    _, grown = voxelise(poly, 12.0, 5.0, 1.0, grow=1.0)
    assert grown.sum() == 12 * 8


def _fused_column_heights(frame, ndsm, grid):
    return column_medians(fused_fine_heights(frame, ndsm, grid), frame.shape[:2])


def test_fused_column_heights_follow_the_ndsm_under_each_column():
    """A 30-degree frame over a 0.25 m nDSM: a 4 m roof on the local strip x < 6 m,
    paving beyond it; unseen cells and cells off the grid decide nothing."""
    angle = np.radians(30)
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    poly = Polygon(np.array([[0, 0], [10, 0], [10, 6], [0, 6]]) @ R.T + [100, 200])
    frame, columns = voxelise(poly, 12.0, 5.0, 1.0, grow=0.0)
    grid = Grid(xmin=95.0, ymax=215.0, gsd=0.25, width=80, height=80)
    rows, cols = np.mgrid[0 : grid.height, 0 : grid.width]
    x, y = grid.xmin + (cols + 0.5) * grid.gsd, grid.ymax - (rows + 0.5) * grid.gsd
    local_x = frame.to_local_xy(np.column_stack([x.ravel(), y.ravel()]))[:, 0].reshape(x.shape)
    ndsm = np.where(local_x < frame.x0 + 6.0, 4.0, 0.3)
    fused = _fused_column_heights(frame, ndsm, grid)
    assert fused.shape == columns.shape
    # 10 x 6 columns of 1 m from the frame's corner: the first 6 along x are the roof
    np.testing.assert_allclose(fused[:6], 4.0)
    np.testing.assert_allclose(fused[6:], 0.3)
    ground = fused_ground_columns(fused, min_height=2.0)
    assert not ground[:6].any() and ground[6:].all()
    ndsm[:, :] = np.nan
    unseen = _fused_column_heights(frame, ndsm, grid)
    assert np.isnan(unseen).all() and not fused_ground_columns(unseen, 2.0).any()
    off_grid = Grid(xmin=0.0, ymax=10.0, gsd=0.25, width=40, height=40)
    assert np.isnan(_fused_column_heights(frame, np.zeros((40, 40)), off_grid)).all()


def test_fused_flat_levels_place_grow_and_merge_flat_levels():
    """One flat roof at 3.7 m that the photo-consistency split into levels at 3 and 5 m
    and left holes in, and a pitched level whose fused heights run from 6 to 10 m."""
    levels = np.zeros((10, 6), np.int64)
    levels[:3] = 1  # 18 columns
    levels[3:5] = 2  # 12 columns
    levels[5:8] = 4  # 18 columns; level 3 is unused; rows 8 and 9 empty
    fused = np.full(levels.shape, np.nan)
    rng = np.random.default_rng(0)
    fused[:5] = 3.7 + rng.uniform(-0.05, 0.05, (5, 6))
    fused[5:8] = np.linspace(6.0, 10.0, 18).reshape(3, 6)
    fused[0, 0] = np.nan  # unseen: no vote
    fused[4, :2] = 9.0  # a tree over two columns of the flat level
    fused[8] = 9.0  # beside the pitched level, at its height: a pitched level does not grow
    fused[9] = 3.7  # at the flat roof's height, but not connected to it
    domain = np.ones(levels.shape, bool)
    levels[1, 5] = 0  # a hole at the roof's height: filled
    levels[2, 4], fused[2, 4] = 0, 5.0  # a hole at another height: kept
    levels[0, 5], domain[0, 5] = 0, False  # outside the domain: kept
    photo = np.array([3.0, 5.0, 7.0, 9.0])
    out, heights = fused_flat_levels(levels, photo, fused, domain, 0.5, 1.5)
    # the flat levels merge at the column-weighted mean of their fused medians...
    known = np.isfinite(fused)
    med1 = np.median(fused[(levels == 1) & known])
    med2 = np.median(fused[levels == 2])
    n1 = (levels == 1).sum() + 1
    expected = (n1 * med1 + 12 * med2) / (n1 + 12)
    np.testing.assert_allclose(heights, [expected, 9.0])
    assert abs(heights[0] - 3.7) < 0.05
    # ...the hole at the roof's height joins it, and the pitched level keeps its photo-
    # consistent height and extent (levels renumbered by height)
    want = np.where(levels == 4, 2, np.minimum(levels, 1))
    want[1, 5] = 1
    np.testing.assert_array_equal(out, want)
    # it is the flatness test that keeps it: called flat, it would drop to its median
    _, lowered = fused_flat_levels(levels, photo, fused, domain, 10.0, 1.5)
    np.testing.assert_allclose(lowered[-1], np.median(fused[5:8]))
    none, block = np.zeros((3, 3), np.int64), np.s_[:3, :3]
    empty, no_heights = fused_flat_levels(none, np.zeros(0), fused[block], domain[block], 0.5, 1.5)
    assert not empty.any() and len(no_heights) == 0


def test_fused_upper_levels_stand_a_wedding_cakes_tiers_on_their_own():
    """One level of 20 x 20 columns at 10 m whose fused heights hold an 8 x 8 tier at
    14 m with a 4 x 4 tier at 18 m on it (the k-means folded both into the base: small
    tiers do not pay for a cluster under c_e), and a ramp from 10 to 16 m (a pitched
    part, not flat) and a single column at 20 m (a chimney, no 3 x 3 part); then a
    gable level, whose ridge is no tier."""
    levels = np.ones((20, 20), np.int64)
    levels[:, 18:] = 0
    fused = np.full(levels.shape, 10.0)
    fused[2:10, 2:10] = 14.0
    fused[4:8, 4:8] = 18.0
    fused[12:18, 2:14] = np.linspace(10.0, 16.0, 12)[None, :]
    fused[15, 16] = 20.0
    fused[2, 2] = np.nan  # unseen: left where it is
    out, heights = fused_upper_levels(levels, np.array([10.0]), fused, 0.5, 1.5)
    np.testing.assert_allclose(heights, [10.0, 14.0, 18.0])
    want = levels.copy()
    want[2:10, 2:10] = 2
    want[4:8, 4:8] = 3
    want[2, 2] = 1
    np.testing.assert_array_equal(out, want)
    same, kept = fused_upper_levels(levels, np.array([10.0]), np.full(levels.shape, 10.0), 0.5,
                                    1.5)  # fmt: skip
    np.testing.assert_array_equal(same, levels)
    np.testing.assert_allclose(kept, [10.0])
    # a gable level (30 deg, 0.58 m a column): the three rows along its ridge, two of
    # them at one height, pass the part's flatness test; the level itself does not
    gable = np.ones((20, 11), np.int64)
    ridge = 10.0 + 0.577 * (5 - np.abs(np.arange(11) - 5))[None, :].repeat(20, 0)
    same, kept = fused_upper_levels(gable, np.array([10.5]), ridge, 0.5, 1.5)
    np.testing.assert_array_equal(same, gable)
    np.testing.assert_allclose(kept, [10.5])


def test_fused_floating_levels_empty_a_level_above_what_was_seen():
    """A tower's tiers at 31, 41 and 46 m, and a level k-means made at the grid's top
    (70 m) over columns the fusion sees at 41 and 46 m (dev seed 10): that level's columns
    are emptied. Kept: a gable level at 10.5 m between eaves at 10 m and a ridge at 12.9 m,
    with or without an antenna on it; an unseen level; a flat level 2 m above its fused
    heights, which fused_flat_levels stands on them."""
    levels = np.ones((24, 20), np.int64)
    fused = np.full(levels.shape, 31.0)
    levels[0:10, 0:10], fused[0:10, 0:10] = 2, 41.0
    levels[12:20, 0:8], fused[12:20, 0:8] = 3, 46.0
    levels[0:10, 10:20] = 4
    fused[0:5, 10:20], fused[5:10, 10:20] = 41.0, 46.0
    heights = np.array([31.0, 41.0, 46.0, 70.0])
    out = fused_floating_levels(levels, heights, fused, 0.5, 1.5)
    want = levels.copy()
    want[0:10, 10:20] = 0
    np.testing.assert_array_equal(out, want)
    gable = np.ones((20, 11), np.int64)
    ridge = 10.0 + 0.577 * (5 - np.abs(np.arange(11) - 5))[None, :].repeat(20, 0)
    antenna = ridge.copy()
    antenna[0, :] = 20.0  # 11 of 220 columns
    for seen, height in ((ridge, 10.5), (antenna, 10.5), (np.full(ridge.shape, np.nan), 30.0),
                         (np.full(ridge.shape, 2.9), 5.0)):  # fmt: skip
        kept = fused_floating_levels(gable, np.array([height]), seen, 0.5, 1.5)
        np.testing.assert_array_equal(kept, gable)
    assert not fused_floating_levels(gable, np.array([14.5]), ridge, 0.5, 1.5).any()


def test_ellipsoid_normals_point_up_on_top_and_out_at_the_sides():
    frame = VoxelFrame(np.zeros(2), np.eye(2), 0.0, 0.0, 1.0, (10, 10, 10), 0.0)
    columns = np.ones((10, 10), bool)
    n = ellipsoid_normals(frame, columns).reshape(10, 10, 10, 3)
    # voxel (4, 4, 9): x = y = -0.5, z = 9.5 around the floor centre; a = b = 5 sqrt(2), c = 10
    expected = np.array([2 * -0.5 / 50, 2 * -0.5 / 50, 2 * 9.5 / 100])
    np.testing.assert_allclose(n[4, 4, 9], expected / np.linalg.norm(expected))
    assert n[0, 4, 0, 0] < -0.95  # west side, at the bottom: west
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0)


def test_sample_variance_by_hand():
    s = np.full((2, 4, 1), np.nan, np.float32)
    s[0, :3, 0] = [1.0, 2.0, 3.0]  # variance 2/3
    s[1, :1, 0] = [5.0]  # one view: unknown
    var, views = sample_variance(s)
    np.testing.assert_allclose(var[0], 2 / 3, rtol=1e-6)
    assert np.isnan(var[1]) and views.tolist() == [3, 1]
    s2 = np.full((1, 5, 1), np.nan, np.float32)
    s2[0, :, 0] = [1.0, 1.2, 0.8, 1.0, 9.0]  # a tree hides the voxel in one view
    trimmed, _ = sample_variance(s2, keep=0.8)
    np.testing.assert_allclose(trimmed[0], (0.04 + 0.04 + 0 + 0) / 4, rtol=1e-5)


def test_view_median_is_numpys_nanmedian_to_the_bit():
    rng = np.random.default_rng(3)
    for k in (1, 2, 5, 40):
        s = rng.random((300, k, 3)).astype(np.float32)
        unseen = rng.random((300, k)) < 0.4
        unseen[:4], unseen[4:8] = True, False  # no view, every view
        s[unseen] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            expected = np.nanmedian(s, axis=1)
        got = view_median(s)
        assert got.dtype == expected.dtype
        np.testing.assert_array_equal(got, expected)


def test_column_minimum_band_and_outliers():
    m = np.array(
        [
            [9.0, 5.0, 1.0, 1.05, 1.1, 7.0, 9.0],  # run 2-4 around the minimum at 2
            [np.nan] * 7,
            [0.5, 6.0, 6.0, 6.0, 6.0, 6.0, 6.0],  # ground
        ]
    )
    layer, value = column_minimum(m)
    assert layer.tolist() == [2, -1, 0]
    assert np.isnan(value[1])
    lo, hi = consistent_band(m, layer, tolerance=0.1)
    assert (lo[0], hi[0]) == (2, 4) and (lo[2], hi[2]) == (0, 0)
    out = variance_outliers(np.array([1.0, 1.1, 0.9, 1.0, 1.05, 0.95, 1.0, 1.0, 1.0, 50.0]))
    assert out.tolist() == [False] * 9 + [True]


def test_highest_tied_prefers_the_roof_over_a_consistent_interior():
    # layers 0-3 inside a building (one uniform facade: the minimum), 5-6 the roof just
    # above the minimum, 7-11 air; row 0: median 2.575, ties within 0.05 x 2.475 of 0.1
    air = [5.0] * 5
    m = np.array(
        [
            [0.1, 0.1, 0.1, 0.12, 5.0, 0.14, 0.15, *air],
            [0.1, 0.1, 0.1, 0.12, 5.0, 0.3, 0.3, *air],  # the "roof" is no tie
            [np.nan] * 12,
        ]
    )
    layer, _ = column_minimum(m)
    assert layer.tolist() == [0, 0, -1]
    assert highest_tied(m, layer, tolerance=0.05).tolist() == [6, 3, -1]
    lo, hi = consistent_band(m, highest_tied(m, layer, 0.05), tolerance=0.1)
    assert (lo[0], hi[0]) == (5, 6)


class _UniformImages:
    """Every view the same grey everywhere: every sample is consistent."""

    def consistency_samples(self, k, uv, half_width):
        return np.full((len(uv), 3), 50.0, np.float32)


def test_upward_views_rescue_voxels_no_view_faces_by_their_normal():
    # three cameras east of the voxels, looking down to the west: the voxel whose eq. 1
    # normal points west (a footprint corner at the west edge of the flight) faces none
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    cams = []
    for y in (-10.0, 0.0, 10.0):
        C = np.array([40.0, y, 40.0])
        R = look_at_rotation(-C)
        cams.append(Camera(K, R, -R @ C, 101, 101))
    centres = np.zeros((2, 3))
    normals = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    pc = voxel_variance(centres, normals, 1.0, cams, _UniformImages())
    assert pc.views.tolist() == [0, 3]
    again = upward_views(
        pc, centres, 3, lambda c, n: voxel_variance(c, n, 1.0, cams, _UniformImages())
    )
    assert again.views.tolist() == [3, 3]
    np.testing.assert_allclose(again.variance, [0.0, 0.0])
    assert pc.views.tolist() == [0, 3]  # the input is not changed


def test_cluster_heights_raises_k_while_it_pays():
    heights = np.r_[np.full(20, 3.0), np.full(20, 10.0), np.full(10, 10.4)]
    labels, centres = cluster_heights(heights, cluster_error=0.3)
    # error at k = 1: 611.7; k = 2 leaves 1.07 (the 0.4 m split); 2 -> 3 saves 1.07 < 0.3 x 611.7
    assert len(centres) == 2
    np.testing.assert_allclose(centres, [3.0, 10 + 0.4 / 3], atol=1e-6)
    assert (labels[:20] == 0).all() and (labels[20:] == 1).all()
    _, one = cluster_heights(np.full(10, 7.0))
    assert one.tolist() == [7.0]


def test_consensus_levels_take_the_layer_all_runs_share():
    # a uniform roof at layer 5: interior runs are long, edge runs short
    lo = np.array([5, 3, 2, 4, 0])
    hi = np.array([5, 8, 9, 6, 0])
    labels = np.array([0, 0, 0, 0, 1])
    out, levels = consensus_levels(lo, hi, labels, 2, 10)
    np.testing.assert_allclose(levels, [0.0, 5.0])
    assert out.tolist() == [1, 1, 1, 1, 0]


def test_filter_levels_closes_gaps_drops_islands_keeps_one_part():
    levels = np.zeros((9, 9), int)
    levels[1:6, 1:6] = 1
    levels[3, 3] = 0  # a hole
    levels[8, 8] = 1  # an island, and a part of its own
    levels[2:5, 2:5][levels[2:5, 2:5] > 0] = 2
    out = filter_levels(levels, np.ones((9, 9), bool))
    assert out[3, 3] == 2  # the hole takes its neighbours' level
    assert out[8, 8] == 0
    assert (out[1:6, 1:6] > 0).all() and out[6:, :].sum() == 0


def test_proxy_mesh_is_closed_with_the_volume_of_its_levels():
    frame = VoxelFrame(
        np.array([50.0, 20.0]), dominant_axes(box(0, 0, 2, 1)), 0.0, 0.0, 1.0, (8, 6, 12), 3.0
    )
    levels = np.zeros((8, 6), int)
    levels[1:7, 1:5] = 1  # 24 columns at 4 m
    levels[2:4, 2:4] = 2  # 4 of them at 9.5 m
    m = proxy_mesh(frame, _flat(levels, [4.0, 9.5]), 0.0)
    v, t, outline = m.mesh.vertices, m.mesh.triangles, m.footprint
    assert is_watertight(v, t)
    assert _volume(v, t) == pytest.approx(20 * 4.0 + 4 * 9.5)
    assert outline.area == pytest.approx(24.0)
    assert v[:, 2].min() == pytest.approx(3.0) and v[:, 2].max() == pytest.approx(12.5)
    assert len(t) < 60  # coplanar voxel faces merged, not 2 triangles per voxel face
    assert m.roof_type == "multi-level" and m.ridge_z == pytest.approx(12.5)


def _flat(levels, heights):
    return RoofFaces(levels, flat_planes(np.array(heights)), 1, False)


def _hipped_heights(shape, cell, slope_deg=30.0, eave=6.0, box_m=(2, 2, 18, 12), gable=False):
    """Heights of a hipped (or gable: no hips at the short ends) roof over a box, on
    cells of ``cell`` metres from the origin, NaN off the box."""
    x = (np.arange(shape[0]) + 0.5) * cell
    y = (np.arange(shape[1]) + 0.5) * cell
    X, Y = np.meshgrid(x, y, indexing="ij")
    x0, y0, x1, y1 = box_m
    d = np.minimum(Y - y0, y1 - Y)
    if not gable:
        d = np.minimum(d, np.minimum(X - x0, x1 - X))
    h = eave + np.tan(np.radians(slope_deg)) * d
    inside = (X > x0) & (X < x1) & (Y > y0) & (Y < y1)
    return np.where(inside, h, np.nan)


@pytest.mark.parametrize("gable", [False, True])
def test_pitched_roof_planes_where_the_levels_leave_a_high_error(gable):
    rng = np.random.default_rng(0)
    k, shape = 4, (20, 14)
    fine = _hipped_heights((20 * k, 14 * k), 1.0 / k, gable=gable)
    fine += rng.normal(0, 0.05, fine.shape)  # the fusion's noise
    column_h = column_medians(fine, shape)
    levels = np.where(np.isfinite(column_h), 1, 0)
    level = np.array([float(np.nanmean(column_h))])  # what k-means leaves: one slab
    roof = roof_faces(levels, level, fine, 1.0, 0.0, 0.0, tolerance=0.3, gain=0.5,
                      min_points=6, min_height=2.0)  # fmt: skip
    assert roof.pitched and len(roof.planes) == (2 if gable else 4)
    slopes = np.degrees(np.arccos(roof.planes[:, 2]))
    np.testing.assert_allclose(slopes, 30.0, atol=1.0)
    frame = VoxelFrame(np.zeros(2), np.eye(2), 0.0, 0.0, 1.0, (20, 14, 20), 100.0)
    m = proxy_mesh(frame, roof, 0.25)
    assert is_watertight(m.mesh.vertices, m.mesh.triangles)
    assert m.roof_type == ("gable" if gable else "hipped")
    true_ridge = 6.0 + np.tan(np.radians(30)) * 5.0
    assert m.ridge_z == pytest.approx(100.0 + true_ridge, abs=0.2)
    # the model's volume and heights against the roof's
    true_h = _hipped_heights((20 * k, 14 * k), 1.0 / k, gable=gable)
    true = np.nansum(true_h) / k**2
    volume = _volume(m.mesh.vertices - [0.0, 0.0, 100.0], m.mesh.triangles)
    assert volume == pytest.approx(true, rel=0.01)
    inside = np.isfinite(true_h)
    rms = np.sqrt(np.mean((roof.fine_heights(1.0, 0.0, 0.0)[inside] - true_h[inside]) ** 2))
    assert rms < 0.1 < 0.5 < np.nanstd(true_h)  # one slab would be off by its spread
    # the voxel columns stand at the roof's height over them
    tops = roof.column_tops(1.0, 0.0, 0.0)
    ok = np.isfinite(column_h)
    assert np.abs(tops[ok] - column_h[ok]).max() < 0.5


def test_flat_roof_stays_a_level():
    rng = np.random.default_rng(1)
    fine = np.full((48, 48), np.nan)
    fine[8:40, 8:40] = 7.0 + rng.normal(0, 0.1, (32, 32))
    levels = np.where(np.isfinite(column_medians(fine, (12, 12))), 1, 0)
    roof = roof_faces(levels, np.array([7.0]), fine, 1.0, 0.0, 0.0, tolerance=0.3,
                      gain=0.5, min_points=6, min_height=2.0)  # fmt: skip
    assert not roof.pitched and roof.planes.tolist() == [[0.0, 0.0, 1.0, -7.0]]


def test_a_shed_stops_where_nothing_was_seen_above_its_eave():
    """A 30 degree shed, 6 m to 6 + 10 tan 30 m over 10 m, with two more columns of
    levels past its high wall where the fusion saw nothing (behind the wall): carried on,
    its plane would rise 1.15 m above the highest cell seen; those columns leave the
    roof instead of the plane being dropped for a slab."""
    k, shape = 2, (14, 8)
    x = (np.arange(shape[0] * k) + 0.5) / k
    fine = np.broadcast_to((6.0 + np.tan(np.radians(30)) * x)[:, None], (28, 16)).copy()
    fine[20:] = np.nan  # columns 10-13: the blind strip
    fine[:, :2] = fine[:, -2:] = np.nan
    levels = np.zeros(shape, np.int64)
    levels[:12, 1:7] = 1  # the levels reach two columns into the strip
    roof = roof_faces(levels, np.array([8.9]), fine, 1.0, 0.0, 0.0, tolerance=0.3, gain=0.5,
                      min_points=6, min_height=2.0)  # fmt: skip
    assert roof.pitched and len(roof.planes) == 1
    assert np.degrees(np.arccos(roof.planes[0, 2])) == pytest.approx(30.0, abs=0.5)
    # the first unseen fine row stands within the tolerance of the highest seen
    assert not (roof.faces[21:] > 0).any() and (roof.faces[:21, 2:14] > 0).all()


def test_no_roof_rises_above_what_was_seen():
    """A 60 degree plane over 3 m rises 5.2 m; capped at 4 m (the highest height seen),
    its cells above 4 m become a flat face at 4 m, the others keep their plane, and the
    proxy stays closed."""
    k, shape = 2, (3, 4)
    faces = np.ones((shape[0] * k, shape[1] * k), np.int64)
    steep = np.array([[-np.sin(np.radians(60)), 0.0, np.cos(np.radians(60)), 0.0]])
    roof = RoofFaces(faces, steep, k, True)
    h = roof.fine_heights(1.0, 0.0, 0.0)  # tan 60 x (0.25 ... 2.75 m): 0.43 ... 4.76 m
    out = capped(roof, h, 4.0)
    heights = out.fine_heights(1.0, 0.0, 0.0)
    assert heights.max() == pytest.approx(4.0)
    np.testing.assert_array_equal(out.faces == 2, h > 4.0)
    np.testing.assert_allclose(heights[h <= 4.0], h[h <= 4.0])
    assert out.pitched and out.planes[1].tolist() == [0.0, 0.0, 1.0, -4.0]
    assert capped(roof, h, 10.0) is roof
    frame = VoxelFrame(np.zeros(2), np.eye(2), 0.0, 0.0, 1.0, (3, 4, 8), 100.0)
    m = proxy_mesh(frame, out, 0.25)
    assert is_watertight(m.mesh.vertices, m.mesh.triangles)
    # the faces are cut at cell edges: the plane's last cells under the cap reach half a
    # fine cell (0.25 m) past their centres, 0.43 m higher on this slope
    top = m.mesh.vertices[:, 2].max() - 100.0
    assert 4.0 <= top <= 4.0 + np.tan(np.radians(60)) * 0.25 + 1e-9


def test_fused_roof_columns_join_the_roof_they_touch():
    """Empty columns that the fusion sees as roof take the nearest level if they touch
    one; a separate raised patch (a shed across the yard) and trees (NaN) do not."""
    levels = np.zeros((8, 6), np.int64)
    levels[1:4, 1:5] = 1
    levels[4:6, 1:5] = 2
    fused = np.full((8, 6), np.nan)
    fused[1:7, 1:5] = [[3.0], [3.2], [3.5], [4.2], [4.6], [4.4]]  # row 6: an empty roof row
    fused[0, 1:5] = 1.0  # the paving beside it
    fused[7, 5] = 3.0  # not connected to the roof
    out = fused_roof_columns(levels, np.array([3.2, 4.5]), fused, np.ones((8, 6), bool), 2.0)
    assert (out[6, 1:5] == 2).all() and (out[:6] == levels[:6]).all()
    assert out[7, 5] == 0 and (out[0] == 0).all()
    assert (fused_roof_columns(np.zeros_like(levels), np.zeros(0), fused, out > 0, 2.0) == 0).all()


def test_tree_cells_are_no_roof_height():
    ndsm = np.array([[5.0, 12.0], [5.1, np.nan]])
    classes = np.array([[4, 3], [4, 0]])
    np.testing.assert_array_equal(roof_heights(ndsm, classes), [[5.0, np.nan], [5.1, np.nan]])


def test_surface_normals_of_a_box():
    occ = occupancy(np.pad(np.full((5, 5), 3.0), 2, constant_values=-np.inf), 1.0, 6)
    exterior, n = surface_normals(occ, sigma_n=0.7)
    assert exterior[4, 4, 3] and not exterior[4, 4, 2]  # top layer is the surface
    np.testing.assert_allclose(n[4, 4, 3], [0, 0, 1], atol=1e-6)
    assert n[2, 4, 1, 0] < -0.9  # the west wall looks west


def _two_view_strip(n=24, agree=(4, 7), offset=20.0):
    """A strip of n texels 0.25 m apart seen by two views; they agree only on texels
    ``agree[0]..agree[1]`` and differ by ``offset`` Lab units elsewhere."""
    i = np.arange(n)
    positions = np.column_stack([i * 0.25, np.zeros(n), np.zeros(n)])
    edges = np.column_stack([i[:-1], i[1:]])
    lab = np.zeros((n, 2, 3), np.float32)
    lab[:, 0, 0] = 50.0
    lab[:, 1, 0] = 50.0 + np.where((i >= agree[0]) & (i <= agree[1]), 0.0, offset)
    samples = ViewSamples(
        np.ones((n, 2), bool), np.ones((n, 2), np.float32), lab, np.zeros((n, 2, 3), np.uint8)
    )
    return positions, edges, samples


def test_texture_sources_are_matched_over_neighbourhoods():
    # a strip textured from view 0 on its left half and view 1 on its right; the views
    # agree on texels 4-7, where one texel's own colour could not tell them apart
    _, edges, samples = _two_view_strip(12)
    texture = np.where(np.arange(12)[:, None] < 6, 0, 1)
    rgb = np.take_along_axis(samples.lab, texture[:, :, None], axis=1)[:, 0]
    rgb = cv2.cvtColor(rgb.reshape(-1, 1, 3).astype(np.float32), cv2.COLOR_Lab2RGB) * 255
    labels, dist = source_views(rgb.reshape(-1, 3), samples, edges)
    assert labels[:4].tolist() == [0] * 4 and labels[8:].tolist() == [1] * 4
    assert np.nanmax(dist) < 1.0
    samples.visible[:, 1] = False  # a view that sees nothing is no source
    assert (source_views(rgb.reshape(-1, 3), samples, edges)[0] == 0).all()


def test_seam_cost_by_hand():
    _, edges, samples = _two_view_strip(12)
    labels = np.array([0] * 10 + [1] * 2)  # seam between texels 9 and 10: 20 Lab apart
    assert seam_cost(edges, labels, samples) == (20.0 / 11, 1)  # per edge of the graph
    labels = np.array([0] * 6 + [1] * 6)  # seam inside the agreeing run
    assert seam_cost(edges, labels, samples) == (0.0, 1)
    assert seam_cost(edges, np.zeros(12, int), samples) == (0.0, 0)
    # neither view sees both sides of the seam between texels 5 and 6: the worst cost
    samples.visible[5, 1] = samples.visible[6, 0] = False
    assert seam_cost(edges, labels, samples) == (100.0 / 11, 1)


def test_stitching_moves_the_seam_to_where_the_views_agree():
    positions, edges, samples = _two_view_strip()
    labels = np.array([0] * 10 + [1] * 14)  # view 1's patch is stitched first
    out = stitch_patches(edges, positions, labels, samples, overlap_m=2.0, min_patch=1)
    assert seam_cost(edges, out.labels, samples)[0] == 0.0
    seam = np.flatnonzero(out.labels[:-1] != out.labels[1:])
    assert len(seam) == 1 and 4 <= seam[0] <= 6
    assert out.labels[0] == 0 and out.labels[-1] == 1  # both ends outside the band
    assert patches(edges, out.labels).max() == 1


def test_refinement_moves_a_seam_the_greedy_band_cannot_reach():
    # view 0 faces the left end, view 1 the right one; they agree only on texels 4-7,
    # 8 texels (2 m) from where the greedy cuts left the seam
    _, edges, samples = _two_view_strip(24)
    i = np.arange(24)
    samples.facing[:, 0] = np.where(i >= 8, 0.2, 1.0)
    samples.facing[:, 1] = np.where(i < 4, 0.2, 1.0)
    samples.visible[22:, 0] = False
    labels = np.array([0] * 16 + [1] * 6 + [-1] * 2)
    out = refine_seams(edges, labels, samples, facing_weight=10.0)
    seam = np.flatnonzero(out[:-1] != out[1:])
    assert seam_cost(edges, out, samples)[0] == 0.0 and 4 <= seam[0] <= 6
    assert out[0] == 0 and np.all(out[8:22] == 1) and np.all(out[22:] == -1)


def test_refinement_never_raises_its_energy_and_keeps_views_that_see():
    rng = np.random.default_rng(3)
    n, k = 60, 4
    edges = np.array([(a, b) for a in range(n) for b in (a + 1, a + 10) if b < n])
    visible = rng.random((n, k)) < 0.7
    visible[np.arange(n), rng.integers(0, k, n)] = True
    lab = rng.normal(50, 5, (n, k, 3)).astype(np.float32)
    facing = rng.random((n, k)).astype(np.float32)
    samples = ViewSamples(visible, facing, lab, np.zeros((n, k, 3), np.uint8))
    labels = np.array([rng.choice(np.flatnonzero(v)) for v in visible])

    def energy(x):
        a, b = x[edges[:, 0]], x[edges[:, 1]]
        seam = a != b
        pair = seam_costs(edges[seam], a[seam], b[seam], samples).sum()
        return 5.0 * (1 - facing[np.arange(n), x]).sum() + pair

    out = refine_seams(edges, labels, samples, facing_weight=5.0)
    assert visible[np.arange(n), out].all()
    assert energy(out) < energy(labels)


def _random_texture_graph(seed, n=80, k=5):
    """A 8 x 10 texel grid (8-neighbours) seen by ``k`` views, some texels by none."""
    rng = np.random.default_rng(seed)
    r, c = np.divmod(np.arange(n), 10)
    positions = np.column_stack([c * 0.25, r * 0.25, np.zeros(n)])
    edges = np.array([(a, b) for a in range(n) for b in range(a + 1, n)
                      if max(abs(r[a] - r[b]), abs(c[a] - c[b])) == 1])  # fmt: skip
    visible = rng.random((n, k)) < 0.75
    visible[rng.random(n) < 0.05] = False
    lab = rng.normal(50, 5, (n, k, 3)).astype(np.float32)
    facing = rng.random((n, k)).astype(np.float32)
    samples = ViewSamples(visible, facing, lab, np.zeros((n, k, 3), np.uint8))
    labels = np.array([rng.choice(np.flatnonzero(v)) if v.any() else -1 for v in visible])
    return positions, edges, samples, labels


def _refine_by_definition(edges, labels, samples, w, sweeps=2):
    """Expansion moves written from their definition: every vertex a node, every edge's
    three costs from eq. 5 directly (what :func:`refine_seams` must equal)."""
    from workbench.graph_cuts import pairwise_cut

    labels, rows, seen = labels.copy(), np.arange(len(labels)), labels >= 0
    d_now = w * (1.0 - samples.facing[rows, np.maximum(labels, 0)])
    for _ in range(sweeps):
        improved = False
        for alpha in np.unique(labels[seen]):
            movable = seen & samples.visible[:, alpha] & (labels != alpha)
            if not movable.any():
                continue
            e = edges[movable[edges[:, 0]] | movable[edges[:, 1]]]
            unary = np.column_stack(
                [d_now, np.where(movable, w * (1.0 - samples.facing[:, alpha]), 1e9)]
            )
            pair = np.zeros((len(e), 4))
            ends = (labels[e[:, 0]], labels[e[:, 1]], np.full(len(e), alpha))
            for col, (u, v) in enumerate(((0, 1), (0, 2), (2, 1))):
                a, b = ends[u], ends[v]
                differ = (a != b) & (a >= 0) & (b >= 0)
                pair[differ, col] = seam_costs(e[differ], a[differ], b[differ], samples)
            x = pairwise_cut(unary, e, pair)
            taken = pair[np.arange(len(e)), 2 * x[e[:, 0]] + x[e[:, 1]]]
            if np.sum((unary[:, 1] - d_now)[x == 1]) + np.sum(taken - pair[:, 0]) < -1e-9:
                labels = np.where(x == 1, alpha, labels)
                d_now = np.where(x == 1, unary[:, 1], d_now)
                improved = True
        if not improved:
            break
    return labels


@pytest.mark.parametrize("seed", range(6))
def test_refinement_is_its_definition(seed):
    # the moves cut only the vertices that may move and their neighbours, and share each
    # vertex's seam term among its edges: the same labels as the plain definition
    _, edges, samples, labels = _random_texture_graph(seed)
    out = refine_seams(edges, labels, samples, facing_weight=5.0)
    assert (out != labels).any()
    assert np.array_equal(out, _refine_by_definition(edges, labels, samples, 5.0))


@pytest.mark.parametrize("seed", range(4))
def test_move_costs_are_eq5_on_every_edge(seed):
    from modeling.voxel.surface_graph import _move_costs

    _, edges, samples, labels = _random_texture_graph(seed)
    for k in range(samples.visible.shape[1]):
        out = _move_costs(edges, labels, k, samples)
        ends = (labels[edges[:, 0]], labels[edges[:, 1]], np.full(len(edges), k))
        for col, (u, v) in enumerate(((0, 1), (0, 2), (2, 1))):
            a, b = ends[u], ends[v]
            differ = (a != b) & (a >= 0) & (b >= 0)
            assert np.array_equal(
                out[differ, col], seam_costs(edges[differ], a[differ], b[differ], samples)
            )
            assert (out[~differ, col] == 0).all()
        assert (out[:, 3] == 0).all()


def test_stitching_a_random_graph_keeps_every_view_that_sees():
    for seed in range(4):
        positions, edges, samples, labels = _random_texture_graph(seed)
        out = stitch_patches(edges, positions, labels, samples, overlap_m=0.6, min_patch=3)
        seen = out.labels >= 0
        assert np.array_equal(seen, labels >= 0)
        assert samples.visible[np.flatnonzero(seen), out.labels[seen]].all()
        assert out.patches_after < out.patches_before and out.cuts > 0
        assert seam_cost(edges, out.labels, samples)[0] < seam_cost(edges, labels, samples)[0]


def test_a_view_that_sees_nothing_is_no_label():
    from workbench.texture_seams import rgb_to_lab, seen_views, view_samples

    def nadir(x, y):  # 100 m above (x, y), looking down, 1000 x 1000 px, f = 1000 px
        R = np.diag([1.0, -1.0, -1.0])
        K = np.array([[1000.0, 0, 500], [0, 1000.0, 500], [0, 0, 1]])
        return Camera(K, R, -R @ np.array([x, y, 100.0]), 1000, 1000)

    class Images:
        def rgb_samples(self, k, uv):
            return np.tile(np.array([[60.0, 120.0, 30.0 * (k + 1)]], np.float32), (len(uv), 1))

    xy = np.stack(np.meshgrid(np.arange(5.0), np.arange(4.0)), -1).reshape(-1, 2)
    positions = np.column_stack([xy, np.zeros(len(xy))])
    up = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    cams = [nadir(500.0, 0.0), nadir(2.0, 1.5), nadir(10.0, 1.5)]  # the first is too far
    every = view_samples(positions, up, cams, Images())
    assert every.visible[:, 0].sum() == 0 and every.visible[:, 1:].all()
    views, samples = seen_views(positions, up, cams, Images())
    assert views == [1, 2]
    for name in ("visible", "facing", "lab", "rgb"):
        assert np.array_equal(getattr(samples, name), getattr(every, name)[:, 1:])
    to_cam = cams[2].center - positions
    cos = to_cam[:, 2] / np.linalg.norm(to_cam, axis=1)
    assert np.allclose(samples.facing[:, 1], cos)
    assert np.allclose(samples.lab[:, 1], rgb_to_lab(np.array([60.0, 120.0, 90.0])))
    assert (samples.rgb[:, 0] == [60, 120, 60]).all()  # view 1
    # no view sees anything: every view stays, with empty columns
    views, samples = seen_views(positions, -up, cams, Images())
    assert views == [0, 1, 2] and not samples.visible.any()


def test_view_selection_keeps_the_views_that_face_the_roof():
    """A gable's two slopes, 30 degrees each, under four downward-looking views 100 m up:
    A above the ridge (cosine 0.87 to both slopes), B and C 57.7 m east and west (1.0 to
    their own slope, 0.5 to the other) and D 5 m east of A (0.89 and 0.84). Greedily:
    A first (0.87 a texel against 0.75 for B or C), then B and C (0.07 each), which give
    every texel its best cosine; D adds nothing. Wider tolerances stop earlier."""

    def downward(x):  # 100 m up at (x, 0), looking down, f = 300 px, 1000 x 1000 px
        R = np.diag([1.0, -1.0, -1.0])
        K = np.array([[300.0, 0, 500], [0, 300.0, 500], [0, 0, 1]])
        return Camera(K, R, -R @ np.array([x, 0.0, 100.0]), 1000, 1000)

    x, y = np.meshgrid([0.5, 1.0, 1.5], [0.0, 1.0, 2.0])
    east = np.column_stack([x.ravel(), y.ravel(), 10 - np.tan(np.pi / 6) * x.ravel()])
    west = east * [-1, 1, 1]
    positions = np.vstack([east, west])
    normals = np.repeat([[0.5, 0, np.sqrt(0.75)], [-0.5, 0, np.sqrt(0.75)]], len(east), axis=0)
    cams = [downward(0.0), downward(57.7), downward(-57.7), downward(5.0)]
    every = [0, 1, 2, 3]
    assert select_views(positions, normals, normals, cams, every, tolerance=0.0) == every
    assert select_views(positions, normals, normals, cams, every, tolerance=0.01) == [0, 1, 2]
    # A alone falls short of 0.999 by 0.13; A and B by 0.07 (half the texels at 0.87)
    assert select_views(positions, normals, normals, cams, every, tolerance=0.1) == [0, 1]
    assert select_views(positions, normals, normals, cams, every, tolerance=0.2) == [0]
    # facing away from every view: nothing to choose from, every view stays
    assert select_views(positions, -normals, -normals, cams, every, tolerance=0.01) == every


def test_stitching_band_reaches_into_the_new_patch():
    """The overlap band lies in both patches (Fig. 5g): a new patch that the stitched
    view sees and that lies wholly in the band is cut away when every seam would cost;
    where the stitched view cannot see its far end, the seam stays, at its cheapest."""
    positions, edges, samples = _two_view_strip(24, agree=(-1, -1))
    labels = np.array([0] * 20 + [1] * 4)
    out = stitch_patches(edges, positions, labels, samples, overlap_m=2.0, min_patch=1)
    assert (out.labels == 0).all()
    samples.visible[22:, 0] = False
    samples.lab[16, 1, 0] = 50.0  # the views agree at texels 16 and 17 only
    samples.lab[17, 1, 0] = 50.0
    out = stitch_patches(edges, positions, labels, samples, overlap_m=2.0, min_patch=1)
    assert np.flatnonzero(out.labels[:-1] != out.labels[1:]).tolist() == [16]
    assert seam_cost(edges, out.labels, samples)[0] == 0.0


def test_surface_graph_and_atlas_on_a_box(tmp_path):
    frame = VoxelFrame(np.zeros(2), np.eye(2), 0.0, 0.0, 1.0, (4, 4, 4), 0.0)
    levels = np.zeros((4, 4), int)
    levels[1:3, 1:3] = 1
    box_model = proxy_mesh(frame, _flat(levels, [2.0]), 0.0)  # a 2 x 2 x 2 m box
    v, t = box_model.mesh.vertices, box_model.mesh.triangles
    g = surface_graph(v, t, 0.5, np.array([1.0, 0, 0]))
    assert len(g.positions) == 5 * 16  # 4 walls and a roof of 4 x 4 texels; no floor
    roof = g.normals[:, 2] > 0.9
    np.testing.assert_allclose(g.positions[roof, 2], 2.0)
    # texels across the roof edge are joined: every roof edge texel has a wall neighbour
    wall = ~roof
    cross = roof[g.edges[:, 0]] != roof[g.edges[:, 1]]
    assert cross.sum() >= 4 * 4 and wall.sum() == 64
    colours = np.zeros((len(g.positions), 3), np.uint8)
    colours[roof] = (200, 10, 10)
    colours[wall] = (10, 10, 200)
    image, uvs = atlas(g, colours, v, t)
    # the centre of every roof triangle maps to a red texel, of every wall triangle to blue
    h, w = image.shape[:2]
    centre_uv = uvs.mean(axis=1)
    px = image[((1 - centre_uv[:, 1]) * h).astype(int), (centre_uv[:, 0] * w).astype(int)]
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    assert (px[n[:, 2] > 0.5] == (200, 10, 10)).all()
    assert (px[np.abs(n[:, 2]) < 0.5] == (10, 10, 200)).all()
    write_obj(tmp_path / "box.obj", v, t, uvs=uvs, material="m", mtllib="box.mtl")
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "box.obj"))
    assert len(mesh.triangle_uvs) == 3 * len(t)


def test_a_planar_roof_is_one_chart_at_utm_too():
    """A pitched plane of 800 triangles, turned 23 degrees: one chart near the origin and
    at UTM coordinates (in world coordinates its triangles' plane offsets scattered over
    millimetres and made 130 charts)."""
    a, b = np.meshgrid(np.linspace(0, 10, 21), np.linspace(0, 8, 21))
    x, y = a.ravel(), b.ravel()
    th = np.radians(23.0)
    local = np.column_stack(
        [np.cos(th) * x - np.sin(th) * y, np.sin(th) * x + np.cos(th) * y, 10.0 + 0.57 * x]
    )
    idx = np.arange(21 * 21).reshape(21, 21)
    quad = np.column_stack([idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(),
                            idx[1:, :-1].ravel()])  # fmt: skip
    tri = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])
    utm = np.array([500123.4, 5701234.5, 0.0])
    near, far = mesh_charts(local, tri, 0.1), mesh_charts(local + utm, tri, 0.1)
    assert len(near) == len(far) == 1
    assert near[0].shape == far[0].shape
    np.testing.assert_allclose(far[0].origin - utm, near[0].origin, atol=1e-6)


def test_pack_charts_do_not_overlap():
    shapes = [(5, 7), (3, 3), (10, 2), (1, 1), (4, 9)]
    offsets, (h, w) = pack_charts(shapes)
    canvas = np.zeros((h, w), int)
    for (r, c), (sh, sw) in zip(offsets, shapes, strict=True):
        canvas[r : r + sh, c : c + sw] += 1
    assert canvas.max() == 1 and canvas.sum() == sum(a * b for a, b in shapes)


def test_perturbed_proxy_grows_and_shrinks():
    frame = VoxelFrame(np.zeros(2), np.eye(2), 0.0, 0.0, 1.0, (10, 10, 20), 0.0)
    levels = np.zeros((10, 10), int)
    levels[2:8, 2:8] = 1
    roof = _flat(levels, [10.0])
    proxy = Proxy("1", frame, levels > 0, None, None, levels, np.array([10.0]), roof, None,
                  None, proxy_mesh(frame, roof, 0.0))  # fmt: skip
    rng = np.random.default_rng(0)
    for scale in (1.1, 0.9):
        v, t = perturbed_mesh(proxy, scale, 2.0, rng)
        assert is_watertight(v, t)
        area = _volume(v, t) / v[:, 2].max()
        assert area == pytest.approx(36 * scale**2)
        assert 8.0 <= v[:, 2].max() <= 12.0


def test_a_proxy_keeps_its_exterior_as_a_list_and_two_slices_of_its_variance():
    from modeling.voxel.building import variance_slices

    frame = VoxelFrame(np.array([100.0, 200.0]), np.eye(2), 0.0, 0.0, 0.5, (4, 6, 8), 10.0)
    levels = np.ones((4, 6), int)
    variance = np.arange(4 * 6 * 8, dtype=float).reshape(4, 6, 8)
    vertical, at_roof = variance_slices(variance, frame, _flat(levels, [1.5]))
    np.testing.assert_array_equal(vertical, variance[:, 3, :])  # the middle row
    np.testing.assert_array_equal(at_roof, variance[:, :, 3])  # 1.5 m: layer 3
    ijk, normals = np.array([[1, 2, 3], [0, 5, 7]]), np.array([[0.0, 0, 1], [1.0, 0, 0]])
    proxy = Proxy("1", frame, levels > 0, (vertical, at_roof), None, levels, np.array([1.5]),
                  None, ijk, normals, None)  # fmt: skip
    centres, world = proxy.exterior_voxels_world()
    np.testing.assert_allclose(centres, [[100.75, 201.25, 11.5], [100.25, 202.75, 13.5]])
    np.testing.assert_allclose(world, normals)


@pytest.fixture(scope="module")
def voxel_run(tiny_models):
    """The path as a user runs it: the scene's views and ``workbench fusion``'s rasters."""
    return tiny_models("voxel")


def test_voxel_heights_from_fused_rasters(voxel_run):
    """Thresholds a little above what was measured (tiny, seed 0): height error median
    1.30 %, mean 1.52 %, every roof type at most 3.3 % mean (hipped), 2D quality 0.823
    (tiny's 20 views miss some walls), every building found."""
    b = voxel_run[2]["buildings"]
    assert b["height_error_pct_median"] < 1.8 and b["height_error_pct_mean"] < 1.8
    assert max(t["mean"] for t in b["height_error_pct_by_roof_type"].values()) < 3.5
    assert b["missed_over_50m2"] == 0
    assert voxel_run[2]["footprint_2d"]["quality"] > 0.80


def test_voxel_run_writes_closed_textured_models(voxel_run):
    out, record, metrics = voxel_run
    assert record["counts"]["buildings"] >= 5
    for b in record["buildings"]:
        bid = b["id"]
        for suffix in (".obj", ".mtl", ".png", ".ply"):
            assert (out / "buildings" / f"{bid}{suffix}").exists()
        mesh = o3d.io.read_triangle_mesh(str(out / "buildings" / f"{bid}.obj"), True)
        assert mesh.has_triangle_uvs() and mesh.has_textures()
        assert b["watertight"]
        assert b["patches_after"] <= b["patches_before"] + 2
        assert {"variance", "clustering", "visibility", "refine_seams"} <= set(b["times_s"])
    for name in ("ground.obj", "ground.png", "scene.obj", "scene.ply", "preview.png"):
        assert (out / name).exists()
    assert metrics["complexity"]["watertight_fraction"] == 1.0


def test_voxel_proxies_beat_the_gis_heights(voxel_run, tiny_scene):
    """The proxies must be much closer to the true heights than the over-estimated GIS
    heights they start from."""
    _, record, metrics = voxel_run
    truth = json.loads((tiny_scene / "truth" / "buildings.json").read_text())["buildings"]
    gis_err, proxy_err = [], []
    for b in record["buildings"]:
        gis = Polygon(b["gis_footprint"]["coordinates"][0])
        t = max(truth, key=lambda t: gis.intersection(Polygon(t["footprint"][0])).area)
        true_h = t["ridge_z"] - t["base_z"]
        gis_err.append(abs(b["gis_height_m"] - true_h) / true_h)
        proxy_err.append(abs(max(b["roof_heights_m"]) - true_h) / true_h)
    assert np.median(proxy_err) < 0.6 * np.median(gis_err)
    # the grown footprints reach over the paving, which the fusion's nDSM calls ground
    assert record["parameters"]["fusion_ground"]
    assert sum(b["columns_on_fused_ground"] for b in record["buildings"]) > 0
    objects = metrics["footprint_2d"]["objects"]
    assert objects["found"] >= objects["truth_buildings"] - 1  # tiny's 20 views miss some walls


def test_flat_roofs_stand_at_the_fused_height(voxel_run, tiny_scene):
    """With --fusion a flat roof stands at the fused nDSM's height, not at the photo-
    consistent voxel (tiny's first house: half a voxel too high)."""
    _, record, _ = voxel_run
    assert record["parameters"]["fusion_flat_roofs"]
    truth = json.loads((tiny_scene / "truth" / "buildings.json").read_text())["buildings"]
    flat = 0
    for b in record["buildings"]:
        gis = Polygon(b["gis_footprint"]["coordinates"][0])
        t = max(truth, key=lambda t: gis.intersection(Polygon(t["footprint"][0])).area)
        if t["roof_type"] == "flat":
            flat += 1
            assert abs(b["base_z"] + max(b["roof_heights_m"]) - t["ridge_z"]) < 0.15
    assert flat >= 2


def test_graph_cuts_lower_the_seam_cost(voxel_run):
    _, record, metrics = voxel_run
    t = metrics["texture"]
    # recomputed by compare from the written textures and the scene's views
    assert t["source"] == "recomputed"
    assert t["source_lab_median"] < 3.0  # the texture's colours are the views' own
    assert t["seam_cost"] < 0.5 * t["seam_cost_projective"]
    own = t["reported"]  # the run's own figures, on its surface graph
    assert own["seam_cost"] < 0.5 * own["seam_cost_projective"]
    assert own["seam_cost_greedy"] < own["seam_cost_projective"]  # the paper's cuts alone
    lower = [b["seam_cost"] <= b["seam_cost_projective"] for b in record["buildings"]]
    assert all(lower)


def test_bad_footprints_are_skipped_or_refused(tiny_scene, tmp_path):
    fusion = truth_fusion_run(tiny_scene, tmp_path / "fusion")
    doc = json.loads((tiny_scene / "footprints_gis.geojson").read_text())
    keep = doc["features"][:1]
    bowtie = {
        "type": "Feature",
        "id": "bowtie",
        "properties": {"height": 10},
        "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [6, 6], [6, 0], [0, 3], [0, 0]]]},
    }
    far = {
        "type": "Feature",
        "id": "far",
        "properties": {"height": 10},
        "geometry": {
            "type": "Polygon",
            "coordinates": [[[5000, 5000], [5010, 5000], [5010, 5010], [5000, 5000]]],
        },
    }
    path = tmp_path / "fp.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": keep + [bowtie, far]}))
    out = tmp_path / "model"
    proc = run_cli(
        "model", "voxel", tiny_scene, "-o", out, "--fusion", fusion, "--footprints", path
    )
    assert proc.returncode == 0, proc.stderr
    assert "bowtie: self-intersecting" in proc.stderr and "far: outside the images" in proc.stderr
    record = json.loads((out / "model.json").read_text())
    assert record["counts"]["skipped"] == 2 and record["counts"]["buildings"] == 1
    path.write_text("{ not json")
    proc = run_cli(
        "model",
        "voxel",
        tiny_scene,
        "-o",
        tmp_path / "bad",
        "--footprints",
        path,
        "--fusion",
        fusion,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "fp.geojson" in proc.stderr
    assert not (tmp_path / "bad").exists()


def test_without_footprints_the_fusion_building_mask_stands_in(tiny_scene, tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    for name in ("images", "depth"):
        (scene / name).symlink_to(tiny_scene / name)
    doc = json.loads((tiny_scene / "scene.json").read_text())
    doc.pop("footprints")
    doc.pop("training_labels")
    doc.pop("truth")
    (scene / "scene.json").write_text(json.dumps(doc))
    out = tmp_path / "model"
    proc = run_cli("model", "voxel", scene, "-o", out)
    assert proc.returncode == 2 and "footprints" in proc.stderr and not out.exists()
    fusion = truth_fusion_run(tiny_scene, tmp_path / "fusion")
    proc = run_cli("model", "voxel", scene, "-o", out, "--fusion", fusion)
    assert proc.returncode == 0, proc.stderr
    record = json.loads((out / "model.json").read_text())
    assert record["inputs"]["footprints"] == "fusion building mask"
    truth = json.loads((tiny_scene / "truth" / "buildings.json").read_text())["buildings"]
    assert record["counts"]["buildings"] >= len(truth) - 1


def test_footprints_from_the_fusion_in_strips_are_the_whole_grids(
    tiny_fusion, monkeypatch
):  # fmt: skip
    """The views fusion's building regions polygonised 7 rows at a time: the same
    footprints (their regions joined across the strips, simplified on a canonical ring)
    with the same heights as in one strip."""
    import workbench.regions
    from modeling.voxel.inputs import _read_fusion, footprints_from_fusion

    fusion = _read_fusion(tiny_fusion)
    whole = footprints_from_fusion(fusion)
    monkeypatch.setattr(workbench.regions, "STRIP_CELLS", 7 * fusion["grid"].width)
    strips = footprints_from_fusion(fusion)
    assert len(whole) >= 5 and len(strips) == len(whole)
    crossing = 0
    for f in whole:
        same = [g for g in strips if g.polygon.equals(f.polygon)]
        assert len(same) == 1 and same[0].height == f.height
        _, y0, _, y1 = f.polygon.bounds
        crossing += int((y1 - y0) / fusion["grid"].gsd) > 7
    assert crossing >= 3  # regions in pieces, put together


def test_framing_cameras_keep_every_view_that_sees_the_box(tiny_scene):
    from workbench.camera import framing_cameras
    from workbench.scene import load_scene

    cams = [v.camera for v in load_scene(tiny_scene).views]
    box = np.array([[-4.0, -3.0, 30.0], [5.0, 4.0, 45.0]])
    kept = framing_cameras(cams, box)
    # every camera that has a point of the box in frame is kept
    g = np.stack(np.meshgrid(*(np.linspace(box[0, i], box[1, i], 6) for i in range(3))), -1)
    points = g.reshape(-1, 3)
    for k, cam in enumerate(cams):
        uv, depth = cam.project(points)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (
            uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)  # fmt: skip
        if inside.any():
            assert k in kept
    # a box far off the flight is kept only by the views whose image plane it straddles
    far = box + [5000.0, 0.0, 0.0]
    corners = np.array([[x, y, z] for x in far[:, 0] for y in far[:, 1] for z in far[:, 2]])
    for k in framing_cameras(cams, far):
        depth = cams[k].project(corners)[1]
        assert (depth <= 0).any() and (depth > 0).any(), k
    assert len(framing_cameras(cams, far)) < len(cams) // 4


def test_ring_cuts_paint_the_ground_in_tiles_as_they_would_paint_it_whole(
    tiny_scene, tiny_fusion, tmp_path
):  # fmt: skip
    """Each building's ring cut on its window of the ground, in tiles of 16 texels of
    which two are held, reading its heights from the tiles: the same cut, and in the end
    the same texture, as the cuts on the whole ground held at once."""
    import modeling.voxel.path as vp
    from modeling.voxel.ground_texture import GroundTexture, ground_cut, ring_cut
    from modeling.voxel.ground_tiles import CUT, HEIGHTS, GroundTiles, PaintedGround
    from modeling.voxel.inputs import read_inputs
    from modeling.voxel.options import VoxelOptions

    opts = VoxelOptions()
    inputs = read_inputs(tiny_scene, opts, fusion_dir=tiny_fusion)
    shelf = TaskStore(tmp_path)
    proxies = vp.build_proxies(inputs, opts, shelf)
    occ = vp.proxy_occluders(proxies, inputs)
    for e in proxies:
        vp.texture_task((e, False), inputs, opts, occ, shelf)
    grid = vp.ground_grid(inputs.scene, proxies, opts.ground_gsd_m)
    gz = inputs.ground(grid)
    everything = occ.scene([shelf.load("mesh", e.id) for e in proxies])
    cut = ground_cut(grid, gz, inputs.cameras, inputs.images, everything, opts.overlap_m)
    tiles = GroundTiles(grid, 16, shelf)
    for k, (rows, cols) in enumerate(tiles.tiles):
        shelf.save(HEIGHTS, str(k), gz[rows, cols])
        shelf.save(CUT, str(k), cut.image[rows, cols])
    whole = GroundTexture(grid, gz, cut.image.copy())
    painted = PaintedGround(tiles, cached=2)
    everywhere = slice(0, grid.height), slice(0, grid.width)
    n = 0
    for e in proxies:
        a = ring_cut(whole, vp.ring_task((everywhere, e.id), inputs, opts, occ, tiles),
                     opts.ring_m)  # fmt: skip
        window = vp.ring_window(grid, e.outline, opts.ring_m)
        assert len(list(tiles.overlapping(*window))) > 2
        image = painted.read(*window)
        samples = vp.ring_task((window, e.id), inputs, opts, occ, tiles)
        b = ring_cut(GroundTexture(grid.window(*window), None, image), samples, opts.ring_m)
        painted.paint(*window, image)
        assert a == b
        n += a["from_building"]
    assert n > 0
    np.testing.assert_array_equal(painted.read(*everywhere), whole.image)


def test_a_ground_tile_beyond_every_view_is_unseen(tiny_scene):
    from modeling.voxel.ground_texture import ground_cut, ground_record
    from workbench.raster import Grid
    from workbench.scene import load_scene

    cams = [v.camera for v in load_scene(tiny_scene).views]
    far = Grid(5000.0, 5000.0, 0.5, 8, 6)
    cut = ground_cut(far, np.zeros(far.shape), cams, images=None, occluders=None, overlap_m=1.0)
    assert (cut.labels == -1).all() and cut.counts == {"texels": 48, "unseen": 48}
    record = ground_record(far, [cut.counts])
    assert record["unseen_fraction"] == 1.0 and record["views"] == []


def test_the_ground_under_a_footprint_is_read_from_a_window_of_the_dtm(tmp_path):
    """A 300 x 300 cell DTM at 1 m, z = row + column, with a 151-cell hole in the middle,
    read a window at a time from its file: the median under a footprint over known
    cells; the nearest known cell for one inside the hole (76 cells away: beyond the
    first search window) and for one off the raster; heights on another grid."""
    from modeling.voxel.inputs import Ground
    from workbench.raster import RasterWindows, write_raster

    grid = Grid(0.0, 300.0, 1.0, 300, 300)
    rows, cols = np.mgrid[0:300, 0:300]
    z = (rows + cols).astype(np.float32)
    z[75:226, 75:226] = np.nan
    write_raster(tmp_path / "dtm.tif", z, grid, None)
    ground = Ground("test", RasterWindows(tmp_path / "dtm.tif", grid), grid)
    # x 10.2-13.8, y 280.2-283.8: rows 16-19, columns 10-13, every cell touched
    under = (rows + cols)[16:20, 10:14]
    assert ground.under(box(10.2, 280.2, 13.8, 283.8)) == np.median(under)
    # the hole's centre, cell (150, 150): the nearest known cells are 76 away, the first
    # in row-major order (74, 150)
    assert ground.under(box(150.1, 149.1, 150.9, 149.9)) == 74 + 150
    # off the raster, west of row 20: the border cell (20, 0)
    assert ground.under(box(-50.0, 279.1, -40.0, 279.9)) == 20
    # on a coarser grid over the hole's corner: its cells' centres, the unknown ones at
    # the median of the known
    coarse = Grid(70.5, 229.5, 2.0, 3, 3)  # centres in rows and columns 71, 73 and 75
    expected = np.array([[142, 144, 146], [144, 146, 148], [146, 148, np.nan]])
    expected[2, 2] = np.nanmedian(expected)
    np.testing.assert_array_equal(ground(coarse), expected)


def test_the_workers_inputs_hold_the_fusions_rasters_as_files(
    tiny_scene, tiny_fusion, monkeypatch
):  # fmt: skip
    """What every worker receives reads the fusion's DTM, nDSM and classes a window at a
    time (a city's whole grids are gigabytes per worker), by absolute paths (a worker
    elsewhere starts in another folder), and reads what the whole arrays hold: a
    building's fine heights, NaN under the fusion's trees."""
    import pickle

    from modeling.voxel.inputs import read_inputs, roof_heights
    from modeling.voxel.options import VoxelOptions
    from modeling.voxel.proxy import voxelise
    from workbench.raster import read_raster

    opts = VoxelOptions()
    monkeypatch.chdir(tiny_fusion.parent)
    inputs = read_inputs(tiny_scene, opts, fusion_dir=Path(tiny_fusion.name))
    roofs, grid = inputs.fused_ndsm
    assert len(pickle.dumps(roofs)) < 1000 and len(pickle.dumps(inputs.ground)) < 1000
    assert roofs.ndsm.path.is_absolute() and inputs.ground.z.path.is_absolute()
    ndsm = read_raster(tiny_fusion / "ndsm.tif")[0][0]
    classes = read_raster(tiny_fusion / "class.tif")[0][0]
    whole = roof_heights(ndsm, classes)
    for f, base, h in inputs.buildings:
        frame, _ = voxelise(f.polygon, h, base, opts.voxel_m, opts.grow_m)
        np.testing.assert_array_equal(fused_fine_heights(frame, roofs, grid),
                                      fused_fine_heights(frame, whole, grid))  # fmt: skip


def test_views_framing_counts_the_cameras_whose_image_holds_each_point():
    from modeling.voxel.inputs import views_framing

    def nadir(x):  # from 500 m, f = 1000 px, 1001 px wide: +-250 m of the ground
        K = np.array([[1000.0, 0, 500], [0, 1000.0, 500], [0, 0, 1]])
        R = look_at_rotation(np.array([0.0, 0.0, -1.0]))
        return Camera(K, R, -R @ np.array([x, 0.0, 500.0]), 1001, 1001)

    cams = [nadir(0.0), nadir(400.0)]
    points = np.array([[0.0, 0, 0], [200.0, 0, 0], [300.0, 0, 0], [700.0, 0, 0],
                       [0.0, 0, 600]])  # fmt: skip
    # the last stands above the first camera, behind it
    assert views_framing(cams, points).tolist() == [1, 2, 1, 0, 0]


def test_a_fusion_raster_of_another_size_is_one_line_and_writes_nothing(
    tiny_scene, tiny_fusion, tmp_path
):  # fmt: skip
    """The voxel path reads the fusion a window at a time: an nDSM one row short, whose
    first cell agrees with the DTM's, is refused up front, not read past its edge."""
    from workbench.raster import read_raster, write_raster

    broken = tmp_path / "fusion"
    broken.mkdir()
    for f in tiny_fusion.iterdir():
        if f.is_file():
            (broken / f.name).write_bytes(f.read_bytes())
    ndsm, grid, crs = read_raster(tiny_fusion / "ndsm.tif")
    short = grid.window(slice(0, grid.height - 1), slice(0, grid.width))
    write_raster(broken / "ndsm.tif", ndsm[0, :-1], short, crs)
    out = tmp_path / "out"
    proc = run_cli("model", "voxel", tiny_scene, "--fusion", broken, "-o", out, "--workers", "1")
    assert proc.returncode != 0
    assert "ndsm.tif" in proc.stderr and "grid differs" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not out.exists()
