"""narf_client against a mocked transport: what it sends, what it decodes, errors, retries, poses."""

from __future__ import annotations

import asyncio
import base64
import io
import json
import os
import re
import subprocess
import sys

import httpx
import numpy as np
import pytest
from PIL import Image

import narf_client
from helpers import ROOT
from narf_client import (
    AsyncNarfClient,
    InvalidInput,
    NarfClient,
    NarfConnectionError,
    NotFound,
    Pose,
    ServerError,
    ServiceUnavailable,
)
from narf_client.types import matrix_to_quaternion, quaternion_to_matrix

K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])


def b64png(array: np.ndarray) -> str:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


def estimate_body() -> dict:
    return {
        "model": "toy",
        "pose": {"matrix": np.eye(4).tolist(), "position": [0, 0, 0], "orientation": [0, 0, 0, 1]},
        "joints": {"a": 0.1},
        "loss": 0.01,
        "iterations": 3,
        "status": "converged",
        "recovered_non_finite": False,
        "seconds": 0.5,
        "wall_seconds": 0.6,
        "trace": [[0.3, 0.1], [None, 0.2], [0.01, 0.3]],
        "metrics": {"add": 0.004},
    }


def client_for(handler, **kwargs) -> NarfClient:
    return NarfClient("http://narf.test", transport=httpx.MockTransport(handler), **kwargs)


# --- poses ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "q",
    [[0, 0, 0, 1], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.5, 0.5, 0.5, 0.5], [0.70710678, 0, 0.70710678, 1e-9]],
)
def test_quaternion_round_trip_including_half_turns(q) -> None:
    q = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    R = quaternion_to_matrix(q)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1)
    back = matrix_to_quaternion(R)
    assert back[3] >= 0 and np.allclose(back, q if q[3] >= 0 else -q, atol=1e-9)


