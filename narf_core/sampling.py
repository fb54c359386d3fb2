"""Ray marching: which samples along each ray a render evaluates (nerfacc's estimator side).

:func:`march` gives them as :class:`Samples` (``ray``, ``t``, ``delta``, grouped by ray in ascending
``t``), found from densities alone; :func:`narf_core.compositing.composite` turns samples into
colour, depth and opacity. The marching itself (:class:`Marcher`) is also driven round by round by
the compositor that composites while it marches (no gradients: one field evaluation per sample).

Sampling: every ray is clipped to the box (cut down to the occupancy's :meth:`~Occupancy.bounds`)
and cut by a lattice of spacing ``step`` anchored at the ray origin (``t = 0``), so that the
intervals tile ``[t_near, t_far]`` exactly (the first and last ones shorter) and their positions
do not depend on how tightly the ray was clipped; each interval is represented by one sample, at its
middle or (``jitter``) at one random offset per ray. An occupancy that knows where along each ray it
can be occupied at all (its :meth:`~narf_core.occupancy.RayOccupancy` has ``span()``: the
articulated field's posed part grids) has each ray marched only there, on the same lattice. Samples the occupancy calls empty are never
evaluated (their density counts as 0). Rays are marched together in rounds: each round looks ahead
a window of intervals per ray, evaluates the field at the ray's next few occupied samples (its
budget: 5 in the first round; then as many as its last round's optical depth per sample says it
needs to become opaque, or 1.4 times as many as before, up to 128, while it is still in empty or
faint space), and retires the ray once its transmittance is below ``transmittance_eps`` (early
termination; the colour error this adds is below that value) or it leaves the box. Sample positions
``t`` are not differentiated (a quadrature choice).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from narf_core.geometry import Rays
from narf_core.occupancy import Occupancy, RayOccupancy

_DIR_EPS = 1e-12  # |direction| components below this are replaced by a signed epsilon
_FIRST_ROUND = 5  # occupied samples evaluated per ray in the first round (bounds the work wasted past termination)
_GROWTH = 1.4  # ... growing by this factor per round while a ray is in empty or faint space
_MAX_ROUND = 128  # ... up to this many (few rounds for long translucent stretches)
_LOOKAHEAD = 4  # window of intervals checked per round, in multiples of the samples evaluated
_MAX_WINDOW = 512  # ... up to this many


def ray_aabb(origins: Tensor, directions: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test of rays ``origins [n,3]``, ``directions [n,3]`` against the box ``aabb [2,3]``.

    Returns ``t_near [n]`` (>= 0: a ray starting inside the box starts at 0), ``t_far [n]``
    (>= ``t_near``) and ``hit [n]`` (bool, ``t_far > t_near``). Direction components smaller than
    1e-12 are replaced by a signed 1e-12, so an axis-parallel ray starting on a face gives no
    ``0 * inf = NaN``.
    """
    d = directions
    d = torch.where(d.abs() < _DIR_EPS, torch.where(d < 0, -_DIR_EPS, _DIR_EPS).to(d.dtype), d)
    inv = 1.0 / d
    aabb = aabb.to(origins.dtype)
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0)
    t_far = torch.maximum(t0, t1).amin(-1)
    hit = t_far > t_near
    return t_near, torch.maximum(t_far, t_near), hit


@dataclass
class Samples:
    """Samples along rays, grouped by ray in ascending ``t`` (all ``[s]``).

    ``ray``: index of the sample's ray (int64); ``t``: its distance along the ray (the point is
    ``o + t d``); ``delta``: the length of the interval it stands for (>= 0). Rays without samples
    do not appear.
    """

    ray: Tensor
    t: Tensor
    delta: Tensor

    def __len__(self) -> int:
        return self.ray.shape[0]


@dataclass
class Round:
    """The samples one marching round evaluates, for the ``m`` rays still marching (``[s]`` each).

    ``ray``: index into the caller's rays; ``row``: the ray's row among the ``m``; ``slot``: the
    sample's place among its ray's samples of this round (ascending ``t``); ``t``, ``delta``: as in
    :class:`Samples`. ``origins``, ``directions [m,3]``: the marching rays (differentiable where the
    caller's are); ``tau_before [m]``: each one's optical depth before this round.
    """

    ray: Tensor
    row: Tensor
    slot: Tensor
    t: Tensor
    delta: Tensor
    origins: Tensor
    directions: Tensor
    tau_before: Tensor

    @property
    def x(self) -> Tensor:
        """``[s,3]`` the sample positions ``o + t d``."""
        return self.origins[self.row] + self.t[:, None] * self.directions[self.row]

    @property
    def d(self) -> Tensor:
        """``[s,3]`` the sample directions."""
        return self.directions[self.row]


