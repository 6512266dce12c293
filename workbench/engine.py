"""Where a run's tasks execute: threads of this process, or a Dask cluster; and the
finished tasks kept on disk so that ``--resume`` redoes only the others.

A long stage is a list of independent tasks (a fusion tile, a view, a building). A path
hands them to :meth:`Engine.map`, which yields their results in the tasks' order,
whatever ran them and in whatever order they finished, so that the products do not
depend on the engine or the number of workers. Large read-only inputs (the views, a
forest, the DTM) go to :meth:`Engine.share` once and reach every task by reference.

:class:`ThreadEngine` runs the tasks in threads of this process (``--workers 1``, and
what the library's functions use when given no engine). :class:`DaskEngine` runs them on
a ``dask.distributed`` cluster: a local one of the machine's cores by default, or the
scheduler of ``--scheduler ADDRESS``, whose workers read the inputs from paths they all
see.

With a :class:`TaskStore`, each finished task's result is saved as it finishes, under
the stage's name and the task's key; a run started again with ``--resume`` loads those
and submits only the rest.
"""

from __future__ import annotations

import copy
import errno
import importlib
import json
import logging
import os
import pickle
import shutil
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from .errors import WorkbenchError
from .parallel import default_workers, ordered_map
from .progress import progress

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 10  # for a scheduler to answer, and for its first worker to join
MANIFEST = "manifest.json"


class TaskStore:
    """Finished tasks' results, one pickle each, under ``folder/<stage>/<key>.pkl``.

    A result is written to a temporary file and renamed, so a task is either finished
    in the store or absent, even when the run is killed while writing.

    Parameters
    ----------
    folder : path
        The run's partial folder (``.<OUT>.partial`` beside the output).
    """

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)

    def path(self, stage: str, key: str) -> Path:
        return self.folder / stage / f"{key}.pkl"

    def has(self, stage: str, key: str) -> bool:
        return self.path(stage, key).exists()

    def load(self, stage: str, key: str):
        with open(self.path(stage, key), "rb") as f:
            return pickle.load(f)

    def save(self, stage: str, key: str, result) -> None:
        path = self.path(stage, key)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp-{os.getpid()}")
        with full_disk_named(path, partial=tmp):
            with open(tmp, "wb") as f:
                pickle.dump(result, f, protocol=5)
            os.replace(tmp, path)

    def clear(self, stage: str) -> None:
        """Forget every result of ``stage``."""
        shutil.rmtree(self.folder / stage, ignore_errors=True)

    def finished(self, stage: str) -> int:
        """How many of ``stage``'s tasks are in the store."""
        d = self.folder / stage
        return len(list(d.glob("*.pkl"))) if d.is_dir() else 0

    def empty(self) -> bool:
        """Whether no task has finished (the folder holds its manifest at most), its
        nested stores' (:meth:`Engine.kept_in`) included."""
        return not any(self.folder.rglob("*.pkl"))

    def scratch(self, name: str) -> Path:
        """A folder of the store for a stage's own files (every worker must see it)."""
        d = self.folder / name
        d.mkdir(parents=True, exist_ok=True)
        return d


def disk_full(e: OSError, path=None) -> WorkbenchError | None:
    """The one-line error of a full disk (None for another OSError)."""
    if e.errno != errno.ENOSPC:
        return None
    return WorkbenchError(
        f"{path or e.filename}: disk full while keeping a finished task; the tasks finished "
        "before it are kept: free some space and run again with --resume"
    )


@contextmanager
def full_disk_named(path, partial: Path | None = None):
    """A full disk met inside the block becomes :func:`disk_full`'s one-line error naming
    ``path``, ``partial`` (a file half written) removed first; other errors pass."""
    try:
        yield
    except OSError as e:
        if partial is not None:
            partial.unlink(missing_ok=True)
        full = disk_full(e, path)
        if full is None:
            raise
        raise full from None


def _raise_disk_full(e: OSError) -> None:
    full = disk_full(e)
    if full is not None:
        raise full from None


def partial_folder(out: str | os.PathLike) -> Path:
    """Where a run writing ``out`` keeps its finished tasks: ``.<name>.partial`` beside it."""
    out = Path(out).absolute()
    return out.with_name(f".{out.name}.partial")


