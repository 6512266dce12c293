"""``workbench import-odm``: OpenSfM cameras into the scene's CRS, exactly; the tiny city as
an ODM project fused and scored against its truth; one-line errors."""

import json

import cv2
import numpy as np
import pytest
from pyproj import Transformer
from rasterio.crs import CRS

from data_samples.odm_project import write_odm_project
from tests.conftest import run_cli
from workbench.odm import import_odm, opensfm_camera, topocentric_to_crs
from workbench.raster import Grid, read_raster, write_raster
from workbench.scene import load_scene

SITE = {"latitude": 52.0003, "longitude": 4.3702, "altitude": 45.0}  # the sample's site


def test_the_tiny_city_round_trips_through_an_odm_project(tiny_scene, tmp_path):
    project = write_odm_project(tiny_scene, tmp_path / "odm", SITE)
    doc = json.loads((project / "opensfm" / "reconstruction.json").read_text())[0]
    kinds = {c["projection_type"] for c in doc["cameras"].values()}
    assert kinds == {"perspective", "brown"}
    # shots are topocentric: metres east, north and up of the reference, tens of metres away
    assert max(abs(np.asarray(s["translation"])).max() for s in doc["shots"].values()) < 500
    import_odm(project, tmp_path / "scene")
    a = {v.id: v.camera for v in load_scene(tiny_scene).views}
    b = {v.id: v.camera for v in load_scene(tmp_path / "scene").views}
    assert a.keys() == b.keys()
    for k, cam in a.items():
        np.testing.assert_allclose(b[k].K, cam.K, atol=1e-9)
        np.testing.assert_allclose(b[k].R, cam.R, atol=1e-8)
        np.testing.assert_allclose(b[k].center, cam.center, atol=1e-5)


@pytest.mark.parametrize(
    "params, K, dist",
    [
        ({"projection_type": "perspective", "focal": 0.8, "k1": -0.1, "k2": 0.01},
         [[640, 0, 399.5], [0, 640, 299.5]], [-0.1, 0.01, 0, 0, 0]),
        ({"projection_type": "simple_radial", "focal_x": 0.8, "focal_y": 0.81, "c_x": 0.01,
          "c_y": -0.02, "k1": -0.1}, [[640, 0, 407.5], [0, 648, 283.5]], [-0.1, 0, 0, 0, 0]),
        ({"projection_type": "radial", "focal_x": 0.8, "focal_y": 0.8, "c_x": 0.0,
          "c_y": 0.0, "k1": -0.1, "k2": 0.02}, [[640, 0, 399.5], [0, 640, 299.5]],
         [-0.1, 0.02, 0, 0, 0]),
        ({"projection_type": "brown", "focal_x": 0.8, "focal_y": 0.8, "c_x": 0.0, "c_y": 0.0,
          "k1": -0.1, "k2": 0.02, "p1": 0.001, "p2": -0.002, "k3": 0.003},
         [[640, 0, 399.5], [0, 640, 299.5]], [-0.1, 0.02, 0.001, -0.002, 0.003]),
    ],
)  # fmt: skip
def test_opensfm_cameras_in_opencv_pixels(params, K, dist):
    # normalised by the larger side (800 px), centred on the image: (w - 1) / 2, (h - 1) / 2
    got_K, got_dist, fisheye = opensfm_camera(params, 800, 600, "cameras['c']", "r.json")
    np.testing.assert_allclose(got_K[:2], K)
    np.testing.assert_allclose(got_dist, dist)
    assert not fisheye


