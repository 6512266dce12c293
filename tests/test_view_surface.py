"""The surface a view sees, sampled at cell centres, on a hand-built box on flat ground."""

import numpy as np
import open3d as o3d
import pytest

from data_samples.depth import degrade_depth
from fusion.view_surface import median_depth, steep_ray_preferred, view_surface_heights
from workbench.camera import Camera, look_at_rotation
from workbench.raster import Grid

ROOF = 10.0  # the box: x, y in [-5, 5], z in [0, 10]


def _world() -> o3d.t.geometry.RaycastingScene:
    ground = o3d.geometry.TriangleMesh.create_box(80, 80, 1).translate((-40, -40, -1))
    box = o3d.geometry.TriangleMesh.create_box(10, 10, ROOF).translate((-5, -5, 0))
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in (ground, box):
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def _view(centre, target, size=(240, 180), focal=300.0):
    """A camera and its depth map of the box, edges rounded as dense matching does."""
    w, h = size
    R = look_at_rotation(np.subtract(target, centre))
    K = np.array([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1]])
    cam = Camera(K, R, -R @ np.asarray(centre, float), w, h)
    origin, dirs = cam.pixel_grid_rays()
    rays = np.column_stack([np.broadcast_to(origin, dirs.shape), dirs]).astype(np.float32)
    depth = _world().cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(h, w)
    depth = degrade_depth(
        depth,
        np.full((h, w), 128, np.uint8),
        np.ones((h, w), bool),
        np.random.default_rng(0),
        sigma=0.0,
        reference_depth=50.0,
        outliers=0.0,
    )
    return cam, depth


GRID = Grid.from_bounds(-20, -20, 20, 20, 0.25)
WHOLE = (0, 0, *GRID.shape)


@pytest.mark.parametrize("centre", [(0, -40, 45), (0, 0, 50)], ids=["oblique", "nadir"])
def test_heights_are_the_box_or_the_ground_never_a_ramp_between(centre):
    cam, depth = _view(centre, (0, 0, 0))
    cells, z, sin_el = view_surface_heights(cam, depth, GRID, WHOLE)
    assert len(z) > 5000
    on_roof, on_ground = np.abs(z - ROOF) < 0.05, np.abs(z) < 0.05
    # the rounded depth edge is not bridged: no height between ground and roof (the
    # median filter leaves a few centimetres on the ground beside an occluding edge)
    assert ((z < 1.0) | (z > ROOF - 1.0)).all() and (on_roof | on_ground).mean() > 0.98
    rows, cols = np.divmod(cells, GRID.width)
    x = GRID.xmin + (cols + 0.5) * GRID.gsd
    y = GRID.ymax - (rows + 0.5) * GRID.gsd
    inside = np.maximum(np.abs(x), np.abs(y))
    # the median filter rounds the creases at the top and foot of a facade
    assert (np.abs(z[inside < 4.5] - ROOF) < 0.25).all() and (z[inside > 6.0] < 0.5).all()
    assert (inside < 4.5).sum() > 0.6 * (9 / GRID.gsd) ** 2  # the roof is seen, not cut away
    # the sine of the elevation of the ray from each hit to the camera
    to_cam = cam.center - np.column_stack([x, y, z])
    np.testing.assert_allclose(sin_el, to_cam[:, 2] / np.linalg.norm(to_cam, axis=1), atol=1e-4)


def test_a_window_samples_the_same_heights_as_the_whole_grid():
    cam, depth = _view((0, -40, 45), (0, 0, 0))
    cells, z, _ = view_surface_heights(cam, depth, GRID, WHOLE)
    r0, c0, h, w = 50, 70, 40, 60
    local, z_win, _ = view_surface_heights(cam, depth, GRID, (r0, c0, h, w))
    whole = np.full(GRID.shape, np.nan, np.float32)
    whole.ravel()[cells] = z
    window = np.full((h, w), np.nan, np.float32)
    window.ravel()[local] = z_win
    assert np.isfinite(window).sum() > 1000
    np.testing.assert_array_equal(window, whole[r0 : r0 + h, c0 : c0 + w])


def test_median_depth_removes_a_gross_error_and_keeps_holes():
    depth = np.full((20, 20), 50.0, np.float32)
    depth[10, 10] = 80.0
    depth[3, 4] = np.nan
    out = median_depth(depth)
    assert out[10, 10] == pytest.approx(50.0)
    assert np.isnan(out[3, 4]) and np.isfinite(out).sum() == 399


def test_steep_rays_are_preferred_where_a_cell_has_them():
    cells = np.array([0, 0, 0, 1, 1])
    sin_el = np.array([0.95, 0.5, 0.6, 0.5, 0.7], np.float32)
    np.testing.assert_array_equal(
        steep_ray_preferred(cells, sin_el, 2), [True, False, False, True, True]
    )
