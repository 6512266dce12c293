"""The synthetic city against independent checks of its own ground truth."""

import json

import numpy as np
import open3d as o3d
import pytest
import shapely

from data_samples.depth import degrade_depth, depth_error_stats
from tests.conftest import run_cli
from workbench.camera import Camera
from workbench.footprints import read_footprints
from workbench.meshio import read_ply
from workbench.raster import read_raster
from workbench.raycast import cast, raycasting_scene
from workbench.scene import load_scene


def _cast(scene, origins, dirs):
    hits = cast(scene, origins, dirs)
    return hits.t, hits.tri


@pytest.fixture(scope="module")
def truth_mesh(tiny_scene):
    v, t, props = read_ply(tiny_scene / "truth" / "mesh.ply")
    return v, t, props, raycasting_scene(v, t)


@pytest.fixture(scope="module")
def true_cameras(tiny_scene):
    doc = json.loads((tiny_scene / "truth" / "cameras.json").read_text())
    return {
        c["id"]: Camera(
            np.array(c["K"]), np.array(c["R"]), np.array(c["t"]), c["width"], c["height"]
        )
        for c in doc["cameras"]
    }


def test_scene_is_valid_and_documented_layout(tiny_scene, tiny_meta):
    s = load_scene(tiny_scene)
    assert len(s.views) == tiny_meta["counts"]["views"] == 20
    assert all(v.depth_path is not None for v in s.views)
    assert s.truth is not None and s.footprints is not None and s.training_labels is not None
    for name in (
        "mesh.ply",
        "buildings.json",
        "ortho.tif",
        "dsm.tif",
        "dtm.tif",
        "class.tif",
        "footprints.geojson",
        "building_id.tif",
        "cameras.json",
    ):
        assert (tiny_scene / "truth" / name).exists(), name
    assert (tiny_scene / "preview.png").stat().st_size > 10_000
    assert 4 <= tiny_meta["counts"]["buildings"] <= 9
    for axis in ("x", "y"):  # the issue asks for 60-80 % overlap
        assert 0.6 <= tiny_meta["coverage"][f"nadir_overlap_{axis}"] <= 0.8


def test_truth_rasters_share_grid_and_crs(tiny_scene):
    s = load_scene(tiny_scene)
    grids = []
    for name in ("ortho", "dsm", "dtm", "class", "building_id"):
        data, grid, crs = read_raster(tiny_scene / "truth" / f"{name}.tif")
        assert crs == s.crs, name
        grids.append(grid)
    assert all(g == grids[0] for g in grids)
    assert grids[0].gsd == pytest.approx(s.gsd)
    assert grids[0].bounds == pytest.approx(s.bounds)


def test_dsm_and_class_equal_vertical_ray_cast_of_mesh(tiny_scene, truth_mesh):
    v, t, props, scene = truth_mesh
    dsm, grid, _ = read_raster(tiny_scene / "truth" / "dsm.tif")
    cls, _, _ = read_raster(tiny_scene / "truth" / "class.tif")
    X, Y = grid.cell_centers()
    top = v[:, 2].max() + 5
    org = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, top)])
    th, ids = _cast(scene, org, np.tile([0, 0, -1.0], (X.size, 1)))
    z = top - th
    assert np.isfinite(dsm).all()
    np.testing.assert_allclose(dsm[0].ravel(), z, atol=2e-3)
    np.testing.assert_array_equal(cls[0].ravel(), props["class"][ids])


def test_dtm_is_below_dsm_and_equals_it_on_open_ground(tiny_scene):
    dsm = read_raster(tiny_scene / "truth" / "dsm.tif")[0][0]
    dtm = read_raster(tiny_scene / "truth" / "dtm.tif")[0][0]
    cls = read_raster(tiny_scene / "truth" / "class.tif")[0][0]
    assert np.all(dsm >= dtm - 1e-3)
    ground = cls <= 2
    np.testing.assert_allclose(dsm[ground], dtm[ground], atol=1e-3)
    assert np.all(dsm[cls == 4] - dtm[cls == 4] > 2.0)


def test_truth_points_reproject_to_pixels_whose_rays_hit_them(tiny_scene, truth_mesh, true_cameras):
    v, t, props, scene = truth_mesh
    rng = np.random.default_rng(1)
    pick = rng.choice(len(t), 3000, replace=False)
    bary = rng.dirichlet([1, 1, 1], len(pick))
    pts = np.einsum("ij,ijk->ik", bary, v[t[pick]])
    checked = 0
    for cam in list(true_cameras.values())[::3]:
        uv, depth = cam.project(pts)
        inside = (depth > 0) & np.all((uv >= 0) & (uv <= [cam.width - 1, cam.height - 1]), axis=1)
        origin, dirs = cam.pixel_rays(uv[inside])
        th, _ = _cast(scene, origin, dirs)
        d = depth[inside]
        # the ray through the projection never passes the point ...
        assert np.all(th <= d * (1 + 1e-5) + 1e-3)
        # ... and stops at it wherever the point is visible (most of them)
        visible = np.abs(th - d) < 1e-3 * d + 1e-3
        assert visible.mean() > 0.3
        checked += visible.sum()
    assert checked > 1000


