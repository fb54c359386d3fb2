"""What the worker threads run: validated requests in, response models out.

The checks that need the model (joints against its limits, the render mode) are here as well,
and are run before a job is queued so that bad input never waits for a worker.
"""

from __future__ import annotations

import base64
import math
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from narf_core.checks import InputError, check_joints as check_joints_core
from narf_core.depth import depth_to_mm
from narf_core.estimate import EstimateOptions, choose_preset
from narf_core.geometry import Pinhole
from narf_service.engine import Engine
from narf_service.errors import ApiError, invalid
from narf_service.images import (
    decode_depth,
    decode_mask,
    decode_rgb,
    encode_png,
    opacity_to_uint8,
    rgb_to_uint8,
)
from narf_service.schemas import (
    Camera,
    EstimateRequest,
    EstimateResponse,
    JointInfo,
    ModelInfo,
    ModelSummary,
    PoseOut,
    RenderRequest,
    RenderResponse,
    UncertaintyOut,
)

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel


def check_joints(model: NarfModel, joints: Mapping[str, float] | None, field: str, *, complete: bool = False) -> None:
    """The core's joint check (:func:`narf_core.checks.check_joints`) as a 422 naming
    ``<field>.<joint>`` (an unknown joint, a value outside its limits) or ``field``.

    With ``complete``, every movable joint of the model must be given.
    """
    try:
        check_joints_core(model.joints, joints, field, complete=complete)
    except InputError as e:
        raise invalid(e.field or field, e.reason) from None


def check_mode(model: NarfModel, mode: str | None, field: str) -> tuple[str, str]:
    """``(mode, reason)`` the requested ``mode`` (``None``: ``auto``) comes to for ``model``
    (:func:`narf_core.modes.choose_mode`); its refusal (``parts`` without part fields) as a 422 naming ``field``."""
    from narf_core.modes import choose_mode

    try:
        return choose_mode(model, mode or "auto", field=field)
    except InputError as e:
        raise invalid(field, e.reason) from None


def pinhole(camera: Camera, device: torch.device) -> Pinhole:
    return Pinhole(torch.tensor(camera.K, dtype=torch.float32, device=device), camera.width, camera.height)


def describe(name: str, model: NarfModel, *, full: bool) -> ModelSummary | ModelInfo:
    """The model as served under ``name``, from :meth:`NarfModel.describe` (plus, in full, its
    metadata less the URDF text)."""
    about = model.describe()
    summary = {"name": name, "links": about["links"], "joints": [JointInfo(**j) for j in about["joints"]],
               "modes": about["modes"], "auto_mode": about["auto_mode"]["mode"],
               "auto_mode_reason": about["auto_mode"]["reason"]}
    if not full:
        return ModelSummary(**summary)
    metadata = _json_safe({k: v for k, v in model.metadata.items() if k != "urdf"})
    return ModelInfo(**summary, bounds=about["bounds"], metrics=_json_safe(about["metrics"]), metadata=metadata)


