"""The run contract, held by every registered modeling path: each is run as a user
would run it (from the tiny city's fused rasters, not its truth) and its run folder is
checked against what `workbench compare` and other tools rely on."""

import json
import subprocess
import sys

import numpy as np
import pytest
from rasterio.crs import CRS
from shapely.geometry import shape

from modeling import PATHS
from modeling.shared.roof_types import ROOF_TYPES
from tests.conftest import run_cli
from workbench.cityjson_check import check_city_model
from workbench.meshes import is_watertight, read_mesh
from workbench.model_run import BUILDING_KEYS, SCHEMA
from workbench.options import options_record
from workbench.raster import read_raster
from workbench.scene import load_scene


@pytest.fixture(scope="module", params=sorted(PATHS))
def path_run(request, tiny_models):
    # every input the tiny city has, the truth apart: the paths run as a user runs them
    out, record, metrics = tiny_models(request.param)
    return PATHS[request.param], out, record, metrics


def test_model_json_follows_the_schema(path_run, tiny_scene):
    spec, _, record, _ = path_run
    assert record["schema"] == SCHEMA and record["method"] == spec.name
    made = record["provenance"]
    assert made["command"].startswith(f"workbench model {spec.name} ")
    assert made["workbench_version"] and made["libraries"]["numpy"] == np.__version__
    assert set(record["parameters"]) >= set(options_record(spec.options()))
    assert CRS.from_user_input(record["crs"]) == load_scene(tiny_scene).crs
    assert set(record["counts"]) >= {"buildings", "faces", "watertight"}
    assert record["counts"]["buildings"] == len(record["buildings"]) >= 4
    assert all(s["wall_s"] >= 0 and s["peak_memory_mb"] > 0 for s in record["stages"].values())
    ids = [b["id"] for b in record["buildings"]]
    assert len(set(ids)) == len(ids)


def test_every_building_is_a_closed_mesh_with_its_common_record(path_run):
    _, out, record, _ = path_run
    for b in record["buildings"]:
        assert list(b)[: len(BUILDING_KEYS)] == list(BUILDING_KEYS)
        vertices, triangles = read_mesh(out / b["mesh"])
        assert len(triangles) == b["faces"] and b["watertight"]
        assert is_watertight(vertices, triangles)
        assert b["roof_type"] in ROOF_TYPES and b["lod"] in ("1.3", "2.2")
        assert b["base_z"] < b["eave_z"] <= b["ridge_z"]
        assert vertices[:, 2].max() == pytest.approx(b["ridge_z"], abs=0.01)
        footprint = shape(b["footprint"])
        lo, hi = vertices[:, :2].min(axis=0), vertices[:, :2].max(axis=0)
        assert footprint.bounds == pytest.approx((*lo, *hi), abs=0.01)
        for p in b["planes"]:
            assert np.linalg.norm(p["normal"]) == pytest.approx(1, abs=1e-3) and p["area_m2"] > 0
        for suffix in (".ply", ".obj", ".mtl"):
            assert (out / "buildings" / f"{b['id']}{suffix}").exists()


def test_the_folder_holds_scene_ground_dtm_and_preview(path_run, tiny_scene):
    _, out, record, _ = path_run
    for name in ("scene.ply", "scene.obj", "scene.mtl", "ground.ply", "ground.obj",
                 "preview.png"):  # fmt: skip
        assert (out / name).exists(), name
    scene_v, scene_t = read_mesh(out / "scene.ply")
    ground_v, ground_t = read_mesh(out / "ground.ply")
    assert len(scene_t) == record["counts"]["faces"] + len(ground_t)
    dtm, grid, crs = read_raster(out / "dtm.tif")
    assert dtm.dtype == np.float32 and crs == load_scene(tiny_scene).crs
    true_dtm, tgrid, _ = read_raster(tiny_scene / "truth" / "dtm.tif")
    # the ground the path stood its buildings on lies on the true terrain
    X, Y = grid.cell_centers()
    r, c = tgrid.cell_index(X.ravel(), Y.ravel(), clip=True)
    err = dtm[0].ravel() - true_dtm[0][r, c]
    assert np.nanmedian(np.abs(err)) < 0.3


def test_model_city_json_is_cityjson_every_reader_takes(path_run):
    spec, out, record, _ = path_run
    path = out / "model.city.json"
    doc = json.loads(path.read_text())
    assert check_city_model(doc) == []  # every solid closed, outward, planar, not crossing
    # both readers in a child: cjio rounds every float the json module writes to 6 decimals
    # (it patches json.encoder at import), which would change later tests' files
    strict = "import cityjson_lib, sys; cityjson_lib.CityModel.parse_document_bytes(open(sys.argv[1], 'rb').read())"  # noqa: E501
    proc = subprocess.run([sys.executable, "-c", strict, path], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr  # cityjson-lib: a strict reader
    cjio = "from cjio.cjio import cli; cli()"
    proc = subprocess.run([sys.executable, "-c", cjio, path, "info", "--long"],
                          capture_output=True, text=True)  # fmt: skip
    info = proc.stdout
    assert proc.returncode == 0 and f"Building ({len(record['buildings'])})" in info
    assert "semantics surfaces = ['GroundSurface', 'RoofSurface', 'WallSurface']" in info
    for b in record["buildings"]:
        obj = doc["CityObjects"][f"{spec.name}-{b['id']}"]
        lods = [g["lod"] for g in obj["geometry"]]
        assert lods[:2] == ["0", "1.2"] and lods[-1] == b["lod"]  # the LOD path adds 1.3
        a = obj["attributes"]
        assert a["roofType"] == b["roof_type"] and a["ridge_z"] == b["ridge_z"]
        assert b["base_z"] < a["lod1_z"] <= b["ridge_z"]
        if spec.name != "voxel":  # the raster paths: the model's distance to the DSM
            # the parametric path's mansard reaches 2.2 m (0.11 m before the fusion's
            # one-sided normals): the fused DSM reads more of the cells a fifth under its
            # eave at the eave, its rectangle registers 0.3 m wider and takes in ground
            # cells; against the truth the run's height RMSE off the jumps went 1.89 ->
            # 1.57 m
            assert 0 < a["rmse_m"] < 2.5


def test_compare_scores_the_run(path_run):
    spec, _, _, m = path_run  # scored by `workbench compare OUT --truth SCENE`
    assert m["method"] == spec.name and m["complexity"]["watertight_fraction"] == 1.0
    assert m["footprint_2d"]["objects"]["found"] >= 4


@pytest.mark.parametrize("name", sorted(PATHS))
def test_a_missing_input_is_one_line_and_writes_nothing(name, tmp_path):
    spec = PATHS[name]
    missing = tmp_path / "nowhere"
    args = [missing for item in spec.inputs if item.flag is None]
    proc = run_cli("model", name, *args, "-o", tmp_path / "out")
    assert proc.returncode == 2 and str(missing) in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", sorted(PATHS))
def test_an_existing_output_is_refused_before_any_work(name, tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep").write_text("x")
    args = [tmp_path / "nowhere" for item in PATHS[name].inputs if item.flag is None]
    proc = run_cli("model", name, *args, "-o", tmp_path / "out")
    assert proc.returncode == 2 and "exists" in proc.stderr  # not the missing input
    assert (tmp_path / "out" / "keep").exists()
