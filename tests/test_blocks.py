"""`workbench model blocks`: the DEM-blocks paper's library, energy and sampler on hand-made
cases, and the path end to end from fused rasters, scored by the shared metrics."""

import json
import shutil

import numpy as np
import pytest
import rasterio
from affine import Affine
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from modeling.blocks.block_meshes import block_faces
from modeling.blocks.energy import joinable, likelihood, pair_energy, parameter_distance
from modeling.blocks.library import Block, Frame, block_heights, parameter_ranges
from modeling.blocks.options import BlocksOptions
from modeling.blocks.path import (
    BlocksInputs,
    building_task,
    closed_solid,
    flat_block,
    raster_solid,
    summary_lines,
)
from modeling.blocks.rjmcmc import Pair, SupportData, _Chain, anneal, form_sweep
from modeling.blocks.supports import (
    Support,
    automatic_supports,
    connected_rectangles,
    gap_supports,
    height_regions,
    junction_sides,
    neighbour_pairs,
    rectangle_frame,
    supports_from_file,
)
from modeling.shared.footprint_priors import Prior, crowns_over_the_edge, rasterize_on
from modeling.shared.opened_parts import (
    lowest_around,
    nearest_of,
    under_ceiling,
    unseen_between,
    unseen_parts,
    unseen_rim_filled,
)
from modeling.shared.roof_envelope import building_solid
from tests.conftest import run_cli
from workbench.errors import InputError
from workbench.meshes import is_watertight
from workbench.raster import Grid
from workbench.truth import TopDown

FREE = (False, False, False, False)
FRAME = Frame(0.0, (0.0, 0.0), (0.0, 10.0, 0.0, 6.0))  # 10 m along u, 6 m along v


def _heights(block, u, v, ends=FREE, frame=FRAME):
    return block_heights(block, np.asarray(u, float), np.asarray(v, float), frame, ends)


def test_roof_forms_by_hand():
    """Heights at the points each form's geometry fixes (a 10 x 6 m support)."""
    gable = Block("gable", 0, False, (10.0, 13.0))
    assert np.allclose(_heights(gable, [5, 5, 5, 0], [0, 3, 1.5, 3]), [10, 13, 11.5, 13])
    hipped = Block("hipped", 0, False, (10.0, 13.0, 3.0))  # hips 3 m long
    assert np.allclose(_heights(hipped, [0, 3, 5, 10, 1.5], [3, 3, 3, 3, 3]),
                       [10, 13, 13, 10, 11.5])  # fmt: skip
    pyramid = Block("pyramid", 0, False, (10.0, 14.0))
    assert np.allclose(_heights(pyramid, [5, 0, 10, 2.5], [3, 0, 6, 3]), [14, 10, 10, 12])
    # a mansard: 70-degree-like lower band 1 m deep up to 12.5, then up to 13.5 at the ridge
    mansard = Block("mansard", 0, False, (10.0, 12.5, 13.5, 1.0))
    assert np.allclose(_heights(mansard, [5, 5, 5, 0.5], [0, 1, 3, 3]), [10, 12.5, 13.5, 11.25])
    gambrel = Block("gambrel", 0, False, (10.0, 12.5, 13.5, 1.0))  # no hipped ends
    assert np.allclose(_heights(gambrel, [0, 0], [3, 1]), [13.5, 12.5])
    half = Block("half-hipped", 0, False, (10.0, 13.0, 12.0, 1.0))  # hip from 12 m, 1 m long
    assert np.allclose(_heights(half, [0, 1, 0], [3, 3, 0]), [12, 13, 10])
    shed = Block("shed", 1, True, (10.0, 12.0))  # ridge along v: t is u, low at u = 10
    assert np.allclose(_heights(shed, [0, 10, 5], [3, 3, 3]), [12, 10, 11])
    vault = Block("semi-elliptic", 0, False, (10.0, 13.0))
    phi = np.pi / 4  # a chord vertex: on the ellipse
    assert np.allclose(_heights(vault, [5, 5, 5], [3, 0, 3 * (1 - np.cos(phi))]),
                       [13, 10, 10 + 3 * np.sin(phi)])  # fmt: skip


def test_junction_end_has_no_hip():
    """A ridge end on a common edge runs on into the neighbour: no end plane there."""
    hipped = Block("hipped", 0, False, (10.0, 13.0, 3.0))
    joined = (False, False, True, False)  # the u1 side is a junction
    assert _heights(hipped, [10], [3], joined)[0] == pytest.approx(13.0)
    assert _heights(hipped, [0], [3], joined)[0] == pytest.approx(10.0)


def test_likelihood_is_eq3():
    model, dsm = np.array([1.0, 2.0, 3.0]), np.array([0.0, 4.0, 3.0])
    assert likelihood(model, dsm, 1.5) == pytest.approx((1.0 + 2.0**1.5) ** (1 / 1.5))
    assert likelihood(model, dsm, 2.0) == pytest.approx(np.sqrt(5.0))


def test_joinable_prior():
    """Eq. 4-5: same form, a ridge into the common edge, no step: beta (D / D_max - 1)."""
    a = Block("gable", 0, False, (10.0, 13.0))
    b = Block("gable", 0, False, (10.2, 13.4))
    u, v = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    assert joinable(a, b, u, u, v)  # both ridges run into an edge along v ("-")
    assert joinable(a, b, u, v, v)  # one does (an "L")
    assert not joinable(a, b, v, v, v)  # side by side along the edge: a valley
    assert not joinable(a, Block("hipped", 0, False, (10.0, 13.0, 3.0)), u, u, v)
    assert not joinable(a, Block("gable", 0, False, (12.0, 15.0)), u, u, v)  # a storey's step
    assert parameter_distance(a, b, 6.0) == pytest.approx(0.6 / 6.0 - 1.0)
    assert pair_energy(a, b, u, u, v, 6.0, beta=5.0) == pytest.approx(5.0 * (0.1 - 1.0))
    assert pair_energy(a, b, v, v, v, 6.0, beta=5.0) == 0.0


def _support_data(block, frame=FRAME, ends=FREE, noise=0.1, seed=0):
    u0, u1, v0, v1 = frame.rect
    U, V = np.meshgrid(np.arange(u0 + 0.125, u1, 0.25), np.arange(v0 + 0.125, v1, 0.25))
    z = _heights(block, U.ravel(), V.ravel(), ends, frame)
    z = z + np.random.default_rng(seed).normal(0.0, noise, z.shape)
    return SupportData(frame, ends, U.ravel(), V.ravel(), z)


@pytest.mark.parametrize(
    "truth",
    [
        Block("gable", 0, False, (10.0, 13.0)),
        Block("hipped", 0, False, (20.0, 23.0, 3.0)),
        Block("shed", 1, True, (15.0, 17.0)),
        Block("mansard", 0, False, (10.0, 12.5, 13.5, 1.2)),
        Block("flat", 0, False, (31.0,)),
    ],
    ids=lambda b: b.form,
)
def test_annealing_finds_the_block_of_a_dsm(truth):
    """A DSM of one block with 10 cm of noise: the sampler returns its form and its
    parameters within 5 cm (measured: within 2 cm), the same for the same seed."""
    data = _support_data(truth)
    run = anneal([data], [], alpha=1.5, beta=5.0, iterations=4000, seed=3, form_cost=0.05)
    found = run.blocks[0]
    assert found.form == truth.form
    if truth.form != "flat" and truth.form != "pyramid":
        assert found.along == truth.along
    assert np.allclose(found.params, truth.params, atol=0.05)
    again = anneal([data], [], alpha=1.5, beta=5.0, iterations=4000, seed=3, form_cost=0.05)
    assert again.blocks == run.blocks and again.trace == run.trace
    assert run.adjustment_from is not None  # reached the adjustment stage
    assert run.trace[-1][2] <= run.trace[0][2]


