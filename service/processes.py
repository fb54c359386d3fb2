"""Child processes that run jobs with the served models, off the server's interpreter.

A tracking step is thousands of small torch calls with Python between them, which needs the GIL:
two worker threads of one process stepping at once take turns at that lock at every call, and the
event loop, parsing the next requests, waits for it as well. :class:`ModelProcesses` keeps one
child process per worker thread instead, each with its own copy of the models (sent once, pickled,
when it starts) and its own ``torch_threads``: a worker thread hands its job to an idle child and
waits on a socket, without the GIL, for the answer. Jobs are plain functions ``fn(models, *args)``
defined at module level (they travel by name) whose arguments and result pickle.

Children start on first use (a few seconds: a fresh interpreter imports torch and unpickles the
models), so a server that never tracks never starts one. A child that dies mid-job (killed, out of
memory) fails that job with :class:`WorkerLost` and is replaced on the next; one that runs past
``timeout_s`` is killed the same way. An :class:`~narf_service.errors.ApiError` raised in a child
(bad input found while decoding) reaches the caller as the same error.
"""

from __future__ import annotations

import logging
import os
import pickle
import queue
import signal
import socket
import subprocess
import sys
import threading
import traceback
from collections.abc import Callable, Mapping
from multiprocessing.connection import Connection
from typing import Any, TypeVar

from narf_service.errors import ApiError

T = TypeVar("T")
log = logging.getLogger("narf_service.processes")

_START_TIMEOUT_S = 300.0
_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))
_CHILD_MAIN = """
import importlib.util, sys
from multiprocessing.connection import Connection
fd, threads, package = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
# the parent's narf_service, also where it is a plain checkout registered by path (tests/checkout.py)
spec = importlib.util.spec_from_file_location("narf_service", package + "/__init__.py",
                                              submodule_search_locations=[package])
sys.modules["narf_service"] = module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
from narf_service.processes import _serve
_serve(Connection(fd), threads)
"""


class WorkerLost(RuntimeError):
    """The child process running a job ended or ran past its time; the job has no answer."""


