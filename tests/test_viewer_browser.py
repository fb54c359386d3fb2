"""The web viewer (/viewer) driven in a real headless Chromium against a real ``narf serve`` on loopback.

The browser is Debian's ``chromium`` (``/usr/bin/chromium``, or ``NARF_CHROMIUM``) driven through
Playwright's Python API; nothing is downloaded at run time. Outside CI the tests skip when either is
missing; in CI (``CI=true``, where ``.ci/run`` installs chromium) they fail instead. Screenshots of each
state go to ``NARF_VIEWER_SHOTS`` if set, else to a temporary folder printed with ``-s``.
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Iterator
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from narf_service.main import serve_process
from narf_benchmarks.viewer import CHROMIUM_ARGS, NARF_CANVAS, SLIDE_AND_WAIT, chromium_path

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "viewer-test-token"
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
FRAME_TIMEOUT_MS = 30_000
ESTIMATE_TIMEOUT_MS = 120_000  # 30 iterations take seconds; the margin is for a machine shared with other jobs


def _missing(reason: str) -> None:
    if IN_CI:
        pytest.fail(f"{reason} (CI installs it: see .ci/run)")
    pytest.skip(reason)


def _chromium() -> str:
    path = chromium_path()
    if path is None:
        _missing("no chromium executable (apt-get install chromium, or set NARF_CHROMIUM)")
    return path


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    """``narf serve`` of the bundled model, with a token and the page public, as its own process on a free loopback port."""
    env = {**os.environ, "NARF_WORKERS": "2", "NARF_TORCH_THREADS": "1", "NARF_TOKEN": TOKEN,
           "NARF_PUBLIC_ROUTES": "/healthz,/readyz,/viewer"}  # the page is public, its API calls carry the token
    with serve_process(["--models", str(ROOT / "models")], env) as url:
        yield url


@pytest.fixture(scope="module")
def browser() -> Iterator:
    executable = _chromium()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _missing("the playwright Python package is not installed (pip install -e '.[dev]')")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        yield browser
        browser.close()


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    folder = Path(os.environ.get("NARF_VIEWER_SHOTS") or tmp_path_factory.mktemp("viewer-shots"))
    folder.mkdir(parents=True, exist_ok=True)
    print(f"\nviewer screenshots: {folder}")
    return folder


class Page:
    """A page of the viewer with its console errors collected."""

    def __init__(self, browser, server: str, *, token: str | None = TOKEN, width: int = 1280, height: int = 800,
                 touch: bool = False):
        self.context = browser.new_context(viewport={"width": width, "height": height}, accept_downloads=True, has_touch=touch)
        if token is not None:
            self.context.add_init_script(f"sessionStorage.setItem('narf.token', {json.dumps(token)})")
        self.page = self.context.new_page()
        self.page.set_default_timeout(FRAME_TIMEOUT_MS)
        self.errors: list[str] = []
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(f"uncaught: {e}"))
        self.page.goto(f"{server}/viewer/")

    def wait_frames(self, count: int = 1, timeout_ms: float = FRAME_TIMEOUT_MS, **match) -> None:
        """Wait until ``count`` logged frames match ``match`` (e.g. ``view="model", mode="narf"``); on a
        timeout, fail with the frames drawn so far, the console errors and the panes' error texts."""
        from playwright.sync_api import TimeoutError as PlaywrightTimeout

        try:
            self.page.wait_for_function(
                """([count, match]) => window.narfViewer && window.narfViewer.frames
                     .filter((f) => Object.entries(match).every(([k, v]) => f[k] === v)).length >= count""",
                arg=[count, match],
                timeout=timeout_ms,
            )
        except PlaywrightTimeout:
            seen = self.page.evaluate(
                """() => ({frames: (window.narfViewer?.frames ?? []).map(({view, mode, input, seq}) => ({view, mode, input, seq})),
                          paneErrors: [...document.querySelectorAll('.pane .error')].map((e) => e.textContent)})"""
            )
            pytest.fail(f"no {count} frame(s) matching {match} in {timeout_ms / 1000:.0f} s; "
                        f"seen {seen}; console errors {self.errors}")

    def pixels(self, selector: str) -> np.ndarray:
        data = self.page.evaluate(
            """(selector) => { const c = document.querySelector(selector);
                 return [c.width, c.height, Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data)]; }""",
            selector,
        )
        width, height, values = data
        return np.asarray(values, dtype=np.uint8).reshape(height, width, 4)

    def shot(self, folder: Path, name: str) -> None:
        self.page.screenshot(path=str(folder / f"{name}.png"), full_page=True)

    def close(self) -> None:
        self.context.close()


