"""The super-pixel path's steps on hand-computed cases."""

import itertools
from types import SimpleNamespace

import numpy as np
import pytest
import rasterio.features
import shapely
from shapely.geometry import Polygon, box, shape
from shapely.geometry.polygon import orient

from modeling.shared.affinity_propagation import sparse_affinity_propagation
from modeling.shared.outline_regularity import regularise_outline
from modeling.shared.roof_mesh import (
    extrude_faces,
    face_polygons,
    untangle_diagonals,
    vertex_matched,
)
from modeling.shared.roof_types import roof_type
from modeling.superpixel.aggregation import LABEL_SHARE, plane_residuals, superpixel_graph
from modeling.superpixel.building_tasks import adjacency_lists, building_shares, points_of
from modeling.superpixel.buildings import split_buildings
from modeling.superpixel.class_crf import geometry_factor
from modeling.superpixel.options import SuperpixelOptions
from modeling.superpixel.plane_hypotheses import SuperpixelPoints
from modeling.superpixel.prototype_crf import (
    cells_to_fitting_planes,
    edges_within,
    label_prototypes,
)
from modeling.superpixel.prototypes import cluster_prototypes, hypothesis_similarity
from modeling.superpixel.quickshift import (
    colour_height_image,
    quickshift_superpixels,
    relief_image,
    split_disconnected,
)
from modeling.superpixel.rooftop import model_building, observed_faces, with_unseen_parts
from workbench.graph_cuts import alpha_expansion, binary_cut, crf_energy, pairwise_cut
from workbench.meshes import is_watertight, unpaired_edges
from workbench.planes import plane_heights, ransac_plane, ransac_planes
from workbench.raster import Grid


def _plane(a, b, c):
    """The plane z = a x + b y + c as (n, d)."""
    p = np.array([-a, -b, 1.0, -c])
    return p / np.linalg.norm(p[:3])


def _volume(v, t):
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return float(np.sum(a * np.cross(b, c)) / 6)


def _brute_force(unary, edges, w, omega, allowed=None):
    n, L = unary.shape
    return min(
        crf_energy(np.array(c), unary, edges, w, omega)
        for c in itertools.product(range(L), repeat=n)
        if allowed is None or allowed[np.arange(n), list(c)].all()
    )


def _random_crf(rng, n: int, L: int):
    """Unary (n, L), edges (E, 2) and weights (E,) of a random Potts problem."""
    unary = rng.random((n, L)) * 3
    edges = np.array([(a, b) for a in range(n) for b in range(a + 1, n) if rng.random() < 0.4])
    edges = edges.reshape(-1, 2)
    return unary, edges, rng.random(len(edges))


def test_graph_cuts_against_brute_force():
    rng = np.random.default_rng(1)
    for trial in range(40):
        n, L = 7, 2 + trial % 3
        unary, edges, w = _random_crf(rng, n, L)
        best = _brute_force(unary, edges, w, 1.0)
        got = crf_energy(alpha_expansion(unary, edges, w, 1.0), unary, edges, w, 1.0)
        if L == 2:
            assert got == pytest.approx(best)  # one exact cut
        assert best - 1e-9 <= got <= 2 * best + 1e-9  # alpha-expansion's Potts bound
        assert got <= crf_energy(unary.argmin(1), unary, edges, w, 1.0) + 1e-9


def test_alpha_expansion_keeps_each_node_to_its_allowed_labels():
    rng = np.random.default_rng(3)
    for trial in range(30):
        n, L = 7, 3 + trial % 2
        unary, edges, w = _random_crf(rng, n, L)
        allowed = rng.random((n, L)) < 0.6
        allowed[np.arange(n), rng.integers(0, L, n)] = True
        labels = alpha_expansion(unary, edges, w, 1.0, allowed=allowed)
        assert allowed[np.arange(n), labels].all()
        best = _brute_force(unary, edges, w, 1.0, allowed)  # over the allowed labellings
        got = crf_energy(labels, unary, edges, w, 1.0)
        assert best - 1e-9 <= got <= 2 * best + 1e-9
        everywhere = alpha_expansion(unary, edges, w, 1.0, allowed=np.ones((n, L), bool))
        np.testing.assert_array_equal(everywhere, alpha_expansion(unary, edges, w, 1.0))


def test_pairwise_cut_against_brute_force():
    """Any submodular pair terms (not only Potts): the cut is the exact minimum."""
    rng = np.random.default_rng(2)
    n = 8
    for _ in range(30):
        unary = rng.random((n, 2)) * 2
        edges = np.array([(a, b) for a in range(n) for b in range(a + 1, n) if rng.random() < 0.4])
        edges = edges.reshape(-1, 2)
        pair = rng.random((len(edges), 4))
        pair[:, 1] += pair[:, 0] + pair[:, 3]  # E01 + E10 >= E00 + E11
        every = (np.arange(2**n)[:, None] >> np.arange(n)) & 1
        energy = unary[np.arange(n), every].sum(1) + pair[
            np.arange(len(edges)), 2 * every[:, edges[:, 0]] + every[:, edges[:, 1]]
        ].sum(1)
        x = pairwise_cut(unary, edges, pair)
        got = (
            unary[np.arange(n), x].sum()
            + pair[np.arange(len(edges)), 2 * x[edges[:, 0]] + x[edges[:, 1]]].sum()
        )
        assert got == pytest.approx(energy.min())
    # no node at all (a stitching band that met no edge): no labels, not PyMaxflow's error
    assert pairwise_cut(np.zeros((0, 2)), np.zeros((0, 2), int), np.zeros((0, 4))).shape == (0,)


def test_binary_cut_smooths_a_weak_outlier():
    unary = np.array([[0.0, 1.0], [0.0, 1.0], [0.6, 0.4], [0.0, 1.0]])
    edges = np.array([[0, 2], [1, 2], [2, 3]])
    w = np.ones(3)
    assert binary_cut(unary, edges, w, 0.0).tolist() == [0, 0, 1, 0]
    assert binary_cut(unary, edges, w, 1.0).tolist() == [0, 0, 0, 0]


