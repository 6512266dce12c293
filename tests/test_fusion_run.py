"""`workbench fusion` end to end on the tiny city, scored against its truth."""

import json

import cv2
import laspy
import numpy as np
import pytest
import rasterio
from scipy.interpolate import LinearNDInterpolator

from fusion.point_clouds import read_points
from fusion.points import ASPRS_TO_CLASS
from tests.conftest import SHARED_DATA, run_cli
from workbench.errors import InputError
from workbench.raster import read_raster
from workbench.scene import load_scene

PRODUCTS = (
    "ortho.tif",
    "dsm.tif",
    "dtm.tif",
    "ndsm.tif",
    "class_prob.tif",
    "class.tif",
    "count.tif",
    "ceiling.tif",
    "fusion.json",
    "preview.png",
)


@pytest.fixture(scope="module")
def fused(tiny_fusion):
    """The session's default fusion of tiny (a local cluster of a worker per core), its
    record and its saved forest."""
    record = json.loads((tiny_fusion / "fusion.json").read_text())
    return tiny_fusion, record, tiny_fusion.parent / "forest.joblib"


def test_products_are_georeferenced_rasters(fused, tiny_scene):
    out, record, _ = fused
    for name in PRODUCTS:
        assert (out / name).exists(), name
    crs = load_scene(tiny_scene).crs
    shapes = set()
    for name in ("ortho", "dsm", "dtm", "ndsm", "class_prob", "class", "count"):
        with rasterio.open(out / f"{name}.tif") as src:
            assert src.crs == crs, name
            assert src.transform.e < 0 and src.transform.b == 0  # north-up
            assert src.profile.get("compress", "").lower() == "deflate"
            shapes.add((src.height, src.width))
    assert len(shapes) == 1
    prob = read_raster(out / "class_prob.tif")[0]
    seen = np.isfinite(prob[0])
    np.testing.assert_allclose(prob[:, seen].sum(axis=0), 1.0, atol=1e-5)
    cls = read_raster(out / "class.tif")[0][0]
    # the class CRF moves boundaries, hardly confident cells (measured on tiny: 2.6 % of
    # the cells changed; 10 of 44,455 cells above 0.99, lone cells against weak edges)
    argmax = np.argmax(prob[:, seen], axis=0) + 1
    confident = prob[:, seen].max(axis=0) > 0.99
    assert np.mean(cls[seen][confident] != argmax[confident]) < 0.001
    assert 0 < np.mean(cls[seen] != argmax) < 0.05
    assert (cls[~seen] == 0).all()
    dsm, dtm, ndsm = (read_raster(out / f"{n}.tif")[0][0] for n in ("dsm", "dtm", "ndsm"))
    ok = np.isfinite(dsm)
    np.testing.assert_allclose(ndsm[ok], dsm[ok] - dtm[ok], atol=1e-4)
    count = read_raster(out / "count.tif")[0][0]
    assert (np.isnan(dsm) == (count == 0)).all()  # unseen stays unseen; -1 marks filled holes
    assert record["filled_cells"] == int((count == -1).sum())
    # a ceiling over every cell no view saw, and over none other; each at or above the
    # ground beside it, none above the highest roof
    ceiling = read_raster(out / "ceiling.tif")[0][0]
    assert (np.isfinite(ceiling) == (count == 0)).all() and (count == 0).any()
    assert record["hidden_cells"] == int((count == 0).sum())
    assert np.nanmin(ceiling) >= np.nanmin(dtm) - 0.25 and np.nanmax(ceiling) <= np.nanmax(dsm)


def test_quality_against_truth(fused):
    """The figures this fusion reaches on tiny (see the issue note for the targets)."""
    _, record, _ = fused
    q = record["quality"]
    assert q["dsm"]["median_abs_m"] <= 0.15
    assert q["dsm"]["rmse_m"] <= 0.5  # the target (0.52 m before crown_sightings)
    assert q["dsm"]["valid_fraction"] >= 0.90
    assert q["dtm"]["rmse_m"] <= 0.4
    # measured 0.990; 0.993 before the views kept the roofs' rims, whose points past an
    # outline, where the ground behind is hidden, make some 160 ground cells building
    assert q["classification"]["overall_accuracy"] >= 0.985
    assert set(q["classification"]["per_class_accuracy"]) == {"ground", "grass", "tree", "building"}
    # each cell's most probable class, ground and grass weighed by the cell's colour
    # (measured 0.989; 0.950 without the colours), and the class CRF after it (0.993)
    most_probable = q["classification_most_probable"]["overall_accuracy"]
    assert most_probable >= 0.985
    assert q["classification"]["overall_accuracy"] > most_probable + 0.002
    assert record["flat_colours"]["training_cells"]["ground"] > 100
    assert q["ortho_mae"]["mean"] <= 12.0


