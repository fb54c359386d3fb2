"""Tracking over a sequence: the refiner warm-started frame after frame (issue #10).

Each frame is one :func:`~narf_core.estimate.refine` call of a few iterations that starts from a
constant-velocity prediction of the previous estimate. The state carried from frame to frame is a
:class:`TrackState`: the last estimate (pose, θ), its time, the velocity of the object's box
centre and its angular velocity (both in camera axes, so that the prediction turns the object
about itself), the joint velocities and, where the solver gives one, the covariance Σ.

A frame's status (:data:`STATUSES`):
  - ``tracking``: the estimate explains the mask (overlap at least ``options.uncertain_overlap``)
    and Σ, if known, is within ``options.max_position_sigma_m`` / ``max_rotation_sigma_deg``;
  - ``uncertain``: the estimate stands but the overlap is low (an occlusion) or Σ is large;
  - ``lost``: no object in the mask, or no pose found that explains it (overlap below
    ``options.lost_overlap``, a non-finite loss); the state keeps the last estimate;
  - ``reinitialised``: the warm start failed (or the track was lost, or the time gap since the
    last estimate exceeds ``options.max_gap_s``) and the multi-start refiner, started from the last
    estimate moved onto the mask's centroid, found a pose that explains the mask. The velocity
    starts again from zero.

The overlap is cheap and independent of the loss's scale: the model's surface points at the
estimate are projected into the image (no render), and ``overlap = min(inside, covered)`` where
``inside`` is the fraction of the projected points inside the image that land on the (slightly
dilated) mask (so an object leaving the view through an image border keeps its overlap) and
``covered`` the fraction of mask pixels near a projected point. A wrong pose or configuration
lowers one or the other; an occluder lowers ``inside``.

Frames must come in time order (a frame at or before the previous time is an input error).
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import torch

from narf_core.checks import check_number, check_option_types, check_pose, option_rule
from narf_core.estimate import MIN_MASK_PIXELS, SOLVERS, EstimateInputError, EstimateOptions, EstimateResult, refine
from narf_core.geometry import Pinhole, so3_exp, so3_log

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel

STATUSES = ("tracking", "uncertain", "lost", "reinitialised")
_MIN_VELOCITY_GAP_S = 1e-3  # velocities are measured over at least this long


class TrackInputError(EstimateInputError):
    """Unusable input to the tracker (frames out of order, a non-finite state, ...); names the field."""


@dataclass
class TrackOptions:
    """Tracker settings (plain JSON-able fields).

    ``iterations``/``rays_per_iteration``: the refiner's budget per frame from the prediction (few
    iterations on many rays: an iteration's cost is mostly per render call, little per ray);
    ``reinit_iterations``/``reinit_theta_starts``: that of a re-initialisation (multi-start,
    coarse-to-fine). ``solver``: the refiner's solver preset where :mod:`narf_core.estimate` has
    several ("adam" is the robust preset with one start).
    """

    iterations: int = 6
    rays_per_iteration: int = 768
    lr_pose: float = 0.003  # Adam moves every parameter by about its rate per step: small, from a close start
    lr_theta: float = 0.01
    lr_decay: float = 0.5
    silhouette_weight: float = 1.0  # with depth
    ray_sampling: str = "uniform"
    # Without depth the silhouette's scale is the main cue to distance: it weighs more, and half the
    # rays go near the mask's edges and image gradients ("edges"), where a distance error shows.
    silhouette_weight_rgb: float = 5.0
    ray_sampling_rgb: str = "edges"
    solver: str = "adam"
    mode: str = "narf"
    band_m: float = 0.0  # march only this far around the model's surface (EstimateOptions.band_m); 0 = off
    eval_rays: int = 512  # rays of the final loss (only reported: one start, nothing to choose between)
    uncertainty_rays: int = 256  # rays for Σ per frame; 0 = no Σ
    reinit_solver: str = "robust"
    reinit_iterations: int = 100
    reinit_theta_starts: int = 4
    velocity_smoothing: float = 0.6  # weight of the newest velocity measurement
    max_gap_s: float = 0.25  # longer since the last estimate: no prediction, re-initialise
    lost_overlap: float = 0.35
    uncertain_overlap: float = 0.6
    # Σ includes the model's error (estimate.model_error): a good 160x120 frame at 0.6 m has σ 5-10 mm.
    max_position_sigma_m: float = 0.02
    max_rotation_sigma_deg: float = 10.0
    seed: int = 0

    def __post_init__(self) -> None:
        check_option_types(self, TrackInputError)
        need = option_rule(self, TrackInputError)
        need(self.iterations >= 1, "iterations", "must be >= 1")
        need(self.rays_per_iteration >= 1, "rays_per_iteration", "must be >= 1")
        need(self.reinit_iterations >= 1, "reinit_iterations", "must be >= 1")
        need(1 <= self.reinit_theta_starts <= 64, "reinit_theta_starts", "must be in [1, 64]")
        need(0 < self.velocity_smoothing <= 1, "velocity_smoothing", "must be in (0, 1]")
        need(self.max_gap_s > 0, "max_gap_s", "must be > 0")
        need(0 <= self.lost_overlap <= self.uncertain_overlap <= 1, "lost_overlap",
             "must satisfy 0 <= lost_overlap <= uncertain_overlap <= 1")
        need(self.solver in SOLVERS, "solver", f"must be one of {', '.join(SOLVERS)}")
        need(self.reinit_solver in ("robust", "gauss-newton"), "reinit_solver", "must be 'robust' or 'gauss-newton'")
        need(self.uncertainty_rays >= 0, "uncertainty_rays", "must be >= 0")
        need(self.silhouette_weight >= 0, "silhouette_weight", "must be >= 0")
        need(self.silhouette_weight_rgb >= 0, "silhouette_weight_rgb", "must be >= 0")
        for name in ("ray_sampling", "ray_sampling_rgb"):
            need(getattr(self, name) in ("uniform", "edges"), name, "must be 'uniform' or 'edges'")
        need(self.mode in ("narf", "parts"), "mode", "must be 'narf' or 'parts'")
        need(self.band_m == 0 or 0.001 <= self.band_m <= 1, "band_m", "must be 0 (off) or in [0.001, 1] metres")
        need(self.eval_rays >= 16, "eval_rays", "must be >= 16")

    def step_options(self, depth: bool) -> EstimateOptions:
        """The refiner's options for a warm-started frame."""
        common = {"iterations": self.iterations, "rays_per_iteration": self.rays_per_iteration, "mode": self.mode,
                  "theta_starts": 1, "coarse_to_fine": 1, "early_stop": False, "seed": self.seed,
                  "band_m": self.band_m, "eval_rays": self.eval_rays,
                  "ray_sampling": self.ray_sampling if depth else self.ray_sampling_rgb,
                  "uncertainty": self.uncertainty_rays > 0, "uncertainty_rays": max(self.uncertainty_rays, 16)}
        if self.solver != "adam":
            return EstimateOptions.preset(self.solver, **common)
        return EstimateOptions.preset("robust", lr_pose=self.lr_pose, lr_theta=self.lr_theta, lr_decay=self.lr_decay,
                                      silhouette_weight=self.silhouette_weight if depth else self.silhouette_weight_rgb,
                                      **common)

    def reinit_options(self) -> EstimateOptions:
        """The multi-start refiner's options for a re-initialisation."""
        return EstimateOptions.preset(self.reinit_solver, iterations=self.reinit_iterations, mode=self.mode,
                                      theta_starts=self.reinit_theta_starts, seed=self.seed, band_m=self.band_m,
                                      uncertainty=self.uncertainty_rays > 0, uncertainty_rays=max(self.uncertainty_rays, 16))