def test_superpixel_graph_boundaries_and_aggregates():
    labels = np.array([[0, 0, 1], [0, 0, 1], [2, 2, 2]])
    rgb = np.zeros((3, 3, 3), np.uint8)
    rgb[:, 2] = 255
    prob = np.zeros((4, 3, 3), np.float32)
    prob[3] = 1.0
    prob[:, 2, :] = np.nan  # unknown cells count as uniform
    prob[:, 1, 2] = 0.0  # and so do cells without any confidence
    dsm = np.arange(9, dtype=float).reshape(3, 3)
    g = superpixel_graph(labels, rgb, prob, dsm)
    pairs = {tuple(e): b for e, b in zip(g.edges.tolist(), g.boundary, strict=True)}
    assert pairs == {(0, 1): 2, (0, 2): 2, (1, 2): 1}
    assert g.count.tolist() == [4, 2, 3]
    assert g.class_sum[0].tolist() == [0, 0, 0, 4] and g.class_sum[2].tolist() == [0.75] * 4
    assert g.class_sum[1].tolist() == [0.25, 0.25, 0.25, 1.25]
    assert g.height_median.tolist() == [2.0, 3.5, 7.0]
    assert g.colour_distance[0] > 50  # black against white in Lab
    assert np.isnan(g.plane_residual).all()  # under 6 cells each: no plane to fit


def test_the_fusions_class_map_takes_half_of_each_seen_cells_likelihood():
    """A roof's shaded hip: the forest says tree at 0.7, the fusion's map building."""
    labels = np.array([[0, 0, 1]])
    prob = np.zeros((4, 1, 3), np.float32)
    prob[2], prob[3] = 0.7, 0.3
    prob[:, 0, 2] = np.nan  # unseen: uniform, whatever the map says
    classes = np.array([[4, 3, 0]], np.uint8)
    g = superpixel_graph(labels, np.zeros((1, 3, 3), np.uint8), prob, np.zeros((1, 3)),
                         residuals=False, classes=classes)  # fmt: skip
    assert LABEL_SHARE == 0.5
    # cell 0: tree 0.35, building 0.15 + 0.5; cell 1: tree 0.35 + 0.5, building 0.15
    np.testing.assert_allclose(g.class_sum[0], [0, 0, 1.2, 0.8], atol=1e-6)
    np.testing.assert_allclose(g.class_sum[1], [0.25] * 4)


def test_plane_residuals_of_a_roof_face_and_a_crown():
    rng = np.random.default_rng(0)
    rows, cols = np.indices((20, 40))
    dsm = 10.0 + 0.3 * cols + 0.1 * rows  # one tilted plane ...
    labels = (cols >= 20).astype(np.int64)
    bumps = rng.normal(0.0, 0.5, (20, 20))
    dsm[:, 20:] += bumps  # ... and, on the right, a lumpy crown
    dsm[0, 0] = np.nan  # unknown cells are left out
    r = plane_residuals(labels, dsm, 2)
    assert r[0] == pytest.approx(0.0, abs=1e-9)
    # the residual of the bumps about their own best plane: at most their spread
    assert 0.9 * np.std(bumps) < r[1] <= np.std(bumps) + 1e-9


def test_geometry_factor_learns_tree_and_building_residuals_from_the_strokes():
    rng = np.random.default_rng(1)
    n = 40
    residual = np.r_[rng.uniform(0.02, 0.05, 20), rng.uniform(0.3, 0.6, 20)]  # roofs, crowns
    graph = SimpleNamespace(plane_residual=residual, n=n, class_sum=np.ones((n, 4)))
    stroked = np.zeros(n, np.int64)
    stroked[:6], stroked[20:26] = 4, 3  # a few of each under the strokes
    f, record = geometry_factor(graph, stroked)
    assert record["used"] and record["building"]["superpixels"] == 6
    assert (f[:20, 3] > 1.9).all() and (f[:20, 2] < 0.1).all()  # planar: building
    assert (f[20:, 2] > 1.9).all() and (f[20:, 3] < 0.1).all()  # lumpy: tree
    assert (f[:, :2] == 1).all()  # ground and grass are both flat: no say
    stroked[20:23] = 0  # three tree super-pixels are too few to learn from
    assert geometry_factor(graph, stroked)[0] is None


def test_geometry_factor_is_not_overconfident_from_a_few_strokes():
    """Five stroked roof faces of nearly one residual (0.05 m) and twenty crowns spread
    about 0.12 m: a roof face at 0.07 m lies nearer the roofs' mean in log terms, and
    must lean building. A spread fitted to the five alone (0.1 in log) made it tree by
    a factor of 30."""
    rng = np.random.default_rng(2)
    crowns = np.exp(np.log(0.12) + 0.6 * rng.standard_normal(20))
    residual = np.r_[0.05 * (1 + 0.01 * rng.standard_normal(5)), crowns, 0.07]
    n = len(residual)
    graph = SimpleNamespace(plane_residual=residual, n=n, class_sum=np.ones((n, 4)))
    stroked = np.r_[np.full(5, 4), np.full(20, 3), 0]
    f, record = geometry_factor(graph, stroked)
    assert 0.4 < record["log_sigma"] < 0.8  # pooled: the crowns' spread, not the roofs'
    assert f[-1, 3] > 1.0 > f[-1, 2]


def test_quickshift_tiles_keep_super_pixels_connected_and_on_edges():
    rgb = np.zeros((120, 150, 3), np.uint8)
    rgb[:, 70:] = (200, 40, 40)
    labels = quickshift_superpixels(rgb, tile=64)
    assert labels.min() == 0 and len(np.unique(labels)) == labels.max() + 1
    crossing = np.intersect1d(np.unique(labels[:, :70]), np.unique(labels[:, 70:]))
    assert len(crossing) == 0  # no super-pixel straddles the colour edge


def test_split_disconnected_numbers_regions_by_label_then_raster_order():
    labels = np.array([
        [5, 5, 2, 5],
        [2, 2, 2, 5],
        [5, 2, 5, 5],
    ])  # fmt: skip
    # label 2: one region (4-connected); label 5: the top-left pair, the
    # right-hand group (first cell (0, 3)), the lone cell at (2, 0): numbered after
    # label 2's region by their first cell in raster order
    expected = np.array([
        [1, 1, 0, 2],
        [0, 0, 0, 2],
        [3, 0, 2, 2],
    ])  # fmt: skip
    np.testing.assert_array_equal(split_disconnected(labels), expected)
    diagonal = np.array([[0, 1], [1, 0]])  # touching at a corner only: two regions each
    np.testing.assert_array_equal(split_disconnected(diagonal), [[0, 2], [3, 1]])
    assert split_disconnected(np.zeros((0, 4), np.int64)).shape == (0, 4)


