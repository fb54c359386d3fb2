"""Issue #12, reproducibly: the service against an attacker and a careless client.

Every case runs against a real uvicorn server on a loopback port, mostly over raw sockets (so that
slow, half-sent and abandoned requests are what they claim to be). Limits and timeouts are set
small so that the suite stays within seconds; the last test checks that no request of the suite
was answered with a 5xx other than 503.
"""

from __future__ import annotations

import io
import json
import socket
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from helpers import ROOT, ToyModel, camera_json, pose_json, toy_engine, toy_load_bundle, toy_refine, wait_until
from narf_service.app import create_app
from narf_service.engine import Engine
from narf_service.images import decode_rgb
from narf_service.main import serve_in_thread
from narf_service.registry import ModelRegistry
from narf_service.settings import Settings

TOKEN = "adversarial-s3cret"
TIMEOUT_S = 1.0  # header, body and keep-alive timeouts of the servers here
W, H = 32, 24
BUNDLED = ROOT / "models" / "clamp.narf"


# --- helpers: raw HTTP over sockets --------------------------------------------------------------


@dataclass
class Reply:
    status: int
    headers: dict[str, str]
    body: bytes

    def json(self) -> dict:
        return json.loads(self.body)

    def error(self) -> dict:
        return self.json()["error"]


def connect(url: str, timeout: float = 10.0) -> socket.socket:
    host, port = url.removeprefix("http://").split(":")
    return socket.create_connection((host, int(port)), timeout=timeout)


