"""Run the service with uvicorn: :func:`serve` (what ``narf serve`` calls) and ``python -m narf_service``."""

from __future__ import annotations

import argparse
import logging
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import uvicorn
from fastapi import FastAPI
from pydantic import ValidationError

from narf_service.app import create_app
from narf_service.guards import timed_h11_protocol
from narf_service.settings import Settings


def serve(
    models_dir: str | Path | None = None,
    host: str = "127.0.0.1",
    port: int = 8000,
    token: str | None = None,
    *,
    token_file: str | Path | None = None,
    log_level: str = "info",
    **settings: Any,
) -> None:
    """Serve every ``*.narf`` in ``models_dir`` on ``host:port`` until interrupted.

    Unset arguments fall back to the ``NARF_*`` environment (``NARF_MODELS_DIR``, ``NARF_TOKEN``, ...),
    then to the defaults of :class:`~narf_service.settings.Settings`; ``settings`` takes any of its
    other fields (``workers=2``, ``max_body_bytes=...``). ``token_file`` names a file holding the
    token (``NARF_TOKEN_FILE``). Raises ``ValueError`` for a models folder that does not exist or
    invalid settings.
    """
    overrides = dict(settings)
    if models_dir is not None:
        overrides["models_dir"] = Path(models_dir)
    if token is not None:
        overrides["token"] = token
    if token_file is not None:
        overrides["token_file"] = Path(token_file)
    try:
        config = Settings(**overrides)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        message = str(first["msg"]).removeprefix("Value error, ")
        raise ValueError(f"invalid setting {where}: {message}" if where else message) from None
    if not config.models_dir.is_dir():
        raise ValueError(f"models folder {config.models_dir} does not exist")
    logging.basicConfig(level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    uvicorn.Server(uvicorn_config(create_app(config), host, port, log_level=log_level)).run()


def uvicorn_config(app: FastAPI, host: str, port: int, *, log_level: str = "info") -> uvicorn.Config:
    """uvicorn's configuration for ``app``, with its settings' connection timeouts: request headers
    (``header_timeout_s``, on uvicorn's h11 protocol) and idle keep-alive (``keep_alive_timeout_s``)."""
    settings: Settings = app.state.settings
    return uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level=log_level,
        lifespan="on",
        http=timed_h11_protocol(settings.header_timeout_s),
        timeout_keep_alive=settings.keep_alive_timeout_s,  # type: ignore[arg-type]  (a float works)
        timeout_graceful_shutdown=10,
    )


@contextmanager
def serve_in_thread(app: FastAPI, host: str = "127.0.0.1", port: int = 0, *, startup_timeout_s: float = 60.0) -> Iterator[str]:
    """Run ``app`` with uvicorn on a background thread, yielding its base URL (``port=0``: a free port).

    For tests, benchmarks and examples; the server is stopped (lifespan shutdown included) on exit.
    """
    server = uvicorn.Server(uvicorn_config(app, host, port, log_level="warning"))
    thread = threading.Thread(target=server.run, name="narf-uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + startup_timeout_s
    while not server.started:
        if not thread.is_alive():
            raise RuntimeError(f"the server on {host}:{port} failed to start (see its log)")
        if time.monotonic() > deadline:
            server.should_exit = True
            raise TimeoutError(f"the server on {host}:{port} did not start within {startup_timeout_s} s")
        time.sleep(0.01)
    bound_port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://{host}:{bound_port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` now (another process may still take it before it is bound)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


@contextmanager
def serve_process(
    args: Sequence[str] = (), env: Mapping[str, str] | None = None, *, startup_timeout_s: float = 90.0
) -> Iterator[str]:
    """Run ``narf serve ARGS`` as its own process on a free loopback port, yielding its base URL once
    ``/readyz`` answers 200; it is terminated (killed if it lingers) on exit.

    For tests and benchmarks that need the server apart from the client's interpreter, as deployed.
    ``env`` replaces the environment (default: this process's). Its output goes to a temporary file
    (never a pipe nobody reads, which would stall it) whose end is quoted if it fails to start.
    """
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    command = [sys.executable, "-m", "narf_core.cli", "serve", *args, "--port", str(port)]
    with tempfile.TemporaryFile("w+") as log:
        process = subprocess.Popen(command, env=dict(env) if env is not None else None, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + startup_timeout_s
            while not _ready(url):
                if process.poll() is not None or time.monotonic() > deadline:
                    log.seek(0)
                    why = f"exited with {process.returncode}" if process.poll() is not None else "is not ready"
                    raise RuntimeError(f"narf serve {why} after {startup_timeout_s:g} s at most: {log.read()[-2000:]}")
                time.sleep(0.1)
            yield url
        finally:
            process.terminate()
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def _ready(url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/readyz", timeout=2) as response:
            return response.status == 200
    except (urllib.error.URLError, ConnectionError, TimeoutError):
        return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m narf_service",
        description="Serve NARF models over HTTP (API v1). Settings also come from NARF_* environment "
        "variables; the bearer token only from NARF_TOKEN or a file, so it never shows in a process list.",
    )
    parser.add_argument("--models", type=Path, default=None, help="folder of *.narf bundles (NARF_MODELS_DIR)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default: loopback only)")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--workers", type=int, default=None, help="compute threads (default: one per core)")
    parser.add_argument("--token-file", type=Path, default=None, help="file holding the bearer token (NARF_TOKEN_FILE)")
    parser.add_argument("--state-key-file", type=Path, default=None,
                        help="key signing /v1/track state tokens (NARF_STATE_KEY_FILE; default: random per process)")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    args = parser.parse_args(argv)
    extra = {} if args.workers is None else {"workers": args.workers}
    if args.state_key_file is not None:
        extra["state_key_file"] = args.state_key_file
    try:
        serve(args.models, args.host, args.port, token_file=args.token_file, log_level=args.log_level, **extra)
    except ValueError as e:
        print(f"narf serve: error: {e}", file=sys.stderr)
        return 2
    return 0
