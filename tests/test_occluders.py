"""The occluders a task's rays are cast against: the meshes near enough to hide its
points from a view (modeling/voxel/occluders.py, workbench.camera.steepest_sight)."""

import numpy as np
import pytest
import shapely

from modeling.voxel.inputs import prism, read_inputs
from modeling.voxel.occluders import REACH_MARGIN_M, Occluders
from modeling.voxel.options import VoxelOptions
from workbench.camera import Camera, look_at_rotation, steepest_sight
from workbench.raycast import occluded


def _camera(forward, f=1000.0, size=1001, centre=(0.0, 0.0, 500.0)):
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    R = look_at_rotation(np.asarray(forward, float))
    return Camera(K, R, -R @ np.asarray(centre, float), size, size)


def test_the_steepest_sight_is_to_the_farthest_framing_camera_from_the_top():
    nadir = _camera([0, 0, -1])  # from (0, 0, 500): frames +-250 m of the ground
    box = np.array([100.0, 0.0, 0.0]), np.array([120.0, 10.0, 20.0])
    # the box's far corner (120, 10) from 480 m above its top
    assert steepest_sight([nadir], *box) == pytest.approx(np.hypot(120, 10) / 480)
    # a view 2 km east looking away frames none of it: no sight
    away = _camera([1, 0, -1], centre=(2000.0, 0.0, 500.0))
    assert steepest_sight([nadir, away], *box) == pytest.approx(np.hypot(120, 10) / 480)
    assert steepest_sight([away], *box) == 0.0
    # a view 300 m west, 200 m up, looking at it: flatter
    west = _camera([1, 0, -0.5], centre=(-300.0, 0.0, 200.0))
    assert steepest_sight([nadir, west], *box) == pytest.approx(np.hypot(420, 10) / 180)
    # a camera no higher than the box's top frames it: every mesh
    low = _camera([1, 0, 0], centre=(-300.0, 5.0, 10.0))
    assert steepest_sight([low], *box) == np.inf


def test_a_tower_that_just_hides_a_corner_ray_is_near():
    """A nadir view from 500 m: the ground point at its frame's corner sees it along a
    line of ratio 0.7071; a 50 m tower 34.85 m along it (its top 0.5 m short of the
    line's reach) hides the point, and is near it; a ratio a fifth lower would leave
    it out."""
    cam = _camera([0, 0, -1])
    _, d = cam.pixel_rays(np.array([[0.0, 0.0]]))
    P = cam.center + d[0] * 500.0  # the corner pixel's ground point, z = 0
    toward = -d[0, :2] / np.hypot(*d[0, :2])  # horizontally, toward the camera
    c = P[:2] + toward * (50.0 * np.sqrt(0.5) - 0.5)
    box = np.array([[c[0] - 1, c[1] - 1, c[0] + 1, c[1] + 1]])
    tower = prism(shapely.box(*box[0]), 0.0, 50.0)
    occ = Occluders(["tower"], box, np.array([50.0]), np.zeros(3))
    assert occluded(occ.scene([tower]), P, cam.center - P, tfar=1.0).all()
    lo, hi = P - [0.1, 0.1, 0.0], P + [0.1, 0.1, 0.0]
    assert occ.around([cam], lo, hi).tolist() == [0]
    tangent = steepest_sight([cam], lo, hi)
    assert occ.near((*lo[:2], *hi[:2]), 0.0, 0.8 * tangent).tolist() == []


def test_a_mesh_is_near_when_its_top_can_reach_a_ray_out_of_the_window():
    boxes = np.array([[18.0, 0, 28, 10],  # 8 m east of the window, 10 m high
                      [0.0, 18, 10, 28],  # 8 m north, 5 m high
                      [-30.0, 0, -20, 10],  # 20 m west, 40 m high
                      [0.0, 0, 10, 10]])  # fmt: skip
    tops = np.array([10.0, 5.0, 40.0, 3.0])
    occ = Occluders(list("abcd"), boxes, tops, origin=np.zeros(3))
    window = (0.0, 0.0, 10.0, 10.0)
    # from the ground, sights of ratio 1: reaches 11, 6, 41 and 4 m
    assert occ.near(window, 0.0, 1.0).tolist() == [0, 2, 3]
    # from 4 m up: 7, 2, 37 and 1 m (the window's own mesh, lower, still touches it)
    assert occ.near(window, 4.0, 1.0).tolist() == [2, 3]
    assert REACH_MARGIN_M == 1.0  # the reaches above
    # a camera as low as the points: everything
    assert occ.near(window, 4.0, np.inf).tolist() == [0, 1, 2, 3]


