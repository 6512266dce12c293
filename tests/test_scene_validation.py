"""Every validation path of the scene format: one error naming the file and the field."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from workbench.errors import InputError
from workbench.scene import load_scene


@pytest.fixture
def scene_copy(tiny_scene, tmp_path) -> Path:
    """A private copy of the tiny scene (images and depth of 2 views only, for speed)."""
    doc = json.loads((tiny_scene / "scene.json").read_text())
    doc["images"] = doc["images"][:2]
    dst = tmp_path / "scene"
    for sub in ("images", "depth", "training"):
        (dst / sub).mkdir(parents=True)
    for v in doc["images"]:
        shutil.copy(tiny_scene / v["file"], dst / v["file"])
        shutil.copy(tiny_scene / v["depth"], dst / v["depth"])
    shutil.copy(tiny_scene / "footprints_gis.geojson", dst / "footprints_gis.geojson")
    shutil.copy(tiny_scene / "training" / "labels.tif", dst / "training" / "labels.tif")
    shutil.copytree(tiny_scene / "truth", dst / "truth")
    (dst / "scene.json").write_text(json.dumps(doc))
    return dst


def _edit(scene: Path, fn):
    doc = json.loads((scene / "scene.json").read_text())
    fn(doc)
    (scene / "scene.json").write_text(json.dumps(doc))


def _expect(scene: Path, field: str, words: str):
    with pytest.raises(InputError) as exc:
        load_scene(scene)
    assert exc.value.field == field, str(exc.value)
    assert words in exc.value.message, str(exc.value)
    assert "\n" not in str(exc.value)
    return exc.value


def test_copy_is_valid(scene_copy):
    s = load_scene(scene_copy)
    assert len(s.views) == 2 and s.views[0].depth_path is not None


def test_missing_scene(tmp_path):
    with pytest.raises(InputError, match="scene file not found"):
        load_scene(tmp_path)


def test_not_json(scene_copy):
    (scene_copy / "scene.json").write_text("{ nope")
    _expect(scene_copy, None, "not valid JSON")


def test_missing_crs(scene_copy):
    _edit(scene_copy, lambda d: d.pop("crs"))
    _expect(scene_copy, "crs", "missing")


def test_unknown_crs(scene_copy):
    _edit(scene_copy, lambda d: d.update(crs="EPSG:999999"))
    _expect(scene_copy, "crs", "unknown CRS")


def test_geographic_crs(scene_copy):
    _edit(scene_copy, lambda d: d.update(crs="EPSG:4326"))
    _expect(scene_copy, "crs", "projected")


@pytest.mark.parametrize(
    "key,value,words",
    [
        ("K", [[1, 0, 0], [0, 1, 0]], "expected shape (3, 3)"),
        ("K", [[500, 0, 320], [0, 500, 240], [0, 1, 1]], "[0, 0, 1]"),
        ("K", [[-500, 0, 320], [0, 500, 240], [0, 0, 1]], "positive"),
        ("K", "abc", "array of numbers"),
        ("R", [[1, 0, 0], [0, 1, 0], [0, 0, -1]], "not a rotation"),
        ("R", [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]], "not a rotation"),
        ("R", [[1, 0, 0], [0, 1, 0]], "expected shape (3, 3)"),
        ("t", [1, 2], "expected shape (3,)"),
        ("t", [1, 2, float("nan")], "non-finite"),
        ("width", 640.5, "positive integer"),
        ("height", 0, "positive integer"),
        ("distortion", [0.1, 0.2], "k1 k2 p1 p2"),
    ],
)
def test_bad_camera_fields(scene_copy, key, value, words):
    _edit(scene_copy, lambda d: d["images"][1].update({key: value}))
    _expect(scene_copy, f"images[1].{key}", words)


def test_missing_camera_field(scene_copy):
    _edit(scene_copy, lambda d: d["images"][0].pop("R"))
    _expect(scene_copy, "images[0].R", "missing")


def test_missing_image(scene_copy):
    (scene_copy / "images" / "v000_n.png").unlink()
    _expect(scene_copy, "images[0].file", "image not found")


def test_image_size_differs_from_camera(scene_copy):
    _edit(scene_copy, lambda d: d["images"][0].update(width=800))
    _expect(scene_copy, "images[0].file", "image is 640x480 but the camera says 800x480")


def test_depth_wrong_shape(scene_copy):
    np.save(scene_copy / "depth" / "v000_n.npy", np.zeros((10, 10), np.float32))
    _expect(scene_copy, "images[0].depth", "depth map is (10, 10)")


def test_depth_not_float(scene_copy):
    np.save(scene_copy / "depth" / "v000_n.npy", np.zeros((480, 640), np.int16))
    _expect(scene_copy, "images[0].depth", "expected float")


def test_depth_missing(scene_copy):
    (scene_copy / "depth" / "v000_n.npy").unlink()
    _expect(scene_copy, "images[0].depth", "not found")


def test_duplicate_view_id(scene_copy):
    _edit(scene_copy, lambda d: d["images"][1].update(id=d["images"][0]["id"]))
    _expect(scene_copy, "images[1].id", "duplicate")


def test_optional_file_missing(scene_copy):
    _edit(scene_copy, lambda d: d.update(dsm="nope.tif"))
    _expect(scene_copy, "dsm", "file not found: nope.tif")


def test_training_labels_bad_codes(scene_copy):
    from workbench.raster import read_raster, write_raster

    data, grid, crs = read_raster(scene_copy / "training" / "labels.tif")
    data[0, 0, 0] = 9
    write_raster(scene_copy / "training" / "labels.tif", data[0], grid, crs, nodata=0)
    _expect(scene_copy, "training_labels", "class codes [9]")


def test_raster_crs_must_match(scene_copy):
    from rasterio.crs import CRS

    from workbench.raster import read_raster, write_raster

    data, grid, _ = read_raster(scene_copy / "truth" / "dsm.tif")
    write_raster(scene_copy / "dsm.tif", data[0], grid, CRS.from_epsg(32631))
    _edit(scene_copy, lambda d: d.update(dsm="dsm.tif"))
    _expect(scene_copy, "dsm", "CRS differs")


@pytest.mark.parametrize(
    "geojson,field,words",
    [
        ("[]", "type", "FeatureCollection"),
        (
            '{"type": "FeatureCollection", "features": [{"type": "Feature", "geometry": '
            '{"type": "Point", "coordinates": [0, 0]}}]}',
            "features[0].geometry",
            "Polygon",
        ),
        (
            '{"type": "FeatureCollection", "features": [{"type": "Feature", "geometry": '
            '{"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 1]]]}}]}',
            "features[0].geometry.coordinates ring 0",
            "closed",
        ),
        (
            '{"type": "FeatureCollection", "features": [{"type": "Feature", "geometry": '
            '{"type": "Polygon", "coordinates": [[[0, 0], [1, "a"], [1, 1], [0, 0]]]}}]}',
            "features[0].geometry.coordinates ring 0",
            "number pairs",
        ),
        (
            '{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": '
            '{"height": -3}, "geometry": {"type": "Polygon", "coordinates": '
            "[[[0, 0], [1, 0], [1, 1], [0, 0]]]}}]}",
            "features[0].properties.height",
            "positive",
        ),
        ("{ broken", None, "not valid JSON"),
    ],
)
def test_invalid_geojson(scene_copy, geojson, field, words):
    (scene_copy / "footprints_gis.geojson").write_text(geojson)
    err = _expect(scene_copy, field, words)
    assert err.path.endswith("footprints_gis.geojson")


def test_cli_reports_one_line_exit_2(scene_copy):
    _edit(scene_copy, lambda d: d["images"][1].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]))
    proc = subprocess.run(
        [sys.executable, "-m", "workbench.cli", "validate", str(scene_copy)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "scene.json: images[1].R: not a rotation matrix" in lines[0]
    assert "Traceback" not in proc.stderr


def test_cli_validate_ok(scene_copy):
    proc = subprocess.run(
        [sys.executable, "-m", "workbench.cli", "validate", str(scene_copy), "--json"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["views"] == 2 and summary["views_with_depth"] == 2