def test_pose_forms_agree_and_bad_poses_raise() -> None:
    pose = Pose.from_position_orientation([0.1, -0.2, 0.5], [0, 0, np.sin(0.25), np.cos(0.25)])
    assert np.allclose(pose.position, [0.1, -0.2, 0.5])
    assert np.allclose(pose.orientation, [0, 0, np.sin(0.25), np.cos(0.25)])
    assert pose.to_json()["matrix"][2][3] == 0.5
    with pytest.raises(ValueError, match="4x4"):
        Pose(np.eye(3))
    with pytest.raises(ValueError, match="finite"):
        Pose(np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="non-zero"):
        Pose.from_position_orientation([0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError):
        pose.matrix[0, 0] = 2.0  # read-only


# --- requests and responses -----------------------------------------------------------------------


def test_render_sends_the_wire_format_and_decodes_images() -> None:
    sent = {}
    depth_mm = np.array([[0, 380], [1000, 65535]], dtype=np.uint16)

    def handler(request: httpx.Request) -> httpx.Response:
        sent.update(json.loads(request.content))
        body = {
            "rgb": b64png(np.full((2, 2, 3), 7, np.uint8)),
            "depth": b64png(depth_mm),
            "opacity": None,
            "joints": {"a": 0.5},
            "seconds": 0.01,
        }
        return httpx.Response(200, json=body)

    with client_for(handler) as narf:
        result = narf.render("toy", np.eye(4), K, 2, 2, joints={"a": 0.5}, outputs=("rgb", "depth"))
    assert sent["camera"] == {"K": K.tolist(), "width": 2, "height": 2} and sent["joints"] == {"a": 0.5}
    assert sent["pose"] == {"matrix": np.eye(4).tolist()} and sent["outputs"] == ["rgb", "depth"]
    assert result.rgb.dtype == np.uint8 and (result.rgb == 7).all() and result.opacity is None
    assert result.depth.dtype == np.float32
    assert np.allclose(result.depth, [[0, 0.38], [1.0, 65.535]]) and result.joints == {"a": 0.5}


def test_estimate_sends_image_mask_depth_and_request_parts() -> None:
    parts = {}

    def handler(request: httpx.Request) -> httpx.Response:
        content_type = request.headers["content-type"]
        assert content_type.startswith("multipart/form-data")
        parts["body"] = request.content
        return httpx.Response(200, json=estimate_body())

    image = np.zeros((24, 32, 3), np.uint8)
    mask = np.zeros((24, 32), bool)
    mask[5:10, 5:10] = True
    depth = np.full((24, 32), 0.5, np.float32)
    with client_for(handler) as narf:
        est = narf.estimate(
            image,
            mask,
            K,
            np.eye(4),
            model="toy",
            depth=depth,
            iterations=7,
            ground_truth=(np.eye(4), {"a": 0.1}),
            options={"seed": 3},
        )
    body = parts["body"]
    for name in (b'name="image"', b'name="mask"', b'name="depth"', b'name="request"', b"\x93NUMPY"):
        assert name in body
    request_json = json.loads(body.split(b'name="request"')[1].split(b"\r\n\r\n", 1)[1].split(b"\r\n--")[0])
    assert request_json["iterations"] == 7 and request_json["camera"]["width"] == 32
    assert request_json["ground_truth"]["joints"] == {"a": 0.1} and request_json["options"] == {"seed": 3}
    assert est.pose.matrix.shape == (4, 4) and est.trace[1] == (None, 0.2) and est.metrics == {"add": 0.004}
    assert est.status == "converged" and est.iterations == 3


def test_estimate_passes_encoded_image_bytes_through() -> None:
    sent = {}

    def handler(request: httpx.Request) -> httpx.Response:
        sent["body"] = request.content
        return httpx.Response(200, json=estimate_body())

    jpeg = io.BytesIO()
    Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(jpeg, format="JPEG")
    with client_for(handler) as narf:
        narf.estimate(jpeg.getvalue(), np.ones((24, 32), bool), K, np.eye(4), model="toy")
        with pytest.raises(ValueError, match="mask must be"):
            narf.estimate(jpeg.getvalue(), np.ones((32, 24), bool), K, np.eye(4), model="toy")
    assert jpeg.getvalue() in sent["body"] and b'filename="image.jpeg"' in sent["body"]
    assert b'"width": 32, "height": 24' in sent["body"]


def test_estimate_checks_shapes_before_sending() -> None:
    with client_for(lambda r: httpx.Response(500)) as narf:
        with pytest.raises(ValueError, match="mask must be"):
            narf.estimate(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5)), K, np.eye(4), model="toy")
        with pytest.raises(ValueError, match="uint8"):
            narf.estimate(np.zeros((4, 4, 3), np.float32), np.zeros((4, 4)), K, np.eye(4), model="toy")
        with pytest.raises(ValueError, match="K must be 3x3"):
            narf.render("toy", np.eye(4), np.eye(2), 4, 4)


# --- errors and retries ---------------------------------------------------------------------------


def test_server_errors_become_typed_exceptions_with_the_message() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("nope"):
            return httpx.Response(404, json={"error": {"code": "not_found", "message": "model: unknown", "field": "model"}})
        if request.url.path == "/v1/render":
            return httpx.Response(422, json={"error": {"code": "invalid_input", "message": "joints.a: outside", "field": "joints.a"}})
        return httpx.Response(500, text="boom")

    with client_for(handler) as narf:
        with pytest.raises(NotFound) as info:
            narf.model("nope")
        assert info.value.status_code == 404 and info.value.field == "model" and "unknown" in str(info.value)
        with pytest.raises(InvalidInput) as info:
            narf.render("toy", np.eye(4), K, 4, 4)
        assert info.value.field == "joints.a" and info.value.code == "invalid_input"
        with pytest.raises(ServerError, match="boom"):
            narf.models()


def test_model_names_are_quoted_into_the_path() -> None:
    paths = []

    def handler(request: httpx.Request) -> httpx.Response:
        paths.append(request.url.raw_path)
        return httpx.Response(404, json={"error": {"code": "not_found", "message": "no"}})

    with client_for(handler) as narf, pytest.raises(NotFound):
        narf.model("../etc")
    assert paths == [b"/v1/models/..%2Fetc"]


