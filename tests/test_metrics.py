"""The shared metrics on hand-computed cases."""

import numpy as np
import open3d as o3d
import pytest

from workbench import metrics
from workbench.meshes import is_watertight, sample_surface, self_intersecting, triangle_areas
from workbench.pictures import colorize_error
from workbench.report import bar_chart_svg, summary_rows


def test_classification_confusion_and_accuracies():
    truth = np.array([[1, 1, 2, 4], [4, 4, 3, 0]])
    pred = np.array([[1, 2, 2, 4], [4, 1, 3, 4]])  # the 0 cell is not scored
    c = metrics.classification(pred, truth)
    assert c["scored_cells"] == 7
    assert c["overall_accuracy"] == pytest.approx(5 / 7)
    assert c["per_class_accuracy"] == pytest.approx(
        {"ground": 0.5, "grass": 1.0, "tree": 1.0, "building": 2 / 3}
    )
    assert c["mean_class_accuracy"] == pytest.approx((0.5 + 1 + 1 + 2 / 3) / 4)
    assert c["confusion"][3] == [1, 0, 0, 2]
    # building against the rest: only the building called ground is wrong
    assert c["building_accuracy"] == pytest.approx(6 / 7)


def test_classification_skips_the_training_strokes():
    truth = np.array([[1, 1, 2, 4], [4, 4, 3, 0]])
    pred = np.array([[1, 2, 2, 4], [4, 1, 3, 4]])
    strokes = np.zeros(truth.shape, bool)
    strokes[0, :2] = True  # a stroke over one right and one wrong ground cell
    c = metrics.classification(pred, truth, exclude=strokes)
    assert c["scored_cells"] == 5 and c["excluded_cells"] == 2
    assert c["overall_accuracy"] == pytest.approx(4 / 5)
    assert "ground" not in c["per_class_accuracy"]


def test_footprint_of_an_eroded_square_has_the_known_completeness():
    truth = np.zeros((20, 20), bool)
    truth[5:15, 5:15] = True  # 100 cells
    eroded = np.zeros_like(truth)
    eroded[6:14, 6:14] = True  # 64 cells
    f = metrics.footprint_2d(eroded, truth)
    assert (f["tp"], f["fp"], f["fn"]) == (64, 0, 36)
    assert f["completeness"] == pytest.approx(0.64)
    assert f["correctness"] == 1.0
    assert f["quality"] == pytest.approx(0.64)
    shifted = np.roll(truth, 2, axis=1)  # 80 shared, 20 each side
    f = metrics.footprint_2d(shifted, truth)
    assert f["quality"] == pytest.approx(80 / 120)
    assert "quality" not in metrics.footprint_2d(np.zeros_like(truth), np.zeros_like(truth))


def test_objects_found_need_half_their_cells():
    truth = np.zeros((10, 10), int)
    truth[0:4, 0:4] = 1  # 16 cells
    truth[6:10, 6:10] = 2
    pred = np.zeros_like(truth)
    pred[0:2, 0:4] = 5  # exactly half of building 1
    pred[6:7, 6:10] = 6  # a quarter of building 2
    pred[0:3, 7:10] = 7  # nothing true under it
    o = metrics.building_objects(truth, pred)
    assert o == {"truth_buildings": 2, "found": 1, "model_buildings": 3, "correct": 2}


def test_volume_3d_by_hand():
    truth = np.array([[10.0, 10.0, 0.0, 4.0]])
    pred = np.array([[10.5, 13.0, 5.0, np.nan]])
    v = metrics.volume_3d(pred, truth, tolerance=1.0)
    # cell 1: within tolerance, 10.5 agrees; cell 2: 11 agrees, 2 too high;
    # cell 3: 5 false positive; cell 4: 4 false negative
    assert v["vtp"] == pytest.approx(10.5 + 11.0)
    assert v["vfp"] == pytest.approx(2.0 + 5.0)
    assert v["vfn"] == pytest.approx(4.0)
    assert v["quality"] == pytest.approx(21.5 / 32.5)
    same = metrics.volume_3d(truth, truth)
    assert same["completeness"] == same["correctness"] == same["quality"] == 1.0
    # the paper's: voxels at the same altitude, no tolerance
    p = metrics.volume_3d(pred, truth)
    assert p["tolerance_m"] == 0.0
    assert p["vtp"] == pytest.approx(10.0 + 10.0)
    assert p["vfp"] == pytest.approx(0.5 + 3.0 + 5.0)
    assert p["vfn"] == pytest.approx(4.0)
    assert p["quality"] == pytest.approx(20.0 / 32.5)