def _one_shot_project(tmp_path, camera, crs="EPSG:32631", image=None):
    """An ODM project of one shot looking down from 100 m over a UTM 31N DSM."""
    reference = {"latitude": 51.45, "longitude": 4.37, "altitude": 12.0}
    project = tmp_path / "odm"
    for d in ("images", "opensfm", "odm_dem"):
        (project / d).mkdir(parents=True)
    R = np.diag([1.0, -1.0, -1.0]) @ cv2.Rodrigues(np.array([0.05, -0.03, 0.2]))[0]
    C = np.array([10.0, -20.0, 100.0])
    shot = {"rotation": cv2.Rodrigues(R)[0].ravel().tolist(), "translation": (-R @ C).tolist(),
            "camera": "cam"}  # fmt: skip
    doc = [{"cameras": {"cam": camera}, "shots": {"a.png": shot}, "reference_lla": reference}]
    (project / "opensfm" / "reconstruction.json").write_text(json.dumps(doc))
    cv2.imwrite(
        str(project / "images" / "a.png"),
        np.zeros((600, 800, 3), np.uint8) if image is None else image,
    )
    centre = topocentric_to_crs(reference, CRS.from_user_input(crs))(np.zeros(3))[0]
    grid = Grid(centre[0] - 100, centre[1] + 100, 1.0, 200, 200)
    write_raster(project / "odm_dem" / "dsm.tif", np.full((200, 200), 12.0, np.float32), grid,
                 CRS.from_user_input(crs))  # fmt: skip
    return project, reference, R, C


def _enu_pixel(R, C, X_enu, K, dist):
    x = R @ (X_enu - C)
    return cv2.projectPoints(x.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, dist)[0].ravel()


def test_brown_cameras_land_in_utm_with_the_meridian_convergence(tmp_path):
    brown = {"projection_type": "brown", "width": 800, "height": 600, "focal_x": 0.9,
             "focal_y": 0.91, "c_x": 0.01, "c_y": -0.02, "k1": -0.1, "k2": 0.02, "p1": 0.001,
             "p2": -0.002, "k3": 0.0}  # fmt: skip
    project, reference, R, C = _one_shot_project(tmp_path, brown)
    import_odm(project, tmp_path / "scene")
    scene = load_scene(tmp_path / "scene")
    assert scene.crs.to_epsg() == 32631
    cam = scene.views[0].camera
    # the centre where pyproj puts it (topocentric -> WGS84 -> UTM 31N)
    to_geo = Transformer.from_pipeline(
        "+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0=51.45 +lon_0=4.37 "
        "+h_0=12.0 +step +inv +proj=cart +ellps=WGS84 +step +proj=unitconvert +xy_in=rad "
        "+xy_out=deg"
    )
    lon, lat, h = to_geo.transform(*C)
    e, n = Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True).transform(lon, lat)
    np.testing.assert_allclose(cam.center, [e, n, h], atol=1e-3)
    # 0.98 degrees of convergence at 4.37 E, 51.45 N in zone 31 (central meridian 3 E): a
    # point 60 m off the nadir moves 1 m (13 px) if it is ignored; here it projects where
    # OpenSfM puts it, but for UTM's scale (0.99986 across, 1 in height), which no pinhole
    # camera holds: 1.4 cm at 100 m, 0.1 px
    s = 800
    K = np.array([[0.9 * s, 0, 399.5 + 0.01 * s], [0, 0.91 * s, 299.5 - 0.02 * s], [0, 0, 1]])
    dist = np.array([-0.1, 0.02, 0.001, -0.002, 0.0])
    move = topocentric_to_crs(reference, scene.crs)
    for X in ([40.0, 30.0, 5.0], [-50.0, -60.0, 0.0], [10.0, -20.0, 20.0]):
        X = np.array(X)
        want = _enu_pixel(R, C, X, K, dist)
        got = cam.project(move(X))[0][0]
        np.testing.assert_allclose(got, want, atol=0.15)  # pixels