def test_median_fusion_beats_the_mean(fused):
    q = fused[1]["quality"]
    assert q["dsm"]["rmse_m"] < q["dsm_mean_fusion"]["rmse_m"]
    assert q["dsm"]["mae_m"] < q["dsm_mean_fusion"]["mae_m"]


def test_record_has_stages_and_throughput(fused):
    record = fused[1]
    for stage in ("heights", "ground", "training", "classification", "colour_and_class",
                  "class_crf"):  # fmt: skip
        assert record["stages"][stage]["wall_s"] >= 0
        assert record["stages"][stage]["peak_memory_mb"] > 0
    assert record["observations"] > 0 and record["observations_per_s"] > 0
    assert "forest trained on" in record["class_source"]
    assert "labelled pixels dropped" in record["class_source"]
    assert "contrast-sensitive Potts model (omega 8)" in record["class_source"]
    made = record["provenance"]  # what made it: the command, the versions
    assert made["command"].startswith("workbench fusion ") and made["libraries"]["open3d-cpu"]


def test_saved_classifier_is_reused(fused, tiny_scene, tmp_path):
    _, record, clf = fused
    proc = run_cli(
        "fusion", tiny_scene, "-o", tmp_path / "again", "--classifier", clf, "--truth", tiny_scene
    )
    assert proc.returncode == 0, proc.stderr
    again = json.loads((tmp_path / "again" / "fusion.json").read_text())
    assert again["class_source"].startswith("classifier file")
    assert again["quality"]["classification"]["overall_accuracy"] == pytest.approx(
        record["quality"]["classification"]["overall_accuracy"], abs=0.02
    )


def test_bad_classifier_file_is_one_line(tiny_scene, tmp_path):
    bad = tmp_path / "bad.joblib"
    bad.write_bytes(b"not a pickle")
    proc = run_cli("fusion", tiny_scene, "-o", tmp_path / "o", "--classifier", bad)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "bad.joblib" in proc.stderr
    assert not (tmp_path / "o").exists()


def test_scene_without_depth_or_dsm_is_refused(tiny_scene, tmp_path):
    doc = json.loads((tiny_scene / "scene.json").read_text())
    for v in doc["images"]:
        v.pop("depth")
        v["file"] = str(tiny_scene / v["file"])
    (tmp_path / "scene.json").write_text(
        json.dumps(doc | {"footprints": None, "training_labels": None, "truth": None})
    )
    proc = run_cli("fusion", tmp_path, "-o", tmp_path / "o")
    assert proc.returncode == 2
    assert "no view has a depth map, and no DSM or point cloud is given" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_too_fine_a_grid_is_refused_before_allocating(tiny_scene, tmp_path):
    proc = run_cli("fusion", tiny_scene, "-o", tmp_path / "o", "--gsd", "0.0005")
    assert proc.returncode == 2
    assert "--gsd 0.0005" in proc.stderr and "GiB" in proc.stderr
    assert not (tmp_path / "o").exists()


# -- point clouds -------------------------------------------------------------------

AUTZEN = SHARED_DATA / "autzen" / "autzen_trim.las"
AHN3 = SHARED_DATA / "ahn3_buildings"
needs_shared = pytest.mark.skipif(not AUTZEN.exists(), reason="../shared/data is absent")


