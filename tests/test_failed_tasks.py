"""A task that raises (a bug, a degenerate building) is left out with its reason, and the
run finishes the others; the machine's errors still stop it."""

import errno
import json

import pytest

from workbench import cli
from workbench.engine import DaskEngine, ThreadEngine, failure_reason, open_store


def inverse(x):
    return 1.0 / x


def unreadable(x):
    raise PermissionError(errno.EACCES, "Permission denied", "/data/view_3.png")


def left_out(x, why):
    return ("left out", x, why)


def test_a_failing_task_is_left_out_and_not_kept(tmp_path):
    store = open_store(tmp_path / "out", {}, resume=False)
    engine = ThreadEngine(2, store)
    got = list(engine.map(inverse, [1, 0, 2], stage="inv", on_failure=left_out))
    assert got[0] == 1.0 and got[2] == 0.5
    assert got[1][:2] == ("left out", 0)
    assert got[1][2].startswith("failed: ZeroDivisionError: float division by zero at ")
    assert got[1][2].endswith(" at tests/test_failed_tasks.py:14 in inverse")
    assert engine.failures == [{"stage": "inv", "key": "1", "reason": got[1][2][8:]}]
    assert engine.describe()["failed_tasks"] == engine.failures
    assert store.finished("inv") == 2  # the failed one is tried again by --resume
    with pytest.raises(ZeroDivisionError):  # a stage that lets no task fail
        list(ThreadEngine(1).map(inverse, [1, 0], stage="inv"))
    with pytest.raises(PermissionError):  # the machine's error stops the stage
        list(ThreadEngine(1).map(unreadable, [1], stage="read", on_failure=left_out))


def test_a_failing_task_on_a_cluster_is_left_out(tmp_path):
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:  # fmt: skip
        engine = DaskEngine(Client(cluster.scheduler_address))
        try:
            got = list(engine.map(inverse, [1, 0, 4, 0], stage="inv", on_failure=left_out))
            record = engine.describe()
        finally:
            engine.close()
    assert got[0] == 1.0 and got[2] == 0.25
    assert [g[:2] for g in (got[1], got[3])] == [("left out", 0)] * 2
    assert [f["key"] for f in record["failed_tasks"]] == ["1", "3"]
    assert record["failed_tasks"][0]["reason"].endswith("in inverse")


def test_the_reason_is_one_line_naming_where():
    try:
        raise ValueError("first line\nsecond line")
    except ValueError as e:
        why = failure_reason(e)
    assert why.startswith("ValueError: first line at tests/test_failed_tasks.py:")
    assert "\n" not in why


# the building task of each path on fused rasters, as its module calls it
TASKS = {
    "blocks": "modeling.blocks.path.building_task",
    "parametric": "modeling.parametric.path.building_task",
    "lod": "modeling.lod.path.building_lod",
    "superpixel": "modeling.superpixel.path.model_building_roofs",
    "voxel": "modeling.voxel.path.proxy_task",  # its task takes the footprint's position
}


@pytest.mark.parametrize("path_name", sorted(TASKS))
def test_one_failing_building_leaves_the_others_modelled(
    path_name, tiny_models, tiny_scene, tiny_fusion, tmp_path, monkeypatch, capsys, caplog
):  # fmt: skip
    """The first building's task raises (each time: the parametric path's rounds try it
    again): the command still exits 0, writes the other buildings as the run without the
    failure wrote them, and says what failed."""
    from modeling import PATHS

    module, attr = TASKS[path_name].rsplit(".", 1)
    task = getattr(__import__(module, fromlist=[attr]), attr)
    calls = []

    def first_fails(item, *args):
        calls.append(getattr(item, "id", item))  # a segment's number, a building's share
        if calls[-1] == calls[0]:
            raise RuntimeError("a degenerate building")
        return task(item, *args)

    monkeypatch.setattr(f"{module}.{attr}", first_fails)
    args = PATHS[path_name].arguments({"scene_dir": tiny_scene, "fusion_dir": tiny_fusion})
    out = tmp_path / "m"
    assert cli.main(["model", path_name, *map(str, args), "-o", str(out), "--workers", "1"]) == 0
    said = capsys.readouterr()
    assert "task(s) failed and were left out" in said.out
    assert "failed, left out (the others go on): RuntimeError: a degenerate building" in caplog.text
    model = json.loads((out / "model.json").read_text())
    for failed in model["failed_tasks"]:
        assert failed["reason"].startswith("RuntimeError: a degenerate building at ")
        assert failed["key"] == str(calls[0]) or path_name == "voxel"
    _, whole, _ = tiny_models(path_name)
    assert len(model["buildings"]) == whole["counts"]["buildings"] - 1

    def shape(b):  # the building as modelled, whatever its number
        return json.dumps([b["footprint"], b["faces"], b["eave_z"], b["ridge_z"]])

    assert {shape(b) for b in model["buildings"]} < {shape(b) for b in whole["buildings"]}
