"""Same seed, same bytes; a different seed, a different city; the CLI's contracts."""

import hashlib
from pathlib import Path

import pytest

from data_samples import generate as gen
from data_samples.generate import generate_sample
from tests.conftest import run_cli


def _digests(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_same_seed_gives_identical_files(tiny_scene, tmp_path):
    generate_sample(tmp_path / "again", "tiny", 0)
    a, b = _digests(tiny_scene), _digests(tmp_path / "again")
    assert a.keys() == b.keys()
    differing = [k for k in a if a[k] != b[k]]
    assert not differing, differing


def test_different_seed_gives_a_different_city(tiny_scene, tmp_path):
    generate_sample(tmp_path / "other", "tiny", 1)
    a, b = _digests(tiny_scene), _digests(tmp_path / "other")
    for name in ("truth/mesh.ply", "truth/dsm.tif", "images/v000_n.png", "scene.json"):
        assert a[name] != b[name], name


def test_existing_output_is_refused_without_overwrite(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    proc = run_cli("sample", out)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"workbench: error: {out}: output exists (pass --overwrite to replace it)"
    ]
    assert (out / "keep.txt").read_text() == "mine"


def test_failure_leaves_no_output(tmp_path, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("simulated failure while rendering")

    monkeypatch.setattr(gen, "_render_views", boom)
    with pytest.raises(RuntimeError):
        generate_sample(tmp_path / "out", "tiny", 0)
    assert list(tmp_path.iterdir()) == []  # neither the output nor a temporary folder


def test_cli_unexpected_error_is_one_line(tmp_path):
    proc = run_cli("sample", tmp_path / "x", "--calibration-error", "-1")
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "--calibration-error" in proc.stderr
    proc = run_cli("sample", tmp_path / "x", "--true-depth", "--depth-noise", "0.1")
    assert proc.returncode == 2 and "--depth-noise" in proc.stderr
    assert not (tmp_path / "x").exists()


def test_cli_help_lists_commands_and_units():
    proc = run_cli("--help")
    assert proc.returncode == 0
    for cmd in ("sample", "validate", "import-colmap", "demo"):
        assert cmd in proc.stdout
    proc = run_cli("sample", "--help")
    assert "pixels" in proc.stdout and "metres" in proc.stdout
