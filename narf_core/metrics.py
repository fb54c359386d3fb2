"""Evaluation metrics: image error (MSE, PSNR), pose error (ADD, ADD-S), configuration error.

Pure functions. Inputs are numpy arrays or torch tensors (detached, copied to the CPU, computed in
float64); outputs are Python floats or numpy arrays. Units follow docs/design.md §2: metres and radians,
RGB in ``[0, 1]``. ADD and ADD-S are PoseCNN's (Xiang et al. 2018), extended to articulated objects
by moving each link's surface points with FK (docs/design.md §4.5).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from narf_core.checks import check_pose
from narf_core.diameter import PAIRWISE_BLOCK, as_points

ArrayLike = np.ndarray | torch.Tensor | Sequence | float

_ANGULAR_JOINTS = ("revolute", "continuous")


def _array(x: ArrayLike, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be numeric, got {type(x).__name__}") from e


# --- images ---------------------------------------------------------------------------------------


def mse(pred: ArrayLike, target: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Mean squared error of images ``pred``, ``target [..., C]`` over the pixels ``mask`` selects.

    ``mask`` is ``[...]`` (per pixel; every channel counts) or ``[..., C]``; non-zero selects.
    Raises ``ValueError`` on mismatched shapes or a mask that selects nothing.
    """
    p, t = _array(pred, "pred"), _array(target, "target")
    if p.shape != t.shape:
        raise ValueError(f"pred and target must have the same shape, got {list(p.shape)} and {list(t.shape)}")
    err = (p - t) ** 2
    if mask is None:
        if err.size == 0:
            raise ValueError("pred is empty")
        return float(err.mean())
    m = _array(mask, "mask") != 0
    if m.shape == err.shape[:-1]:
        m = m[..., None]
    elif m.shape != err.shape:
        raise ValueError(f"mask must have shape {list(err.shape[:-1])} or {list(err.shape)}, got {list(m.shape)}")
    selected = err[np.broadcast_to(m, err.shape)]
    if selected.size == 0:
        raise ValueError("mask selects no pixels")
    return float(selected.mean())


def psnr_from_mse(mse: ArrayLike) -> float | np.ndarray:
    """PSNR in dB, ``-10 log10(mse)``, for signals in ``[0, 1]``; ``inf`` where ``mse == 0``.

    A scalar gives a float, an array ``[...]`` an array ``[...]``.
    """
    m = _array(mse, "mse")
    if not (m >= 0).all():
        raise ValueError(f"mse must be >= 0 and not NaN, got {m.min()}")
    with np.errstate(divide="ignore"):
        out = -10.0 * np.log10(m)
    return float(out) if out.ndim == 0 else out


# --- poses ----------------------------------------------------------------------------------------


def _camera_points(
    points_per_link: Mapping[str, ArrayLike],
    link_poses: ArrayLike,
    T_cam_obj: ArrayLike,
    links: Sequence[str],
    which: str,
) -> np.ndarray:
    """All links' points ``[m, 3]`` moved into the camera frame by ``T_cam_obj @ T_obj_link``."""
    poses = _array(link_poses, f"link_poses_{which}")
    if poses.shape != (len(links), 4, 4):
        expected = f"[{len(links)}, 4, 4] (one per link)"
        raise ValueError(f"link_poses_{which} must have shape {expected}, got {list(poses.shape)}")
    T_cam_obj = check_pose(_array(T_cam_obj, f"T_cam_obj_{which}"), f"T_cam_obj_{which}")
    index = {name: i for i, name in enumerate(links)}
    moved = []
    for name, points in points_per_link.items():
        if name not in index:
            raise ValueError(f"points_per_link has link {name!r}, which is not in links {list(links)}")
        T = T_cam_obj @ poses[index[name]]
        moved.append(as_points(points, f"points_per_link[{name!r}]") @ T[:3, :3].T + T[:3, 3])
    out = np.concatenate(moved) if moved else np.zeros((0, 3))
    if len(out) == 0:
        raise ValueError("points_per_link holds no points")
    return out