def read_reply(sock: socket.socket) -> Reply:
    """One HTTP/1.1 response (Content-Length framed, as the server sends them)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"closed before a full response: {data!r}")
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    length = int(headers.get("content-length", 0))
    while len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        body += chunk
    return Reply(status, headers, body[:length])


def request_bytes(method: str, path: str, body: bytes = b"", headers: dict[str, str] | None = None) -> bytes:
    lines = [f"{method} {path} HTTP/1.1", "Host: test"]
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
    if body or method == "POST":
        lines.append(f"Content-Length: {len(body)}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + body


def call(url: str, method: str, path: str, body: bytes = b"", headers: dict[str, str] | None = None) -> Reply:
    with connect(url) as sock:
        sock.sendall(request_bytes(method, path, body, headers))
        return read_reply(sock)


def post_json(url: str, path: str, document, **headers: str) -> Reply:
    body = document if isinstance(document, bytes) else json.dumps(document).encode()
    return call(url, "POST", path, body, {"Content-Type": "application/json", **headers})


def closed_by_server(sock: socket.socket, within_s: float) -> tuple[bool, bytes]:
    """Whether the server closes ``sock`` within ``within_s`` seconds, and what it sent before."""
    sock.settimeout(within_s)
    received = b""
    try:
        while chunk := sock.recv(65536):
            received += chunk
        return True, received
    except TimeoutError:
        return False, received
    except ConnectionResetError:
        return True, received


def multipart(parts: dict[str, tuple[str | None, bytes, str]]) -> tuple[bytes, str]:
    boundary = "narf-adversarial-boundary"
    out = b""
    for name, (filename, data, content_type) in parts.items():
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out += f"--{boundary}\r\nContent-Disposition: {disposition}\r\nContent-Type: {content_type}\r\n\r\n".encode()
        out += data + b"\r\n"
    return out + f"--{boundary}--\r\n".encode(), f"multipart/form-data; boundary={boundary}"


def png(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def estimate_parts(**overrides) -> dict[str, tuple[str | None, bytes, str]]:
    rgb = np.zeros((H, W, 3), np.uint8)
    mask = np.zeros((H, W), np.uint8)
    mask[8:16, 10:22] = 255
    # The paper's preset: the least work per iteration, so that the requests stay inside the work limit
    # of these servers (settings_for) with a depth part or without.
    request = {"model": "toy", "camera": camera_json(W, H), "initial_pose": pose_json(0.41), "iterations": 5,
               "options": {"preset": "paper"}}
    parts = {
        "request": (None, json.dumps(request).encode(), "application/json"),
        "image": ("image.png", png(rgb), "image/png"),
        "mask": ("mask.png", png(mask), "image/png"),
    }
    for name, value in overrides.items():
        if isinstance(value, dict):
            value = (None, json.dumps({**request, **value}).encode(), "application/json")
        parts[name] = value
    return parts


def post_estimate(url: str, parts: dict, **headers: str) -> Reply:
    body, content_type = multipart(parts)
    return call(url, "POST", "/v1/estimate", body, {"Content-Type": content_type, **headers})


# --- the servers ------------------------------------------------------------------------------------


@dataclass
class SlowEngine:
    """The toy engine, but each refinement iteration takes ``step_s``; it records every call."""

    step_s: float = 0.05
    started: list[str] = field(default_factory=list)
    finished: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def engine(self, load_bundle=None) -> Engine:
        def refine(model, image, mask, camera, T_init, *, options=None, should_stop=None, **kwargs):
            tag = f"{int(mask.sum())}"
            with self.lock:
                self.started.append(tag)

            def slow_stop() -> str | None:
                time.sleep(self.step_s)
                return should_stop() if should_stop is not None else None

            result = toy_refine(model, image, mask, camera, T_init, options=options, should_stop=slow_stop, **kwargs)
            with self.lock:
                self.finished.append(result.status)
            return result

        return toy_engine(load_bundle or toy_load_bundle, refine)


def settings_for(models_dir: Path, **overrides) -> Settings:
    values = dict(
        models_dir=models_dir,
        workers=1,
        queue_size=4,
        torch_threads=1,
        max_body_bytes=512 * 1024,
        max_json_bytes=32 * 1024,
        max_image_pixels=64 * 64,
        max_seconds=30.0,
        max_work_rays=200_000,
        header_timeout_s=TIMEOUT_S,
        body_timeout_s=TIMEOUT_S,
        keep_alive_timeout_s=TIMEOUT_S,
    )
    return Settings(**(values | overrides))


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[str]:
    """No token; one worker on the toy model, iterations of 10 ms."""
    engine = SlowEngine(step_s=0.01)
    app = create_app(
        settings_for(tmp_path_factory.mktemp("models")),
        engine=engine.engine(),
        registry=ModelRegistry(models={"toy": ToyModel("toy")}),
    )
    with serve_in_thread(app) as url:
        yield url


@pytest.fixture(scope="module")
def guarded(tmp_path_factory) -> Iterator[str]:
    """With a token (from a file), serving the models of a folder: the toy one and three refused bundles."""
    from narf_core.bundle import load_bundle

    folder = tmp_path_factory.mktemp("guarded")
    (folder / "toy.narf").write_bytes(b"toy")
    raw = bytearray(BUNDLED.read_bytes())
    raw[-1001] ^= 0x10
    (folder / "flipped.narf").write_bytes(bytes(raw))
    (folder / "garbage.narf").write_bytes(b"\x00" * 64)
    model = load_bundle(BUNDLED)
    next(iter(model.field.parameters())).data.fill_(float("nan"))
    from narf_core.bundle import save_bundle

    save_bundle(folder / "nan.narf", model)
    token_file = tmp_path_factory.mktemp("secret") / "token"
    token_file.write_text(TOKEN + "\n")

    def load(path: Path, device: str = "cpu"):
        return ToyModel(path.stem) if path.read_bytes() == b"toy" else load_bundle(path, device)

    app = create_app(settings_for(folder, token_file=token_file), engine=SlowEngine().engine(load))
    with serve_in_thread(app) as url:
        yield url


AUTH = {"Authorization": f"Bearer {TOKEN}"}


def render_body(**overrides) -> dict:
    return {"model": "toy", "pose": pose_json(), "camera": camera_json(W, H), **overrides}


# --- 1. sizes are checked before allocating ---------------------------------------------------------


def npy_header(shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}".encode()
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header


def test_an_npy_header_declaring_a_huge_array_is_413_and_the_connection_lives(server: str) -> None:
    with connect(server) as sock:
        body, content_type = multipart(estimate_parts(depth=("d.npy", npy_header((100000, 100000)) + b"\0" * 64, "application/octet-stream")))
        sock.sendall(request_bytes("POST", "/v1/estimate", body, {"Content-Type": content_type}))
        reply = read_reply(sock)
        assert reply.status == 413 and reply.error()["field"] == "depth", reply
        sock.sendall(request_bytes("GET", "/healthz"))  # same keep-alive connection
        assert read_reply(sock).status == 200


@pytest.mark.parametrize(
    ("depth", "status", "word"),
    [
        (npy_header((24, 32)) + b"\0" * 100, 422, "truncated"),  # fewer bytes than the header says
        (npy_header((24, 32), "|O") + b"\0" * 64, 422, "expected a 2-D float"),  # a pickle payload
        (npy_header((24, 32, 3)) + b"\0" * (24 * 32 * 12), 422, "expected a 2-D float"),
        (b"\x93NUMPY\x09\x00" + b"\0" * 32, 422, "not a readable"),
        (npy_header((24, 32)) + np.full((24, 32), -1, np.float32).tobytes(), 422, "negative"),
    ],
)
def test_hostile_npy_depths_are_422(server: str, depth: bytes, status: int, word: str) -> None:
    reply = post_estimate(server, estimate_parts(depth=("d.npy", depth, "application/octet-stream")))
    assert reply.status == status and reply.error()["field"] == "depth" and word in reply.error()["message"], reply


def test_a_decompression_bomb_png_is_413(server: str) -> None:
    bomb = io.BytesIO()
    Image.new("L", (4000, 4000)).save(bomb, format="PNG")  # ~16 kB of zeros claiming 16 Mpx
    reply = post_estimate(server, estimate_parts(mask=("mask.png", bomb.getvalue(), "image/png")))
    assert reply.status == 413 and reply.error()["field"] == "mask"


def test_garbage_images_are_422_naming_the_part(server: str) -> None:
    for data in (b"\x89PNG\r\n\x1a\n" + b"\xff" * 200, b"\xff\xd8\xff" + b"\x00" * 300, b"GIF89a" + b"\0" * 50):
        reply = post_estimate(server, estimate_parts(image=("image.png", data, "image/png")))
        assert reply.status == 422 and reply.error()["field"] == "image", reply


def test_a_jpeg_exif_orientation_is_applied() -> None:
    upright = np.zeros((20, 40, 3), np.uint8)
    upright[:, :10] = 255  # white on the left
    exif = Image.Exif()
    exif[0x0112] = 8  # stored rotated: turn 90° counter-clockwise to view (PIL: Image.ROTATE_90)
    buffer = io.BytesIO()
    Image.fromarray(upright).transpose(Image.Transpose.ROTATE_270).save(buffer, format="JPEG", exif=exif, quality=95)
    decoded = decode_rgb(buffer.getvalue(), "image", 10_000)
    assert decoded.shape == (20, 40, 3)
    assert decoded[:, :8].mean() > 200 and decoded[:, 12:].mean() < 50


# --- 2. bodies: media type, size, parsing off the loop, after auth ----------------------------------


def test_a_text_plain_body_is_415(server: str) -> None:
    reply = call(server, "POST", "/v1/render", json.dumps(render_body()).encode(), {"Content-Type": "text/plain"})
    assert reply.status == 415 and reply.error()["field"] == "body"
    assert call(server, "POST", "/v1/render", json.dumps(render_body()).encode()).status == 415  # no type at all


def test_a_json_body_over_its_limit_is_413_before_it_is_read(server: str) -> None:
    with connect(server) as sock:  # 30 MB declared: refused on the header, nothing sent
        sock.sendall(request_bytes("POST", "/v1/render", b"", {"Content-Type": "application/json"}).replace(
            b"Content-Length: 0", b"Content-Length: 31457280"))
        assert read_reply(sock).status == 413
    big = json.dumps({**render_body(), "padding": "x" * 40_000}).encode()  # over max_json_bytes, under max_body_bytes
    reply = post_json(server, "/v1/render", big)
    assert reply.status == 413 and reply.error()["field"] == "body" and "JSON body" in reply.error()["message"]


def test_an_estimate_request_part_over_the_json_limit_is_413(server: str) -> None:
    document = json.dumps({f"k{i}": 0 for i in range(5000)}).encode()  # ~50 kB, over max_json_bytes
    reply = post_estimate(server, estimate_parts(request=(None, document, "application/json")))
    assert reply.status == 413 and reply.error()["field"] == "body" and "form field" in reply.error()["message"]


def test_a_body_of_thousands_of_keys_is_422_with_their_count(server: str) -> None:
    document = {**render_body(), **{f"k{i}": i for i in range(1500)}}  # ~15 kB: validated off the loop
    reply = post_json(server, "/v1/render", document)
    assert reply.status == 422 and "(and 1499 more)" in reply.error()["message"], reply


@pytest.mark.parametrize(
    ("body", "status", "field"),
    [
        (b'{"model": "toy", "pose": ', 400, "body"),
        (b"\xff\xfe" * 5000, 400, "body"),  # large and not UTF-8
        (b"[" * 5000 + b"]" * 5000, 400, "body"),  # deep nesting
        (json.dumps(render_body(pose={"matrix": [[float("nan")] * 4] * 4})).encode(), 422, "pose.matrix[0][0]"),
        (json.dumps(render_body(pose={"matrix": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.4], [0, 0, 0, 1]]})).encode(), 422, "pose.matrix"),
        (json.dumps(render_body(model="../../etc/passwd")).encode(), 422, "model"),
    ],
)
def test_malformed_and_hostile_json_is_4xx_naming_the_field(server: str, body: bytes, status: int, field) -> None:
    reply = post_json(server, "/v1/render", body)
    assert reply.status == status, reply
    if field is not None:
        assert reply.error()["field"] == field, reply


def test_unknown_model_names_never_become_paths(server: str) -> None:
    """An encoded slash matches no route (404); dots and a NUL fail the name's pattern (422 naming it)."""
    assert call(server, "GET", "/v1/models/..%2F..%2Fetc%2Fpasswd").status == 404
    for name in ("%2e%2e", "clamp.narf%00"):
        reply = call(server, "GET", f"/v1/models/{name}")
        assert reply.status == 422 and reply.error()["field"] == "name", reply


