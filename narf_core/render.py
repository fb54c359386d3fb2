"""Volume rendering: the entry points, on top of occupancy, sampling and compositing (nerfacc's split).

:func:`render_rays` renders rays in the field's frame, :func:`render_image` an image of the object at a
pose, over the pixels :func:`box_pixels` says can see its box. They are built from
:mod:`narf_core.occupancy` (which points may hold density: :class:`OccupancyGrid` and the
:class:`Occupancy` protocol), :mod:`narf_core.sampling` (:func:`~narf_core.sampling.march`: which
samples along each ray are evaluated) and :mod:`narf_core.compositing`
(:func:`~narf_core.compositing.composite`: colour, depth and opacity from those samples). The
renderer never imports a concrete field: a *field* is any callable ``(x [n,3], d [n,3], theta [n,k]
| None) -> (sigma [n], rgb [n,3])`` (docs/design.md §5); if it also has ``density_only(x, theta) ->
sigma [n]``, renders without colour use it. Gradients reach the field, ``theta`` and the ray origins
and directions; sample positions ``t`` are not differentiated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from narf_core.compositing import OUTPUTS, RenderOutput, check_outputs, composite, composite_marching, volume_render_weights
from narf_core.geometry import Pinhole, Rays, box_corners, invert_pose, transform_points
from narf_core.occupancy import Field, Occupancy, OccupancyGrid, density_fn
from narf_core.sampling import Marcher, Samples, clip_box, march, ray_aabb

__all__ = [
    "OUTPUTS", "Field", "Occupancy", "OccupancyGrid", "RenderOutput", "Samples", "box_pixels", "composite", "march",
    "ray_aabb", "render_image", "render_rays", "volume_render_weights",
]


_TRANSMITTANCE_EPS = 1e-3  # render_rays' defaults: a ray stops below this transmittance ...
_MAX_SAMPLES = 1024  # ... or after this many intervals


def render_rays(
    field: Field,
    rays: Rays,
    aabb: Tensor,
    *,
    theta: Tensor | None = None,
    grid: Occupancy | None = None,
    step: float,
    outputs: Sequence[str] = ("rgb",),
    background: float | Tensor = 0.0,
    transmittance_eps: float = _TRANSMITTANCE_EPS,
    max_samples: int = _MAX_SAMPLES,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    t_range: tuple[Tensor, Tensor] | None = None,
) -> RenderOutput:
    """Volume-render ``rays`` (in the field's frame) through ``field`` inside the box ``aabb [2,3]``.

    Args:
        field: ``(x [m,3], d [m,3], theta [m,k] | None) -> (sigma [m], rgb [m,3])``.
        rays: ``[n]`` rays; ``z_per_t`` converts distance along a ray into camera z-depth.
        theta: ``[k]`` for all rays or ``[n,k]`` per ray; ``None`` for a part field.
        grid: an :class:`Occupancy` (an :class:`OccupancyGrid`, or the part composition); ``None``: all.
        step: interval length in metres (e.g. the box diagonal / 256).
        outputs: any of ``"rgb"``, ``"depth"``, ``"opacity"``; the others come back ``None``.
        background: colour (a float or ``[3]``) behind the object, composited by ``1 - opacity``.
        transmittance_eps: a ray stops once its transmittance falls below this.
        max_samples: at most this many intervals per ray (longer rays get longer intervals).
        jitter: sample each interval at one random offset per ray (training) instead of its middle.
        t_range: ``(near [n], far [n])`` distances along each ray outside which nothing is marched
            (a band around an expected surface); a ray whose band misses the box is empty. The
            interval lattice stays anchored at ``t = 0``, so inside the band the samples are those
            the full march takes there (while a ray's box segment fits in ``max_samples`` steps).

    Without gradients the rays are marched and composited in one pass
    (:func:`~narf_core.compositing.composite_marching`). When gradients are needed (grad mode on,
    and the rays, ``theta`` or the field's parameters require them), the march runs without a
    graph, on densities only, to find each ray's samples (:meth:`~narf_core.sampling.Marcher.samples`);
    then the field is evaluated once on all of them and composited in one differentiable pass
    (:func:`~narf_core.compositing.composite`): the same samples and the same result, with one small
    autograd graph instead of one per marching round.
    """
    outputs = check_outputs(outputs)
    marcher = Marcher(
        len(rays), grid=grid, theta=theta, step=step, max_samples=max_samples, transmittance_eps=transmittance_eps,
        generator=generator if jitter else None, t_range=t_range,
    )
    if not _needs_grad(field, rays, marcher.theta):
        return composite_marching(field, rays, aabb, marcher, outputs=outputs, background=background)
    samples = marcher.samples(density_fn(field), rays, aabb)
    return composite(field, rays, samples, theta=marcher.theta, outputs=outputs, background=background)


def march_samples(field: Field, rays: Rays, aabb: Tensor, *, theta: Tensor | None = None, grid: Occupancy | None = None,
                  step: float, t_range: tuple[Tensor, Tensor] | None = None) -> Samples:
    """The samples a differentiable :func:`render_rays` of these arguments (and its default stopping rules)
    composites, marched on densities without a graph: for a caller that differentiates the compositing itself."""
    marcher = Marcher(len(rays), grid=grid, theta=theta, step=step, max_samples=_MAX_SAMPLES,
                      transmittance_eps=_TRANSMITTANCE_EPS, t_range=t_range)
    return marcher.samples(density_fn(field), rays, aabb)


def _needs_grad(field, rays: Rays, theta: Tensor | None) -> bool:
    """Whether a render must be differentiable: grad mode on and any input or parameter requiring it
    (a field without ``parameters()`` is assumed to have some)."""
    if not torch.is_grad_enabled():
        return False
    if rays.origins.requires_grad or rays.directions.requires_grad or (theta is not None and theta.requires_grad):
        return True
    parameters = getattr(field, "parameters", None)
    return parameters is None or any(p.requires_grad for p in parameters())


# --------------------------------------------------------------------------------------------
# Images


def box_pixels(camera: Pinhole, T_cam_obj: Tensor, aabb: Tensor) -> Tensor:
    """Pixels ``[m, 2]`` (``(u, v)``, row-major) whose rays can meet the box ``aabb [2,3]`` (object frame).

    The bounding rectangle of the projected corners; every pixel when the box reaches behind the
    camera's plane; none when it lies entirely behind it.
    """
    K = camera.K
    corners = transform_points(T_cam_obj.to(K.dtype), box_corners(aabb.to(K.dtype)))
    z = corners[:, 2]
    if bool((z <= 0).all()):
        return torch.zeros(0, 2, dtype=torch.long, device=K.device)
    u0, v0, u1, v1 = 0, 0, camera.width, camera.height
    if bool((z > 1e-9).all()):
        uv, _ = camera.project(corners)
        lo, hi = uv.amin(0), uv.amax(0)
        u0, v0 = max(u0, math.floor(float(lo[0]))), max(v0, math.floor(float(lo[1])))
        u1, v1 = min(u1, math.ceil(float(hi[0]))), min(v1, math.ceil(float(hi[1])))
    if u1 <= u0 or v1 <= v0:
        return torch.zeros(0, 2, dtype=torch.long, device=K.device)
    v, u = torch.meshgrid(torch.arange(v0, v1, device=K.device), torch.arange(u0, u1, device=K.device), indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def _empty_images(camera: Pinhole, outputs: Sequence[str], background: Tensor) -> dict[str, Tensor]:
    H, W = camera.height, camera.width
    images: dict[str, Tensor] = {}
    if "rgb" in outputs:
        images["rgb"] = background.to(torch.float32).expand(H, W, 3).clone()
    if "depth" in outputs:
        images["depth"] = torch.zeros(H, W, device=background.device)
    if "opacity" in outputs:
        images["opacity"] = torch.zeros(H, W, device=background.device)
    return images


def _fill_images(images: dict[str, Tensor], flat_index: Tensor, out: RenderOutput, depth_min_opacity: float) -> None:
    """Write per-ray results into ``[H,W,...]`` images at ``flat_index`` (``v * W + u``)."""
    if "rgb" in images:
        images["rgb"].view(-1, 3)[flat_index] = out.rgb.to(torch.float32)
    if "opacity" in images:
        images["opacity"].view(-1)[flat_index] = out.opacity.to(torch.float32)
    if "depth" in images:
        opaque = out.opacity > depth_min_opacity
        z = torch.where(opaque, out.depth / out.opacity.clamp_min(depth_min_opacity), 0)
        images["depth"].view(-1)[flat_index] = z.to(torch.float32)


def _object_rays(camera: Pinhole, pixels: Tensor, T_obj_cam: Tensor) -> Rays:
    """The rays of ``pixels [m,2]`` in the object frame (one shared origin, one small matmul)."""
    rays = camera.rays(pixels)
    origins = T_obj_cam[:3, 3].expand(pixels.shape[0], 3)
    return Rays(origins, rays.directions @ T_obj_cam[:3, :3].T, rays.z_per_t)


def render_image(
    field: Field,
    camera: Pinhole,
    T_cam_obj: Tensor,
    *,
    theta: Tensor | None = None,
    aabb: Tensor,
    grid: Occupancy | None = None,
    outputs: Sequence[str] = ("rgb",),
    step: float,
    background: float | Tensor = 0.0,
    transmittance_eps: float = 1e-3,
    chunk: int = 1 << 15,
) -> dict[str, Tensor]:
    """Render the field at pose ``T_cam_obj [4,4]`` (and ``theta [k]``) into float32 images.

    Only the pixels of the box's projection are marched (``chunk`` rays at a time). Returns the
    asked outputs: ``rgb [H,W,3]`` (over ``background``), ``opacity [H,W]``, and ``depth [H,W]``:
    the surface z-depth (metres, opacity-normalised) where opacity > 0.5, else 0 (no return).
    """
    outputs = check_outputs(outputs)
    if theta is not None and theta.dim() != 1:
        raise ValueError(f"render_image takes one configuration theta [k], got shape {tuple(theta.shape)}")
    bg = torch.as_tensor(background, dtype=torch.float32, device=camera.K.device).expand(3)
    images = _empty_images(camera, outputs, bg)
    box = clip_box(aabb, grid, theta)
    if box is None:
        return images
    pixels = box_pixels(camera, T_cam_obj, box)
    if pixels.shape[0] == 0:
        return images
    flat_index = pixels[:, 1] * camera.width + pixels[:, 0]
    T_obj_cam = invert_pose(T_cam_obj.to(camera.K.dtype))
    for s in range(0, pixels.shape[0], chunk):
        rays = _object_rays(camera, pixels[s : s + chunk], T_obj_cam)
        out = render_rays(
            field, rays, aabb, theta=theta, grid=grid, step=step, outputs=tuple(set(outputs) | {"opacity"}),
            background=background, transmittance_eps=transmittance_eps,
        )
        _fill_images(images, flat_index[s : s + chunk], out, 0.5)
    return images

