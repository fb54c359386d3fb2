"""The HTTP API v1 through FastAPI's TestClient: every route, and bad input answered 4xx naming the problem."""

from __future__ import annotations

import base64
import io
import json
import threading

import numpy as np
import pytest
import torch
from PIL import Image

from helpers import ON_BOTH_MODELS, GatedEngine, ToyModel, camera_json, make_client, pose_json, scene_for, wait_until
from narf_core.estimate import EstimateOptions
from narf_service.engine import Engine
from narf_service.settings import Settings


def png(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def decode_png(data: str | bytes) -> np.ndarray:
    raw = base64.b64decode(data) if isinstance(data, str) else data
    return np.asarray(Image.open(io.BytesIO(raw)))


def render_body(**overrides) -> dict:
    return {"model": "toy", "pose": pose_json(), "camera": camera_json(), **overrides}


def post_json(client, path: str, body: dict, **kwargs):
    """POST ``body`` as JSON, NaN and infinities written out (as a careless client would)."""
    return client.post(path, content=json.dumps(body), headers={"content-type": "application/json"}, **kwargs)


def assert_error(response, status: int, field: str | None = None, *words: str) -> dict:
    """The error body of ``response``: its status, the field it names (``None``: none) and words of its message."""
    assert response.status_code == status, response.text
    error = response.json()["error"]
    assert set(error) <= {"code", "message", "field"} and error["code"] and error["message"]
    assert error.get("field") == field, error
    if field is not None:
        assert error["message"].startswith(field), error
    for word in words:
        assert word in error["message"], error
    return error


@pytest.fixture
def observation(client, service_model) -> dict:
    """A rendered view of the model (image, mask, depth) and the request that made it."""
    body = render_body(outputs=["rgb", "opacity", "depth"])
    r = client.post("/v1/render", json=body)
    assert r.status_code == 200
    rgb, opacity, depth = (decode_png(r.json()[k]) for k in ("rgb", "opacity", "depth"))
    return {"rgb": rgb, "mask": opacity > 127, "depth_mm": depth, "body": body, "joints": r.json()["joints"]}


def estimate_parts(observation: dict, body: dict | None = None, **parts) -> dict:
    """The multipart files of an estimate of ``observation``; ``parts`` replace the defaults."""
    return {
        "image": ("image.png", png(observation["rgb"]), "image/png"),
        "mask": ("mask.png", png(observation["mask"].astype(np.uint8) * 255), "image/png"),
        "request": (None, json.dumps(body or estimate_request()), "application/json"),
        **parts,
    }


def estimate_request(**overrides) -> dict:
    return {"model": "toy", "camera": camera_json(), "initial_pose": pose_json(0.41), "iterations": 5, **overrides}


# --- operations -----------------------------------------------------------------------------------


@ON_BOTH_MODELS
def test_healthz_and_readyz(client, service_model) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json() == {"status": "ready", "models": [service_model.name], "failed": {}}


def test_readyz_is_503_without_models(service_settings, service_engine) -> None:
    from fastapi.testclient import TestClient

    from narf_service.app import create_app

    with TestClient(create_app(service_settings, engine=service_engine)) as c:  # empty models folder
        r = c.get("/readyz")
    assert r.status_code == 503 and r.json()["status"] == "not_ready" and r.json()["models"] == []


def test_metrics_count_requests_per_route_and_status(client) -> None:
    client.get("/v1/models")
    client.get("/v1/models/nope")
    text = client.get("/metrics").text
    assert 'narf_http_requests_total{method="GET",route="/v1/models",status="200"} 1.0' in text
    assert 'narf_http_requests_total{method="GET",route="/v1/models/{name}",status="404"} 1.0' in text
    assert "narf_queue_depth 0.0" in text and "narf_queue_capacity 6.0" in text
    assert "narf_http_request_duration_seconds_bucket" in text and "narf_process_peak_rss_bytes" in text


def test_openapi_documents_the_error_body_and_both_pose_forms(client) -> None:
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    assert {"matrix", "position", "orientation"} <= set(schemas["Pose"]["properties"])
    assert spec["paths"]["/v1/render"]["post"]["responses"]["422"]["content"]["application/json"]["schema"] == {
        "$ref": "#/components/schemas/ErrorResponse"
    }
    assert "EstimateRequest" in schemas and "HTTPValidationError" not in schemas


# --- models ---------------------------------------------------------------------------------------


@ON_BOTH_MODELS
def test_models_list_and_detail(client, service_model) -> None:
    listed = client.get("/v1/models").json()["models"]
    assert [m["name"] for m in listed] == [service_model.name]
    assert [j["name"] for j in listed[0]["joints"]] == [j.name for j in service_model.joints]
    assert listed[0]["modes"] == (["narf", "parts"] if service_model.has_parts else ["narf"])
    info = client.get(f"/v1/models/{service_model.name}").json()
    assert info["links"] == list(service_model.links)
    assert np.allclose(info["bounds"], service_model.aabb.tolist())
    assert "urdf" not in info["metadata"]
    if isinstance(service_model, ToyModel):
        assert info["metrics"] == {"psnr_test": None}  # an infinite PSNR: JSON has no infinity
        assert info["metadata"]["arch"] == "box"
    else:  # the bundle's own metadata, passed through
        assert info["metadata"]["checksum"] == service_model.metadata["checksum"]
        assert info["metrics"] == (service_model.metadata.get("metrics") or {})
    got = [(j["name"], j["type"], j["lower"], j["upper"]) for j in info["joints"]]
    assert got == [(j.name, j.type, j.lower, j.upper) for j in service_model.joints]


@pytest.mark.parametrize(
    ("path", "status", "field"),
    [("/v1/models/nope", 404, "name"), ("/v1/models/a..b", 422, "name"), ("/v1/models/..%2Fetc", 404, None)],
)
def test_model_names_resolve_only_to_served_models(client, path: str, status: int, field: str | None) -> None:
    """A name with a slash matches no route at all; one with ``..`` is refused by the name pattern."""
    assert_error(client.get(path), status, field)


# --- render ---------------------------------------------------------------------------------------


def scene_render(client, scene, **overrides) -> dict:
    """The JSON answer to a render of ``scene`` (all three outputs, the scene's joints)."""
    body = {"model": scene.model, "pose": scene.pose_json(), "camera": scene.camera_json(), "joints": scene.joints,
            "outputs": ["rgb", "depth", "opacity"], **overrides}
    r = client.post("/v1/render", json=body)
    assert r.status_code == 200, r.text
    return r.json()


@ON_BOTH_MODELS
def test_render_json_images_are_pngs_of_the_models_own_render(client, service_model) -> None:
    """rgb and opacity in 8 bits, depth in millimetres (16 bits) of the model's render at the asked
    pose and joints; the object whole in the image, its depth within its box's depth range."""
    scene = scene_for(service_model)
    body = scene_render(client, scene)
    rgb, depth, opacity = (decode_png(body[k]) for k in ("rgb", "depth", "opacity"))
    assert rgb.shape == (scene.height, scene.width, 3) and rgb.dtype == np.uint8
    assert depth.shape == opacity.shape == (scene.height, scene.width)
    assert depth.dtype == np.uint16 and opacity.dtype == np.uint8
    own = service_model.render(torch.tensor(scene.T_cam_obj, dtype=torch.float32), service_model.joint_vector(scene.joints),
                               scene.pinhole(), outputs=("rgb", "depth", "opacity"))
    np.testing.assert_allclose(rgb, own["rgb"].numpy() * 255, atol=1)
    np.testing.assert_allclose(opacity, own["opacity"].numpy() * 255, atol=1)
    np.testing.assert_allclose(depth, own["depth"].numpy() * 1000, atol=1)
    inside = opacity > 127
    assert inside.sum() > 0.05 * inside.size and not inside[[0, -1]].any() and not inside[:, [0, -1]].any()
    near, far = scene.depth_range()
    solid = opacity == 255  # (rendered depth is opacity-weighted)
    assert solid.any() and (depth[solid] >= 1000 * near - 1).all() and (depth[solid] <= 1000 * far + 1).all()
    assert (depth[opacity == 0] <= 1).all() and (rgb[inside].max(-1) > 0).all()
    assert np.allclose(body["pose"]["matrix"], scene.T_cam_obj) and body["joints"] == pytest.approx(scene.joints)


def test_render_answers_the_pose_in_both_forms(client) -> None:
    body = client.post("/v1/render", json=render_body()).json()
    assert body["pose"]["position"] == [0, 0, 0.4] and body["pose"]["orientation"] == [0, 0, 0, 1]


def test_render_depth_is_millimetres(client) -> None:
    """The toy box's near face is 0.4 - 0.02 m from the camera: 380 mm at the centre pixel."""
    r = client.post("/v1/render", json=render_body(outputs=["depth"]))
    depth = decode_png(r.json()["depth"])
    assert depth[12, 16] == 380 and r.json()["rgb"] is None


def test_render_pose_as_position_and_quaternion_equals_matrix(client) -> None:
    a = client.post("/v1/render", json=render_body())
    pose = {"position": [0, 0, 0.4], "orientation": [0, 0, 0, 1.0005]}  # normalised: within 1e-3 of unit
    b = client.post("/v1/render", json=render_body(pose=pose))
    assert b.status_code == 200 and a.json()["rgb"] == b.json()["rgb"]


def test_render_accept_png_returns_one_image(client) -> None:
    r = client.post("/v1/render", json=render_body(outputs=["depth"]), headers={"accept": "image/png"})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert decode_png(r.content).dtype == np.uint16
    r = client.post("/v1/render", json=render_body(outputs=["rgb", "depth"]), headers={"accept": "image/png"})
    assert_error(r, 422, "outputs", "exactly one")


@ON_BOTH_MODELS
def test_render_joints_move_the_image(client, service_model) -> None:
    scene = scene_for(service_model, 64, 48)
    j = service_model.joints[0]
    a = scene_render(client, scene, joints={j.name: j.lower})
    b = scene_render(client, scene, joints={j.name: j.upper})
    assert a["joints"][j.name] == pytest.approx(j.lower) and b["joints"][j.name] == pytest.approx(j.upper)
    changed = np.abs(decode_png(a["rgb"]).astype(int) - decode_png(b["rgb"]).astype(int)).max(-1) > 8
    assert changed.sum() >= 10  # pixels, not rounding noise


BAD_POSES = [
    ({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, float("nan")], [0, 0, 0, 1]]}, "pose.matrix[2][3]", "finite"),
    ({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, float("inf")], [0, 0, 0, 1]]}, "pose.matrix[2][3]", "finite"),
    ({"matrix": [[1, 0.01, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.4], [0, 0, 0, 1]]}, "pose.matrix", "orthonormal"),
    ({"matrix": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.4], [0, 0, 0, 1]]}, "pose.matrix", "reflection"),
    ({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.4], [0, 0, 1, 1]]}, "pose.matrix", "last row"),
    ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "pose.matrix[0]", "4 items"),
    ({"position": [0, 0, 0.4], "orientation": [0, 0, 0, 0.5]}, "pose.orientation", "norm"),
    ({"position": [0, 0, 0.4], "orientation": [0, 0, 0, 0]}, "pose.orientation", "norm"),
    ({"position": [0, 0, float("nan")], "orientation": [0, 0, 0, 1]}, "pose.position[2]", "finite"),
    ({"position": [0, 0, 0.4]}, "pose", "go together"),
    ({}, "pose", "either"),
    ({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.4], [0, 0, 0, 1]], "position": [0, 0, 0]}, "pose", "either"),
    ({"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1e9], [0, 0, 0, 1]]}, "pose.matrix[2][3]", ""),
]


@pytest.mark.parametrize(("pose", "field", "word"), BAD_POSES)
def test_render_refuses_bad_poses(client, pose: dict, field: str, word: str) -> None:
    assert_error(post_json(client, "/v1/render", render_body(pose=pose)), 422, field, word)


BAD_CAMERAS = [
    ({"K": [[0, 0, 16], [0, 30, 12], [0, 0, 1]]}, "camera.K", "focal"),
    ({"K": [[-30, 0, 16], [0, 30, 12], [0, 0, 1]]}, "camera.K", "focal"),
    ({"K": [[30, 0, 16], [0, 30, 12], [0, 1, 1]]}, "camera.K", "form"),
    ({"K": [[30, 0, 16], [0, 30, 12]]}, "camera.K", ""),
    ({"K": [[30, 0, float("nan")], [0, 30, 12], [0, 0, 1]]}, "camera.K[0][2]", "finite"),
    ({"width": 0}, "camera.width", ""),
    ({"height": -3}, "camera.height", ""),
    ({"width": 10**6}, "camera.width", ""),
    ({"width": 2.5}, "camera.width", ""),
]


@pytest.mark.parametrize(("change", "field", "word"), BAD_CAMERAS)
def test_render_refuses_bad_cameras(client, change: dict, field: str, word: str) -> None:
    assert_error(post_json(client, "/v1/render", render_body(camera={**camera_json(), **change})), 422, field, word)


def test_render_refuses_too_many_pixels(client) -> None:
    r = client.post("/v1/render", json=render_body(camera=camera_json(4096, 4096)))
    assert_error(r, 413, "camera", "pixels")


def test_render_refuses_joints_outside_limits_and_unknown_joints(client, service_model) -> None:
    j = service_model.joints[0]
    r = post_json(client, "/v1/render", render_body(joints={j.name: j.upper + 1e-3}))
    assert_error(r, 422, f"joints.{j.name}", "limits")
    r = post_json(client, "/v1/render", render_body(joints={j.name: j.lower - 1e-3}))
    assert_error(r, 422, f"joints.{j.name}", "limits")
    r = post_json(client, "/v1/render", render_body(joints={j.name: float("nan")}))
    assert_error(r, 422, f"joints.{j.name}", "finite")
    r = post_json(client, "/v1/render", render_body(joints={"no_such_joint": 0.0}))
    assert_error(r, 422, "joints.no_such_joint", "unknown joint", j.name)


def test_render_joints_at_their_limits_are_accepted(client, service_model) -> None:
    lows = {j.name: j.lower for j in service_model.joints}
    highs = {j.name: j.upper for j in service_model.joints}
    assert client.post("/v1/render", json=render_body(joints=lows)).status_code == 200
    assert client.post("/v1/render", json=render_body(joints=highs)).status_code == 200


@pytest.mark.parametrize(
    ("model", "status"), [("nope", 404), ("../toy", 422), ("/etc/passwd", 422), ("toy/../toy", 422), ("", 422)]
)
def test_render_model_names(client, model: str, status: int) -> None:
    assert_error(client.post("/v1/render", json=render_body(model=model)), status, "model")


def test_render_other_bad_fields(client, service_model) -> None:
    assert_error(client.post("/v1/render", json=render_body(outputs=["normals"])), 422, "outputs[0]")
    assert_error(client.post("/v1/render", json=render_body(outputs=[])), 422, "outputs")
    assert_error(client.post("/v1/render", json=render_body(outputs=["rgb", "rgb"])), 422, "outputs", "once")
    assert_error(client.post("/v1/render", json=render_body(mode="magic")), 422, "mode")
    assert_error(client.post("/v1/render", json=render_body(colour="red")), 422, "colour", "Extra")
    assert_error(client.post("/v1/render", json={"model": "toy"}), 422, "pose", "required")
    if not service_model.has_parts:
        assert_error(client.post("/v1/render", json=render_body(mode="parts")), 422, "mode", "part")


def test_malformed_json_is_400(client) -> None:
    r = client.post("/v1/render", content=b'{"model": "toy", ', headers={"content-type": "application/json"})
    assert_error(r, 400, "body", "malformed JSON")
    assert r.json()["error"]["code"] == "malformed_json"


def test_oversized_body_is_413_by_header_and_by_stream(client) -> None:
    big = b"{" + b" " * (2**20 + 10) + b"}"
    assert_error(client.post("/v1/render", content=big, headers={"content-type": "application/json"}), 413)

    def chunks():  # no Content-Length: chunked transfer, counted as it streams
        for _ in range(20):
            yield b" " * 2**16

    r = client.post("/v1/render", content=chunks(), headers={"content-type": "application/json"})
    assert_error(r, 413, None, "exceeds")


def test_bearer_token(service_settings, service_engine, service_model) -> None:
    settings = Settings(**{**service_settings.model_dump(), "token": "s3cret"})
    with make_client(settings, service_engine, service_model) as c:
        assert_error(c.get("/v1/models"), 401, None, "token")
        assert c.get("/v1/models", headers={"authorization": "Bearer wrong"}).status_code == 401
        assert c.get("/v1/models", headers={"authorization": "Bearer s3cret"}).status_code == 200
        assert c.get("/v1/models").headers["www-authenticate"] == "Bearer"
        assert c.get("/healthz").status_code == 200 and c.get("/readyz").status_code == 200


def test_unknown_route_and_method_use_the_error_body(client) -> None:
    assert_error(client.get("/v2/render"), 404)
    assert_error(client.get("/v1/render"), 405)


# --- estimate -------------------------------------------------------------------------------------


def add_of(model, T: np.ndarray, joints: dict, T_true: np.ndarray, joints_true: dict) -> float:
    """ADD (metres) of ``T``, ``joints`` against the truth, from the model's surface points."""
    from narf_core.metrics import add

    links = model.kinematics.link_poses
    return add(model.sample_points, links(model.joint_vector(joints_true)).numpy(), T_true,
               links(model.joint_vector(joints)).numpy(), T, model.links)


@ON_BOTH_MODELS
def test_estimate_of_a_rendered_view_is_scored_against_the_truth(client, service_model) -> None:
    """Render the scene, then estimate it from 1 cm off in x and z, the joints at mid-range, with depth.

    The toy refiner stays at its start, so its ADD is the start's 1.41 cm exactly. The real one must
    at least halve the start's ADD (measured: to 0.29 cm from 2.19 cm), its reported ADD must be the
    ADD of the pose and joints it answers, and it comes with a finite covariance.
    """
    toy = isinstance(service_model, ToyModel)
    scene = scene_for(service_model)
    view = scene_render(client, scene)
    rgb, depth_mm, opacity = (decode_png(view[k]) for k in ("rgb", "depth", "opacity"))
    start = scene.moved((0.01, 0.0, 0.01))
    iterations = 5 if toy else 30
    request = {"model": scene.model, "camera": scene.camera_json(), "initial_pose": scene.pose_json(start),
               "iterations": iterations,
               "ground_truth": {"pose": scene.pose_json(), "joints": scene.joints}}
    files = {
        "image": ("image.png", png(rgb), "image/png"),
        "mask": ("mask.png", png((opacity > 127).astype(np.uint8) * 255), "image/png"),
        "depth": ("depth.png", png(depth_mm), "image/png"),
        "request": (None, json.dumps(request), "application/json"),
    }
    r = client.post("/v1/estimate", files=files)
    assert r.status_code == 200, r.text
    body = r.json()
    T = np.asarray(body["pose"]["matrix"])
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9) and np.allclose(body["pose"]["position"], T[:3, 3])
    assert len(body["pose"]["orientation"]) == 4 and np.linalg.norm(body["pose"]["orientation"]) == pytest.approx(1)
    assert set(body["joints"]) == set(scene.joints)
    assert all(j.lower <= body["joints"][j.name] <= j.upper for j in service_model.joints)
    assert 1 <= body["iterations"] <= iterations and len(body["trace"]) == body["iterations"]  # every one finite
    assert not body["recovered_non_finite"] and all(loss is not None for loss, _ in body["trace"])
    assert body["status"] in ("converged", "max_iterations")
    assert body["wall_seconds"] >= body["seconds"] > 0
    assert body["preset"] == "gauss-newton"  # auto, with a depth image
    metrics = body["metrics"]
    assert set(metrics) >= {"add"} | {f"joint_error/{j}" for j in scene.joints}
    if toy:
        assert metrics["add"] == pytest.approx(np.hypot(0.01, 0.01)) and body["uncertainty"] is None
        return
    mid = {j.name: (j.lower + j.upper) / 2 for j in service_model.joints}
    assert metrics["add"] == pytest.approx(add_of(service_model, T, body["joints"], scene.T_cam_obj, scene.joints), rel=1e-4)
    assert metrics["add"] < add_of(service_model, start, mid, scene.T_cam_obj, scene.joints) / 2
    uncertainty = body["uncertainty"]
    covariance = np.asarray(uncertainty["covariance"])
    k = len(service_model.joints)
    assert covariance.shape == (6 + k, 6 + k) and np.isfinite(covariance).all()
    assert np.allclose(covariance, covariance.T) and (np.linalg.eigvalsh(covariance) > 0).all()
    sigmas = uncertainty["position_sigma_m"] + uncertainty["rotation_sigma_rad"] + list(uncertainty["joint_sigma"].values())
    assert set(uncertainty["joint_sigma"]) == set(scene.joints) and all(0 < s < 1 for s in sigmas)


