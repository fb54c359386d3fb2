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
surface points a few millimetres apart (``NarfModel.dense_points``, link frame; in a bundle saved
without them its ``sample_points``, centimetres apart on a large part, where a pair sits millimetres
off the surface and biases the fit), moved by forward kinematics at θ and by the pose, those no
other point hides in its image cell at the start (:func:`narf_core.band.hidden_points`:
a point on a part's far side must not pair with the near side's observation). Each iteration pairs
every observed point with the nearest model point (a k-d tree) and takes the Gauss-Newton step
(Levenberg-Marquardt, a fixed damping) in the translation, the rotation about the paired points' centroid (both camera
frame) and θ that moves the paired points onto the observed ones: point to point, each pair weighted
by Huber at ``huber_m`` and left out beyond ``reject_m`` (a mask's stray blob, an occluder's edge).
θ's columns of the Jacobian are central differences of forward kinematics, θ stays within the
limits. Several starts (the refiner's rows) are fitted at once. Point to point, not to the plane:
normals from the surface points' neighbours (a few millimetres apart) were wrong on thin parts, and the
observed depth's own normals, which converge in fewer iterations from centimetres off, tracked no better
on our sequences and would carry a real sensor's noise (docs/benchmarks.md, session 64).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from narf_core.band import hidden_points
from narf_core.gauss_newton import robust_weights
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


def _link_points(model: NarfModel) -> tuple[Tensor, Tensor, float]:
    """Every link's surface points ``[N, 3]`` (link frame, float64: ``model.dense_points``, else its
    ``sample_points``), their links' indices ``[N]`` in ``model.links`` order and the points' spacing (metres:
    twice the mean distance to the nearest point on the same link); cached on the model."""
    from scipy.spatial import cKDTree

    cached = getattr(model, "_surface_fit_points", None)
    if cached is not None:
        return cached
    source = getattr(model, "dense_points", None) or model.sample_points
    points, owners, gaps = [], [], []
    for i, name in enumerate(model.links):
        p = np.asarray(source.get(name, np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        points.append(torch.from_numpy(p))
        owners.append(torch.full((len(p),), i, dtype=torch.long))
        if len(p) > 1:
            gaps.append(cKDTree(p).query(p, k=2)[0][:, 1])
    spacing = 2 * float(np.concatenate(gaps).mean()) if gaps else 0.0
    cached = (torch.cat(points), torch.cat(owners), spacing)
    model._surface_fit_points = cached
    return cached


def _camera_from_links(T_cam_obj: Tensor, links: Tensor, points: Tensor, owners: Tensor) -> Tensor:
    """``[S, C, N, 3]``: link-frame ``points`` (``[N, 3]``, or ``[S, N, 3]`` per pose) of links ``owners`` (``[N]`` or
    ``[S, N]``) in the camera frame, for every pose ``T_cam_obj [S, 4, 4]`` and each of its configurations' link poses
    ``links [S, C, L, 4, 4]`` (object frame)."""
    A = T_cam_obj[:, None, None] @ links  # [S, C, L, 4, 4]
    S, C = A.shape[:2]
    points, owners = points.expand(S, -1, -1), owners.expand(S, -1)
    index = owners[:, None, :, None, None].expand(S, C, owners.shape[1], 4, 4)
    A = torch.gather(A, 2, index)  # [S, C, N, 4, 4]
    return (A[..., :3, :3] @ points[:, None, :, :, None])[..., 0] + A[..., :3, 3]


class _LinkTrees:
    """Each start's k-d trees of its links' surface points (link frame) that the start's pose left visible, built
    once: a link's points move with it rigidly, so the observed points are moved into each link's frame instead and
    the nearest over the links' trees is the pose's nearest point (no tree to build again each iteration)."""

    def __init__(self, points: Tensor, owners: Tensor, hidden: Tensor, n_links: int) -> None:
        from scipy.spatial import cKDTree

        self.trees: list[list[tuple[int, cKDTree, Tensor]]] = []
        for hide in hidden:
            kept = [(link, torch.nonzero(~hide & (owners == link))[:, 0]) for link in range(n_links)]
            self.trees.append([(link, cKDTree(points[index].numpy()), index) for link, index in kept if len(index)])

    def nearest(self, observed: Tensor, camera_from_link: Tensor) -> tuple[Tensor, Tensor]:
        """``(distance [S, M], index [S, M])``: for each of the camera-frame points ``observed [M, 3]``, the nearest
        kept point of each start whose links sit at ``camera_from_link [S, L, 4, 4]`` (inf, 0 where none is kept)."""
        S, M = camera_from_link.shape[0], len(observed)
        distance = torch.full((S, M), float("inf"), dtype=torch.float64)
        index = torch.zeros(S, M, dtype=torch.long)
        for s, trees in enumerate(self.trees):
            for link, tree, kept in trees:
                A = camera_from_link[s, link]
                local = (observed - A[:3, 3]) @ A[:3, :3]  # R^T (o - t), row-wise
                d, i = tree.query(local.numpy())
                d = torch.from_numpy(d)
                closer = d < distance[s]
                distance[s] = torch.where(closer, d, distance[s])
                index[s] = torch.where(closer, kept[torch.from_numpy(i)], index[s])
        return distance, index


def _pair_weights(distance: Tensor, scale: float, reject: float) -> Tensor:
    """IRLS weights of Huber's loss at ``scale`` (:func:`~narf_core.gauss_newton.robust_weights`) for the pairs'
    ``distance``, 0 beyond ``reject``."""
    w = robust_weights(distance, "huber", scale)
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
    T, theta, pairs, rms = fit_points(model, camera, torch.as_tensor(np.asarray(T_cam_obj), dtype=torch.float64)[None],
                                      kin.joint_vector(joints).double()[None],
                                      observed_points(camera, mask, depth, options.observed_points), options)
    return SurfaceFit(T[0].numpy().copy(), {n: float(theta[0, i]) for i, n in enumerate(kin.joint_names)},
                      int(pairs[0]), float(rms[0]))


def fit_points(
    model: NarfModel, camera: Pinhole, T_cam_obj: Tensor, theta: Tensor, observed: Tensor,
    options: SurfaceFitOptions = SurfaceFitOptions(),
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The fit of the module from each of the starts ``T_cam_obj [S, 4, 4]`` and ``θ [S, k]`` (float64) to the
    camera-frame points ``observed [M, 3]``, all starts at once: the moved poses ``[S, 4, 4]`` and θ ``[S, k]``, the
    pairs each one's last step kept ``[S]`` and their weighted RMS distance before it ``[S]`` (metres). A start comes
    back as it was (0 pairs, NaN) where there is nothing to fit: no surface points, fewer than ``_MIN_PAIRS``
    observed or kept pairs; a start stops where its step is not finite or it keeps too few pairs."""
    kin = model.kinematics
    S, k = theta.shape
    T0, theta0 = T_cam_obj.detach().double().cpu(), theta.detach().double().cpu()
    T, theta = T0.clone(), theta0.clone()
    points, owners, spacing = _link_points(model)
    O = observed.double().cpu()
    pairs, rms = torch.zeros(S, dtype=torch.long), torch.full((S,), float("nan"), dtype=torch.float64)
    if options.iterations <= 0 or len(points) == 0 or len(O) < _MIN_PAIRS:
        return T, theta, pairs, rms
    shifts = torch.cat([torch.zeros(1, k), torch.eye(k), -torch.eye(k)]).double() * _DIFFERENCE
    active = torch.ones(S, dtype=torch.bool)
    trees = None  # of the points not hidden at the start (a far side must not pair with the near side's points)
    eye = torch.eye(6 + k, dtype=torch.float64)
    for _ in range(options.iterations):
        links = (kin.link_poses(theta[:, None] + shifts) if k  # [S, 1 + 2k, L, 4, 4]: at θ, then θ ± a step
                 else kin.link_poses(None)[None, None].expand(S, 1, -1, -1, -1))
        if trees is None:
            X = _camera_from_links(T, links[:, :1], points, owners)[:, 0]  # [S, N, 3] at the start
            everything = torch.ones(1, len(points), dtype=torch.bool)
            far = torch.stack([hidden_points(x, camera, spacing, everything)[0] for x in X])
            active &= ~far.all(1)
            trees = _LinkTrees(points, owners, far, len(model.links))
        distance, nearest = trees.nearest(O, T[:, None] @ links[:, 0])  # [S, M]
        w = _pair_weights(distance, options.huber_m, options.reject_m)
        kept = (w > 0).sum(1)
        active &= kept >= _MIN_PAIRS
        if not bool(active.any()):
            break
        paired = torch.gather(points.expand(S, -1, -1), 1, nearest[..., None].expand(-1, -1, 3))  # [S, M, 3]
        P = _camera_from_links(T, links[:, :1], paired, owners[nearest])[:, 0]  # [S, M, 3] camera frame at θ
        centre = (w[..., None] * P).sum(1) / w.sum(1).clamp_min(1e-12)[:, None]
        q = P - centre[:, None]
        J = torch.zeros(S, len(O), 3, 6 + k, dtype=torch.float64)
        J[..., :3] = torch.eye(3, dtype=torch.float64)
        J[..., 3:6] = -skew(q)  # d(ω x q)/dω = -[q]x
        if k:
            moved = _camera_from_links(T, links[:, 1:], paired, owners[nearest])  # [S, 2k, M, 3]
            J[..., 6:] = ((moved[:, :k] - moved[:, k:]) / (2 * _DIFFERENCE)).permute(0, 2, 3, 1)
        Jf, wf = J.reshape(S, -1, 6 + k), w.repeat_interleave(3, dim=1)
        H = Jf.transpose(1, 2) @ (wf[..., None] * Jf)
        H = H + options.damping * torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2)) + 1e-12 * eye
        g = (Jf.transpose(1, 2) @ (wf * (O - P).reshape(S, -1))[..., None])[..., 0]
        step = torch.linalg.solve(H, g)
        active &= torch.isfinite(step).all(1)
        step = torch.where(active[:, None], step, torch.zeros_like(step))
        R = so3_exp(step[:, 3:6])
        T[:, :3, 3] = (R @ (T[:, :3, 3] - centre)[..., None])[..., 0] + centre + step[:, :3]
        T[:, :3, :3] = R @ T[:, :3, :3]
        if k:
            theta = torch.minimum(torch.maximum(theta + step[:, 6:], kin.lower), kin.upper)
        fitted = torch.sqrt((w * distance**2).sum(1) / w.sum(1).clamp_min(1e-12))
        pairs = torch.where(active, kept, pairs)
        rms = torch.where(active, fitted, rms)
    never = pairs == 0  # as it came, to the bit
    T[never], theta[never] = T0[never], theta0[never]
    return T, theta, pairs, rms