def test_neighbours_are_drawn_together_by_the_prior():
    """Two supports of one gable roof ("-" junction), one of them with a noisy DSM: the
    prior's pull gives them the same heights (within 5 cm) and makes them joinable."""
    left = Frame(0.0, (0.0, 0.0), (0.0, 8.0, 0.0, 6.0))
    right = Frame(0.0, (0.0, 0.0), (8.0, 16.0, 0.0, 6.0))
    truth = Block("gable", 0, False, (10.0, 13.0))
    a = _support_data(truth, left, (False, False, True, False), noise=0.05, seed=1)
    b = _support_data(truth, right, (True, False, False, False), noise=0.4, seed=2)
    run = anneal([a, b], [Pair(0, 1, np.array([0.0, 1.0]))], alpha=1.5, beta=5.0,
                 iterations=4000, seed=0, form_cost=0.05)  # fmt: skip
    x, y = run.blocks
    assert x.form == y.form == "gable"
    assert np.allclose(x.params, y.params, atol=0.05)
    assert run.prior < -0.9 * 5.0


def test_an_arm_carries_its_roof_into_the_valleys():
    """An L of two gables whose DSM has the valleys of a real L (the arm's roof running on
    into the other's up to its ridge, 15 cm of noise): with the arm's roof carried over
    the other's near half, the valley costs nothing, and both blocks come back within
    5 cm."""
    a_frame = Frame(0.0, (0.0, 0.0), (0.0, 12.0, 6.0, 12.0))  # the main arm, ridge along u
    b_frame = Frame(0.0, (0.0, 0.0), (7.0, 12.0, 0.0, 6.0))  # the other, ridge along v
    a_true = Block("gable", 0, False, (10.0, 13.0))
    b_true = Block("gable", 1, False, (10.0, 13.0))
    b_ends = (False, False, False, True)  # its v1 side is the junction
    a = _support_data(a_true, a_frame, FREE, noise=0.15, seed=0)
    b = _support_data(b_true, b_frame, b_ends, noise=0.15, seed=1)
    carried = (a.v <= 9.0) & (a.u >= 7.0)  # the main arm's near half, the other's width
    a.z[carried] = np.maximum(a.z[carried], _heights(b_true, a.u[carried], a.v[carried],
                                                     b_ends, b_frame))  # fmt: skip
    pairs = [Pair(0, 1, np.array([1.0, 0.0]))]
    plain = _Chain([a, b], pairs, [a_true, b_true], 1.5, 5.0).energy
    idx = np.flatnonzero(carried)
    b.strips[3] = (0, idx, a.u[idx], a.v[idx])
    assert _Chain([a, b], pairs, [a_true, b_true], 1.5, 5.0).energy < 0.5 * plain
    run = anneal([a, b], pairs, alpha=1.5, beta=5.0, iterations=4000, seed=0, form_cost=0.05)
    x, y = run.blocks
    assert (x.form, x.along, y.form, y.along) == ("gable", 0, "gable", 1)
    assert np.allclose(x.params, a_true.params, atol=0.05)
    assert np.allclose(y.params, b_true.params, atol=0.05)


def test_form_sweep_leaves_a_wrong_form_for_the_right_one():
    """The zero-temperature sweep over the forms, from the wrong ones an annealing can end
    in: an L of two hipped-ended gables (the one above) left as two joinable mansards, and
    a hipped roof left as a pyramid. It returns the true forms within 5 cm, the energy
    lower, and the count of blocks it changed; it draws nothing at random."""
    a_frame = Frame(0.0, (0.0, 0.0), (0.0, 12.0, 6.0, 12.0))
    b_frame = Frame(0.0, (0.0, 0.0), (7.0, 12.0, 0.0, 6.0))
    a_true, b_true = Block("gable", 0, False, (10.0, 13.0)), Block("gable", 1, False, (10.0, 13.0))
    b_ends = (False, False, False, True)
    a = _support_data(a_true, a_frame, FREE, noise=0.1, seed=0)
    b = _support_data(b_true, b_frame, b_ends, noise=0.1, seed=1)
    near = (a.v <= 9.0) & (a.u >= 7.0)
    a.z[near] = np.maximum(a.z[near], _heights(b_true, a.u[near], a.v[near], b_ends, b_frame))
    idx = np.flatnonzero(near)
    b.strips[3] = (0, idx, a.u[idx], a.v[idx])
    pairs = [Pair(0, 1, np.array([1.0, 0.0]))]
    wrong = [Block("mansard", 0, False, (10.0, 11.5, 13.0, 1.0)),
             Block("mansard", 1, False, (10.0, 11.5, 13.0, 1.0))]  # fmt: skip
    chain = _Chain([a, b], pairs, wrong, 1.5, 5.0, 0.05)
    before = chain.energy
    swept, evaluations, changed = form_sweep(chain)
    x, y = swept.blocks
    assert (x.form, x.along, y.form, y.along) == ("gable", 0, "gable", 1)
    assert np.allclose(x.params, a_true.params, atol=0.05)
    assert np.allclose(y.params, b_true.params, atol=0.05)
    assert swept.energy < 0.5 * before and changed == 2 and evaluations > 0

    hipped = Block("hipped", 0, False, (20.0, 23.0, 3.0))
    data = _support_data(hipped)
    chain = _Chain([data], [], [Block("pyramid", 0, False, (20.0, 23.0))], 1.5, 5.0, 0.05)
    swept, _, changed = form_sweep(chain)
    assert swept.blocks[0].form == "hipped" and changed == 1
    assert np.allclose(swept.blocks[0].params, hipped.params, atol=0.05)
    again = form_sweep(_Chain([data], [], [Block("pyramid", 0, False, (20.0, 23.0))], 1.5,
                              5.0, 0.05))[0]  # fmt: skip
    assert again.blocks == swept.blocks


def test_prior_arms_become_connected_rectangles():
    """An L prior's two arms, cut where they overlap, share an edge and cover it."""
    prior = Prior("L", 0.3, np.array([5.0, 7.0]), np.array([-10.0, 10.0, -6.0, 6.0]),
                  [np.array([-10.0, 2.0, -6.0, 0.0])])  # fmt: skip
    rects = connected_rectangles(prior)
    assert len(rects) == 2
    polys = [prior.frame_polygon(r) for r in rects]
    assert polys[0].intersection(polys[1]).area < 1e-6
    assert polys[0].union(polys[1]).area == pytest.approx(prior.polygon().area)
    frames = [Frame(0.3, (5.0, 7.0), tuple(r)) for r in rects]
    supports = [Support(p, f, 1) for p, f in zip(polys, frames, strict=True)]
    pairs = neighbour_pairs(supports)
    assert len(pairs) == 1 and abs(pairs[0][2] @ [np.cos(0.3), np.sin(0.3)]) > 0.99
    ends = junction_sides(supports)
    assert ends[0] == FREE and ends[1] == (False, False, False, True)  # the arm's v1 end