def ray_theta(theta: Tensor | None, n: int) -> tuple[Tensor | None, bool]:
    """Validate ``theta`` for ``n`` rays; returns it and whether it is per ray (``[n,k]``) rather than
    shared (``[k]``). An empty ``theta`` (a part field's) comes back as ``None``."""
    if theta is None or theta.numel() == 0 and theta.dim() == 1:
        return None, False
    if theta.dim() == 1:
        return theta, False
    if theta.dim() == 2 and theta.shape[0] == n:
        return (None, False) if theta.shape[1] == 0 else (theta, True)
    raise ValueError(f"theta must be [k] or [n_rays={n}, k], got shape {tuple(theta.shape)}")


def sample_theta(theta: Tensor | None, per_ray: bool, ray: Tensor) -> Tensor | None:
    """The configuration of each sample of the rays ``ray [s]``: ``[s, k]``, ``None`` for a part field."""
    if theta is None:
        return None
    return theta[ray] if per_ray else theta.expand(ray.shape[0], -1)


def _check_band(t_range: tuple[Tensor, Tensor] | None, n: int) -> tuple[Tensor, Tensor] | None:
    """Validate ``t_range``: two ``[n]`` tensors of distances along the rays (``NaN`` is refused)."""
    if t_range is None:
        return None
    near, far = t_range
    if near.shape != (n,) or far.shape != (n,):
        raise ValueError(f"t_range must be two [n_rays={n}] tensors, got {tuple(near.shape)} and {tuple(far.shape)}")
    if bool(torch.isnan(near).any() | torch.isnan(far).any()):
        raise ValueError("t_range must not hold NaN")
    return near.detach(), far.detach()


class Marcher:
    """The marching settings of one render of ``n`` rays, validated once (see the module docstring).

    ``grid``: an :class:`~narf_core.occupancy.Occupancy` (``None``: everything may hold density);
    ``theta``: ``[k]`` for all rays, ``[n,k]`` per ray, or ``None``; ``step``: interval length in
    metres; ``max_samples``: at most this many intervals per ray (longer rays get longer
    intervals); ``transmittance_eps``: a ray stops once its transmittance falls below this;
    ``generator``: jitter each ray's sample offset with it (``None``: interval middles);
    ``t_range``: ``(near [n], far [n])``, march only that band of each ray.
    """

    def __init__(
        self,
        n: int,
        *,
        grid: Occupancy | None = None,
        theta: Tensor | None = None,
        step: float,
        max_samples: int = 1024,
        transmittance_eps: float = 1e-3,
        generator: torch.Generator | None = None,
        t_range: tuple[Tensor, Tensor] | None = None,
    ) -> None:
        if not (math.isfinite(step) and step > 0):
            raise ValueError(f"step must be a positive number of metres, got {step}")
        if not 0 < transmittance_eps < 1:
            raise ValueError(f"transmittance_eps must be in (0, 1), got {transmittance_eps}")
        if max_samples < 3:
            raise ValueError(f"max_samples must be >= 3, got {max_samples}")
        self.grid = grid
        self.theta, self.per_ray = ray_theta(theta, n)
        self.step, self.max_samples, self.transmittance_eps = step, max_samples, transmittance_eps
        self.generator = generator
        self.band = _check_band(t_range, n)

    def sample_theta(self, ray: Tensor) -> Tensor | None:
        """``[s, k]`` the configuration of each sample of the rays ``ray [s]`` (``None``: a part field)."""
        return sample_theta(self.theta, self.per_ray, ray)

    def rounds(self, rays: Rays, aabb: Tensor, evaluate: Callable[[Round], Tensor]) -> Tensor:
        """March ``rays`` through ``aabb [2,3]`` in rounds; ``evaluate(round)`` gives the optical depth
        ``sigma * delta [s]`` of the round's samples. Returns each ray's total optical depth ``[n]``
        (differentiable as ``evaluate``'s results are; 0 for a ray never evaluated)."""
        live = _start(rays, aabb, self)
        tau_stop = -math.log(self.transmittance_eps)
        retired_ids: list[Tensor] = []
        retired_tau: list[Tensor] = []
        while live.ids.numel() > 0:
            most, left = int(live.budget.max()), int((live.n_steps - live.j).max())
            with torch.no_grad():  # no window reaches past the last ray's end (those intervals are empty)
                t, delta, occ = _candidates(live, max(1, min(_LOOKAHEAD * most, _MAX_WINDOW, left)))
                rank = occ.to(torch.int32).cumsum(1, dtype=torch.int32)  # int32: many times faster than bool -> int64
                take = occ & (rank <= live.budget[:, None])
                full = rank[:, -1] >= live.budget
                advance = torch.where(full, (rank < live.budget[:, None]).sum(1, dtype=torch.int32) + 1, occ.shape[1])
                row, col = take.nonzero(as_tuple=True)
                slot = rank[row, col] - 1
                t_s, delta_s = t[row, col], delta[row, col]
            added = None
            if row.numel() > 0:
                tau_s = evaluate(Round(live.ids[row], row, slot, t_s, delta_s, live.o, live.d, live.tau))
                added = live.o.new_zeros(live.ids.shape[0]).index_add(0, row, tau_s)
                live.tau = live.tau + added
            with torch.no_grad():
                live.j = live.j + advance
                going = (live.j < live.n_steps) & (live.tau < tau_stop)
                live.budget = _next_budget(live.budget, added, take.sum(1, dtype=torch.int32), live.tau, tau_stop)
            if not bool(going.all()):
                retired_ids.append(live.ids[~going])
                retired_tau.append(live.tau[~going])
                live = live.select(going.nonzero().squeeze(-1))
        tau_total = rays.origins.new_zeros(len(rays))
        if retired_ids:
            tau_total = tau_total.index_put((torch.cat(retired_ids),), torch.cat(retired_tau))
        return tau_total

    def samples(self, density: Callable[[Tensor, Tensor | None], Tensor], rays: Rays, aabb: Tensor) -> Samples:
        """The samples the march evaluates, found from ``density(x [s,3], theta [s,k] | None) -> sigma [s]``."""
        kept: list[tuple[Tensor, Tensor, Tensor]] = []

        def evaluate(r: Round) -> Tensor:
            sigma = density(r.x, self.sample_theta(r.ray))
            kept.append((r.ray, r.t, r.delta))
            return sigma.to(r.t.dtype) * r.delta

        with torch.no_grad():
            self.rounds(Rays(rays.origins.detach(), rays.directions.detach(), rays.z_per_t), aabb, evaluate)
        if not kept:
            empty = rays.origins.new_zeros(0)
            return Samples(torch.zeros(0, dtype=torch.long, device=empty.device), empty, empty)
        ray, t, delta = (torch.cat(parts) for parts in zip(*kept))
        order = torch.sort(ray, stable=True).indices  # by ray; within a ray rounds and slots are in t order
        return Samples(ray[order], t[order], delta[order])


