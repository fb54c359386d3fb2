"""A bounded work queue: compute runs on worker threads, off the event loop, and overload is refused.

At most ``workers`` jobs run at once and at most ``queue_size`` more wait; a job submitted beyond
that raises :class:`QueueFull` at once (the service answers 503 with ``Retry-After``) instead of
piling up latency. A slot is released when its job *finishes* (or is cancelled before it starts),
not when the awaiting request goes away, so a client that disconnects cannot let more work in than
the threads can run. A job is handed a :class:`Stop`, which it polls between steps: cancelling the
awaiting coroutine cancels a waiting job (it never starts, its slot is free at once) and tells a
running one to stop (``"cancelled"``); past ``max_seconds`` of running it says ``"budget_exceeded"``.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")


class QueueFull(Exception):
    """No room for another job; ``retry_after_s`` is a hint for when to try again."""

    def __init__(self, retry_after_s: int) -> None:
        super().__init__(f"the work queue is full; retry in {retry_after_s} s")
        self.retry_after_s = retry_after_s


class Stop:
    """Whether a job should stop early, and why: call it between steps; ``None`` means go on.

    ``"cancelled"`` once :meth:`cancel` was called (its client went away), ``"budget_exceeded"``
    once it has run ``max_seconds`` (``None``: no limit) since :meth:`start`. Thread-safe.
    """

    def __init__(self, max_seconds: float | None = None) -> None:
        self.max_seconds = max_seconds
        self._cancelled = threading.Event()
        self._deadline = math.inf

    def start(self) -> None:
        if self.max_seconds is not None:
            self._deadline = time.monotonic() + self.max_seconds

    def cancel(self) -> None:
        self._cancelled.set()

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()

    def __call__(self) -> str | None:
        if self._cancelled.is_set():
            return "cancelled"
        if time.monotonic() > self._deadline:
            return "budget_exceeded"
        return None


class WorkQueue:
    """``workers`` threads and room for ``queue_size`` waiting jobs."""

    def __init__(self, workers: int, queue_size: int, *, retry_after_max_s: int = 30) -> None:
        if workers < 1 or queue_size < 0:
            raise ValueError(f"need workers >= 1 and queue_size >= 0, got {workers} and {queue_size}")
        self.workers = workers
        self.capacity = workers + queue_size
        self.retry_after_max_s = retry_after_max_s
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="narf-worker")
        self._lock = threading.Lock()
        self._admitted = 0
        self._running = 0
        self._mean_job_s = 0.0  # exponential moving average, for the Retry-After hint

    @property
    def running(self) -> int:
        return self._running

    @property
    def waiting(self) -> int:
        """Jobs admitted but not yet started (the queue depth)."""
        with self._lock:
            return self._admitted - self._running

    def retry_after_s(self) -> int:
        """Seconds until a slot is likely free: the queue ahead, at the mean job time, over the workers."""
        ahead = self._admitted - self.workers + 1
        estimate = math.ceil(max(ahead, 1) * self._mean_job_s / self.workers)
        return min(max(estimate, 1), self.retry_after_max_s)

    def submit(self, fn: Callable[[], T], stop: Stop | None = None) -> Future[T]:
        """Queue ``fn()`` for a worker thread (``stop`` is started when it starts); raises
        :class:`QueueFull` if there is no room."""
        with self._lock:
            if self._admitted >= self.capacity:
                raise QueueFull(self.retry_after_s())
            self._admitted += 1
        future: Future[T] = self._executor.submit(self._timed, fn, stop)
        future.add_done_callback(self._release)
        return future

    async def run(self, fn: Callable[[], T], stop: Stop | None = None) -> T:
        """Run ``fn()`` on a worker thread; raises :class:`QueueFull` if there is no room.

        Cancelling the caller cancels the job: a waiting one never starts, a running one is told
        through ``stop``.
        """
        future = self.submit(fn, stop)
        try:
            return await asyncio.wrap_future(future)
        except asyncio.CancelledError:
            future.cancel()
            if stop is not None:
                stop.cancel()
            raise

    def _timed(self, fn: Callable[[], T], stop: Stop | None) -> T:
        with self._lock:
            self._running += 1
        if stop is not None:
            stop.start()
        start = time.perf_counter()
        try:
            return fn()
        finally:
            elapsed = time.perf_counter() - start
            with self._lock:
                self._running -= 1
                self._mean_job_s = elapsed if self._mean_job_s == 0 else 0.8 * self._mean_job_s + 0.2 * elapsed

    def _release(self, _: Future) -> None:
        with self._lock:
            self._admitted -= 1

    def shutdown(self) -> None:
        """Finish the running jobs, drop the waiting ones."""
        self._executor.shutdown(wait=True, cancel_futures=True)