@dataclass
class TrackFrame:
    """One observation: ``image [H,W,3]`` uint8, ``mask [H,W]`` (None = no mask this frame),
    ``depth [H,W]`` metres (None = RGB only) at ``time`` seconds."""

    image: np.ndarray
    mask: np.ndarray | None
    time: float
    depth: np.ndarray | None = None


@dataclass
class TrackState:
    """What the tracker carries from one frame to the next.

    ``T_cam_obj [4,4]`` and ``joints``: the last estimate, made at ``anchor_time``; ``time``: the
    last frame seen; ``velocity [6]``: the box centre's velocity (m/s) and the angular velocity
    (rad/s), camera axes; ``joint_velocity``: per joint, units per second; ``covariance``
    ``[6+k, 6+k]`` or None; ``status``: the last frame's; ``lost_frames``: frames since the last
    estimate that stood.
    """

    T_cam_obj: np.ndarray
    joints: dict[str, float]
    time: float
    anchor_time: float
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(6))
    joint_velocity: dict[str, float] = field(default_factory=dict)
    covariance: np.ndarray | None = None
    status: str = "tracking"
    lost_frames: int = 0

    @classmethod
    def initial(cls, model: NarfModel, T_cam_obj: np.ndarray, joints: Mapping[str, float] | None, time: float,
                status: str = "lost") -> TrackState:
        """A state at rest at ``T_cam_obj`` and ``joints`` (missing joints at mid-range), just before
        ``time``; ``lost`` by default, so that the first frame is found by the multi-start refiner."""
        theta = _joints(model, joints, "joints")
        pose = _pose(T_cam_obj, "T_cam_obj")
        t = _finite(time, "time")
        return cls(pose, theta, t - 1e-6, t, status=status)

    def check(self, model: NarfModel) -> None:
        """Raise :class:`TrackInputError` for a state that cannot be tracked from (non-finite, wrong joints)."""
        _pose(self.T_cam_obj, "state.T_cam_obj")
        _finite(self.time, "state.time")
        _finite(self.anchor_time, "state.anchor_time")
        v = np.asarray(self.velocity, dtype=np.float64)
        if v.shape != (6,) or not np.isfinite(v).all():
            raise TrackInputError("state.velocity must be 6 finite numbers")
        names = [j.name for j in model.joints]
        if sorted(self.joints) != sorted(names):
            raise TrackInputError(f"state.joints must name exactly the model's joints {names}")
        for name, value in [*self.joints.items(), *self.joint_velocity.items()]:
            _finite(value, f"state.joints.{name}")
        if self.covariance is not None and not np.isfinite(np.asarray(self.covariance)).all():
            raise TrackInputError("state.covariance must be finite")
        if self.status not in STATUSES:
            raise TrackInputError(f"state.status must be one of {', '.join(STATUSES)}, got {self.status!r}")


