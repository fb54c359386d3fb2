"""CPU threads for torch on a machine that other processes share.

torch's CPU kernels run on OpenMP (libgomp in the CPU wheels). Two habits make them collapse on a
busy machine: more threads than cores that are actually free, so every parallel region waits at its
barrier for a thread the kernel has descheduled; and threads that spin while they wait, burning the
core the other process needs. The cure is in two parts, both here:

- :func:`prefer_passive_wait` sets ``OMP_WAIT_POLICY=PASSIVE`` (unless the user set a policy), so
  idle OpenMP threads sleep instead of spinning. libgomp reads it once, when it is loaded, so this
  must run before the first ``import torch`` of the process; entry points (the CLI, the service)
  call it first thing.
- :func:`free_cores` counts the cores this process may use (affinity mask and cgroup quota) minus
  the ones other processes keep busy (sampled from ``/proc/stat`` over a short interval), and
  :func:`choose_threads` turns a request (``auto`` or a number) into a thread count.

Only Linux exposes the counters; elsewhere every allowed core counts as free.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

AUTO = "auto"
WAIT_POLICY_ENV = "OMP_WAIT_POLICY"
_PROC_STAT = Path("/proc/stat")
_CGROUP_CPU_MAX = Path("/sys/fs/cgroup/cpu.max")
_SAMPLE_S = 0.1  # long enough for a few scheduler ticks (100 Hz) on each core


def prefer_passive_wait() -> bool:
    """Make idle OpenMP threads sleep rather than spin, unless ``OMP_WAIT_POLICY`` is already set.

    Returns whether the policy this process will use is passive. Call it before ``import torch``:
    once libgomp is loaded the variable is no longer read.
    """
    os.environ.setdefault(WAIT_POLICY_ENV, "PASSIVE")
    return os.environ[WAIT_POLICY_ENV].strip().upper() == "PASSIVE"


def allowed_cpus() -> list[int]:
    """The CPU ids this process may run on (its affinity mask), sorted."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return list(range(os.cpu_count() or 1))


def cgroup_cpu_limit(path: Path = _CGROUP_CPU_MAX) -> float | None:
    """The cgroup v2 CPU quota in cores (``quota / period``), or ``None`` when unlimited or unknown."""
    try:
        quota, period = path.read_text().split()[:2]
    except (OSError, ValueError):
        return None
    if quota == "max":
        return None
    try:
        cores = int(quota) / int(period)
    except (ValueError, ZeroDivisionError):
        return None
    return cores if cores > 0 else None


def available_cores() -> int:
    """Cores this process may use: its affinity mask, capped by a cgroup quota (rounded up)."""
    cores = len(allowed_cpus())
    limit = cgroup_cpu_limit()
    return max(1, min(cores, math.ceil(limit)) if limit is not None else cores)


def _cpu_times(cpus: list[int], stat: Path = _PROC_STAT) -> tuple[float, float] | None:
    """``(busy, total)`` clock ticks summed over ``cpus`` from ``/proc/stat``, or ``None``."""
    wanted = {f"cpu{i}" for i in cpus}
    busy = total = 0.0
    try:
        lines = stat.read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        name, *values = line.split()
        if name not in wanted:
            continue
        ticks = [float(v) for v in values[:8]]  # user nice system idle iowait irq softirq steal
        idle = ticks[3] + ticks[4]
        total += sum(ticks)
        busy += sum(ticks) - idle
    return (busy, total) if total > 0 else None


def busy_cores(interval_s: float = _SAMPLE_S, stat: Path = _PROC_STAT) -> float:
    """How many of this process's allowed cores *other* processes kept busy over ``interval_s``.

    From the busy share of the allowed CPUs' ticks in ``/proc/stat``, less this process's own CPU
    time over the same interval. 0 where the counters cannot be read.
    """
    cpus = allowed_cpus()
    before, own_before = _cpu_times(cpus, stat), _own_cpu_s()
    if before is None:
        return 0.0
    time.sleep(interval_s)
    after, own_after = _cpu_times(cpus, stat), _own_cpu_s()
    if after is None or after[1] <= before[1]:
        return 0.0
    share = (after[0] - before[0]) / (after[1] - before[1])
    own = (own_after - own_before) / interval_s
    return max(0.0, share * len(cpus) - own)


def _own_cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def free_cores(interval_s: float = _SAMPLE_S) -> int:
    """Cores this process may use that other processes leave free now (at least 1).

    A core counts as taken when other processes keep it more than half busy.
    """
    return max(1, available_cores() - math.floor(busy_cores(interval_s) + 0.5))


def parse_threads(text: str) -> int | str:
    """``"auto"`` or a positive integer, from a command-line or environment value."""
    text = text.strip().lower()
    if text == AUTO:
        return AUTO
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"threads must be 'auto' or a positive integer, got {text!r}") from None
    if value <= 0:
        raise ValueError(f"threads must be 'auto' or a positive integer, got {value}")
    return value


def choose_threads(requested: int | str = AUTO, *, share: int = 1) -> int:
    """The torch thread count for ``requested`` (``"auto"``: the free cores split ``share`` ways)."""
    if requested == AUTO:
        return max(1, free_cores() // max(1, share))
    if isinstance(requested, bool) or not isinstance(requested, int) or requested <= 0:
        raise ValueError(f"threads must be 'auto' or a positive integer, got {requested!r}")
    return requested


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's threads set to ``n`` for the block and restored after: for a figure that must not depend on
    the machine's share of cores, or for small work that a second thread only slows (tracked frames)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