def test_health_answers_while_a_large_hostile_body_is_refused(server: str) -> None:
    """A body of many keys just under the JSON limit is validated on a thread; /healthz still answers
    during it, and both answers are right."""
    document = {**render_body(), **{f"{i}": 0 for i in range(1600)}}
    results: dict[str, int] = {}

    def hostile() -> None:
        results["hostile"] = post_json(server, "/v1/render", document).status

    thread = threading.Thread(target=hostile)
    thread.start()
    statuses = [call(server, "GET", "/healthz").status for _ in range(5)]
    thread.join(timeout=10)
    assert statuses == [200] * 5 and results["hostile"] == 422


# --- 3. slow and idle connections -------------------------------------------------------------------


def test_a_trickled_body_is_408_and_closed(server: str) -> None:
    body = json.dumps(render_body()).encode()
    with connect(server) as sock:
        head = request_bytes("POST", "/v1/render", body, {"Content-Type": "application/json"})[: -len(body)]
        sock.sendall(head + body[:1])
        for byte in body[1:4]:  # a byte every 0.25 s, stopping before the server's 1 s deadline
            time.sleep(0.25)
            sock.sendall(bytes([byte]))
        closed, received = closed_by_server(sock, 5 * TIMEOUT_S)
        assert closed and received.startswith(b"HTTP/1.1 408"), received