def add(
    points_per_link: Mapping[str, ArrayLike],
    link_poses_true: ArrayLike,
    T_cam_obj_true: ArrayLike,
    link_poses_est: ArrayLike,
    T_cam_obj_est: ArrayLike,
    links: Sequence[str],
) -> float:
    """ADD: the mean distance (m) between each surface point under the true and the estimated state.

    ``points_per_link``: ``{link: [m, 3]}`` in the link's frame; ``link_poses_* [n_links, 4, 4]``:
    ``T_obj_link`` from FK at the true / estimated configuration, in the order of ``links``;
    ``T_cam_obj_* [4, 4]``. Every point counts once, so links weigh by their number of points.
    """
    true = _camera_points(points_per_link, link_poses_true, T_cam_obj_true, links, "true")
    est = _camera_points(points_per_link, link_poses_est, T_cam_obj_est, links, "est")
    return float(np.linalg.norm(true - est, axis=-1).mean())


def add_s(
    points_per_link: Mapping[str, ArrayLike],
    link_poses_true: ArrayLike,
    T_cam_obj_true: ArrayLike,
    link_poses_est: ArrayLike,
    T_cam_obj_est: ArrayLike,
    links: Sequence[str],
) -> float:
    """ADD-S: the mean over true points of the distance (m) to the closest estimated point.

    Same arguments as :func:`add`; blind to symmetries (and, over the union of all links, to
    which link a point belongs). Uses scipy's KD tree when scipy is installed, else an exact
    brute-force search.
    """
    true = _camera_points(points_per_link, link_poses_true, T_cam_obj_true, links, "true")
    est = _camera_points(points_per_link, link_poses_est, T_cam_obj_est, links, "est")
    return float(_nearest_distances(true, est).mean())


def _nearest_distances(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``[q]``: for each of ``queries [q, 3]`` the distance to its nearest neighbour in ``points [p, 3]``."""
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        return _nearest_distances_brute(queries, points)
    return cKDTree(points).query(queries)[0]


def _nearest_distances_brute(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact nearest-neighbour distances in blocks of queries that keep memory bounded."""
    block = max(1, PAIRWISE_BLOCK // len(points))
    out = np.empty(len(queries))
    for start in range(0, len(queries), block):
        q = queries[start : start + block]
        out[start : start + block] = np.sqrt(((q[:, None, :] - points[None]) ** 2).sum(-1).min(1))
    return out


# --- configuration --------------------------------------------------------------------------------


def joint_errors(theta_true: ArrayLike, theta_est: ArrayLike, joint_types: Sequence[str]) -> np.ndarray:
    """Absolute per-joint error ``[..., k]`` in each joint's unit (radians or metres).

    ``theta_* [..., k]``; ``joint_types [k]`` are URDF types. Continuous joints take the wrapped
    angle difference, in ``[0, pi]``.
    """
    true, est = _array(theta_true, "theta_true"), _array(theta_est, "theta_est")
    types = list(joint_types)
    if true.shape != est.shape or true.ndim == 0 or true.shape[-1] != len(types):
        raise ValueError(
            f"theta_true and theta_est must both have shape [..., {len(types)}] (one per joint type), "
            f"got {list(true.shape)} and {list(est.shape)}"
        )
    unknown = sorted({t for t in types if t not in ("revolute", "continuous", "prismatic")})
    if unknown:
        raise ValueError(f"joint_types must be revolute, continuous or prismatic, got {unknown}")
    diff = est - true
    wrapped = np.abs(np.remainder(diff + math.pi, 2 * math.pi) - math.pi)
    return np.where(np.array([t == "continuous" for t in types]), wrapped, np.abs(diff))


def success_rates(add_values: ArrayLike, diameter: float) -> dict[str, float]:
    """Fractions of estimates with ADD below 1 cm and below a tenth of the object's ``diameter`` (m)."""
    values = _array(add_values, "add_values").reshape(-1)
    if values.size == 0:
        raise ValueError("add_values is empty")
    if not np.isfinite(values).all():
        raise ValueError("add_values must be finite")
    if not (math.isfinite(diameter) and diameter > 0):
        raise ValueError(f"diameter must be a positive number of metres, got {diameter}")
    return {"add<1cm": float((values < 0.01).mean()), "add<0.1d": float((values < 0.1 * diameter).mean())}