@pytest.fixture
def viewer(browser, server) -> Iterator[Page]:
    page = Page(browser, server)
    yield page
    page.close()


def test_the_page_loads_with_no_console_errors(viewer: Page, shots: Path) -> None:
    viewer.wait_frames(view="model", mode="narf")
    viewer.wait_frames(view="model", mode="parts")
    page = viewer.page
    assert page.input_value("#model") == "clamp"
    assert page.locator("#model-joints input[type=range]").count() == 1
    assert "mm" in page.locator("#model-joints output").inner_text()
    narf = viewer.pixels(NARF_CANVAS)
    assert narf.shape == (120, 160, 4) and (narf[..., :3].max(-1) > 40).mean() > 0.02, "the clamp is on screen"
    assert "ms" in page.locator('.pane[data-mode="narf"] .timing').inner_text()
    viewer.shot(shots, "model-1280x800")

    page.focus("#tab-model")  # the tabs follow the WAI-ARIA pattern: arrow keys switch
    page.keyboard.press("ArrowRight")
    assert page.get_attribute("#tab-estimate", "aria-selected") == "true" and page.locator("#view-estimate").is_visible()
    page.keyboard.press("ArrowLeft")
    assert page.locator("#view-model").is_visible()

    page.set_viewport_size({"width": 390, "height": 844})
    page.wait_for_timeout(200)
    width = page.evaluate("document.documentElement.scrollWidth")
    assert width <= 390, f"the page scrolls sideways on a phone ({width} px wide)"
    slider = page.locator("#model-joints input[type=range]").bounding_box()
    assert slider["y"] + slider["height"] <= 844, "on a phone the joint slider is on the first screen, under the images"
    viewer.shot(shots, "model-390x844")
    assert viewer.errors == []


def test_a_missing_token_is_asked_for_next_to_the_token_field(browser, server: str, shots: Path) -> None:
    viewer = Page(browser, server, token=None)
    try:
        error = viewer.page.locator("#token-error")
        error.wait_for(state="visible")
        assert "bearer token" in error.inner_text()
        viewer.shot(shots, "token-missing")
        viewer.page.fill("#token", TOKEN)
        viewer.page.click('#token-form button[type="submit"]')
        viewer.wait_frames(view="model", mode="narf")
        assert error.is_hidden()
        assert all("401" in e for e in viewer.errors), viewer.errors  # only the refused request itself
    finally:
        viewer.close()


def test_a_slider_change_renders_a_new_image(viewer: Page, shots: Path) -> None:
    viewer.wait_frames(view="model", mode="narf")
    before = viewer.pixels(NARF_CANVAS)
    frame = viewer.page.evaluate(SLIDE_AND_WAIT, [0.2, "narf"])
    after = viewer.pixels(NARF_CANVAS)
    assert frame["output"] == "rgb" and frame["width"] == 160
    changed = (np.abs(before.astype(int) - after.astype(int)).max(-1) > 30).mean()
    assert changed > 0.005, f"only {changed:.2%} of the pixels changed when the jaw opened"
    viewer.shot(shots, "model-jaw-open")

    viewer.page.check('input[name="output"][value="depth"]')
    viewer.wait_frames(view="model", mode="narf", output="depth")
    depth = viewer.pixels(NARF_CANVAS)
    assert viewer.page.locator("#depth-scale").is_visible()
    assert not np.array_equal(depth, after)
    viewer.shot(shots, "model-depth")

    viewer.page.focus(NARF_CANVAS)  # keyboard: the arrow keys orbit the camera
    count = viewer.page.evaluate("window.narfViewer.frames.filter((f) => f.input === 'keydown').length")
    viewer.page.keyboard.press("ArrowRight")
    viewer.wait_frames(count + 1, view="model", mode="narf", input="keydown")
    assert not np.array_equal(viewer.pixels(NARF_CANVAS), depth)
    assert viewer.errors == []


@pytest.mark.slow
def test_slider_drag_latency_is_measured_in_the_browser(viewer: Page, shots: Path) -> None:
    """Input event to the frame that paints the new image, 20 slider moves at 160x120 (printed, not asserted)."""
    viewer.wait_frames(view="model", mode="narf")
    viewer.wait_frames(view="model", mode="parts")
    results = {}
    for label, parts in (("narf and parts side by side", True), ("narf alone", False)):
        viewer.page.set_checked('input[name="mode"][value="parts"]', parts)
        viewer.page.wait_for_timeout(300)
        latencies = []
        for i in range(20):
            frame = viewer.page.evaluate(SLIDE_AND_WAIT, [0.05 + 0.007 * i, "narf"])
            latencies.append(frame["latencyMs"])
        results[label] = latencies
    for label, latencies in results.items():
        assert all(np.isfinite(latencies)) and min(latencies) > 0
        print(f"slider drag -> new image on screen, 160x120, {label}: median {statistics.median(latencies):.0f} ms, "
              f"p90 {np.percentile(latencies, 90):.0f} ms, max {max(latencies):.0f} ms over {len(latencies)} drags")
    (shots / "latency.json").write_text(json.dumps(results, indent=1))


