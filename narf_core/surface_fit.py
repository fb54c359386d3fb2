"""The model's surface points fitted to a depth image's points: articulated ICP in pose and θ.

A warm-started frame's photometric iterations see a thin part's joint move only where the part's
edge crosses one of their rays: a degree of a lamp's shoulder moves its arm by a pixel or less at
160x120, the rays beside the arm render the part behind it, and the robust loss is flat until the
edge has crossed them (docs/benchmarks.md, sessions 63 and 64). Points do not have that edge: every
observed point of the arm pulls the arm's nearest surface point towards it from wherever it is, so
the fit below reaches a joint's motion of degrees in an iteration or two, and the photometric
iterations start within their reach.

Observed points: the mask's pixels with a finite depth > 0, back-projected into the camera frame
(up to ``observed_points`` of them, an even draw with a fixed seed). Model points: every link's
surface points (``NarfModel.sample_points``, link frame) moved by forward kinematics at θ and by the
pose, those no other point hides in its image cell at the start (:func:`narf_core.band.hidden_points`:
a point on a part's far side must not pair with the near side's observation). Each iteration pairs
every observed point with the nearest model point and takes the Gauss-Newton step (Levenberg-Marquardt,
a fixed damping) in the translation, the rotation about the paired points' centroid (both camera
frame) and θ that moves the paired points onto the observed ones: point to point, each pair weighted
by Huber at ``huber_m`` and left out beyond ``reject_m`` (a mask's stray blob, an occluder's edge).
θ's columns of the Jacobian are central differences of forward kinematics, θ stays within the
limits. Point to point, not to the plane: normals from the surface points' neighbours (a few millimetres
apart) were wrong on thin parts, and the observed depth's own normals, which converge in fewer iterations
from centimetres off, tracked no better on our sequences and would carry a real sensor's noise
(docs/benchmarks.md, session 64).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from narf_core.band import hidden_points, point_spacing
from narf_core.geometry import Pinhole, skew, so3_exp

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel

_DIFFERENCE = 1e-4  # θ's step for the Jacobian's central differences (radians or metres)
_MIN_PAIRS = 20  # fewer kept pairs than this: no step (nor without as many observed points)


@dataclass(frozen=True)
class SurfaceFitOptions:
    """The fit's budget and robustness: ``iterations`` (0: no fit), ``observed_points`` drawn from the mask,
    the Huber scale ``huber_m`` and the pair distance ``reject_m`` beyond which a pair is left out (metres),
    and the Levenberg-Marquardt ``damping`` (a share of the normal matrix's diagonal)."""

    iterations: int = 3
    observed_points: int = 800
    huber_m: float = 0.004
    reject_m: float = 0.03
    damping: float = 1e-3


@dataclass
class SurfaceFit:
    """The fit's result: ``T_cam_obj [4, 4]`` and ``joints`` (name -> value), the ``pairs`` its last step
    kept and their weighted RMS distance ``rms_m`` before that step (metres; NaN where it took no step)."""

    T_cam_obj: np.ndarray
    joints: dict[str, float]
    pairs: int
    rms_m: float


def observed_points(camera: Pinhole, mask: np.ndarray, depth: np.ndarray, count: int, seed: int = 0) -> Tensor:
    """``[M, 3]``: :func:`pixel_points` of ``mask``'s pixels (``[H, W]``, > 0.5) at their ``depth`` (``[H, W]``)."""
    d = np.asarray(depth, dtype=np.float64)
    v, u = np.nonzero(np.asarray(mask) > 0.5)
    return pixel_points(camera, torch.from_numpy(np.stack([u, v], -1)), torch.from_numpy(d[v, u]), count, seed)


def pixel_points(camera: Pinhole, uv: Tensor, z: Tensor, count: int, seed: int = 0) -> Tensor:
    """``[M, 3]`` float64 camera-frame points of up to ``count`` of the integer pixels ``uv [Q, 2]`` (u, v) whose
    depth ``z [Q]`` (metres) is finite and > 0, drawn evenly with ``seed``; a pixel is seen at its centre."""
    uv, z = uv.cpu().double(), z.cpu().double()
    has = torch.isfinite(z) & (z > 0)
    uv, z = uv[has], z[has]
    if len(z) > count:
        pick = np.sort(np.random.default_rng(seed).choice(len(z), count, replace=False))
        uv, z = uv[pick], z[pick]
    K = camera.K.detach().double().cpu()
    xy = (uv + 0.5 - K[:2, 2]) / torch.stack([K[0, 0], K[1, 1]]) * z[:, None]
    return torch.cat([xy, z[:, None]], -1)


def _link_points(model: NarfModel) -> tuple[Tensor, Tensor]:
    """Every link's surface points ``[N, 3]`` (link frame, float64) and their links' indices ``[N]`` in
    ``model.links`` order; cached on the model."""
    cached = getattr(model, "_surface_fit_points", None)
    if cached is not None:
        return cached
    points, owners = [], []
    for i, name in enumerate(model.links):
        p = torch.as_tensor(np.asarray(model.sample_points.get(name, np.zeros((0, 3))), dtype=np.float64))
        points.append(p.reshape(-1, 3))
        owners.append(torch.full((len(points[-1]),), i, dtype=torch.long))
    cached = (torch.cat(points), torch.cat(owners))
    model._surface_fit_points = cached
    return cached


def _camera_from_links(T_cam_obj: Tensor, links: Tensor, points: Tensor, owners: Tensor) -> Tensor:
    """``[C, N, 3]``: link-frame ``points [N, 3]`` of links ``owners [N]`` in the camera frame, for every
    configuration's link poses ``links [C, L, 4, 4]`` (object frame) under ``T_cam_obj [4, 4]``."""
    A = T_cam_obj @ links  # [C, L, 4, 4]
    R, t = A[:, owners, :3, :3], A[:, owners, :3, 3]
    return (R @ points[None, :, :, None])[..., 0] + t


def _huber_weights(distance: Tensor, scale: float, reject: float) -> Tensor:
    """IRLS weights of Huber's loss at ``scale`` for ``distance [M]``, 0 beyond ``reject``."""
    w = torch.where(distance <= scale, torch.ones_like(distance), scale / distance.clamp_min(1e-12))
    return torch.where(distance > reject, torch.zeros_like(w), w)


def surface_fit(
    model: NarfModel,
    camera: Pinhole,
    T_cam_obj: np.ndarray,
    joints: Mapping[str, float],
    mask: np.ndarray,
    depth: np.ndarray,
    options: SurfaceFitOptions = SurfaceFitOptions(),
) -> SurfaceFit:
    """The pose ``T_cam_obj [4, 4]`` and ``joints`` moved so that the model's visible surface points meet
    the points the ``depth`` image (``[H, W]``, z in metres) observes inside ``mask`` (``[H, W]``): see the
    module and :func:`fit_points`."""
    kin = model.kinematics
    T, theta, pairs, rms = fit_points(model, camera, torch.as_tensor(np.asarray(T_cam_obj), dtype=torch.float64),
                                      kin.joint_vector(joints).double(),
                                      observed_points(camera, mask, depth, options.observed_points), options)
    return SurfaceFit(T.numpy().copy(), {n: float(theta[i]) for i, n in enumerate(kin.joint_names)}, pairs, rms)


def fit_points(
    model: NarfModel, camera: Pinhole, T_cam_obj: Tensor, theta: Tensor, observed: Tensor,
    options: SurfaceFitOptions = SurfaceFitOptions(),
) -> tuple[Tensor, Tensor, int, float]:
    """The fit of the module from ``T_cam_obj [4, 4]`` and ``θ [k]`` (float64) to the camera-frame points
    ``observed [M, 3]``: the moved pose and θ, the pairs the last step kept and their weighted RMS distance
    before it (metres). The start comes back (0 pairs, NaN) where there is nothing to fit: no surface points,
    fewer than ``_MIN_PAIRS`` observed or kept pairs, a step that is not finite."""
    kin = model.kinematics
    k = theta.shape[0]
    T, theta = T_cam_obj.detach().double().cpu().clone(), theta.detach().double().cpu().clone()
    points, owners = _link_points(model)
    O = observed.double().cpu()
    if options.iterations <= 0 or len(points) == 0 or len(O) < _MIN_PAIRS:
        return T, theta, 0, float("nan")
    low, high = kin.lower, kin.upper
    shifts = torch.cat([torch.zeros(1, k), torch.eye(k), -torch.eye(k)]).double() * _DIFFERENCE
    seen = None
    start = (T.clone(), theta.clone())
    pairs, rms = 0, float("nan")
    for _ in range(options.iterations):
        links = kin.link_poses(theta[None] + shifts) if k else kin.link_poses(None)[None]
        X = _camera_from_links(T, links[:1], points, owners)[0]  # [N, 3] at θ
        if seen is None:
            everything = torch.ones(1, len(points), dtype=torch.bool)
            seen = torch.nonzero(~hidden_points(X, camera, point_spacing(model), everything)[0])[:, 0]
            if len(seen) == 0:
                break
        distance, nearest = torch.cdist(O, X[seen]).min(1)
        paired = seen[nearest]
        w = _huber_weights(distance, options.huber_m, options.reject_m)
        kept = int((w > 0).sum())
        if kept < _MIN_PAIRS:
            break
        P = X[paired]
        centre = (w[:, None] * P).sum(0) / w.sum()
        q = P - centre
        J = torch.zeros(len(P), 3, 6 + k, dtype=torch.float64)
        J[:, :, :3] = torch.eye(3, dtype=torch.float64)
        J[:, :, 3:6] = -skew(q)  # d(ω x q)/dω = -[q]x
        if k:
            moved = _camera_from_links(T, links[1:], points[paired], owners[paired])  # [2k, M, 3]
            J[:, :, 6:] = ((moved[:k] - moved[k:]) / (2 * _DIFFERENCE)).permute(1, 2, 0)
        r = (O - P).reshape(-1)
        Jf, wf = J.reshape(-1, 6 + k), w.repeat_interleave(3)
        H = Jf.T @ (wf[:, None] * Jf)
        H = H + options.damping * torch.diag(torch.diagonal(H)) + 1e-12 * torch.eye(6 + k, dtype=H.dtype)
        step = torch.linalg.solve(H, Jf.T @ (wf * r))
        if not bool(torch.isfinite(step).all()):
            break
        R = so3_exp(step[3:6])
        T[:3, :3] = R @ T[:3, :3]
        T[:3, 3] = R @ (T[:3, 3] - centre) + centre + step[:3]
        if k:
            theta = torch.minimum(torch.maximum(theta + step[6:], low), high)
        pairs, rms = kept, float(((w * distance**2).sum() / w.sum()).sqrt())
    if pairs == 0:
        return start[0], start[1], 0, float("nan")
    return T, theta, pairs, rms