def test_depth_maps_follow_the_noise_model(tiny_scene, tiny_meta, truth_mesh, true_cameras):
    _, _, _, scene = truth_mesh
    s = load_scene(tiny_scene)
    prm = tiny_meta["preset"]
    stats = []
    for view in s.views:
        cam = true_cameras[view.id]
        origin, dirs = cam.pixel_grid_rays()
        true_depth, _ = _cast(scene, origin, dirs)
        depth = view.read_depth()
        assert depth.dtype == np.float32 and depth.shape == (cam.height, cam.width)
        stats.append(
            depth_error_stats(
                depth,
                true_depth.reshape(cam.height, cam.width),
                sigma=prm["depth_sigma"],
                reference_depth=prm["flying_height"],
            )
        )
    ratio = np.median([x["noise_ratio"] for x in stats])
    outliers = np.mean([x["outlier_fraction"] for x in stats])
    valid = np.mean([x["valid_fraction"] for x in stats])
    assert 0.8 < ratio < 1.25, stats
    assert 0.01 < outliers < 0.04, stats
    assert 0.6 < valid < 0.995, stats  # holes exist, but not everywhere


def test_true_depth_sample_holds_the_renderers_depth(
    tiny_scene, truth_mesh, true_cameras, tmp_path
):
    out = tmp_path / "true"
    proc = run_cli("sample", out, "--true-depth")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "sample.json").read_text())["preset"]["depth_matching"] is False
    _, _, _, scene = truth_mesh
    sampled, true = load_scene(tiny_scene), load_scene(out)
    for matched, view in list(zip(sampled.views, true.views, strict=True))[::6]:
        cam = true_cameras[view.id]
        origin, dirs = cam.pixel_grid_rays()
        cast_depth = _cast(scene, origin, dirs)[0].reshape(cam.height, cam.width)
        depth = view.read_depth()
        seen = np.isfinite(cast_depth)
        assert np.array_equal(np.isfinite(depth), seen)  # no holes
        np.testing.assert_allclose(depth[seen], cast_depth[seen], rtol=1e-6, atol=1e-4)
        # the same views: only their depth maps differ from the matched sample's
        assert view.image_path.read_bytes() == matched.image_path.read_bytes()
        assert np.nanmax(np.abs(matched.read_depth() - depth)) > 1.0


def test_depth_edges_are_rounded_unless_asked_sharp():
    depth = np.full((40, 60), 100.0)
    depth[:, 30:] = 80.0  # a roof's edge: the right half 20 m nearer
    gray = np.full(depth.shape, 128, np.uint8)  # textured enough: no shadow holes
    lit = np.ones(depth.shape, bool)
    kw = dict(sigma=0.0, reference_depth=100.0, outliers=0.0)
    rounded = degrade_depth(depth, gray, lit, np.random.default_rng(0), **kw)
    sharp = degrade_depth(depth, gray, lit, np.random.default_rng(0), round_edges=False, **kw)
    seen = np.isfinite(sharp)
    assert np.array_equal(np.isfinite(rounded), seen)  # the same holes either way
    assert np.array_equal(sharp[seen], depth[seen])
    ramp = seen & (rounded != depth)
    assert ramp[:, 27:30].all() and not ramp[:, :27].any()  # within 2 pixels of the edge
    assert np.all((rounded[ramp] > 80.0) & (rounded[ramp] < 100.0))


def test_depth_error_stats_on_a_hand_made_case():
    rng = np.random.default_rng(0)
    true = np.full((200, 200), 50.0)
    noisy = true + rng.normal(0, 0.15, true.shape)  # exactly the model at 50 m
    noisy[:10] = np.nan
    noisy[100, :40] += 20.0  # 40 gross errors; the Gaussian tail beyond 8 sigma is ~1e-15
    st = depth_error_stats(noisy, true, sigma=0.15, reference_depth=50.0)
    assert st["noise_ratio"] == pytest.approx(1.0, rel=0.03)
    assert st["outlier_fraction"] == pytest.approx(40 / (190 * 200), rel=1e-9)
    assert st["valid_fraction"] == pytest.approx(0.95)
    twice = depth_error_stats(
        true + rng.normal(0, 0.3, true.shape), true, sigma=0.15, reference_depth=50.0
    )
    assert twice["noise_ratio"] == pytest.approx(2.0, rel=0.03)
    # without a noise model (the floors' noise-free samples) the residual is in metres
    metres = depth_error_stats(noisy, true, sigma=0.0, reference_depth=50.0)
    assert metres["noise_ratio"] == pytest.approx(0.15, rel=0.03)
    assert metres["outlier_fraction"] == st["outlier_fraction"]  # 20 m errors, beyond 8 m