def test_fisheye_images_are_resampled_to_pinhole(tmp_path):
    fisheye = {"projection_type": "fisheye", "width": 800, "height": 600, "focal": 0.5,
               "k1": -0.05, "k2": 0.01}  # fmt: skip
    K = np.array([[400.0, 0, 399.5], [0, 400.0, 299.5], [0, 0, 1]])
    D = np.array([-0.05, 0.01, 0.0, 0.0])
    # a white dot where the fisheye sees a point 30 m east and 20 m north of the nadir
    R = np.diag([1.0, -1.0, -1.0]) @ cv2.Rodrigues(np.array([0.05, -0.03, 0.2]))[0]
    C = np.array([10.0, -20.0, 100.0])
    X = np.array([40.0, 0.0, 0.0])
    seen = cv2.fisheye.projectPoints((R @ (X - C)).reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    u, v = seen[0].ravel()
    image = np.zeros((600, 800, 3), np.uint8)
    cv2.circle(image, (round(u), round(v)), 3, (255, 255, 255), -1)
    project, reference, *_ = _one_shot_project(tmp_path, fisheye, image=image)
    import_odm(project, tmp_path / "scene")
    view = load_scene(tmp_path / "scene").views[0]
    assert not view.camera.has_distortion and view.image_path.parent.name == "images"
    move = topocentric_to_crs(reference, load_scene(tmp_path / "scene").crs)
    pu, pv = view.camera.project(move(X))[0][0]
    resampled = cv2.imread(str(view.image_path), cv2.IMREAD_GRAYSCALE)
    rows, cols = np.nonzero(resampled > 128)
    assert abs(cols.mean() - pu) < 1.0 and abs(rows.mean() - pv) < 1.0


@pytest.mark.slow
def test_an_odm_project_fuses_against_the_truth(tiny_scene, tiny_fusion, tmp_path):
    # the ODM project's DSM is the one dense matching made (the tiny city's depth-map
    # fusion), as ODM's own is; its views are projected onto it to fuse colour and classes
    project = write_odm_project(tiny_scene, tmp_path / "odm", SITE, dsm=tiny_fusion / "dsm.tif")
    scene = tmp_path / "scene"
    proc = run_cli("import-odm", project, "-o", scene, "--training-labels",
                   tiny_scene / "training" / "labels.tif")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    proc = run_cli("fusion", scene, "-o", tmp_path / "fused", "--truth", tiny_scene)
    assert proc.returncode == 0, proc.stderr
    q = json.loads((tmp_path / "fused" / "fusion.json").read_text())["quality"]
    # measured: classes 0.984 (0.976 fused from the depth maps; each cell's most probable
    # class 0.949), ortho MAE 7.5 (7.5)
    assert q["classification"]["overall_accuracy"] > 0.975, q["classification"]
    assert q["ortho_mae"]["mean"] < 8.2, q["ortho_mae"]
    given, grid, _ = read_raster(tiny_fusion / "dsm.tif")
    fused, grid_odm, _ = read_raster(tmp_path / "fused" / "dsm.tif")
    assert grid_odm == grid  # the DSM's extent and cell
    same = np.isclose(fused, given, atol=1e-3) | np.isnan(given)
    assert same.mean() > 0.99


@pytest.mark.parametrize("case", ["no_reconstruction", "no_dsm", "camera_model"])
def test_bad_odm_projects_are_one_line_errors(tmp_path, case):
    brown = {"projection_type": "brown", "width": 800, "height": 600, "focal_x": 0.9,
             "focal_y": 0.9}  # fmt: skip
    project, *_ = _one_shot_project(tmp_path, brown)
    if case == "no_reconstruction":
        (project / "opensfm" / "reconstruction.json").unlink()
        words = "reconstruction.json"
    elif case == "no_dsm":
        (project / "odm_dem" / "dsm.tif").unlink()
        words = "no DSM"
    else:
        doc = json.loads((project / "opensfm" / "reconstruction.json").read_text())
        doc[0]["cameras"]["cam"]["projection_type"] = "spherical"
        (project / "opensfm" / "reconstruction.json").write_text(json.dumps(doc))
        words = "camera model 'spherical' is not supported"
    proc = run_cli("import-odm", project, "-o", tmp_path / "scene")
    assert proc.returncode == 2 and words in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "scene").exists()
