"""The occluders a task's rays are cast against: the meshes near enough to hide its
points from a view (modeling/voxel/occluders.py, workbench.camera.max_ray_tangent)."""

import numpy as np
import pytest
import shapely

from modeling.voxel.inputs import prism, read_inputs
from modeling.voxel.occluders import REACH_MARGIN_M, Occluders
from modeling.voxel.options import VoxelOptions
from workbench.camera import Camera, look_at_rotation, max_ray_tangent
from workbench.raycast import occluded


def _camera(forward, f=1000.0, size=1001):
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    R = look_at_rotation(np.asarray(forward, float))
    centre = np.array([0.0, 0.0, 500.0])
    return Camera(K, R, -R @ centre, size, size)


def test_the_steepest_ray_of_a_nadir_frame_is_through_its_corner():
    # the corner pixel 2 px outside the frame: 502 px off the axis both ways, f = 1000 px
    assert max_ray_tangent([_camera([0, 0, -1])]) == pytest.approx(np.hypot(502, 502) / 1000)
    # a view tilted 30 degrees: its far corner's ray is flatter than the tilt alone
    tilted = max_ray_tangent([_camera([np.sin(np.pi / 6), 0, -np.cos(np.pi / 6)])])
    assert tilted > np.tan(np.pi / 6 + np.arctan(0.502))
    # a frame that holds the horizon: every mesh can hide every point
    assert max_ray_tangent([_camera([1, 0, -0.2])]) == np.inf


def test_a_tower_that_just_hides_a_corner_ray_is_near():
    """A nadir view from 500 m: the ground point at its frame's corner sees it along a
    ray of tangent 0.7071; a 50 m tower 34.85 m along it (its top 0.5 m short of the
    ray's reach) hides the point, and is near it; a tangent a fifth lower would leave
    it out."""
    cam = _camera([0, 0, -1])
    _, d = cam.pixel_rays(np.array([[0.0, 0.0]]))
    P = cam.center + d[0] * 500.0  # the corner pixel's ground point, z = 0
    toward = -d[0, :2] / np.hypot(*d[0, :2])  # horizontally, toward the camera
    c = P[:2] + toward * (50.0 * np.sqrt(0.5) - 0.5)
    box = np.array([[c[0] - 1, c[1] - 1, c[0] + 1, c[1] + 1]])
    tower = prism(shapely.box(*box[0]), 0.0, 50.0)
    occ = Occluders(["tower"], box, np.array([50.0]), max_ray_tangent([cam]), np.zeros(3))
    assert occluded(occ.scene([tower]), P, cam.center - P, tfar=1.0).all()
    window = (P[0] - 0.1, P[1] - 0.1, P[0] + 0.1, P[1] + 0.1)
    assert occ.near(window, 0.0).tolist() == [0]
    occ.tangent *= 0.8
    assert occ.near(window, 0.0).tolist() == []


def test_a_mesh_is_near_when_its_top_can_reach_a_ray_out_of_the_window():
    boxes = np.array([[18.0, 0, 28, 10],  # 8 m east of the window, 10 m high
                      [0.0, 18, 10, 28],  # 8 m north, 5 m high
                      [-30.0, 0, -20, 10],  # 20 m west, 40 m high
                      [0.0, 0, 10, 10]])  # fmt: skip
    tops = np.array([10.0, 5.0, 40.0, 3.0])
    occ = Occluders(list("abcd"), boxes, tops, tangent=1.0, origin=np.zeros(3))
    # from the ground: reaches 11, 6, 41 and 4 m
    assert occ.near((0.0, 0.0, 10.0, 10.0), 0.0).tolist() == [0, 2, 3]
    # from 4 m up: 7, 2, 37 and 1 m (the window's own mesh, lower, still touches it)
    assert occ.near((0.0, 0.0, 10.0, 10.0), 4.0).tolist() == [2, 3]
    assert REACH_MARGIN_M == 1.0  # the reaches above
    # views that see the horizon: everything
    flat = Occluders(list("abcd"), boxes, tops, tangent=np.inf, origin=np.zeros(3))
    assert flat.near((0.0, 0.0, 10.0, 10.0), 4.0).tolist() == [0, 1, 2, 3]


def _near_hides_what_all_hide(occ: Occluders, meshes, cameras, windows, rng):
    """For points in each window ((xmin, ymin, xmax, ymax), z_low, z_high), cast to every
    camera that frames them: the rays the meshes near the window hide are those all of
    them hide. Returns the meshes left out and the rays hidden, summed over windows."""
    everything = occ.scene(meshes)
    left_out, hidden = 0, 0
    for (x0, y0, x1, y1), z0, z1 in windows:
        near = occ.near((x0, y0, x1, y1), z0)
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
    """Towers of 5-60 m on a 300 m square, views from 500 m tilted up to 40 degrees, the
    ground around the towers and their sides as windows: fewer meshes, the same hits."""
    rng = np.random.default_rng(1)
    xy = rng.uniform(-150, 150, (60, 2))
    tops = rng.uniform(5, 60, 60)
    boxes = np.column_stack([xy - 6, xy + 6])
    meshes = [prism(shapely.box(*b), 0.0, t) for b, t in zip(boxes, tops, strict=True)]
    cameras = []
    for tilt in (0, 20, 40):
        for azimuth in (0, 120, 240):
            a, t = np.radians(azimuth), np.radians(tilt)
            cameras.append(_camera([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)],
                                   f=800.0))  # fmt: skip
    occ = Occluders(list(range(60)), boxes, tops, max_ray_tangent(cameras), np.zeros(3))
    corners = rng.uniform(-160, 140, (40, 2))
    windows = [((x, y, x + 20, y + 20), z, z + 10) for (x, y), z in
               zip(corners, rng.choice([0.0, 10.0, 30.0], 40), strict=True)]  # fmt: skip
    left_out, hidden = _near_hides_what_all_hide(occ, meshes, cameras, windows, rng)
    assert left_out >= 1700 and hidden >= 9000  # of 2400 pairs; measured 1753, 9834


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
    assert left_out >= 8 and hidden >= 10000  # measured 8 of 144 pairs, 11428