def test_side_by_side_blocks_close_where_their_roofs_cross():
    """An L of a gable ending on another's eave: the two roofs cross along their common
    edge, and the mesh needs a vertex where they do (it was open without one)."""
    a = Support(box(0, 6, 12, 12), Frame(0.0, (0.0, 0.0), (0.0, 12.0, 6.0, 12.0)))
    b = Support(box(7, 0, 12, 6), Frame(0.0, (0.0, 0.0), (7.0, 12.0, 0.0, 6.0)))
    blocks = [Block("gable", 0, False, (10.0, 13.0)), Block("gable", 1, False, (9.8, 12.0))]
    ends = [FREE, (False, False, False, True)]
    faces = [block_faces(x, s, e) for x, s, e in zip(blocks, [a, b], ends, strict=True)]
    solid = building_solid(faces, 0.0, 0.0, np.zeros(2))
    assert is_watertight(solid.vertices, solid.triangles)
    how, _, _, _, closed = closed_solid(blocks, [a, b], ends, 0.0)
    assert closed and how == "in the frame of support 0"


def test_blocks_meshed_from_the_raster_keep_their_roof_planes():
    """The raster fallback meshes the blocks' own faces (before flattening them): an L of
    a shed and a gable keeps both roofs' heights at the cells' corners, hand-computed,
    and closes."""
    a = Support(box(0, 6, 12, 12), Frame(0.0, (0.0, 0.0), (0.0, 12.0, 6.0, 12.0)))
    b = Support(box(7, 0, 12, 6), Frame(0.0, (0.0, 0.0), (7.0, 12.0, 0.0, 6.0)))
    shed = Block("shed", 1, True, (10.0, 13.0))  # along v: low (10 m) at u = 12, 13 at u = 0
    gable = Block("gable", 1, False, (9.0, 11.0))  # ridge along v at u = 9.5
    ends = [FREE, (False, False, False, True)]
    faces = [block_faces(x, s, e) for x, s, e in zip([shed, gable], [a, b], ends, strict=True)]
    mesh = raster_solid(faces, 0.0, Grid(-1.0, 13.0, 0.5, 30, 28))
    assert is_watertight(mesh.vertices, mesh.triangles)
    roof = mesh.vertices[np.unique(mesh.triangles[mesh.part == 0])]
    x, y, z = roof.T
    on_shed = y > 6.0 + 1e-6
    assert np.allclose(z[on_shed], 13.0 - 3.0 * x[on_shed] / 12.0, atol=1e-6)
    on_gable = (y < 6.0 - 1e-6) & (z < 10.9)  # below the shed's lowest: the gable's own
    assert np.allclose(z[on_gable], 11.0 - 2.0 * np.abs(x[on_gable] - 9.5) / 2.5, atol=1e-6)
    assert z.max() == pytest.approx(13.0) and z.min() == pytest.approx(9.0)


def test_a_tower_whose_tiers_cross_at_slivers_closes():
    """A tower of the 1 km² city (seed 0, building 559 of the block path): a courtyard of
    four supports at 55.74 m and a tier at 63.33 m turned 1.2 degrees from them, their
    edges crossing a few centimetres apart. Their envelope is not a manifold in any
    support's frame, even flat, until the planes' crossings snapped to the faces' corners
    and the arrangement kept its smallest cells; on the cells of the building's grid it
    closes too (the last resort, :func:`raster_solid`)."""
    ring = Frame(0.006724343477883373, (182.26714754098361, -314.67370491803285), (0, 0, 0, 0))
    tier = Frame(-0.014704651853685963, (179.2262108262108, -314.6119658119659), (0, 0, 0, 0))
    corners = [
        [(191.80355, -323.12233), (191.77618, -319.05241), (170.79102, -319.19352),
         (170.81839, -323.26344)],
        [(191.71545, -310.02074), (191.68805, -305.94534), (170.70289, -306.08645),
         (170.73029, -310.16185)],
        [(173.79096, -319.17335), (173.73022, -310.14168), (170.73029, -310.16185),
         (170.79102, -319.19352)],
        [(191.77618, -319.05241), (191.71545, -310.02074), (185.48385, -310.06264),
         (185.54458, -319.09431)],
        [(185.49494, -319.22329), (185.62818, -310.16291), (172.90664, -309.97583),
         (172.7734, -319.03622)],
    ]  # fmt: skip
    supports = []
    for k, c in enumerate(corners):
        f = ring if k < 4 else tier
        u, v = f.to_frame(np.array([x for x, _ in c]), np.array([y for _, y in c]))
        frame = Frame(f.theta, f.origin, (u.min(), u.max(), v.min(), v.max()))
        supports.append(Support(Polygon(c), frame, 1 if k < 4 else 2))
    heights = [55.7398, 55.7371, 55.7475, 55.7371, 63.3277]
    blocks = [Block("flat", 0, False, (h,)) for h in heights]
    ends = [FREE, FREE, (False, True, False, True), (False, True, False, True), FREE]
    how, _, _, solid, closed = closed_solid(blocks, supports, ends, 23.16)
    assert closed and how == "in the frame of support 0"
    faces = [block_faces(b, s, e) for b, s, e in zip(blocks, supports, ends, strict=True)]
    raster = raster_solid(faces, 23.16, Grid(168.0, -303.0, 0.25, 100, 86))
    for mesh in (solid, raster):
        assert is_watertight(mesh.vertices, mesh.triangles)
        # the tier stands on the courtyard: its roof is the highest, the ring's the lowest
        roof = mesh.vertices[np.unique(mesh.triangles[mesh.part == 0])]
        assert roof[:, 2].max() == pytest.approx(63.3277)
        assert roof[:, 2].min() == pytest.approx(55.7371)


