"""Compositing: colour, depth and opacity of rays from their samples (nerfacc's ``volrend`` side).

:func:`composite` evaluates a field once at given :class:`~narf_core.sampling.Samples` and composites
them per ray, differentiably in the field, ``theta`` and the rays' origins and directions (through
the sample positions ``o + t d``). :func:`composite_marching` composites while a
:class:`~narf_core.sampling.Marcher` marches, round by round (no gradients needed: each sample is
evaluated once, with colour, and a ray's weights continue from its optical depth so far).

Stability (docs/design.md §5): ``alpha = -expm1(-sigma * delta)``; transmittance is ``exp`` of minus the
*exclusive* (shifted) cumulative optical depth, never "cumsum minus the current term"; interval
lengths are >= 0 by construction; opacity is ``-expm1(-total optical depth)``. All finite for
``sigma`` up to 1e6 and beyond, ``delta`` down to 0, rays grazing the box or starting inside it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from narf_core.geometry import Rays
from narf_core.occupancy import Field, density_fn
from narf_core.sampling import Marcher, Round, Samples, ray_theta, sample_theta

OUTPUTS = ("rgb", "depth", "opacity")


@dataclass
class RenderOutput:
    """Per-ray results; an output that was not asked for is ``None``.

    ``rgb [n,3]``: colour composited over the background. ``opacity [n]``: ``1 - T`` at the end
    of the ray. ``depth [n]``: the *opacity-weighted* expected camera z-depth ``sum_i w_i z_i``
    (metres; 0 for an empty ray); divide by ``opacity`` for the surface depth. ``n_samples``:
    the number of field evaluations.
    """

    rgb: Tensor | None
    depth: Tensor | None
    opacity: Tensor | None
    n_samples: int = 0


def check_outputs(outputs: Sequence[str]) -> tuple[str, ...]:
    """``outputs`` as a tuple; ``ValueError`` unless it is a non-empty subset of :data:`OUTPUTS`."""
    outputs = tuple(outputs)
    bad = [o for o in outputs if o not in OUTPUTS]
    if not outputs or bad:
        raise ValueError(f"outputs must be a non-empty subset of {OUTPUTS}, got {outputs}")
    return outputs


def volume_render_weights(sigma: Tensor, deltas: Tensor, tau_in: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Compositing weights in the padded layout.

    Args:
        sigma: ``[n_rays, n_samples]`` densities (>= 0; 0 for padding).
        deltas: ``[n_rays, n_samples]`` interval lengths (>= 0).
        tau_in: ``[n_rays]`` optical depth accumulated before these samples (default 0).

    Returns ``weights [n_rays, n_samples]`` (``T_i * alpha_i``) and ``transmittance
    [n_rays, n_samples]`` (``T_i``, before sample ``i``), with ``alpha_i = -expm1(-sigma_i
    delta_i)`` and ``T_i = exp(-(tau_in + sum_{j<i} sigma_j delta_j))`` from a shifted cumsum.
    """
    return _weights_from_optical_depth(sigma * deltas, tau_in)


def _weights_from_optical_depth(tau: Tensor, tau_in: Tensor | None) -> tuple[Tensor, Tensor]:
    """:func:`volume_render_weights` from the per-sample optical depths ``tau = sigma * delta``."""
    excl = torch.cat([tau.new_zeros(tau.shape[0], 1), tau[:, :-1].cumsum(1)], dim=1)
    if tau_in is not None:
        excl = excl + tau_in[:, None]
    transmittance = torch.exp(-excl)
    return transmittance * -torch.expm1(-tau), transmittance


def _packed_weights(tau: Tensor, row: Tensor, slot: Tensor, n_rows: int, tau_in: Tensor | None) -> Tensor:
    """Weights ``[s]`` of packed samples (optical depth ``tau [s]``, ray row and slot in ascending ``t``),
    through the padded ``[n_rows, most slots]`` layout."""
    padded = tau.new_zeros(n_rows, int(slot.max()) + 1).index_put((row, slot), tau)
    return _weights_from_optical_depth(padded, tau_in)[0][row, slot]


def _over_background(rgb: Tensor, opacity: Tensor, background: float | Tensor) -> Tensor:
    """Composite ``rgb [n, 3]`` (premultiplied by ``opacity [n]``) over a constant background colour."""
    return rgb + (1 - opacity)[:, None] * torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device).expand(3)