def test_estimate_without_ground_truth_has_no_metrics(client, observation) -> None:
    r = client.post("/v1/estimate", files=estimate_parts(observation))
    assert r.status_code == 200 and r.json()["metrics"] is None


def test_the_preset_auto_is_resolved_per_view_and_named_in_the_response(service_settings, toy_engine, toy_model,
                                                                        observation) -> None:
    """``options.preset`` left out is ``auto``: Gauss-Newton's options reach the refiner for a view with a
    depth image, the robust preset's for one without; the response names the preset and why."""
    seen = []

    def refine(model, image, mask, camera, T_init, **kwargs):
        seen.append(kwargs["options"])
        return toy_engine.refine(model, image, mask, camera, T_init, **kwargs)

    engine = Engine(toy_engine.load_bundle, refine, toy_engine.options, toy_engine.input_error)
    depth = ("d.png", png(observation["depth_mm"]), "image/png")
    with make_client(service_settings, engine, toy_model) as c:
        with_depth = c.post("/v1/estimate", files=estimate_parts(observation, depth=depth)).json()
        without = c.post("/v1/estimate", files=estimate_parts(observation)).json()
        paper = c.post("/v1/estimate", files=estimate_parts(
            observation, estimate_request(options={"preset": "paper"}), depth=depth)).json()
        differences = c.post("/v1/estimate", files=estimate_parts(
            observation, estimate_request(options={"jacobian": "differences"}), depth=depth)).json()
    assert (with_depth["preset"], without["preset"], paper["preset"]) == ("gauss-newton", "robust", "paper")
    assert differences["preset"] == "gauss-newton" and seen[3].jacobian == "differences" != seen[0].jacobian
    assert "depth" in with_depth["preset_reason"] and "no depth" in without["preset_reason"]
    assert paper["preset_reason"] == "requested"
    assert [o.solver for o in seen] == ["gauss-newton", "adam", "adam", "gauss-newton"]
    assert seen[0].depth_weight == EstimateOptions.preset("gauss-newton").depth_weight and seen[1].rgb_polish == EstimateOptions.preset("robust").rgb_polish > 0
    assert seen[2] == EstimateOptions.preset("paper", iterations=5)