@dataclass
class TrackResult:
    """One frame's answer: its ``time``, ``status``, the estimate (for ``lost``: the last one that
    stood), the uncertainty (``position_sigma_m``, ``rotation_sigma_rad``, ``joint_sigma``) where
    known, ``overlap`` (None when not measured), the refiner's ``loss`` and ``iterations``, the
    wall-clock ``seconds`` and, for ``lost``/``reinitialised``/``uncertain``, a ``reason``."""

    time: float
    status: str
    T_cam_obj: np.ndarray
    joints: dict[str, float]
    overlap: float | None
    loss: float | None
    iterations: int
    seconds: float
    reason: str | None = None
    uncertainty: dict | None = None
    covariance: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {
            "time": self.time, "status": self.status, "T_cam_obj": np.asarray(self.T_cam_obj).tolist(),
            "joints": dict(self.joints), "overlap": self.overlap, "loss": self.loss, "iterations": self.iterations,
            "seconds": self.seconds, "reason": self.reason, "uncertainty": self.uncertainty,
        }


# --------------------------------------------------------------------------------------------
# checks


# The core's rules (narf_core/checks.py), raising TrackInputError.
_finite = partial(check_number, error=TrackInputError)
_pose = partial(check_pose, error=TrackInputError)


def _joints(model: NarfModel, joints: Mapping[str, float] | None, name: str) -> dict[str, float]:
    return model.joint_dict(model.kinematics.joint_vector(joints, field=name, error=TrackInputError))


# --------------------------------------------------------------------------------------------
# motion model


def _centre(model: NarfModel) -> np.ndarray:
    """The object's box centre ``[3]`` in its frame."""
    box = model.aabb.double().cpu().numpy()
    return (box[0] + box[1]) / 2