def composite(
    field: Field,
    rays: Rays,
    samples: Samples,
    *,
    theta: Tensor | None = None,
    outputs: Sequence[str] = ("rgb",),
    background: float | Tensor = 0.0,
) -> RenderOutput:
    """Evaluate ``field`` once at ``samples`` of ``rays`` and composite them per ray.

    ``theta``: ``[k]`` for all rays, ``[n,k]`` per ray, or ``None``; ``outputs`` and ``background``
    as in :func:`narf_core.render.render_rays`. Differentiable in the field, ``theta`` and the rays
    (through the sample positions ``o + t d``); the samples' ``t`` and ``delta`` are constants. A
    field evaluated without colour uses its ``density_only`` where it has one.
    """
    outputs = check_outputs(outputs)
    theta, per_ray = ray_theta(theta, len(rays))
    n, dtype = len(rays), rays.origins.dtype
    ray, t, delta = samples.ray, samples.t.to(dtype), samples.delta.to(dtype)
    zero = (rays.origins[:, 0] + rays.directions[:, 0]) * 0  # [n] zeros in the graph, so backward() always works
    tau_total, rgb_out, depth_out = zero, zero[:, None].expand(n, 3), zero
    if ray.numel() > 0:
        rays_hit, row, counts = torch.unique_consecutive(ray, return_inverse=True, return_counts=True)
        slot = torch.arange(ray.shape[0], device=ray.device) - (counts.cumsum(0) - counts)[row]
        d = rays.directions[ray]
        x = rays.origins[ray] + t[:, None] * d
        th = sample_theta(theta, per_ray, ray)
        if "rgb" in outputs:
            sigma, rgb = field(x, d, th)
        else:
            sigma, rgb = density_fn(field)(x, th), None
        tau = sigma.to(dtype) * delta
        w = _packed_weights(tau, row, slot, rays_hit.shape[0], None)
        tau_total = zero.index_add(0, ray, tau)
        if "rgb" in outputs:
            rgb_out = rgb_out.index_add(0, ray, w[:, None] * rgb.to(dtype))
        if "depth" in outputs:
            depth_out = zero.index_add(0, ray, w * t * rays.z_per_t[ray].to(dtype))
    opacity = -torch.expm1(-tau_total)
    if "rgb" in outputs:
        rgb_out = _over_background(rgb_out, opacity, background)
    return RenderOutput(
        rgb_out if "rgb" in outputs else None,
        depth_out if "depth" in outputs else None,
        opacity if "opacity" in outputs else None,
        int(ray.shape[0]),
    )


# The optical depth in front of a sample beyond which composite_in_rounds leaves it out (transmittance 1e-5, the
# cut of narf_core.track.visible).
ROUNDS_TAU_STOP = -math.log(1e-5)


@torch.no_grad()
def composite_in_rounds(
    field: Field,
    rays: Rays,
    samples: Samples,
    reach: Tensor,
    *,
    theta: Tensor | None = None,
    outputs: Sequence[str] = ("rgb",),
    background: float | Tensor = 0.0,
    keep: Callable[[Tensor, Tensor | None], Tensor] | None = None,
    tau_stop: float = ROUNDS_TAU_STOP,
) -> RenderOutput:
    """:func:`composite` of ``samples`` (ray-major, ascending ``t``) without a graph, in two rounds: each ray's
    samples up to the distance ``reach [n]`` (a guess of where it turns opaque, from a render nearby), then
    the rest of those rays whose optical depth so far is under ``tau_stop``. A ray that turns opaque by its
    ``reach`` costs its samples in front of the surface; one that does not costs what :func:`composite` would.
    ``keep(x [s, 3], θ [s, k] | None) -> [s]`` (an occupancy's ``occupied``): each round evaluates only the
    samples it holds, the others empty. The result is :func:`composite`'s of the samples ``keep`` holds, but
    for those behind an opaque ray's ``reach`` (together under ``exp(-tau_stop)``)."""
    outputs = check_outputs(outputs)
    theta, per_ray = ray_theta(theta, len(rays))
    n, dtype = len(rays), rays.origins.dtype
    ray = samples.ray
    tau_before = rays.origins.new_zeros(n)
    rgb_out, depth_out = rays.origins.new_zeros(n, 3), rays.origins.new_zeros(n)
    evaluated = 0
    opening = samples.t <= reach.to(samples.t)[ray]
    for later in (False, True):  # then the rest of the rays light still crosses
        chosen = ~opening & (tau_before < tau_stop)[ray] if later else opening
        pick = chosen.nonzero()[:, 0]
        r, t = ray[pick], samples.t[pick].to(dtype)
        x = rays.origins[r] + t[:, None] * rays.directions[r]
        th = sample_theta(theta, per_ray, r)
        if keep is not None and pick.numel():
            held = keep(x, th)
            pick, r, t, x = pick[held], r[held], t[held], x[held]
            th = None if th is None else th[held]
        if pick.numel() == 0:
            continue
        sigma, rgb = field(x, rays.directions[r], th) if "rgb" in outputs else (density_fn(field)(x, th), None)
        tau = sigma.to(dtype) * samples.delta[pick].to(dtype)
        hit, row, counts = torch.unique_consecutive(r, return_inverse=True, return_counts=True)
        slot = torch.arange(r.shape[0], device=r.device) - (counts.cumsum(0) - counts)[row]
        w = _packed_weights(tau, row, slot, hit.shape[0], tau_before[hit])
        if "rgb" in outputs:
            rgb_out = rgb_out.index_add(0, r, w[:, None] * rgb.to(dtype))
        if "depth" in outputs:
            depth_out = depth_out.index_add(0, r, w * t * rays.z_per_t[r].to(dtype))
        tau_before = tau_before.index_add(0, r, tau)
        evaluated += int(pick.numel())
    opacity = -torch.expm1(-tau_before)
    return RenderOutput(
        _over_background(rgb_out, opacity, background) if "rgb" in outputs else None,
        depth_out if "depth" in outputs else None,
        opacity if "opacity" in outputs else None,
        evaluated,
    )