def test_height_jumps_flag_both_sides_of_a_wall_not_a_steep_roof():
    t = np.zeros((6, 8))
    t[:, 4:] = 5.0  # a 5 m wall between columns 3 and 4
    t[:, 6:] += np.array([0.0, 0.9])  # a 0.9 m step per cell: a steep roof, no wall
    j = metrics.height_jumps(t)
    assert j[:, 3:5].all() and not j[:, :3].any() and not j[:, 5:].any()
    b = np.full((5, 5), np.nan)
    b[1:4, 1:4] = 7.0  # a building surface, unknown off the building
    jb = metrics.height_jumps(b)
    assert jb[1:4, 1:4].sum() == 8 and not jb[2, 2] and not jb[0].any()


def test_height_errors_by_hand_and_off_the_jumps():
    t = np.zeros((4, 6))
    t[:, 3:] = 10.0  # columns 2 and 3 are on the wall
    model = t.copy()
    model[:, 2] = 10.0  # the wall one cell too far west: 4 cells 10 m off
    model[0, 0] += 0.5  # and one cell 0.5 m off away from the wall
    model[3, 5] = np.nan
    e = metrics.height_errors(model, t)
    assert e["valid_fraction"] == pytest.approx(23 / 24)
    assert e["rmse_m"] == pytest.approx(np.sqrt((4 * 100 + 0.25) / 23))
    assert e["median_abs_m"] == 0.0
    assert e["jump_fraction"] == pytest.approx(8 / 23)
    assert e["rmse_off_jumps_m"] == pytest.approx(np.sqrt(0.25 / 15))


def test_error_share_off_jumps_by_hand():
    t = np.full((6, 6), np.nan)
    t[:, :5] = 10.0  # a building over columns 0-4, its outline at column 4
    model = t.copy()
    model[0:2, 1] = 0.0  # two cells off the jumps the run has no building on: 10 m each
    model[3, 1] += 1.0  # a roof cell 1 m off
    missed = np.zeros(t.shape, bool)
    missed[0:2, 1] = True
    share = metrics.error_share_off_jumps(model, t, np.isfinite(t), missed)
    assert share == pytest.approx(200 / 201)
    assert metrics.error_share_off_jumps(t, t, np.isfinite(t), missed) is None


def test_building_heights_and_percent_errors():
    ids = np.array([[1, 1, 2, 0]])
    ground = np.array([[100.0, 100.0, 50.0, 0.0]])
    surface = np.array([[110.0, 110.0, 60.0, 999.0]])
    h = metrics.building_heights(surface, ground, ids, percentile=100)
    assert h == {1: 10.0, 2: 10.0}
    err = metrics.height_error_pct({1: 11.0}, h)
    assert err == pytest.approx({1: 10.0, 2: -100.0})  # building 2 missing: -100 %


def test_building_windows_are_each_ids_bounding_box_in_order():
    from workbench.evaluate import building_windows

    ids = np.zeros((6, 7), np.int64)
    ids[1:3, 2:5] = 7
    ids[4, 0] = 10**12  # an id far beyond the count (a GIS key)
    ids[5, 6] = 7  # a second piece widens 7's box
    got = [(k, (r.start, r.stop, c.start, c.stop)) for k, (r, c) in building_windows(ids)]
    assert got == [(7, (1, 6, 2, 7)), (10**12, (4, 5, 0, 1))]
    assert list(building_windows(ids[:1])) == []  # no building
    full = np.ones((2, 2), np.int64)  # no background cell
    assert [(k, w) for k, w in building_windows(full)] == [(1, (slice(0, 2), slice(0, 2)))]


def test_height_error_summary_is_of_absolute_errors():
    s = metrics.height_error_summary([-10.0, 2.0, 3.0])
    assert s == {"median": 3.0, "mean": 5.0, "n": 3}
    assert metrics.height_error_summary([]) == {"n": 0}