def test_trickled_headers_are_408_and_closed(server: str) -> None:
    with connect(server) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: t")
        for _ in range(3):  # a byte every 0.25 s, stopping before the server's 1 s deadline
            time.sleep(0.25)
            sock.sendall(b"e")
        closed, received = closed_by_server(sock, 5 * TIMEOUT_S)
        assert closed and received.startswith(b"HTTP/1.1 408"), received


def test_idle_connections_are_closed(server: str) -> None:
    fresh = [connect(server) for _ in range(3)]  # never send a byte
    used = connect(server)
    used.sendall(request_bytes("GET", "/healthz"))
    assert read_reply(used).status == 200  # then idle, kept alive
    try:
        for sock in [*fresh, used]:
            closed, received = closed_by_server(sock, 5 * TIMEOUT_S)
            assert closed and received == b""
    finally:
        for sock in [*fresh, used]:
            sock.close()


def test_clients_gone_in_the_middle_of_a_body_are_no_server_error(server: str) -> None:
    body, content_type = multipart(estimate_parts())
    for path, data, kind in (("/v1/estimate", body, content_type), ("/v1/render", json.dumps(render_body()).encode(), "application/json")):
        sock = connect(server)
        sock.sendall(request_bytes("POST", path, data, {"Content-Type": kind})[: -len(data) // 2])
        time.sleep(0.1)
        sock.close()
    time.sleep(0.3)
    assert server_errors(server) == {}  # a 499 nobody reads, not a 500 with a traceback


# --- 4. abandoned work stops; work is bounded --------------------------------------------------------


@pytest.fixture
def slow_server(tmp_path) -> Iterator[tuple[str, SlowEngine, object]]:
    engine = SlowEngine(step_s=0.05)
    app = create_app(
        settings_for(tmp_path, max_seconds=0.5), engine=engine.engine(), registry=ModelRegistry(models={"toy": ToyModel("toy")})
    )
    with serve_in_thread(app) as url:
        yield url, engine, app


def test_disconnected_estimates_are_cancelled_waiting_and_running(slow_server) -> None:
    url, engine, app = slow_server
    queue = app.state.queue
    body, content_type = multipart(estimate_parts(request={"iterations": 90}))  # 4.5 s each if left to run
    socks = []
    for _ in range(3):
        sock = connect(url)
        sock.sendall(request_bytes("POST", "/v1/estimate", body, {"Content-Type": content_type}))
        socks.append(sock)
    wait_until(lambda: queue.running == 1 and queue.waiting == 2, timeout=5)
    for sock in socks:
        sock.close()
    wait_until(lambda: queue.running == 0 and queue.waiting == 0, timeout=2)
    assert engine.started == ["96"] and engine.finished == ["cancelled"]  # the two waiting ones never started
    assert server_errors(url) == {}


def test_an_estimate_past_the_time_budget_stops_with_budget_exceeded(slow_server) -> None:
    url, engine, _ = slow_server
    reply = post_estimate(url, estimate_parts(request={"iterations": 60}))  # 3 s, over the budget of 0.5 s
    assert reply.status == 200, reply
    answer = reply.json()
    assert answer["status"] == "budget_exceeded" and 0 < answer["iterations"] < 60


def test_work_beyond_the_budget_is_refused_before_it_starts(slow_server) -> None:
    url, engine, _ = slow_server
    reply = post_estimate(url, estimate_parts(request={"iterations": 50, "options": {"preset": "paper", "rays_per_iteration": 4096}}))
    assert reply.status == 422 and reply.error()["field"] == "request.options", reply
    # 50 x 4096 rays, then the final choice and pruning on 5 x 4096 and the covariance on 4096 squares of 4 x 4
    assert "would trace up to 290816 rays" in reply.error()["message"] and engine.started == []


def test_a_one_pixel_mask_is_422_naming_the_mask(server: str) -> None:
    mask = np.zeros((H, W), np.uint8)
    mask[5, 5] = 255
    reply = post_estimate(server, estimate_parts(mask=("mask.png", png(mask), "image/png")))
    assert reply.status == 422 and reply.error()["field"] == "mask", reply


# --- 5. auth scope and leaks; 6. bundle integrity ------------------------------------------------------


def test_only_the_public_routes_answer_without_the_token(guarded: str) -> None:
    assert call(guarded, "GET", "/healthz").status == 200
    assert call(guarded, "HEAD", "/healthz").status == 200
    for path in ("/metrics", "/docs", "/openapi.json", "/v1/models", "/viewer/", "/some/future/route", "/healthz/../v1/models"):
        reply = call(guarded, "GET", path)
        assert reply.status == 401 and reply.headers.get("www-authenticate") == "Bearer", (path, reply)
    assert call(guarded, "GET", "/metrics", headers=AUTH).status == 200
    assert call(guarded, "GET", "/openapi.json", headers=AUTH).status == 200


def test_an_unauthenticated_body_is_never_read(guarded: str) -> None:
    with connect(guarded) as sock:  # declares 400 kB, sends none of it: the 401 must come anyway
        sock.sendall(request_bytes("POST", "/v1/render", b"", {"Content-Type": "application/json"}).replace(
            b"Content-Length: 0", b"Content-Length: 400000"))
        assert read_reply(sock).status == 401
    assert post_json(guarded, "/v1/render", render_body(), Authorization="Bearer wrong").status == 401
    assert post_json(guarded, "/v1/render", render_body(), **AUTH).status == 200


def test_readyz_names_refused_bundles_and_shows_reasons_only_with_the_token(guarded: str) -> None:
    public = call(guarded, "GET", "/readyz").json()
    assert public["status"] == "ready" and public["models"] == ["toy"]
    assert public["failed"] == {"flipped": "not loaded", "garbage": "not loaded", "nan": "not loaded"}
    detailed = call(guarded, "GET", "/readyz", headers=AUTH).json()["failed"]
    assert "checksum mismatch" in detailed["flipped"] and "non-finite weights in field." in detailed["nan"]
    assert "not a NARF model bundle" in detailed["garbage"]
    for reason in detailed.values():
        assert "/" not in reason and "\n" not in reason  # one line, no paths
    assert call(guarded, "GET", "/v1/models/nan", headers=AUTH).status == 404


def test_serve_refuses_a_token_on_the_command_line(capsys) -> None:
    from narf_core.cli import main

    assert main(["serve", "--token", "s3cret", "--models", str(ROOT / "models")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("narf serve: error: ") and "s3cret" not in err and "--token-file" in err


def test_settings_read_the_token_from_a_file_and_refuse_two_sources(tmp_path) -> None:
    path = tmp_path / "token"
    path.write_text("  from-a-file\n")
    assert Settings(models_dir=tmp_path, token_file=path).token.get_secret_value() == "from-a-file"
    with pytest.raises(ValueError, match="not both"):
        Settings(models_dir=tmp_path, token_file=path, token="x")
    path.write_text("\n")
    with pytest.raises(ValueError, match="empty"):
        Settings(models_dir=tmp_path, token_file=path)


# --- last: nothing in this suite was a server error ----------------------------------------------------


def server_errors(url: str, headers: dict[str, str] | None = None) -> dict[str, float]:
    text = call(url, "GET", "/metrics", headers=headers).body.decode()
    counts = {}
    for line in text.splitlines():
        if line.startswith("narf_http_requests_total{"):
            labels, value = line.rsplit(" ", 1)
            status = labels.split('status="')[1].split('"')[0]
            if status.startswith("5") and status != "503":
                counts[labels] = float(value)
    return counts


def test_zz_no_request_of_the_suite_was_a_server_error(server: str, guarded: str) -> None:
    assert server_errors(server) == {}
    assert server_errors(guarded, AUTH) == {}
