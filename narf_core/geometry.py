"""Rotations, rigid poses, the pinhole camera and its rays.

Conventions (docs/design.md §2): metres and radians; quaternions are ``[qx, qy, qz, qw]`` (ROS order);
poses are 4x4 matrices named ``T_<to>_<from>``; twists are ``xi = [rho (3), omega (3)]`` with the
translation part first; the camera is OpenCV's (x right, y down, z forward) with pixel ``(u, v)``
centred at ``(u + 0.5, v + 0.5)``.

Every function takes any leading batch shape ``[...]`` and keeps the dtype it is given. The exp and
log maps switch to Taylor series near zero rotation, and ``so3_log`` goes through a quaternion, so
values *and* gradients stay finite at zero rotation and near pi.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

_SMALL_ANGLE_SQ = 1e-4  # below this squared angle the series terms are used


def skew(v: Tensor) -> Tensor:
    """``[..., 3] -> [..., 3, 3]``: the matrix ``[v]x`` with ``[v]x @ w == cross(v, w)``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def _angle_terms(theta_sq: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3`` from ``t^2``, finite at 0."""
    small = theta_sq < _SMALL_ANGLE_SQ
    t_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    t = t_sq.sqrt()
    s, c = torch.sin(t), torch.cos(t)
    a = torch.where(small, 1 - theta_sq / 6 + theta_sq**2 / 120, s / t)
    b = torch.where(small, 0.5 - theta_sq / 24 + theta_sq**2 / 720, (1 - c) / t_sq)
    cc = torch.where(small, 1 / 6 - theta_sq / 120 + theta_sq**2 / 5040, (t - s) / (t_sq * t))
    return a, b, cc


def so3_exp(omega: Tensor) -> Tensor:
    """Axis-angle ``[..., 3]`` to rotation matrix ``[..., 3, 3]`` (Rodrigues, series near 0)."""
    a, b, _ = _angle_terms((omega * omega).sum(-1))
    k = skew(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(k)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(R: Tensor) -> Tensor:
    """Rotation matrix ``[..., 3, 3]`` to axis-angle ``[..., 3]``, angle in ``[0, pi]``."""
    return quaternion_to_axis_angle(matrix_to_quaternion(R))


def quaternion_to_axis_angle(q: Tensor) -> Tensor:
    """Quaternion ``[..., 4]`` (xyzw) to axis-angle ``[..., 3]``; finite gradient at the identity."""
    q = q * torch.where(q[..., 3:] < 0, -1.0, 1.0).to(q.dtype)  # w >= 0: angle in [0, pi]
    v, w = q[..., :3], q[..., 3]
    n_sq = (v * v).sum(-1)
    small = n_sq < _SMALL_ANGLE_SQ
    n = torch.where(small, torch.ones_like(n_sq), n_sq).sqrt()
    # 2 atan2(n, w) / n, with its series 2/w (1 - n^2 / (3 w^2)) where n is tiny (then w ~ 1).
    w_safe = torch.where(small, w, torch.ones_like(w))
    scale = torch.where(small, 2 / w_safe * (1 - n_sq / (3 * w_safe**2)), 2 * torch.atan2(n, w) / n)
    return v * scale[..., None]


def axis_angle_to_quaternion(omega: Tensor) -> Tensor:
    """Axis-angle ``[..., 3]`` to unit quaternion ``[..., 4]`` (xyzw)."""
    theta_sq = (omega * omega).sum(-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    t = torch.where(small, torch.ones_like(theta_sq), theta_sq).sqrt()
    half_sinc = torch.where(small, 0.5 - theta_sq / 48, torch.sin(t / 2) / t)
    w = torch.where(small, 1 - theta_sq / 8, torch.cos(t / 2))
    return torch.cat([omega * half_sinc[..., None], w[..., None]], dim=-1)


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Rotation matrix ``[..., 3, 3]`` to unit quaternion ``[..., 4]`` (xyzw, ``w >= 0``).

    Shepperd's method: of the four candidate formulas the one with the largest denominator is
    used, so the result (and its gradient) stays well conditioned for every rotation.
    """
    m = R
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z; clamped so the unused branches never take sqrt of a negative.
    sq = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    root = sq.clamp_min(1e-12).sqrt()  # 2 |q_i|
    d21, d12 = m[..., 2, 1], m[..., 1, 2]
    d02, d20 = m[..., 0, 2], m[..., 2, 0]
    d10, d01 = m[..., 1, 0], m[..., 0, 1]
    cands = torch.stack(
        [
            torch.stack([d21 - d12, d02 - d20, d10 - d01, sq[..., 0]], dim=-1) / root[..., 0:1],
            torch.stack([sq[..., 1], d01 + d10, d02 + d20, d21 - d12], dim=-1) / root[..., 1:2],
            torch.stack([d01 + d10, sq[..., 2], d12 + d21, d02 - d20], dim=-1) / root[..., 2:3],
            torch.stack([d02 + d20, d12 + d21, sq[..., 3], d10 - d01], dim=-1) / root[..., 3:4],
        ],
        dim=-2,
    ) / 2
    best = sq.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return q * torch.where(q[..., 3:] < 0, -1.0, 1.0).to(q.dtype)


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Quaternion ``[..., 4]`` (xyzw, normalised here) to rotation matrix ``[..., 3, 3]``."""
    q = q / q.norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def make_pose(R: Tensor, t: Tensor) -> Tensor:
    """Rotation ``[..., 3, 3]`` and translation ``[..., 3]`` to a pose ``[..., 4, 4]``."""
    bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat([torch.cat([R, t[..., None]], dim=-1), bottom], dim=-2)


def pose_from_position_quaternion(position: Tensor, quaternion: Tensor) -> Tensor:
    """Position ``[..., 3]`` and quaternion ``[..., 4]`` (xyzw) to a pose ``[..., 4, 4]``."""
    return make_pose(quaternion_to_matrix(quaternion), position)


def pose_to_position_quaternion(T: Tensor) -> tuple[Tensor, Tensor]:
    """Pose ``[..., 4, 4]`` to position ``[..., 3]`` and quaternion ``[..., 4]`` (xyzw, ``w >= 0``)."""
    return T[..., :3, 3], matrix_to_quaternion(T[..., :3, :3])


def invert_pose(T: Tensor) -> Tensor:
    """``T_a_b [..., 4, 4] -> T_b_a``, using the rotation's transpose."""
    R_t = T[..., :3, :3].transpose(-1, -2)
    return make_pose(R_t, -(R_t @ T[..., :3, 3:4])[..., 0])


def transform_points(T: Tensor, x: Tensor) -> Tensor:
    """Apply ``T [..., 4, 4]`` to points ``x [..., 3]`` (batch shapes broadcast)."""
    return (T[..., :3, :3] @ x[..., None])[..., 0] + T[..., :3, 3]


def rotate_vectors(T: Tensor, v: Tensor) -> Tensor:
    """Apply the rotation of ``T [..., 4, 4]`` (or ``R [..., 3, 3]``) to vectors ``v [..., 3]``."""
    return (T[..., :3, :3] @ v[..., None])[..., 0]


def box_corners(aabb: Tensor) -> Tensor:
    """``[2,3] -> [8,3]`` the corners of the axis-aligned box ``aabb`` (min, max)."""
    sel = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], device=aabb.device)
    return torch.where(sel.bool(), aabb[1], aabb[0])