def test_surface_distances_symmetric_summary():
    a, b = np.zeros((2, 3)), np.zeros((3, 3))
    s = metrics.surface_distances(a, np.array([0.0, 2.0]), b, np.array([1.0, 1.0, 4.0]))
    assert s["model_to_truth"]["mean_m"] == 1.0 and s["truth_to_model"]["mean_m"] == 2.0
    assert s["mean_distance_m"] == 1.5
    assert s["hausdorff_m"] == 4.0
    assert s["rms_distance_m"] == pytest.approx(np.sqrt((2.0 + 6.0) / 2))


def test_plane_angles_ignore_normal_sign():
    up = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    tilted = np.array([[0, np.sin(np.radians(30)), np.cos(np.radians(30))], [0, 0, -1.0]])
    assert metrics.plane_angles_deg(up, tilted) == pytest.approx([30.0, 0.0])


def test_complexity_roof_types_and_cost():
    c = metrics.complexity([12, 20, 40], [True, True, False])
    assert c["faces_total"] == 72 and c["faces_per_building_median"] == 20
    assert c["watertight_fraction"] == pytest.approx(2 / 3)
    r = metrics.roof_type_accuracy(["flat", "gable", "hipped"], ["flat", "hipped", "hipped"])
    assert r["roof_type_accuracy"] == pytest.approx(2 / 3)
    assert r["confusion"]["hipped"] == {"gable": 1, "hipped": 1}
    cost = metrics.cost({"a": {"wall_s": 1.5, "peak_memory_mb": 300}, "b": {"wall_s": 2.0}})
    assert cost == {"wall_s": 3.5, "peak_memory_mb": 300.0}


def test_a_hipped_roof_whose_ridge_the_grid_cannot_show_is_a_pyramid_too():
    # 9.76 m by 9.70 m: a 6 cm ridge, under two 0.25 m cells; 10.0 by 9.4: 0.6 m, over
    square = [{"half_length": 4.88, "half_width": 4.85}]
    oblong = [{"half_length": 5.0, "half_width": 4.7}]
    assert metrics.indistinguishable_roof_types("hipped", square, 0.25) == {"hipped", "pyramid"}
    assert metrics.indistinguishable_roof_types("hipped", oblong, 0.25) == {"hipped"}
    assert metrics.indistinguishable_roof_types("hipped", oblong, 0.5) == {"hipped", "pyramid"}
    assert metrics.indistinguishable_roof_types("gable", square, 0.25) == {"gable"}
    assert metrics.indistinguishable_roof_types("hipped", square + oblong, 0.25) == {"hipped"}
    pred, truth = ["pyramid", "pyramid", "hipped"], ["hipped", "hipped", "hipped"]
    accepted = [{"hipped", "pyramid"}, {"hipped"}, {"hipped", "pyramid"}]
    r = metrics.roof_type_accuracy(pred, truth, accepted)
    assert r["roof_type_accuracy"] == pytest.approx(2 / 3)
    assert r["confusion"] == {"hipped": {"pyramid": 2, "hipped": 1}}


def test_watertight_needs_closed_consistent_outward_faces():
    box = o3d.geometry.TriangleMesh.create_box(2, 3, 4)
    v, t = np.asarray(box.vertices), np.asarray(box.triangles).copy()
    assert is_watertight(v, t)
    assert not is_watertight(v, t[:-1])  # a hole
    assert not is_watertight(v, t[:, ::-1])  # inside out
    t[0] = t[0, ::-1]
    assert not is_watertight(v, t)  # one face flipped


