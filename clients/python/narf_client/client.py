"""``NarfClient`` and its async twin ``AsyncNarfClient``: numpy in, numpy out, over HTTP (API v1).

Both share the request builders and response parsers below and differ only in how they wait.
A 503 (the server's queue is full) is retried with exponential backoff, honouring the server's
``Retry-After`` but never waiting longer than ``max_backoff`` per try nor trying more than
``retries`` more times. ``/v1/estimate`` gets its own, long read timeout.
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import time
from collections.abc import AsyncIterable, AsyncIterator, Iterable, Iterator, Mapping, Sequence
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np
from PIL import Image

from narf_client.errors import NarfConnectionError, NarfError, error_for_status
from narf_client.types import (
    Estimate,
    JointInfo,
    ModelInfo,
    Pose,
    RenderResult,
    TrackFrame,
    TrackUpdate,
    Uncertainty,
)

DEFAULT_URL = "http://127.0.0.1:8000"
PoseLike = Pose | np.ndarray | Sequence[Sequence[float]]
GroundTruth = tuple[PoseLike, Mapping[str, float]]


# --- requests -------------------------------------------------------------------------------------


def camera_json(K: np.ndarray | Sequence[Sequence[float]], width: int, height: int) -> dict[str, Any]:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got shape {K.shape}")
    return {"K": K.tolist(), "width": int(width), "height": int(height)}


def _joints_json(joints: Mapping[str, float] | None) -> dict[str, float] | None:
    return None if joints is None else {str(k): float(v) for k, v in joints.items()}


def render_payload(
    model: str,
    pose: PoseLike,
    K: np.ndarray,
    width: int,
    height: int,
    joints: Mapping[str, float] | None,
    outputs: Sequence[str],
    mode: str,
) -> dict[str, Any]:
    body: dict[str, Any] = {
        "model": model,
        "pose": Pose.coerce(pose).to_json(),
        "camera": camera_json(K, width, height),
        "outputs": list(outputs),
        "mode": mode,
    }
    if joints is not None:
        body["joints"] = _joints_json(joints)
    return body


def encode_png(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def _image_part(image: np.ndarray | bytes) -> tuple[tuple[str, bytes, str], tuple[int, int]]:
    """The ``image`` file part and the image's ``(width, height)``; encoded bytes pass unchanged."""
    if isinstance(image, bytes):
        with Image.open(io.BytesIO(image)) as probe:
            kind = {"PNG": "image/png", "JPEG": "image/jpeg"}.get(probe.format or "")
            if kind is None:
                raise ValueError(f"image bytes must be PNG or JPEG, got {probe.format}")
            return (f"image.{kind.split('/')[1]}", image, kind), probe.size
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be uint8 [H, W, 3], got {image.dtype} {list(image.shape)}")
    return ("image.png", encode_png(image), "image/png"), (image.shape[1], image.shape[0])


def estimate_files(
    image: np.ndarray | bytes,
    mask: np.ndarray,
    K: np.ndarray,
    initial_pose: PoseLike,
    *,
    model: str,
    initial_joints: Mapping[str, float] | None,
    depth: np.ndarray | None,
    iterations: int | None,
    options: Mapping[str, Any] | None,
    ground_truth: GroundTruth | None,
) -> dict[str, tuple[str | None, bytes | str, str]]:
    """The multipart parts of ``POST /v1/estimate``; depth goes as ``.npy`` float32 metres (lossless)."""
    image_part, (width, height) = _image_part(image)
    mask = np.asarray(mask)
    if mask.shape != (height, width):
        raise ValueError(f"mask must be [H, W] = [{height}, {width}] like the image, got {list(mask.shape)}")
    request: dict[str, Any] = {
        "model": model,
        "camera": camera_json(K, width, height),
        "initial_pose": Pose.coerce(initial_pose).to_json(),
        "options": dict(options or {}),
    }
    if initial_joints is not None:
        request["initial_joints"] = _joints_json(initial_joints)
    if iterations is not None:
        request["iterations"] = int(iterations)
    if ground_truth is not None:
        gt_pose, gt_joints = ground_truth
        request["ground_truth"] = {"pose": Pose.coerce(gt_pose).to_json(), "joints": _joints_json(gt_joints)}
    files: dict[str, tuple[str | None, bytes | str, str]] = {
        "image": image_part,
        "mask": ("mask.png", encode_png((mask != 0).astype(np.uint8) * 255), "image/png"),
        "request": (None, json.dumps(request), "application/json"),
    }
    if depth is not None:
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != (height, width):
            raise ValueError(f"depth must be [H, W] = [{height}, {width}] like the image, got {list(depth.shape)}")
        buffer = io.BytesIO()
        np.save(buffer, depth, allow_pickle=False)
        files["depth"] = ("depth.npy", buffer.getvalue(), "application/octet-stream")
    return files