@needs_shared
def test_autzen_keeps_its_crs_and_feet(tmp_path):
    proc = run_cli("fusion", "--points", AUTZEN, "-o", tmp_path / "a")
    assert proc.returncode == 0, proc.stderr
    record = json.loads((tmp_path / "a" / "fusion.json").read_text())
    assert record["inputs"]["units_per_metre"] == pytest.approx(3.28084, rel=1e-4)
    dsm, grid, crs = read_raster(tmp_path / "a" / "dsm.tif")
    assert crs.linear_units_factor[1] == pytest.approx(0.3048, rel=1e-5)
    # the DSM is the surface through the highest return of each cell, read at the cell
    # centres (scipy's linear interpolator on the same returns), or that return itself
    # where the surface is a wall or the centre lies off the returns' hull
    las = laspy.read(AUTZEN)
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    r, c = grid.world_to_cell(x, y)
    r, c = np.floor(r + 0.5).astype(int), np.floor(c + 0.5).astype(int)
    ok = (r >= 0) & (r < grid.height) & (c >= 0) & (c < grid.width)
    top = np.full(grid.shape, -np.inf)
    np.maximum.at(top, (r[ok], c[ok]), z[ok])
    seen = np.isfinite(top)
    # of a cell's tied highest returns, the last in the file (a stable sort's last)
    cell = r * grid.width + c
    order = np.flatnonzero(ok)[np.lexsort((z[ok], cell[ok]))]
    returns = order[np.r_[cell[order][1:] != cell[order][:-1], True]]
    X, Y = grid.cell_centers()
    x0, y0 = x[returns].min(), y[returns].min()  # both triangulate in a local origin
    tin = LinearNDInterpolator(np.column_stack([x[returns] - x0, y[returns] - y0]), z[returns])(
        X[seen] - x0, Y[seen] - y0
    )
    on_tin = np.isclose(dsm[0][seen], tin, atol=1e-3)
    assert np.all(on_tin | np.isclose(dsm[0][seen], top[seen], atol=1e-3))
    assert (on_tin & ~np.isclose(tin, top[seen], atol=0.05)).mean() > 0.25  # 0.28 measured
    dtm = read_raster(tmp_path / "a" / "dtm.tif")[0][0]
    assert np.all(dtm[seen] <= dsm[0][seen] + 1e-4)
    assert record["dtm_source"].startswith("LAS ground class")
    cls = read_raster(tmp_path / "a" / "class.tif")[0][0]
    assert set(np.unique(cls)) <= {0, *ASPRS_TO_CLASS.values()} and (cls == 1).any()


@needs_shared
def test_ahn3_ply_in_its_local_frame(tmp_path):
    proc = run_cli("fusion", "--points", AHN3 / "9.ply", "-o", tmp_path / "b")
    assert proc.returncode == 0, proc.stderr
    dsm, _, crs = read_raster(tmp_path / "b" / "dsm.tif")
    assert crs is None
    pts = read_points(AHN3 / "9.ply").xyz
    assert np.nanmax(dsm) == pytest.approx(pts[:, 2].max(), abs=1e-3)
    assert np.nanmin(dsm) >= pts[:, 2].min() - 1e-3


def test_point_cloud_errors_are_one_line(tmp_path):
    (tmp_path / "bad.las").write_bytes(b"LASF" + b"\0" * 50)
    for args, words in (
        (["--points", tmp_path / "missing.laz"], "point cloud not found"),
        (["--points", tmp_path / "bad.las"], "not a readable LAS/LAZ file"),
    ):
        proc = run_cli("fusion", *args, "-o", tmp_path / "o")
        assert proc.returncode == 2, proc.stderr
        assert words in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_las_without_crs_needs_one(tmp_path):
    las = laspy.create(point_format=3, file_version="1.2")
    rng = np.random.default_rng(0)
    las.x, las.y, las.z = rng.uniform(0, 50, 500), rng.uniform(0, 50, 500), rng.uniform(0, 5, 500)
    las.write(tmp_path / "nocrs.las")
    with pytest.raises(InputError, match="pass --crs"):
        read_points(tmp_path / "nocrs.las")
    assert read_points(tmp_path / "nocrs.las", "EPSG:28992").crs.to_epsg() == 28992
    proc = run_cli(
        "fusion",
        "--points",
        tmp_path / "nocrs.las",
        "-o",
        tmp_path / "o",
        "--bounds",
        "100",
        "100",
        "200",
        "200",
        "--crs",
        "EPSG:28992",
    )
    assert proc.returncode == 2 and "no points inside the bounds" in proc.stderr


def test_true_orthophoto_from_a_dsm(tiny_scene, tmp_path):
    doc = json.loads((tiny_scene / "scene.json").read_text())
    for v in doc["images"]:
        v.pop("depth")
        v["file"] = str(tiny_scene / v["file"])
    doc.update(
        dsm=str(tiny_scene / "truth" / "dsm.tif"),
        training_labels=str(tiny_scene / "training" / "labels.tif"),
        footprints=None,
        truth=None,
    )
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    proc = run_cli("fusion", tmp_path, "-o", tmp_path / "o", "--truth", tiny_scene)
    assert proc.returncode == 0, proc.stderr
    record = json.loads((tmp_path / "o" / "fusion.json").read_text())
    assert record["mode"].startswith("true orthophoto")
    q = record["quality"]
    assert q["dsm"]["rmse_m"] < 1e-3  # the given DSM is the height product
    assert q["ortho_mae"]["mean"] <= 10.0
    assert q["classification"]["overall_accuracy"] >= 0.9