def _example_estimate(viewer: Page, iterations: int = 30) -> None:
    page = viewer.page
    viewer.wait_frames(view="model", mode="narf")  # the model list has arrived
    examples = page.evaluate("window.narfViewer.frames.filter((f) => f.kind === 'example').length")
    page.click("#tab-estimate")
    page.click("#example")
    viewer.wait_frames(examples + 1, view="estimate", kind="example")  # inputs filled, start outline drawn
    page.fill("#iterations", str(iterations))


def _count(pixels: np.ndarray, colour: tuple[int, int, int]) -> int:
    return int((np.abs(pixels[..., :3].astype(int) - colour).max(-1) <= 2).sum())


@pytest.mark.slow
def test_an_estimate_round_trip_shows_the_outlines_plot_and_result(viewer: Page, shots: Path) -> None:
    page = viewer.page
    _example_estimate(viewer)
    assert page.locator("#overlay").is_visible()
    start = viewer.pixels("#overlay")
    assert _count(start, (255, 140, 0)) > 20, "the start outline is drawn over the image"
    viewer.shot(shots, "estimate-start")

    page.click("#run")
    viewer.wait_frames(view="estimate", kind="result", timeout_ms=ESTIMATE_TIMEOUT_MS)
    overlay = viewer.pixels("#overlay")
    assert _count(overlay, (0, 200, 83)) > 20, "the result outline is drawn over the image"
    assert _count(overlay, (255, 140, 0)) > 0
    summary = page.locator("#result-summary").inner_text()
    assert "jaw_opening" in summary and "add" in summary and "position" in summary
    assert page.locator("#loss-plot path.plot-line").count() == 1
    page.check('input[name="plot-x"][value="seconds"]')
    assert "time (s)" in page.locator("#loss-plot").text_content()
    viewer.shot(shots, "estimate-result")

    with page.expect_download() as download:
        page.click("#download")
    exchange = json.loads(Path(download.value.path()).read_text())
    response = exchange["response"]
    assert exchange["request"]["iterations"] == 30 and exchange["request"]["ground_truth"] is not None
    # The default preset, auto, with the example's depth image: gauss-newton, which may refine a second time
    # from its pose starts (pose_starts_overlap) when the first estimate misses the mask.
    assert response["preset"] == "gauss-newton" and "preset" in summary
    assert np.asarray(response["pose"]["matrix"]).shape == (4, 4) and 1 <= response["iterations"] <= 2 * 30
    assert response["metrics"]["add"] < 0.05, "the example's estimate lands near the true pose"
    assert response["uncertainty"] is not None and page.locator("#uncertainty").is_visible()
    assert "mm" in page.locator("#uncertainty-values").inner_text()

    page.set_viewport_size({"width": 390, "height": 844})
    page.wait_for_timeout(200)
    width = page.evaluate("document.documentElement.scrollWidth")
    assert width <= 390, f"the page scrolls sideways on a phone ({width} px wide)"
    viewer.shot(shots, "estimate-result-390x844")
    assert viewer.errors == []


def _png(array: np.ndarray) -> bytes:
    buffer = BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


@pytest.mark.slow
def test_bad_uploads_show_an_error_next_to_their_control(viewer: Page, shots: Path) -> None:
    page = viewer.page
    _example_estimate(viewer, iterations=5)

    page.set_input_files("#image", files=[{"name": "notes.png", "mimeType": "image/png", "buffer": b"not an image"}])
    error = page.locator("#image-error")
    error.wait_for(state="visible")
    assert "cannot read 'notes.png'" in error.inner_text()
    assert page.get_attribute("#image", "aria-invalid") == "true"
    assert page.locator("#gt-label").is_hidden(), "a new image is no longer the example: no ground truth to score"
    viewer.shot(shots, "error-unreadable-image")

    _example_estimate(viewer, iterations=5)  # good inputs again, then a mask the server refuses
    rgb_mask = np.zeros((120, 160, 3), np.uint8)
    page.set_input_files("#mask", files=[{"name": "rgb-mask.png", "mimeType": "image/png", "buffer": _png(rgb_mask)}])
    page.click("#run")
    error = page.locator("#mask-error")
    error.wait_for(state="visible")
    assert "single-channel" in error.inner_text(), error.inner_text()
    assert page.locator("#run-status").inner_text() == "Failed."
    viewer.shot(shots, "error-rgb-mask")

    small_mask = np.full((60, 80), 255, np.uint8)
    page.set_input_files("#mask", files=[{"name": "small-mask.png", "mimeType": "image/png", "buffer": _png(small_mask)}])
    page.click("#run")
    page.wait_for_function(
        "document.querySelector('#mask-error').textContent.includes('does not match')", timeout=ESTIMATE_TIMEOUT_MS
    )
    assert "80x60" in error.inner_text()
    assert page.locator("#image-error").is_hidden()
    assert [e for e in viewer.errors if "422" not in e] == []  # the refused requests are the only console errors