def track_files(
    frame: TrackFrame | tuple,
    K: np.ndarray,
    *,
    model: str,
    state: str | None,
    initial_pose: PoseLike | None,
    initial_joints: Mapping[str, float] | None,
    options: Mapping[str, Any] | None,
) -> dict[str, tuple[str | None, bytes | str, str]]:
    """The multipart parts of ``POST /v1/track`` for one frame (a :class:`TrackFrame` or a tuple
    ``(time, image, mask[, depth])``)."""
    if not isinstance(frame, TrackFrame):
        frame = TrackFrame(*frame)
    image_part, (width, height) = _image_part(frame.image)
    request: dict[str, Any] = {"model": model, "camera": camera_json(K, width, height), "time": float(frame.time),
                               "options": dict(options or {})}
    if state is not None:
        request["state"] = state
    else:
        if initial_pose is None:
            raise ValueError("the first frame needs initial_pose (later ones send the previous answer's state)")
        request["initial_pose"] = Pose.coerce(initial_pose).to_json()
        if initial_joints is not None:
            request["initial_joints"] = _joints_json(initial_joints)
    files: dict[str, tuple[str | None, bytes | str, str]] = {
        "image": image_part, "request": (None, json.dumps(request), "application/json"),
    }
    if frame.mask is not None:
        mask = np.asarray(frame.mask)
        if mask.shape != (height, width):
            raise ValueError(f"mask must be [H, W] = [{height}, {width}] like the image, got {list(mask.shape)}")
        files["mask"] = ("mask.png", encode_png((mask != 0).astype(np.uint8) * 255), "image/png")
    if frame.depth is not None:
        depth = np.asarray(frame.depth, dtype=np.float32)
        if depth.shape != (height, width):
            raise ValueError(f"depth must be [H, W] = [{height}, {width}] like the image, got {list(depth.shape)}")
        buffer = io.BytesIO()
        np.save(buffer, depth, allow_pickle=False)
        files["depth"] = ("depth.npy", buffer.getvalue(), "application/octet-stream")
    return files


def parse_track(body: dict[str, Any]) -> TrackUpdate:
    return TrackUpdate(
        time=float(body["time"]), status=body["status"], reason=body.get("reason"),
        pose=Pose(np.asarray(body["pose"]["matrix"], dtype=np.float64)), joints=dict(body["joints"]),
        uncertainty=Uncertainty.from_json(body.get("uncertainty")), overlap=body.get("overlap"),
        iterations=int(body["iterations"]), seconds=float(body["seconds"]), state=body["state"],
        mode=body.get("mode"), mode_reason=body.get("mode_reason"), warnings=tuple(body.get("warnings", ())),
    )


# --- responses ------------------------------------------------------------------------------------


def _decode_png(data: str | None) -> np.ndarray | None:
    if data is None:
        return None
    with Image.open(io.BytesIO(base64.b64decode(data))) as image:
        return np.asarray(image)


def parse_render(body: dict[str, Any]) -> RenderResult:
    rgb, depth, opacity = (_decode_png(body.get(k)) for k in ("rgb", "depth", "opacity"))
    return RenderResult(
        rgb=rgb,
        depth=None if depth is None else depth.astype(np.float32) / 1000,
        opacity=None if opacity is None else opacity.astype(np.float32) / 255,
        joints=dict(body.get("joints", {})),
        seconds=float(body.get("seconds", 0.0)),
        mode=body.get("mode"),
        mode_reason=body.get("mode_reason"),
    )


