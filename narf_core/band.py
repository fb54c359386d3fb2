"""Where along a ray the object can be: a band around its surface, so the refiner marches only that.

The refiner renders at known poses: each iteration's ``(T_cam_obj, θ)``. At such a pose the
model's surface points (``NarfModel.sample_points``, in their links' frames) are projected into
the camera. A ray whose pixel has no projected point nearby cannot meet the object and is not
marched at all (its render is empty, as the full march would find); any other ray is marched only
between the nearest and the farthest camera depth of the points near its pixel, widened by
``margin`` metres (the field's surface is not exactly the sampled one). What it leaves out is the
rays that miss the object (most of a mask's box) and, along the others, the stretches away from
the surface; the occupancy grid skips empty space already, so what that saves depends on how tight
the model's grid is (``narf bench track --band-m`` measures it against the whole box).

"Nearby": the image is cut into square cells of about the points' spacing on the surface as seen
at the object's nearest point (:func:`point_spacing`, in pixels), and a ray takes the depths of
the points in its cell and the 8 around it, so that a gap between neighbouring points seldom hides
the surface (where the sampled points are sparser than that, a ray can miss what the full march
finds). All depths are camera z; :func:`ray_band` turns them into distances along each ray with
its ``z_per_t``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from narf_core.geometry import Pinhole, Rays

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel


def point_spacing(model: NarfModel) -> float:
    """Metres between neighbouring surface points: twice the mean nearest-neighbour distance over
    each link's points (0 when the model has none); cached on the model."""
    cached = getattr(model, "_band_spacing_m", None)
    if cached is not None:
        return cached
    distances = []
    for points in model.sample_points.values():
        p = torch.as_tensor(points, dtype=torch.float64)
        if len(p) > 1:
            d = torch.cdist(p, p)
            d.fill_diagonal_(math.inf)
            distances.append(d.min(1).values)
    spacing = 2 * float(torch.cat(distances).mean()) if distances else 0.0
    model._band_spacing_m = spacing
    return spacing


def surface_points(model: NarfModel, T_cam_obj: Tensor, theta: Tensor) -> Tensor:
    """The surface points of every pose ``T_cam_obj [S,4,4]`` at ``θ [S,k]`` in the camera frame ``[S, N, 3]``
    (float64, no gradient)."""
    T_cam_obj, theta = T_cam_obj.detach().double().cpu(), theta.detach().double().cpu()
    links = model.kinematics.link_poses(theta)  # [S, L, 4, 4]
    parts = []
    for i, name in enumerate(model.links):
        p = model.sample_points.get(name)
        if p is not None and len(p):
            p = torch.as_tensor(p, dtype=torch.float64)
            parts.append(p @ links[:, i, :3, :3].transpose(-1, -2) + links[:, i, None, :3, 3])
    if not parts:
        return T_cam_obj.new_zeros(T_cam_obj.shape[0], 0, 3)
    x = torch.cat(parts, dim=1)
    return x @ T_cam_obj[:, :3, :3].transpose(-1, -2) + T_cam_obj[:, None, :3, 3]


def depth_band(
    points_cam: Tensor, camera: Pinhole, rays_cam: Rays, spacing_m: float, margin: float
) -> tuple[Tensor, Tensor] | None:
    """Camera depths ``(near [S, n], far [S, n])`` between which each of the rays ``rays_cam [n]`` can meet
    the surface points ``points_cam [S, N, 3]`` of each pose (see the module docstring); ``near = far = 0``
    where a ray meets nothing. ``None`` when the band cannot be trusted (a pose with points behind or
    on the camera's plane, or no points): march everything."""
    S, N = points_cam.shape[:2]
    z = points_cam[..., 2]
    if N == 0 or not bool((z > 1e-3).all()) or not bool(torch.isfinite(points_cam).all()):
        return None
    grid = _CellGrid(points_cam, camera, spacing_m)
    h, w = grid.shape
    K = camera.K.detach().double().cpu()
    d = rays_cam.directions.detach().double().cpu()
    ray_uv = (d @ K.T)[:, :2] / d[:, 2:3]  # [n, 2]
    z_min, z_max = grid.nearest(z), -grid.nearest(-z)
    rc = torch.floor(ray_uv / grid.cell).long() - grid.lo  # [n, 2]
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < w) & (rc[:, 1] >= 0) & (rc[:, 1] < h) & (d[:, 2] > 0)
    at = (rc[:, 1].clamp(0, h - 1) * w + rc[:, 0].clamp(0, w - 1))[None].expand(S, -1)
    near, far = z_min.gather(1, at) - margin, z_max.gather(1, at) + margin
    hit = inside[None] & torch.isfinite(near) & torch.isfinite(far)
    zero = torch.zeros_like(near)
    return torch.where(hit, near.clamp_min(0), zero), torch.where(hit, far, zero)