def predict(model: NarfModel, state: TrackState, time: float) -> tuple[np.ndarray, dict[str, float]]:
    """``T_cam_obj`` and joints at ``time`` under constant velocity from the state's estimate
    (the box centre moves straight, the object turns about it; joints stay within their limits)."""
    dt = time - state.anchor_time
    T = np.array(state.T_cam_obj, dtype=np.float64)
    c_obj = _centre(model)
    centre = T[:3, :3] @ c_obj + T[:3, 3] + state.velocity[:3] * dt
    R = so3_exp(torch.from_numpy(state.velocity[3:] * dt)).numpy() @ T[:3, :3]
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, centre - R @ c_obj
    joints = {}
    for j in model.joints:
        value = state.joints[j.name] + state.joint_velocity.get(j.name, 0.0) * dt
        joints[j.name] = float(min(max(value, j.lower), j.upper))
    return out, joints


def _velocity(model: NarfModel, before: TrackState, T: np.ndarray, dt: float) -> np.ndarray:
    """The box centre's velocity and the angular velocity ``[6]`` from ``before``'s estimate to ``T``."""
    c_obj = _centre(model)
    T0 = before.T_cam_obj
    v = ((T[:3, :3] @ c_obj + T[:3, 3]) - (T0[:3, :3] @ c_obj + T0[:3, 3])) / dt
    w = so3_log(torch.from_numpy(T[:3, :3] @ T0[:3, :3].T)).numpy() / dt
    return np.concatenate([v, w])


# --------------------------------------------------------------------------------------------
# overlap: the model's surface points against the mask


def _box_dilate(image: np.ndarray, r: int) -> np.ndarray:
    """Boolean ``[H, W]`` dilated by a ``(2r+1)^2`` square (integral image)."""
    if r <= 0:
        return image.copy()
    h, w = image.shape
    s = np.pad(image.astype(np.int32), ((r + 1, r), (r + 1, r))).cumsum(0).cumsum(1)
    total = s[2 * r + 1 :, 2 * r + 1 :] - s[: h, 2 * r + 1 :] - s[2 * r + 1 :, : w] + s[: h, : w]
    return total > 0


def surface_pixels(model: NarfModel, camera: Pinhole, T_cam_obj: np.ndarray, joints: Mapping[str, float]) -> np.ndarray:
    """Pixels ``[N, 2]`` (u, v, float) of the model's surface points in front of the camera."""
    x = _surface_points_cam(model, T_cam_obj, joints)
    K = camera.K.detach().double().cpu().numpy()
    uv = x @ K.T
    return uv[:, :2] / uv[:, 2:3]


def _surface_points_cam(model: NarfModel, T_cam_obj: np.ndarray, joints: Mapping[str, float]) -> np.ndarray:
    """The model's surface points ``[N, 3]`` in the camera frame, those in front of the camera."""
    theta = model.kinematics.joint_vector(joints)
    links = model.kinematics.link_poses(theta).double().numpy()
    points = []
    for i, name in enumerate(model.links):
        p = model.sample_points.get(name)
        if p is not None and len(p):
            points.append(np.asarray(p, dtype=np.float64) @ links[i, :3, :3].T + links[i, :3, 3])
    if not points:
        return np.zeros((0, 3))
    x = np.concatenate(points) @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    return x[x[:, 2] > 1e-6]


