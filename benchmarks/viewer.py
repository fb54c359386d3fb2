"""Viewer benchmark: how long a joint-slider move takes to reach the screen in the web viewer (/viewer).

A real service (the app ``narf serve`` runs, on loopback) and a real headless Chromium (Debian's
``chromium``, driven by Playwright; nothing downloaded): the page's own log (``window.narfViewer``)
times each frame from the slider's ``input`` event to the animation frame that paints it. Two drags:
``steps`` (one move, wait for its image, repeat) and ``continuous`` (a move every 16 ms for 2 s, as
a hand drags; superseded requests are dropped, so fewer frames come back than inputs went out). The
error column checks that what is on screen is the server's image: the largest difference, in 8-bit
levels, between the narf pane's pixels and the same request's PNG decoded here.

    narf bench viewer --models models --drags 20
"""

from __future__ import annotations

import base64
import io
import os
import shutil
import statistics
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from PIL import Image

CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run", "--disable-quic",
]
NARF_CANVAS = '.pane[data-mode="narf"] canvas'

SLIDE_AND_WAIT = """async ([value, mode]) => {
  const slider = document.querySelector('#model-joints input[type=range]');
  const frame = new Promise((resolve) => {
    const seen = (e) => { if (e.detail.mode === mode && e.detail.input === 'input') {
      document.removeEventListener('narf:frame', seen); resolve(e.detail); } };
    document.addEventListener('narf:frame', seen);
  });
  slider.value = value;
  slider.dispatchEvent(new Event('input', { bubbles: true }));
  return frame;
}"""
"""Move the first joint's slider to ``value`` and resolve with the log entry of ``mode``'s next frame."""

CONTINUOUS_DRAG = """async ([steps, intervalMs, mode]) => {
  const slider = document.querySelector('#model-joints input[type=range]');
  const [lo, hi] = [Number(slider.min), Number(slider.max)];
  const frames = [];
  const seen = (e) => { if (e.detail.mode === mode && e.detail.input === 'input') frames.push(e.detail); };
  document.addEventListener('narf:frame', seen);
  const started = performance.now();
  for (let i = 0; i < steps; i++) {
    slider.value = lo + (hi - lo) * (0.5 - 0.4 * Math.cos((2 * Math.PI * i) / steps));
    slider.dispatchEvent(new Event('input', { bubbles: true }));
    await new Promise((resolve) => setTimeout(resolve, intervalMs));
  }
  const seconds = (performance.now() - started) / 1000;
  await new Promise((resolve) => setTimeout(resolve, 1500));
  document.removeEventListener('narf:frame', seen);
  return { frames, seconds, inputs: steps };
}"""
"""Drag the first joint's slider through its range and back; the frames of ``mode`` that came back."""


def chromium_path() -> str | None:
    """Debian's chromium (or ``NARF_CHROMIUM``), None when absent."""
    path = os.environ.get("NARF_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
    return path if Path(path).is_file() else None


@contextmanager
def browser(executable: str) -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


def _summary(latencies: list[float]) -> dict[str, float]:
    ordered = sorted(latencies)
    return {
        "median_ms": statistics.median(ordered),
        "p90_ms": ordered[min(len(ordered) - 1, int(round(0.9 * (len(ordered) - 1))))],
        "max_ms": ordered[-1],
        "n": len(ordered),
    }


def _screen_error(page: Any, url: str) -> float:
    """Largest |screen - server| (8-bit levels) of the narf pane's last frame, re-requested here."""
    width, height, values = page.evaluate(
        """(s) => { const c = document.querySelector(s);
             return [c.width, c.height, Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data)]; }""",
        NARF_CANVAS,
    )
    screen = np.asarray(values, dtype=np.int16).reshape(height, width, 4)[..., :3]
    request = page.evaluate("window.narfViewer.lastRequest.narf")
    reply = httpx.post(f"{url}/v1/render", json=request, timeout=30).raise_for_status().json()
    served = np.asarray(Image.open(io.BytesIO(base64.b64decode(reply["rgb"]))).convert("RGB"), dtype=np.int16)
    return float(np.abs(screen - served).max())


def run(models_dir: Path = Path("models"), *, drags: int = 20, size: tuple[int, int] = (160, 120)) -> dict[str, Any]:
    """Serve ``models_dir`` on loopback, open the viewer and time slider moves; see the module docstring."""
    from narf_service.app import create_app
    from narf_service.main import serve_in_thread
    from narf_service.settings import Settings

    executable = chromium_path()
    if executable is None:
        raise RuntimeError("no chromium executable (apt-get install chromium, or set NARF_CHROMIUM)")
    settings = Settings(models_dir=models_dir, workers=2, torch_threads=1)
    result: dict[str, Any] = {
        "size": list(size), "drags": drags, "cpu_count": os.cpu_count(), "load_average": list(os.getloadavg())
    }
    rows = []
    with serve_in_thread(create_app(settings)) as url, browser(executable) as chromium:
        page = chromium.new_page(viewport={"width": 1280, "height": 800})
        page.set_default_timeout(60_000)
        page.goto(f"{url}/viewer/")
        page.select_option("#size", f"{size[0]}x{size[1]}")
        page.wait_for_function("window.narfViewer.frames.filter((f) => f.mode === 'parts').length >= 1")
        for label, parts in (("narf and parts side by side", True), ("narf alone", False)):
            page.set_checked('input[name="mode"][value="parts"]', parts)
            page.wait_for_timeout(500)
            lower, upper = (float(page.get_attribute("#model-joints input[type=range]", a)) for a in ("min", "max"))
            values = [lower + (upper - lower) * (i % 10 + 1) / 11 for i in range(drags)]
            steps = [page.evaluate(SLIDE_AND_WAIT, [value, "narf"]) for value in values]
            error = _screen_error(page, url)
            drag = page.evaluate(CONTINUOUS_DRAG, [125, 16, "narf"])
            frames = drag["frames"]
            rows.append({
                "panes": label,
                "steps": _summary([f["latencyMs"] for f in steps]),
                "server_render_ms": statistics.median(f["serverMs"] for f in steps),
                "continuous": {**_summary([f["latencyMs"] for f in frames]), "frames_per_s": len(frames) / drag["seconds"],
                               "inputs": drag["inputs"]},
                "screen_vs_server_max_levels": error,
            })
        page.close()
    result["rows"] = rows
    return result


def markdown(result: dict[str, Any]) -> str:
    w, h = result["size"]
    lines = [
        f"Viewer: joint slider -> new image on screen, {w}x{h}, {result['drags']} moves "
        f"({result['cpu_count']} cores, load average {result['load_average'][0]:.2f} at start)",
        "",
        "| panes | error: screen vs server (8-bit levels) | one move: median / p90 / max | server render (median) "
        "| continuous drag: median / p90 latency | frames/s |",
        "|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        s, c = row["steps"], row["continuous"]
        lines.append(
            f"| {row['panes']} | {row['screen_vs_server_max_levels']:.0f} | {s['median_ms']:.0f} / {s['p90_ms']:.0f} / "
            f"{s['max_ms']:.0f} ms | {row['server_render_ms']:.0f} ms | {c['median_ms']:.0f} / {c['p90_ms']:.0f} ms "
            f"| {c['frames_per_s']:.1f} |"
        )
    return "\n".join(lines)