def se3_exp(xi: Tensor) -> Tensor:
    """Twist ``xi = [rho, omega] [..., 6]`` to a pose ``[..., 4, 4]`` (series near 0)."""
    rho, omega = xi[..., :3], xi[..., 3:]
    a, b, c = _angle_terms((omega * omega).sum(-1))
    k = skew(omega)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(k)
    R = eye + a[..., None, None] * k + b[..., None, None] * k2
    V = eye + b[..., None, None] * k + c[..., None, None] * k2
    return make_pose(R, (V @ rho[..., None])[..., 0])


def se3_log(T: Tensor) -> Tensor:
    """Pose ``[..., 4, 4]`` to twist ``[rho, omega] [..., 6]``; the inverse of :func:`se3_exp`."""
    omega = so3_log(T[..., :3, :3])
    theta_sq = (omega * omega).sum(-1)
    a, b, _ = _angle_terms(theta_sq)
    small = theta_sq < _SMALL_ANGLE_SQ
    t_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    # V^-1 = I - 1/2 [w]x + D [w]x^2 with D = (1 - A / (2B)) / t^2, series 1/12 + t^2/720 near 0.
    d = torch.where(small, 1 / 12 + theta_sq / 720 + theta_sq**2 / 30240, (1 - a / (2 * b)) / t_sq)
    k = skew(omega)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(k)
    V_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    rho = (V_inv @ T[..., :3, 3:4])[..., 0]
    return torch.cat([rho, omega], dim=-1)


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """``T_world_cam [..., 4, 4]`` of an OpenCV camera at ``eye`` looking at ``target``.

    The camera's y axis (down in the image) points away from ``up`` ``[..., 3]``; ``up`` must not
    be parallel to the viewing direction.
    """
    z = target - eye
    z = z / z.norm(dim=-1, keepdim=True)
    x = torch.linalg.cross(z, up.expand_as(z))
    x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x)
    return make_pose(torch.stack([x, y, z], dim=-1), eye)


