"""Peak memory as the runs and the benchmarks record it."""

import subprocess
import sys

import numpy as np

from workbench.records import peak_memory_mb


def _child(code: str) -> list[float]:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return [float(x) for x in out.stdout.split()]


def test_peak_memory_grows_with_what_the_process_touches():
    code = (
        "import numpy as np; from workbench.records import peak_memory_mb as p\n"
        "a = p(); b = np.ones(40_000_000); print(a, p())"  # 305 MiB, every page written
    )
    before, after = _child(code)
    assert 250 < after - before < 400


def test_a_child_of_a_large_process_reports_its_own_peak():
    block = np.ones(60_000_000)  # 458 MiB in the parent at the fork
    (child,) = _child("from workbench.records import peak_memory_mb; print(peak_memory_mb())")
    assert child < 200 < peak_memory_mb()
    del block