def test_raster_forest_on_an_unseen_synthetic_city(tmp_path):
    """The forest for unlabelled clouds, on rasters of a city it was not trained on."""
    from data_samples.generate import generate_sample
    from fusion.ground import dtm_from_dsm
    from fusion.raster_forest import classify_rasters, synthetic_raster_forest
    from workbench.metrics import classification

    generate_sample(tmp_path / "s", "tiny", 7)
    dsm, grid, _ = read_raster(tmp_path / "s" / "truth" / "dsm.tif")
    ortho = np.moveaxis(read_raster(tmp_path / "s" / "truth" / "ortho.tif")[0], 0, -1)
    truth = read_raster(tmp_path / "s" / "truth" / "class.tif")[0][0]
    dtm, _ = dtm_from_dsm(dsm[0], grid.gsd)
    prob = classify_rasters(synthetic_raster_forest(), dsm[0], dtm, ortho, grid.gsd)
    np.testing.assert_allclose(prob.sum(axis=0), 1.0, atol=1e-5)
    pred = np.argmax(prob, axis=0) + 1
    score = classification(pred, truth)
    assert score["overall_accuracy"] >= 0.85, score


def test_tiles_give_the_same_rasters_as_one_tile(tiny_scene):
    from fusion.scene_fusion import FusionOptions, fuse_views

    scene = load_scene(tiny_scene)
    scene.training_labels = None  # classes from the raster forest: the test is about tiling
    bounds = (-20.0, -12.0, 10.0, 14.0)
    one = fuse_views(scene, FusionOptions(bounds=bounds, tile=4096))
    many = fuse_views(scene, FusionOptions(bounds=bounds, tile=48))
    assert one.grid == many.grid and one.grid.width > 48 * 2
    np.testing.assert_array_equal(one.dsm, many.dsm)
    np.testing.assert_array_equal(one.ortho, many.ortho)
    np.testing.assert_array_equal(one.count, many.count)
    np.testing.assert_array_equal(one.classes, many.classes)


def test_workers_do_not_change_the_products(fused, tiny_fusion_one_process):
    out, record, _ = fused
    if record["workers"] == 1:
        pytest.skip("one core: the default run is one process too")
    one = tiny_fusion_one_process
    assert json.loads((one / "fusion.json").read_text())["workers"] == 1
    for name in ("dsm.tif", "ortho.tif", "class_prob.tif", "count.tif"):
        a, _, _ = read_raster(out / name)
        b, _, _ = read_raster(one / name)
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_view_workers_follow_the_option_then_the_cores_and_the_memory(tiny_scene):
    from fusion.scene_fusion import (
        FEATURE_BYTES_PER_PIXEL,
        FusionOptions,
        physical_memory,
        view_workers,
    )
    from workbench.parallel import default_workers

    views = load_scene(tiny_scene).views
    assert view_workers(views, FusionOptions(workers=3)) == 3
    assert 1 <= view_workers(views, FusionOptions()) <= default_workers()
    one_view = max(v.camera.width * v.camera.height for v in views) * FEATURE_BYTES_PER_PIXEL
    for held in (1, 2):  # memory for 1.5 and 2.5 views' features: 1 and 2 workers at most
        fraction = (held + 0.5) * one_view / physical_memory()
        workers = view_workers(views, FusionOptions(max_memory_fraction=fraction))
        assert workers == min(held, default_workers())


def test_default_grid_without_scene_bounds_covers_what_the_views_see(tiny_scene):
    from fusion.observations import lift_depth
    from fusion.scene_fusion import FusionOptions, default_grid

    scene = load_scene(tiny_scene)
    aoi = scene.bounds
    scene.bounds, scene.gsd = None, None
    grid = default_grid(scene, FusionOptions())
    x0, y0, x1, y1 = grid.bounds
    assert x0 <= aoi[0] and y0 <= aoi[1] and x1 >= aoi[2] and y1 >= aoi[3]
    v = scene.views[0]
    _, xyz = lift_depth(v.camera, v.read_depth())
    assert x0 <= xyz[:, 0].min() and x1 >= xyz[:, 0].max()
    nadir = next(v for v in scene.views if v.id.endswith("_n"))
    expected = np.nanmedian(nadir.read_depth()) / nadir.camera.K[0, 0]
    assert grid.gsd == pytest.approx(expected, rel=0.2)  # about the nadir image's GSD