def _near_hides_what_all_hide(occ: Occluders, meshes, cameras, windows, rng):
    """For points in each window ((xmin, ymin, xmax, ymax), z_low, z_high), cast to every
    camera that frames them: the rays the meshes near the window hide are those all of
    them hide. Returns the meshes left out and the rays hidden, summed over windows."""
    everything = occ.scene(meshes)
    left_out, hidden = 0, 0
    for (x0, y0, x1, y1), z0, z1 in windows:
        near = occ.around(cameras, (x0, y0, z0), (x1, y1, z1))
        left_out += len(meshes) - len(near)
        some = occ.scene([meshes[i] for i in near])
        n = 400
        P = np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n),
                             rng.uniform(z0, z1, n)])  # fmt: skip
        for cam in cameras:
            uv, depth = cam.project(P)
            framed = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1)
            framed &= (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
            Q = P[framed]
            a = occluded(everything, Q, cam.center - Q, tfar=1.0)
            b = occluded(some, Q, cam.center - Q, tfar=1.0) if some else np.zeros(len(Q), bool)
            np.testing.assert_array_equal(a, b)
            hidden += int(a.sum())
    return left_out, hidden


def test_the_near_meshes_hide_every_ray_of_oblique_views_all_of_them_hide():
    """Towers of 5-60 m on a 300 m square; views from 500 m, nadir, and tilted 20 and 40
    degrees toward the square's centre from 180 and 420 m off it; windows of 20 m from
    the ground to 40 m: fewer meshes, the same hits."""
    rng = np.random.default_rng(1)
    xy = rng.uniform(-150, 150, (60, 2))
    tops = rng.uniform(5, 60, 60)
    boxes = np.column_stack([xy - 6, xy + 6])
    meshes = [prism(shapely.box(*b), 0.0, t) for b, t in zip(boxes, tops, strict=True)]
    cameras = []
    for tilt in (0, 20, 40):
        for azimuth in (0, 120, 240):
            a, t = np.radians(azimuth), np.radians(tilt)
            look = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)])
            # looking at the square's centre from 500 m up
            cameras.append(_camera(look, f=800.0, centre=-look * 500.0 / np.cos(t)))
    occ = Occluders(list(range(60)), boxes, tops, np.zeros(3))
    corners = rng.uniform(-160, 140, (40, 2))
    windows = [((x, y, x + 20, y + 20), z, z + 10) for (x, y), z in
               zip(corners, rng.choice([0.0, 10.0, 30.0], 40), strict=True)]  # fmt: skip
    left_out, hidden = _near_hides_what_all_hide(occ, meshes, cameras, windows, rng)
    assert left_out >= 2200 and hidden >= 19000  # of 2400 pairs; measured 2247, 19914


def test_the_near_initial_proxies_hide_every_ray_all_of_them_hide(tiny_scene, tiny_fusion):
    """The tiny city's views, its footprints' initial proxies, each footprint and the
    ground around it as windows."""
    inputs = read_inputs(tiny_scene, VoxelOptions(), fusion_dir=tiny_fusion)
    meshes = [prism(f.polygon, base, h) for f, base, h in inputs.buildings]
    windows = []
    for f, base, h in inputs.buildings:
        x0, y0, x1, y1 = f.polygon.bounds
        windows += [((x0, y0, x1, y1), base, base + h + 5.0),
                    ((x0 - 15, y0 - 15, x1 + 15, y1 + 15), base, base + 1.0)]  # fmt: skip
    rng = np.random.default_rng(0)
    left_out, hidden = _near_hides_what_all_hide(inputs.prisms, meshes, inputs.cameras,
                                                 windows, rng)  # fmt: skip
    assert left_out >= 30 and hidden >= 11000  # measured 31 of 144 pairs, 11428
