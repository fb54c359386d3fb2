"""What the client hands back: poses, rendered images, estimates and model descriptions (numpy inside).

Conventions are the server's (docs/design.md §2): metres, radians; ``K`` in the OpenCV frame; a pose is
``T_cam_obj``; quaternions are ``[qx, qy, qz, qw]`` (ROS order).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternion ``[4]`` (xyzw, normalised here) -> rotation ``[3, 3]``."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Rotation ``[3, 3]`` -> unit quaternion ``[4]`` (xyzw, ``qw >= 0``); Shepperd's method, stable at pi."""
    m = np.asarray(R, dtype=np.float64)
    trace = np.trace(m)
    diagonal = np.diag(m)
    i = int(np.argmax([trace, *diagonal]))
    if i == 0:
        r = 2 * np.sqrt(1 + trace)  # 4 qw
        q = np.array([(m[2, 1] - m[1, 2]) / r, (m[0, 2] - m[2, 0]) / r, (m[1, 0] - m[0, 1]) / r, r / 4])
    else:  # (a, b, c) cyclic, a the largest diagonal entry; r = 4 q_a
        a = i - 1
        b, c = (a + 1) % 3, (a + 2) % 3
        r = np.sqrt(1 + m[a, a] - m[b, b] - m[c, c]) * 2
        q = np.empty(4)
        q[a] = r / 4
        q[b] = (m[a, b] + m[b, a]) / r
        q[c] = (m[a, c] + m[c, a]) / r
        q[3] = (m[c, b] - m[b, c]) / r
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


@dataclass(frozen=True)
class Pose:
    """A rigid pose ``T_cam_obj``: ``matrix [4, 4]`` (float64); ``position [3]`` and ``orientation [4]`` (xyzw)."""

    matrix: np.ndarray

    def __post_init__(self) -> None:
        m = np.array(self.matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"a pose matrix must be 4x4, got shape {m.shape}")
        if not np.isfinite(m).all():
            raise ValueError("a pose matrix must be finite (it holds NaN or infinity)")
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)

    @classmethod
    def from_position_orientation(cls, position, orientation) -> Pose:
        """From ``position [3]`` (metres) and ``orientation [4]`` (xyzw, normalised here)."""
        q = np.asarray(orientation, dtype=np.float64)
        p = np.asarray(position, dtype=np.float64)
        if p.shape != (3,) or q.shape != (4,):
            raise ValueError(f"position must have 3 values and orientation 4, got {p.shape} and {q.shape}")
        if not np.linalg.norm(q) > 0:
            raise ValueError("orientation must be a non-zero quaternion")
        m = np.eye(4)
        m[:3, :3] = quaternion_to_matrix(q)
        m[:3, 3] = p
        return cls(m)

    @classmethod
    def coerce(cls, pose: Pose | np.ndarray | Any) -> Pose:
        """A :class:`Pose` from a Pose or a ``[4, 4]`` array-like."""
        return pose if isinstance(pose, Pose) else cls(np.asarray(pose, dtype=np.float64))

    @property
    def position(self) -> np.ndarray:
        return self.matrix[:3, 3].copy()

    @property
    def orientation(self) -> np.ndarray:
        return matrix_to_quaternion(self.matrix[:3, :3])

    def to_json(self) -> dict[str, list]:
        return {"matrix": self.matrix.tolist()}


@dataclass(frozen=True)
class RenderResult:
    """Rendered images; those not asked for are ``None``.

    ``rgb`` uint8 ``[H, W, 3]``; ``depth`` float32 metres ``[H, W]`` (0 = no return, 1 mm steps);
    ``opacity`` float32 ``[H, W]`` in [0, 1] (1/255 steps).
    """

    rgb: np.ndarray | None
    depth: np.ndarray | None
    opacity: np.ndarray | None
    joints: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    mode: str | None = None  # the render mode that ran ("narf" or "parts"; "auto" resolved) ...
    mode_reason: str | None = None  # ... and why ("requested", or the rule "auto" followed)