def parse_estimate(body: dict[str, Any]) -> Estimate:
    return Estimate(
        pose=Pose(np.asarray(body["pose"]["matrix"], dtype=np.float64)),
        joints=dict(body["joints"]),
        loss=body["loss"],
        iterations=int(body["iterations"]),
        seconds=float(body["seconds"]),
        wall_seconds=float(body["wall_seconds"]),
        status=body["status"],
        trace=[(loss, t) for loss, t in body["trace"]],
        metrics=body.get("metrics"),
        recovered_non_finite=bool(body.get("recovered_non_finite", False)),
        warnings=tuple(body.get("warnings", ())),
        uncertainty=Uncertainty.from_json(body.get("uncertainty")),
        mode=body.get("mode"),
        mode_reason=body.get("mode_reason"),
        preset=body.get("preset"),
        preset_reason=body.get("preset_reason"),
    )


def parse_model(body: dict[str, Any]) -> ModelInfo:
    bounds = body.get("bounds")
    return ModelInfo(
        name=body["name"],
        links=list(body["links"]),
        joints=[JointInfo(**j) for j in body["joints"]],
        modes=list(body.get("modes", ["narf"])),
        bounds=None if bounds is None else np.asarray(bounds, dtype=np.float64),
        metrics=dict(body.get("metrics") or {}),
        metadata=dict(body.get("metadata") or {}),
        auto_mode=body.get("auto_mode"),
        auto_mode_reason=body.get("auto_mode_reason"),
    )


def _retry_after(response: httpx.Response) -> float | None:
    value = response.headers.get("retry-after")
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None  # an HTTP date: fall back to the backoff schedule


def error_from(response: httpx.Response) -> NarfError:
    """The exception for an error response, with the server's message, code and field."""
    try:
        error = response.json()["error"]
        message, code, field = str(error["message"]), error.get("code"), error.get("field")
    except (ValueError, KeyError, TypeError):
        message, code, field = response.text[:300] or response.reason_phrase, None, None
    cls = error_for_status(response.status_code)
    return cls(message, status_code=response.status_code, code=code, field=field, retry_after=_retry_after(response))


class _Base:
    def __init__(
        self,
        base_url: str,
        token: str | None,
        timeout: float,
        estimate_timeout: float,
        retries: int,
        backoff: float,
        max_backoff: float,
    ) -> None:
        if retries < 0 or backoff < 0 or max_backoff < 0:
            raise ValueError("retries, backoff and max_backoff must be >= 0")
        self.base_url = base_url.rstrip("/")
        self.retries = retries
        self.backoff = backoff
        self.max_backoff = max_backoff
        self._headers = {"authorization": f"Bearer {token}"} if token else {}
        self._timeout = httpx.Timeout(timeout, connect=min(timeout, 10.0))
        self._estimate_timeout = httpx.Timeout(timeout, read=estimate_timeout, connect=min(timeout, 10.0))

    def _delay(self, response: httpx.Response, attempt: int) -> float | None:
        """Seconds to wait before retrying ``response``, or ``None`` to give up and raise."""
        if response.status_code != 503 or attempt >= self.retries:
            return None
        hint = _retry_after(response)
        return min(self.max_backoff, hint if hint is not None else self.backoff * 2**attempt)