def open_store(out: str | os.PathLike, signature: dict, *, resume: bool) -> TaskStore:
    """The task store of a run writing ``out``.

    With ``resume``, the partial folder of an interrupted run is kept if it was started
    with the same ``signature`` (the options and inputs, as JSON); a different one is
    refused, naming the first field that differs. Without it, any earlier partial folder
    is discarded.
    """
    folder = partial_folder(out)
    signature = json.loads(json.dumps(signature, default=str))
    manifest = folder / MANIFEST
    if resume and manifest.exists():
        before = _flat(json.loads(manifest.read_text()))
        now = _flat(signature)
        if before != now:
            field = next(k for k in sorted(set(before) | set(now)) if before.get(k) != now.get(k))
            raise WorkbenchError(
                f"{folder}: {field}: the interrupted run was started with other inputs or "
                "options; drop --resume to start afresh"
            )
        log.info("resuming from %s", folder)
        return TaskStore(folder)
    if folder.exists():
        if resume:
            log.warning("%s has no manifest: starting afresh", folder)
        else:
            log.info("discarding the unfinished run in %s (--resume keeps it)", folder)
        shutil.rmtree(folder)
    elif resume:
        log.warning("nothing to resume for %s: starting afresh", out)
    folder.mkdir(parents=True)
    manifest.write_text(json.dumps(signature, indent=1))
    return TaskStore(folder)


def _flat(d: dict, prefix: str = "") -> dict:
    """A nested dict as {"a.b": value}."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def run_signature(options, inputs: dict) -> dict:
    """What an interrupted run must share with its resumption: its inputs (as absolute
    paths) and its options but the number of workers."""
    from .options import options_record

    params = {k: v for k, v in options_record(options).items() if k != "workers"}
    paths = {k: [str(Path(p).absolute()) for p in v] if isinstance(v, list | tuple)
             else str(Path(v).absolute()) if v is not None else None
             for k, v in inputs.items()}  # fmt: skip
    return {"inputs": paths, "parameters": params}


def discard_store(store: TaskStore | None) -> None:
    """Remove a finished run's partial folder."""
    if store is not None:
        shutil.rmtree(store.folder, ignore_errors=True)


# tasks in flight per worker for a stage whose results are small (a building's model, a
# few hundred kilobytes): enough that one large building does not hold the others back
BUILDINGS_IN_FLIGHT = 16


class Engine:
    """Runs a stage's tasks and yields their results in the tasks' order.

    Attributes
    ----------
    workers : int
        Tasks that can run at once.
    store : TaskStore or None
        Where finished tasks are kept (None: nothing is kept).
    failures : list of dict
        The tasks that raised and that their stage let fail (``on_failure`` of
        :meth:`map`): stage, key and reason, in the record's ``failed_tasks``.
    """

    workers: int = 1
    store: TaskStore | None = None
    name: str = ""
    failures: list

    @property
    def local(self) -> bool:
        """Whether the workers run on this machine (and share its memory)."""
        return True

    def share(self, obj):
        """A handle on ``obj`` to pass to every task of :meth:`map` (the object itself)."""
        return obj

    def map(
        self,
        fn: Callable,
        items: Sequence,
        *shared,
        stage: str,
        keys: Sequence[str] | None = None,
        in_flight: int | None = None,
        on_failure: Callable | None = None,
    ) -> Iterator:
        """``fn(item, *shared)`` for each item, yielded in the items' order.

        Parameters
        ----------
        fn : callable
            A module-level function (it may be sent to other processes).
        items : sequence
            One per task, small (sent with the task).
        *shared
            Handles from :meth:`share`, or small objects, passed to every task.
        stage : str
            The stage's name: its progress bar, and its folder in the store.
        keys : sequence of str, optional
            Unique keys of the tasks in the store (default: their positions). Without a
            store the results are not kept.
        in_flight : int, optional
            Tasks submitted and not yet yielded (default: twice the workers). The results
            of that many are held at most; a larger window keeps the workers busy when
            the tasks' costs differ (buildings: one large building otherwise holds the
            next ones back while the other workers wait).
        on_failure : callable, optional
            ``on_failure(item, reason)``, the result of a task that raised (reason: one
            line, the error and where it was raised), so that one building's failure
            leaves the others to finish. The failure is logged, added to
            :attr:`failures` and not kept in the store (``--resume`` tries it again).
            Errors of the machine rather than of the task (an ``OSError``, a
            ``MemoryError``, a :class:`~workbench.errors.WorkbenchError`, a worker
            killed) stop the stage whatever this says. Default: every error stops it.
        """
        raise NotImplementedError

    def _failed(self, stage: str, key: str, error: BaseException, on_failure, item):
        """``on_failure``'s result for a task that raised ``error``, or the error
        raised again when the stage lets no task fail or the error is the machine's."""
        if on_failure is None or not task_error(error):
            raise error
        reason = failure_reason(error)
        log.warning("%s task %s failed, left out (the others go on): %s", stage, key, reason)
        log.debug("%s task %s", stage, key, exc_info=error)
        self.failures.append({"stage": stage, "key": key, "reason": reason})
        return on_failure(item, f"failed: {reason}")

    def close(self) -> None:
        pass

    def kept_in(self, store: TaskStore | None, name: str) -> Engine:
        """The same workers, keeping their finished tasks in folder ``name`` of ``store``
        (a block of a fusion: its stages' names are those of every other block's)."""
        sub = copy.copy(self)
        sub.store = None if store is None else TaskStore(store.folder / name)
        return sub

    def describe(self) -> dict:
        """The engine for the run's record (and the tasks that failed, if any)."""
        return {"engine": self.name, "workers": self.workers, **self._failed_tasks()}

    def _failed_tasks(self) -> dict:
        return {"failed_tasks": list(self.failures)} if self.failures else {}

    def _keys(self, items, keys):
        return [str(k) for k in keys] if keys is not None else [str(i) for i in range(len(items))]

    def _log_resumed(self, stage: str, done: int, total: int) -> None:
        if done:
            log.info("%s: %d of %d tasks finished before, kept", stage, done, total)


