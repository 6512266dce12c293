"""The engine: tasks in order on threads or a Dask cluster, finished tasks kept for
--resume, the same products whatever runs them, one-line errors when the cluster or the
disk fails."""

import errno
import json
import pickle
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.conftest import interrupted_after, run_cli
from workbench.engine import (
    TaskStore,
    ThreadEngine,
    engine_for,
    open_store,
    partial_folder,
    run_signature,
)
from workbench.errors import WorkbenchError
from workbench.model_run import BuildingsOnDisk
from workbench.raster import read_raster

RASTERS = ("dsm.tif", "dtm.tif", "ortho.tif", "class_prob.tif", "class.tif", "count.tif")


def square(x):
    return x * x


def refuse(x):
    raise AssertionError(f"task {x} ran again")


def test_thread_engine_yields_in_order_and_keeps_what_finished(tmp_path):
    store = open_store(tmp_path / "out", {"a": 1}, resume=False)
    engine = ThreadEngine(3, store)
    assert list(engine.map(square, list(range(7)), stage="sq")) == [x * x for x in range(7)]
    assert store.finished("sq") == 7
    # started again with --resume: every task is in the store, none runs
    again = ThreadEngine(2, open_store(tmp_path / "out", {"a": 1}, resume=True))
    assert list(again.map(refuse, list(range(7)), stage="sq")) == [x * x for x in range(7)]


def test_resume_refuses_a_run_started_with_other_options(tmp_path):
    out = tmp_path / "out"
    open_store(out, {"parameters": {"tile": 512, "seed": 0}}, resume=False)
    with pytest.raises(WorkbenchError, match=r"parameters\.seed: .*drop --resume"):
        open_store(out, {"parameters": {"tile": 512, "seed": 1}}, resume=True)
    # without --resume the old partial run is discarded
    store = open_store(out, {"parameters": {"seed": 1}}, resume=False)
    assert store.empty() and json.loads((store.folder / "manifest.json").read_text()) == {
        "parameters": {"seed": 1}
    }


def test_the_number_of_workers_is_no_part_of_a_runs_signature():
    from fusion.options import FusionOptions

    a = run_signature(FusionOptions(workers=1), {"scene": "s"})
    assert a == run_signature(FusionOptions(workers=4), {"scene": "s"})
    assert a != run_signature(FusionOptions(seed=3), {"scene": "s"})


def test_a_full_disk_is_one_line_and_keeps_the_finished_tasks(tmp_path, monkeypatch):
    store = TaskStore(tmp_path / "partial")
    real_dump, calls = pickle.dump, []

    def dump(obj, f, **kw):
        calls.append(obj)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_dump(obj, f, **kw)

    monkeypatch.setattr(pickle, "dump", dump)
    with pytest.raises(WorkbenchError, match="disk full.*--resume") as err:
        list(ThreadEngine(1, store).map(square, [1, 2, 3, 4], stage="sq"))
    assert "\n" not in str(err.value)
    assert store.finished("sq") == 2 and not list((store.folder / "sq").glob("*.tmp-*"))


def fills_the_disk(x):
    if x == 2:
        raise OSError(errno.ENOSPC, "No space left on device", f"/scratch/{x}.npz")
    return x


def test_a_task_that_fills_the_disk_is_one_line(tmp_path):
    store = TaskStore(tmp_path / "partial")
    with pytest.raises(WorkbenchError, match=r"^/scratch/2.npz: disk full.*--resume"):
        list(ThreadEngine(1, store).map(fills_the_disk, [0, 1, 2, 3], stage="s"))
    assert store.finished("s") == 2


