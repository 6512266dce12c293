"""Time and peak memory of each stage of a run, for the run's JSON record."""

from __future__ import annotations

import contextlib
import importlib.metadata
import platform
import resource
import sys
import time

# the distributions whose version can change a product
LIBRARIES = (
    "numpy", "scipy", "scikit-learn", "scikit-image", "opencv-python-headless", "open3d-cpu",
    "PyMaxflow", "rasterio", "laspy", "shapely",
)  # fmt: skip


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, MiB.

    On Linux the high-water mark of /proc/self/status: ``ru_maxrss`` survives the exec
    of a forked child, so a process started by a large one would report its parent's
    size as its own.
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024


def run_speed(seconds: float, buildings: int, cells: int) -> dict:
    """A modeling run's speed and memory for its record: seconds per building and per
    megapixel of its grid (``cells``), and the process's peak memory so far (MiB)."""
    return {"seconds_per_building": round(seconds / max(buildings, 1), 3),
            "seconds_per_megapixel": round(seconds / (cells / 1e6), 3),
            "peak_memory_mb": round(peak_memory_mb(), 1)}  # fmt: skip


class StageTimer:
    """Collects ``{stage: {"wall_s", "peak_memory_mb"}}``; peak memory is the process's
    peak so far when the stage ends (it never decreases). A stage run more than once (in
    each block of a fusion) adds its times up."""

    def __init__(self):
        self.stages: dict[str, dict] = {}

    @contextlib.contextmanager
    def stage(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            before = self.stages.get(name, {}).get("wall_s", 0.0)  # a stage run again adds up
            self.stages[name] = {
                "wall_s": round(before + time.perf_counter() - t0, 3),
                "peak_memory_mb": round(peak_memory_mb(), 1),
            }

    def add(self, stages: dict) -> None:
        """Another timer's ``stages`` (a task's, run elsewhere) added to these: their
        times summed, their peaks the larger."""
        for name, st in stages.items():
            s = self.stages.setdefault(name, {"wall_s": 0.0, "peak_memory_mb": 0.0})
            s["wall_s"] = round(s["wall_s"] + st["wall_s"], 3)
            s["peak_memory_mb"] = max(s["peak_memory_mb"], st["peak_memory_mb"])

    @property
    def total_s(self) -> float:
        return round(sum(s["wall_s"] for s in self.stages.values()), 3)


def provenance(command: list[str] | None = None) -> dict:
    """What made a run: the workbench's version, the command line (None from Python),
    Python's and the libraries' versions, for the run's record."""
    from . import __version__

    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "workbench_version": __version__,
        "command": " ".join(command) if command else None,
        "python": platform.python_version(),
        "libraries": versions,
    }