def test_estimate_with_zero_iterations_scores_the_initial_pose(client, observation) -> None:
    r = client.post("/v1/estimate", files=estimate_parts(observation, estimate_request(iterations=0)))
    assert r.status_code == 200 and r.json()["iterations"] == 0
    assert np.allclose(r.json()["pose"]["matrix"], pose_json(0.41)["matrix"])


def test_estimate_accepts_jpeg_image_and_depth_as_png_or_npy(service_settings, toy_engine, toy_model, observation) -> None:
    """The refiner gets the JPEG's pixels and the depth in metres, from millimetres (PNG) or metres (.npy)."""
    seen = []

    def refine(model, image, mask, camera, T_init, **kwargs):
        seen.append((image, kwargs["depth"]))
        return toy_engine.refine(model, image, mask, camera, T_init, **kwargs)

    engine = Engine(toy_engine.load_bundle, refine, toy_engine.options, toy_engine.input_error)
    jpeg = io.BytesIO()
    Image.fromarray(observation["rgb"]).save(jpeg, format="JPEG", quality=95)
    npy = io.BytesIO()
    np.save(npy, observation["depth_mm"].astype(np.float32) / 1000)
    with make_client(service_settings, engine, toy_model) as c:
        for depth in (("d.png", png(observation["depth_mm"]), "image/png"), ("d.npy", npy.getvalue(), "application/octet-stream")):
            files = estimate_parts(observation, image=("i.jpg", jpeg.getvalue(), "image/jpeg"), depth=depth)
            assert c.post("/v1/estimate", files=files).status_code == 200
    assert len(seen) == 2
    for image, depth in seen:
        assert image.shape == observation["rgb"].shape and np.abs(image.astype(int) - observation["rgb"]).mean() < 3
        assert depth.dtype == np.float32 and np.allclose(depth, observation["depth_mm"] / 1000, atol=1e-6)


