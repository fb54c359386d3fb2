"""The wire format of API v1: pydantic models, the single source of the OpenAPI contract.

Conventions (docs/design.md §2): metres, radians, seconds; ``K`` in the OpenCV frame; poses ``T_cam_obj``
either as ``{"matrix": 4x4}`` or ``{"position": [x, y, z], "orientation": [qx, qy, qz, qw]}``
(ROS order); responses give both. Every number must be finite: NaN and infinities are refused with
a 422 naming the field, as are non-rigid matrices, non-unit quaternions and impossible cameras.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Annotated, Any, Literal, Optional

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator, model_validator

from narf_core.checks import ROTATION_TOLERANCE, check_pose
from narf_core.estimate import (
    JACOBIANS, MASK_TRUSTS, MODES, PRESET_NAMES, PRESETS, RAY_SAMPLINGS, ROBUST_LOSSES, SOLVERS, EstimateOptions,
)
from narf_core.geometry import pose_from_position_quaternion, pose_to_position_quaternion
from narf_core.modes import RENDER_MODES
from narf_core.track import TrackOptions, auto_solver_text, budget_text
from narf_service.registry import MODEL_NAME_MAX, MODEL_NAME_PATTERN

MAX_COORDINATE = 1e3  # metres: a pose farther than a kilometre is a unit mistake
MAX_IMAGE_SIDE = 16384
MAX_JOINTS = 64

Number = Annotated[float, Field(allow_inf_nan=False)]
Coordinate = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_COORDINATE, le=MAX_COORDINATE)]
Vector3 = Annotated[list[Coordinate], Field(min_length=3, max_length=3)]
Quaternion = Annotated[list[Number], Field(min_length=4, max_length=4, description="[qx, qy, qz, qw]")]
Row4 = Annotated[list[Coordinate], Field(min_length=4, max_length=4)]
Matrix4 = Annotated[list[Row4], Field(min_length=4, max_length=4, description="4x4, row-major")]
Row3 = Annotated[list[Number], Field(min_length=3, max_length=3)]
Matrix3 = Annotated[list[Row3], Field(min_length=3, max_length=3, description="3x3, row-major")]
ModelName = Annotated[
    str,
    Field(
        min_length=1,
        max_length=MODEL_NAME_MAX,
        pattern=MODEL_NAME_PATTERN,
        description="A served model (GET /v1/models), e.g. 'clamp'.",
    ),
]
Joints = Annotated[
    dict[Annotated[str, Field(min_length=1, max_length=128)], Number],
    Field(
        max_length=MAX_JOINTS,
        description="{joint: value}, radians or metres, within the joint's limits; a missing joint is at mid-range.",
    ),
]
RenderOutput = Literal["rgb", "depth", "opacity"]
RenderMode = Literal[RENDER_MODES]
RequestMode = Literal[MODES]
_MODE_MEANING = ("'narf': the configuration field; 'parts': the composed part fields; 'auto': the one the model's "
                 "training measured as better (the answer says which ran, and why)")
_MODE_OUT = "The render mode that ran ('auto' resolved)"
_MODE_REASON = "Why: 'requested', or the rule 'auto' followed (narf_core.modes)"


class StrictModel(BaseModel):
    """Request bodies refuse unknown fields, so a typo is a 422 naming it rather than ignored."""

    model_config = ConfigDict(extra="forbid")


class Pose(StrictModel):
    """A rigid pose ``T_cam_obj`` (object root-link frame -> camera frame).

    Exactly one form: ``matrix``, or ``position`` with ``orientation``.
    """

    matrix: Matrix4 | None = None
    position: Vector3 | None = None
    orientation: Quaternion | None = None

    @field_validator("matrix")
    @classmethod
    def _rigid(cls, m: list[list[float]] | None) -> list[list[float]] | None:
        if m is None:
            return None
        T = check_pose(m, "the matrix")  # the core's rule; a pose within its tolerance is re-projected
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
        return T.tolist()

    @field_validator("orientation")
    @classmethod
    def _unit(cls, q: list[float] | None) -> list[float] | None:
        if q is None:
            return None
        norm = math.sqrt(sum(x * x for x in q))
        if abs(norm - 1) > ROTATION_TOLERANCE:
            raise ValueError(f"quaternion norm {norm:.6g} is not 1 (tolerance {ROTATION_TOLERANCE})")
        return [x / norm for x in q]

    @model_validator(mode="after")
    def _one_form(self) -> Pose:
        has_matrix = self.matrix is not None
        has_pq = self.position is not None or self.orientation is not None
        if has_matrix == has_pq:
            raise ValueError("give either 'matrix' or 'position' and 'orientation'")
        if has_pq and (self.position is None or self.orientation is None):
            raise ValueError("'position' and 'orientation' go together")
        return self

    def as_matrix(self) -> np.ndarray:
        """``float64 [4, 4]``."""
        if self.matrix is not None:
            return np.asarray(self.matrix, dtype=np.float64)
        position = torch.tensor(self.position, dtype=torch.float64)
        orientation = torch.tensor(self.orientation, dtype=torch.float64)
        return pose_from_position_quaternion(position, orientation).numpy()


class PoseOut(BaseModel):
    """A pose in both wire forms."""

    matrix: list[list[float]] = Field(description="4x4, row-major")
    position: list[float] = Field(description="[x, y, z] metres")
    orientation: list[float] = Field(description="[qx, qy, qz, qw], qw >= 0")

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> PoseOut:
        """``T [4, 4]`` in both forms."""
        position, orientation = pose_to_position_quaternion(torch.as_tensor(T, dtype=torch.float64))
        return cls(matrix=np.asarray(T).tolist(), position=position.tolist(), orientation=orientation.tolist())


class Camera(StrictModel):
    """A pinhole camera (OpenCV frame, undistorted images); pixel (u, v) is centred at (u + .5, v + .5)."""

    K: Matrix3 = Field(description="[[fx, s, cx], [0, fy, cy], [0, 0, 1]], pixels")
    width: int = Field(gt=0, le=MAX_IMAGE_SIDE)
    height: int = Field(gt=0, le=MAX_IMAGE_SIDE)

    @field_validator("K")
    @classmethod
    def _intrinsics(cls, K: list[list[float]]) -> list[list[float]]:
        (fx, s, cx), (k10, fy, cy), last = K
        if not (1e-3 <= fx <= 1e7 and 1e-3 <= fy <= 1e7):
            raise ValueError(f"focal lengths must lie in [1e-3, 1e7] pixels, got fx={fx:g}, fy={fy:g}")
        if k10 != 0 or list(last) != [0, 0, 1]:
            raise ValueError("must have the form [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
        if max(abs(s), abs(cx), abs(cy)) > 1e7:
            raise ValueError("skew and principal point must lie within 1e7 pixels")
        return K


class JointInfo(BaseModel):
    name: str
    type: str = Field(description="URDF joint type: revolute (radians) or prismatic (metres)")
    lower: float
    upper: float


_EXAMPLE_CAMERA = {"K": [[134.1, 0, 80], [0, 134.1, 60], [0, 0, 1]], "width": 160, "height": 120}
_EXAMPLE_POSE = {"position": [0.0, 0.0, 0.5], "orientation": [0.0, 0.0, 0.0, 1.0]}


class RenderRequest(StrictModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"model": "clamp", "pose": _EXAMPLE_POSE, "camera": _EXAMPLE_CAMERA, "outputs": ["rgb", "depth"]}
            ]
        }
    )

    model: ModelName
    pose: Pose
    joints: Joints | None = None
    camera: Camera
    outputs: list[RenderOutput] = Field(
        default=["rgb"],
        min_length=1,
        max_length=3,
        description="Images to return; with 'Accept: image/png' exactly one.",
    )
    mode: RequestMode = Field("auto", description=_MODE_MEANING)

    @field_validator("outputs")
    @classmethod
    def _distinct(cls, outputs: list[str]) -> list[str]:
        if len(set(outputs)) != len(outputs):
            raise ValueError(f"each output at most once, got {outputs}")
        return outputs


class RenderResponse(BaseModel):
    """Images as base64 PNG: ``rgb`` 8-bit sRGB, ``depth`` 16-bit millimetres with 0 = no return
    (ROS 16UC1), ``opacity`` 8-bit (255 = opaque); the ones not asked for are null."""

    model: str
    width: int
    height: int
    mode: RenderMode = Field(description=_MODE_OUT)
    mode_reason: str = Field(description=_MODE_REASON)
    pose: PoseOut
    joints: dict[str, float] = Field(description="The full configuration rendered (missing joints at mid-range)")
    rgb: str | None = None
    depth: str | None = None
    opacity: str | None = None
    seconds: float = Field(description="Render time, excluding the wait in the queue")


_REFINE_OPTIONS: dict[str, tuple[str, dict[str, float]]] = {
    # The fields of EstimateOptions a request may set: what each means, and the caps that keep one
    # request's cost within reason (the validity rules themselves are EstimateOptions', applied when
    # the options are built: a 422 naming request.options.<field>).
    "lr_pose": ("Adam step, radians and object radii", {"le": 10}),
    "lr_theta": ("Adam step on the joints' sine parameter", {"le": 10}),
    "lr_decay": ("Final over first learning rate", {}),
    "rays_per_iteration": ("Rays rendered per iteration", {"ge": 16, "le": 65536}),
    "mode": (_MODE_MEANING, {}),
    "jacobian": ("gauss-newton's Jacobian: derivatives (the field's own, one pass) or differences (central "
                 "differences of the render, 2 (6 + k) renders: nearer on objects with several joints, 1.7-2x the "
                 "time)", {}),
    "silhouette_weight": ("Weight of the silhouette term (opacity - mask)^2", {"le": 1e3}),
    "depth_weight": ("Weight of the depth term; used when a depth part is sent", {"le": 1e3}),
    "theta_starts": ("Configurations tried at first", {"le": 16}),
    "coarse_to_fine": ("Image pyramid levels; 1 = the plain loss", {}),
    "box_margin": ("Growth of the mask's box rays come from", {"le": 10}),
    "early_stop": ("Stop once the estimate and the loss settle", {}),
    "tolerance": ("Early stop: mean motion per iteration", {"le": 1}),
    "loss_tolerance": ("Early stop: relative loss change", {"le": 1}),
    "patience": ("Early stop: iterations looked back over", {"le": 10_000}),
    "seed": ("Seed of the rays' random choice", {"ge": 0, "le": 2**31 - 1}),
    "solver": ("Adam (the paper) or Levenberg-Marquardt", {}),
    "robust_loss": ("Per-residual loss (either solver)", {}),
    "robust_scale": ("Where the robust loss bends, residual units", {"le": 1e3}),
    "damping": ("First Levenberg-Marquardt damping", {}),
    "photometric_compensation": ("Fit a gain and bias per colour channel", {}),
    "occlusion_margin": ("Metres; depth this far in front = occluder", {"le": 10}),
    "depth_sigma": ("Depth noise at 1 m (σ = depth_sigma z²)", {"le": 1}),
    "ray_sampling": ("Where each iteration's rays go", {}),
    "reference_box_px": ("Mask box side (px) above which more rays are drawn; 0 = off", {"le": 65536}),
    "band_m": ("Metres; march only this band around the model's surface; 0 = off", {}),
    "mask_trust": ("How far the mask is trusted: full, partial, or auto (partial where the depth contradicts the mask)", {}),
    "mask_band_px": ("Partial trust: pixels near the mask's edge that carry no mask residual", {}),
    "outside_weight": ("Partial trust: weight of the rays outside the mask", {}),
    "pose_starts": ("Pose starts scored before refining (1 = the given pose only)", {}),
    "pose_spread_deg": ("Degrees the other pose starts are turned by", {}),
    "slide_share": ("Where the mask is trusted partially: refine once more from the estimate slid along the object's "
                    "longest axis by this share of its length (and twice it) where a slid copy scores lower; 0 = off", {}),
    "adam_iterations": ("gauss-newton: Adam iterations first", {"le": 100_000}),
    "uncertainty": ("Return the covariance of the estimate", {}),
    "sigma_floor_position": ("Model error added to Σ, metres", {"le": 10}),
    "sigma_floor_rotation": ("Model error added to Σ, radians", {"le": 10}),
    "sigma_floor_joint": ("Model error added to Σ, joint range fraction", {"le": 10}),
}
_OPTION_CHOICES = {"mode": MODES, "solver": SOLVERS, "robust_loss": ROBUST_LOSSES, "ray_sampling": RAY_SAMPLINGS,
                   "mask_trust": MASK_TRUSTS, "jacobian": JACOBIANS}
_OPTION_TYPES = {"int": int, "float": float, "bool": bool}


def _options_model(
    name: str, core: type, exposed: dict[str, tuple[str, dict[str, float]]], left_out: str, doc: str,
    **extra: Any,
) -> type[StrictModel]:
    """A request's options, built from the core dataclass ``core``'s fields (types, choices, defaults)
    for the names in ``exposed`` (what each means, the caps on its cost); every field optional, and
    what one left out means is ``left_out`` (formatted with the core's default). ``extra``: fields
    that are the request's own."""
    specs = {f.name: f for f in dataclasses.fields(core)}
    fields: dict[str, Any] = dict(extra)
    for field, (meaning, caps) in exposed.items():
        spec = specs[field]
        kind = Literal[_OPTION_CHOICES[field]] if field in _OPTION_CHOICES else _OPTION_TYPES[spec.type]
        allow = {"allow_inf_nan": False} if kind is float else {}
        description = f"{meaning}. Left out: {left_out.format(json.dumps(spec.default))}"
        fields[field] = (Optional[kind], Field(None, description=description, **caps, **allow))
    return create_model(name, __base__=StrictModel, __doc__=doc, **fields)


RefineOptions = _options_model(
    "RefineOptions", EstimateOptions, _REFINE_OPTIONS, "the preset's value (paper: {})",
    "Refiner settings (``narf_core.estimate.EstimateOptions``); a field left out keeps the value of "
    "the preset (``auto``, the default: ``gauss-newton`` with a depth image, ``robust`` without; ``paper`` "
    "follows the paper; ``robust`` adds silhouette and depth terms, several joint starts and coarse-to-fine; "
    "``gauss-newton`` uses Levenberg-Marquardt steps on the same terms).",
    preset=(Optional[Literal[PRESET_NAMES]], Field(
        None, description="The starting set of options (default: auto; the response says which it chose)")),
)


class UncertaintyOut(BaseModel):
    """The estimate's covariance: order δposition of the box centre (m, camera axes), δrotation
    about it (rad, camera axes), then the joints (joint units)."""

    covariance: list[list[float]] = Field(description="[6 + k, 6 + k]")
    position_sigma_m: list[float] = Field(description="[3], metres")
    rotation_sigma_rad: list[float] = Field(description="[3], radians about the camera axes")
    joint_sigma: dict[str, float] = Field(description="Per joint, radians or metres")
    residual_variance: float
    dof: int


class GroundTruth(StrictModel):
    """The true pose and full configuration; the answer then carries ADD, ADD-S and joint errors."""

    pose: Pose
    joints: Joints = Field(default_factory=dict)


class EstimateRequest(StrictModel):
    """The JSON ``request`` part of ``POST /v1/estimate``; the images come as file parts."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"model": "clamp", "camera": _EXAMPLE_CAMERA, "initial_pose": _EXAMPLE_POSE, "iterations": 100}]
        }
    )

    model: ModelName
    camera: Camera = Field(description="Must match the size of the uploaded images")
    initial_pose: Pose
    initial_joints: Joints | None = None
    iterations: int | None = Field(
        None, ge=0, le=100_000,
        description="Default: the preset's (gauss-newton 25, the others 150); 0 scores the initial pose; capped by the server"
    )
    options: RefineOptions = Field(default_factory=RefineOptions)
    ground_truth: GroundTruth | None = None


class EstimateResponse(BaseModel):
    model: str
    pose: PoseOut
    joints: dict[str, float]
    loss: float | None = Field(description="Final loss; null if it was not finite")
    iterations: int
    status: str = Field(
        description="'converged', 'max_iterations', 'no_overlap', 'non_finite' or 'budget_exceeded' (stopped "
        "after the server's time budget per job, NARF_MAX_SECONDS, with the best estimate so far)"
    )
    recovered_non_finite: bool = Field(description="True if a non-finite step was detected and undone")
    seconds: float = Field(description="Refinement time")
    wall_seconds: float = Field(description="Time in the server, queue and decoding included")
    trace: list[tuple[float | None, float]] = Field(description="(loss, elapsed seconds) per iteration")
    metrics: dict[str, float | None] | None = Field(
        None, description="With ground truth: add, add_s (metres), joint_error/<name>"
    )
    uncertainty: UncertaintyOut | None = Field(None, description="Covariance of the estimate; null when not computed")
    warnings: list[str] = Field(
        default_factory=list,
        description="Doubts about the input and the answer, as '<code>: <message>' (codes: clipped, mask_border, "
                    "depth_unit, depth_overlap, coarse_model, unobserved_joint); after depth_unit or depth_overlap "
                    "the depth was not used; coarse_model: without depth, a camera over twice as fine as the model's "
                    "training views; unobserved_joint: the view hardly constrains that joint, its value is a guess",
    )
    mode: RenderMode = Field(description=_MODE_OUT)
    mode_reason: str = Field(description=_MODE_REASON)
    preset: Literal[PRESETS] = Field(description="The refiner preset that ran (options.preset, 'auto' resolved) ...")
    preset_reason: str = Field(description="... and why ('requested', or the rule 'auto' followed)")


class ModelSummary(BaseModel):
    name: str
    links: list[str]
    joints: list[JointInfo]
    modes: list[RenderMode]
    auto_mode: RenderMode = Field(description="The mode 'auto' renders this model in (narf_core.modes) ...")
    auto_mode_reason: str = Field(description="... and why")


class ModelList(BaseModel):
    models: list[ModelSummary]


class ModelInfo(ModelSummary):
    bounds: list[list[float]] = Field(description="Object-frame box [[xmin, ymin, zmin], [xmax, ymax, zmax]], metres")
    metrics: dict[str, Any] = Field(description="Evaluation metrics recorded at training")
    metadata: dict[str, Any] = Field(description="The bundle's metadata (architecture, provenance, ...), URDF text left out")


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class Readiness(BaseModel):
    status: Literal["ready", "not_ready"]
    models: list[str]
    failed: dict[str, str] = Field(description="Bundles that could not be loaded, with the reason")


class ErrorDetail(BaseModel):
    code: str = Field(description="Machine-readable: invalid_input, malformed_json, not_found, too_large, busy, ...")
    message: str = Field(description="Human-readable, starting with the field it is about")
    field: str | None = Field(None, description="Dotted path of the offending field or file part")


class ErrorResponse(BaseModel):
    error: ErrorDetail


_TRACK_OPTIONS: dict[str, tuple[str, dict[str, float]]] = {
    # The fields of TrackOptions a request may set, with the caps on one frame's cost (the validity
    # rules are TrackOptions', applied when the options are built: a 422 naming request.options.<field>).
    "iterations": (f"Refiner iterations per frame, 0 for the solver's own ({budget_text(0)})", {"le": 200}),
    "rays_per_iteration": (f"Rays rendered per iteration (left out: the solver's own, {budget_text(1)})",
                           {"ge": 16, "le": 8192}),
    "solver": (f"The per-frame solver: gauss-newton, adam, or auto ({auto_solver_text()})", {}),
    "jacobian": ("A Gauss-Newton frame's Jacobian with depth: differences (central differences of the render, "
                 "2 (6 + k) renders) or derivatives (the field's own, one pass: about twice the rate where they "
                 "suffice)", {}),
    "mode": (_MODE_MEANING, {}),
}

TrackOptionsIn = _options_model(
    "TrackOptionsIn", TrackOptions, _TRACK_OPTIONS, "the tracker's value ({})",
    "Tracker settings a request may change (``narf_core.track.TrackOptions``; the rest are the server's).",
    uncertainty=(Optional[bool], Field(None, description="Compute Σ per frame (default true)")),
)


class TrackRequest(StrictModel):
    """One frame of a track. The first frame sends ``initial_pose`` (and optionally ``initial_joints``);
    every later one sends the ``state`` token of the previous answer, so that any replica can answer it."""

    model: ModelName
    camera: Camera = Field(description="Must match the size of the uploaded images")
    time: Number = Field(ge=0, le=1e9, description="Frame time, seconds; must increase along a track")
    state: str | None = Field(None, max_length=16384, description="The previous answer's state token")
    initial_pose: Pose | None = Field(None, description="T_cam_obj at this frame (first frame only; rough is fine)")
    initial_joints: Joints | None = None
    options: TrackOptionsIn = Field(default_factory=TrackOptionsIn)

    @model_validator(mode="after")
    def _state_or_initial(self) -> TrackRequest:
        if (self.state is None) == (self.initial_pose is None):
            raise ValueError("give either 'state' (from the previous answer) or 'initial_pose' (first frame)")
        return self


class TrackResponse(BaseModel):
    model: str
    time: float
    status: Literal["tracking", "uncertain", "lost", "reinitialised"] = Field(
        description="'tracking'; 'uncertain' (partly occluded or a large Σ); 'lost' (no object in the mask or "
        "no pose explains it: the pose is the last one that stood); 'reinitialised' (found again by the "
        "multi-start refiner)"
    )
    reason: str | None = Field(None, description="Why the status is not 'tracking'")
    pose: PoseOut
    joints: dict[str, float]
    uncertainty: UncertaintyOut | None = None
    overlap: float | None = Field(None, description="How well the estimate explains the mask, 0..1")
    iterations: int
    seconds: float = Field(description="Tracking time of this frame")
    mode: RenderMode = Field(description=_MODE_OUT)
    mode_reason: str = Field(description=_MODE_REASON)
    warnings: list[str] = Field(
        default_factory=list,
        description="The frame's doubts, each '<code>: <message>': the input's (as /v1/estimate's) and "
        "'unobserved_joint' where this frame's view leaves a joint a guess within its range",
    )
    state: str = Field(description="Opaque, signed token: send it with the next frame")
