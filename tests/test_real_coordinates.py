"""Real coordinates: the same city at its CRS's zero and at UTM 31N (500 km, 5,700 km)
gives the same products, moved; float32 ray casting works in a local origin."""

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tests.conftest import run_cli
from workbench.cityjson_check import check_city_model
from workbench.raster import read_raster
from workbench.raycast import cast, occluded, raycasting_scene, unsigned_distance
from workbench.scene import load_scene

UTM = (500000.0, 5700000.0)


@pytest.mark.parametrize("origin", [(0.0, 0.0), UTM])
def test_ray_casting_keeps_millimetres_far_from_the_origin(origin):
    # a roof plane z = 0.3 x + 20, 40 m square, with rays 3.7 mm apart
    x0, y0 = origin
    v = np.array([[x0, y0, 20.0], [x0 + 40, y0, 32.0], [x0 + 40, y0 + 40, 32.0], [x0, y0 + 40, 20]])
    scene = raycasting_scene(v, np.array([[0, 1, 2], [0, 2, 3]]))
    xs = x0 + 10.0 + 0.0037 * np.arange(20)
    hits = cast(scene, np.column_stack([xs, np.full(20, y0 + 7.0), np.full(20, 100.0)]),
                np.tile([0.0, 0.0, -1.0], (20, 1)))  # fmt: skip
    np.testing.assert_allclose(hits.points[:, 2], 0.3 * (xs - x0) + 20.0, atol=2e-4)
    np.testing.assert_allclose(hits.points[:, 0], xs, atol=1e-9)  # float64 from the ray
    above = np.column_stack([xs, np.full(20, y0 + 7.0), 0.3 * (xs - x0) + 20.0 + 0.002])
    np.testing.assert_allclose(unsigned_distance(scene, above), 0.002 / np.hypot(1, 0.3), atol=2e-4)
    assert not occluded(scene, above, [0.0, 0.0, 1.0]).any()
    assert occluded(scene, above - [0, 0, 0.004], [0.0, 0.0, 1.0]).all()


@pytest.mark.slow
@pytest.mark.xdist_group("voxel")  # with the tests that read the tiny city's voxel run
def test_every_command_gives_the_same_city_at_utm(tiny_scene, tiny_fusion, tiny_models,
                                                  tmp_path):  # fmt: skip
    utm = tmp_path / "utm"
    proc = run_cli("sample", utm, "--origin", *UTM, "--crs", "EPSG:32631")
    assert proc.returncode == 0, proc.stderr
    assert load_scene(utm).crs.to_epsg() == 32631
    assert run_cli("validate", utm).returncode == 0
    runs = {}
    for name, scene in (("local", tiny_scene), ("utm", utm)):
        fusion, sp, vx, report = (tmp_path / f"{name}_{k}" for k in ("fusion", "sp", "vx",
                                                                      "report"))  # fmt: skip
        commands = [("fusion", scene, "-o", fusion),
                    ("model", "superpixel", fusion, "-o", sp),
                    ("model", "voxel", scene, "--fusion", fusion, "-o", vx)]  # fmt: skip
        if name == "local":  # the session's runs of these commands on the tiny city
            fusion, sp, vx = tiny_fusion, tiny_models("superpixel")[0], tiny_models("voxel")[0]
            commands = []
        commands.append(("compare", fusion, sp, vx, "--truth", scene, "-o", report,
                         "--names", "fusion", "superpixel", "voxel"))  # fmt: skip
        for args in commands:
            proc = run_cli(*args)
            assert proc.returncode == 0, proc.stderr
        metrics = json.loads((report / "metrics.json").read_text())["runs"]
        runs[name] = {"fusion": fusion, "sp": sp, "vx": vx, "metrics": metrics}
    # the fused rasters: the same cells, moved (float rounding flips a median in 0.1 %)
    a, grid_a, _ = read_raster(runs["local"]["fusion"] / "dsm.tif")
    b, grid_b, crs = read_raster(runs["utm"]["fusion"] / "dsm.tif")
    assert crs.to_epsg() == 32631 and (grid_b.xmin - grid_a.xmin, grid_b.ymax - grid_a.ymax) == UTM
    same = np.isclose(a, b, atol=1e-4) | (np.isnan(a) & np.isnan(b))
    assert same.mean() > 0.998
    for path in ("sp", "vx"):
        ma, mb = (json.loads((runs[k][path] / "model.json").read_text()) for k in ("local", "utm"))
        assert len(ma["buildings"]) == len(mb["buildings"])
        for ba, bb in zip(ma["buildings"], mb["buildings"], strict=True):
            assert bb["ridge_z"] == pytest.approx(ba["ridge_z"], abs=0.02)
    # CityJSON: the same millimetres from an origin moved by the offset, the CRS a URL
    ca, cb = (json.loads((runs[k]["sp"] / "model.city.json").read_text()) for k in ("local", "utm"))
    assert cb["metadata"]["referenceSystem"].endswith("/EPSG/0/32631")
    moved = np.subtract(cb["transform"]["translate"], ca["transform"]["translate"])
    assert moved[:2] == pytest.approx(UTM) and check_city_model(cb) == []
    va, vb = np.asarray(ca["vertices"]), np.asarray(cb["vertices"])
    # the same vertices but for rounding (at UTM one pair of corners merged in the grid)
    assert abs(len(va) - len(vb)) <= 0.01 * len(va)
    assert max(cKDTree(vb).query(va)[0].max(), cKDTree(va).query(vb)[0].max()) <= 20  # mm
    for run in ("fusion", "superpixel", "voxel"):
        la, ub = runs["local"]["metrics"][run], runs["utm"]["metrics"][run]
        assert ub["footprint_2d"]["quality"] == pytest.approx(
            la["footprint_2d"]["quality"], abs=2e-3
        )
        assert ub["height"]["rmse_m"] == pytest.approx(la["height"]["rmse_m"], abs=0.01)
    # the texture seams: in float32 at 5.7e6 m the occlusion tests moved the projective
    # seam cost by 9 %; then the charts' plane offsets, n . p in world coordinates, carried
    # the normals' rounding as millimetres and split coplanar faces (66 charts for 51:
    # the run's own costs moved 14 % and 22 %). In a local origin only the rounding of
    # the moved cameras and of the fused DSM (0.06 % of its cells) can move them, through
    # the views whose scores tie at a texel (select_views may then take other views for
    # a building); measured against the projective cost: the run's own 0 % and 0 %, as
    # compare recomputes them from the written textures 0.14 % and 0.11 %
    ta, tb = (runs[k]["metrics"]["voxel"]["texture"] for k in ("local", "utm"))
    moved = {
        (source, key): abs(within[key] - figures[key]) / figures["seam_cost_projective"]
        for source, figures, within in (("run", ta["reported"], tb["reported"]),
                                        ("compare", ta, tb))
        for key in ("seam_cost", "seam_cost_projective")
    }  # fmt: skip
    assert moved["compare", "seam_cost"] < 0.01 and moved["compare", "seam_cost_projective"] < 0.01
    assert moved["run", "seam_cost"] < 0.04 and moved["run", "seam_cost_projective"] < 0.04, moved