def march(
    density: Callable[[Tensor, Tensor | None], Tensor],
    rays: Rays,
    aabb: Tensor,
    *,
    grid: Occupancy | None = None,
    theta: Tensor | None = None,
    step: float,
    max_samples: int = 1024,
    transmittance_eps: float = 1e-3,
    jitter: bool = False,
    generator: torch.Generator | None = None,
    t_range: tuple[Tensor, Tensor] | None = None,
) -> Samples:
    """The samples a render of ``rays`` (in the field's frame) inside ``aabb [2,3]`` evaluates.

    ``density(x [s,3], theta [s,k] | None) -> sigma [s]`` decides where each ray stops (e.g.
    :func:`narf_core.occupancy.density_fn` of a field). The other arguments are those of
    :func:`narf_core.render.render_rays`. No gradients flow (sample positions are not differentiated).
    """
    marcher = Marcher(
        len(rays), grid=grid, theta=theta, step=step, max_samples=max_samples, transmittance_eps=transmittance_eps,
        generator=generator if jitter else None, t_range=t_range,
    )
    return marcher.samples(density, rays, aabb)


@dataclass
class _LiveRays:
    """The rays still being marched, one row each (all ``[m]`` or ``[m, ...]``)."""

    ids: Tensor  # index into the caller's rays
    o: Tensor  # origins and directions [m, 3], differentiable
    d: Tensor
    occupancy: RayOccupancy | None  # the grid along these rays
    t0: Tensor  # the clipped segment
    t1: Tensor
    step: Tensor  # interval length
    k0: Tensor  # lattice index of the first interval (whole number, rays' dtype)
    n_steps: Tensor  # intervals in the segment
    offset: Tensor  # where in its interval a sample sits, in [0, 1)
    j: Tensor  # next interval, from k0
    budget: Tensor  # occupied samples to evaluate next round (int32)
    tau: Tensor  # optical depth so far, differentiable

    def select(self, keep: Tensor) -> _LiveRays:
        return _LiveRays(**{
            name: value if value is None else value.select(keep) if name == "occupancy" else value[keep]
            for name, value in vars(self).items()
        })