def test_adjacency_lists_keep_each_nodes_edges_in_order():
    edges = np.array([[0, 2], [1, 2], [0, 1], [2, 5]])
    assert adjacency_lists(edges) == {0: [2, 1], 1: [2, 0], 2: [0, 1, 5], 5: [2]}
    assert list(adjacency_lists(edges)[2]) == [0, 1, 5]  # the edges' order, not sorted
    assert adjacency_lists(np.zeros((0, 2), np.int64)) == {}


def test_quickshift_workers_do_not_change_the_labels():
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 255, (150, 170, 3)).astype(np.uint8)
    rgb[:, 80:] //= 3
    one = quickshift_superpixels(rgb, tile=48, workers=1)
    three = quickshift_superpixels(rgb, tile=48, workers=3)
    assert len(np.unique(one)) > 100  # 16 tiles of noise: many super-pixels to keep in order
    np.testing.assert_array_equal(one, three)


def test_height_keeps_super_pixels_off_a_wall_the_colour_does_not_show():
    """A grey roof 3 m above grey paving of nearly the same colour: with the height beside
    the colour no super-pixel crosses the wall; with the colour alone some do."""
    rng = np.random.default_rng(1)
    rgb = np.clip(120 + rng.normal(0, 4, (60, 80, 3)), 0, 255).astype(np.uint8)
    rgb[:, 40:] += 3  # the roof: 3 grey levels lighter, under Quickshift's tau
    dsm = np.where(np.arange(80) < 40, 10.0, 13.0)[None, :].repeat(60, axis=0)
    dsm[20:30, 38:42] = np.nan  # unseen beside the wall: each cell takes its nearest side

    def straddling(labels):
        return np.intersect1d(np.unique(labels[:, :40]), np.unique(labels[:, 40:]))

    assert len(straddling(quickshift_superpixels(rgb))) > 0
    labels = quickshift_superpixels(rgb, height=dsm, height_weight=10.0)
    assert len(straddling(labels)) == 0
    image = colour_height_image(rgb, dsm, 10.0)
    assert image.shape == (60, 80, 4)
    assert image[25, 39, 3] == 100.0 and image[25, 40, 3] == 130.0  # nearest known height


def test_relief_super_pixels_split_a_grey_gable_at_its_ridge():
    """A LiDAR-like ortho, one noisy grey level, over a 40-degree gable: the relief of the
    DSM separates the two faces, the ortho cannot."""
    rng = np.random.default_rng(0)
    gsd = 0.5
    col = np.arange(40) * gsd
    dsm = np.tile(10.0 - np.tan(np.radians(40)) * np.abs(col - 9.75), (30, 1))
    grey = rng.integers(90, 170, (30, 40)).astype(np.uint8)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    image = relief_image(dsm, gsd)
    np.testing.assert_allclose(image[5, 5], [100 * np.sin(np.radians(-40)), 0], atol=1e-9)
    labels = quickshift_superpixels(image)
    west, east = labels[:, 2:19], labels[:, 21:38]  # clear of the ridge cells
    assert len(np.intersect1d(np.unique(west), np.unique(east))) == 0
    assert len(np.unique(labels)) <= 8  # and each face is a few large super-pixels
    assert len(np.unique(quickshift_superpixels(rgb))) > 50  # the grey noise shatters


def test_ransac_recovers_a_plane_despite_outliers():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 10, (2, 400))
    z = 0.3 * x - 0.2 * y + 5 + rng.normal(0, 0.02, 400)
    z[:60] += rng.uniform(1, 4, 60)  # a tree
    plane = ransac_plane(np.column_stack([x, y, z]))
    assert plane_heights(plane, 2.0, 3.0) == pytest.approx(0.3 * 2 - 0.2 * 3 + 5, abs=0.02)
    wall = np.column_stack([x, np.full(400, 1.0), 10 * y])  # vertical: not a roof
    assert ransac_plane(wall) is None


def test_a_buildings_share_numbers_its_own_superpixels_from_zero():
    """Two buildings of two super-pixels each, and ground between: each share holds its
    super-pixels' points, the one edge between them and its window, renumbered."""
    labels = np.repeat(np.array([[0, 1, 2, 2, 3, 4]]), 3, axis=0)
    dsm = np.where(np.isin(labels, [0, 1, 3, 4]), 10.0, 0.0)
    dsm[0, 4] = np.nan
    grid = Grid(100.0, 50.0, 1.0, 6, 3)
    graph = superpixel_graph(labels, np.zeros((3, 6, 3), np.uint8), np.ones((4, 3, 6)), dsm)
    owner = np.array([1, 1, 0, 2, 2])
    X, Y = grid.cell_centers()
    order = np.argsort(labels.ravel(), kind="stable")
    pts = SuperpixelPoints(np.column_stack([X.ravel(), Y.ravel(), dsm.ravel()])[order],
                           np.array([0, 3, 6, 12, 15]), np.array([3, 6, 12, 15, 18]))  # fmt: skip
    first, second = building_shares(graph, owner, pts, dsm, np.zeros((3, 6)), grid)
    assert first.window == (0, 3, 0, 3) and second.window == (0, 3, 3, 6)
    assert second.grid.xmin == 103.0 and second.grid.width == 3
    np.testing.assert_array_equal(second.graph.labels, np.repeat([[-1, 0, 1]], 3, axis=0))
    np.testing.assert_array_equal(second.graph.edges, [[0, 1]])
    assert second.graph.boundary.tolist() == [3.0] and second.graph.count.tolist() == [3, 3]
    np.testing.assert_array_equal(second.points.of(1), pts.of(4))
    assert not second.known[0, 1] and second.known[1, 1]
    picked = points_of(pts, np.array([4, 0]))
    np.testing.assert_array_equal(picked.points, np.r_[pts.of(4), pts.of(0)])