class NarfClient(_Base):
    """A blocking client. Use as a context manager, or call :meth:`close`.

    ``timeout`` bounds each request (seconds); ``estimate_timeout`` is the read timeout of
    ``/v1/estimate``, which may queue behind other work. A 503 is retried ``retries`` times.
    """

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        token: str | None = None,
        *,
        timeout: float = 30.0,
        estimate_timeout: float = 600.0,
        retries: int = 3,
        backoff: float = 0.5,
        max_backoff: float = 10.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        super().__init__(base_url, token, timeout, estimate_timeout, retries, backoff, max_backoff)
        self._http = httpx.Client(base_url=self.base_url, headers=self._headers, timeout=self._timeout, transport=transport)

    def __enter__(self) -> NarfClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        attempt = 0
        while True:
            try:
                response = self._http.request(method, path, **kwargs)
            except httpx.TransportError as e:
                raise NarfConnectionError(f"{method} {self.base_url}{path}: {e!r}") from e
            if response.is_success:
                return response
            delay = self._delay(response, attempt)
            if delay is None:
                raise error_from(response)
            time.sleep(delay)
            attempt += 1

    def render(
        self,
        model: str,
        pose: PoseLike,
        K: np.ndarray,
        width: int,
        height: int,
        *,
        joints: Mapping[str, float] | None = None,
        outputs: Sequence[str] = ("rgb",),
        mode: str = "auto",
    ) -> RenderResult:
        """Render ``model`` at ``pose`` (``T_cam_obj``) and ``joints`` (missing: mid-range)."""
        body = render_payload(model, pose, K, width, height, joints, outputs, mode)
        return parse_render(self._request("POST", "/v1/render", json=body).json())

    def estimate(
        self,
        image: np.ndarray | bytes,
        mask: np.ndarray,
        K: np.ndarray,
        initial_pose: PoseLike,
        *,
        model: str,
        initial_joints: Mapping[str, float] | None = None,
        depth: np.ndarray | None = None,
        iterations: int | None = None,
        options: Mapping[str, Any] | None = None,
        ground_truth: GroundTruth | None = None,
    ) -> Estimate:
        """Refine ``initial_pose`` and ``initial_joints`` against ``image`` (uint8 ``[H, W, 3]``, or PNG/JPEG
        bytes) inside ``mask`` (``[H, W]``, non-zero = object), optionally with ``depth`` (float32 metres)."""
        files = estimate_files(
            image,
            mask,
            K,
            initial_pose,
            model=model,
            initial_joints=initial_joints,
            depth=depth,
            iterations=iterations,
            options=options,
            ground_truth=ground_truth,
        )
        return parse_estimate(self._request("POST", "/v1/estimate", files=files, timeout=self._estimate_timeout).json())

    def track_step(
        self,
        frame: TrackFrame | tuple,
        K: np.ndarray,
        *,
        model: str,
        state: str | None = None,
        initial_pose: PoseLike | None = None,
        initial_joints: Mapping[str, float] | None = None,
        options: Mapping[str, Any] | None = None,
    ) -> TrackUpdate:
        """Track one frame: from ``state`` (the previous update's token) or, first, from ``initial_pose``."""
        files = track_files(frame, K, model=model, state=state, initial_pose=initial_pose,
                            initial_joints=initial_joints, options=options)
        return parse_track(self._request("POST", "/v1/track", files=files, timeout=self._estimate_timeout).json())

    def track(
        self,
        frames: Iterable[TrackFrame | tuple],
        K: np.ndarray,
        initial_pose: PoseLike,
        *,
        model: str,
        initial_joints: Mapping[str, float] | None = None,
        options: Mapping[str, Any] | None = None,
    ) -> Iterator[TrackUpdate]:
        """Track ``frames`` (in time order) from ``initial_pose`` at the first; yields one update per frame,
        carrying the state token from each answer to the next request."""
        state = None
        for frame in frames:
            update = self.track_step(frame, K, model=model, state=state, initial_pose=initial_pose,
                                     initial_joints=initial_joints, options=options)
            state = update.state
            yield update

    def models(self) -> list[ModelInfo]:
        return [parse_model(m) for m in self._request("GET", "/v1/models").json()["models"]]

    def model(self, name: str) -> ModelInfo:
        return parse_model(self._request("GET", f"/v1/models/{quote(name, safe='')}").json())

    def health(self) -> bool:
        """Whether the server answers (``/healthz``); never raises."""
        return self._probe("/healthz")

    def ready(self) -> bool:
        """Whether the server has models loaded (``/readyz``); never raises."""
        return self._probe("/readyz")

    def _probe(self, path: str) -> bool:
        try:
            return self._http.get(path).status_code == 200
        except httpx.TransportError:
            return False