class ThreadEngine(Engine):
    """The tasks in ``workers`` threads of this process (NumPy and OpenCV release the
    GIL), at most ``workers`` results waiting (:func:`~workbench.parallel.ordered_map`)."""

    name = "threads"

    def __init__(self, workers: int | None = None, store: TaskStore | None = None):
        self.workers = workers or default_workers()
        self.store = store
        self.failures = []

    def map(self, fn, items, *shared, stage, keys=None, in_flight=None, on_failure=None):
        keys = self._keys(items, keys)
        store = self.store
        if store is not None:
            self._log_resumed(stage, sum(store.has(stage, k) for k in keys), len(keys))

        def one(j):
            if store is not None and store.has(stage, keys[j]):
                return store.load(stage, keys[j])
            try:
                result = fn(items[j], *shared)
            except Exception as e:  # noqa: BLE001 - _failed raises what may not fail
                return self._failed(stage, keys[j], e, on_failure, items[j])
            if store is not None:
                store.save(stage, keys[j], result)
            return result

        try:
            yield from progress(ordered_map(one, range(len(items)), self.workers, in_flight),
                                stage, total=len(items))  # fmt: skip
        except OSError as e:  # a task's own files (the fusion's observations, say)
            _raise_disk_full(e)
            raise


class DaskEngine(Engine):
    """The tasks on a ``dask.distributed`` cluster, at most twice its threads submitted
    or waiting in order, so that the client's memory follows the workers, not the tasks.

    Parameters
    ----------
    client : distributed.Client
    cluster : distributed.LocalCluster, optional
        Closed with the engine (a cluster this run started).
    store : TaskStore, optional
    """

    name = "dask"

    def __init__(self, client, cluster=None, store: TaskStore | None = None):
        self.client, self.store, self.cluster = client, store, cluster
        self.failures = []
        self.settings = None  # dask settings kept while a local cluster lives
        self.workers = max(1, sum(client.nthreads().values()))
        self.address = client.scheduler.address

    @property
    def local(self) -> bool:
        return self.cluster is not None

    def share(self, obj):
        # one copy per worker, deserialised once; tasks receive that object
        return self.client.scatter(obj, broadcast=True, hash=False)

    def map(self, fn, items, *shared, stage, keys=None, in_flight=None, on_failure=None):
        from distributed import as_completed

        keys = self._keys(items, keys)
        store = self.store
        stored = [store is not None and store.has(stage, k) for k in keys]
        self._log_resumed(stage, sum(stored), len(keys))
        window = max(in_flight or 0, 2 * self.workers)
        run_id = os.urandom(4).hex()  # task keys unique on a shared scheduler
        done: dict[int, object] = {}
        index: dict = {}
        running = as_completed()
        next_submit, next_yield = 0, 0
        bar = progress(range(len(items)), stage)
        bar_iter = iter(bar)

        def submit_more():
            nonlocal next_submit
            while next_submit < len(items) and next_submit - next_yield < window:
                j = next_submit
                next_submit += 1
                if stored[j]:
                    continue
                key = f"{stage}-{keys[j]}-{run_id}"
                fut = self.client.submit(fn, items[j], *shared, pure=False, key=key)
                index[fut.key] = j
                running.add(fut)

        try:
            submit_more()
            while next_yield < len(items):
                if stored[next_yield]:
                    result = store.load(stage, keys[next_yield])
                elif next_yield in done:
                    result = done.pop(next_yield)
                else:
                    fut = next(running)
                    j = index.pop(fut.key)
                    try:
                        done[j] = _task_result(fut, stage, keys[j])
                    except Exception as e:  # noqa: BLE001 - _failed raises what may not fail
                        done[j] = self._failed(stage, keys[j], e, on_failure, items[j])
                    else:
                        if store is not None:
                            store.save(stage, keys[j], done[j])
                    finally:
                        fut.release()
                    continue
                next_yield += 1
                next(bar_iter, None)
                submit_more()
                yield result
        finally:
            bar.close()
            for fut in list(running.futures):
                fut.cancel()

    def close(self) -> None:
        """Close the client and a cluster this run started (again: nothing)."""
        if self.client.status in ("closing", "closed"):
            return
        if self.cluster is not None:
            quiet_workers(self.client)
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        if self.settings is not None:
            self.settings.__exit__(None, None, None)
            self.settings = None

    def describe(self) -> dict:
        """The engine, and each worker's peak resident memory so far (MiB)."""
        from .records import peak_memory_mb

        peaks = self.client.run(peak_memory_mb)
        return {"engine": self.name, "workers": self.workers,
                "scheduler": None if self.cluster is not None else self.address,
                "worker_peak_memory_mb": [round(peaks[w], 1) for w in sorted(peaks)],
                **self._failed_tasks()}  # fmt: skip