def test_a_gap_narrower_than_a_support_is_filled_not_a_slot():
    """A 16 m x 12 m building whose supports (a podium's south part at 10 m, a tower at
    20 m) leave a 0.8 m strip between them, narrower than ``min_part_m`` (3 m) allows a
    support: the blocks' envelope goes down to the ground there, a slot through the
    building. :func:`gap_supports` makes the strip a support of its own, which a flat
    block closes. A 4 m gap (a courtyard a support fits) and a strip off the building's
    cells (an alley) are not filled."""
    grid = Grid(-10.0, 8.0, 0.25, 80, 64)
    X, Y = grid.cell_centers()
    mask = (np.abs(X) < 8) & (np.abs(Y) < 6)
    south, tower = box(-8, -6, 8, -2), box(-8, -1.2, 8, 6)
    supports = [Support(p, rectangle_frame(p), 1) for p in (south, tower)]
    gaps = gap_supports(supports, mask, grid, 3.0)
    assert len(gaps) == 1 and gaps[0].polygon.symmetric_difference(box(-8, -2, 8, -1.2)).area < 1e-6
    assert not gap_supports(supports, mask & ~((Y > -2) & (Y < -1.2)), grid, 3.0)
    wide = [Support(p, rectangle_frame(p), 1) for p in (box(-8, -6, -2, 6), box(2, -6, 8, 6))]
    assert not gap_supports(wide, mask, grid, 3.0)
    # a 0.8 m ring round a tower's support, inside the podium's: two pieces without holes
    podium = (box(-8, -6, 8, -3.8), box(-8, 3.8, 8, 6), box(-8, -3.8, -4.8, 3.8),
              box(4.8, -3.8, 8, 3.8))  # fmt: skip
    ring = [Support(p, rectangle_frame(p), 1) for p in (box(-4, -3, 4, 3), *podium)]
    outer = box(-4.8, -3.8, 4.8, 3.8).difference(box(-4, -3, 4, 3))
    ring_gaps = gap_supports(ring, mask, grid, 3.0)
    assert len(ring_gaps) == 2 and not any(g.polygon.interiors for g in ring_gaps)
    assert unary_union([g.polygon for g in ring_gaps]).symmetric_difference(outer).area < 1e-6
    blocks = [Block("flat", 0, False, (10.0,)), Block("flat", 0, False, (20.0,))]
    covered = []
    for extra, more in (([], []), (gaps, [Block("flat", 0, False, (15.0,))])):
        _, _, _, solid, closed = closed_solid(blocks + more, supports + extra,
                                              [FREE] * (2 + len(extra)), 0.0)  # fmt: skip
        assert closed
        ids, top, _ = TopDown(solid.vertices, solid.triangles, np.ones(len(solid.triangles)),
                              grid).window(slice(0, grid.height), slice(0, grid.width))  # fmt: skip
        covered.append((ids > 0)[mask].mean())
    strip = mask & (Y > -1.9) & (Y < -1.3)
    assert covered[0] == pytest.approx(1 - strip.sum() / mask.sum(), abs=0.01)  # the slot
    assert covered[1] == 1.0 and np.allclose(top[strip], 15.0)


def test_a_sliver_between_supports_over_cell_centres_is_a_gap():
    """Two supports cut from different priors a hair apart: a 0.15 m sliver over a row
    of cell centres is a slot on the grid, and a gap support of its own; a 0.05 m one
    between two rows of centres is left (measured before: both left, so the row was
    the ground)."""
    grid = Grid(-10.0, 8.0, 0.25, 80, 64)
    X, Y = grid.cell_centers()
    mask = (np.abs(X) < 8) & (np.abs(Y) < 6)
    for top_edge, found in ((-0.85, True), (-0.95, False)):  # centres at y = -0.875
        pair = [Support(p, rectangle_frame(p), 1)
                for p in (box(-8, -6, 8, -1.0), box(-8, top_edge, 8, 6))]  # fmt: skip
        gaps = gap_supports(pair, mask, grid, 3.0)
        assert bool(gaps) == found
        if found:
            assert gaps[0].polygon.symmetric_difference(box(-8, -1.0, 8, top_edge)).area < 1e-6
            assert rasterize_on(gaps[0].polygon, grid).sum() == 64


def test_flat_fallback_is_the_roofs_median():
    """The last mesh attempt's block: flat at the median of the roof over its support."""
    support = Support(box(0, 0, 10, 6), FRAME)
    flat = flat_block(Block("gable", 0, False, (10.0, 13.0)), support, FREE)
    assert flat.form == "flat" and flat.params[0] == pytest.approx(11.5, abs=0.08)


def test_supports_from_a_file_are_checked():
    grid = Grid.from_bounds(0.0, 0.0, 50.0, 50.0, 0.25)
    ok = [box(1, 1, 10, 10), box(10, 1, 20, 10), box(30, 30, 40, 40)]
    buildings = supports_from_file("s.geojson", ok, grid)
    assert sorted(len(b) for b in buildings) == [1, 2]  # touching supports: one building
    with pytest.raises(InputError, match=r"features\[1\]: overlaps features\[0\]"):
        supports_from_file("s.geojson", [box(1, 1, 10, 10), box(5, 1, 20, 10)], grid)
    pentagon = Polygon([(1, 1), (10, 1), (12, 5), (10, 10), (1, 10)])
    with pytest.raises(InputError, match=r"features\[0\]: a polygon of 5 corners"):
        supports_from_file("s.geojson", [pentagon], grid)
    with pytest.raises(InputError, match=r"features\[0\]: outside the fusion's grid"):
        supports_from_file("s.geojson", [box(45, 45, 60, 60)], grid)


def test_height_regions_split_tiers_and_mark_small_levels():
    """A tower (30 m) on a podium (20 m) at 0.25 m cells: the podium's wide side and the
    tower are regions of their own; the podium's 1 m strip along the tower's other side
    (120 cells off the wall's two step cells, over ``min_cells``, but narrower than a
    support of 3 m, ``min_width``) is a lower tier: it joins no region, and is marked
    off-level with the steps, so that no tower block fits it. With
    ``tiers=False``, or when the strip slopes at 70 degrees (a mansard's lower slope, one
    block's roof) with fewer than ``min_cells``, it joins the nearest region, the tower,
    for the outline."""
    dsm = np.full((40, 60), 20.0)
    dsm[:, 20:56] = 30.0  # the tower: the podium is 5 m wide west of it, 1 m east
    mask = np.ones(dsm.shape, bool)
    regions, off, tiers = height_regions(mask, dsm, 0.25, 1.5, 100, min_width=12)
    assert regions.max() == 2
    tower, podium = regions[20, 40], regions[20, 5]
    assert tower != podium and tower > 0 and podium > 0
    strip = np.zeros(dsm.shape, bool)
    strip[:, 57:] = True  # clear of the steps: the podium's strip east of the tower
    assert (regions[strip] == 0).all() and off[strip].all() and (tiers == strip).all()
    assert (regions[:, 56] == 0).all()  # the wall's step cell nearer the strip
    assert not off[20, 5] and not off[20, 40]  # a level's own cells are scored
    assert off[20, 19] and off[20, 20]  # the wall: steps on both of its sides
    assert not off[20, 18] and not off[20, 21]  # and no further
    joined, off_joined, none = height_regions(mask, dsm, 0.25, 1.5, 100, False, 12)
    assert (joined[strip] == tower).all() and (off_joined == off).all() and not none.any()
    dsm[:, 57:] = 20.0 + np.tan(np.radians(70.0)) * 0.25 * np.arange(3)
    regions, off, tiers = height_regions(mask, dsm, 0.25, 1.5, 160, min_width=12)
    assert (regions[strip] == tower).all() and off[strip].all() and not tiers.any()
    # with min_cells of it, a narrow level that is no lower tier is a region of its own
    # (an AHN3 house's pitched annex under 3 m wide, cloud 30, had its own block before the
    # narrow levels were tried as tiers, and keeps it)
    regions, off, tiers = height_regions(mask, dsm, 0.25, 1.5, 100, min_width=12)
    assert regions.max() == 3 and (regions[strip] == 3).all() and not off[strip].any()


