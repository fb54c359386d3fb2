"""``POST /v1/track``: tracking that keeps the replicas stateless.

The tracker's state (pose, θ, velocities, Σ, frame times, status, colour gain) travels with the client as an
opaque token: ``v1.<payload>.<signature>``, where the payload is compact JSON (base64url) naming
the model and a fingerprint of its bundle, and the signature is HMAC-SHA256 over the version and
payload with the server's state key (``NARF_STATE_KEY`` / ``--state-key-file``; every replica
behind one address needs the same key). Any replica can answer any frame; a token that was
altered, signed with another key, made for another model (or another bundle of the same name) or
written in another format version is refused with a 422 naming ``request.state``.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import json
import logging
import math
import secrets
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, FastAPI, File, Form, Request, UploadFile
from pydantic import Json

from narf_service import jobs
from narf_service.bodies import GuardedBodyRoute
from narf_service.errors import ApiError, invalid
from narf_service.images import decode_depth, decode_mask, decode_rgb
from narf_service.processes import ModelProcesses, WorkerLost
from narf_service.registry import ModelRegistry
from narf_service.routing import check_pixels, error_responses, registry_of, require_token, run_job
from narf_service.schemas import PoseOut, TrackRequest, TrackResponse, UncertaintyOut
from narf_service.settings import Settings

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel
    from narf_core.track import TrackState

log = logging.getLogger("narf_service.tracking")

TOKEN_VERSION = "v1"
STATE_FIELD = "request.state"

router = APIRouter(prefix="/v1", dependencies=[Depends(require_token)], responses=error_responses(401),
                   route_class=GuardedBodyRoute)


def install(app: FastAPI, settings: Settings) -> None:
    """Add the route to ``app`` with the state key from ``settings`` (or a random one, logged)."""
    if settings.state_key is not None:
        app.state.track_key = settings.state_key.get_secret_value().encode()
    else:
        app.state.track_key = secrets.token_bytes(32)
        log.warning("no NARF_STATE_KEY set: /v1/track state tokens are signed with a random key and only work "
                    "with this replica (and until it restarts)")
    app.include_router(router)


# --------------------------------------------------------------------------------------------
# the state token


def fingerprint(model: NarfModel) -> str:
    """A short hash of the bundle's metadata: tokens of another bundle under the same name are refused."""
    text = json.dumps(model.metadata, sort_keys=True, default=str) + model.name
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def _sign(key: bytes, body: str) -> str:
    return _b64(hmac.new(key, body.encode(), hashlib.sha256).digest())


def encode_state(key: bytes, name: str, model: NarfModel, state: TrackState) -> str:
    """The signed token of ``state`` for model ``name``."""
    payload = {
        "m": name, "f": fingerprint(model), "t": state.time, "a": state.anchor_time,
        "T": np.asarray(state.T_cam_obj)[:3].ravel().tolist(), "j": state.joints, "v": np.asarray(state.velocity).tolist(),
        "jv": state.joint_velocity, "s": state.status, "l": state.lost_frames,
        "c": None if state.covariance is None else np.asarray(state.covariance).tolist(),
        "g": np.asarray(state.colour_gain).tolist(), "n": state.colour_frames,
    }
    body = f"{TOKEN_VERSION}.{_b64(json.dumps(payload, separators=(',', ':'), allow_nan=False).encode())}"
    return f"{body}.{_sign(key, body)}"


def decode_state(key: bytes, token: str, name: str, model: NarfModel) -> TrackState:
    """The state a token holds, or a 422 naming ``request.state`` saying what is wrong with it."""
    from narf_core.track import TrackInputError, TrackState

    parts = token.split(".")
    if len(parts) != 3 or not parts[0]:
        raise invalid(STATE_FIELD, "not a state token (expected 'v1.<payload>.<signature>' from a /v1/track answer)")
    version, payload, signature = parts
    if version != TOKEN_VERSION:
        raise invalid(STATE_FIELD, f"state token of format {version[:16]!r}; this server reads {TOKEN_VERSION!r}: "
                                   "start the track again with initial_pose")
    if not hmac.compare_digest(_sign(key, f"{version}.{payload}"), signature):
        raise invalid(STATE_FIELD, "state token signature does not match: altered, or signed by a server with "
                                   "another state key")
    try:
        data = json.loads(_unb64(payload))
        if data["m"] != name:
            raise invalid(STATE_FIELD, f"state token is for model {data['m']!r}, not {name!r}")
        if data["f"] != fingerprint(model):
            raise invalid(STATE_FIELD, f"state token is for another bundle of model {name!r} (it was replaced)")
        T = np.eye(4)
        T[:3] = np.asarray(data["T"], dtype=np.float64).reshape(3, 4)
        state = TrackState(
            T, {k: float(v) for k, v in data["j"].items()}, float(data["t"]), float(data["a"]),
            np.asarray(data["v"], dtype=np.float64), {k: float(v) for k, v in data["jv"].items()},
            None if data["c"] is None else np.asarray(data["c"], dtype=np.float64), str(data["s"]), int(data["l"]),
            np.asarray(data.get("g", [1.0, 1.0, 1.0]), dtype=np.float64), int(data.get("n", 0)),
        )
        state.check(model)
    except TrackInputError as e:
        raise invalid(STATE_FIELD, f"state token holds an unusable state: {e}") from None
    except (binascii.Error, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError):
        raise invalid(STATE_FIELD, "state token payload is malformed") from None
    return state


# --------------------------------------------------------------------------------------------
# the route