def test_a_command_that_fills_the_disk_is_one_line_and_keeps_its_finished_tasks(
    tiny_fusion, tmp_path, monkeypatch, capsys
):  # fmt: skip
    """The disk fills while the command itself writes (here the run's preview): one line
    naming the file and the finished tasks kept, exit 2, no output and no temporary
    folder; another OSError stays an internal error (exit 1); with space again,
    ``--resume`` finishes the run."""
    import workbench.model_run
    from workbench import cli

    real = workbench.model_run.write_rgb

    def full(path, image):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(workbench.model_run, "write_rgb", full)
    out = tmp_path / "blocks"
    argv = ["model", "blocks", str(tiny_fusion), "-o", str(out), "--workers", "1"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    partial = partial_folder(out)
    assert "\n" not in err and err.startswith("workbench: error: ")
    assert f"preview.png: disk full; the finished tasks are kept in {partial}" in err
    assert [p.name for p in tmp_path.iterdir()] == [partial.name]

    def denied(path, image):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(workbench.model_run, "write_rgb", denied)
    assert cli.main([*argv, "--resume"]) == 1
    assert "internal error: PermissionError" in capsys.readouterr().err
    monkeypatch.setattr(workbench.model_run, "write_rgb", real)
    assert cli.main([*argv, "--resume"]) == 0
    assert (out / "preview.png").exists() and not partial.exists()


def test_engine_for_leaves_nothing_when_nothing_finished(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(ValueError), engine_for(out, {"a": 1}, workers=1) as engine:
        list(engine.map(int, ["x"], stage="bad"))
    assert not partial_folder(out).exists()
    with engine_for(out, {"a": 1}, workers=1) as engine:
        assert list(engine.map(square, [2], stage="ok")) == [4]
    assert not partial_folder(out).exists()  # a finished run leaves no partial folder


def test_an_unreachable_scheduler_is_one_line(tiny_scene, tmp_path):
    out = tmp_path / "o"
    proc = run_cli("fusion", tiny_scene, "-o", out, "--scheduler", "tcp://127.0.0.1:9")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--scheduler tcp://127.0.0.1:9" in lines[0], proc.stderr
    assert not out.exists() and not partial_folder(out).exists()


def test_a_second_run_at_once_starts_its_cluster_quietly():
    """Two runs at once: the first holds the dashboard's default port, 8787; the second's
    local cluster must not warn about it, since its stderr may be a one-line error (this
    broke three one-line tests while another run's cluster was up)."""
    import socket
    import warnings

    from workbench.engine import local_cluster

    held = socket.socket()
    try:
        held.bind(("", 8787))
        held.listen()
    except OSError:
        pass  # taken already: the case itself
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            client, cluster = local_cluster(1)
            client.close()
            cluster.close()
    finally:
        held.close()
    assert not [w for w in caught if "already in use" in str(w.message)], caught


def test_a_local_cluster_is_quietened_only_when_it_closes():
    """A worker's heartbeat racing the scheduler's shutdown logs a 30-line traceback at
    ERROR after a run that succeeded: the workers' logs go to CRITICAL just before the
    cluster closes, and not before (a worker's errors while tasks run still show)."""
    import logging

    from workbench.engine import local_cluster, quiet_workers

    client, cluster = local_cluster(1)
    try:
        logs_errors = lambda: logging.getLogger("distributed.worker").isEnabledFor(logging.ERROR)  # noqa: E731
        before = list(client.run(logs_errors).values())
        quiet_workers(client)
        after = list(client.run(logs_errors).values())
    finally:
        client.close()
        cluster.close()
    assert before == [True] and after == [False], (before, after)


def test_a_local_cluster_keeps_the_shared_context_in_every_worker():
    """Dask's active memory manager would drop a worker's copy of a shared context
    between tasks; the next task there would unpickle it anew (and the fusion rebuild
    its ray-casting surface): each worker sees one object for the whole stage."""
    from workbench.engine import start_engine

    engine = start_engine(2)
    try:
        assert not engine.client.amm.running()
        shared = engine.share(np.zeros(1000))
        seen = set(engine.map(_worker_and_object, range(12), shared, stage="test"))
    finally:
        engine.close()
    assert len(seen) == 2  # two workers, one copy each


def test_a_long_task_does_not_hold_the_others_back_within_the_window(tmp_path):
    """One building that takes long, then six short ones: with 8 tasks in flight the other
    worker runs the short ones while the long one runs (all but the one Dask may have
    queued behind it); with the default window (twice the workers) it stops after three at
    most, waiting for the long one to be yielded. The results come in the tasks' order
    either way. (The long task is 40 times a short one.)"""
    from workbench.engine import start_engine

    engine = start_engine(2)
    try:
        finished = {}
        for in_flight in (8, None):
            log = tmp_path / f"log{in_flight}"
            log.mkdir()
            out = list(engine.map(_long_then_short, range(7), str(log), stage="test",
                                  in_flight=in_flight))  # fmt: skip
            assert out == list(range(7))
            # the short tasks that had finished when the long one did
            finished[in_flight] = int((log / "0").read_text())
    finally:
        engine.close()
    assert finished[8] >= 5 and finished[None] <= 3, finished


def _long_then_short(i, log):
    import time
    from pathlib import Path

    if i == 0:
        time.sleep(2.0)
        (Path(log) / "0").write_text(str(len(list(Path(log).iterdir()))))
    else:
        time.sleep(0.05)
        (Path(log) / str(i)).write_text("")
    return i


def _worker_and_object(i, context):
    import os
    import time

    time.sleep(0.3)
    return os.getpid(), id(context)


@pytest.fixture(scope="module")
def cluster():
    """A local Dask cluster of two worker processes, as `dask scheduler` and two
    `dask worker`s would be."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as c:  # fmt: skip
        yield c


def test_a_worker_that_cannot_read_an_image_names_it(cluster, tiny_scene, tmp_path):
    """An image the command saw but a worker cannot read (not mounted there, say): the
    worker's one-line error reaches the command as it was raised."""
    from distributed import Client

    from fusion.scene_fusion import fuse_views
    from workbench.engine import DaskEngine
    from workbench.errors import InputError
    from workbench.scene import load_scene

    scene_dir = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene_dir)
    scene = load_scene(scene_dir)  # checked and read by the command
    gone = scene.views[3].image_path
    gone.unlink()  # ... and not there for the workers
    engine = DaskEngine(Client(cluster.scheduler_address))
    try:
        with pytest.raises(InputError, match="not a readable image") as err:
            fuse_views(scene, engine=engine)
    finally:
        engine.close()
    assert err.value.path == str(gone) and "\n" not in str(err.value)


def test_the_scratch_folder_goes_although_a_task_still_writes_into_it(tmp_path, monkeypatch):
    """A failed run's siblings go on writing into the scratch folder (a cancelled task
    already running is not stopped): a file saved while the folder is removed (the CI
    once failed with ENOTEMPTY on this) is removed by the next try, and no error hides
    the task's."""
    from fusion import scene_fusion

    folder = tmp_path / "fusion-scratch"
    folder.mkdir()
    (folder / "0_probs.npy").write_bytes(b"x")
    rmtree, tries = shutil.rmtree, []

    def rmtree_as_a_sibling_saves(path, ignore_errors=False):
        tries.append(path)
        if len(tries) > 1:
            return rmtree(path, ignore_errors=ignore_errors)
        (path / "0_probs.npy").unlink()  # the files listed go ...
        (path / "1_probs.npy").write_bytes(b"x")  # ... a sibling saves one, and rmdir fails
        if not ignore_errors:
            raise OSError(errno.ENOTEMPTY, "Directory not empty", str(path))

    monkeypatch.setattr(scene_fusion.shutil, "rmtree", rmtree_as_a_sibling_saves)
    scene_fusion.remove_folder(folder, pause_s=0.0)
    assert not folder.exists() and len(tries) == 2


@pytest.mark.slow
def test_two_worker_processes_give_the_products_of_one_process(
    cluster, tiny_scene, tiny_fusion_one_process, tmp_path
):  # fmt: skip
    one, two = tiny_fusion_one_process, tmp_path / "two"
    proc = run_cli("fusion", tiny_scene, "-o", two, "--scheduler", cluster.scheduler_address)
    assert proc.returncode == 0, proc.stderr
    record = json.loads((two / "fusion.json").read_text())
    assert record["engine"] == "dask" and record["workers"] == 2
    assert record["scheduler"] == cluster.scheduler_address
    assert "its active memory manager drops the workers' copies" in proc.stderr  # the fixture's
    assert len(record["worker_peak_memory_mb"]) == 2
    for name in RASTERS:  # byte for byte
        a, _, _ = read_raster(one / name)
        b, _, _ = read_raster(two / name)
        np.testing.assert_array_equal(a, b, err_msg=name)
    for path, inputs in (("voxel", [tiny_scene, "--fusion", one]), ("superpixel", [one]),
                         ("lod", [one])):  # fmt: skip
        m1, m2 = tmp_path / f"{path}1", tmp_path / f"{path}2"
        for out, how in ((m1, ["--workers", "1"]),
                         (m2, ["--scheduler", cluster.scheduler_address])):  # fmt: skip
            proc = run_cli("model", path, *inputs, "-o", out, *how)
            assert proc.returncode == 0, proc.stderr
        assert json.loads((m2 / "model.json").read_text())["workers"] == 2
        meshes = sorted(p.name for p in (m1 / "buildings").iterdir())
        assert meshes == sorted(p.name for p in (m2 / "buildings").iterdir()) and meshes
        for name in meshes:
            assert (m1 / "buildings" / name).read_bytes() == (m2 / "buildings" / name).read_bytes()


@pytest.mark.slow
def test_a_killed_fusion_resumes_with_only_the_unfinished_tasks(
    tiny_scene, tiny_fusion_one_process, tmp_path
):  # fmt: skip
    out = tmp_path / "o"
    partial = partial_folder(out)
    cmd = [sys.executable, "-m", "workbench.cli", "fusion", str(tiny_scene), "-o", str(out),
           "--workers", "1"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while TaskStore(partial).finished("classification") < 5:
        assert proc.poll() is None and time.monotonic() < deadline, "the run ended first"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)  # no clean-up at all: a killed machine
    proc.wait()
    assert not out.exists()
    kept = TaskStore(partial).finished("classification")
    assert 5 <= kept < 20
    again = run_cli(*cmd[3:], "--resume")
    assert again.returncode == 0, again.stderr
    assert f"classification: {kept} of 20 tasks finished before, kept" in again.stderr
    assert "observations: 20 of 20 tasks finished before, kept" in again.stderr
    assert not partial.exists()
    whole = tiny_fusion_one_process  # the same command, run through
    for name in RASTERS:
        a, _, _ = read_raster(out / name)
        b, _, _ = read_raster(whole / name)
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_an_interrupted_voxel_run_redoes_only_its_unfinished_buildings(
    tiny_scene, tiny_fusion, tmp_path, monkeypatch
):  # fmt: skip
    import modeling.voxel.path as vp
    from modeling.voxel.options import VoxelOptions

    opts = VoxelOptions(workers=1)
    monkeypatch.setattr(vp, "GROUND_TILE", 64)  # the ground in 2 x 2 tiles
    whole = vp.run_voxel(tiny_scene, opts, fusion_dir=tiny_fusion)
    out = tmp_path / "vx"
    sig = run_signature(opts, {"scene": tiny_scene, "fusion": tiny_fusion})
    real_texture = vp.texture_task
    monkeypatch.setattr(vp, "texture_task", interrupted_after(real_texture, 3, []))
    with pytest.raises(KeyboardInterrupt), engine_for(out, sig, workers=1) as engine:
        vp.run_voxel(tiny_scene, opts, fusion_dir=tiny_fusion, engine=engine)
    store = TaskStore(partial_folder(out))
    assert store.finished("proxies") == 6 and store.finished("textures") == 3

    # resumed: no proxy is built again, three buildings are textured
    monkeypatch.setattr(vp, "building_proxy", refuse)
    textured = []
    monkeypatch.setattr(vp, "texture_task", lambda *a: textured.append(1) or real_texture(*a))
    with engine_for(out, sig, workers=1, resume=True) as engine:
        resumed = vp.run_voxel(tiny_scene, opts, fusion_dir=tiny_fusion, engine=engine)
        # with a task store the textured buildings wait on disk, not in the command
        assert isinstance(resumed.buildings, BuildingsOnDisk) and len(resumed.buildings) == 6
        buildings = list(resumed.buildings)
        # so does the ground, a tile at a time
        assert resumed.ground.folder is not None and resumed.dtm is None
        ground = list(resumed.ground)
        dtm = read_raster(resumed.raster_files["dtm"])[0][0]
    assert isinstance(whole.buildings, list)
    assert len(textured) == 3
    assert [b.id for b in buildings] == [b.id for b in whole.buildings]
    for a, b in zip(buildings, whole.buildings, strict=True):
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        np.testing.assert_array_equal(a.mesh.texture.image, b.mesh.texture.image)
    assert whole.ground.folder is None and len(ground) == len(whole.ground) == 4
    for a, b in zip(ground, whole.ground, strict=True):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.texture.image, b.texture.image)
    np.testing.assert_array_equal(dtm, whole.dtm.astype(np.float32))