def test_estimate_missing_parts(client, observation) -> None:
    for part in ("image", "mask", "request"):
        files = {k: v for k, v in estimate_parts(observation).items() if k != part}
        assert_error(client.post("/v1/estimate", files=files), 422, part, "required")


def test_estimate_bad_images(client, observation) -> None:
    h, w = observation["mask"].shape
    cases = [
        ({"image": ("i.png", b"not an image at all", "image/png")}, 422, "image", "readable"),
        ({"image": ("i.gif", b"GIF89a....", "image/gif")}, 422, "image", "readable"),
        ({"image": ("i.png", png(observation["rgb"][:, :, 0]), "image/png")}, 422, "image", "RGB"),
        ({"image": ("i.png", png(observation["rgb"][: h - 1]), "image/png")}, 422, "image", "does not match"),
        ({"image": ("i.png", png(observation["rgb"])[:60], "image/png")}, 422, "image", ""),
        ({"mask": ("m.png", png(np.zeros((h, w + 1), np.uint8)), "image/png")}, 422, "mask", "does not match"),
        ({"mask": ("m.png", png(np.zeros((h, w), np.uint8)), "image/png")}, 422, "mask", "empty"),
        ({"mask": ("m.png", png(observation["rgb"]), "image/png")}, 422, "mask", "single-channel"),
        ({"depth": ("d.png", png(observation["rgb"]), "image/png")}, 422, "depth", "16-bit"),
        ({"depth": ("d.bin", b"\x00\x01\x02", "application/octet-stream")}, 422, "depth", ".npy"),
        ({"image": ("i.png", b"", "image/png")}, 422, "image", "empty"),
    ]
    for files, status, field, word in cases:
        assert_error(client.post("/v1/estimate", files=estimate_parts(observation, **files)), status, field, word)


