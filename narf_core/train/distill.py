"""Stage 2: distil the part composition into one configuration field F(x, d, θ) (docs/design.md §4.3).

The paper renders 5000 composited images (cameras on a 1 m sphere, θ uniform within the limits)
and trains on them. Here the same distribution is *streamed*: every step draws fresh cameras and
configurations, casts rays from each camera through random points of the object box (so every ray
crosses the object's box and none is wasted), renders them with the composition (the teacher) and
fits the configuration field (the student) to its colour, opacity and depth. ``composites=N``
instead pre-renders a fixed pool of N views, as the paper does.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from narf_core.geometry import Rays, look_at
from narf_core.train.parts import RayTargets


def random_views(
    n: int, center: Tensor, distance: tuple[float, float], generator: torch.Generator
) -> Tensor:
    """``T_obj_cam [n,4,4]``: cameras on a sphere shell around ``center`` looking at it."""
    u = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    z = 2 * u[:, 0] - 1
    phi = 2 * math.pi * u[:, 1]
    r = distance[0] + (distance[1] - distance[0]) * u[:, 2]
    direction = torch.stack([(1 - z**2).sqrt() * phi.cos(), (1 - z**2).sqrt() * phi.sin(), z], dim=-1)
    eye = center.double() + r[:, None] * direction
    up = torch.where(z.abs()[:, None] > 0.9, torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return look_at(eye, center.double().expand_as(eye), up).float()


def rays_through_box(T_obj_cam: Tensor, aabb: Tensor, rays_per_view: int, generator: torch.Generator) -> tuple[Rays, Tensor]:
    """Rays (object frame) from each camera through uniform points of ``aabb``; and each ray's view index."""
    n_views = T_obj_cam.shape[0]
    view = torch.arange(n_views).repeat_interleave(rays_per_view)
    target = aabb[0] + (aabb[1] - aabb[0]) * torch.rand(len(view), 3, generator=generator)
    origin = T_obj_cam[view, :3, 3]
    d = target - origin
    d = d / d.norm(dim=-1, keepdim=True)
    cam_z = T_obj_cam[view, :3, 2]
    return Rays(origin, d, (d * cam_z).sum(-1)), view


@torch.no_grad()
def composite_rays(
    teacher,
    render,
    aabb: Tensor,
    lower: Tensor,
    upper: Tensor,
    *,
    n_views: int,
    rays_per_view: int,
    distance: tuple[float, float],
    generator: torch.Generator,
) -> tuple[RayTargets, Tensor]:
    """A batch rendered by ``teacher``: targets for ``n_views * rays_per_view`` rays, and their θ ``[n,k]``.

    ``render(field, rays, theta [n,k]) -> RenderOutput`` with rgb, opacity and depth.
    """
    center = (aabb[0] + aabb[1]) / 2
    T_obj_cam = random_views(n_views, center, distance, generator)
    rays, view = rays_through_box(T_obj_cam, aabb, rays_per_view, generator)
    theta_view = lower + (upper - lower) * torch.rand(n_views, len(lower), generator=generator)
    theta = theta_view[view]
    out = render(teacher, rays, theta)
    targets = RayTargets(rays, out.rgb, out.opacity, torch.where(out.opacity > 0.5, out.depth / out.opacity.clamp_min(1e-6), 0.0))
    return targets, theta