@pytest.mark.slow
def test_the_initial_pose_follows_the_mouse_and_the_keys(viewer: Page, shots: Path) -> None:
    page = viewer.page
    _example_estimate(viewer)
    x0, z0 = float(page.input_value("#px")), float(page.input_value("#pz"))
    page.focus("#overlay")
    page.keyboard.press("ArrowRight")
    viewer.wait_frames(view="estimate", input="keydown")
    x1 = float(page.input_value("#px"))
    assert x1 > x0, "the right arrow moves the model right (+x in the camera frame)"

    box = page.locator("#overlay").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx - 60, cy, steps=4)
    page.mouse.up()
    viewer.wait_frames(view="estimate", input="pointermove")
    assert float(page.input_value("#px")) < x1 and float(page.input_value("#pz")) == pytest.approx(z0, abs=1e-4)

    page.mouse.wheel(0, 200)  # away from the camera
    viewer.wait_frames(view="estimate", input="wheel")
    assert float(page.input_value("#pz")) > z0
    angles = "['#roll', '#pitch', '#yaw'].map((id) => document.querySelector(id).value).join()"
    before = page.evaluate(angles)
    page.focus("#overlay")
    page.keyboard.press("]")  # roll about the line of sight
    page.wait_for_function(f"(before) => {angles} !== before", arg=before)
    viewer.shot(shots, "estimate-aligned")
    assert viewer.errors == []


@pytest.mark.slow
def test_touch_orbits_with_one_finger_and_zooms_with_two(browser, server: str, shots: Path) -> None:
    viewer = Page(browser, server, width=390, height=844, touch=True)
    try:
        page = viewer.page
        viewer.wait_frames(view="model", mode="narf")
        viewer.wait_frames(view="model", mode="parts")  # both panes sized: the layout no longer moves
        cdp = page.context.new_cdp_session(page)
        canvas = page.locator(NARF_CANVAS)
        canvas.scroll_into_view_if_needed()
        box = canvas.bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        hit = page.evaluate("([x, y]) => document.elementFromPoint(x, y)?.closest('.pane')?.dataset.mode ?? null", [x, y])
        assert hit == "narf", f"the touch point ({x:.0f}, {y:.0f}) is on {hit!r}, not the narf canvas"

        def touch(kind: str, *points: tuple[float, float]) -> None:
            touches = [{"x": px, "y": py, "id": i} for i, (px, py) in enumerate(points)]
            cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": touches})

        pose = page.locator("#camera-pose").text_content()
        touch("touchStart", (x, y))
        for step in range(1, 5):
            touch("touchMove", (x + 12 * step, y))
        touch("touchEnd")
        viewer.wait_frames(view="model", mode="narf", input="pointermove")
        orbited = page.locator("#camera-pose").text_content()
        assert orbited != pose, "one finger orbits the camera"

        zooms = page.evaluate(  # counted as waited for below: the narf pane's frames only, not the parts pane's
            "window.narfViewer.frames.filter((f) => f.view === 'model' && f.mode === 'narf' && f.input === 'pointermove').length"
        )
        touch("touchStart", (x - 20, y), (x + 20, y))
        for step in range(1, 5):
            touch("touchMove", (x - 20 - 10 * step, y), (x + 20 + 10 * step, y))
        touch("touchEnd")
        viewer.wait_frames(zooms + 1, view="model", mode="narf", input="pointermove")
        distance = lambda text: np.linalg.norm(np.array(text.split(), dtype=float).reshape(4, 4)[:3, 3])  # noqa: E731
        assert distance(page.locator("#camera-pose").text_content()) < distance(orbited), "spreading two fingers zooms in"
        viewer.shot(shots, "model-touch-390x844")
        assert viewer.errors == []
    finally:
        viewer.close()