def test_ransac_of_many_sets_at_once_is_each_sets_own():
    """Sets of different sizes stacked and scored together: each gets the plane it gets
    alone, and a NaN row where alone it gets none (too few points, a wall, a line)."""
    rng = np.random.default_rng(1)
    sets = []
    for n in (3, 7, 40, 40, 250, 9, 1200):
        x, y = rng.uniform(0, 5, (2, n))
        z = rng.normal(0, 0.5) * x + rng.normal(0, 0.5) * y + rng.normal(0, 0.04, n)
        z[: n // 5] += rng.uniform(1, 3, n // 5)  # a fifth of them off the plane
        sets.append(np.column_stack([x + 500, y - 300, z + 40]))
    sets.append(np.column_stack([np.full(30, 2.0), rng.uniform(0, 5, (2, 30)).T]))  # a wall
    sets.append(np.column_stack([np.arange(20.0), np.arange(20.0), np.zeros(20)]))  # a line
    planes = ransac_planes(sets)
    assert planes.shape == (len(sets), 4)
    for points, plane in zip(sets, planes, strict=True):
        alone = ransac_plane(points)
        if alone is None:
            assert np.isnan(plane).all()
        else:
            np.testing.assert_allclose(plane, alone, atol=1e-9)
    assert np.isnan(planes[[0, -2, -1], 0]).all() and np.isfinite(planes[1:-2]).all()
    assert ransac_planes([]).shape == (0, 4)


def test_prototypes_group_hypotheses_of_one_plane():
    rng = np.random.default_rng(0)
    pts, planes = [], []
    for k in range(6):  # six super-pixels: three on each side of a ridge
        x, y = rng.uniform(0, 4, (2, 50)) + [[k * 4], [0]]
        slope = 0.5 if k < 3 else -0.5
        pts.append(np.column_stack([x, y, slope * y + 3]))
        planes.append(_plane(0, slope, 3) + rng.normal(0, 1e-3, 4))
    adjacency = {a: [b for b in range(6) if abs(a - b) == 1] for a in range(6)}
    S = hypothesis_similarity(np.array(planes), pts, np.arange(6), adjacency)
    assert len(S[0]) == 10  # the adjacent pairs only, both ways
    exemplars, assignment = cluster_prototypes(S, 6, -0.25)
    assert len(exemplars) == 2
    assert len(set(assignment[:3])) == 1 and len(set(assignment[3:])) == 1


def test_edges_within_groups_the_edges_both_ends_of_a_building_own():
    owner = np.array([0, 1, 1, 2, 2, 1])
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [1, 5], [4, 5], [2, 5]])
    groups = edges_within(edges, owner)
    assert [g.tolist() for g in groups] == [[0, 2, 5], [1, 4, 6], [3]]


def test_cells_past_a_ridge_take_the_plane_that_fits_them():
    """A gable roof, ridge along x = 0, slopes of 1 in 2; the super-pixel of its west slope
    reaches 1 m past the ridge and took the west plane. Its cells past the ridge by more
    than 0.15 m (where the west plane stands more than the inlier distance above the roof)
    take the east plane, its neighbour's; the others stay; a cell with no height stays."""
    gsd = 0.1
    xs = np.arange(-3.0, 3.0, gsd) + gsd / 2
    X, Y = np.meshgrid(xs, np.arange(5) * gsd)
    heights = 10.0 - 0.5 * np.abs(X)
    labels = np.where(X < 1.0, 0, 1)
    labels[:, :2] = -1  # off the building
    heights[2, 35] = np.nan
    west, east = [-0.5, 0.0, 1.0, -10.0], [0.5, 0.0, 1.0, -10.0]  # z = 10 +- x / 2
    planes = np.array([west, east]) / np.linalg.norm([0.5, 0.0, 1.0])
    faces = cells_to_fitting_planes(labels, np.array([0, 1]), np.array([[0, 1]]), heights,
                                    X, Y, planes, 0.15)  # fmt: skip
    assert (faces[labels < 0] == 0).all() and (faces[labels == 1] == 2).all()
    west_sp = labels == 0
    past = X > 0.15 / 1.0  # the west plane stands x above the roof east of the ridge
    assert (faces[west_sp & past & np.isfinite(heights)] == 2).all()
    assert (faces[west_sp & ~past] == 1).all()
    assert faces[2, 35] == 1  # unknown height: its super-pixel's plane
    # with no neighbour, nothing to move to
    alone = cells_to_fitting_planes(np.where(labels == 0, 0, -1), np.array([0]),
                                    np.zeros((0, 2), np.int64), heights, X, Y, planes[:1],
                                    0.15)  # fmt: skip
    assert (alone[west_sp] == 1).all()


def test_prototype_crf_of_a_building_among_others_by_hand():
    """Two roof sides of 4 super-pixels each (1..4 and 5..8 on a row, 0 and 9 another
    building's); the CRF gives each side its plane, whether the building's edges are
    given or found in the whole graph."""
    rng = np.random.default_rng(0)
    pts, starts = [], [0]
    for k in range(10):
        x, y = rng.uniform(0, 4, (2, 30)) + [[4 * k], [0]]
        pts.append(np.column_stack([x, y, (0.5 if k < 5 else -0.5) * y + 3]))
        starts.append(starts[-1] + 30)
    points = SuperpixelPoints(np.concatenate(pts), np.array(starts[:-1]), np.array(starts[1:]))
    edges = np.array([[k, k + 1] for k in range(9)])
    graph = SimpleNamespace(n=10, edges=edges, boundary=np.full(9, 10.0),
                            colour_distance=np.zeros(9))  # fmt: skip
    members = np.arange(1, 9)
    planes = np.array([_plane(0, 0.5, 3), _plane(0, -0.5, 3)])
    options = SuperpixelOptions()
    owner = np.zeros(10, np.int64)
    owner[members] = 1
    found = label_prototypes(members, planes, points, graph, options, np.array([2, 7]))
    given = label_prototypes(members, planes, points, graph, options, np.array([2, 7]),
                             edges_within(edges, owner)[1])  # fmt: skip
    assert found.tolist() == given.tolist() == [0, 0, 0, 0, 1, 1, 1, 1]