def test_self_intersection_ignores_open3d_coplanar_false_positives():
    # two floor triangles of a voxel proxy in world metres; in the proxy's frame they are
    # (-3, -2) (0, -5) (-3, -5) and (-5, -5) (-4, -2) (-4, -5): apart, yet Open3D reports
    # them (isl-org/Open3D#6462)
    z = 38.100296020507812
    v = np.array(
        [
            [2.4900633626774651, -85.321008772177208, z],
            [1.7669272583710995, -89.501567846589225, z],
            [0.038215773318276192, -87.049720257230035, z],
            [-1.1142585500502715, -85.415155197657242, z],
            [1.9138262009931908, -84.503726242390812, z],
            [-0.53802138836599767, -86.232437727443639, z],
        ]
    )
    t = np.array([[0, 1, 2], [3, 4, 5]])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    assert mesh.is_self_intersecting()  # the false positive this guards against
    assert not self_intersecting(v, t)
    crossing = v.copy()
    crossing[3:] += crossing[:3].mean(axis=0) - crossing[3:].mean(axis=0)  # B onto A
    assert self_intersecting(crossing, t)
    tilted = v.copy()
    tilted[3:, 2] += np.array([-1.0, 1.0, 0.0])
    tilted[3:, :2] = crossing[3:, :2]  # B pierces A's plane inside A
    assert self_intersecting(tilted, t)
    # two triangles of one sloped roof polygon in a CityJSON file (vertices rounded to the
    # millimetre), 1.4 m apart: Open3D has them cross
    roof = np.array([
        [-5.33, 27.001, 3.527], [-5.24, -2.491, 3.632], [-2.54, -0.991, 6.155],
        [-2.639, -2.491, 6.063], [-2.54, -2.491, 6.156], [-2.54, -2.39, 6.156],
    ])  # fmt: skip
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(roof), o3d.utility.Vector3iVector(t)
    )
    assert mesh.is_self_intersecting()
    assert not self_intersecting(roof, t)  # no axis separates them: 1.4 m apart
    assert not self_intersecting(roof, t, coplanar_m=0.01)  # planar to 1 cm, as checked
    # within that tolerance, the crossing pairs above still cross
    assert self_intersecting(crossing, t, coplanar_m=0.01)
    assert self_intersecting(tilted, t, coplanar_m=0.01)


def test_self_intersection_ignores_open3d_false_positives_in_two_planes():
    # two roof triangles of a hipped L's parametric mesh, on two hips, 9 mm apart in plan
    # (full precision: rounded to 0.1 mm, Open3D no longer reports them; isl-org/Open3D#5117)
    v = np.array([
        [-0.14034150244874866, -0.30268792574176473, 0.31061719389553133],
        [-2.402910129821194, 2.0788410823599506, -1.2367135083830547],
        [-0.1796106460355844, -0.3328571876146853, 0.329602100812302],
        [0.04896559688810953, -0.329561558556577, 0.329602100812302],
        [0.019841848891474, -0.30037839041757763, 0.31061719389553133],
        [-0.16401226725339768, -0.3326322890437865, 0.329602100812302],
    ])  # fmt: skip
    t = np.array([[0, 1, 2], [3, 4, 5]])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    assert mesh.is_self_intersecting()  # the false positive this guards against
    assert not self_intersecting(v, t)
    pierced = v.copy()
    pierced[3:] += v[:3].mean(axis=0) - v[3:].mean(axis=0)  # B's centre onto A's
    pierced[3:, 2] += np.array([-0.5, 0.5, 0.0])  # and tilted through A's plane
    assert self_intersecting(pierced, t)


def test_surface_samples_are_on_the_mesh_and_spread_by_area():
    box = o3d.geometry.TriangleMesh.create_box(1, 1, 10)
    v, t = np.asarray(box.vertices), np.asarray(box.triangles)
    assert triangle_areas(v, t).sum() == pytest.approx(42.0)
    p, tri = sample_surface(v, t, 42000, np.random.default_rng(0))
    on_faces = np.isclose(p, 0).any(axis=1) | np.isclose(p, [1, 1, 10]).any(axis=1)
    assert on_faces.all()
    top = np.isclose(p[:, 2], 10).mean()  # top face: 1 of 42 square metres
    assert top == pytest.approx(1 / 42, abs=0.005)


def test_error_colours_green_blue_red():
    rgb = colorize_error(np.array([0.0, 1.0, 2.0, 5.0, np.nan]), max_error=2.0)
    assert rgb[0].tolist() == [0, 200, 0]
    assert rgb[1].tolist() == [0, 0, 255]
    assert rgb[2].tolist() == rgb[3].tolist() == [255, 0, 0]
    assert rgb[4].tolist() == [255, 255, 255]


def test_summary_marks_every_tied_best_run():
    runs = {
        "a": {"height": {"rmse_m": 1.0}, "footprint_2d": {"quality": 0.9}},
        "b": {"height": {"rmse_m": 1.0}},
        "c": {"height": {"rmse_m": 2.0}},
    }
    rows = {label: (cells, best) for label, cells, best in summary_rows(runs)}
    assert rows["height RMSE on buildings (m)"] == (["1.00", "1.00", "2.00"], {0, 1})
    assert rows["footprint 2D: quality"] == (["0.900", "", ""], set())
    assert not any(label.startswith("volume") for label in rows)  # no data: no row


