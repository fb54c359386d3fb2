"""Prometheus metrics: request counts and latency per route and status, the work queue, memory.

Each app owns its own :class:`prometheus_client.CollectorRegistry`, so several apps (tests) never
share counters. Routes are labelled by their template (``/v1/models/{name}``), never by the raw path,
(and unknown methods as ``other``) so the label set stays bounded whatever clients send.
"""

from __future__ import annotations

import time
from collections.abc import Sized
from pathlib import Path

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from narf_service.workers import WorkQueue

UNMATCHED_ROUTE = "<unmatched>"
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120)


def peak_rss_bytes(status_file: Path = Path("/proc/self/status")) -> float:
    """This process's peak resident set size (``VmHWM``), or NaN where ``/proc`` does not exist."""
    try:
        for line in status_file.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) * 1024
    except OSError:
        pass
    return float("nan")


class ServiceMetrics:
    """The service's instruments, registered in a private registry."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "narf_http_requests", "HTTP requests answered", ["method", "route", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "narf_http_request_duration_seconds",
            "Time to answer an HTTP request",
            ["method", "route"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.rejected = Counter(
            "narf_queue_rejected", "Jobs refused with 503 because the work queue was full", registry=self.registry
        )
        self.cancelled = Counter(
            "narf_jobs_cancelled", "Jobs cancelled because their client disconnected", registry=self.registry
        )
        self.queue_depth = Gauge("narf_queue_depth", "Jobs waiting for a worker", registry=self.registry)
        self.queue_running = Gauge("narf_queue_running", "Jobs running on workers", registry=self.registry)
        self.queue_capacity = Gauge("narf_queue_capacity", "Jobs running plus waiting, at most", registry=self.registry)
        self.models_loaded = Gauge("narf_models_loaded", "Models served", registry=self.registry)
        Gauge("narf_process_peak_rss_bytes", "Peak resident memory (VmHWM)", registry=self.registry).set_function(
            peak_rss_bytes
        )

    def watch(self, queue: WorkQueue, models: Sized) -> None:
        """Report ``queue``'s state and the number of ``models`` (called once they exist, at start)."""
        self.queue_depth.set_function(lambda: queue.waiting)
        self.queue_running.set_function(lambda: queue.running)
        self.queue_capacity.set(queue.capacity)
        self.models_loaded.set(len(models))

    def exposition(self) -> bytes:
        return generate_latest(self.registry)


class MetricsMiddleware:
    """Pure ASGI middleware timing every HTTP request and counting it by route and final status."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_recording_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_recording_status)
        finally:
            route = scope.get("route")
            label = getattr(route, "path", UNMATCHED_ROUTE)
            method = scope["method"] if scope["method"] in KNOWN_METHODS else "other"
            self.metrics.requests.labels(method, label, str(status)).inc()
            self.metrics.latency.labels(method, label).observe(time.perf_counter() - start)
