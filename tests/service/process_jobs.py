"""Jobs for the :class:`narf_service.processes.ModelProcesses` tests: module-level functions ``fn(models, ...)``
that a child process imports by name (so they import only the standard library and the service)."""

from __future__ import annotations

import os
import time

from narf_service.errors import invalid


def lookup(models: dict, name: str) -> tuple[object, int]:
    """The child's copy of ``models[name]`` and the child's process id."""
    return models[name], os.getpid()


def wait(models: dict, seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def refuse(models: dict, field: str) -> None:
    raise invalid(field, "refused in the child")


def fail(models: dict) -> None:
    raise ZeroDivisionError("a bug in the job")


def die(models: dict) -> None:
    os._exit(3)