def test_a_crown_over_a_corner_leaves_the_support_its_corner():
    """A flat roof of 12 m x 10 m at 20 m whose north-east corner a taller crown of 5 m
    radius hides (its cells the class map's tree, at 25 m): without them the building's
    cells are an L and the supports leave the corner out; with them hidden from the
    priors (``crowns_over_the_edge``) one support covers the whole roof."""
    grid = Grid(-10.0, 10.0, 0.25, 80, 80)
    X, Y = grid.cell_centers()
    roof = (np.abs(X) < 6) & (np.abs(Y) < 5)
    crown = (X - 6) ** 2 + (Y - 5) ** 2 < 5.0**2
    mask = roof & ~crown
    dsm = np.where(crown, 25.0, np.where(roof, 20.0, 0.0))
    xs, ys = X[0], Y[:, 0]
    hidden = crowns_over_the_edge(mask, crown, dsm, grid.gsd)
    assert (hidden == crown & ~mask).all()
    for given, area in ((None, 120.0 - 0.25 * np.pi * 5.0**2), (hidden, 120.0)):
        found = automatic_supports(mask, dsm, xs, ys, grid, 3.0, 160, 1.5, np.zeros_like(dsm),
                                   given)  # fmt: skip
        covered = unary_union([s.polygon for s in found.supports]).area
        assert abs(covered - area) < 4.0, (given is None, covered)


def _podium_and_tower():
    """A podium of 12 m x 10 m at 20 m round a tower of 9 m x 8 m at 30 m (a ring 2 m
    wide on the west, 1 m elsewhere), heights with 3 cm of noise: grid, cell centres,
    the podium's cells and the DSM."""
    grid = Grid(-10.0, 8.0, 0.25, 80, 64)
    X, Y = grid.cell_centers()
    podium = (np.abs(X) < 6) & (np.abs(Y) < 5)
    tower = (X > -4) & (X < 5) & (np.abs(Y) < 4)
    noise = np.random.default_rng(0).normal(0, 0.03, X.shape)
    dsm = np.where(tower, 30.0, np.where(podium, 20.0, 0.0)) + noise
    return grid, X, Y, podium, dsm


def test_a_lower_tier_narrower_than_a_support_keeps_its_level():
    """A podium of 12 m x 10 m at 20 m round a tower of 9 m x 8 m at 30 m: the podium is
    a ring 2 m wide on the west, 1 m elsewhere, narrower than a support (``min_part_m``,
    3 m), and once its steps are out its west side is a level too small for a region
    (156 cells, under 160). It used to join the tower's region, whose block then covered
    it at 30 m (dev seed 9 of the sample city: three multi-level buildings, 0.64 of its
    squared error off the jumps). Now it is a flat tier at 20 m, and so are the 1 m
    sides, whose two cells clear of the wall's step cells are their own level (before,
    every cell within 0.5 m of the wall on both sides was a step, and they went with the
    tower at 30 m)."""
    grid, X, Y, podium, dsm = _podium_and_tower()
    boxes = np.array([[0, 0, 0, 0], [0, grid.height, 0, grid.width]])
    inputs = BlocksInputs(grid, dsm, np.zeros(X.shape), None, boxes, podium.astype(np.int32))
    building = building_task(1, inputs, BlocksOptions(iterations=2000)).building
    tiers = [s["block"]["params"]["h_gutter"] for s in building.record["supports"] if s.get("tier")]
    assert tiers and np.allclose(tiers, 20.0, atol=0.05)
    assert building.footprint.area == pytest.approx(120.0, abs=2.0)
    mesh = building.mesh
    ids, top, _ = TopDown(mesh.vertices, mesh.triangles, np.ones(len(mesh.triangles)),
                          grid).window(slice(0, grid.height), slice(0, grid.width))  # fmt: skip
    west = (X > -5.5) & (X < -4.5) & (np.abs(Y) < 4.5)  # the tier clear of its walls
    assert (ids[west] > 0).all() and np.allclose(top[west], 20.0, atol=0.05)
    east = (X > 5.25) & (X < 5.75) & (np.abs(Y) < 3.5)  # the 1 m side's middle
    assert (ids[east] > 0).all() and np.allclose(top[east], 20.0, atol=0.05)
    assert np.allclose(top[(X > -3.5) & (X < 4.5) & (np.abs(Y) < 3.5)], 30.0, atol=0.05)


def test_a_tier_over_unknown_ground_is_a_tier():
    """The podium and tower above: the west ring's flat level is a tier where it stands
    more than a step above the DTM, and where the DTM is unknown there (no view saw the
    ground beside it: dev seed 13's hidden ring east of a tower, 0.41 of its squared
    error, modelled as the ground), but not where the DTM is within a step of it (the
    ground the outline took in)."""
    grid, X, Y, podium, dsm = _podium_and_tower()
    xs, ys = X[0], Y[:, 0]
    ring = podium & ~((X > -4) & (X < 5) & (np.abs(Y) < 4))
    for ground, tier in ((0.0, True), (np.nan, True), (19.0, False)):
        dtm = np.where(ring, ground, 0.0)
        found = automatic_supports(podium, dsm, xs, ys, grid, 3.0, 160, 1.5, dtm)
        assert bool(found.tiers) == tier, ground


def _three_levels():
    """A podium of 16 m x 14 m at 20 m, a middle tier of 9 m x 7 m at 30 m, a tower of
    5 m x 5 m at 40 m, heights with 3 cm of noise: grid, cell centres, the three parts'
    cells and the DSM."""
    grid = Grid(-10.0, 9.0, 0.25, 80, 72)
    X, Y = grid.cell_centers()
    podium = (np.abs(X) < 8) & (np.abs(Y) < 7)
    middle = (np.abs(X) < 4.5) & (np.abs(Y) < 3.5)
    tower = (np.abs(X) < 2.5) & (np.abs(Y) < 2.5)
    noise = np.random.default_rng(0).normal(0, 0.03, X.shape)
    dsm = np.where(tower, 40.0, np.where(middle, 30.0, np.where(podium, 20.0, 0.0))) + noise
    return grid, X, Y, podium, middle, tower, dsm


def test_a_middle_tier_between_a_podium_and_a_tower_keeps_its_level():
    """Three levels: a podium of 16 m x 14 m at 20 m, a middle tier of 9 m x 7 m at 30 m,
    a tower of 5 m x 5 m at 40 m. The podium's ring (3.5 m wide) is a region whose
    courtyard prior reaches under the middle tier; the middle tier's ring (2 m wide east
    and west, 1 m north and south) is too small for a region. Its piece is cut from the
    outline of the part above the podium, and its block stands on the podium's in the
    envelope (measured before: the ring split between the podium's 20 m and the tower's
    40 m)."""
    grid, X, Y, podium, middle, tower, dsm = _three_levels()
    boxes = np.array([[0, 0, 0, 0], [0, grid.height, 0, grid.width]])
    inputs = BlocksInputs(grid, dsm, np.zeros(X.shape), None, boxes, podium.astype(np.int32))
    building = building_task(1, inputs, BlocksOptions(iterations=2000)).building
    tiers = [s["block"]["params"]["h_gutter"] for s in building.record["supports"] if s.get("tier")]
    assert tiers and np.allclose(tiers, 30.0, atol=0.05)
    mesh = building.mesh
    _, top, _ = TopDown(mesh.vertices, mesh.triangles, np.ones(len(mesh.triangles)),
                        grid).window(slice(0, grid.height), slice(0, grid.width))  # fmt: skip
    ring = (np.abs(X) > 3) & (np.abs(X) < 4) & (np.abs(Y) < 3)  # clear of its walls
    assert np.allclose(top[ring], 30.0, atol=0.05)
    assert np.allclose(top[(np.abs(X) < 2) & (np.abs(Y) < 2)], 40.0, atol=0.05)
    assert np.allclose(top[podium & ((np.abs(X) > 5) | (np.abs(Y) > 4))
                           & (np.abs(X) < 7.5) & (np.abs(Y) < 6.5)], 20.0, atol=0.05)  # fmt: skip


