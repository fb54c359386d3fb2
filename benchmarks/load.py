"""Other busy processes on the machine, for benchmarks that measure a shared computer, and what a
benchmark's timings were measured on.

A robot's computer runs other nodes; ``narf bench --busy N ...`` starts ``N`` CPU-bound processes
(plain Python loops, one core each at most) for the length of the benchmark, so its run times are
those of a machine that is not idle.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

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


def device_of(models: Iterable[Any]) -> str:
    """Where ``models`` (anything with an ``aabb`` tensor) render: ``cpu``, or a GPU by index and name
    (``cuda:0 (NVIDIA H100 80GB HBM3)``); several, comma-separated."""
    import torch

    names = []
    for device in dict.fromkeys(m.aabb.device for m in models):
        name = str(device)
        if device.type == "cuda":
            name = f"cuda:{device.index or 0} ({torch.cuda.get_device_name(device)})"
        names.append(name)
    return ", ".join(names) or "none"


def machine(models: Iterable[Any]) -> dict[str, Any]:
    """The device of ``models`` (:func:`device_of`), the 1-minute load average and the core count: what a
    benchmark prints beside its timings."""
    return {"device": device_of(models), **machine_load()}


def describe_machine(record: dict[str, Any] | None) -> str:
    """One sentence of :func:`machine`'s record to append to a benchmark's description, with its leading
    space (empty for results without one)."""
    if not record:
        return ""
    return (f" Measured on {record['device']}, load {record['loadavg_1min']:.1f} on {record['cores']:.0f} cores at "
            "the end.")