class AsyncNarfClient(_Base):
    """The asyncio twin of :class:`NarfClient` (same arguments, same methods, awaited)."""

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        token: str | None = None,
        *,
        timeout: float = 30.0,
        estimate_timeout: float = 600.0,
        retries: int = 3,
        backoff: float = 0.5,
        max_backoff: float = 10.0,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        super().__init__(base_url, token, timeout, estimate_timeout, retries, backoff, max_backoff)
        self._http = httpx.AsyncClient(
            base_url=self.base_url, headers=self._headers, timeout=self._timeout, transport=transport
        )

    async def __aenter__(self) -> AsyncNarfClient:
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        attempt = 0
        while True:
            try:
                response = await self._http.request(method, path, **kwargs)
            except httpx.TransportError as e:
                raise NarfConnectionError(f"{method} {self.base_url}{path}: {e!r}") from e
            if response.is_success:
                return response
            delay = self._delay(response, attempt)
            if delay is None:
                raise error_from(response)
            await asyncio.sleep(delay)
            attempt += 1

    async def render(
        self,
        model: str,
        pose: PoseLike,
        K: np.ndarray,
        width: int,
        height: int,
        *,
        joints: Mapping[str, float] | None = None,
        outputs: Sequence[str] = ("rgb",),
        mode: str = "auto",
    ) -> RenderResult:
        body = render_payload(model, pose, K, width, height, joints, outputs, mode)
        return parse_render((await self._request("POST", "/v1/render", json=body)).json())

    async def estimate(
        self,
        image: np.ndarray | bytes,
        mask: np.ndarray,
        K: np.ndarray,
        initial_pose: PoseLike,
        *,
        model: str,
        initial_joints: Mapping[str, float] | None = None,
        depth: np.ndarray | None = None,
        iterations: int | None = None,
        options: Mapping[str, Any] | None = None,
        ground_truth: GroundTruth | None = None,
    ) -> Estimate:
        files = estimate_files(
            image,
            mask,
            K,
            initial_pose,
            model=model,
            initial_joints=initial_joints,
            depth=depth,
            iterations=iterations,
            options=options,
            ground_truth=ground_truth,
        )
        response = await self._request("POST", "/v1/estimate", files=files, timeout=self._estimate_timeout)
        return parse_estimate(response.json())

    async def track_step(
        self,
        frame: TrackFrame | tuple,
        K: np.ndarray,
        *,
        model: str,
        state: str | None = None,
        initial_pose: PoseLike | None = None,
        initial_joints: Mapping[str, float] | None = None,
        options: Mapping[str, Any] | None = None,
    ) -> TrackUpdate:
        files = track_files(frame, K, model=model, state=state, initial_pose=initial_pose,
                            initial_joints=initial_joints, options=options)
        response = await self._request("POST", "/v1/track", files=files, timeout=self._estimate_timeout)
        return parse_track(response.json())

    async def track(
        self,
        frames: Iterable[TrackFrame | tuple] | AsyncIterable[TrackFrame | tuple],
        K: np.ndarray,
        initial_pose: PoseLike,
        *,
        model: str,
        initial_joints: Mapping[str, float] | None = None,
        options: Mapping[str, Any] | None = None,
    ) -> AsyncIterator[TrackUpdate]:
        """Like :meth:`NarfClient.track`, an async generator; ``frames`` may be a sync or an async iterable."""
        state = None

        async def each() -> AsyncIterator[TrackFrame | tuple]:
            if isinstance(frames, AsyncIterable):
                async for frame in frames:
                    yield frame
            else:
                for frame in frames:
                    yield frame

        async for frame in each():
            update = await self.track_step(frame, K, model=model, state=state, initial_pose=initial_pose,
                                           initial_joints=initial_joints, options=options)
            state = update.state
            yield update

    async def models(self) -> list[ModelInfo]:
        return [parse_model(m) for m in (await self._request("GET", "/v1/models")).json()["models"]]

    async def model(self, name: str) -> ModelInfo:
        return parse_model((await self._request("GET", f"/v1/models/{quote(name, safe='')}")).json())

    async def health(self) -> bool:
        return await self._probe("/healthz")

    async def ready(self) -> bool:
        return await self._probe("/readyz")

    async def _probe(self, path: str) -> bool:
        try:
            return (await self._http.get(path)).status_code == 200
        except httpx.TransportError:
            return False