def test_a_middle_tier_partly_hidden_keeps_its_rectangle():
    """The three levels above, with the cells south-east of the tower hidden from every
    view (the middle tier's south-east corner and the podium beyond: no DSM, no DTM,
    under the ceiling of the rays past the tower's edge). They take the lowest level
    around, the podium's; the middle tier's seen cells are an L. Its rectangle prior
    neither pays for covering the hidden cells nor for leaving them out, so it is the
    tier's whole rectangle: its south ring, seen in the west only, stays at 30 m across
    (measured before: the podium's 20 m there; dev seeds 9 and 11 of the sample city,
    whose hidden middle-tier corners carried 0.39 and 0.62 of their squared error)."""
    grid, X, Y, podium, middle, tower, dsm = _three_levels()
    hidden = (X > 0) & (Y < -1) & (Y > -7.5) & ~tower
    dsm[hidden] = np.nan
    dtm = np.where(hidden, np.nan, 0.0)
    ceiling = np.where(hidden, 44.0 + 4.0 * np.minimum(Y + 2.5, 0.0), np.nan)
    boxes = np.array([[0, 0, 0, 0], [0, grid.height, 0, grid.width]])
    segments = (podium & ~hidden).astype(np.int32)
    inputs = BlocksInputs(grid, dsm, dtm, None, boxes, segments, ceiling=ceiling)
    mesh = building_task(1, inputs, BlocksOptions(iterations=2000)).building.mesh
    _, top, _ = TopDown(mesh.vertices, mesh.triangles, np.ones(len(mesh.triangles)),
                        grid).window(slice(0, grid.height), slice(0, grid.width))  # fmt: skip
    south_ring = (np.abs(X) < 4.25) & (Y > -3.25) & (Y < -3.0)  # clear of its walls
    east_corner = (X > 2.75) & (X < 4.25) & (Y > -2.25) & (Y < -1.0)  # hidden
    assert np.allclose(top[south_ring | east_corner], 30.0, atol=0.05)
    assert np.allclose(top[podium & hidden & (np.maximum(np.abs(X) - 5, np.abs(Y) - 4) > 0)
                           & (np.abs(X) < 7.5) & (np.abs(Y) < 6.5)], 20.0, atol=0.05)  # fmt: skip


def test_parameter_ranges_keep_hips_hips():
    """A hip end is at most twice as steep as the sides (shorter is a shaved gable end)."""
    r = parameter_ranges("hipped", 12.0, 8.0, 10.0, 20.0)
    assert r[2].tolist() == [2.0, 6.0]


@pytest.fixture(scope="module")
def blocks_run(tiny_models):
    return tiny_models("blocks")


def test_blocks_end_to_end_from_fused_rasters(blocks_run):
    """From `workbench fusion` of tiny, as a user runs it (measured: 2D quality 0.909,
    3D 0.886, roof types 4 of 6, mean height error 0.19 %, every mesh closed). The two
    wrong have a lower energy than the true forms: the mansard comes out a pyramid on its
    shallow top, the hipped roof of two supports a mansard whose 45-degree lower slopes
    fit its DSM better (before the zero-temperature sweep: 5 of 6, that roof a gable)."""
    out, model, metrics = blocks_run
    assert metrics["footprint_2d"]["quality"] > 0.90
    assert metrics["volume_3d"]["quality"] > 0.87
    assert metrics["buildings"]["missed_over_50m2"] == 0
    assert metrics["buildings"]["roof_type_accuracy"] >= 4 / 6
    assert metrics["buildings"]["height_error_pct_mean"] < 0.4
    assert metrics["complexity"]["watertight_fraction"] == 1.0
    b = model["buildings"][0]
    assert b["energy_trace"][-1][2] < b["energy_trace"][0][2]
    assert set(b["acceptance_rate"]) == {"uniform", "data-driven", "regularisation"}
    assert len(b["face_blocks"]) == b["faces"]
    assert all(s["block"]["form"] for s in b["supports"])
    assert b["zero_temperature"]["evaluations"] > 0
    assert model["iterations_per_second"] > 0


def test_blocks_summary_counts_the_forms_the_sweep_changed(blocks_run):
    """The command's summary: the blocks per form, how many the zero-temperature sweep
    changed and the lower tiers and gaps filled flat, from model.json's buildings."""
    _, model, _ = blocks_run
    lines = summary_lines(model, model["buildings"])
    switched = sum(b["zero_temperature"]["forms_switched"] for b in model["buildings"])
    supports = [s for b in model["buildings"] for s in b["supports"]]
    flat = sum(bool(s.get("gap")) for s in supports)
    tiers = sum(bool(s.get("tier")) for s in supports)
    assert f"{len(supports) - flat} blocks" in lines[0]
    assert (f"({switched} changed form at zero temperature); flat: {tiers} lower tiers and "
            f"{flat - tiers} gaps") in lines[1]  # fmt: skip


def test_blocks_from_given_supports(blocks_run, tiny_fusion, tmp_path):
    """--supports: the automatic run's supports written as a GeoJSON give back one
    building per group of touching supports, every one closed."""
    out, model, _ = blocks_run
    rings = [s["polygon_m"] + s["polygon_m"][:1] for b in model["buildings"] for s in b["supports"]]
    features = [{"type": "Feature", "properties": {},
                 "geometry": {"type": "Polygon", "coordinates": [r]}} for r in rings]  # fmt: skip
    path = tmp_path / "supports.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    proc = run_cli("model", "blocks", tiny_fusion, "--supports", path, "-o", tmp_path / "m")
    assert proc.returncode == 0, proc.stderr
    again = json.loads((tmp_path / "m" / "model.json").read_text())
    assert len(again["buildings"]) == len(model["buildings"])
    assert all(b["watertight"] for b in again["buildings"])
    # in 4 blocks, each group given to one: the same buildings, none twice
    proc = run_cli("model", "blocks", tiny_fusion, "--supports", path, "-o", tmp_path / "b",
                   "--block", 32, "--block-margin", 12, "--workers", 1)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    blocked = json.loads((tmp_path / "b" / "model.json").read_text())
    assert blocked["blocks"]["count"] == 4
    assert sorted(len(b["supports"]) for b in blocked["buildings"]) == sorted(
        len(b["supports"]) for b in again["buildings"]
    )


