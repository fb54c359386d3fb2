"""Other busy processes on the machine, for benchmarks that measure a shared computer.

A robot's computer runs other nodes; ``narf bench --busy N ...`` starts ``N`` CPU-bound processes
(plain Python loops, one core each at most) for the length of the benchmark, so its run times are
those of a machine that is not idle.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

_SPIN = "while True: pass"
_SETTLE_S = 0.3  # let the scheduler see them before threads are chosen


@contextmanager
def busy_processes(count: int) -> Iterator[list[subprocess.Popen]]:
    """Run ``count`` CPU-bound processes while the block runs; they are killed on exit, error or not."""
    procs: list[subprocess.Popen] = []
    try:
        for _ in range(count):
            procs.append(subprocess.Popen([sys.executable, "-c", _SPIN], stdin=subprocess.DEVNULL))
        if procs:
            time.sleep(_SETTLE_S)
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def machine_load() -> dict[str, float]:
    """The 1-minute load average and the core count, to print beside timings."""
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    return {"loadavg_1min": load, "cores": float(os.cpu_count() or 1)}