def task_error(error: BaseException) -> bool:
    """Whether ``error`` is the task's own (a bug, a degenerate building), which its
    stage may let fail, rather than the machine's or the input's: those stop a run."""
    machine = (OSError, MemoryError, WorkbenchError)
    return isinstance(error, Exception) and not isinstance(error, machine)


def failure_reason(error: BaseException) -> str:
    """One line: the error's type and first line, and the innermost frame of our code
    that raised it (``modeling/blocks/supports.py:321 in tier_supports``)."""
    message = str(error).splitlines()[0] if str(error) else ""
    frames = traceback.extract_tb(error.__traceback__)
    ours = [f for f in frames if "site-packages" not in f.filename] or frames
    where = ""
    if ours:
        f = ours[-1]
        path = Path(f.filename)
        root = Path(__file__).resolve().parents[1]  # the project's: its modules by their path
        name = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
        where = f" at {name}:{f.lineno} in {f.name}"
    return f"{type(error).__name__}: {message}{where}"


def _task_result(fut, stage: str, key: str):
    from distributed import KilledWorker

    try:
        return fut.result()
    except OSError as e:
        _raise_disk_full(e)
        raise
    except KilledWorker:
        raise WorkbenchError(
            f"{stage} task {key}: the workers running it died (out of memory, or killed); "
            "the finished tasks are kept: run again with --resume"
        ) from None


def start_engine(
    workers: int | None = None,
    scheduler: str | None = None,
    store: TaskStore | None = None,
    preload: tuple[str, ...] = (),
) -> Engine:
    """The engine of a command: ``--scheduler ADDRESS``'s cluster; else one worker in
    this process (``--workers 1``); else a local cluster of ``workers`` processes
    (default: this process's cores), one thread each. Dask workers import the modules
    ``preload`` names before the first task, so that no stage's time counts it."""
    if scheduler is not None:
        engine = DaskEngine(connect(scheduler), store=store)
    elif (workers or default_workers()) == 1:
        return ThreadEngine(1, store)
    else:
        import dask
        import distributed  # noqa: F401 - its defaults in dask's config, which the exit restores

        # the scheduler reads some of its log lengths when it first logs: for as long as it
        # lives (this process's dask settings, until the engine closes)
        settings = dask.config.set(SHORT_SCHEDULER_LOGS)
        try:
            engine = DaskEngine(*local_cluster(workers or default_workers()), store=store)
        except BaseException:
            settings.__exit__(None, None, None)
            raise
        engine.settings = settings
    engine.client.run(glibc_malloc_defaults)
    engine.client.run(one_opencv_thread)
    for module in preload:
        engine.client.run(importlib.import_module, module)
    return engine