def test_a_killed_runs_temporary_folder_goes_when_its_output_is_written_again(tmp_path):
    """A command killed (SIGKILL: no cleanup runs) leaves its temporary folder beside
    the output. The next run writing that output removes it; a running process's folder
    (this one's) and another machine's stay."""
    import os
    import socket

    from workbench.atomic import atomic_output_dir, killed_runs_folders

    out = tmp_path / "fusion"
    killed = ("import os, signal\nfrom workbench.atomic import atomic_output_dir\n"
              f"with atomic_output_dir({str(out)!r}) as tmp:\n"
              "    (tmp / 'dsm.tif').write_bytes(b'half')\n"
              "    os.kill(os.getpid(), signal.SIGKILL)\n")  # fmt: skip
    assert subprocess.run([sys.executable, "-c", killed]).returncode == -9
    left = list(tmp_path.glob(".fusion.tmp-*"))
    assert len(left) == 1 and (left[0] / "dsm.tif").exists() and not out.exists()
    running = tmp_path / f".fusion.tmp-{socket.gethostname()}-{os.getpid()}-x"
    elsewhere = tmp_path / ".fusion.tmp-another-machine-1-x"
    running.mkdir()
    elsewhere.mkdir()
    assert killed_runs_folders(out) == left
    with atomic_output_dir(out) as tmp:
        (tmp / "dsm.tif").write_bytes(b"whole")
    assert (out / "dsm.tif").read_bytes() == b"whole"
    assert sorted(tmp_path.iterdir()) == sorted([out, running, elsewhere])