class _CellGrid:
    """The image cut into square cells of the points' spacing ``spacing_m`` on the surface as seen at the
    nearest of the points ``points_cam [S, N, 3]`` (camera frame, every z > 0), one grid per pose, with a
    border of one cell."""

    def __init__(self, points_cam: Tensor, camera: Pinhole, spacing_m: float):
        S = points_cam.shape[0]
        z = points_cam[..., 2]
        K = camera.K.detach().double().cpu()
        f = float(max(K[0, 0], K[1, 1]))
        self.cell = max(1.0, spacing_m * f / float(z.min()))  # pixels per cell
        uv = (points_cam @ K.T)[..., :2] / z[..., None]  # [S, N, 2]
        ci = torch.floor(uv / self.cell).long()  # [S, N, 2] cell (column, row) of every point
        self.lo = ci.amin(dim=(0, 1)) - 1
        hi = ci.amax(dim=(0, 1)) + 1
        w, h = int(hi[0] - self.lo[0]) + 1, int(hi[1] - self.lo[1]) + 1
        self.shape, self.poses = (h, w), S
        self.flat = (torch.arange(S)[:, None] * (h * w) + (ci[..., 1] - self.lo[1]) * w + (ci[..., 0] - self.lo[0]))

    def nearest(self, value: Tensor, use: Tensor | None = None, pool: int = 3) -> Tensor:
        """``[S, h*w]``: per cell the least ``value [S, N]`` of the points ``use [S, N]`` (bool; None: all) in
        the ``pool`` x ``pool`` cells around it (``inf`` where there are none)."""
        (h, w), S = self.shape, self.poses
        flat, value = (self.flat, value) if use is None else (self.flat[use], value[use])
        least = torch.full((S * h * w,), math.inf, dtype=torch.float64)
        least = least.scatter_reduce(0, flat.reshape(-1), value.reshape(-1).double(), "amin")
        return -F.max_pool2d(-least.reshape(S, 1, h, w), pool, stride=1, padding=pool // 2).reshape(S, h * w)


def hidden_points(points_cam: Tensor, camera: Pinhole, spacing_m: float, occluders: Tensor) -> Tensor:
    """``[k, N]`` bool: for each of the ``k`` sets of ``occluders [k, N]`` (bool) among the surface points
    ``points_cam [N, 3]`` (camera frame), whether a point of the set lies more than ``spacing_m`` nearer
    the camera in a point's own cell (cells as in :func:`depth_band`): the point is behind another part.
    Not the neighbouring cells too: those would hide the sliver of a part that shows past another's edge
    (a drawer's front under the one above, pulled out). Points behind the camera's plane neither hide nor
    are hidden."""
    k, N = occluders.shape
    front = points_cam[:, 2] > 1e-3
    out = torch.zeros(k, N, dtype=torch.bool)
    if not bool(front.any()) or spacing_m <= 0:
        return out
    grid = _CellGrid(points_cam[front][None], camera, spacing_m)
    z = points_cam[front, 2]
    for j in range(k):
        nearest = grid.nearest(z[None], occluders[j, front][None], pool=1)[0]
        out[j, front] = nearest[grid.flat[0]] < z - spacing_m
    return out


def ray_band(
    model: NarfModel, camera: Pinhole, rays_cam: Rays, T_cam_obj: Tensor, theta: Tensor, margin: float
) -> tuple[Tensor, Tensor] | None:
    """``t_range = (near [S*n], far [S*n])`` for :func:`~narf_core.render.render_rays`: for the rays
    ``rays_cam [n]`` seen from every pose ``T_cam_obj [S,4,4]`` at ``θ [S,k]`` (start-major, like the
    refiner's object-frame rays), distances along each ray around the model's surface; ``None``:
    march the whole box."""
    spacing = point_spacing(model)
    if spacing <= 0:
        return None
    band = depth_band(surface_points(model, T_cam_obj, theta), camera, rays_cam, spacing, margin)
    if band is None:
        return None
    per_t = rays_cam.z_per_t.detach().double().cpu()[None]
    near, far = (b / per_t for b in band)
    device, dtype = rays_cam.origins.device, rays_cam.origins.dtype
    return near.reshape(-1).to(device, dtype), far.reshape(-1).to(device, dtype)