def test_buildings_json_matches_rasters(tiny_scene, truth_mesh):
    v, t, props, _ = truth_mesh
    doc = json.loads((tiny_scene / "truth" / "buildings.json").read_text())
    bid, grid, _ = read_raster(tiny_scene / "truth" / "building_id.tif")
    bid = bid[0]
    dsm = read_raster(tiny_scene / "truth" / "dsm.tif")[0][0]
    cls = read_raster(tiny_scene / "truth" / "class.tif")[0][0]
    for b in doc["buildings"]:
        m = (bid == b["id"]) & (cls == 4)
        assert m.sum() > 0.5 * b["area_m2"] / grid.gsd**2, b["id"]  # mostly visible from above
        assert dsm[m].max() == pytest.approx(b["ridge_z"], abs=0.15)
        assert b["eave_z"] <= b["ridge_z"] + 1e-6
        assert 3.0 <= b["height"] <= 60.0
        poly = shapely.Polygon(b["footprint"][0], b["footprint"][1:])
        assert poly.area == pytest.approx(b["area_m2"], rel=1e-4)
        # each building of the truth mesh is closed and oriented outwards
        tri = t[props["building_id"] == b["id"]]
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(tri)
        )
        mesh.remove_unreferenced_vertices()
        assert mesh.is_watertight(), b["id"]
        assert mesh.get_volume() > b["area_m2"] * (b["eave_z"] - b["base_z"])


def test_gis_footprints_are_displaced_and_heights_overestimated(tiny_scene):
    truth = {str(f.id): f for f in read_footprints(tiny_scene / "truth" / "footprints.geojson")}
    gis = read_footprints(tiny_scene / "footprints_gis.geojson")
    assert len(gis) == len(truth)
    for f in gis:
        tf = truth[f.id]
        shift = f.polygon.centroid.distance(tf.polygon.centroid)
        assert 0.5 < shift < 2.8, (f.id, shift)
        assert 0.6 < f.polygon.hausdorff_distance(tf.polygon) < 4.0
        ratio = f.height / tf.height
        assert 1.3 - 0.3 / tf.height <= ratio <= 1.7 + 0.3 / tf.height


def test_training_strokes(tiny_scene):
    labels = read_raster(tiny_scene / "training" / "labels.tif")[0][0]
    cls = read_raster(tiny_scene / "truth" / "class.tif")[0][0]
    frac = np.mean(labels > 0)
    assert 0.01 < frac < 0.035
    assert set(np.unique(labels[labels > 0])) == {1, 2, 3, 4}
    np.testing.assert_array_equal(labels[labels > 0], cls[labels > 0])


def test_calibration_error_of_written_poses(tiny_scene, truth_mesh, true_cameras, tiny_meta):
    v, t, props, _ = truth_mesh
    pts = v[t[props["class"] <= 2][::50, 0]]
    s = load_scene(tiny_scene)
    errs = []
    for view in s.views:
        true = true_cameras[view.id]
        a, _ = true.project(pts)
        b, _ = view.camera.project(pts)
        ok = np.all((a >= 0) & (a < [true.width, true.height]), axis=1)
        errs.append(np.sqrt(np.mean(np.sum((a[ok] - b[ok]) ** 2, axis=1))))
        assert not np.allclose(view.camera.R, true.R)  # the written poses are not the truth
    assert 0.3 < np.median(errs) < 0.7, errs
    assert tiny_meta["calibration_error_px_rms"] == pytest.approx(0.5, abs=0.02)


def test_images_look_like_the_true_ortho_from_above(tiny_scene, true_cameras):
    """The nadir image's pixel at a ground point has the ortho's colour there (same
    surface, shading and sun): a check that images and truth are rendered alike."""
    ortho, grid, _ = read_raster(tiny_scene / "truth" / "ortho.tif")
    dsm = read_raster(tiny_scene / "truth" / "dsm.tif")[0][0]
    cls = read_raster(tiny_scene / "truth" / "class.tif")[0][0]
    s = load_scene(tiny_scene)
    view = next(v for v in s.views if v.id.endswith("_n"))
    img = view.read_image().astype(float)
    cam = true_cameras[view.id]
    X, Y = grid.cell_centers()
    sel = (cls == 1)[::7, ::7]
    pts = np.column_stack([X[::7, ::7][sel], Y[::7, ::7][sel], dsm[::7, ::7][sel]])
    uv, _ = cam.project(pts)
    ok = np.all((uv >= 1) & (uv < [cam.width - 2, cam.height - 2]), axis=1)
    px = img[np.round(uv[ok, 1]).astype(int), np.round(uv[ok, 0]).astype(int)]
    ref = np.moveaxis(ortho, 0, -1)[::7, ::7][sel][ok].astype(float)
    corr = np.corrcoef(px.mean(1), ref.mean(1))[0, 1]
    assert corr > 0.7, corr