def test_blocks_bad_input_is_one_line(tiny_fusion, tmp_path):
    """A missing fusion folder, supports far off the grid, a class map on another grid
    (it says where the crowns are): one line, exit 2, no output."""
    far = tmp_path / "far.geojson"
    square = [[[1e6, 1e6], [1e6 + 9, 1e6], [1e6 + 9, 1e6 + 9], [1e6, 1e6 + 9], [1e6, 1e6]]]
    far.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon",
                                                          "coordinates": square}}]}))  # fmt: skip
    shifted = tmp_path / "shifted"  # a class map on another grid than the other rasters
    shutil.copytree(tiny_fusion, shifted)
    with rasterio.open(tiny_fusion / "class.tif") as src:
        profile, classes = src.profile, src.read()
    profile["transform"] = profile["transform"] @ Affine.translation(3, 0)
    with rasterio.open(shifted / "class.tif", "w", **profile) as dst:
        dst.write(classes)
    for args, says in (((tmp_path / "nowhere",), "no such fusion folder"),
                       ((tiny_fusion, "--supports", far), "far.geojson"),
                       ((shifted,), "class.tif")):  # fmt: skip
        proc = run_cli("model", "blocks", *args, "-o", tmp_path / "o")
        assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert says in proc.stderr
        assert not (tmp_path / "o").exists()


def test_unseen_rim_filled_by_hand():
    """Unknown cells within the reach take their nearest known cell's value; farther
    ones stay unknown."""
    row = np.array([[10.0, 10.0, np.nan, np.nan, np.nan, 0.0]])
    (filled,) = unseen_rim_filled([row], np.isfinite(row), 1)
    assert np.array_equal(filled, [[10.0, 10.0, 10.0, np.nan, 0.0, 0.0]], equal_nan=True)
    (same,) = unseen_rim_filled([row], np.isfinite(row), 0)
    assert np.array_equal(same, row, equal_nan=True)


def _turned(angle_deg: float, n: int = 160, gsd: float = 0.25):
    """(u, v) metres of the cells of an n x n grid of ``gsd`` in a frame turned by
    ``angle_deg`` about its centre."""
    c = (np.arange(n) + 0.5 - n / 2) * gsd
    X, Y = np.meshgrid(c, -c)
    t = np.radians(angle_deg)
    return X * np.cos(t) + Y * np.sin(t), -X * np.sin(t) + Y * np.cos(t)


@pytest.mark.parametrize("angle", [0.0, 30.0, 45.0])
def test_unseen_between_fills_a_notch_not_a_corner_or_a_courtyard(angle):
    """A 24 m x 12 m roof at 10 m whose south side has an 8 m x 4 m notch no view saw
    (and the ground beyond it): the notch, between the roof's known sides, is filled at
    the roof's height. Hidden ground in an L's inner corner (the building on one side
    only) and a hidden strip of a U's courtyard beside ground the views saw are not
    (but for a few cells where a turned grid's staircase meets the corner)."""
    u, v = _turned(angle)
    zero = np.zeros(u.shape)
    rect = (np.abs(u) < 12) & (np.abs(v) < 6)
    notch = (np.abs(u) < 4) & (v > -9) & (v < -2)
    dsm = np.where(rect, 10.0, 0.0)
    dsm[notch] = np.nan
    inside = unseen_between(rect & ~notch, dsm, zero)
    filled = nearest_of(dsm, rect & ~notch, inside)
    assert (inside & rect).sum() == (notch & rect).sum()  # measured: all of it
    assert (inside & ~rect).sum() <= 0.07 * (notch & rect).sum()  # measured 0, 31, 0 cells
    assert np.all(filled[inside] == 10.0) and np.isnan(filled[notch & ~inside]).all()
    ell = ((np.abs(v - 6) < 3) & (np.abs(u) < 12)) | ((np.abs(u + 9) < 3) & (np.abs(v) < 9))
    corner = ~ell & (u > -6) & (u < 0) & (v < 3) & (v > -6)
    dsm = np.where(ell, 10.0, 0.0)
    dsm[corner] = np.nan
    inside = unseen_between(ell, dsm, zero)
    assert inside.sum() <= 0.08 * corner.sum()  # measured 0, 60, 41 of 864, 865, 833
    arms = ((np.abs(u + 9) < 3) | (np.abs(u - 9) < 3)) & (np.abs(v) < 9)
    u_shape = arms | ((v < -6) & (v > -9) & (np.abs(u) < 12))
    strip = ~u_shape & (u > 3) & (u < 6) & (v > -6) & (v < 9)
    dsm = np.where(u_shape, 10.0, 0.0)
    dsm[strip] = np.nan
    inside = unseen_between(u_shape, dsm, zero)
    assert not inside.any()


def test_unseen_between_leaves_an_alley_the_ground_closes_at_both_ends():
    """Two roofs of one region, at 20 m and 10 m, with a strip 8 cells wide and 120 long
    between them that no view saw but at its two ends, where the views saw the ground:
    a passage between two buildings, not a hidden part (``small`` seed 0's tower and its
    neighbour to the south on the mesh; its ends under a tenth of its ring). Closed at
    one end by a third part of the region, the same strip is a hidden part, taken in."""
    dsm = np.zeros((50, 140))
    dsm[5:25, 10:130] = 20.0
    dsm[33:45, 10:130] = 10.0
    dsm[25:33, 10:130] = np.nan
    zero = np.zeros(dsm.shape)
    alley = np.isnan(dsm)
    assert not unseen_between(dsm > 5.0, dsm, zero).any()
    dsm[5:45, 130:136] = 15.0  # the region's third part across the east end
    inside = unseen_between(dsm > 5.0, dsm, zero)
    np.testing.assert_array_equal(inside, alley)


def test_a_hidden_part_takes_the_lowest_level_around_it():
    """Hidden cells between an upper tier at 20 m (north) and the lower tier's known
    ends at 10 m (east and west) take 10 m, all of them (the nearest cell's height
    would give the upper rows 20 m); hidden cells with only the upper tier within two
    cells take 20 m; nothing else changes."""
    heights = np.full((12, 12), np.nan)
    heights[:4, :] = 20.0
    heights[4:8, :3] = heights[4:8, 9:] = 10.0
    hidden = np.zeros((12, 12), bool)
    hidden[4:8, 3:9] = True
    out = lowest_around(heights, np.isfinite(heights), hidden)
    assert (out[hidden] == 10.0).all()
    np.testing.assert_array_equal(out[~hidden], heights[~hidden])
    assert (nearest_of(heights, np.isfinite(heights), hidden)[4, 3:9] == 20.0).any()
    heights[4:8, 9:] = np.nan
    hidden[:] = False
    hidden[4:6, 6:10] = True  # the lower tier's cells 4 columns away
    out = lowest_around(heights, np.isfinite(heights), hidden)
    assert (out[hidden] == 20.0).all()


def test_a_roof_notch_no_view_saw_is_modelled():
    """A flat roof of 12 m x 8 m at 10 m whose south side hides an 8 m x 4 m notch from
    every view, with the ground beyond it (a taller part hides a lower tier from views
    that all stand on one side): the building class covers the known roof only, and
    the model covers the whole rectangle, not an outline with a bite out of it
    (measured without :func:`unseen_between`: 74.8 m², three supports)."""
    grid = Grid(-10.0, 8.0, 0.25, 80, 64)
    xs = grid.xmin + (np.arange(grid.width) + 0.5) * grid.gsd
    ys = grid.ymax - (np.arange(grid.height) + 0.5) * grid.gsd
    X, Y = np.meshgrid(xs, ys)
    roof = (np.abs(X) < 6.0) & (np.abs(Y) < 4.0)
    dsm = np.where(roof, 10.0, 0.0) + np.random.default_rng(0).normal(0, 0.03, X.shape)
    dsm[(np.abs(X) < 4.0) & (Y < 0.0) & (Y > -6.0)] = np.nan
    dtm = np.where(np.isfinite(dsm), 0.0, np.nan)
    segments = (roof & np.isfinite(dsm)).astype(np.int32)
    boxes = np.array([[0, 0, 0, 0], [0, grid.height, 0, grid.width]])
    inputs = BlocksInputs(grid, dsm, dtm, None, boxes, segments)
    found = building_task(1, inputs, BlocksOptions(iterations=2000)).building
    # measured 97.1 m²; the known roof alone is 64 m²
    assert abs(found.footprint.area - 96.0) < 1.5


