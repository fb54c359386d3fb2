"""Service under attack (issue #12): does ``/healthz`` stay fast while the server refuses hostile
bodies and serves estimates, and does a disconnected client's work stop?

Starts ``narf serve`` as a child process on a free loopback port (so that the client's
own work never shares the server's interpreter), then, at the same time:
  * a thread polls ``GET /healthz`` every 10 ms and records each latency;
  * ``estimates`` threads each send one estimate (``size``, ``iterations``, from a 10 degree / 2 cm
    perturbation of the benchmark's view);
  * a thread sends ``hostile_mb`` MB bodies: a JSON document of millions of keys to ``/v1/render``
    and a multipart estimate whose ``request`` part is such a document.
Then ``cancel_clients`` estimates are sent and their connections closed, and the time until the
server's queue (``/metrics``) is empty again is measured.

    narf bench hostile --models models --json      (or: python benchmarks/service_hostile.py)
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
from narf_client import NarfClient
from narf_client.client import estimate_files

from narf_benchmarks.service import percentile, perturbed, view
from narf_service.main import serve_process


def _hostile_json(megabytes: float) -> bytes:
    """A JSON object of about ``megabytes`` MB made of short keys (millions of them)."""
    count = int(megabytes * 1e6 / 12)
    return ("{" + ",".join(f'"k{i}":0' for i in range(count)) + "}").encode()


def _queue(url: str) -> tuple[float, float]:
    """The server's (waiting, running) jobs from ``/metrics``."""
    values = {}
    for line in httpx.get(f"{url}/metrics", timeout=10).text.splitlines():
        name, _, value = line.partition(" ")
        if name in ("narf_queue_depth", "narf_queue_running"):
            values[name] = float(value)
    return values["narf_queue_depth"], values["narf_queue_running"]


def run(
    models_dir: Path,
    *,
    model: str = "clamp",
    estimates: int = 4,
    iterations: int = 30,
    size: tuple[int, int] = (160, 120),
    hostile_mb: float = 30.0,
    cancel_clients: int = 16,
) -> dict[str, Any]:
    env = {k: v for k, v in os.environ.items() if k != "NARF_TOKEN"}
    with serve_process(["--models", str(models_dir)], env, startup_timeout_s=60) as url:
        return _measure(url, model, estimates, iterations, size, hostile_mb, cancel_clients)


def _measure(url, model, estimates, iterations, size, hostile_mb, cancel_clients) -> dict[str, Any]:
    width, height = size
    with NarfClient(url) as narf:
        info = narf.model(model)
        K, T = view(info.bounds, width, height)
        observed = narf.render(model, T, K, width, height, joints=info.mid_joints, outputs=("rgb", "opacity"))
    files = estimate_files(
        observed.rgb, observed.opacity > 0.5, K, perturbed(T), model=model, initial_joints=info.mid_joints,
        depth=None, iterations=iterations, options=None, ground_truth=None,
    )
    document = _hostile_json(hostile_mb)
    results: dict[str, Any] = {"estimates": [], "hostile": []}
    latencies: list[float] = []
    stop = threading.Event()

    def poll() -> None:
        with httpx.Client(timeout=30) as http:
            while not stop.is_set():
                t0 = time.perf_counter()
                http.get(f"{url}/healthz")
                latencies.append(time.perf_counter() - t0)
                time.sleep(0.01)

    def estimate() -> None:
        t0 = time.perf_counter()
        r = httpx.post(f"{url}/v1/estimate", files=files, timeout=600)
        status = r.json().get("status") if r.status_code == 200 else None
        results["estimates"].append({"http": r.status_code, "status": status, "seconds": time.perf_counter() - t0})

    def hostile() -> None:
        for route, kwargs in (
            ("/v1/render", {"content": document, "headers": {"Content-Type": "application/json"}}),
            ("/v1/estimate", {"files": {**files, "request": (None, document, "application/json")}}),
        ):
            t0 = time.perf_counter()
            try:
                status = httpx.post(f"{url}{route}", timeout=600, **kwargs).status_code
            except httpx.TransportError as e:  # the server may answer and close before the whole body is sent
                status = type(e).__name__
            results["hostile"].append({"route": route, "answer": status, "seconds": time.perf_counter() - t0})

    poller = threading.Thread(target=poll)
    poller.start()
    time.sleep(0.5)
    workers = [threading.Thread(target=estimate) for _ in range(estimates)] + [threading.Thread(target=hostile)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    stop.set()
    poller.join()

    body, content_type = _multipart(files)
    socks = []
    for _ in range(cancel_clients):
        sock = socket.create_connection(("127.0.0.1", int(url.rsplit(":", 1)[1])))
        head = (f"POST /v1/estimate HTTP/1.1\r\nHost: x\r\nContent-Type: {content_type}\r\n"
                f"Content-Length: {len(body)}\r\n\r\n")
        sock.sendall(head.encode() + body)
        socks.append(sock)
    time.sleep(1.0)
    before = _queue(url)
    for sock in socks:
        sock.close()
    t0 = time.perf_counter()
    while _queue(url) != (0.0, 0.0) and time.perf_counter() - t0 < 30:
        time.sleep(0.02)
    emptied = time.perf_counter() - t0

    return {
        "model": model,
        "size": list(size),
        "estimate_iterations": iterations,
        "hostile_mb": round(len(document) / 1e6, 1),
        "healthz": {
            "n": len(latencies),
            "p50_ms": percentile(latencies, 50) * 1000,
            "p99_ms": percentile(latencies, 99) * 1000,
            "max_ms": max(latencies) * 1000,
        },
        "estimates": results["estimates"],
        "hostile": results["hostile"],
        "cancel": {"clients": cancel_clients, "queue_before": list(before), "seconds_to_empty": emptied},
    }


def _multipart(files: dict) -> tuple[bytes, str]:
    """``files`` (httpx's form) as a multipart body, for sending over a raw socket."""
    request = httpx.Request("POST", "http://x/", files=files)
    return request.read(), request.headers["content-type"]


def markdown(result: dict[str, Any]) -> str:
    h = result["healthz"]
    lines = [
        f"/healthz during {len(result['estimates'])} estimates and {result['hostile_mb']} MB hostile bodies: "
        f"{h['n']} probes, p50 {h['p50_ms']:.1f} ms, p99 {h['p99_ms']:.1f} ms, max {h['max_ms']:.1f} ms",
    ]
    for e in result["estimates"]:
        lines.append(f"  estimate: HTTP {e['http']} {e['status']} in {e['seconds']:.2f} s")
    for e in result["hostile"]:
        lines.append(f"  hostile {e['route']}: {e['answer']} in {e['seconds']:.2f} s")
    c = result["cancel"]
    lines.append(
        f"{c['clients']} estimates whose clients disconnected (queue waiting/running before: {c['queue_before']}): "
        f"queue empty after {c['seconds_to_empty']:.2f} s"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--estimates", type=int, default=4)
    parser.add_argument("--hostile-mb", type=float, default=30.0)
    parser.add_argument("--cancel-clients", type=int, default=16)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    result = run(args.models, estimates=args.estimates, hostile_mb=args.hostile_mb, cancel_clients=args.cancel_clients)
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
