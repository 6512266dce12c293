"""COLMAP import: cameras and poses survive the round trip; bad models are one-line errors."""

import json
import shutil

import numpy as np
import pytest

from workbench.colmap import import_colmap, quaternion_to_rotation, read_colmap_depth
from workbench.errors import InputError
from workbench.scene import load_scene


def rotation_to_quaternion(R):
    """Hand-written inverse of quaternion_to_rotation (w first, w >= 0)."""
    w = np.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    if w > 1e-3:
        x = (R[2, 1] - R[1, 2]) / (4 * w)
        y = (R[0, 2] - R[2, 0]) / (4 * w)
        z = (R[1, 0] - R[0, 1]) / (4 * w)
        return np.array([w, x, y, z])
    x = np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = (R[0, 1] + R[1, 0]) / (4 * x)
    z = (R[0, 2] + R[2, 0]) / (4 * x)
    w = (R[2, 1] - R[1, 2]) / (4 * x)
    return np.array([w, x, y, z])


@pytest.fixture
def colmap_model(tiny_scene, tmp_path):
    """The tiny scene's written cameras as a COLMAP text model (PINHOLE, +0.5 px centres)."""
    doc = json.loads((tiny_scene / "scene.json").read_text())
    views = doc["images"][:4]
    model = tmp_path / "sparse"
    model.mkdir()
    images = tmp_path / "imgs"
    images.mkdir()
    cams = ["# Camera list"]
    imgs = ["# Image list"]
    for i, v in enumerate(views, start=1):
        K = np.array(v["K"])
        fx, fy, cx, cy = (
            float(K[0, 0]),
            float(K[1, 1]),
            float(K[0, 2]) + 0.5,
            float(K[1, 2]) + 0.5,
        )
        cams.append(f"{i} PINHOLE {v['width']} {v['height']} {fx!r} {fy!r} {cx!r} {cy!r}")
        q = rotation_to_quaternion(np.array(v["R"]))
        t = v["t"]
        imgs.append(
            f"{i} {' '.join(repr(float(c)) for c in q)} {t[0]!r} {t[1]!r} {t[2]!r} "
            f"{i} {v['id']}.png"
        )
        imgs.append("" if i % 2 else "1.0 2.0 -1")
        shutil.copy(tiny_scene / v["file"], images / f"{v['id']}.png")
    (model / "cameras.txt").write_text("\n".join(cams) + "\n")
    (model / "images.txt").write_text("\n".join(imgs) + "\n")
    return model, images, views


def test_quaternion_roundtrip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= np.sign(q[0])
        R = quaternion_to_rotation(q)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(rotation_to_quaternion(R), q, atol=1e-9)


def test_import_reproduces_the_cameras(colmap_model, tmp_path, tiny_scene):
    model, images, views = colmap_model
    path = import_colmap(model, images, tmp_path / "scene", crs=load_scene(tiny_scene).crs.to_wkt())
    scene = load_scene(path)
    assert [v.id for v in scene.views] == [v["id"] for v in views]
    for got, want in zip(scene.views, views, strict=True):
        np.testing.assert_allclose(got.camera.K, want["K"], atol=1e-9)
        np.testing.assert_allclose(got.camera.R, want["R"], atol=1e-9)
        np.testing.assert_allclose(got.camera.t, want["t"], atol=1e-9)
        assert got.image_path.read_bytes() == (images / f"{want['id']}.png").read_bytes()


def test_import_reads_colmap_depth_maps(colmap_model, tmp_path):
    model, images, views = colmap_model
    depth_dir = tmp_path / "depth_maps"
    depth_dir.mkdir()
    w, h = views[0]["width"], views[0]["height"]
    truth = np.random.default_rng(0).uniform(10, 50, (h, w)).astype(np.float32)
    truth[5, 7] = 0.0  # COLMAP's "unknown"
    with open(depth_dir / f"{views[0]['id']}.png.geometric.bin", "wb") as f:
        f.write(f"{w}&{h}&1&".encode())
        # COLMAP's write_array: array.T reshaped in Fortran order, i.e. rows contiguous
        f.write(truth.T.reshape(-1, order="F").astype("<f4").tobytes())
    path = import_colmap(model, images, tmp_path / "scene", crs="EPSG:32631", depth_dir=depth_dir)
    scene = load_scene(path)
    d = scene.views[0].read_depth()
    assert np.isnan(d[5, 7])
    d[5, 7] = 0.0
    np.testing.assert_array_equal(d, truth)
    assert scene.views[1].depth_path is None
    np.testing.assert_array_equal(
        read_colmap_depth(depth_dir / f"{views[0]['id']}.png.geometric.bin")[0], d[0]
    )


def test_unsupported_model_names_file_and_camera(colmap_model, tmp_path):
    model, images, _ = colmap_model
    text = (model / "cameras.txt").read_text().replace("PINHOLE", "FULL_OPENCV", 1)
    (model / "cameras.txt").write_text(text)
    with pytest.raises(InputError) as exc:
        import_colmap(model, images, tmp_path / "scene", crs="EPSG:32631")
    assert exc.value.path.endswith("cameras.txt")
    assert "camera 1" in exc.value.field and "FULL_OPENCV" in exc.value.message
    assert not (tmp_path / "scene").exists()


def test_missing_image_is_an_error_and_nothing_is_written(colmap_model, tmp_path):
    model, images, views = colmap_model
    (images / f"{views[2]['id']}.png").unlink()
    with pytest.raises(InputError, match="not found"):
        import_colmap(model, images, tmp_path / "scene", crs="EPSG:32631")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imgs", "sparse"]


def test_crs_is_required_to_be_projected(colmap_model, tmp_path):
    model, images, _ = colmap_model
    with pytest.raises(InputError, match="projected"):
        import_colmap(model, images, tmp_path / "scene", crs="EPSG:4326")
