"""ModelProcesses: jobs run in child processes on their own copy of the models; errors, deaths and
overruns come back as exceptions, and a lost child is replaced."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator

import process_jobs as jobs
import pytest
import torch

from narf_service.errors import ApiError
from narf_service.processes import ModelProcesses, WorkerLost


@pytest.fixture(scope="module")
def pool() -> Iterator[ModelProcesses]:
    processes = ModelProcesses({"m": {"links": [1, 2, 3]}, "t": torch.arange(4.0)}, 2, torch_threads=1, timeout_s=20)
    yield processes
    processes.close()


def test_jobs_run_in_children_at_once(pool: ModelProcesses) -> None:
    value, pid = pool.call(jobs.lookup, "m")
    assert value == {"links": [1, 2, 3]} and pid != os.getpid()
    tensor, _ = pool.call(jobs.lookup, "t")  # tensors travel by value (no shared memory a plain child cannot reach)
    assert torch.equal(tensor, torch.arange(4.0))
    pids: list[int] = []
    threads = [threading.Thread(target=lambda: pids.append(pool.call(jobs.wait, 0.5))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(pids)) == 2 and os.getpid() not in pids  # two children, side by side
    assert pool.started == 2


def test_errors_in_a_child_reach_the_caller(pool: ModelProcesses) -> None:
    with pytest.raises(ApiError) as info:
        pool.call(jobs.refuse, "request.camera")
    assert info.value.status_code == 422 and info.value.field == "request.camera"
    with pytest.raises(RuntimeError, match="ZeroDivisionError: a bug in the job"):
        pool.call(jobs.fail)
    assert pool.call(jobs.lookup, "m")[0] == {"links": [1, 2, 3]}  # the child goes on


@pytest.mark.slow  # three children start one after the other
def test_a_dead_or_overrunning_child_is_replaced() -> None:
    processes = ModelProcesses({"m": 1}, 1, torch_threads=0, timeout_s=1.0)
    try:
        first = processes.call(jobs.lookup, "m")[1]
        with pytest.raises(WorkerLost, match="ended during a job"):
            processes.call(jobs.die)
        assert processes.started == 0
        second = processes.call(jobs.lookup, "m")[1]
        assert second != first
        with pytest.raises(WorkerLost, match="ran past 1 s"):
            processes.call(jobs.wait, 30)
        assert processes.call(jobs.lookup, "m")[0] == 1 and processes.started == 1
    finally:
        processes.close()
    with pytest.raises(RuntimeError, match="shut down"):
        processes.call(jobs.lookup, "m")