@pytest.mark.parametrize("seed", range(5))
def test_sparse_affinity_propagation_on_all_pairs_is_scikit_learns(seed):
    import warnings

    from sklearn.cluster import AffinityPropagation

    rng = np.random.default_rng(seed)
    X = np.concatenate([rng.normal(c, 0.3, (15, 2)) for c in rng.uniform(0, 10, (4, 2))])
    S = -((X[:, None] - X[None]) ** 2).sum(-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ap = AffinityPropagation(
            affinity="precomputed", preference=np.median(S), damping=0.7, random_state=0
        ).fit(S)
    r, c = np.nonzero(~np.eye(len(X), dtype=bool))
    exemplars, labels = sparse_affinity_propagation(r, c, S[r, c], len(X), np.median(S))
    assert np.array_equal(exemplars, ap.cluster_centers_indices_)
    assert np.array_equal(labels, ap.labels_)


def test_sparse_affinity_propagation_never_joins_items_without_a_pair():
    # two chains of 5 items, similar within, no pair between: no exemplar spans both
    r = np.array([0, 1, 1, 2, 2, 3, 3, 4, 5, 6, 6, 7, 7, 8, 8, 9])
    c = np.array([1, 0, 2, 1, 3, 2, 4, 3, 6, 5, 7, 6, 8, 7, 9, 8])
    exemplars, labels = sparse_affinity_propagation(r, c, np.full(16, -0.01), 10, -1.0)
    assert set(exemplars[labels[:5]]).isdisjoint(exemplars[labels[5:]])
    for i, k in enumerate(exemplars[labels]):  # each item's exemplar is itself or a neighbour
        assert k == i or abs(k - i) == 1


def test_split_buildings_cuts_a_thin_bridge_and_drops_small_ones():
    labels = np.arange(40 * 40).reshape(40, 40)  # one super-pixel per cell
    building = np.zeros(40 * 40, bool)
    mask = np.zeros((40, 40), bool)
    mask[5:15, 5:15] = mask[5:15, 25:35] = True
    mask[9, 15:25] = True  # a one-cell bridge
    mask[30:32, 30:32] = True  # 4 cells: too small
    building[labels[mask]] = True
    owner = split_buildings(building, labels, gsd=0.5, opening_m=1.0, min_area_m2=5.0)
    ids = owner[labels]
    assert len(np.unique(ids[ids > 0])) == 2
    assert ids[10, 10] != ids[10, 30] and ids[31, 31] == 0


def test_extruded_roofs_are_closed_with_the_volume_of_their_planes():
    A, B = box(0, 0, 10, 5), box(0, 5, 10, 10)
    v, t = extrude_faces([A, B], [_plane(0, 0.5, 3), _plane(0, -0.5, 8)], 0.0)
    assert is_watertight(v, t)
    assert _volume(v, t) == pytest.approx(50 * 4.25 * 2)  # mean height 4.25 on each half
    C, D = box(0, 5, 5, 10), box(5, 5, 10, 10)  # a T-junction and steps
    v, t = extrude_faces([A, C, D], [_plane(0, 0, 3), _plane(0, 0, 5), _plane(0, 0, 4)], 0.0)
    assert is_watertight(v, t) and _volume(v, t) == pytest.approx(150 + 125 + 100)
    v, t = extrude_faces([A, B], [_plane(0.3, 0, 3), _plane(-0.3, 0, 6)], 0.0)  # crossing
    assert is_watertight(v, t)
    court = Polygon([(0, 0), (20, 0), (20, 20), (0, 20)], [[(5, 5), (5, 15), (15, 15), (15, 5)]])
    v, t = extrude_faces([court], [_plane(0, 0, 5)], 0.0)
    assert is_watertight(v, t) and _volume(v, t) == pytest.approx(300 * 5)


def _floor_triangles(v, t):
    P = v[t]
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    return P[n[:, 2] < 0]


def test_floor_is_triangulated_over_the_outline_alone():
    A, C, D = box(0, 0, 10, 5), box(0, 5, 5, 10), box(5, 5, 10, 10)
    v, t = extrude_faces([A, C, D], [_plane(0, 0, 3), _plane(0, 0, 5), _plane(0, 0, 4)], 0.0)
    floor = _floor_triangles(v, t)
    # 7 outline vertices, (5, 5) inside: a 7-gon is 5 triangles, none touching (5, 5)
    assert len(floor) == 5 and np.all(floor[..., 2] == 0)
    assert not np.any(np.all(floor[..., :2] == (5, 5), axis=-1))
    assert is_watertight(v, t) and _volume(v, t) == pytest.approx(150 + 125 + 100)
    court = Polygon([(0, 0), (20, 0), (20, 20), (0, 20)], [[(5, 5), (5, 15), (15, 15), (15, 5)]])
    left, right = (orient(court & box(x, 0, x + 10, 20)) for x in (0, 10))
    v, t = extrude_faces([left, right], [_plane(0, 0, 5), _plane(0, 0, 6)], 0.0)
    # outline: 6 outer and 6 inner vertices (the faces' seam ends on both rings)
    assert len(_floor_triangles(v, t)) == 6 + 6 + 2 * 1 - 2
    assert is_watertight(v, t) and _volume(v, t) == pytest.approx(150 * 5 + 150 * 6)
    # two faces touching at a corner: the outline walk is ambiguous, the floor follows them
    v, t = extrude_faces([box(0, 0, 5, 5), box(5, 5, 10, 10)], [_plane(0, 0, 3)] * 2, 0.0)
    assert len(_floor_triangles(v, t)) == 4 and _volume(v, t) == pytest.approx(150)


def test_unpaired_edges_of_open_and_doubled_meshes():
    tetra = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    assert len(unpaired_edges(tetra)) == 0
    # without its first face, the edges that walked back along that face are unpaired
    assert {tuple(map(int, e)) for e in unpaired_edges(tetra[1:])} == {(2, 0), (1, 2), (0, 1)}
    doubled = np.vstack([tetra, tetra[:1]])  # one triangle twice: its edges walked twice
    assert len(unpaired_edges(doubled)) == 6


def test_closure_mends_the_cells_at_the_open_vertex_not_the_smallest_face_anywhere():
    # high A and D, low B and C meet at (12, 12): their walls share one vertical edge
    # there, four triangles on it; E, the smallest face, is far from it. The cells next to
    # that vertex of the smallest face there go to a neighbour; every face stays.
    faces = np.zeros((24, 24), int)
    faces[2:12, 2:12], faces[2:12, 12:22] = 1, 2
    faces[12:22, 2:12], faces[12:22, 12:22] = 3, 4
    faces[4:7, 22:24] = 5
    planes = np.array([_plane(0, 0, z) for z in (8, 5, 5, 8, 6.5)])
    grid = Grid(0.0, 24.0, 1.0, 24, 24)
    (model,) = model_building(
        faces, grid, planes, np.zeros((24, 24)), SuperpixelOptions(simplify_m=0.01)
    )
    assert model.watertight and model.record["faces_merged_for_closure"] == 1
    assert len(model.planes) == 5  # E kept, and A-D
    assert sorted(model.plane_areas)[1] >= 100 - 9  # at most the 3 x 3 cells at the vertex


def test_a_t_junction_is_vertex_matched_and_the_faces_simplify():
    """Face 1 runs the full height of the west side; faces 2 and 3 meet on its east
    edge, where polygonising leaves face 1 no vertex. The outline is a 1-cell zigzag
    that a 1.5-cell tolerance removes."""
    faces = np.zeros((24, 24), int)
    faces[2:22, 2:10] = 1
    faces[2:12, 10:22] = 2
    faces[12:22, 10:22] = 3
    faces[2:22:2, 1] = 1  # teeth on the west and east sides
    faces[3:12:2, 22] = 2
    faces[13:22:2, 22] = 3
    grid = Grid(0.0, 24.0, 1.0, 24, 24)
    shapes = list(rasterio.features.shapes(faces.astype(np.int32), mask=faces > 0))
    raw, raw_labels = [shape(g) for g, _ in shapes], [int(k) for _, k in shapes]
    assert not shapely.coverage_is_valid(np.array(raw, dtype=object))
    assert shapely.coverage_is_valid(vertex_matched(raw, 1e-3))
    polys, labels = face_polygons(faces, grid, tolerance=1.5, min_face_m2=0.5)
    assert sorted(labels) == [1, 2, 3]
    assert sum(len(p.exterior.coords) for p in polys) <= 20  # from 89 (23 + 23 + 43)
    (face1,) = [p for p, k in zip(polys, labels, strict=True) if k == 1]
    assert (10.0, 12.0) in list(face1.exterior.coords)  # the T vertex
    planes = {1: _plane(0, 0.3, 4), 2: _plane(-0.3, 0, 9), 3: _plane(0, 0, 6)}
    v, t = extrude_faces(polys, [planes[k] for k in labels], 0.0)
    assert is_watertight(v, t)
    # simplified without the matching, face 1 loses the T vertex and the solid opens there
    unmatched = shapely.coverage_simplify(np.array(raw, dtype=object), 1.5)
    v, t = extrude_faces(list(unmatched), [planes[k] for k in raw_labels], 0.0)
    assert not is_watertight(v, t)


def test_face_polygons_from_a_checkerboard_corner_stay_manifold():
    faces = np.zeros((8, 8), int)
    faces[1:4, 1:4] = 1
    faces[4:7, 4:7] = 1  # touches the first square only at a corner
    faces[1:4, 4:7] = 2
    assert not (untangle_diagonals(faces) != faces).sum() == 0
    grid = Grid(0.0, 8.0, 1.0, 8, 8)
    polys, labels = face_polygons(faces, grid, tolerance=0.1, min_face_m2=1.0)
    planes = {1: _plane(0, 0, 4), 2: _plane(0.2, 0, 5)}
    v, t = extrude_faces(polys, [planes[k] for k in labels], 0.0)
    assert is_watertight(v, t)


@pytest.mark.parametrize(
    "planes, outline_z, expect",
    [
        ([_plane(0, 0, 5)], [5, 5, 5, 5], "flat"),
        ([_plane(0, 0, 5), _plane(0, 0, 9)], [5, 5, 9, 9], "multi-level"),
        ([_plane(0, 0.3, 5)], [5, 5, 8, 8], "shed"),
        ([_plane(0, 0.5, 5), _plane(0, -0.5, 15)], [5, 5, 10, 10, 5, 5], "gable"),
        (
            [_plane(0, 0.5, 5), _plane(0, -0.5, 15), _plane(0.5, 0, 5), _plane(-0.5, 0, 15)],
            [5, 5, 5, 5],
            "pyramid",
        ),
        (
            [_plane(0, 0.5, 5), _plane(0, -0.5, 15), _plane(0.5, 0, 5), _plane(-0.5, 0, 19)],
            [5, 5, 5, 5],
            "hipped",
        ),
    ],
)
def test_roof_types(planes, outline_z, expect):
    planes = np.array(planes)
    areas = np.full(len(planes), 10.0)
    heights = np.array([plane_heights(p, 10.0, 10.0) for p in planes])
    assert roof_type(planes, areas, heights, np.array(outline_z, float)) == expect


def test_roof_types_of_fitted_models():
    """What a fitted model gives: plane mean heights half-way up, outline vertices up to
    half a metre off the walls, a mansard's fourth steep face lost, an L's hips."""
    t = np.tan(np.radians(40))  # a 10 x 6 m hipped roof, eaves at 5 m, ridge 5 + 3t
    hipped = np.array(
        [_plane(0, t, 5), _plane(0, -t, 5 + 6 * t), _plane(t, 0, 5), _plane(-t, 0, 5 + 10 * t)]
    )
    areas, heights = np.array([20.0, 20, 10, 10]), np.full(4, 5 + t)
    off_walls = np.array([4.6, 4.75, 5.0, 4.58, 5.1, 4.9, 4.6, 5.0])
    got = roof_type(hipped, areas, heights, off_walls, ridge_z=5 + 3 * t, centre=(5, 3, 7.7))
    assert got == "hipped"
    # the same planes over an L-shaped gable: its ends reach the ridge
    gable_ends = np.array([5.0, 5.0, 5 + 3 * t, 5.0, 5.0, 5 + 3 * t, 5.0, 5.0])
    assert roof_type(hipped, areas, heights, gable_ends, ridge_z=5 + 3 * t) == "gable"
    # four hips meeting in one point: a pyramid over the centre, an L's hips elsewhere
    pyramid = np.array(
        [_plane(0, 0.5, 5), _plane(0, -0.5, 15), _plane(0.5, 0, 5), _plane(-0.5, 0, 15)]
    )
    level = np.full(4, 5.0)
    assert (
        roof_type(pyramid, np.full(4, 10.0), np.full(4, 7.0), level, 10.0, (10, 10, 20))
        == "pyramid"
    )
    assert (
        roof_type(pyramid, np.full(4, 10.0), np.full(4, 7.0), level, 10.0, (25, 10, 20)) == "hipped"
    )
    # a mansard: three 70-degree faces (the fourth under 8 % of the roof) under a flat top
    s = np.tan(np.radians(70))
    mansard = np.array(
        [_plane(0, s, 5), _plane(s, 0, 5), _plane(-s, 0, 5 + 10 * s), _plane(0, 0, 8)]
    )
    got = roof_type(mansard, np.array([8.0, 6, 6, 40]), np.array([6.5, 6.5, 6.5, 8]), level, 8.0)
    assert got == "mansard"


@pytest.mark.parametrize("turn_deg", [0.0, 30.0, 45.0, 60.0])
def test_roof_types_do_not_turn_with_the_building(turn_deg):
    """The 10 x 6 m hipped roof of ``test_roof_types_of_fitted_models`` turned about its
    centre, each face a few tenths of a degree off as fitted faces are: they face four
    ways whatever the turn. In the world's quarters, at 45 degrees the faces fell on
    either side of the quarters' bounds, two of them into one quarter ("complex")."""
    t = np.tan(np.radians(40))
    slopes = [(0, t), (0, -t), (t, 0), (-t, 0)]
    off = np.radians([-0.2, -0.3, 0.4, 0.4])
    a = np.radians(turn_deg) + off
    turned = [(gx * np.cos(ak) - gy * np.sin(ak), gx * np.sin(ak) + gy * np.cos(ak))
              for (gx, gy), ak in zip(slopes, a, strict=True)]  # fmt: skip
    ridge = 5 + 3 * t  # each face rises from its eave at 5 m, 3 m (long sides) or 5 m out
    reach = [3.0, 3.0, 5.0, 5.0]
    planes = np.array([_plane(gx, gy, 5 + t * r)
                       for (gx, gy), r in zip(turned, reach, strict=True)])  # fmt: skip
    areas, heights = np.array([20.0, 20, 10, 10]), np.full(4, 5 + t)
    got = roof_type(planes, areas, heights, np.full(8, 5.0), ridge_z=ridge, centre=(0, 0, 7.7))
    assert got == "hipped"


def test_unseen_edge_cells_stay_within_reach_and_when_enclosed():
    faces = np.zeros((7, 12), int)
    faces[1:6, 1:11] = 1
    observed = np.zeros_like(faces, bool)
    observed[1:6, 1:6] = True  # the east part of the super-pixels was never seen
    observed[3, 3] = False  # a hole in the roof, enclosed
    kept = observed_faces(faces, observed, reach=2)
    assert kept[3, 3] == 1
    assert (kept[1:6, 6:8] == 1).all() and (kept[1:6, 8:] == 0).all()
    assert (observed_faces(faces, observed, reach=0)[1:6, 6:] == 0).all()


def test_a_gable_notch_no_view_saw_takes_its_side_face():
    """A 24 m x 12 m gable turned by 30 degrees, 10 m at its eaves, whose south side hides
    an 8 m x 4 m notch from every view (and the ground beyond it): the notch's cells take
    the south face, and the modelled roof covers the whole 288 m² (without them it
    has the notch cut out, 256 m²). The notch's rim fits a 70-degree face, as a wall's
    blurred top does: the notch is not given that one."""
    gsd, n, t = 0.5, 80, np.radians(30)
    grid = Grid(-20.0, 20.0, gsd, n, n)
    X, Y = grid.cell_centers()
    u, v = X * np.cos(t) + Y * np.sin(t), -X * np.sin(t) + Y * np.cos(t)
    rect = (np.abs(u) < 12) & (np.abs(v) < 6)
    notch = (np.abs(u) < 4) & (v > -9) & (v < -2)
    slope = 0.5  # the roof rises by 0.5 m per metre to the ridge on v = 0
    dsm = np.where(rect, 13.0 - slope * np.abs(v), 0.0)
    dsm[notch] = np.nan
    faces = np.where(rect & ~notch, np.where(v < 0, 1, 2), 0)
    rim = (faces == 1) & (np.abs(u) < 4) & (v < -1.25)
    faces[rim] = 3
    nx, ny = -np.sin(t), np.cos(t)  # v's direction: z = 13 - 0.5 |x nx + y ny|
    planes = np.array([_plane(slope * nx, slope * ny, 13), _plane(-slope * nx, -slope * ny, 13),
                       _plane(2.75 * nx, 2.75 * ny, 16)])  # fmt: skip
    filled = with_unseen_parts(faces, planes, dsm, np.zeros((n, n)), X, Y)
    # a turned grid's staircase along the roof's edge: measured 125 of 129 cells in,
    # 7 cells of ground past the eaves out
    assert (filled[notch & rect] == 1).sum() >= 0.95 * (notch & rect).sum()
    assert (filled[notch & ~rect] > 0).sum() <= 0.07 * (notch & rect).sum()
    np.testing.assert_array_equal(filled[~notch], faces[~notch])
    options = SuperpixelOptions(simplify_m=0.01)
    (whole,) = model_building(filled, grid, planes, np.zeros((n, n)), options)
    (cut,) = model_building(faces, grid, planes, np.zeros((n, n)), options)
    assert whole.watertight
    assert whole.footprint.area == pytest.approx(288, rel=0.02)
    assert cut.footprint.area == pytest.approx(256, rel=0.02)


def test_a_hidden_lower_tier_takes_the_lower_face():
    """A 24 m x 12 m building, its north half at 20 m, its south half at 10 m, with an
    8 m x 6 m part of the lower half behind the upper one from every view (and the
    ground beyond it): the hidden cells take the lower half's face, all of them, where
    the nearest face would have given the upper one's to those nearer to it."""
    gsd, n = 0.5, 80
    grid = Grid(-20.0, 20.0, gsd, n, n)
    X, Y = grid.cell_centers()
    rect = (np.abs(X) < 12) & (np.abs(Y) < 6)
    hidden = (np.abs(X) < 4) & (Y > -9) & (Y < 0)
    dsm = np.where(rect, np.where(Y > 0, 20.0, 10.0), 0.0)
    dsm[hidden] = np.nan
    faces = np.where(rect & ~hidden, np.where(Y > 0, 1, 2), 0)
    planes = np.array([_plane(0, 0, 20), _plane(0, 0, 10)])
    filled = with_unseen_parts(faces, planes, dsm, np.zeros((n, n)), X, Y)
    assert (filled[hidden & rect] == 2).all() and (filled[hidden & ~rect] == 0).all()


def test_a_hidden_part_takes_a_face_only_under_the_ceiling():
    """The 24 m x 12 m building of the test above, its hidden part now the east end of
    its lower half, with the ground beyond it east and south (the building on one side
    only along either direction: north of it the upper half, west the lower). With the
    fusion's
    ceiling over them (15 m over the building's cells, 5 m over the ground's) the
    building's take the lower half's face and the ground's none, within the reach too;
    under a ceiling of 9 m the lower face (10 m) fits nowhere; with no ceiling the part
    is not between known sides, and nothing is filled."""
    gsd, n = 0.5, 80
    grid = Grid(-20.0, 20.0, gsd, n, n)
    X, Y = grid.cell_centers()
    rect = (np.abs(X) < 12) & (np.abs(Y) < 6)
    hidden = (X > 4) & (X < 15) & (Y > -9) & (Y < 0)
    dsm = np.where(rect, np.where(Y > 0, 20.0, 10.0), 0.0)
    dsm[hidden] = np.nan
    faces = np.where(rect & ~hidden, np.where(Y > 0, 1, 2), 0)
    planes = np.array([_plane(0, 0, 20), _plane(0, 0, 10)])
    ceiling = np.where(hidden, np.where(rect, 15.0, 5.0), np.nan)
    zero = np.zeros((n, n))
    filled = with_unseen_parts(faces, planes, dsm, zero, X, Y, ceiling, reach=2)
    assert (filled[hidden & rect] == 2).all() and (filled[hidden & ~rect] == 0).all()
    # the ceiling is what keeps the ground out: under a high one the reach's metre
    # past the wall takes the face
    high = np.where(hidden, 15.0, np.nan)
    past = with_unseen_parts(faces, planes, dsm, zero, X, Y, high, reach=2)
    near = (X < 13) & (Y > -7)
    assert (past[hidden & ~rect & near] == 2).all() and (past[hidden & ~near] == 0).all()
    low = np.where(hidden, 9.0, np.nan)
    assert (with_unseen_parts(faces, planes, dsm, zero, X, Y, low, reach=2)[hidden] == 0).all()
    assert (with_unseen_parts(faces, planes, dsm, zero, X, Y)[hidden] == 0).all()


@pytest.mark.parametrize("rotation_deg", [0.0, 30.0])
def test_regularised_outline_is_square_and_still_a_coverage(rotation_deg):
    """Two faces of a 10 x 6 m house whose simplified outline wobbles and has a cut corner:
    the outline comes out with right-angled corners on the house's axes, the faces still
    share their boundary, and no vertex moves farther than allowed."""
    c, s = np.cos(np.radians(rotation_deg)), np.sin(np.radians(rotation_deg))

    def turned(xy):
        xy = np.asarray(xy, float)
        return Polygon(xy @ np.array([[c, s], [-s, c]]))

    west = turned([(0, 0.1), (5, 0), (5, 6), (0.3, 6.05), (0, 5.7)])
    east = turned([(5, 0), (10, -0.1), (10.05, 3), (10, 6), (5, 6)])
    out = regularise_outline([west, east], tolerance_deg=10.0, max_shift=1.0)
    assert shapely.coverage_is_valid(np.array(out, dtype=object))
    outline = shapely.coverage_union_all(out).simplify(1e-6)
    ring = np.asarray(outline.exterior.coords)
    assert len(ring) == 5  # four corners: the cut corner is squared
    d = np.diff(ring, axis=0)
    angles = np.degrees(np.arctan2(d[:, 1], d[:, 0])) - rotation_deg
    assert np.allclose((angles + 45) % 90 - 45, 0, atol=1.0)  # on the house's axes
    cos = np.einsum("ij,ij->i", d, np.roll(d, 1, axis=0)) / np.prod(
        [np.linalg.norm(d, axis=1), np.linalg.norm(np.roll(d, 1, axis=0), axis=1)], axis=0
    )
    assert np.allclose(cos, 0, atol=1e-9)  # right angles
    assert outline.area == pytest.approx(60.0, abs=1.0)
    still = regularise_outline([west, east], tolerance_deg=10.0, max_shift=1e-3)
    for a, b in zip(still, [west, east], strict=True):
        assert a.hausdorff_distance(b) <= 1e-3 + 1e-9


def test_model_of_a_turned_gable_with_regularised_outline():
    """A 20-degree turned 16 x 10 m gable polygonised from 0.25 m cells: with
    --regularise its outline has four right-angled corners on the house's axes and the
    mesh stays closed; without it the simplified staircase keeps more corners."""
    gsd, n = 0.25, 96
    grid = Grid(0.0, n * gsd, gsd, n, n)
    x, y = grid.cell_centres() if hasattr(grid, "cell_centres") else np.meshgrid(
        (np.arange(n) + 0.5) * gsd, n * gsd - (np.arange(n) + 0.5) * gsd
    )  # fmt: skip
    a = np.radians(20)
    u = (x - 12) * np.cos(a) + (y - 12) * np.sin(a)  # along the ridge
    v = -(x - 12) * np.sin(a) + (y - 12) * np.cos(a)
    faces = np.where((np.abs(u) < 8) & (np.abs(v) < 5), np.where(v < 0, 1, 2), 0)
    normal_s = np.array([-np.sin(a), np.cos(a)])  # the south face rises to the ridge
    planes = []
    for sign in (1, -1):
        gx, gy = sign * 0.6 * normal_s
        planes.append(_plane(gx, gy, 10 - gx * 12 - gy * 12))
    ground = np.zeros((n, n))
    corners = {}
    for deg in (0.0, 10.0):
        (model,) = model_building(
            faces, grid, np.array(planes), ground, SuperpixelOptions(regularise_deg=deg)
        )
        assert model.watertight
        outline = model.footprint.simplify(1e-6)
        ring = np.asarray(outline.exterior.coords)
        corners[deg] = len(ring) - 1
        if deg:
            d = np.diff(ring, axis=0)
            off = (np.degrees(np.arctan2(d[:, 1], d[:, 0])) - 20 + 45) % 90 - 45
            assert np.allclose(off, 0, atol=1.0)
            assert outline.area == pytest.approx(160, rel=0.03)
    assert corners[10.0] == 4 < corners[0.0]


def test_closing_a_roof_model_stops_when_no_face_has_a_neighbour(monkeypatch):
    """Two flat faces apart, as if neither closed (a mesh judged open): no face has a
    neighbouring face to take its cells, so the mending stops and the model comes back
    as it is, where it looped for ever (the LOD path on seed 5, a 4-cell island)."""
    import modeling.shared.roof_model as rm

    faces = np.zeros((20, 30), np.int64)
    faces[2:10, 2:12], faces[12:14, 20:22] = 1, 2
    planes = np.array([[0.0, 0.0, 1.0, -10.0], [0.0, 0.0, 1.0, -6.0]])
    monkeypatch.setattr(rm, "_watertight", lambda b: False)
    b = rm.closed_roof_model(faces, Grid(0.0, 20 * 0.25, 0.25, 30, 20), planes, 0.0, 0.5)
    assert b is not None and b.record["faces_merged_for_closure"] == 0