def test_estimate_decompression_bomb_is_413(client, observation) -> None:
    bomb = png(np.zeros((3000, 3000), np.uint8))  # 9 Mpx of zeros compress to a few kB
    r = client.post("/v1/estimate", files=estimate_parts(observation, mask=("m.png", bomb, "image/png")))
    assert_error(r, 413, "mask", "pixels")


def test_estimate_bad_request_part(client, observation, service_model) -> None:
    j = service_model.joints[0]
    cases = [
        ("{not json", 400, "request", "malformed"),
        (json.dumps(estimate_request(model="../etc/passwd")), 422, "request.model", ""),
        (json.dumps(estimate_request(model="nope")), 404, "request.model", "unknown model"),
        (json.dumps(estimate_request(iterations=-1)), 422, "request.iterations", ""),
        (json.dumps(estimate_request(iterations=5000)), 422, "request.iterations", "limit"),
        (json.dumps(estimate_request(initial_joints={"nope": 0})), 422, "request.initial_joints.nope", "unknown"),
        (json.dumps(estimate_request(initial_joints={j.name: j.upper + 1})), 422, f"request.initial_joints.{j.name}", ""),
        (json.dumps(estimate_request(options={"rays_per_iteration": 0})), 422, "request.options.rays_per_iteration", ""),
        (json.dumps(estimate_request(options={"learning_rate": 1})), 422, "request.options.learning_rate", "Extra"),
        (json.dumps(estimate_request(options={"preset": "fast"})), 422, "request.options.preset", "paper"),
        (json.dumps(estimate_request(options={"slide_share": 0.5})), 422, "request.options.slide_share", "[0, 0.25]"),
        (json.dumps(estimate_request(options={"jacobian": "secant"})), 422, "request.options.jacobian", "differences"),
        (json.dumps(estimate_request(ground_truth={"pose": pose_json()})), 422, "request.ground_truth.joints", "missing"),
        (json.dumps(estimate_request(camera=camera_json(4096, 4096))), 413, "request.camera", "pixels"),
        (json.dumps(estimate_request(initial_pose={"matrix": [[1, 0, 0, 0]] * 4})), 422, "request.initial_pose.matrix", ""),
    ]
    for text, status, field, word in cases:
        r = client.post("/v1/estimate", files=estimate_parts(observation, request=(None, text, "application/json")))
        assert_error(r, status, field, word)
    nan_pose = json.dumps(estimate_request(initial_pose={"position": [0, 0, float("nan")], "orientation": [0, 0, 0, 1]}))
    r = client.post("/v1/estimate", files=estimate_parts(observation, request=(None, nan_pose, "application/json")))
    assert_error(r, 422, "request.initial_pose.position[2]", "finite")