def _tower_with_a_hidden_tier():
    """A 12 m x 10 m building: a 20 m tower (x -6 to 2 m, y -4 to 4 m) and a 10 m tier
    round its north and east sides (2 m and 4 m wide). Every view looks from the west
    and north: the tier's east part is hidden behind the tower, and so is the ground
    2 m beyond it and south of the building. The fusion's ceiling over the hidden tier
    is the rays past the tower's edge (28 - x m, above the tier); over the ground
    beyond, 5 m: the rays that saw the ground further out passed lower."""
    grid = Grid(-10.0, 10.0, 0.25, 96, 80)
    X, Y = grid.cell_centers()
    tower = (X > -6) & (X < 2) & (np.abs(Y) < 4)
    building = (np.abs(X) < 6) & (Y > -4) & (Y < 6)
    dsm = np.where(tower, 20.0, np.where(building, 10.0, 0.0))
    dsm += np.random.default_rng(0).normal(0, 0.03, X.shape)
    tier = building & ~tower & (Y < 4)
    beyond = ((X > 6) & (X < 8) & (Y > -6) & (Y < 4)) | ((np.abs(X) < 8) & (Y > -6) & (Y < -4))
    dsm[tier | beyond] = np.nan
    ceiling = np.full(X.shape, np.nan)
    ceiling[tier] = 28.0 - X[tier]
    ceiling[beyond] = 5.0
    dtm = np.where(np.isfinite(dsm), 0.0, np.nan)
    return grid, building, tier, beyond, dsm, dtm, ceiling


def test_a_hidden_part_is_kept_where_its_level_fits_under_the_ceiling():
    """The hidden tier along the tower's outer side has the building on one side only:
    :func:`unseen_between` leaves it out. With the ceiling, the unknown cells within the
    building's rectangle, and up to a metre past it, are candidates; at the tier's level
    (10 m, the lowest around) the tier fits under its ceiling and the ground beyond does
    not. Nor would the tier under a ceiling less than the margin above its level; a roof
    whose rim alone is unknown gets no skirt from the reach."""
    grid, building, tier, beyond, dsm, dtm, ceiling = _tower_with_a_hidden_tier()
    region = building & np.isfinite(dsm)
    assert not (unseen_between(region, dsm, dtm) & tier).any()
    hidden = unseen_parts(region, dsm, dtm, ceiling, reach=4)
    X, Y = grid.cell_centers()
    assert (hidden == (tier | (beyond & (X > -7) & (X < 7) & (Y > -5)))).all()
    levels = lowest_around(dsm, region, hidden)
    np.testing.assert_allclose(levels[hidden], 10.0, atol=0.1)
    assert (under_ceiling(hidden, levels, ceiling, region, 0.5) == tier).all()
    for over, fits in ((0.4, False), (0.6, True)):  # the margin: 0.5 m
        near = np.where(tier, levels + over, ceiling)
        assert (under_ceiling(hidden, levels, near, region, 0.5) == (tier & fits)).all()
    assert (under_ceiling(hidden, levels, None, region, 0.5) == hidden).all()
    roof = (np.abs(X) < 6) & (np.abs(Y) < 4)
    rim = (np.maximum(np.abs(X) - 5.75, np.abs(Y) - 3.75) > 0) & ~roof
    flat = np.where(roof & ~rim, 10.0, np.where(rim, np.nan, 0.0))
    high = np.where(np.isnan(flat), 30.0, np.nan)
    assert not unseen_parts(roof & ~rim, flat, np.zeros(flat.shape), high, reach=4).any()


def test_a_tier_no_view_saw_along_the_outer_side_is_modelled():
    """The building class covers the tower and the tier's known strip: with the ceiling
    the model covers the whole 120 m² (the hidden tier's support, with no cell a view
    saw, fitted to the level it was given), without it the tower and the tier's known
    2 m strip, a flat tier narrower than a support (measured 98 m²: 67 before the
    steps were the wall's two cells alone, when the strip went with the tower)."""
    grid, building, tier, beyond, dsm, dtm, ceiling = _tower_with_a_hidden_tier()
    segments = (building & np.isfinite(dsm)).astype(np.int32)
    boxes = np.array([[0, 0, 0, 0], [0, grid.height, 0, grid.width]])
    areas = []
    for c in (ceiling, None):
        inputs = BlocksInputs(grid, dsm, dtm, None, boxes, segments, ceiling=c)
        areas.append(building_task(1, inputs, BlocksOptions(iterations=2000)).building
                     .footprint.area)  # fmt: skip
    # measured 126.7 and 98.0 m²: the unknown rim's cell (unseen_rim_m) on the north
    # and south sides, where the ground beyond is unknown too; the hidden 32 m² not taken
    assert 118.0 < areas[0] < 129.0 and 88.0 < areas[1] < 100.0


def test_a_roof_whose_rim_no_view_kept_reaches_its_wall():
    """A flat roof of 12 m x 8 m at 10 m whose outer cell and the two ground cells
    beyond it are unknown (a fusion of depth maps: each view drops a jump's ramp, and
    the ground beside the wall is hidden). The building class covers the known roof
    (11.5 m x 7.5 m); with ``unseen_rim_m`` of a cell the outline takes in the rim and
    the model covers the true 96 m², without it 86 m²."""
    grid = Grid(-10.0, 8.0, 0.25, 80, 64)
    xs = grid.xmin + (np.arange(grid.width) + 0.5) * grid.gsd
    ys = grid.ymax - (np.arange(grid.height) + 0.5) * grid.gsd
    X, Y = np.meshgrid(xs, ys)
    out = np.maximum(np.abs(X) - 6.0, np.abs(Y) - 4.0)  # metres outside the walls
    dsm = np.where(out < 0, 10.0, 0.0) + np.random.default_rng(0).normal(0, 0.03, X.shape)
    dsm[(out > -0.25) & (out < 0.5)] = np.nan
    dtm = np.where(np.isfinite(dsm), 0.0, np.nan)
    segments = (out < -0.25).astype(np.int32)
    boxes = np.array([[0, 0, 0, 0], [0, grid.height, 0, grid.width]])
    inputs = BlocksInputs(grid, dsm, dtm, None, boxes, segments)
    areas = {}
    for rim in (0.25, 0.0):
        options = BlocksOptions(iterations=2000, unseen_rim_m=rim)
        areas[rim] = building_task(1, inputs, options).building.footprint.area
    # measured 97.2 and 87.4 m²: the rectangles' fit lies 0.05 m out on every side
    assert abs(areas[0.25] - 96.0) < 1.5 and abs(areas[0.0] - 86.25) < 1.5