class ModelProcesses:
    """At most ``size`` child processes holding ``models`` (``name -> model``), each running one job at a time."""

    def __init__(self, models: Mapping[str, Any], size: int, *, torch_threads: int = 1,
                 timeout_s: float | None = None) -> None:
        if size < 1:
            raise ValueError(f"need size >= 1, got {size}")
        self.size = size
        self.torch_threads = torch_threads
        self.timeout_s = timeout_s
        self._models = dict(models)
        self._idle: queue.SimpleQueue[_Child] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._started = 0
        self._closed = False
        self._all: set[_Child] = set()

    @property
    def started(self) -> int:
        """Children alive now (busy or idle)."""
        return self._started

    def call(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(models, *args)`` in an idle child (started if fewer than ``size`` run); blocks until it answers."""
        child = self._take()
        try:
            return child.call(fn, args, self.timeout_s)
        except WorkerLost:
            self._drop(child)
            child = None
            raise
        finally:
            if child is not None:
                self._idle.put(child)

    def _take(self) -> _Child:
        with self._lock:
            if self._closed:
                raise RuntimeError("the worker processes are shut down")
            start = self._idle.empty() and self._started < self.size
            if start:
                self._started += 1
        if not start:
            return self._idle.get()
        try:
            child = _Child.start(self._models, self.torch_threads)
        except BaseException:
            with self._lock:
                self._started -= 1
            raise
        with self._lock:
            self._all.add(child)
        return child

    def _drop(self, child: _Child) -> None:
        child.kill()
        with self._lock:
            self._started -= 1
            self._all.discard(child)

    def close(self) -> None:
        """End every child (call once no job runs: the work queue is shut down first)."""
        with self._lock:
            self._closed = True
            children, self._all = list(self._all), set()
            self._started = 0
        for child in children:
            child.stop()


class _Child:
    """One child process and the parent's end of its pipe."""

    def __init__(self, process: subprocess.Popen, conn: Connection) -> None:
        self.process = process
        self.conn = conn

    @classmethod
    def start(cls, models: Mapping[str, Any], torch_threads: int) -> _Child:
        # A fresh interpreter running :func:`_serve`, not multiprocessing's spawn, which would run the
        # parent's main script again in the child; never a fork of a process with threads.
        ours, theirs = socket.socketpair()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}  # the parent's imports
        command = [sys.executable, "-c", _CHILD_MAIN, str(theirs.fileno()), str(torch_threads), _PACKAGE_DIR]
        with theirs:
            process = subprocess.Popen(command, pass_fds=[theirs.fileno()], env=env, stdin=subprocess.DEVNULL)
        one = cls(process, Connection(ours.detach()))
        try:
            _send(one.conn, dict(models))
            if not one.conn.poll(_START_TIMEOUT_S) or _receive(one.conn) != "ready":
                raise WorkerLost(f"a worker process did not start within {_START_TIMEOUT_S:g} s")
        except (OSError, EOFError) as e:
            one.kill()
            raise WorkerLost(f"a worker process failed to start (exit code {process.returncode}): {e}") from None
        except BaseException:
            one.kill()
            raise
        log.info("worker process %s started", process.pid)
        return one

    def call(self, fn: Callable[..., T], args: tuple, timeout_s: float | None) -> T:
        try:
            _send(self.conn, (fn, args))
            if not self.conn.poll(timeout_s):
                raise WorkerLost(f"a worker process ran past {timeout_s:g} s on one job and was stopped")
            kind, *value = _receive(self.conn)
        except (OSError, EOFError):
            raise WorkerLost(f"a worker process ended during a job (exit code {self.process.poll()}); "
                             "it is replaced for the next one") from None
        if kind == "ok":
            return value[0]
        if kind == "api":
            status, message, field, code = value
            raise ApiError(status, message, field=field, code=code)
        raise RuntimeError(f"in a worker process: {value[0]}")

    def stop(self) -> None:
        try:
            _send(self.conn, None)
            self.process.wait(timeout=5)
        except (OSError, subprocess.TimeoutExpired):
            pass
        self.kill()

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=5)
        self.conn.close()


def _send(conn: Connection, value: Any) -> None:
    """Plain pickle, not the connection's own: that one would hand tensors over as shared memory through
    multiprocessing's resource sharer, which only a multiprocessing child can reach."""
    conn.send_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))


def _receive(conn: Connection) -> Any:
    return pickle.loads(conn.recv_bytes())


def _serve(conn: Connection, torch_threads: int) -> None:
    """The child's loop: receive the models, then ``(fn, args)`` jobs until ``None`` or the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops its children; Ctrl-C is for the parent
    from narf_core.threads import prefer_passive_wait

    prefer_passive_wait()
    if torch_threads:  # 0: torch's own default
        import torch

        torch.set_num_threads(torch_threads)
    models = _receive(conn)
    _send(conn, "ready")
    while True:
        try:
            job = _receive(conn)
        except (EOFError, OSError):  # the parent is gone
            return
        if job is None:
            return
        fn, args = job
        try:
            answer: tuple = ("ok", fn(models, *args))
        except ApiError as e:
            answer = ("api", e.status_code, e.message, e.field, e.code)
        except Exception as e:  # noqa: BLE001 - sent to the parent, which raises it for the request
            log.error("worker process job %s failed:\n%s", getattr(fn, "__name__", fn), traceback.format_exc())
            answer = ("error", f"{type(e).__name__}: {e}")
        try:
            data = pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as e:  # noqa: BLE001 - an answer that cannot travel is the job's error
            data = pickle.dumps(("error", f"the answer of job {getattr(fn, '__name__', fn)} does not pickle: {e}"))
        conn.send_bytes(data)
