"""POST /v1/track: the signed state token, and round trips through narf_client against a real server
on loopback serving the bundled clamp."""

from __future__ import annotations

import asyncio
import copy
from collections.abc import Iterator

import numpy as np
import pytest

from helpers import ROOT
from narf_client import AsyncNarfClient, InvalidInput, NarfClient, TrackFrame
from narf_service.app import create_app
from narf_service.errors import ApiError
from narf_service.main import serve_in_thread
from narf_service.registry import ModelRegistry
from narf_service.settings import Settings
from narf_service.tracking import decode_state, encode_state

KEY = b"k" * 32
FAST = {"iterations": 2, "rays_per_iteration": 64, "uncertainty": False}


@pytest.fixture(scope="module")
def clamp(bundled_model):
    return bundled_model


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> tuple[list[TrackFrame], np.ndarray, list]:
    """Four frames of a smooth clamp sequence at 160x120, as the client sends them, with K and the labels."""
    pytest.importorskip("pybullet")
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.sequence import synthesize_sequence

    root = synthesize_sequence("clamp", tmp_path_factory.mktemp("seq") / "c", 4, events=False, supersample=1)
    dataset = Dataset.open(root)
    out = []
    for f in dataset.frames():
        images = dataset.load(f)
        out.append(TrackFrame(f.time, images.rgb, images.labels > 0, images.depth))
    return out, dataset.camera.K.double().numpy(), dataset.frames()


@pytest.fixture(scope="module")
def server(clamp, tmp_path_factory) -> Iterator[str]:
    settings = Settings(models_dir=tmp_path_factory.mktemp("models"), workers=2, queue_size=8, torch_threads=1,
                        state_key="s" * 24)
    registry = ModelRegistry(models={"clamp": clamp, "clamp-copy": clamp})
    with serve_in_thread(create_app(settings, registry=registry)) as url:
        yield url


# --------------------------------------------------------------------------------------------
# the token, without a server


def _state(clamp):
    from narf_core.track import TrackState

    T = np.eye(4)
    T[2, 3] = 0.5
    state = TrackState.initial(clamp, T, {"jaw_opening": 0.1}, 1.0, status="tracking")
    state.velocity = np.array([0.01, 0.0, -0.02, 0.1, 0.0, 0.0])
    state.covariance = np.eye(7) * 1e-6
    state.colour_gain, state.colour_frames = np.array([0.8, 1.0, 1.25]), 5
    return state


def test_token_round_trip(clamp) -> None:
    state = _state(clamp)
    back = decode_state(KEY, encode_state(KEY, "clamp", clamp, state), "clamp", clamp)
    np.testing.assert_allclose(back.T_cam_obj, state.T_cam_obj)
    np.testing.assert_allclose(back.velocity, state.velocity)
    np.testing.assert_allclose(back.covariance, state.covariance)
    np.testing.assert_allclose(back.colour_gain, state.colour_gain)
    assert back.joints == state.joints and back.time == state.time and back.status == "tracking"
    assert back.colour_frames == 5


def _refused(token: str, clamp, name: str = "clamp", model=None, key: bytes = KEY) -> str:
    with pytest.raises(ApiError) as info:
        decode_state(key, token, name, model if model is not None else clamp)
    assert info.value.status_code == 422 and info.value.field == "request.state"
    return info.value.message


def test_tampered_foreign_and_old_tokens_are_refused(clamp) -> None:
    import base64
    import json

    token = encode_state(KEY, "clamp", clamp, _state(clamp))
    version, payload, signature = token.split(".")
    data = json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))
    data["T"][3] += 0.1  # move the object 10 cm, keep the signature
    forged = base64.urlsafe_b64encode(json.dumps(data).encode()).rstrip(b"=").decode()
    assert "signature" in _refused(f"{version}.{forged}.{signature}", clamp)
    assert "signature" in _refused(token, clamp, key=b"another key, another replica")
    assert "format 'v0'" in _refused(f"v0.{payload}.{signature}", clamp)
    assert "not a state token" in _refused("garbage", clamp)
    assert "for model 'clamp'" in _refused(token, clamp, name="pliers")
    other = copy.copy(clamp)
    other.metadata = {**clamp.metadata, "retrained": True}
    assert "another bundle" in _refused(token, clamp, model=other)


def _signed(payload: dict) -> str:
    import base64
    import hashlib
    import hmac
    import json

    body = "v1." + base64.urlsafe_b64encode(json.dumps(payload).encode()).rstrip(b"=").decode()
    signature = base64.urlsafe_b64encode(hmac.new(KEY, body.encode(), hashlib.sha256).digest()).rstrip(b"=").decode()
    return f"{body}.{signature}"