def test_estimate_refiner_input_errors_are_422(client, observation) -> None:
    one_pixel = np.zeros_like(observation["mask"])
    one_pixel[5, 5] = True
    files = estimate_parts(observation, mask=("m.png", png(one_pixel.astype(np.uint8) * 255), "image/png"))
    assert_error(client.post("/v1/estimate", files=files), 422, "mask", "1 object pixel")


def test_estimate_sent_as_json_is_422_naming_the_parts(client) -> None:
    r = client.post("/v1/estimate", json=estimate_request())
    assert_error(r, 422, "request", "required")


# --- the work queue -------------------------------------------------------------------------------


def test_full_queue_answers_503_with_retry_after(service_settings, service_engine, service_model, observation) -> None:
    gated = GatedEngine(service_engine)
    settings = Settings(**{**service_settings.model_dump(), "workers": 1, "queue_size": 1})
    with make_client(settings, gated.engine(), service_model) as c:
        answers: list[int] = []

        def post() -> None:
            answers.append(c.post("/v1/estimate", files=estimate_parts(observation)).status_code)

        threads = [threading.Thread(target=post) for _ in range(2)]  # one runs, one waits
        for t in threads:
            t.start()
        wait_until(lambda: c.app.state.queue.waiting == 1 and gated.calls == 1)
        assert "narf_queue_depth 1.0" in c.get("/metrics").text
        r = c.post("/v1/estimate", files=estimate_parts(observation))
        assert_error(r, 503, None, "queue is full")
        assert int(r.headers["retry-after"]) >= 1
        r = c.post("/v1/render", json=render_body())  # renders share the queue
        assert r.status_code == 503
        gated.gate.set()
        for t in threads:
            t.join(timeout=10)
        assert answers == [200, 200]
        assert c.post("/v1/render", json=render_body()).status_code == 200
        assert "narf_queue_rejected_total 2.0" in c.get("/metrics").text