def test_bar_chart_draws_one_bar_per_value():
    svg = bar_chart_svg(["1", "2"], {"a": [5.0, -3.0], "b": [None, 1.0]}, "%")
    assert svg.startswith("<svg") and svg.count("<rect") == 3 + 2  # bars + legend keys


def test_outline_regularity_counts_edges_on_the_facade_directions():
    from shapely import affinity
    from shapely.geometry import Polygon, box

    from workbench.metrics import outline_regularity

    rect = affinity.rotate(box(0, 0, 20, 10), 30, origin=(0, 0))
    assert outline_regularity([rect])["edges_within_2deg"] == pytest.approx(1.0)
    # one side of five 10 degrees off: the other four hold the directions
    bent = Polygon([(0, 0), (20, 0), (20, 10), (10, 10), (0, 10 - 10 * np.tan(np.radians(10)))])
    r = outline_regularity([bent, None])
    assert r["edges"] == 5 and r["edges_within_2deg"] == pytest.approx(4 / 5)


def test_symmetric_plane_pairs_need_the_same_slope_facing_away():
    from workbench.metrics import symmetric_plane_pairs

    def n(slope, azimuth):
        s, a = np.radians(slope), np.radians(azimuth)
        return [np.sin(s) * np.sin(a), np.sin(s) * np.cos(a), np.cos(s)]

    gable = [n(30, 90), n(30, 270)]
    skewed = [n(30, 90), n(35, 270), [0, 0, 1.0]]  # 5 degrees apart; a flat plane
    hipped = [n(30, 0), n(30, 90), n(30, 180), n(30, 270)]  # 2 facing pairs, 4 side by side
    r = symmetric_plane_pairs([gable, skewed, hipped])
    assert r["pairs"] == 1 + 1 + 2 and r["pairs_within_2deg"] == pytest.approx(3 / 4)


def test_rounded_median_counts_to_its_step():
    m = metrics.RoundedMedian(0.1, 1.0)
    assert m.median() is None
    m.add(np.array([0.04, 0.31, 0.26]))  # rounded 0.0, 0.3, 0.3
    assert m.median() == 0.3 and m.n == 3
    m.add(np.array([0.72]))  # even count: the mean of the two middles
    assert m.median() == pytest.approx(0.3)
    m.add(np.array([5.0, 7.5, 6.0]))  # above the top: kept as they are
    assert m.n == 7 and m.median() == 0.7
    m.add(np.array([9.0, 8.0]))
    assert m.median() == 5.0  # 0, 0.3, 0.3, 0.7, 5, 6, 7.5, 8, 9


def test_tiled_regions_are_the_whole_grids_regions():
    from scipy import ndimage

    from workbench.raster import Grid
    from workbench.tiled_regions import TiledRegions

    rng = np.random.default_rng(3)
    mask = ndimage.binary_opening(rng.random((61, 47)) < 0.6)
    mask[9, 9] = mask[10, 10] = True  # two cells that touch only by a tile's corner
    mask[8, 8:12] = mask[11, 8:12] = mask[9:11, 8] = mask[9:11, 11] = False
    mask[9, 10] = mask[10, 9] = False
    grid = Grid(0.0, 61.0, 1.0, 47, 61)
    whole = TiledRegions(grid.tiles(61), lambda r, c: mask[r, c], min_cells=2)(
        slice(0, 61), slice(0, 47)
    )  # one tile: OpenCV's labels of the whole grid
    for size in (10, 16):
        tiles = grid.tiles(size)
        regions = TiledRegions(tiles, lambda r, c: mask[r, c], min_cells=2)
        ids = np.zeros(mask.shape, np.int64)
        for rows, cols in tiles:
            ids[rows, cols] = regions(rows, cols)
        # the same regions, whatever their numbers
        pairs = set(zip(ids.ravel().tolist(), whole.ravel().tolist(), strict=True))
        assert len(pairs) == len(np.unique(ids)) == len(np.unique(whole))
        assert np.array_equal(ids > 0, whole > 0) and regions.count == whole.max()
        assert ids[9, 9] > 0 and ids[9, 9] == ids[10, 10]  # joined across the corner