def test_a_signed_token_with_a_nan_or_a_wild_gain_is_still_refused(clamp) -> None:
    """Defence in depth: even a correctly signed payload must hold a usable state. A v1 payload written before
    the colour gain was carried reads with none (ones)."""
    from narf_service.tracking import fingerprint

    payload = {"m": "clamp", "f": fingerprint(clamp), "t": 1.0, "a": 1.0, "T": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0.5],
               "j": {"jaw_opening": 0.1}, "v": [0, 0, 0, 0, 0, 0], "jv": {}, "s": "tracking", "l": 0, "c": None}
    older = decode_state(KEY, _signed(payload), "clamp", clamp)
    assert older.colour_gain.tolist() == [1.0, 1.0, 1.0] and older.colour_frames == 0
    assert "unusable state" in _refused(_signed({**payload, "v": [0, 0, 0, 0, 0, float("nan")]}), clamp)
    assert "colour_gain" in _refused(_signed({**payload, "g": [0.1, 1.0, 1.0], "n": 3}), clamp)


# --------------------------------------------------------------------------------------------
# over HTTP


@pytest.mark.slow
def test_track_round_trip_sync(server: str, frames) -> None:
    sent, K, labels = frames
    with NarfClient(server) as narf:
        updates = list(narf.track(sent[:3], K, labels[0].T_cam_obj, model="clamp", initial_joints=labels[0].joints,
                                  options=FAST))
    assert [u.status for u in updates][0] == "reinitialised"
    assert all(u.status in ("tracking", "uncertain") for u in updates[1:])
    for update, label in zip(updates, labels):
        assert np.linalg.norm(update.pose.position - label.T_cam_obj[:3, 3]) < 0.02
        assert update.state.startswith("v1.") and update.uncertainty is None
    assert len({u.state for u in updates}) == 3


@pytest.mark.slow
def test_track_round_trip_async_and_any_replica(server: str, frames, clamp) -> None:
    """The async generator; then the same token answered by a second server with the same key."""
    sent, K, labels = frames

    async def go():
        async with AsyncNarfClient(server) as narf:
            return [u async for u in narf.track(sent[:2], K, labels[0].T_cam_obj, model="clamp", options=FAST)]

    updates = asyncio.run(go())
    assert len(updates) == 2 and updates[-1].status in ("tracking", "uncertain", "reinitialised")
    settings = Settings(models_dir=ROOT / "models", workers=1, torch_threads=1, state_key="s" * 24,
                        track_processes=False)  # the other way to run a frame: on the worker thread
    with serve_in_thread(create_app(settings, registry=ModelRegistry(models={"clamp": clamp}))) as other:
        with NarfClient(other) as narf:
            third = narf.track_step(sent[2], K, model="clamp", state=updates[-1].state, options=FAST)
    assert third.status in ("tracking", "uncertain") and third.time == pytest.approx(sent[2].time)


@pytest.mark.slow
def test_track_bad_input_over_http(server: str, frames) -> None:
    sent, K, labels = frames
    with NarfClient(server) as narf:
        first = narf.track_step(sent[0], K, model="clamp", initial_pose=labels[0].T_cam_obj, options=FAST)
        token = first.state
        with pytest.raises(InvalidInput) as info:  # the same frame time again
            narf.track_step(sent[0], K, model="clamp", state=token, options=FAST)
        assert info.value.field == "request.time"
        with pytest.raises(InvalidInput) as info:  # a token of another model
            narf.track_step(sent[1], K, model="clamp-copy", state=token, options=FAST)
        assert info.value.field == "request.state" and "for model 'clamp'" in info.value.message
        with pytest.raises(InvalidInput) as info:
            narf.track_step(sent[1], K, model="clamp", state=token[:-2] + ("AA" if token[-2:] != "AA" else "BB"))
        assert info.value.field == "request.state"
        # neither a state nor an initial pose: the client refuses before sending
        with pytest.raises(ValueError, match="initial_pose"):
            narf.track_step(sent[1], K, model="clamp")
        # a missing mask and an empty one: 'lost' with the last pose, never an error
        lost = narf.track_step(TrackFrame(sent[1].time, sent[1].image), K, model="clamp", state=token, options=FAST)
        assert lost.status == "lost" and np.allclose(lost.pose.matrix, first.pose.matrix)
        empty = TrackFrame(sent[2].time, sent[2].image, np.zeros_like(sent[2].mask))
        lost = narf.track_step(empty, K, model="clamp", state=lost.state, options=FAST)
        assert lost.status == "lost" and "not in view" in lost.reason
        with pytest.raises(InvalidInput) as info:
            narf.track_step(sent[3], K, model="clamp", state=token, options={"iterations": -1})
        assert info.value.field.startswith("request.options")
        with pytest.raises(InvalidInput) as info:  # a Jacobian the tracker does not know
            narf.track_step(sent[3], K, model="clamp", state=token, options={**FAST, "jacobian": "secant"})
        assert info.value.field == "request.options.jacobian"
        fast = narf.track_step(sent[3], K, model="clamp", state=token, options={**FAST, "jacobian": "derivatives"})
        assert fast.status in ("tracking", "uncertain")