# The transmittance below which composite_jacobian leaves a sample's derivatives out (its weight in P and
# in every derivative is under it).
JACOBIAN_TRANSMITTANCE = 1e-4


def composite_jacobian(
    field_jacobian: Callable[[Tensor, Tensor | None], tuple[Tensor, Tensor]],
    rays: Rays,
    samples: Samples,
    *,
    theta: Tensor | None = None,
    field: Field | None = None,
) -> tuple[Tensor, Tensor]:
    """What :func:`composite` gives over a black background, with its derivatives in the rays and ``θ``.

    ``field_jacobian(x [s, 3], θ [s, k] | None)`` gives the field's density and colour ``[s, 4]`` at the
    samples and their derivatives in ``(x, θ)`` ``[s, 4, 3 + k]`` (``ArticulatedField.jacobian``; a
    view-independent field: the direction does not enter). Returns, float64, ``P [n, 5]`` (colour
    premultiplied by opacity, opacity, the opacity-weighted depth) and ``∂P/∂(o, d, θ) [n, 5, 6 + k]`` of
    every ray (origin, direction, its ``θ``): the compositing differentiated in closed form. With
    weights ``w_j = T_j α_j`` and a composited quantity ``P = Σ_j w_j v_j``, ``∂P/∂σ_j = δ_j (T_{j+1}
    v_j - Σ_{l>j} w_l v_l)`` and ``∂P/∂v_j = w_j``; a sample ``x_j = o + t_j d`` moves by ``I`` with
    ``o`` and by ``t_j I`` with ``d``.

    ``field`` (the same view-independent field, as :func:`composite` takes it): evaluated first at every
    sample, and ``field_jacobian`` then only at the samples a ray still sees (transmittance before them at
    least :data:`JACOBIAN_TRANSMITTANCE`); the others' derivatives are 0. A sample's weight in ``P`` and in
    every derivative is under its transmittance, while its derivatives cost ``3 + k`` evaluations more than
    its value: worth it where samples run on behind the surface (a tracked frame not pruned to what light
    reaches)."""
    theta, per_ray = ray_theta(theta, len(rays))
    n, k = len(rays), 0 if theta is None else theta.shape[-1]
    P = torch.zeros(n, 5, dtype=torch.float64, device=rays.origins.device)
    J = P.new_zeros(n, 5, 6 + k)
    ray, t, delta = samples.ray, samples.t.double(), samples.delta.double()
    if ray.numel() == 0:
        return P, J
    rays_hit, row, counts = torch.unique_consecutive(ray, return_inverse=True, return_counts=True)
    slot = torch.arange(ray.shape[0], device=ray.device) - (counts.cumsum(0) - counts)[row]
    d = rays.directions[ray]
    x = rays.origins[ray] + samples.t[:, None].to(rays.origins) * d
    th = sample_theta(theta, per_ray, ray)
    if field is None:
        values, dvalues = field_jacobian(x, th)
        values, dvalues = values.double(), dvalues.double()
    else:
        with torch.no_grad():
            sigma, rgb = field(x, d, th)
        values = torch.cat([sigma[:, None], rgb], 1).double()
    tau = values[:, 0] * delta
    padded = tau.new_zeros(rays_hit.shape[0], int(slot.max()) + 1).index_put((row, slot), tau)
    w, transmittance = (a[row, slot] for a in _weights_from_optical_depth(padded, None))
    if field is not None:  # the derivatives where the ray still sees
        seen = (transmittance >= JACOBIAN_TRANSMITTANCE).nonzero()[:, 0]
        dvalues = values.new_zeros(values.shape[0], 4, 3 + k)
        dvalues[seen] = field_jacobian(x[seen], None if th is None else th[seen])[1].double()
    after = transmittance * torch.exp(-tau)  # T_{j+1}, the transmittance behind the sample
    v = torch.cat([values[:, 1:], torch.ones_like(tau)[:, None], (t * rays.z_per_t[ray].double())[:, None]], 1)  # [s, 5]
    wv = w[:, None] * v
    P = P.index_add(0, ray, wv)
    P[:, 3] = -torch.expm1(-P.new_zeros(n).index_add(0, ray, tau))  # the opacity as composite gives it
    running = wv.new_zeros(*padded.shape, 5).index_put((row, slot), wv).cumsum(1)[row, slot]  # Σ_{l<=j} w_l v_l
    dP_dsigma = delta[:, None] * (after[:, None] * v - (P[ray] - running))  # [s, 5]
    dP_dx = dP_dsigma[..., None] * dvalues[:, None, 0]  # [s, 5, 3 + k]
    dP_dx[:, :3] += w[:, None, None] * dvalues[:, 1:]
    J[..., :3] = J[..., :3].index_add(0, ray, dP_dx[..., :3])
    J[..., 3:6] = J[..., 3:6].index_add(0, ray, t[:, None, None] * dP_dx[..., :3])
    J[..., 6:] = J[..., 6:].index_add(0, ray, dP_dx[..., 3:])
    return P, J