def _json_safe(value: Any) -> Any:
    """``value`` with NaN and infinities (a perfect render's PSNR, say) replaced by ``None``: JSON has neither."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def _theta(model: NarfModel, joints: Mapping[str, float] | None, field: str) -> Tensor:
    try:
        return model.joint_vector(joints)
    except ValueError as e:
        raise invalid(field, str(e)) from None


BAND_PIXELS = 1 << 18
"""A render is made in bands of rows of about this many pixels, ``should_stop`` polled between them
(a 160x120 image is one band; 2048x2048, 16 bands of a second or so each on one CPU core)."""


def _bands(camera: Pinhole) -> list[Pinhole]:
    """``camera`` cut into bands of whole rows, top to bottom. A band's camera is the image's with
    the principal point moved up to the band's first row, so its rays are the image's rays."""
    rows = max(1, BAND_PIXELS // camera.width)
    bands = []
    for top in range(0, camera.height, rows):
        K = camera.K.clone()
        K[1, 2] -= top
        bands.append(Pinhole(K, camera.width, min(rows, camera.height - top)))
    return bands


def render_images(
    model: NarfModel, request: RenderRequest, should_stop: Callable[[], str | None] | None = None
) -> tuple[dict[str, np.ndarray], Tensor, float]:
    """The asked images, encoded-ready (``rgb``/``opacity`` uint8, ``depth`` uint16 mm), θ and seconds.

    ``should_stop`` is polled between bands of rows; a status it returns ends the render with a 422
    of that code (``budget_exceeded``: the image is too large for the server's time budget).
    """
    start = time.perf_counter()
    device = model.aabb.device
    theta = _theta(model, request.joints, "joints").to(device)
    T = torch.as_tensor(request.pose.as_matrix(), dtype=torch.float32, device=device)
    parts = []
    try:
        with torch.inference_mode():
            for band in _bands(pinhole(request.camera, device)):
                if should_stop is not None and (reason := should_stop()):
                    seconds = time.perf_counter() - start
                    message = (
                        f"camera: the render stopped ({reason}) after {seconds:.1f} s, beyond this server's time "
                        "budget per request; ask for fewer pixels"
                    )
                    raise ApiError(422, message, field="camera", code=reason)
                parts.append(model.render(T, theta, band, outputs=tuple(request.outputs), mode=request.mode))
    except ValueError as e:
        raise ApiError(422, str(e)) from None
    out = {name: torch.cat([part[name] for part in parts]) for name in request.outputs}
    convert = {"rgb": rgb_to_uint8, "depth": depth_to_mm, "opacity": opacity_to_uint8}
    images = {name: convert[name](out[name].detach().float().cpu().numpy()) for name in request.outputs}
    return images, theta.cpu(), time.perf_counter() - start


def render_json(
    name: str, model: NarfModel, request: RenderRequest, should_stop: Callable[[], str | None] | None = None
) -> RenderResponse:
    images, theta, seconds = render_images(model, request, should_stop)
    encoded = {k: base64.b64encode(encode_png(v)).decode("ascii") for k, v in images.items()}
    mode, reason = check_mode(model, request.mode, "mode")
    return RenderResponse(
        model=name,
        width=request.camera.width,
        height=request.camera.height,
        mode=mode,
        mode_reason=reason,
        pose=PoseOut.from_matrix(request.pose.as_matrix()),
        joints={**model.joint_dict(theta), **(request.joints or {})},  # the values as sent, not rounded to float32
        seconds=seconds,
        **encoded,
    )


def render_png(
    model: NarfModel, request: RenderRequest, should_stop: Callable[[], str | None] | None = None
) -> tuple[bytes, float]:
    images, _, seconds = render_images(model, request, should_stop)
    (image,) = images.values()
    return encode_png(image), seconds


def _finite_or_none(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _uncertainty_out(uncertainty: Any) -> UncertaintyOut | None:
    """The refiner's :class:`~narf_core.estimate.Uncertainty` for the response; ``None`` if absent or not finite."""
    if uncertainty is None:
        return None
    out = uncertainty.to_dict()
    if not np.isfinite(np.asarray(out["covariance"], dtype=np.float64)).all():
        return None
    return UncertaintyOut(**out)


def refine_options(engine: Engine, request: EstimateRequest, field: str, depth: bool) -> tuple[Any, str, str]:
    """The refiner's options for ``request`` (its ``options`` and ``iterations``) on a view with a depth
    image (``depth``) or without, the preset they start from and why (``auto`` resolved by
    :func:`narf_core.estimate.choose_preset`); 422 naming ``field``."""
    fields = request.options.model_dump(exclude_none=True)
    if request.iterations is not None:
        fields["iterations"] = request.iterations
    try:
        preset, reason = choose_preset(fields.pop("preset", "auto"), depth)
        return engine.options(preset, **fields), preset, reason
    except engine.input_error as e:
        if not isinstance(e, InputError) or e.field is None:
            raise invalid(field, str(e)) from None
        raise invalid(field + e.field.removeprefix("options"), e.reason) from None  # "options.<name>" of the core


def check_work(options: EstimateOptions, max_rays: int, field: str, depth: bool) -> None:
    """422 naming ``field`` if the refinement would trace more than ``max_rays`` rays in all.

    The cost is the core's bound, :meth:`EstimateOptions.max_rays` (iterations x rays_per_iteration
    x the largest box scale x starts x refinements, the choices between starts and estimates and the
    covariance; with gauss-newton also its trial steps and prunings), known before any work; ``depth``:
    whether the request carries a depth image (without one, the RGB-only refinements and polish count).
    """
    rays = options.max_rays(depth=depth)
    if rays > max_rays:
        raise invalid(
            field,
            f"would trace up to {rays} rays (iterations x rays_per_iteration x box scale x starts "
            f"x refinements, with the choices, the polish without depth and the covariance), over this server's work "
            f"limit of {max_rays}",
        )


_REFINE_ARGUMENTS = {
    "image": "image",
    "mask": "mask",
    "depth": "depth",
    "camera": "request.camera",
    "T_init": "request.initial_pose",
    "joints_init": "request.initial_joints",
    "ground_truth": "request.ground_truth",
    "options": "request.options",
}


def _refine_input_error(message: str, field: str | None = None, reason: str | None = None) -> ApiError:
    """The refiner's input error as a 422 naming the request field it is about: its ``field`` and
    ``reason`` (:class:`~narf_core.checks.InputError`'s, about an argument of ``refine``), else the
    field its message's first word names."""
    first = field or (message.replace(":", " ").split(maxsplit=1)[0] if message.strip() else "")
    root, _, rest = first.partition(".")
    named = _REFINE_ARGUMENTS.get(root)
    if named is None:
        return ApiError(422, message)
    named = f"{named}.{rest}" if rest else named
    if field is not None and reason is not None:
        return invalid(named, reason)
    return ApiError(422, message if message.startswith(named) else f"{named}: {message}", field=named)


def estimate(
    engine: Engine,
    name: str,
    model: NarfModel,
    request: EstimateRequest,
    uploads: Mapping[str, bytes | None],
    *,
    options: Any,
    max_pixels: int,
    started: float,
    preset: tuple[str, str],
    should_stop: Callable[[], str | None] | None = None,
) -> EstimateResponse:
    """Decode the uploads (``image``, ``mask``, optional ``depth``), check them against the camera and refine
    with ``options``, which start from the preset ``preset`` (its name and why it was chosen).

    ``should_stop`` is polled once per iteration: a status (``"cancelled"``, ``"budget_exceeded"``)
    ends the refinement early with the best estimate so far.
    """
    size = (request.camera.height, request.camera.width)
    image = decode_rgb(uploads["image"] or b"", "image", max_pixels)
    mask = decode_mask(uploads["mask"] or b"", "mask", max_pixels)
    depth = decode_depth(uploads["depth"], "depth", max_pixels) if uploads.get("depth") else None
    for field, array in (("image", image), ("mask", mask), ("depth", depth)):
        if array is not None and array.shape[:2] != size:
            h, w = array.shape[:2]
            raise invalid(field, f"size {w}x{h} does not match the camera's {size[1]}x{size[0]}")
    if not mask.any():
        raise invalid("mask", "the mask is empty: no object pixel to compare against")
    mode, mode_reason = check_mode(model, options.mode, "request.options.mode")

    ground_truth = None
    if request.ground_truth is not None:
        ground_truth = (request.ground_truth.pose.as_matrix(), dict(request.ground_truth.joints))
    try:
        result = engine.refine(
            model,
            image,
            mask,
            pinhole(request.camera, model.aabb.device),
            request.initial_pose.as_matrix(),
            joints_init=request.initial_joints,
            depth=depth,
            options=options,
            ground_truth=ground_truth,
            should_stop=should_stop,
        )
    except engine.input_error as e:
        if isinstance(e, InputError):
            raise _refine_input_error(str(e), e.field, e.reason) from None
        raise _refine_input_error(str(e)) from None

    T = np.asarray(result.T_cam_obj, dtype=np.float64)
    if not np.isfinite(T).all() or not all(math.isfinite(v) for v in result.joints.values()):
        raise RuntimeError(f"refine returned a non-finite estimate for model {name!r}")
    metrics = None if result.metrics is None else {k: _finite_or_none(v) for k, v in result.metrics.items()}
    return EstimateResponse(
        model=name,
        pose=PoseOut.from_matrix(T),
        joints={k: float(v) for k, v in result.joints.items()},
        loss=_finite_or_none(result.loss),
        iterations=result.iterations,
        status=result.status,
        recovered_non_finite=result.recovered_non_finite,
        seconds=result.seconds,
        wall_seconds=time.perf_counter() - started,
        trace=[(_finite_or_none(loss), float(t)) for loss, t in result.trace],
        metrics=metrics,
        uncertainty=_uncertainty_out(result.uncertainty),
        warnings=list(result.warnings),
        mode=result.mode or mode,  # (the core's refine says; a stand-in refiner may not)
        mode_reason=result.mode_reason or mode_reason,
        preset=preset[0],
        preset_reason=preset[1],
    )
