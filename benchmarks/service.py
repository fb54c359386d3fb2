"""Service benchmark (docs/design.md §10): N concurrent clients on loopback against /v1/render and /v1/estimate.

Reports requests per second, p50/p99 latency of answered requests, errors by status (503s, the
queue's deliberate refusals, counted apart), requests left without an answer ("lost"), and the
server's peak resident memory (its ``VmHWM``, which the server reads from ``/proc/self/status``
and exports on ``/metrics``). Work is bounded in clients, requests and time, and only loopback
servers are accepted.

    python benchmarks/service.py --models models/ --clients 8 --requests 200 --json out/service.json
    python benchmarks/service.py --url http://127.0.0.1:8000
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np
from narf_client import NarfClient, NarfError, Pose
from narf_client.client import estimate_files, render_payload

LOOPBACK = {"127.0.0.1", "localhost", "::1"}
MAX_CLIENTS = 64
MAX_DURATION_S = 600.0


@dataclass
class RouteStats:
    """One load phase: what was sent, what came back, how fast."""

    route: str
    clients: int
    sent: int = 0
    ok: int = 0
    busy_503: int = 0
    errors: dict[str, int] = field(default_factory=dict)  # HTTP status -> count, 200 and 503 excluded
    lost: dict[str, int] = field(default_factory=dict)  # no HTTP answer (timeout, reset, ...) -> count
    seconds: float = 0.0
    requests_per_s: float = 0.0
    p50_ms: float = float("nan")
    p99_ms: float = float("nan")


def percentile(values: list[float], q: float) -> float:
    """The ``q``-th percentile (nearest rank), NaN for no values."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q / 100 * len(ordered)) - 1))]


async def load(
    http: httpx.AsyncClient,
    route: str,
    send: Callable[[httpx.AsyncClient], Any],
    *,
    clients: int,
    requests: int,
    duration_s: float,
) -> RouteStats:
    """``clients`` concurrent loops sharing a budget of ``requests``, stopping after ``duration_s``."""
    stats = RouteStats(route=route, clients=clients)
    latencies: list[float] = []
    statuses: Counter[str] = Counter()
    lost: Counter[str] = Counter()
    issued = 0
    start = time.perf_counter()
    deadline = start + duration_s

    async def client() -> None:
        nonlocal issued
        while issued < requests and time.perf_counter() < deadline:
            issued += 1
            t0 = time.perf_counter()
            try:
                response = await send(http)
            except httpx.TransportError as e:
                lost[type(e).__name__] += 1
                continue
            statuses[str(response.status_code)] += 1
            if response.status_code == 200:
                latencies.append(time.perf_counter() - t0)

    await asyncio.gather(*(client() for _ in range(clients)))
    stats.seconds = time.perf_counter() - start
    stats.sent = issued
    stats.ok = statuses.pop("200", 0)
    stats.busy_503 = statuses.pop("503", 0)
    stats.errors = dict(statuses)
    stats.lost = dict(lost)
    stats.requests_per_s = stats.ok / stats.seconds if stats.seconds > 0 else 0.0
    stats.p50_ms = percentile(latencies, 50) * 1000
    stats.p99_ms = percentile(latencies, 99) * 1000
    return stats


def _rotation(rx: float, ry: float) -> np.ndarray:
    cx, sx, cy, sy = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
    return np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])