def overlap(model: NarfModel, camera: Pinhole, mask: np.ndarray, T_cam_obj: np.ndarray, joints: Mapping[str, float]) -> float:
    """``min(inside, covered)`` of the projected surface points and the mask (see the module docstring)."""
    mask = np.asarray(mask) != 0
    h, w = mask.shape
    n_mask = int(mask.sum())
    uv = surface_pixels(model, camera, T_cam_obj, joints)
    if n_mask == 0 or len(uv) == 0:
        return 0.0
    px = np.floor(uv).astype(np.int64)
    in_image = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    spacing = max(1, int(math.ceil(math.sqrt(n_mask / max(1, int(in_image.sum()))))))
    if not in_image.any():
        return 0.0
    px = px[in_image]
    # The same sums on the crop around the mask and the points, grown by the widest dilation (nothing
    # outside it is set or reached), instead of the whole image.
    v, u = np.nonzero(mask)
    u0, v0 = max(0, min(u.min(), px[:, 0].min()) - spacing - 1), max(0, min(v.min(), px[:, 1].min()) - spacing - 1)
    u1, v1 = min(w, max(u.max(), px[:, 0].max()) + spacing + 2), min(h, max(v.max(), px[:, 1].max()) + spacing + 2)
    mask, px = mask[v0:v1, u0:u1], px - np.array([u0, v0])
    grown = _box_dilate(mask, max(1, spacing // 2))
    inside = float(grown[px[:, 1], px[:, 0]].sum()) / len(px)  # the image shows no more
    splat = np.zeros_like(mask)
    splat[px[:, 1], px[:, 0]] = True
    covered = float((_box_dilate(splat, spacing) & mask).sum()) / n_mask
    return min(inside, covered)


# --------------------------------------------------------------------------------------------
# one frame


def _recentred(model: NarfModel, camera: Pinhole, T: np.ndarray, joints: Mapping[str, float], mask: np.ndarray,
               depth: np.ndarray | None) -> np.ndarray:
    """``T`` shifted so that its projected surface points' centroid lands on the mask's centroid and,
    where there is depth, their median depth on the median depth observed inside the mask."""
    x = _surface_points_cam(model, T, joints)
    if len(x) == 0:
        return T
    K = camera.K.detach().double().cpu().numpy()
    uv = x @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    z = float(np.median(x[:, 2]))
    target_z = z
    v, u = np.nonzero(mask)
    if depth is not None:
        d = np.asarray(depth)[v, u]
        d = d[np.isfinite(d) & (d > 0)]
        if len(d):
            target_z = float(np.median(d))
    here = np.linalg.solve(K, np.array([*uv.mean(0), 1.0])) * z
    there = np.linalg.solve(K, np.array([u.mean() + 0.5, v.mean() + 0.5, 1.0])) * target_z
    if not np.isfinite(there - here).all():
        return T
    out = T.copy()
    out[:3, 3] += there - here
    return out


def _uncertainty(result: EstimateResult) -> tuple[dict | None, np.ndarray | None]:
    u = result.uncertainty
    if u is None:
        return None, None
    cov = np.asarray(u.covariance, dtype=np.float64)
    if not np.isfinite(cov).all():
        return None, None
    return u.to_dict(), cov


def _too_uncertain(info: dict | None, options: TrackOptions) -> bool:
    if info is None:
        return False
    position = max(info.get("position_sigma_m", [0.0]))
    rotation = math.degrees(max(info.get("rotation_sigma_rad", [0.0])))
    return position > options.max_position_sigma_m or rotation > options.max_rotation_sigma_deg


def _check_frame(frame: TrackFrame, camera: Pinhole) -> np.ndarray | None:
    """The frame's mask as bool (None when missing), after checking sizes against the camera."""
    image = np.asarray(frame.image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise TrackInputError(f"image must be uint8 [H, W, 3], got {image.dtype} {list(image.shape)}")
    if (camera.width, camera.height) != (image.shape[1], image.shape[0]):
        raise TrackInputError(f"image is {image.shape[1]}x{image.shape[0]} but the camera is {camera.width}x{camera.height}")
    for name, array in (("mask", frame.mask), ("depth", frame.depth)):
        if array is not None and np.asarray(array).shape != image.shape[:2]:
            raise TrackInputError(f"{name} must be [H, W] = {list(image.shape[:2])}, got {list(np.asarray(array).shape)}")
    return None if frame.mask is None else np.asarray(frame.mask) != 0


def step(
    model: NarfModel,
    camera: Pinhole,
    frame: TrackFrame,
    state: TrackState,
    options: TrackOptions | None = None,
) -> tuple[TrackResult, TrackState]:
    """Track one frame from ``state``; returns the frame's result and the next state.

    Raises:
        TrackInputError: a frame at or before the state's time, a non-finite state, size mismatches.
    """
    start = _time.perf_counter()
    opts = options or TrackOptions()
    t = _finite(frame.time, "frame.time")
    state.check(model)
    if t <= state.time:
        raise TrackInputError(f"frame.time {t:.6f} s is not after the previous frame's {state.time:.6f} s: "
                              "frames must come in time order")
    mask = _check_frame(frame, camera)
    depth = None if frame.depth is None else np.asarray(frame.depth, dtype=np.float32)

    def lost(reason: str, loss: float | None = None, iterations: int = 0, score: float | None = None):
        nxt = TrackState(state.T_cam_obj, dict(state.joints), t, state.anchor_time, np.asarray(state.velocity),
                         dict(state.joint_velocity), state.covariance, "lost", state.lost_frames + 1)
        return TrackResult(t, "lost", state.T_cam_obj.copy(), dict(state.joints), score, loss, iterations,
                           _time.perf_counter() - start, reason), nxt

    if mask is None:
        return lost("no mask in this frame")
    if int(mask.sum()) < MIN_MASK_PIXELS:
        return lost("the object is not in view (empty mask)")
    gap = t - state.anchor_time
    iterations = 0
    if state.status != "lost" and gap <= opts.max_gap_s:
        T_pred, joints_pred = predict(model, state, t)
        result = refine(model, frame.image, mask, camera, T_pred, joints_init=joints_pred, depth=depth,
                        options=opts.step_options(depth is not None))
        iterations += result.iterations
        score = overlap(model, camera, mask, result.T_cam_obj, result.joints) if result.loss is not None else 0.0
        if result.status not in ("no_overlap", "non_finite") and score >= opts.lost_overlap:
            info, cov = _uncertainty(result)
            status, reason = "tracking", None
            if score < opts.uncertain_overlap:
                status, reason = "uncertain", f"the estimate explains only {score:.0%} of the mask (occlusion?)"
            elif _too_uncertain(info, opts):
                status, reason = "uncertain", "large covariance"
            velocity, joint_velocity = np.asarray(state.velocity, dtype=np.float64), dict(state.joint_velocity)
            if gap >= _MIN_VELOCITY_GAP_S:  # (not at a track's first frame, where the estimate has no predecessor)
                a = opts.velocity_smoothing
                velocity = a * _velocity(model, state, result.T_cam_obj, gap) + (1 - a) * velocity
                joint_velocity = {name: a * (value - state.joints[name]) / gap + (1 - a) * joint_velocity.get(name, 0.0)
                                  for name, value in result.joints.items()}
            nxt = TrackState(result.T_cam_obj, dict(result.joints), t, t, velocity, joint_velocity, cov, status, 0)
            return TrackResult(t, status, result.T_cam_obj, dict(result.joints), score, result.loss, iterations,
                               _time.perf_counter() - start, reason, info, cov), nxt
        why = "the warm start lost the object"
    else:
        why = "the track was lost" if state.lost_frames else "first frame: multi-start initialisation"
        if gap > opts.max_gap_s:
            why = f"{gap:.3f} s since the last estimate"
    T0 = _recentred(model, camera, state.T_cam_obj, state.joints, mask, depth)
    result = refine(model, frame.image, mask, camera, T0, joints_init=state.joints, depth=depth,
                    options=opts.reinit_options())
    iterations += result.iterations
    if result.status in ("no_overlap", "non_finite"):
        return lost(f"{why}; re-initialisation failed ({result.status})", result.loss, iterations)
    score = overlap(model, camera, mask, result.T_cam_obj, result.joints)
    if score < opts.uncertain_overlap:
        return lost(f"{why}; re-initialisation explains only {score:.0%} of the mask", result.loss, iterations, score)
    info, cov = _uncertainty(result)
    nxt = TrackState(result.T_cam_obj, dict(result.joints), t, t, np.zeros(6), {}, cov, "reinitialised", 0)
    return TrackResult(t, "reinitialised", result.T_cam_obj, dict(result.joints), score, result.loss, iterations,
                       _time.perf_counter() - start, why, info, cov), nxt


def track(
    model: NarfModel,
    frames: Iterable[TrackFrame],
    camera: Pinhole,
    T_first: np.ndarray,
    joints_first: Mapping[str, float] | None = None,
    options: TrackOptions | None = None,
) -> Iterator[TrackResult]:
    """Track ``frames`` (in time order) from the pose ``T_first`` and joints ``joints_first`` (a rough
    estimate at the first frame: the multi-start refiner refines it there); yields one
    :class:`TrackResult` per frame."""
    state: TrackState | None = None
    for frame in frames:
        if state is None:
            state = TrackState.initial(model, T_first, joints_first, _finite(frame.time, "frame.time"))
        result, state = step(model, camera, frame, state, options)
        yield result