def _start(rays: Rays, aabb: Tensor, marcher: Marcher) -> _LiveRays:
    """Clip the rays to the (occupancy-tightened) box, and to their band when given, and set up
    marching for those that meet it."""
    origins, directions = rays.origins, rays.directions
    grid, theta, per_ray, band = marcher.grid, marcher.theta, marcher.per_ray, marcher.band
    with torch.no_grad():
        box = clip_box(aabb, grid, None if per_ray else theta)
        if box is None:
            ids = torch.zeros(0, dtype=torch.long, device=origins.device)
            t_near = t_far = origins.new_zeros(0)
        else:
            t_near, t_far, hit = ray_aabb(origins, directions, box)
            if band is not None:
                t_near, t_far = torch.maximum(t_near, band[0].to(t_near)), torch.minimum(t_far, band[1].to(t_far))
                hit &= t_far > t_near
            ids = hit.nonzero().squeeze(-1)
            t_near, t_far = t_near[ids], t_far[ids]
    o, d = origins[ids], directions[ids]
    with torch.no_grad():
        occupancy = None if grid is None else grid.along(o.detach(), d.detach(), theta[ids] if per_ray else theta)
        step_r = torch.maximum((t_far - t_near) / (marcher.max_samples - 2), torch.full_like(t_near, marcher.step))
        k0 = torch.floor(t_near / step_r)  # the lattice is anchored at t = 0, not at the clipped t_near
        if marcher.generator is not None:
            offset = torch.rand(ids.shape[0], generator=marcher.generator).to(o)
        else:
            offset = torch.full_like(t_near, 0.5)
        j, n_steps = _occupied_steps(occupancy, step_r, k0, torch.ceil(t_far / step_r) - k0)
    live = _LiveRays(
        ids=ids, o=o, d=d, occupancy=occupancy, t0=t_near, t1=t_far,
        step=step_r, k0=k0, n_steps=n_steps, offset=offset, j=j,
        budget=torch.full(ids.shape, _FIRST_ROUND, dtype=torch.int32, device=ids.device), tau=origins.new_zeros(ids.shape[0]),
    )
    return live if getattr(occupancy, "span", None) is None else live.select((live.j < live.n_steps).nonzero().squeeze(-1))


def _occupied_steps(occupancy: RayOccupancy | None, step: Tensor, k0: Tensor, n_steps: Tensor) -> tuple[Tensor, Tensor]:
    """The first interval (from ``k0``) and the end of each ray's march ``[m]``: the whole segment, or,
    for an occupancy that knows where along each ray it can be occupied (a ``span() -> (near [m], far
    [m])``), only the intervals there, with one more on each side (the lattice is unchanged, so the
    samples are those of the full march; the intervals skipped hold no occupied sample)."""
    span = getattr(occupancy, "span", None)
    if span is None:
        return torch.zeros_like(k0), n_steps
    near, far = span()
    j = (torch.floor(near.to(step) / step) - k0 - 1).clamp_min(0)
    return j, torch.minimum(n_steps, torch.ceil(far.to(step) / step) - k0 + 1)


def _candidates(live: _LiveRays, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """The next ``width`` intervals of every live ray: sample ``t``, length ``delta`` and occupancy, ``[m, width]``.

    The intervals are ``[max(a, t0), min(a + 1, t1)] * step`` for lattice indices ``a``; computing
    each end as the next one's start makes them tile the segment exactly.
    """
    lattice = (live.k0 + live.j)[:, None] + torch.arange(width, device=live.k0.device, dtype=live.k0.dtype)
    start = torch.maximum(lattice * live.step[:, None], live.t0[:, None])
    end = torch.minimum((lattice + 1) * live.step[:, None], live.t1[:, None])
    delta = (end - start).clamp_min_(0)
    t = torch.addcmul(start, live.offset[:, None], delta)
    occ = delta > 0
    if live.occupancy is not None:
        occ &= live.occupancy(t)
    return t, delta, occ


def clip_box(aabb: Tensor, grid: Occupancy | None, theta: Tensor | None) -> Tensor | None:
    """The box to clip rays to: ``aabb`` cut down to the occupancy's bounds (``None``: nothing there)."""
    box = aabb
    if grid is not None:
        tight = grid.bounds(theta)
        if tight is None:
            return None
        box = torch.stack([torch.maximum(aabb[0], tight[0].to(aabb)), torch.minimum(aabb[1], tight[1].to(aabb))])
    return box if bool((box[1] > box[0]).all()) else None


def _next_budget(budget: Tensor, added: Tensor | None, taken: Tensor, tau: Tensor, tau_stop: float) -> Tensor:
    """Occupied samples each live ray evaluates next round ``[m]``.

    A ray that is accumulating density gets about as many as its last round's rate says it needs to
    become opaque (at least 2); a ray in empty or faint space grows its budget by 1.4x, up to 128
    (fewer samples wasted past termination than a fixed doubling, for a few more rounds).
    """
    grow = (budget * _GROWTH).ceil().to(budget.dtype).clamp_max(_MAX_ROUND)
    if added is None:
        return grow
    rate = added.detach() / taken.clamp_min(1)
    need = ((tau_stop - tau.detach()) / rate.clamp_min(1e-12)).ceil().clamp(2, _MAX_ROUND)
    return torch.where(rate > 1e-3, torch.minimum(need.to(grow.dtype), grow), grow)