@pytest.mark.slow
def test_track_faults_over_http(server: str, frames, clamp) -> None:
    """The faults of a real camera stream, over HTTP: each a 4xx naming the field, or an answer (a status,
    a finite pose) the tracking goes on from; never a 500. The server tracks in its child processes, so an
    error found there (a part of the wrong size) must come back as the same 422."""
    import base64
    import json

    import httpx

    from narf_client.client import encode_png, track_files
    from narf_service.tracking import _sign

    sent, K, labels = frames

    def finite(update) -> bool:
        return bool(np.isfinite(update.pose.matrix).all()) and all(np.isfinite(v) for v in update.joints.values())

    with NarfClient(server) as narf:
        first = narf.track_step(sent[0], K, model="clamp", initial_pose=labels[0].T_cam_obj, options=FAST)
        second = narf.track_step(sent[1], K, model="clamp", state=first.state, options=FAST)
        with pytest.raises(InvalidInput) as info:  # out of order: an earlier frame after a later one
            narf.track_step(sent[0], K, model="clamp", state=second.state, options=FAST)
        assert info.value.field == "request.time" and "time order" in info.value.message
        # a depth missing in the middle of an RGB-D sequence, then a depth with no valid return (all NaN)
        no_depth = narf.track_step(TrackFrame(sent[2].time, sent[2].image, sent[2].mask), K, model="clamp",
                                   state=second.state, options=FAST)
        assert no_depth.status in ("tracking", "uncertain") and finite(no_depth)
        blind = TrackFrame(sent[3].time, sent[3].image, sent[3].mask, np.full_like(sent[3].depth, np.nan))
        nan_depth = narf.track_step(blind, K, model="clamp", state=no_depth.state, options=FAST)
        assert nan_depth.status != "lost" and finite(nan_depth)
        # a depth in millimetres: said in the frame's warnings (and not used), as /v1/estimate says it
        in_mm = TrackFrame(sent[2].time, sent[2].image, sent[2].mask, sent[2].depth * 1000)
        millimetres = narf.track_step(in_mm, K, model="clamp", state=second.state, options=FAST)
        assert millimetres.status != "lost" and finite(millimetres)
        assert [w for w in millimetres.warnings if w.startswith("depth_unit: ")]
        assert second.warnings == ()
        # a gap in time (a dropped stretch of the stream): no prediction, the object is found again
        late = TrackFrame(sent[2].time + 5.0, sent[2].image, sent[2].mask, sent[2].depth)
        found = narf.track_step(late, K, model="clamp", state=second.state, options=FAST)
        assert found.status == "reinitialised" and "since the last estimate" in found.reason and finite(found)
        assert np.linalg.norm(found.pose.position - labels[2].T_cam_obj[:3, 3]) < 0.03

    version, payload, _ = second.state.split(".")
    data = json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))
    data["v"][0] = float("nan")  # a NaN in the previous state, correctly signed (as by a buggy replica)
    body = "v1." + base64.urlsafe_b64encode(json.dumps(data).encode()).rstrip(b"=").decode()
    older = f"v0.{payload}.{_sign(b's' * 24, 'v0.' + payload)}"  # a token of an older format, signed
    with NarfClient(server) as narf:
        for token, words in ((f"{body}.{_sign(b's' * 24, body)}", "unusable state"), (older, "format 'v0'")):
            with pytest.raises(InvalidInput) as info:
                narf.track_step(sent[2], K, model="clamp", state=token, options=FAST)
            assert info.value.field == "request.state" and words in info.value.message

    # parts the client would refuse to send, sent raw: the child decodes them and answers 422
    files = track_files(sent[2], K, model="clamp", state=second.state, initial_pose=None, initial_joints=None,
                        options=FAST)
    for field, part in (("mask", ("mask.png", encode_png(np.zeros((60, 80), np.uint8)), "image/png")),
                        ("image", ("image.png", b"\x89PNG\r\n\x1a\n not a png", "image/png"))):
        answer = httpx.post(f"{server}/v1/track", files={**files, field: part}, timeout=120)
        assert answer.status_code in (400, 422), answer.text
        assert answer.json()["error"]["field"] == field
    assert httpx.get(f"{server}/readyz").status_code == 200  # the server still answers


@pytest.mark.slow
def test_a_lost_tracking_process_is_a_503_and_replaced(clamp, frames, tmp_path) -> None:
    """A child process killed between two frames (out of memory, say): that frame is a 503 with Retry-After,
    the client's retry is answered by a fresh child from the same token."""
    from narf_client import ServiceUnavailable

    sent, K, labels = frames
    settings = Settings(models_dir=tmp_path, workers=1, torch_threads=1, state_key="s" * 24)
    app = create_app(settings, registry=ModelRegistry(models={"clamp": clamp}))
    with serve_in_thread(app) as url, NarfClient(url, retries=0) as narf:
        first = narf.track_step(sent[0], K, model="clamp", initial_pose=labels[0].T_cam_obj, options=FAST)
        (child,) = app.state.processes._all
        child.process.kill()
        child.process.wait()
        with pytest.raises(ServiceUnavailable) as info:
            narf.track_step(sent[1], K, model="clamp", state=first.state, options=FAST)
        assert info.value.status_code == 503 and "worker process ended" in str(info.value)
        again = narf.track_step(sent[1], K, model="clamp", state=first.state, options=FAST)
        assert again.status in ("tracking", "uncertain") and app.state.processes.started == 1