def composite_marching(
    field: Field,
    rays: Rays,
    aabb: Tensor,
    marcher: Marcher,
    *,
    outputs: Sequence[str] = ("rgb",),
    background: float | Tensor = 0.0,
) -> RenderOutput:
    """March ``rays`` through ``aabb [2,3]`` with ``marcher`` and composite each round's samples as they
    come (the one-pass render, for when no gradient is needed). The same samples and, up to
    rounding, the same result as :func:`composite` of :meth:`~narf_core.sampling.Marcher.samples`."""
    outputs = check_outputs(outputs)
    n, dtype = len(rays), rays.origins.dtype
    density = None if "rgb" in outputs else getattr(field, "density_only", None)
    sample_ray: list[Tensor] = []  # per round: the ray of each sample, its weighted colour and depth
    sample_rgb: list[Tensor] = []
    sample_z: list[Tensor] = []
    n_samples = 0

    def evaluate(r: Round) -> Tensor:
        nonlocal n_samples
        th = marcher.sample_theta(r.ray)
        x = r.x
        sigma, rgb = (density(x, th), None) if density is not None else field(x, r.d, th)
        n_samples += r.ray.shape[0]
        tau = sigma.to(dtype) * r.delta
        w = _packed_weights(tau, r.row, r.slot, r.tau_before.shape[0], r.tau_before)
        sample_ray.append(r.ray)
        if "rgb" in outputs:
            sample_rgb.append(w[:, None] * rgb.to(dtype))
        if "depth" in outputs:
            sample_z.append(w * r.t * rays.z_per_t[r.ray].to(dtype))
        return tau

    opacity = -torch.expm1(-marcher.rounds(rays, aabb, evaluate))
    ray_of = torch.cat(sample_ray) if sample_ray else torch.zeros(0, dtype=torch.long, device=opacity.device)
    rgb_out = depth_out = None
    if "rgb" in outputs:
        rgb_out = rays.origins.new_zeros(n, 3)
        if sample_rgb:
            rgb_out = rgb_out.index_add(0, ray_of, torch.cat(sample_rgb))
        rgb_out = _over_background(rgb_out, opacity, background)
    if "depth" in outputs:
        depth_out = rays.origins.new_zeros(n)
        if sample_z:
            depth_out = depth_out.index_add(0, ray_of, torch.cat(sample_z))
    return RenderOutput(rgb_out, depth_out, opacity if "opacity" in outputs else None, n_samples)