@dataclass
class Rays:
    """A bundle of rays, nerfstudio-style.

    ``origins [n, 3]``, unit ``directions [n, 3]``, and ``z_per_t [n]``: the camera z-depth of
    the point at unit distance along each ray, so that z-depth ``= t * z_per_t``.
    """

    origins: Tensor
    directions: Tensor
    z_per_t: Tensor

    def __len__(self) -> int:
        return self.origins.shape[0]

    def __getitem__(self, index) -> Rays:
        return Rays(self.origins[index], self.directions[index], self.z_per_t[index])

    def transform(self, T_to_from: Tensor) -> Rays:
        """These rays expressed in another frame; ``T_to_from [4, 4]`` or ``[n, 4, 4]``."""
        return Rays(
            transform_points(T_to_from, self.origins),
            rotate_vectors(T_to_from, self.directions),
            self.z_per_t,
        )


@dataclass(frozen=True)
class Pinhole:
    """An undistorted pinhole camera: intrinsics ``K [3, 3]`` and the image size in pixels."""

    K: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if tuple(self.K.shape) != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {tuple(self.K.shape)}")

    @staticmethod
    def primesense(width: int, height: int, dtype=torch.float32) -> Pinhole:
        """A Primesense-Carmine-like camera (fx = fy = 536.5 at 640x480) scaled to ``width`` x ``height``."""
        fx, fy = 536.5 * width / 640.0, 536.5 * height / 480.0
        K = torch.tensor([[fx, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
        return Pinhole(K, width, height)

    def scaled(self, width: int, height: int) -> Pinhole:
        """The same field of view at another resolution."""
        sx, sy = width / self.width, height / self.height
        K = self.K.clone()
        K[0] *= sx
        K[1] *= sy
        return Pinhole(K, width, height)

    def pixel_grid(self, device=None) -> Tensor:
        """All pixels ``[height * width, 2]`` as integer ``(u, v)``, row-major (v outer)."""
        v, u = torch.meshgrid(
            torch.arange(self.height, device=device), torch.arange(self.width, device=device), indexing="ij"
        )
        return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)

    def rays(self, pixels: Tensor | None = None) -> Rays:
        """Rays in the camera frame through pixel centres; ``pixels [n, 2]`` as ``(u, v)``, default all."""
        K = self.K
        if pixels is None:
            pixels = self.pixel_grid(K.device)
        uv = pixels.to(K.dtype) + 0.5
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * (uv[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        d = torch.stack([x, y, torch.ones_like(x)], dim=-1)
        norm = d.norm(dim=-1)
        return Rays(torch.zeros_like(d), d / norm[:, None], 1 / norm)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-frame points ``[..., 3]`` to continuous pixel coordinates ``[..., 2]`` and z ``[...]``.

        Pixel ``(u, v)`` covers ``[u, u + 1) x [v, v + 1)``; its centre projects to ``(u + 0.5, v + 0.5)``.
        """
        z = points[..., 2]
        uvw = (self.K.to(points.dtype) @ points[..., None])[..., 0]
        return uvw[..., :2] / z[..., None], z