def test_503_is_retried_with_backoff_honouring_retry_after(monkeypatch) -> None:
    calls = []
    delays: list[float] = []
    monkeypatch.setattr("narf_client.client.time.sleep", delays.append)

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(1)
        if len(calls) == 1:
            return httpx.Response(503, headers={"retry-after": "2"}, json={"error": {"code": "busy", "message": "full"}})
        if len(calls) == 2:
            return httpx.Response(503, json={"error": {"code": "busy", "message": "full"}})
        return httpx.Response(200, json={"models": []})

    with client_for(handler, backoff=0.25) as narf:
        assert narf.models() == []
    assert delays == [2.0, 0.5]  # the server's hint, then backoff * 2 ** attempt


def test_503_gives_up_after_the_retries_with_bounded_waits(monkeypatch) -> None:
    delays: list[float] = []
    monkeypatch.setattr("narf_client.client.time.sleep", delays.append)

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(503, headers={"retry-after": "3600"}, json={"error": {"code": "busy", "message": "full"}})

    with client_for(handler, retries=2, max_backoff=5.0) as narf, pytest.raises(ServiceUnavailable) as info:
        narf.models()
    assert delays == [5.0, 5.0] and info.value.retry_after == 3600 and info.value.status_code == 503


def test_other_errors_are_not_retried(monkeypatch) -> None:
    calls = []
    monkeypatch.setattr("narf_client.client.time.sleep", lambda s: pytest.fail("slept"))

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(1)
        return httpx.Response(422, json={"error": {"code": "invalid_input", "message": "x: bad", "field": "x"}})

    with client_for(handler) as narf, pytest.raises(InvalidInput):
        narf.models()
    assert len(calls) == 1


def test_unreachable_server() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused", request=request)

    with client_for(handler) as narf:
        assert narf.health() is False and narf.ready() is False
        with pytest.raises(NarfConnectionError) as info:
            narf.models()
    assert info.value.status_code is None


def test_bearer_token_is_sent() -> None:
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.headers.get("authorization"))
        return httpx.Response(200, json={"models": []})

    with client_for(handler, token="s3cret") as narf:
        narf.models()
    assert seen == ["Bearer s3cret"]


def test_async_client_twin(monkeypatch) -> None:
    delays: list[float] = []
    sleep = asyncio.sleep

    async def record(seconds: float) -> None:
        delays.append(seconds)
        await sleep(0)

    monkeypatch.setattr("narf_client.client.asyncio.sleep", record)

    async def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/models" and not delays:
            return httpx.Response(503, headers={"retry-after": "0"}, json={"error": {"code": "busy", "message": "full"}})
        if request.url.path == "/v1/models":
            return httpx.Response(200, json={"models": [{"name": "toy", "links": ["a"], "joints": [], "modes": ["narf"]}]})
        return httpx.Response(200, json=estimate_body())

    async def main() -> tuple:
        async with AsyncNarfClient("http://narf.test", transport=httpx.MockTransport(handler)) as narf:
            models = await narf.models()
            est = await narf.estimate(np.zeros((4, 4, 3), np.uint8), np.ones((4, 4)), K, np.eye(4), model="toy")
        return models, est

    models, est = asyncio.run(main())
    assert [m.name for m in models] == ["toy"] and est.loss == 0.01 and delays == [0.0]


def test_client_never_imports_torch() -> None:
    code = "import sys, narf_client; assert 'torch' not in sys.modules, 'torch imported'; print('ok')"
    env = {**os.environ, "PYTHONPATH": str(ROOT / "clients" / "python")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
    declared = re.search(r'^version = "(.+)"$', (ROOT / "clients" / "python" / "pyproject.toml").read_text(), re.M)
    assert narf_client.__version__ == declared.group(1)  # the package says the version it is published under
