import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from data_samples.generate import generate_sample

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# the module fixtures that read one path's run of the tiny city (``tiny_models``)
PATH_FIXTURES = {"blocks_run": "blocks", "modelled": "parametric", "voxel_run": "voxel"}


def pytest_collection_modifyitems(items):
    """Under pytest-xdist (``make test``: ``--dist loadgroup``), the tests that read one
    path's ``tiny_models`` run share a worker, so that the session fixture models the
    tiny city once rather than once per worker (the block path's run takes 40 s)."""
    for item in items:
        names = set(item.fixturenames)
        groups = {path for name, path in PATH_FIXTURES.items() if name in names}
        for by_path in ("path_run", "path_name"):  # a test parametrized over the paths
            if by_path in names:
                groups.add(item.callspec.params[by_path])
        if item.get_closest_marker("xdist_group") is None and len(groups) == 1:
            item.add_marker(pytest.mark.xdist_group(groups.pop()))


def made_once(tmp_path_factory, name: str, make) -> Path:
    """``make(folder)`` once for the whole session, whichever pytest-xdist worker asks
    first; the others wait for it rather than make it again (the tiny city's fusion
    takes some 30 s). Returns the folder, which no test may change."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's folder, above each worker's own
    folder, done = root / "made_once" / name, root / "made_once" / f"{name}.done"
    folder.parent.mkdir(exist_ok=True)
    with open(root / "made_once" / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)  # a worker that failed making it
            folder.mkdir()
            make(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """The tiny sample city, seed 0, generated once per test session."""
    return (
        made_once(tmp_path_factory, "tiny", lambda d: generate_sample(d / "scene", "tiny", 0))
        / "scene"
    )


@pytest.fixture(scope="session")
def tiny_meta(tiny_scene) -> dict:
    return json.loads((tiny_scene / "sample.json").read_text())


def interrupted_after(fn, n: int, calls: list):
    """``fn`` counting its calls in ``calls`` (one item each), and stopped as by Ctrl-C
    (KeyboardInterrupt) when it is called once more after ``n``: a task of an interrupted
    run."""

    def wrapped(*args):
        if len(calls) == n:
            raise KeyboardInterrupt
        calls.append(1)
        return fn(*args)

    return wrapped


def run_cli(*args) -> subprocess.CompletedProcess:
    """Run ``workbench ARGS...`` in a fresh interpreter, capturing its output."""
    return subprocess.run(
        [sys.executable, "-m", "workbench.cli", *map(str, args)], capture_output=True, text=True
    )


def model_and_score(root: Path, truth: Path, *model_args) -> tuple[Path, dict, dict]:
    """Run ``workbench model MODEL_ARGS... -o ROOT/model``, then ``workbench compare`` it
    against ``truth``.

    Returns
    -------
    the model folder, its model.json, and its metrics from the comparison
    """
    out, report = root / "model", root / "report"
    proc = run_cli("model", *model_args, "-o", out)
    assert proc.returncode == 0, proc.stderr
    proc = run_cli("compare", out, "--truth", truth, "-o", report)
    assert proc.returncode == 0, proc.stderr
    return scored(root)


def scored(root: Path) -> tuple[Path, dict, dict]:
    """:func:`model_and_score`'s answer read back from ``root``."""
    metrics = json.loads((root / "report" / "metrics.json").read_text())["runs"]["model"]
    return root / "model", json.loads((root / "model" / "model.json").read_text()), metrics


@pytest.fixture(scope="session")
def tiny_fusion(tiny_scene, tmp_path_factory) -> Path:
    """``workbench fusion`` of the tiny city, as a user would run it (default options),
    once per session; scored against the truth (``--truth``: the record's quality) and its
    forest kept beside it (``--save-classifier``: ``forest.joblib``), neither of which
    changes the rasters."""

    def make(folder):
        proc = run_cli("fusion", tiny_scene, "-o", folder / "fusion", "--truth", tiny_scene,
                       "--save-classifier", folder / "forest.joblib")  # fmt: skip
        assert proc.returncode == 0, proc.stderr

    return made_once(tmp_path_factory, "tiny_fusion", make) / "fusion"


@pytest.fixture(scope="session")
def tiny_fusion_one_process(tiny_scene, tmp_path_factory) -> Path:
    """``workbench fusion --workers 1`` of the tiny city (no cluster: the command's own
    process), once per session: what the runs on other engines are compared with."""

    def make(folder):
        proc = run_cli("fusion", tiny_scene, "-o", folder / "fusion", "--workers", "1")
        assert proc.returncode == 0, proc.stderr

    return made_once(tmp_path_factory, "tiny_fusion_one", make) / "fusion"


@pytest.fixture(scope="session")
def tiny_models(tiny_scene, tiny_fusion, tmp_path_factory):
    """``tiny_models(NAME)``: modeling path NAME run on the tiny city as a user runs it
    (the scene and ``workbench fusion``'s rasters, default options) and scored by
    ``workbench compare``, once per session for every test that reads it: the model
    folder, its model.json and its metrics (:func:`model_and_score`)."""
    from modeling import PATHS

    runs = {}

    def run(name: str) -> tuple[Path, dict, dict]:
        if name not in runs:
            given = {"scene_dir": tiny_scene, "fusion_dir": tiny_fusion}
            args = PATHS[name].arguments(given)
            root = made_once(tmp_path_factory, f"tiny_{name}",
                             lambda d: model_and_score(d, tiny_scene, name, *args))  # fmt: skip
            runs[name] = scored(root)
        return runs[name]

    return run


def rewrite_raster(path: Path, data=None, **changes) -> None:
    """Rewrite a raster as a plain GeoTIFF, as another tool would, with ``data`` and
    profile ``changes`` (crs, transform) in place of its own."""
    import rasterio

    with rasterio.open(path) as src:
        profile, old = src.profile, src.read()
    profile.update(driver="GTiff", **changes)
    for key in ("blockxsize", "blockysize", "tiled", "interleave"):
        profile.pop(key, None)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(old if data is None else data)