@dataclass(frozen=True)
class Estimate:
    """A refined pose and configuration.

    ``trace`` holds ``(loss, elapsed seconds)`` per iteration (loss ``None`` where it was not finite);
    ``metrics`` (``add``, ``add_s`` in metres, ``joint_error/<name>``) only when ground truth was sent.
    """

    pose: Pose
    joints: dict[str, float]
    loss: float | None
    iterations: int
    seconds: float
    wall_seconds: float
    status: str
    trace: list[tuple[float | None, float]]
    metrics: dict[str, float | None] | None
    recovered_non_finite: bool = False
    warnings: tuple[str, ...] = ()  # the server's doubts about the input ("<code>: <message>")
    uncertainty: Uncertainty | None = None  # the estimate's covariance, when the server computed one
    mode: str | None = None  # the render mode that ran ("narf" or "parts"; "auto" resolved) ...
    mode_reason: str | None = None  # ... and why ("requested", or the rule "auto" followed)
    preset: str | None = None  # the refiner preset that ran (options["preset"], "auto" resolved) ...
    preset_reason: str | None = None  # ... and why


@dataclass(frozen=True)
class Uncertainty:
    """The covariance of an estimate. Order of ``covariance [6 + k, 6 + k]``: the displacement of the
    object's box centre (metres, camera axes), the rotation about it (radians, camera axes), then
    the joints (radians or metres, the model's order)."""

    covariance: np.ndarray
    position_sigma_m: np.ndarray  # [3]
    rotation_sigma_rad: np.ndarray  # [3]
    joint_sigma: dict[str, float]
    residual_variance: float
    dof: int

    @classmethod
    def from_json(cls, body: dict[str, Any] | None) -> Uncertainty | None:
        if body is None:
            return None
        return cls(
            covariance=np.asarray(body["covariance"], dtype=np.float64),
            position_sigma_m=np.asarray(body["position_sigma_m"], dtype=np.float64),
            rotation_sigma_rad=np.asarray(body["rotation_sigma_rad"], dtype=np.float64),
            joint_sigma={k: float(v) for k, v in body["joint_sigma"].items()},
            residual_variance=float(body["residual_variance"]),
            dof=int(body["dof"]),
        )


@dataclass(frozen=True)
class JointInfo:
    name: str
    type: str
    lower: float
    upper: float


@dataclass(frozen=True)
class ModelInfo:
    """A served model. ``bounds [2, 3]``, ``metrics`` and ``metadata`` are filled by ``model(name)`` only."""

    name: str
    links: list[str]
    joints: list[JointInfo]
    modes: list[str]
    bounds: np.ndarray | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
    auto_mode: str | None = None  # the mode "auto" renders this model in ...
    auto_mode_reason: str | None = None  # ... and why

    @property
    def mid_joints(self) -> dict[str, float]:
        """Every joint at the middle of its range."""
        return {j.name: (j.lower + j.upper) / 2 for j in self.joints}


@dataclass(frozen=True)
class TrackFrame:
    """One frame to track: ``image`` uint8 ``[H, W, 3]`` (or PNG/JPEG bytes) at ``time`` seconds,
    ``mask`` ``[H, W]`` (non-zero = object; ``None`` = none this frame, answered ``lost``) and
    ``depth`` float32 metres ``[H, W]`` (``None`` = RGB only)."""

    time: float
    image: np.ndarray | bytes
    mask: np.ndarray | None = None
    depth: np.ndarray | None = None


@dataclass(frozen=True)
class TrackUpdate:
    """The server's answer for one frame of a track.

    ``status``: ``tracking``, ``uncertain`` (partly occluded or a large covariance), ``lost`` (``pose``
    is then the last one that stood) or ``reinitialised``; ``reason`` says why when not ``tracking``.
    ``state`` is the opaque token the next frame sends (any replica with the same key accepts it).
    """

    time: float
    status: str
    reason: str | None
    pose: Pose
    joints: dict[str, float]
    uncertainty: Uncertainty | None
    overlap: float | None
    iterations: int
    seconds: float
    state: str
    mode: str | None = None  # the render mode the tracker used ("auto" resolved) and why
    mode_reason: str | None = None
    warnings: tuple[str, ...] = ()  # the frame's doubts ("<code>: <message>", as Estimate.warnings)
