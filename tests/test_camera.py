"""Cameras: rays invert the projection (with distortion), the centre and principal
point, a nadir camera is north up, points behind it are NaN."""

import numpy as np
import pytest

from workbench.camera import Camera, look_at_rotation, rotation_about


def _cam(dist=None):
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    R = rotation_about([0.3, -0.2, 1.0], 0.4) @ look_at_rotation([0.2, 0.5, -1.0])
    C = np.array([10.0, -5.0, 80.0])
    return Camera(K, R, -R @ C, 640, 480, np.zeros(5) if dist is None else np.asarray(dist))


@pytest.mark.parametrize("dist", [None, [-0.1, 0.02, 0.001, -0.002, 0.0]])
def test_pixel_rays_invert_project(dist):
    cam = _cam(dist)
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [640, 480], (200, 2))
    depth = rng.uniform(20, 120, 200)
    origin, dirs = cam.pixel_rays(uv)
    np.testing.assert_allclose(
        cam.world_to_camera(origin + dirs)[:, 2] - cam.world_to_camera(origin[None])[:, 2],
        1.0,
        atol=1e-9,
    )
    pts = origin + dirs * depth[:, None]
    uv2, d2 = cam.project(pts)
    np.testing.assert_allclose(d2, depth, rtol=1e-9)
    np.testing.assert_allclose(uv2, uv, atol=1e-4 if dist else 1e-8)


@pytest.mark.parametrize("dist", [None, [-0.1, 0.02, 0.001, -0.002, 0.0]])
def test_a_window_of_grid_rays_is_the_whole_grid_s_to_the_bit(dist):
    cam = _cam(dist)
    _, whole = cam.pixel_grid_rays()
    window = (slice(100, 230), slice(64, 640))
    _, part = cam.pixel_grid_rays(window=window)
    np.testing.assert_array_equal(part, whole.reshape(480, 640, 3)[window].reshape(-1, 3))
    _, coarse = cam.pixel_grid_rays(step=4)
    np.testing.assert_array_equal(coarse, whole.reshape(480, 640, 3)[::4, ::4].reshape(-1, 3))


def test_centre_and_principal_point():
    cam = _cam()
    axis_point = cam.center + 50 * cam.viewing_direction
    uv, d = cam.project(axis_point[None])
    np.testing.assert_allclose(uv[0], [319.5, 239.5], atol=1e-9)
    assert d[0] == pytest.approx(50.0)


def test_nadir_camera_has_north_up():
    R = look_at_rotation([0, 0, -1])
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    cam = Camera(K, R, -R @ np.array([0, 0, 100.0]), 101, 101)
    uv, _ = cam.project(np.array([[10.0, 0, 0], [0, 10.0, 0]]))
    assert uv[0, 0] > 50 and uv[0, 1] == pytest.approx(50)  # east is right
    assert uv[1, 1] < 50 and uv[1, 0] == pytest.approx(50)  # north is up
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_points_behind_are_nan():
    cam = _cam()
    uv, d = cam.project((cam.center - 10 * cam.viewing_direction)[None])
    assert d[0] < 0 and np.isnan(uv).all()