@router.post(
    "/track",
    response_model=TrackResponse,
    responses=error_responses(400, 404, 413, 422, 503),
    summary="Track an object over frames: one frame per request, the state in a signed token",
    description="Multipart: `image` (PNG/JPEG), optional `mask` (PNG; missing or empty = status 'lost'), optional "
    "`depth` (16-bit PNG millimetres or .npy float32 metres) and the `request` form field holding a TrackRequest "
    "as JSON: `initial_pose` for the first frame, then the previous answer's `state`. Frame times must increase.",
)
async def track(
    request: Request,
    params: Annotated[Json[TrackRequest], Form(alias="request", description="JSON: a TrackRequest")],
    image: Annotated[UploadFile, File(description="RGB image, PNG or JPEG, the camera's size")],
    registry: Annotated[ModelRegistry, Depends(registry_of)],
    mask: Annotated[UploadFile | None, File(description="Object mask, single-channel PNG, non-zero = object")] = None,
    depth: Annotated[UploadFile | None, File(description="16-bit PNG (mm, 0 = none) or .npy (float32 m)")] = None,
) -> Any:
    from narf_core.track import TrackInputError, TrackOptions, TrackState

    settings: Settings = request.app.state.settings
    model = registry.get(params.model, field="request.model")
    check_pixels(params.camera, settings, "request.camera")
    key: bytes = request.app.state.track_key
    if params.state is not None:
        state = decode_state(key, params.state, params.model, model)
        if not params.time > state.time:
            raise invalid("request.time", f"{params.time} s is not after the previous frame's {state.time} s: "
                                          "frames must come in time order")
    else:
        jobs.check_joints(model, params.initial_joints, "request.initial_joints")
        state = TrackState.initial(model, params.initial_pose.as_matrix(), params.initial_joints, params.time)
    o = params.options
    if o.iterations is not None and o.iterations > settings.max_iterations:
        raise invalid("request.options.iterations", f"{o.iterations} exceeds this server's limit of {settings.max_iterations}")
    overrides = {k: v for k, v in {"iterations": o.iterations, "rays_per_iteration": o.rays_per_iteration,
                                   "solver": o.solver, "mode": o.mode}.items() if v is not None}
    if o.uncertainty is False:
        overrides["uncertainty_rays"] = 0
    try:
        options = TrackOptions(**overrides)
    except TrackInputError as e:  # the core's rule, named as the request's field
        raise invalid("request." + (e.field or "options"), e.reason) from None
    jobs.check_mode(model, options.mode, "request.options.mode")
    uploads = {"image": await image.read(), "mask": await mask.read() if mask is not None else None,
               "depth": await depth.read() if depth is not None else None}
    processes: ModelProcesses | None = request.app.state.processes
    if processes is None:
        return await run_job(request, lambda stop: _track_frame(key, params, model, state, options, uploads,
                                                              settings.max_image_pixels))

    def in_child(stop: object) -> TrackResponse:
        try:
            return processes.call(_track_in_child, key, params, state, options, uploads, settings.max_image_pixels)
        except WorkerLost as e:  # the server's fault, not the request's: the client may send the frame again
            raise ApiError(503, str(e), headers={"Retry-After": "1"}) from None

    return await run_job(request, in_child)


def _track_in_child(models: dict[str, NarfModel], key: bytes, params: TrackRequest, state: TrackState, options: Any,
                    uploads: dict[str, bytes | None], max_pixels: int) -> TrackResponse:
    """:func:`_track_frame` in a :class:`~narf_service.processes.ModelProcesses` child, on its copy of the model."""
    return _track_frame(key, params, models[params.model], state, options, uploads, max_pixels)


def _track_frame(key: bytes, params: TrackRequest, model: NarfModel, state: TrackState, options: Any,
                 uploads: dict[str, bytes | None], max_pixels: int) -> TrackResponse:
    """Decode the frame, track it from ``state`` and answer with the next state's token."""
    from narf_core.estimate import EstimateInputError
    from narf_core.track import TrackFrame, step

    size = (params.camera.height, params.camera.width)
    image = decode_rgb(uploads["image"] or b"", "image", max_pixels)
    mask = decode_mask(uploads["mask"], "mask", max_pixels) if uploads.get("mask") else None
    depth = decode_depth(uploads["depth"], "depth", max_pixels) if uploads.get("depth") else None
    for field, array in (("image", image), ("mask", mask), ("depth", depth)):
        if array is not None and array.shape[:2] != size:
            h, w = array.shape[:2]
            raise invalid(field, f"size {w}x{h} does not match the camera's {size[1]}x{size[0]}")
    frame = TrackFrame(image, mask, float(params.time), depth)
    try:
        result, nxt = step(model, jobs.pinhole(params.camera, model.aabb.device), frame, state, options)
    except EstimateInputError as e:  # (TrackInputError is one) input the refiner cannot use, named in the message
        raise invalid("request", str(e)) from None
    T = np.asarray(result.T_cam_obj, dtype=np.float64)
    if not np.isfinite(T).all() or not all(math.isfinite(v) for v in result.joints.values()):
        raise RuntimeError(f"the tracker returned a non-finite estimate for model {params.model!r}")
    uncertainty = None
    if result.uncertainty is not None:
        uncertainty = UncertaintyOut(**{k: result.uncertainty[k] for k in UncertaintyOut.model_fields})
    return TrackResponse(
        model=params.model, time=result.time, status=result.status, reason=result.reason, pose=PoseOut.from_matrix(T),
        joints={k: float(v) for k, v in result.joints.items()}, uncertainty=uncertainty,
        overlap=None if result.overlap is None or not math.isfinite(result.overlap) else float(result.overlap),
        iterations=result.iterations, seconds=result.seconds, mode=result.mode, mode_reason=result.mode_reason,
        warnings=list(result.warnings), state=encode_state(key, params.model, model, nxt),
    )