def view(bounds: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """A camera ``K`` and a pose ``T_cam_obj`` that frame the object's box at about half the image."""
    f = 536.5 * width / 640  # a Primesense-like field of view, square pixels
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    centre = bounds.mean(axis=0)
    radius = float(np.linalg.norm(bounds[1] - bounds[0])) / 2
    distance = 4 * radius * f / min(width, height)  # the box's diameter spans half the shorter side
    T = np.eye(4)
    T[:3, :3] = _rotation(-0.5, 0.4)
    T[:3, 3] = np.array([0, 0, distance]) - T[:3, :3] @ centre
    return K, T


def perturbed(T: np.ndarray, degrees: float = 10.0, metres: float = 0.02, seed: int = 0) -> np.ndarray:
    """``T`` rotated by ``degrees`` about a random axis and shifted by ``metres`` in a random direction."""
    rng = np.random.default_rng(seed)
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    axis, shift = axis / np.linalg.norm(axis), shift / np.linalg.norm(shift)
    a = math.radians(degrees)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    out = T.copy()
    out[:3, :3] = (np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k) @ T[:3, :3]
    out[:3, 3] += metres * shift
    return out


def peak_rss_mib(base_url: str, headers: dict[str, str]) -> float:
    """The server's peak RSS in MiB from its ``/metrics`` (NaN if it does not report it)."""
    text = httpx.get(f"{base_url}/metrics", headers=headers, timeout=10).text
    for line in text.splitlines():
        if line.startswith("narf_process_peak_rss_bytes "):
            return float(line.split()[1]) / 2**20
    return float("nan")


@contextmanager
def local_server(models_dir: Path | None, app: Any = None) -> Iterator[str]:
    """An in-process server on a free loopback port, serving ``models_dir`` (or the given ``app``).

    The service is imported here, not at the top: benchmarking a running server needs only the client.
    """
    from narf_service import Settings, create_app
    from narf_service.main import serve_in_thread

    if app is None:
        app = create_app(Settings() if models_dir is None else Settings(models_dir=models_dir))
    with serve_in_thread(app) as url:
        yield url


def run(
    base_url: str | None = None,
    *,
    models_dir: Path | None = None,
    app: Any = None,
    model: str | None = None,
    clients: int = 8,
    requests: int = 200,
    duration_s: float = 30.0,
    estimate_clients: int = 16,
    estimate_iterations: int = 30,
    size: tuple[int, int] = (160, 120),
    token: str | None = None,
) -> dict[str, Any]:
    """Benchmark a server at ``base_url`` (loopback only), or an in-process one for ``models_dir``/``app``.

    ``/v1/render``: ``clients`` concurrent clients share ``requests`` requests (JSON, rgb at ``size``).
    ``/v1/estimate``: ``estimate_clients`` clients send one request each at once (``estimate_iterations``
    iterations from a 10 degree / 2 cm perturbation); every one must be answered, a result or a 503.
    Each phase stops after ``duration_s``.
    """
    if not 1 <= clients <= MAX_CLIENTS or not 1 <= estimate_clients <= MAX_CLIENTS:
        raise ValueError(f"clients must lie in [1, {MAX_CLIENTS}]")
    if not 0 < duration_s <= MAX_DURATION_S or requests < 1:
        raise ValueError(f"duration_s must lie in (0, {MAX_DURATION_S}] and requests be >= 1")
    if base_url is None:
        with local_server(models_dir, app) as url:
            return run(
                url,
                model=model,
                clients=clients,
                requests=requests,
                duration_s=duration_s,
                estimate_clients=estimate_clients,
                estimate_iterations=estimate_iterations,
                size=size,
                token=token,
            )
    host = urlsplit(base_url).hostname
    if host not in LOOPBACK:
        raise ValueError(f"the service benchmark runs on loopback only, not against {host!r}")
    return asyncio.run(
        _run(base_url.rstrip("/"), model, clients, requests, duration_s, estimate_clients, estimate_iterations, size, token)
    )


async def _run(
    base_url: str,
    model: str | None,
    clients: int,
    requests: int,
    duration_s: float,
    estimate_clients: int,
    estimate_iterations: int,
    size: tuple[int, int],
    token: str | None,
) -> dict[str, Any]:
    headers = {"authorization": f"Bearer {token}"} if token else {}
    width, height = size
    with NarfClient(base_url, token) as narf:
        served = [m.name for m in narf.models()]
        if not served or (model is not None and model not in served):
            raise ValueError(f"model {model!r} is not served at {base_url} (served: {', '.join(served) or 'none'})")
        info = narf.model(model or served[0])
        K, T = view(info.bounds, width, height)
        joints = info.mid_joints
        seen = narf.render(info.name, T, K, width, height, joints=joints, outputs=("rgb", "opacity"))
    render_body = render_payload(info.name, T, K, width, height, joints, ("rgb",), "narf")
    files = estimate_files(
        seen.rgb,
        seen.opacity > 0.5,
        K,
        Pose(perturbed(T)),
        model=info.name,
        initial_joints=joints,
        depth=None,
        iterations=estimate_iterations,
        options=None,
        ground_truth=(T, joints),
    )

    limits = httpx.Limits(max_connections=max(clients, estimate_clients), max_keepalive_connections=MAX_CLIENTS)
    timeout = httpx.Timeout(60.0, read=max(duration_s, 60.0) * 2)
    async with httpx.AsyncClient(base_url=base_url, headers=headers, limits=limits, timeout=timeout) as http:
        render = await load(
            http,
            "/v1/render",
            lambda h: h.post("/v1/render", json=render_body),
            clients=clients,
            requests=requests,
            duration_s=duration_s,
        )
        estimate = await load(
            http,
            "/v1/estimate",
            lambda h: h.post("/v1/estimate", files=files),
            clients=estimate_clients,
            requests=estimate_clients,
            duration_s=duration_s,
        )
    return {
        "base_url": base_url,
        "model": info.name,
        "size": [width, height],
        "estimate_iterations": estimate_iterations,
        "routes": [asdict(render), asdict(estimate)],
        "server_peak_rss_mib": peak_rss_mib(base_url, headers),
    }


def markdown(result: dict[str, Any]) -> str:
    """The result as a Markdown table (one row per route) and a line for the server's memory."""
    w, h = result["size"]
    lines = [
        f"Service on {result['base_url']}, model `{result['model']}`, {w}x{h}, "
        f"estimate {result['estimate_iterations']} iterations",
        "",
        "| route | clients | sent | ok | 503 | other errors | lost | req/s | p50 ms | p99 ms |",
        "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in result["routes"]:
        errors = ", ".join(f"{k}: {v}" for k, v in sorted(r["errors"].items())) or "0"
        lost = sum(r["lost"].values())
        lines.append(
            f"| {r['route']} | {r['clients']} | {r['sent']} | {r['ok']} | {r['busy_503']} | {errors} | {lost} "
            f"| {r['requests_per_s']:.1f} | {r['p50_ms']:.0f} | {r['p99_ms']:.0f} |"
        )
    lines += ["", f"Server peak RSS: {result['server_peak_rss_mib']:.0f} MiB"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--url", help="a running server on loopback (default: start one in-process)")
    where.add_argument("--models", type=Path, help="models folder for the in-process server (default: models/)")
    parser.add_argument("--model", help="model to use (default: the first served)")
    parser.add_argument("--clients", type=int, default=8, help="concurrent /render clients")
    parser.add_argument("--requests", type=int, default=200, help="/render requests in all")
    parser.add_argument("--duration", type=float, default=30.0, help="time limit per phase, seconds")
    parser.add_argument("--estimate-clients", type=int, default=16, help="concurrent /estimate requests")
    parser.add_argument("--estimate-iterations", type=int, default=30)
    parser.add_argument("--size", type=int, nargs=2, default=(160, 120), metavar=("W", "H"))
    parser.add_argument("--json", type=Path, help="also write the result here as JSON")
    args = parser.parse_args(argv)
    try:
        result = run(
            args.url,
            models_dir=args.models,
            model=args.model,
            clients=args.clients,
            requests=args.requests,
            duration_s=args.duration,
            estimate_clients=args.estimate_clients,
            estimate_iterations=args.estimate_iterations,
            size=tuple(args.size),
        )
    except (ValueError, OSError, httpx.HTTPError, NarfError) as e:
        print(f"bench service: error: {e}", file=sys.stderr)
        return 2
    print(markdown(result))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