def glibc_malloc_defaults() -> None:
    """Undo, in a Dask worker, the ``MALLOC_TRIM_THRESHOLD_`` its nanny sets: it also
    freezes glibc's mmap threshold, so that every large NumPy temporary is mapped and
    unmapped page by page. On ``small`` the views' observations took 2.5 times longer
    (10.1 s against 4.1 s on one core). The mmap threshold goes to glibc's own ceiling
    (32 MiB on 64 bits), where its dynamic threshold ends up by itself."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if name is None or not os.environ.get("MALLOC_TRIM_THRESHOLD_"):
        return
    libc = ctypes.CDLL(name)
    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    libc.mallopt(m_mmap_threshold, 32 * 2**20)
    libc.mallopt(m_trim_threshold, 64 * 2**20)


# Dask's active memory manager drops a worker's copy of a key that no task queued on it
# needs, every 2 s: a context shared with every worker (:meth:`Engine.share`) is then
# fetched and unpickled again by the worker's next task, which rebuilds what it built
# from it (the fusion's ray-casting surface: 8 s a time on the city, where 29 of 124
# views' tasks met a new copy). The contexts are few and bounded: keep every copy.
KEEP_SHARED_REPLICAS = {"distributed.scheduler.active-memory-manager.start": False}
# A local cluster's scheduler lives in the command's process, and its logs of transitions
# and events (100,000 entries each by default) keep what every task was sent with: on the
# city, the command grew by 250 MiB while its 495 views were classified, every task
# carrying the blocks' list of the tiles each view reaches. The logs are for operators'
# debugging; a run needs none.
SHORT_SCHEDULER_LOGS = {
    "distributed.admin.low-level-log-length": 100,  # the transitions and the events
    "distributed.admin.log-length": 100,
}


def one_opencv_thread() -> None:
    """OpenCV's filters on one thread in a Dask worker, as its nanny sets OpenMP and BLAS
    (``OMP_NUM_THREADS=1``, which OpenCV's own pool ignores): the workers are the
    parallelism, one per core, and two threads per worker on the cores of two workers
    only contend."""
    import cv2

    cv2.setNumThreads(1)


def quiet_workers(client) -> None:
    """Raise the log level of a local cluster's workers to CRITICAL before it closes.

    A worker whose heartbeat reaches the scheduler while it shuts down logs "Failed to
    communicate with scheduler during heartbeat" at ERROR with a 30-line traceback
    (dask/distributed#7192): once in the 2026-12-07 city bench, after a run that had
    succeeded. Its errors while the tasks ran still reach stderr; a worker already gone
    is left alone."""
    try:
        client.run(_quiet_distributed_logs)
    except Exception:  # noqa: BLE001 - closing goes on whatever the workers' state
        log.debug("the workers' logs could not be quietened before closing", exc_info=True)


def _quiet_distributed_logs() -> None:
    logging.getLogger("distributed").setLevel(logging.CRITICAL)


def local_cluster(workers: int):
    """A client of a new local cluster of ``workers`` processes of one thread, and the
    cluster."""
    import dask
    from distributed import Client, LocalCluster

    logging.getLogger("distributed").setLevel(logging.WARNING)  # its INFO is for operators
    # the dashboard on a free port: None still asks for 8787, and a second run at once
    # (another user's, or a test beside it) put "Port 8787 is already in use" on stderr
    with dask.config.set(KEEP_SHARED_REPLICAS):
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
            silence_logs=logging.ERROR,
        )  # fmt: skip
    return Client(cluster), cluster


def connect(address: str):
    """A client of the scheduler at ``address`` with at least one worker, or a one-line
    error naming it."""
    from distributed import Client

    logging.getLogger("distributed").setLevel(logging.WARNING)
    try:
        client = Client(address, timeout=f"{CONNECT_TIMEOUT_S}s")
    except (OSError, TimeoutError, ValueError) as e:
        raise WorkbenchError(
            f"--scheduler {address}: no Dask scheduler answered within "
            f"{CONNECT_TIMEOUT_S} s ({type(e).__name__})"
        ) from None
    try:
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError):
        client.close()
        raise WorkbenchError(
            f"--scheduler {address}: the scheduler has no worker (start `dask worker "
            f"{address}` on the machines that should compute)"
        ) from None
    if client.amm.running():
        log.warning(
            "--scheduler %s: its active memory manager drops the workers' copies of the "
            "shared inputs between tasks, which then fetch them again (start the scheduler "
            "with DASK_DISTRIBUTED__SCHEDULER__ACTIVE_MEMORY_MANAGER__START=False)", address
        )  # fmt: skip
    return client


@contextmanager
def engine_for(out, signature: dict, *, workers=None, scheduler=None, resume=False,
               preload: tuple[str, ...] = ()):  # fmt: skip
    """The engine and task store of a command writing ``out``; the store's partial
    folder goes once the block succeeds, and stays for ``--resume`` if it fails."""
    store = open_store(out, signature, resume=resume)
    try:
        engine = start_engine(workers, scheduler, store, preload)
    except BaseException:
        discard_store(store if store.empty() else None)
        raise
    try:
        yield engine
    except BaseException:
        # nothing finished (bad input, say): nothing to resume, no trace left
        discard_store(store if store.empty() else None)
        raise
    finally:
        engine.close()
    discard_store(store)