def test_raster_prior_is_reported_and_optional(fused, tiny_scene, tmp_path):
    out, record, _ = fused
    q = record["quality"]
    assert "raster forest" not in record["class_source"]  # the paper's method by default
    assert q["classification_raster_forest_alone"]["overall_accuracy"] > 0.5
    proc = run_cli(
        "fusion", tiny_scene, "-o", tmp_path / "p", "--truth", tiny_scene, "--raster-prior"
    )
    assert proc.returncode == 0, proc.stderr
    with_prior = json.loads((tmp_path / "p" / "fusion.json").read_text())
    assert "--raster-prior" in with_prior["class_source"]
    prob = read_raster(tmp_path / "p" / "class_prob.tif")[0]
    seen = np.isfinite(prob[0])
    np.testing.assert_allclose(prob[:, seen].sum(axis=0), 1.0, atol=1e-5)
    # the same views and forest: the prior changes the classes, and the heights only where
    # the classes make crown cells (crown_tops: within 0.5 m of a tree cell) or change
    # which cells lie within 0.75 m of a building (sightings_clear_of_buildings)
    dsm, prior_dsm = (read_raster(d / "dsm.tif")[0][0] for d in (out, tmp_path / "p"))
    classes = [read_raster(d / "class.tif")[0][0] for d in (out, tmp_path / "p")]

    def near(mask, r):
        return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0

    moved = near((classes[0] == 3) | (classes[1] == 3), 2)
    moved |= near(classes[0] == 4, 3) != near(classes[1] == 4, 3)
    np.testing.assert_array_equal(dsm[~moved], prior_dsm[~moved])


def test_point_cloud_scored_against_a_scene_truth(tiny_scene, tmp_path):
    """The truth mesh's vertices as a cloud, fused and scored on the scene's grid."""
    bounds = load_scene(tiny_scene).bounds
    proc = run_cli(
        "fusion",
        "--points",
        tiny_scene / "truth" / "mesh.ply",
        "-o",
        tmp_path / "c",
        "--truth",
        tiny_scene,
        "--bounds",
        *bounds,
        "--gsd",
        "1.0",
    )
    assert proc.returncode == 0, proc.stderr
    q = json.loads((tmp_path / "c" / "fusion.json").read_text())["quality"]
    assert q["dtm"]["rmse_m"] < 1.0
    assert "dsm_mean_fusion" not in q  # no mean fusion of a cloud: absent, not invented


def test_an_existing_output_is_refused_before_any_work(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep").write_text("x")
    proc = run_cli("fusion", tmp_path / "no_scene", "-o", tmp_path / "out")
    assert proc.returncode == 2 and "output exists" in proc.stderr  # not the missing scene
    assert (tmp_path / "out" / "keep").exists()


def test_lifting_some_pixels_gives_the_points_of_the_whole_maps_lift(tiny_scene):
    """view_features lifts the pixels the fused surface fills on their own, beside the
    depth map's lift: each pixel's point must be the one the whole filled map's lift
    gives it, bit for bit, or the elevation cue (and the fused classes) would change."""
    from fusion.observations import lift_depth, lift_pixels

    v = load_scene(tiny_scene).views[0]
    depth = v.read_depth().copy()
    rng = np.random.default_rng(0)
    holes = np.sort(rng.choice(np.flatnonzero(np.isfinite(depth)), 500, replace=False))
    filled = depth.ravel()[holes].copy()
    depth.ravel()[holes] = np.nan
    pixels, xyz = lift_depth(v.camera, depth)
    alone = lift_pixels(v.camera, holes, filled, depth.shape[1])
    depth.ravel()[holes] = filled
    all_pixels, all_xyz = lift_depth(v.camera, depth)
    order = np.argsort(np.concatenate([pixels, holes]))
    assert np.array_equal(np.concatenate([pixels, holes])[order], all_pixels)
    assert np.array_equal(np.concatenate([xyz, alone])[order], all_xyz)
