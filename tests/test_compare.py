"""`workbench compare` end to end: the metrics checked against themselves on the truth."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from data_samples.truth_run import truth_fusion_run, truth_model_run
from tests.conftest import rewrite_raster, run_cli
from workbench.raster import read_raster, write_raster


@pytest.fixture(scope="module")
def report(tiny_scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    runs = [
        truth_model_run(tiny_scene, root / "same"),
        truth_model_run(tiny_scene, root / "up", shift=(0, 0, 1.0)),
        truth_model_run(tiny_scene, root / "less", drop=(1,)),
        truth_fusion_run(tiny_scene, root / "raster"),
    ]
    out = root / "report"
    proc = run_cli("compare", *runs, "--truth", tiny_scene, "-o", out)
    assert proc.returncode == 0, proc.stderr
    return out, json.loads((out / "metrics.json").read_text()), proc.stdout


def test_truth_against_itself_is_perfect(report):
    m = report[1]["runs"]["same"]
    for group in ("footprint_2d", "volume_3d"):
        for key in ("completeness", "correctness", "quality"):
            assert m[group][key] == 1.0
    assert m["height"]["rmse_m"] == pytest.approx(0.0, abs=1e-6)
    assert m["surface"]["hausdorff_m"] < 1e-3
    assert m["buildings"]["height_error_pct_median"] == pytest.approx(0.0, abs=1e-6)
    assert m["buildings"]["roof_type_accuracy"] == 1.0
    assert m["roofs"]["plane_angle_median_deg"] == pytest.approx(0.0, abs=0.01)
    assert m["complexity"]["watertight_fraction"] == 1.0
    objects = m["footprint_2d"]["objects"]
    assert objects["found"] == objects["truth_buildings"] == objects["model_buildings"]


def test_raster_truth_run_is_perfect(report):
    m = report[1]["runs"]["raster"]
    assert m["classification"]["overall_accuracy"] == 1.0
    assert m["classification"]["building_accuracy"] == 1.0
    assert m["dsm"]["rmse_m"] == 0.0 and m["dsm"]["valid_fraction"] == 1.0
    assert m["ortho"]["mae"] == 0.0
    assert m["cost"]["wall_s"] == 2.0


def test_model_one_metre_too_high(report):
    m = report[1]["runs"]["up"]
    assert m["height"]["rmse_m"] == pytest.approx(1.0, abs=1e-4)
    assert m["height"]["mae_m"] == pytest.approx(1.0, abs=1e-4)
    assert m["surface"]["hausdorff_m"] == pytest.approx(1.0, abs=1e-3)
    assert m["volume_3d_tolerant"]["quality"] == 1.0  # within the default 1 m tolerance
    # at the same altitude (the paper's), every building cell has 1 m too much
    assert m["volume_3d"]["vfp"] == pytest.approx(m["footprint_2d"]["tp"], rel=1e-3)
    assert m["volume_3d"]["vfn"] == pytest.approx(0.0, abs=1e-3)
    assert m["footprint_2d"]["quality"] == 1.0


def test_missing_building_costs_its_area(report, tiny_scene):
    ids = read_raster(tiny_scene / "truth" / "building_id.tif")[0][0]
    m = report[1]["runs"]["less"]
    # the building-only truth counts cells under trees too, so compare with the mesh truth
    same = report[1]["runs"]["same"]["footprint_2d"]["tp"]
    assert m["footprint_2d"]["fn"] + m["footprint_2d"]["tp"] == same
    assert m["footprint_2d"]["completeness"] == pytest.approx(1 - m["footprint_2d"]["fn"] / same)
    assert abs(m["footprint_2d"]["fn"] - np.count_nonzero(ids == 1)) <= 0.02 * same
    assert m["footprint_2d"]["correctness"] == 1.0
    o = m["footprint_2d"]["objects"]
    assert o["found"] == o["truth_buildings"] - 1
    rows = {r["id"]: r for r in report[1]["per_building"]["less"]}
    assert rows[1]["height_error_pct"] == -100.0 and rows[1]["covered_fraction"] == 0.0
    big = rows[1]["area_m2"] >= 50
    assert m["buildings"]["missed_over_50m2"] == int(big)
    assert report[1]["runs"]["same"]["buildings"]["missed_over_50m2"] == 0


def _numbers(doc, path=""):
    """{path: value} of every leaf of a JSON document."""
    if isinstance(doc, dict):
        return {k: v for key, x in doc.items() for k, v in _numbers(x, f"{path}/{key}").items()}
    if isinstance(doc, list):
        return {k: v for i, x in enumerate(doc) for k, v in _numbers(x, f"{path}[{i}]").items()}
    return {path: doc}


def test_figures_do_not_depend_on_the_window(report, tiny_scene):
    """compare reads the grid a window at a time (a city's does not fit in memory);
    windows of 37 cells, which cut the buildings, their boxes and the height jumps,
    give the figures of one window over the whole grid (the CLI's on the tiny city)."""
    from workbench.evaluate import EvaluationOptions, evaluate
    from workbench.runs import load_run
    from workbench.truth import open_scene_truth

    _, doc, _ = report
    truth = open_scene_truth(tiny_scene)
    assert max(truth.grid.shape) <= EvaluationOptions().window_cells
    for name, folder in doc["run_folders"].items():
        e = evaluate(load_run(folder, name), truth, EvaluationOptions(window_cells=37))
        got = _numbers(json.loads(json.dumps({"m": e.metrics, "b": e.buildings})))
        want = _numbers({"m": doc["runs"][name], "b": doc["per_building"][name]})
        assert got.keys() == want.keys()
        for key, value in want.items():
            if isinstance(value, float):
                assert got[key] == pytest.approx(value, rel=1e-9, abs=1e-12), (name, key)
            else:
                assert got[key] == value, (name, key)


def test_classes_are_scored_off_the_training_strokes(report, tiny_scene):
    strokes = read_raster(tiny_scene / "training" / "labels.tif")[0][0] > 0
    cls = read_raster(tiny_scene / "truth" / "class.tif")[0][0]
    c = report[1]["runs"]["raster"]["classification"]
    assert c["excluded_cells"] == np.count_nonzero(strokes & (cls > 0)) > 0
    assert c["scored_cells"] == np.count_nonzero(~strokes & (cls > 0))


def test_groups_without_data_are_absent(report):
    runs = report[1]["runs"]
    assert "classification" not in runs["same"] and "dsm" not in runs["same"]
    assert "surface" not in runs["raster"] and "complexity" not in runs["raster"]
    assert "texture" not in runs["same"]  # the truth has no seams to report


def test_report_is_one_self_contained_page(report):
    out, doc, stdout = report
    page = (out / "report.html").read_text()
    assert "http://" not in page.replace('xmlns="http://www.w3.org/2000/svg"', "")
    assert "https://" not in page
    assert page.count("data:image/png;base64,") >= 4 * 2 + 3  # maps, renders, truth
    for name in doc["runs"]:
        assert name in page and name in stdout
    assert "<svg" in page  # the per-building height error chart
    assert any((out / "figures").glob("render-*.png"))


def test_loose_file_truth_scores_what_it_can(tiny_scene, tmp_path):
    run = truth_model_run(tiny_scene, tmp_path / "same")
    truth = tiny_scene / "truth"
    out = tmp_path / "report"
    proc = run_cli(
        "compare", run, "--truth-dsm", truth / "dsm.tif",
        "--truth-footprints", truth / "footprints.geojson", "-o", out,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    m = json.loads((out / "metrics.json").read_text())["runs"]["same"]
    assert m["footprint_2d"]["quality"] > 0.97  # rasterised polygons vs ray-cast meshes
    assert "volume_3d" not in m and "surface" not in m  # no DTM, no mesh truth
    assert "classification" not in m


@pytest.mark.parametrize(
    "case, expect",
    [
        ("not_a_run", "not a run folder"),
        ("missing_mesh", "buildings[0].mesh"),
        ("bad_json", "not valid JSON"),
        ("names", "--names"),
        ("no_truth", "--truth"),
        ("crs", "dsm.tif: crs"),
        ("run_class", "class.tif: class: class codes [9] not in 0-4"),
        ("truth_class", "class.tif: truth class: class codes [6] not in 0-4"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tiny_scene, tmp_path, case, expect):
    run = tmp_path / "run"
    run.mkdir()
    args = [run, "--truth", tiny_scene]
    if case == "missing_mesh":
        (run / "model.json").write_text(json.dumps({"buildings": [{"id": 7}]}))
    elif case == "bad_json":
        (run / "model.json").write_text("{")
    elif case == "names":
        truth_model_run(tiny_scene, run, drop=())
        args += ["--names", "a", "b"]
    elif case == "no_truth":
        truth_model_run(tiny_scene, run)
        args = [run]
    elif case == "crs":
        run.rmdir()
        truth_fusion_run(tiny_scene, run)
        rewrite_raster(run / "dsm.tif", crs="EPSG:32631")
    elif case == "run_class":  # another tool's class scheme
        run.rmdir()
        truth_fusion_run(tiny_scene, run)
        codes = read_raster(run / "class.tif")[0]
        codes[codes == 4] = 9
        rewrite_raster(run / "class.tif", codes)
    elif case == "truth_class":  # ASPRS codes given as a truth (6 building)
        run.rmdir()
        truth_fusion_run(tiny_scene, run)
        shutil.copy(tiny_scene / "truth" / "class.tif", tmp_path / "class.tif")
        codes = read_raster(tmp_path / "class.tif")[0]
        codes[codes == 4] = 6
        rewrite_raster(tmp_path / "class.tif", codes)
        args = [run, "--truth-dsm", tiny_scene / "truth" / "dsm.tif", "--truth-class",
                tmp_path / "class.tif"]  # fmt: skip
    out = tmp_path / "report"
    proc = run_cli("compare", *args, "-o", out)
    assert proc.returncode == 2
    assert expect in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_existing_report_needs_overwrite(report, tiny_scene):
    out = report[0]
    proc = run_cli("compare", out.parent / "same", "--truth", tiny_scene, "-o", out)
    assert proc.returncode == 2 and "exists" in proc.stderr


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Chromium is not installed")
def test_report_renders_in_headless_chromium(report, tmp_path):
    cv2 = pytest.importorskip("cv2")
    shot = tmp_path / "report.png"
    proc = subprocess.run(
        [sys.executable, "scripts/screenshot.py", report[0] / "report.html", shot],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    img = cv2.imread(str(shot))
    assert img.shape[1] == 1400
    rows_with_ink = np.mean(img.min(axis=(1, 2)) < 200)  # text, tables and pictures
    assert rows_with_ink > 0.5


def test_a_hole_in_a_runs_ground_does_not_hide_a_missed_building(tiny_scene, tmp_path):
    """A model run's dtm.tif is its ground where no building stands; where it is NaN the
    truth's ground stands in, so the cells of a building the model missed still count."""
    less = truth_model_run(tiny_scene, tmp_path / "less", drop=(1,))
    holed = truth_model_run(tiny_scene, tmp_path / "holed", drop=(1,))
    dtm, grid, crs = read_raster(tiny_scene / "truth" / "dtm.tif")
    ids = read_raster(tiny_scene / "truth" / "building_id.tif")[0][0]
    raised = dtm[0] + 0.5  # a ground of its own: half a metre above the truth's
    raised[ids == 1] = np.nan  # unknown under the building it missed
    write_raster(holed / "dtm.tif", raised.astype(np.float32), grid, crs)
    out = tmp_path / "report"
    proc = run_cli("compare", less, holed, "--truth", tiny_scene, "-o", out)
    assert proc.returncode == 0, proc.stderr
    runs = json.loads((out / "metrics.json").read_text())["runs"]
    assert runs["holed"]["height"]["valid_fraction"] == 1.0
    assert runs["holed"]["height"]["rmse_m"] == pytest.approx(runs["less"]["height"]["rmse_m"])


def test_a_truth_dsm_with_nodata_is_scored_where_it_is_known(tiny_scene, tmp_path):
    """Real truth DSMs mark their holes with a nodata value (-9999 here), not NaN: those
    cells are unknown, not 9,999 m deep."""
    run = truth_model_run(tiny_scene, tmp_path / "same")
    dsm, grid, crs = read_raster(tiny_scene / "truth" / "dsm.tif")
    ids = read_raster(tiny_scene / "truth" / "building_id.tif")[0][0]
    holes = (ids == 1) & (np.arange(grid.height)[:, None] % 2 == 0)  # on a roof
    for name, nodata in (("nan", None), ("minus9999", -9999.0)):
        data = np.where(holes, np.nan if nodata is None else nodata, dsm[0]).astype(np.float32)
        write_raster(tmp_path / f"{name}.tif", data, grid, crs, nodata=nodata)
    scores = {}
    for name in ("nan", "minus9999"):
        out = tmp_path / f"report_{name}"
        proc = run_cli("compare", run, "--truth-dsm", tmp_path / f"{name}.tif",
                       "--truth-dtm", tiny_scene / "truth" / "dtm.tif", "--truth-footprints",
                       tiny_scene / "truth" / "footprints.geojson", "-o", out)  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        scores[name] = json.loads((out / "metrics.json").read_text())["runs"]["same"]
    assert holes.sum() > 50
    assert scores["minus9999"]["height"] == scores["nan"]["height"]
    assert scores["minus9999"]["height"]["rmse_m"] < 1.0  # with -9999 read as a height: 1,000s


def test_a_window_of_a_raster_on_another_grid_is_the_whole_ones_window(tmp_path):
    """The truth and the runs are read a window at a time onto the evaluation grid,
    from rasters on grids of their own (another cell size, another origin)."""
    from workbench.raster import Grid
    from workbench.truth import read_on_grid, sample_to_grid

    src = Grid(1000.3, 5000.9, 0.7, 53, 41)
    data = np.random.default_rng(0).random((1, 41, 53)).astype(np.float32)
    write_raster(tmp_path / "r.tif", data, src, crs="EPSG:32631")
    dst = Grid(995.0, 5003.0, 0.25, 170, 140)  # wider than the raster on every side
    whole = sample_to_grid(data, src, dst)
    for rows, cols in dst.tiles(33):
        got = read_on_grid(tmp_path / "r.tif", dst.window(rows, cols))
        np.testing.assert_array_equal(got, whole[:, rows, cols])
    assert np.isnan(whole).any() and np.isfinite(whole).any()
