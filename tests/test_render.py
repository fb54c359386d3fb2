"""The volume renderer: ray/box clipping, marching (samples), compositing, occupancy grids, images, part composition.

Fields here are analytic (spheres, constant densities) so that every expected value is hand-checked;
the last tests render the bundled clamp model.
"""

import math
from pathlib import Path

import pytest
import torch

from narf_core.compositing import composite, composite_in_rounds, composite_jacobian, volume_render_weights
from narf_core.fields.composed import compose_parts, composed_aabb
from narf_core.geometry import Pinhole, Rays, invert_pose, look_at, make_pose, se3_exp, so3_exp
from narf_core.occupancy import OccupancyGrid
from narf_core.render import ray_aabb, render_image, render_rays
from narf_core.sampling import Samples, march

BOX = torch.tensor([[-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]])
STEP = 0.2 / 256


class Sphere:
    """Density ``sigma`` inside a ball of radius ``radius + growth * theta[0]``; records what it evaluates."""

    def __init__(self, center=(0.0, 0.0, 0.0), radius=0.05, sigma=1e3, rgb=(1.0, 0.5, 0.0), growth=0.0, aabb=BOX):
        self.center, self.radius, self.sigma, self.growth = torch.tensor(center), radius, sigma, growth
        self.rgb = torch.tensor(rgb)
        self.aabb = aabb
        self.points: list[torch.Tensor] = []

    def density_only(self, x, theta=None):
        self.points.append(x.detach())
        r = self.radius if theta is None else self.radius + self.growth * theta[:, 0].to(x.dtype)
        inside = (x - self.center.to(x.dtype)).norm(dim=-1) < r
        return torch.where(inside, self.sigma, 0.0).to(x.dtype)

    def __call__(self, x, d, theta=None):
        return self.density_only(x, theta), self.rgb.to(x.dtype).expand(x.shape[0], 3)

    @property
    def n_evaluated(self) -> int:
        return sum(p.shape[0] for p in self.points)


class Constant:
    """Density ``sigma`` everywhere (the renderer clips it to the box) and a colour that varies with z."""

    def __init__(self, sigma):
        self.sigma = sigma

    def __call__(self, x, d, theta=None):
        rgb = torch.stack([0.5 + 2 * x[:, 2], torch.full_like(x[:, 0], 0.25), torch.full_like(x[:, 0], 0.75)], -1)
        return torch.full_like(x[:, 0], self.sigma), rgb


class Blob(torch.nn.Module):
    """A differentiable Gaussian density whose centre moves with theta."""

    def __init__(self):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(30.0, dtype=torch.float64))
        self.center = torch.nn.Parameter(torch.tensor([0.01, -0.02, 0.0], dtype=torch.float64))

    def forward(self, x, d, theta=None):
        c = self.center if theta is None else self.center + 0.05 * theta[:, :1] * torch.tensor([1.0, 0.0, 0.0], dtype=x.dtype)
        sigma = self.scale * torch.exp(-((x - c) ** 2).sum(-1) / 0.03**2)
        return sigma, torch.sigmoid(10 * x)


def rays_along_z(xy, z0=-1.0, dtype=torch.float32, z_per_t=1.0) -> Rays:
    xy = torch.as_tensor(xy, dtype=dtype).reshape(-1, 2)
    n = xy.shape[0]
    origins = torch.cat([xy, torch.full((n, 1), z0, dtype=dtype)], -1)
    directions = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype).expand(n, 3)
    return Rays(origins, directions, torch.full((n,), z_per_t, dtype=dtype))


# --------------------------------------------------------------------------------------------
# ray_aabb


def test_ray_aabb_hit_miss_and_away(dtype):
    box = torch.tensor([[-1.0, -1, -1], [1, 1, 1]], dtype=dtype)
    o = torch.tensor([[0.0, 0, -2], [2.0, 0, -2], [0.0, 0, -2]], dtype=dtype)
    d = torch.tensor([[0.0, 0, 1], [0.0, 0, 1], [0.0, 0, -1]], dtype=dtype)
    t_near, t_far, hit = ray_aabb(o, d, box)
    assert hit.tolist() == [True, False, False]
    assert t_near[0] == 1 and t_far[0] == 3
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all()
    assert (t_far >= t_near).all() and (t_near >= 0).all()  # never far < near, even pointing away


def test_ray_aabb_axis_parallel_ray_starting_on_a_face_is_finite(dtype):
    box = torch.tensor([[-1.0, -1, -1], [1, 1, 1]], dtype=dtype)
    o = torch.tensor([[-1.0, 0, -2], [-1.0, 0.5, 0.0], [0.3, -1.0, -1.0]], dtype=dtype)  # on faces / edges
    d = torch.tensor([[0.0, 0, 1], [-0.0, 0, 1], [0.0, -0.0, 1]], dtype=dtype)
    t_near, t_far, hit = ray_aabb(o, d, box)
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all()
    assert hit.all()  # rays along a lower face count as inside
    torch.testing.assert_close(t_far - t_near, torch.tensor([2.0, 1.0, 2.0], dtype=dtype))


def test_ray_aabb_camera_inside_the_box_starts_at_zero(dtype):
    box = torch.tensor([[-1.0, -1, -1], [1, 1, 1]], dtype=dtype)
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 1.0, 0.0]], dtype=dtype), dim=-1)
    t_near, t_far, hit = ray_aabb(torch.zeros(1, 3, dtype=dtype), d, box)
    assert hit.item() and t_near.item() == 0
    assert t_far.item() == pytest.approx(math.sqrt(2))


def test_ray_aabb_grazing_a_corner_gives_a_tiny_nonnegative_segment():
    box = torch.tensor([[-1.0, -1, -1], [1, 1, 1]], dtype=torch.float64)
    o = torch.tensor([[1.0 - 1e-9, 1.0 - 1e-9, -3.0]], dtype=torch.float64)
    t_near, t_far, hit = ray_aabb(o, torch.tensor([[0.0, 0, 1]], dtype=torch.float64), box)
    assert hit.item() and (t_far - t_near).item() == pytest.approx(2.0)
    o = torch.tensor([[-2.0, 0.0, 1.0 - 1e-9]], dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 1e-3]], dtype=torch.float64), dim=-1)
    t_near, t_far, hit = ray_aabb(o, d, box)
    assert 0 <= (t_far - t_near).item() < 1e-5


# --------------------------------------------------------------------------------------------
# march: the samples along each ray


UNIT = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_march_cuts_the_clipped_segment_on_a_lattice_anchored_at_the_origin(dtype):
    faint = Constant(1e-3).__call__  # never stops a ray early
    rays = rays_along_z([[0.0, 0.0], [0.5, 0.5], [2.0, 0.0]], z0=-3.0, dtype=dtype)
    rays.origins[1, 2] = -2.875  # enters the box at t = 1.875, between two lattice points
    samples = march(lambda x, theta: faint(x, x)[0], rays, UNIT, step=0.25)
    assert samples.ray.tolist() == [0] * 8 + [1] * 9  # the third ray misses the box
    first = [2.125 + 0.25 * i for i in range(8)]
    second = [1.9375] + [2.125 + 0.25 * i for i in range(7)] + [3.8125]  # short first and last intervals
    torch.testing.assert_close(samples.t, torch.tensor(first + second, dtype=dtype))
    torch.testing.assert_close(samples.delta, torch.tensor([0.25] * 8 + [0.125] + [0.25] * 7 + [0.125], dtype=dtype))


def test_march_skips_empty_cells_and_clips_to_the_occupied_bounds():
    occ = torch.zeros(2, 2, 2, dtype=torch.bool)
    occ[:, :, 0] = True  # only z < 0 may hold density
    grid = OccupancyGrid(UNIT, occ)
    evaluated = []

    def density(x, theta):
        evaluated.append(x)
        return torch.full_like(x[:, 0], 1e-3)

    samples = march(density, rays_along_z([[0.0, 0.0]], z0=-3.0), UNIT, grid=grid, step=0.25)
    torch.testing.assert_close(samples.t, torch.tensor([2.125, 2.375, 2.625, 2.875]))
    assert (torch.cat(evaluated)[:, 2] < 0).all()


def test_march_stops_a_ray_soon_after_it_is_opaque_and_the_samples_composite_to_it():
    dense = Constant(100.0)  # optical depth 25 per interval: opaque after the first
    rays = rays_along_z([[0.0, 0.0]], z0=-3.0)
    samples = march(lambda x, theta: dense(x, x)[0], rays, UNIT, step=0.25)
    assert 1 <= len(samples) < 8
    torch.testing.assert_close(samples.t, 2.125 + 0.25 * torch.arange(len(samples), dtype=torch.float32))  # a prefix
    out = composite(dense, rays, samples, outputs=("opacity", "depth"))
    assert out.opacity.item() == pytest.approx(1.0) and out.depth.item() == pytest.approx(2.125, abs=1e-6)


def test_march_jitter_keeps_one_offset_per_ray_and_a_band_keeps_only_its_samples():
    faint = Constant(1e-3)
    rays = rays_along_z([[0.0, 0.0], [0.1, 0.0]], z0=-3.0)
    samples = march(lambda x, theta: faint(x, x)[0], rays, UNIT, step=0.25, jitter=True, generator=torch.Generator().manual_seed(0))
    start = torch.floor(samples.t / 0.25) * 0.25
    offset = (samples.t - start) / samples.delta
    for r in (0, 1):
        torch.testing.assert_close(offset[samples.ray == r], offset[samples.ray == r][:1].expand(8))
    assert not torch.equal(offset[samples.ray == 0][0], offset[samples.ray == 1][0])
    near, far = torch.tensor([2.5, 0.0]), torch.tensor([3.0, 0.5])  # the second band ends before the box
    band = march(lambda x, theta: faint(x, x)[0], rays, UNIT, step=0.25, t_range=(near, far))
    assert band.ray.tolist() == [0, 0]
    torch.testing.assert_close(band.t, torch.tensor([2.625, 2.875]))


def test_march_takes_theta_per_ray_to_the_density():
    seen = []

    def density(x, theta):
        seen.append(theta)
        return torch.full_like(x[:, 0], 1e-3)

    rays = rays_along_z([[0.0, 0.0], [0.1, 0.0]], z0=-3.0)
    samples = march(density, rays, UNIT, theta=torch.tensor([[1.0], [2.0]]), step=0.25)
    assert torch.cat(seen)[:, 0].sort().values.tolist() == [1.0] * 8 + [2.0] * 8
    with pytest.raises(ValueError, match=r"theta must be \[k\] or \[n_rays=2, k\]"):
        march(density, rays, UNIT, theta=torch.zeros(3, 1), step=0.25)
    assert len(samples) == 16


# --------------------------------------------------------------------------------------------
# Compositing weights


def test_volume_render_weights_hand_checked(dtype):
    sigma = torch.tensor([[1.0, 2.0, 0.0]], dtype=dtype)
    delta = torch.tensor([[0.5, 0.5, 0.5]], dtype=dtype)
    w, T = volume_render_weights(sigma, delta)
    e = math.exp
    torch.testing.assert_close(T, torch.tensor([[1.0, e(-0.5), e(-1.5)]], dtype=dtype))
    torch.testing.assert_close(w, torch.tensor([[1 - e(-0.5), e(-0.5) * (1 - e(-1.0)), 0.0]], dtype=dtype))
    w_in, _ = volume_render_weights(sigma, delta, torch.tensor([2.0], dtype=dtype))
    torch.testing.assert_close(w_in, w * e(-2.0))


def test_volume_render_weights_huge_density_and_tiny_steps(dtype):
    sigma = torch.tensor([[1e6, 1e6, 1.0], [1e6, 1e6, 1e6], [3e38, 1.0, 1.0]], dtype=dtype, requires_grad=True)
    delta = torch.tensor([[1e-9, 1e-9, 1e-9], [1.0, 1.0, 1.0], [10.0, 1.0, 1.0]], dtype=dtype)
    w, T = volume_render_weights(sigma, delta)
    assert torch.isfinite(w).all() and torch.isfinite(T).all()
    # row 0: alpha ~ 1e-3 each; the weights sum exactly to 1 - exp(-total optical depth)
    total = (sigma * delta)[0].sum()
    torch.testing.assert_close(w[0].sum(), -torch.expm1(-total))
    assert w[1].tolist() == [1.0, 0.0, 0.0]  # opaque at once; no NaN from the shifted cumsum
    assert w[2].tolist() == [1.0, 0.0, 0.0]  # optical depth overflows to inf (float32): still exact
    w[:2].sum().backward()
    assert torch.isfinite(sigma.grad).all()


# --------------------------------------------------------------------------------------------
# composite: colour, depth and opacity from given samples


class Layers:
    """Density 1 below z = 0.25 and 2 above it; red below, green above."""

    def __call__(self, x, d, theta=None):
        above = x[:, 2] > 0.25
        sigma = torch.where(above, 2.0, 1.0).to(x.dtype)
        rgb = torch.stack([(~above).to(x.dtype), above.to(x.dtype), torch.zeros_like(x[:, 0])], -1)
        return sigma, rgb


def test_composite_hand_checked(dtype):
    rays = rays_along_z([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]], z0=-1.0, dtype=dtype, z_per_t=0.5)
    # ray 0: samples at z = 0 (sigma 1) and z = 0.5 (sigma 2), each over 0.5; ray 1: none; ray 2: one at z = 0
    samples = Samples(torch.tensor([0, 0, 2]), torch.tensor([1.0, 1.5, 1.0], dtype=dtype), torch.tensor([0.5, 0.5, 0.25], dtype=dtype))
    out = composite(Layers(), rays, samples, outputs=("rgb", "depth", "opacity"), background=torch.tensor([0.0, 0.0, 1.0]))
    e = math.exp
    w0, w1 = 1 - e(-0.5), e(-0.5) * (1 - e(-1.0))
    torch.testing.assert_close(out.opacity, torch.tensor([1 - e(-1.5), 0.0, 1 - e(-0.25)], dtype=dtype))
    torch.testing.assert_close(out.depth, torch.tensor([0.5 * (w0 * 1.0 + w1 * 1.5), 0.0, 0.5 * (1 - e(-0.25))], dtype=dtype))
    torch.testing.assert_close(
        out.rgb, torch.tensor([[w0, w1, e(-1.5)], [0.0, 0.0, 1.0], [1 - e(-0.25), 0.0, e(-0.25)]], dtype=dtype)
    )
    assert out.n_samples == 3


def test_composite_of_the_march_equals_the_one_pass_render():
    field = Sphere(center=(0.01, 0.0, 0.02))
    rays = rays_along_z(torch.rand(40, 2, generator=torch.Generator().manual_seed(4)) * 0.2 - 0.1)
    outputs = ("rgb", "depth", "opacity")
    with torch.no_grad():
        one_pass = render_rays(field, rays, BOX, step=STEP, outputs=outputs)
    two_pass = composite(field, rays, march(field.density_only, rays, BOX, step=STEP), outputs=outputs)
    for a, b in zip((one_pass.rgb, one_pass.depth, one_pass.opacity), (two_pass.rgb, two_pass.depth, two_pass.opacity)):
        torch.testing.assert_close(a, b)
    assert one_pass.n_samples == two_pass.n_samples > 0


def test_composite_in_rounds_renders_what_composite_renders_evaluating_only_what_light_reaches():
    """:func:`composite_in_rounds` gives :func:`composite`'s result of the samples its ``keep`` holds, whatever the
    first round's reach (short of the surface, beyond it, none): the second round takes the rest of every ray
    light still crosses. With a reach just past the surface it evaluates the samples in front of it and
    little more; each ray's configuration is its own."""
    field = Sphere(center=(0.01, 0.0, 0.02), sigma=1e4, growth=0.1)
    rays = rays_along_z(torch.rand(60, 2, generator=torch.Generator().manual_seed(5)) * 0.2 - 0.1, dtype=torch.float64)
    t = torch.arange(0.9, 1.1, STEP, dtype=torch.float64) + STEP / 2  # the box's lattice, as a tracked frame's band
    n = len(rays)
    samples = Samples(torch.arange(n).repeat_interleave(len(t)), t.repeat(n), torch.full((n * len(t),), STEP, dtype=torch.float64))
    theta = torch.linspace(-0.2, 0.2, n, dtype=torch.float64)[:, None]

    def keep(x, th):  # an occupancy: only the box |x|, |y| < 0.06 is held
        assert th.shape == (x.shape[0], 1)
        return (x[:, :2].abs() < 0.06).all(-1)

    outputs = ("rgb", "depth", "opacity")
    with torch.no_grad():
        x = rays.origins[samples.ray] + samples.t[:, None] * rays.directions[samples.ray]
        held = keep(x, theta[samples.ray])
        expected = composite(field, rays, Samples(samples.ray[held], samples.t[held], samples.delta[held]), theta=theta,
                             outputs=outputs)
    hit = expected.opacity > 0.999
    assert 10 < int(hit.sum()) < n - 10  # rays through the sphere and rays past it
    front = torch.where(hit, expected.depth / expected.opacity.clamp_min(1e-9), torch.full_like(expected.depth, -math.inf))
    short = front + 2 * STEP
    in_front = int((held & ((samples.t <= short[samples.ray]) | ~hit[samples.ray])).sum())  # the rays past it: all
    assert in_front < 0.75 * expected.n_samples
    for reach, evaluated in ((short, in_front), (front - 20 * STEP, expected.n_samples),
                             (torch.full((n,), -math.inf, dtype=torch.float64), expected.n_samples)):
        field.points.clear()
        out = composite_in_rounds(field, rays, samples, reach, theta=theta, outputs=outputs, keep=keep)
        for name in outputs:
            torch.testing.assert_close(getattr(out, name), getattr(expected, name), atol=1e-4, rtol=0)
        assert out.n_samples == field.n_evaluated == evaluated
    assert composite_in_rounds(field, rays, Samples(samples.ray[:0], t[:0], t[:0]), front, theta=theta,
                               outputs=("opacity",)).opacity.abs().max() == 0


def test_composite_is_differentiable_in_theta_and_the_rays():
    blob = Blob()
    rays = rays_along_z(torch.tensor([[0.0, 0.0], [0.02, -0.01]]), dtype=torch.float64)
    samples = march(lambda x, theta: blob(x, x, theta)[0], rays, BOX, theta=torch.tensor([0.3], dtype=torch.float64), step=4 * STEP)

    def rgb_of(theta, origins):
        return composite(blob, Rays(origins, rays.directions, rays.z_per_t), samples, theta=theta).rgb

    inputs = (torch.tensor([0.3], dtype=torch.float64, requires_grad=True), rays.origins.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(rgb_of, inputs)


def _autograd_jacobian(field):
    """A view-independent ``field``'s values ``[s, 4]`` and their derivatives in ``(x, θ)`` ``[s, 4, 3 + k]``, by
    autograd sample by sample (the exact derivatives a field's own ``jacobian`` gives)."""
    def field_jacobian(x, th):
        x, th = x.clone().requires_grad_(True), th.clone().requires_grad_(True)
        sigma, rgb = field(x, x.detach(), th)
        values = torch.cat([sigma[:, None], rgb], 1)
        rows = [torch.cat(torch.autograd.grad(values[:, c].sum(), (x, th), retain_graph=True), 1) for c in range(4)]
        return values.detach(), torch.stack(rows, 1)

    return field_jacobian


def test_composite_jacobian_is_reverse_mode_through_the_composite():
    """Given a field's exact derivatives (here by autograd, sample by sample), the closed-form compositing
    gives what reverse mode through :func:`composite` gives: colour, opacity and depth and their
    derivatives in every ray's origin, direction and θ (two rays crossing the blob, one missing it)."""
    blob = Blob()
    rays = Rays(torch.tensor([[0.0, 0.0, -1.0], [0.02, -0.01, -1.0], [0.3, 0.3, -1.0]], dtype=torch.float64),
                torch.nn.functional.normalize(torch.tensor([[0.01, -0.02, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
                                                           dtype=torch.float64), dim=-1),
                torch.tensor([0.9, 1.0, 1.0], dtype=torch.float64))
    theta = torch.tensor([[0.3], [-0.2], [0.1]], dtype=torch.float64)
    samples = march(lambda x, th: blob(x, x, th)[0], rays, BOX, theta=theta, step=STEP)
    assert len(samples) > 20

    P, J = composite_jacobian(_autograd_jacobian(blob), rays, samples, theta=theta)
    o, d, th = (rays.origins.clone().requires_grad_(True), rays.directions.clone().requires_grad_(True),
                theta.clone().requires_grad_(True))
    out = composite(blob, Rays(o, d, rays.z_per_t), samples, theta=th, outputs=("rgb", "opacity", "depth"))
    expected = torch.cat([out.rgb, out.opacity[:, None], out.depth[:, None]], 1)
    torch.testing.assert_close(P, expected.detach())
    for c in range(5):
        grads = torch.autograd.grad(expected[:, c].sum(), (o, d, th), retain_graph=True)
        torch.testing.assert_close(J[:, c], torch.cat(grads, 1), rtol=1e-7, atol=1e-9)
    assert J[:2].abs().amax() > 0.1 and J[2].abs().amax() == 0


def test_composite_jacobian_given_the_field_leaves_out_the_samples_behind_the_surface():
    """Given the field itself, :func:`composite_jacobian` asks for derivatives only at the samples a ray still
    sees: on an opaque blob many of the crossing rays' samples lie behind its front, and ``P`` and ``J`` stay
    what the derivatives at every sample give, within the transmittance left out."""
    blob = Blob()
    with torch.no_grad():
        blob.scale.fill_(1e5)
    rays = Rays(torch.tensor([[0.0, 0.0, -1.0], [0.02, -0.01, -1.0], [0.3, 0.3, -1.0]], dtype=torch.float64),
                torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=torch.float64), torch.ones(3, dtype=torch.float64))
    theta = torch.tensor([[0.3], [-0.2], [0.1]], dtype=torch.float64)
    t = torch.arange(0.9, 1.1, STEP, dtype=torch.float64)  # every step through the box, as a tracked frame fixes them
    samples = Samples(torch.arange(3).repeat_interleave(len(t)), t.repeat(3), torch.full((3 * len(t),), STEP, dtype=torch.float64))
    asked, exact = [], _autograd_jacobian(blob)

    def field_jacobian(x, th):
        asked.append(x.shape[0])
        return exact(x, th)

    P_all, J_all = composite_jacobian(field_jacobian, rays, samples, theta=theta)
    P, J = composite_jacobian(field_jacobian, rays, samples, theta=theta, field=blob)
    assert asked[0] == len(samples) > 20 and 0 < asked[1] < 0.7 * len(samples)
    assert P_all[:2, 3].min() > 1 - 1e-6  # both crossing rays end opaque
    torch.testing.assert_close(P, P_all)
    assert (J - J_all).abs().amax() <= 1e-3 * J_all.abs().amax()


# --------------------------------------------------------------------------------------------
# render_rays against analytic answers


def test_constant_density_box_gives_the_analytic_opacity_and_depth(dtype):
    sigma, L, t0, z_per_t = 5.0, 0.2, 0.9, 0.8
    rays = rays_along_z([[0.0, 0.0], [0.03, -0.07]], dtype=dtype, z_per_t=z_per_t)
    out = render_rays(Constant(sigma), rays, BOX, step=STEP, outputs=("rgb", "depth", "opacity"), background=0.5)
    opacity = 1 - math.exp(-sigma * L)
    torch.testing.assert_close(out.opacity, torch.full((2,), opacity, dtype=dtype))
    # opacity-weighted depth: integral of t sigma exp(-sigma (t - t0)) over [t0, t0 + L], times z_per_t
    expected = z_per_t * (t0 * opacity + opacity / sigma - L * math.exp(-sigma * L))
    rtol = 1e-4 if dtype == torch.float32 else 1e-5  # midpoint quadrature error ~ step^2
    torch.testing.assert_close(out.depth, torch.full((2,), expected, dtype=dtype), rtol=rtol, atol=0)
    # colour: constant channels composite to c * opacity over the background
    torch.testing.assert_close(out.rgb[:, 1:], (torch.tensor([0.25, 0.75], dtype=dtype) * opacity + 0.5 * (1 - opacity)).expand(2, 2))


def test_camera_inside_the_box():
    rays = Rays(torch.zeros(1, 3), torch.tensor([[0.0, 1.0, 0.0]]), torch.ones(1))
    out = render_rays(Constant(5.0), rays, BOX, step=STEP, outputs=("opacity",))
    assert out.opacity.item() == pytest.approx(1 - math.exp(-5.0 * 0.1), rel=1e-6)


def test_outputs_come_back_only_when_asked():
    class DensityOnly(Sphere):
        def __call__(self, x, d, theta=None):
            raise AssertionError("colour was computed although only opacity was asked for")

    rays = rays_along_z([[0.0, 0.0]])
    out = render_rays(DensityOnly(), rays, BOX, step=STEP, outputs=("opacity",))
    assert out.rgb is None and out.depth is None and out.opacity.item() == pytest.approx(1.0)
    out = render_rays(Sphere(), rays, BOX, step=STEP)
    assert out.depth is None and out.opacity is None and out.rgb is not None


def test_rays_missing_the_box_are_never_evaluated():
    field = Sphere()
    rays = rays_along_z([[0.0, 0.0], [0.5, 0.0], [0.0, -0.3], [0.09, 0.09]])
    with torch.no_grad():  # one pass: every sample evaluated once
        out = render_rays(field, rays, BOX, step=STEP, outputs=("rgb", "opacity"), background=torch.tensor([0.0, 0.0, 1.0]))
    evaluated = torch.cat(field.points)
    assert out.n_samples == evaluated.shape[0] > 0
    field.points.clear()  # differentiable: the same samples, once for the march and once for the composite
    differentiable = render_rays(field, rays, BOX, step=STEP, outputs=("rgb", "opacity"), background=torch.tensor([0.0, 0.0, 1.0]))
    march, composite = torch.cat(field.points).split(evaluated.shape[0])
    torch.testing.assert_close(march, evaluated)
    torch.testing.assert_close(composite.unique(dim=0), evaluated.unique(dim=0))  # grouped by ray there
    torch.testing.assert_close(differentiable.rgb, out.rgb)
    assert ((evaluated >= BOX[0] - 1e-6) & (evaluated <= BOX[1] + 1e-6)).all()
    assert (evaluated[:, :2].abs() < 0.1).all()  # only the two rays through the box were marched
    assert out.rgb[1].tolist() == [0.0, 0.0, 1.0] and out.opacity[1] == 0
    field.points.clear()
    out = render_rays(field, rays[1:3], BOX, step=STEP)
    assert out.n_samples == 0 and not field.points


def test_a_band_around_the_surface_gives_the_full_render_from_fewer_samples():
    field = Sphere()  # surface at t = 0.95 - 0.05 * (1 - sqrt(1 - r^2/R^2)) along each ray
    rays = rays_along_z([[0.0, 0.0], [0.02, 0.01], [-0.03, 0.02], [0.08, 0.0]])  # the last misses the sphere
    outputs = ("rgb", "depth", "opacity")
    full = render_rays(field, rays, BOX, step=STEP, outputs=outputs)
    n_full = field.n_evaluated
    field.points.clear()
    near, far = torch.full((4,), 0.93), torch.full((4,), 0.99)
    band = render_rays(field, rays, BOX, step=STEP, outputs=outputs, t_range=(near, far))
    evaluated = torch.cat(field.points)
    assert band.n_samples < 0.5 * full.n_samples and field.n_evaluated < 0.5 * n_full
    assert ((evaluated[:, 2] >= -0.07 - 1e-6) & (evaluated[:, 2] <= -0.01 + 1e-6)).all()  # t in [0.93, 0.99]
    # the same samples up to where each ray stops (rounds differ, so by less than transmittance_eps)
    torch.testing.assert_close(band.rgb, full.rgb, atol=1e-3, rtol=0)
    torch.testing.assert_close(band.opacity, full.opacity, atol=1e-3, rtol=0)
    torch.testing.assert_close(band.depth[:3], full.depth[:3], atol=STEP, rtol=0)
    assert full.opacity[0] > 0.99 and full.opacity[3] == 0
    field.points.clear()
    before = render_rays(field, rays, BOX, step=STEP, outputs=outputs, t_range=(near - 0.7, far - 0.7))  # ends before the box
    assert before.n_samples == 0 and not field.points and (before.opacity == 0).all()


def test_a_band_of_the_wrong_shape_or_with_nan_is_refused():
    rays = rays_along_z([[0.0, 0.0], [0.01, 0.0]])
    with pytest.raises(ValueError, match="t_range"):
        render_rays(Sphere(), rays, BOX, step=STEP, t_range=(torch.zeros(3), torch.ones(3)))
    with pytest.raises(ValueError, match="NaN"):
        render_rays(Sphere(), rays, BOX, step=STEP, t_range=(torch.tensor([0.0, float("nan")]), torch.ones(2)))


def test_early_termination_changes_the_result_by_less_than_eps():
    field = Constant(100.0)  # T < 1e-3 after 7 cm of the 20 cm through the box
    rays = rays_along_z(torch.rand(64, 2, generator=torch.Generator().manual_seed(0)) * 0.18 - 0.09)
    exact = render_rays(field, rays, BOX, step=STEP, outputs=("rgb", "depth", "opacity"), transmittance_eps=1e-12)
    early = render_rays(field, rays, BOX, step=STEP, outputs=("rgb", "depth", "opacity"), transmittance_eps=1e-3)
    assert early.n_samples < 0.6 * exact.n_samples
    assert (early.rgb - exact.rgb).abs().max() < 1e-3
    assert (early.opacity - exact.opacity).abs().max() < 1e-3


def test_extreme_densities_and_tiny_steps_stay_finite_with_gradients():
    blob = Blob()
    with torch.no_grad():
        blob.scale.fill_(1e6)
    origins = torch.tensor([[0.0, 0.0, -1.0], [0.03, -0.02, -1.0]], dtype=torch.float64, requires_grad=True)
    rays = Rays(origins, torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    out = render_rays(blob, rays, BOX, step=STEP, outputs=("rgb", "depth", "opacity"))
    assert 1 - 1e-3 < out.opacity[0].item() <= 1  # stopped once T < 1e-3
    (out.rgb.sum() + out.depth.sum()).backward()
    assert torch.isfinite(origins.grad).all() and torch.isfinite(blob.scale.grad)
    tiny_box = torch.tensor([[0.0, 0.0, 0.0], [1e-7, 1e-7, 1e-7]], dtype=torch.float64)  # intervals of 1e-9
    rays = Rays(torch.tensor([[5e-8, 5e-8, -1.0]], dtype=torch.float64), rays.directions[:1], torch.ones(1, dtype=torch.float64))
    out = render_rays(Constant(1e6), rays, tiny_box, step=1e-9, outputs=("rgb", "depth", "opacity"))
    assert out.n_samples == 100
    assert out.opacity.item() == pytest.approx(-math.expm1(-1e6 * 1e-7), rel=1e-9)
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()


def test_rays_that_leave_the_box_after_a_pose_update_give_background_and_finite_gradients():
    xi = torch.zeros(6, requires_grad=True)
    rays = rays_along_z([[0.0, 0.0], [0.05, 0.05]], z0=0.5)  # start beyond the box, pointing away
    moved = rays.transform(se3_exp(xi))
    out = render_rays(Sphere(), moved, BOX, step=STEP, outputs=("rgb", "depth", "opacity"), background=0.2)
    assert out.n_samples == 0 and torch.allclose(out.rgb, torch.tensor(0.2))
    (out.rgb.sum() + out.opacity.sum()).backward()
    assert torch.isfinite(xi.grad).all()


def test_gradients_reach_the_field_theta_and_the_rays():
    blob = Blob()
    theta = torch.tensor([0.3], dtype=torch.float64, requires_grad=True)
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    rays = rays_along_z(torch.tensor([[0.0, 0.0], [0.02, -0.01], [0.03, -0.03]]), dtype=torch.float64)
    out = render_rays(blob, rays.transform(se3_exp(xi)), BOX, theta=theta, step=STEP, outputs=("rgb", "depth", "opacity"))
    (out.rgb.sum() + out.depth.sum() + out.opacity.sum()).backward()
    for g in (theta.grad, xi.grad, blob.scale.grad, blob.center.grad):
        assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_render_is_differentiable_in_theta_exactly():
    blob = Blob()
    rays = rays_along_z(torch.tensor([[0.0, 0.0], [0.02, -0.01]]), dtype=torch.float64)

    def rgb_of(theta):
        return render_rays(blob, rays, BOX, theta=theta, step=STEP, transmittance_eps=1e-300).rgb

    assert torch.autograd.gradcheck(rgb_of, (torch.tensor([0.3], dtype=torch.float64, requires_grad=True),))


def test_theta_per_ray_equals_a_shared_theta():
    field = Sphere(growth=0.04)
    rays = rays_along_z(torch.rand(16, 2, generator=torch.Generator().manual_seed(1)) * 0.16 - 0.08)
    shared = render_rays(field, rays, BOX, theta=torch.tensor([0.5]), step=STEP, outputs=("rgb", "opacity"))
    per_ray = render_rays(field, rays, BOX, theta=torch.full((16, 1), 0.5), step=STEP, outputs=("rgb", "opacity"))
    torch.testing.assert_close(shared.rgb, per_ray.rgb)
    assert shared.opacity.sum() > 0


def test_jitter_is_reproducible_and_keeps_the_constant_density_opacity_exact():
    rays = rays_along_z(torch.zeros(4, 2))
    outs = [
        render_rays(Constant(5.0), rays, BOX, step=STEP, outputs=("depth", "opacity"), jitter=True, generator=torch.Generator().manual_seed(s))
        for s in (0, 0, 1)
    ]
    torch.testing.assert_close(outs[0].depth, outs[1].depth)
    assert not torch.equal(outs[0].depth, outs[2].depth)
    for o in outs:
        torch.testing.assert_close(o.opacity, torch.full((4,), 1 - math.exp(-1.0)))


def test_max_samples_caps_the_intervals_per_ray():
    out = render_rays(Constant(0.1), rays_along_z([[0.0, 0.0]]), BOX, step=1e-6, max_samples=16, outputs=("opacity",))
    assert 14 <= out.n_samples <= 16  # the lattice may cut a partial interval at either end
    assert out.opacity.item() == pytest.approx(1 - math.exp(-0.02), rel=1e-6)


def test_bad_arguments_are_refused_with_a_clear_message():
    rays = rays_along_z([[0.0, 0.0]])
    with pytest.raises(ValueError, match="outputs must be"):
        render_rays(Sphere(), rays, BOX, step=STEP, outputs=("normals",))
    with pytest.raises(ValueError, match="step must be"):
        render_rays(Sphere(), rays, BOX, step=0.0)
    with pytest.raises(ValueError, match=r"theta must be \[k\] or \[n_rays=1, k\]"):
        render_rays(Sphere(), rays, BOX, theta=torch.zeros(3, 1), step=STEP)
    with pytest.raises(ValueError, match="transmittance_eps"):
        render_rays(Sphere(), rays, BOX, step=STEP, transmittance_eps=0.0)


# --------------------------------------------------------------------------------------------
# Occupancy grid


def test_occupancy_lookup_hand_checked():
    occ = torch.zeros(2, 2, 2, dtype=torch.bool)
    occ[1, 0, 1] = True  # the cell [0.5, 1) x [0, 0.5) x [0.5, 1)
    grid = OccupancyGrid(torch.tensor([[0.0, 0, 0], [1, 1, 1]]), occ)
    x = torch.tensor([[0.75, 0.25, 0.75], [0.25, 0.25, 0.75], [1.0, 0.0, 1.0], [1.01, 0.25, 0.75], [0.75, 0.25, -0.01]])
    assert grid.occupied(x).tolist() == [True, False, True, False, False]
    torch.testing.assert_close(grid.bounds(), torch.tensor([[0.5, 0.0, 0.5], [1.0, 0.5, 1.0]]))
    assert grid.fraction == 1 / 8 and grid.resolution == (2, 2, 2)
    assert OccupancyGrid.full(BOX, 4).occupied(torch.zeros(1, 3)).item()


def test_a_grid_from_points_holds_their_cells_grown_by_the_dilation():
    box = torch.tensor([[0.0, 0, 0], [1, 1, 1]])
    points = torch.tensor([[0.05, 0.05, 0.05], [1.0, 1.0, 1.0], [0.55, 0.35, 0.95], [1.5, 0.5, 0.5]])  # the last outside
    grid = OccupancyGrid.from_points(box, 10, points)
    assert grid.resolution == (10, 10, 10) and int(grid.occupancy.sum()) == 3  # the far corner is the last cell's
    assert grid.occupancy[0, 0, 0] and grid.occupancy[9, 9, 9] and grid.occupancy[5, 3, 9]
    grown = OccupancyGrid.from_points(box, 10, points[2:3], dilate=1)
    assert int(grown.occupancy.sum()) == 3 * 3 * 2  # a cube of 3 cells, cut by the box's face at z
    assert grown.occupied(torch.tensor([[0.45, 0.25, 0.85], [0.35, 0.35, 0.95]])).tolist() == [True, False]


def test_grid_along_rays_agrees_with_the_pointwise_lookup_per_configuration_bin():
    g = torch.Generator().manual_seed(5)
    grid = OccupancyGrid(BOX, torch.rand(3, 8, 8, 8, generator=g) > 0.6, torch.tensor([[0.0], [3.0]]))
    origins = torch.rand(20, 3, generator=g) * 0.2 - 0.1
    directions = torch.nn.functional.normalize(torch.randn(20, 3, generator=g), dim=-1)
    t = torch.rand(20, 16, generator=g) * 0.05  # short steps: every point stays near the box
    theta = torch.rand(20, 1, generator=g) * 3
    x = origins[:, None] + t[..., None] * directions[:, None]
    inside = ((x >= BOX[0]) & (x <= BOX[1])).all(-1)
    pointwise = grid.occupied(x.reshape(-1, 3), theta.repeat_interleave(16, 0)).reshape(20, 16)
    along = grid.along(origins, directions, theta)
    assert torch.equal(along(t)[inside], pointwise[inside]) and pointwise.any() and not pointwise.all()
    kept = torch.tensor([3, 7])
    assert torch.equal(along.select(kept)(t[kept]), along(t)[kept])
    shared = grid.along(origins, directions, torch.tensor([2.5]))  # one theta: the last bin for every ray
    last = grid.occupied(x.reshape(-1, 3), torch.tensor([2.5])).reshape(20, 16)
    assert torch.equal(shared(t)[inside], last[inside])


def test_grid_validation_errors():
    with pytest.raises(ValueError, match="max > min"):
        OccupancyGrid(torch.tensor([[0.0, 0, 0], [0, 1, 1]]), torch.ones(2, 2, 2))
    with pytest.raises(ValueError, match="needs theta_range"):
        OccupancyGrid(BOX, torch.ones(4, 2, 2, 2))
    with pytest.raises(ValueError, match=r"\[Rx, Ry, Rz\]"):
        OccupancyGrid(BOX, torch.ones(2, 2))


def test_grid_from_field_never_drops_the_sphere_at_any_theta():
    field = Sphere(radius=0.03, growth=0.04)  # radius 3 cm at theta = 0 .. 7 cm at theta = 1
    field.theta_lower, field.theta_upper = torch.tensor([0.0]), torch.tensor([1.0])
    grid = OccupancyGrid.from_field(field, BOX, 16, theta_bins=4)
    assert grid.occupancy.shape == (4, 16, 16, 16)
    g = torch.Generator().manual_seed(0)
    theta = torch.cat([torch.tensor([0.0, 1.0]), torch.rand(998, generator=g)])[:, None]
    direction = torch.nn.functional.normalize(torch.randn(1000, 3, generator=g), dim=-1)
    x = direction * (torch.rand(1000, 1, generator=g) * (0.03 + 0.04 * theta))  # inside the sphere at its theta
    assert grid.occupied(x, theta).all() and grid.occupied(x).all()
    small = grid.bounds(torch.tensor([0.0]))  # the first bin's ball is smaller than the union's
    assert (small[1] - small[0] < grid.bounds()[1] - grid.bounds()[0]).all()
    far = torch.tensor([[0.0, 0.0, 0.095]])  # outside even the largest sphere, beyond the dilation
    assert not grid.occupied(far).item()


def test_grid_from_field_with_explicit_theta_samples_is_one_union_grid():
    field = Sphere(radius=0.02, growth=0.04)
    grid = OccupancyGrid.from_field(field, BOX, 16, theta_samples=torch.tensor([[0.0], [0.5], [1.0]]), passes=1)
    assert grid.occupancy.shape == (16, 16, 16) and grid.theta_range is None
    assert grid.occupied(torch.tensor([[0.055, 0.0, 0.0]])).item()  # inside the theta = 1 ball only


def test_grid_skips_empty_cells_without_changing_the_render():
    field = Sphere(center=(0.02, 0.0, 0.01), radius=0.04, rgb=(0.2, 0.9, 0.4))
    grid = OccupancyGrid.from_field(field, BOX, 32)
    rays = rays_along_z(torch.rand(200, 2, generator=torch.Generator().manual_seed(2)) * 0.2 - 0.1)
    exact = {"step": STEP, "outputs": ("rgb", "depth", "opacity"), "transmittance_eps": 1e-30}  # no early stop
    field.points.clear()
    full = render_rays(field, rays, BOX, **exact)
    n_full = field.n_evaluated
    field.points.clear()
    skipped = render_rays(field, rays, BOX, grid=grid, **exact)
    assert skipped.n_samples < n_full / 5
    assert grid.occupied(torch.cat(field.points)).all()  # nothing evaluated in an empty cell
    for a, b in zip((full.rgb, full.depth, full.opacity), (skipped.rgb, skipped.depth, skipped.opacity)):
        torch.testing.assert_close(a, b)


def test_an_empty_grid_renders_background_without_evaluating():
    field = Sphere()
    grid = OccupancyGrid(BOX, torch.zeros(4, 4, 4, dtype=torch.bool))
    out = render_rays(field, rays_along_z([[0.0, 0.0]]), BOX, grid=grid, step=STEP, background=0.3, outputs=("rgb", "opacity"))
    assert out.n_samples == 0 and out.opacity.item() == 0 and torch.allclose(out.rgb, torch.tensor(0.3))


# --------------------------------------------------------------------------------------------
# Images


def camera_looking_at_origin(distance=0.5, width=64, height=48) -> tuple[Pinhole, torch.Tensor]:
    camera = Pinhole.primesense(width, height)
    T_world_cam = look_at(torch.tensor([0.0, -distance, 0.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    return camera, invert_pose(T_world_cam)


def test_render_image_of_a_sphere_has_the_right_depth_and_silhouette():
    camera, T_cam_obj = camera_looking_at_origin(width=160, height=120)
    field = Sphere(sigma=1e5)  # opaque within one interval
    images = render_image(field, camera, T_cam_obj, aabb=BOX, step=STEP, outputs=("rgb", "depth", "opacity"), background=0.1)
    assert images["rgb"].shape == (120, 160, 3) and images["depth"].shape == images["opacity"].shape == (120, 160)
    assert all(v.dtype == torch.float32 for v in images.values())
    assert images["depth"][60, 80].item() == pytest.approx(0.45, abs=STEP)  # front of the ball, on the axis
    mask = images["opacity"] > 0.5
    radius_px = camera.K[0, 0].item() * 0.05 / math.sqrt(0.5**2 - 0.05**2)  # tangent cone of the ball
    assert mask.sum().item() == pytest.approx(math.pi * radius_px**2, rel=0.05)
    assert (images["depth"][~mask] == 0).all()
    torch.testing.assert_close(images["rgb"][0, 0], torch.full((3,), 0.1))
    torch.testing.assert_close(images["rgb"][60, 80], torch.tensor([1.0, 0.5, 0.0]))


def test_render_image_equals_render_rays_over_every_pixel():
    camera, T_cam_obj = camera_looking_at_origin(distance=0.35)
    field = Sphere(center=(0.03, 0.0, -0.02))
    images = render_image(field, camera, T_cam_obj, aabb=BOX, step=STEP, outputs=("rgb", "opacity"))
    rays = camera.rays().transform(invert_pose(T_cam_obj))
    out = render_rays(field, rays, BOX, step=STEP, outputs=("rgb", "opacity"))
    torch.testing.assert_close(images["rgb"].reshape(-1, 3), out.rgb)
    torch.testing.assert_close(images["opacity"].reshape(-1), out.opacity)


def test_a_box_behind_the_camera_renders_nothing():
    camera, T_cam_obj = camera_looking_at_origin()
    behind = make_pose(so3_exp(torch.tensor([0.0, math.pi, 0.0])), torch.zeros(3)) @ T_cam_obj
    field = Sphere()
    images = render_image(field, camera, behind, aabb=BOX, step=STEP, outputs=("opacity",))
    assert not field.points and images["opacity"].sum() == 0


# --------------------------------------------------------------------------------------------
# Part composition


def two_parts(second_offset=(0.0, 0.0, 0.08)):
    """Two spheres defined at their own origins, posed in the object frame: red at 0, blue at an offset."""
    part_box = torch.tensor([[-0.05] * 3, [0.05] * 3])
    red = Sphere(radius=0.04, sigma=200.0, rgb=(1.0, 0.0, 0.0), aabb=part_box)
    blue = Sphere(radius=0.03, sigma=300.0, rgb=(0.0, 0.0, 1.0), aabb=part_box)
    R = so3_exp(torch.tensor([0.0, 0.0, 0.7]))
    T_obj_part = torch.stack([torch.eye(4), make_pose(R, torch.tensor(second_offset))])
    return [red, blue], T_obj_part


def test_composed_aabb_covers_the_posed_part_boxes():
    boxes = torch.tensor([[[-1.0, -1, -1], [1, 1, 1]], [[0.0, 0, 0], [1, 2, 3]]])
    T = torch.stack([torch.eye(4), make_pose(torch.eye(3), torch.tensor([10.0, 0.0, 0.0]))])
    torch.testing.assert_close(composed_aabb(boxes, T), torch.tensor([[-1.0, -1, -1], [11, 2, 3]]))


def test_volumetric_composition_equals_the_analytic_union():
    parts, T_obj_part = two_parts(second_offset=(0.0, 0.0, 0.05))  # the balls overlap

    def union(x, d, theta=None):
        s1 = torch.where(x.norm(dim=-1) < 0.04, 200.0, 0.0)
        s2 = torch.where((x - torch.tensor([0.0, 0.0, 0.05])).norm(dim=-1) < 0.03, 300.0, 0.0)
        sigma = s1 + s2
        rgb = torch.stack([s1, torch.zeros_like(s1), s2], -1) / sigma.clamp_min(1e-30)[:, None]
        return sigma, rgb

    composition = compose_parts(parts, [None, None], T_obj_part)
    box = composition.aabb
    g = torch.Generator().manual_seed(3)
    offsets = torch.stack([torch.rand(300, generator=g) * 0.12 - 0.06, torch.zeros(300), torch.rand(300, generator=g) * 0.16 - 0.05], -1)
    rays = Rays(torch.tensor([0.0, -1.0, 0.0]) + offsets, torch.tensor([[0.0, 1.0, 0.0]]).expand(300, 3), torch.ones(300))
    exact = {"step": STEP, "outputs": ("rgb", "depth", "opacity"), "transmittance_eps": 1e-30}  # no early stop
    got = render_rays(composition, rays, box, grid=composition, **exact)
    want = render_rays(union, rays, box, **exact)
    for a, b in zip((got.rgb, got.depth, got.opacity), (want.rgb, want.depth, want.opacity)):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    mixed = (got.rgb[:, 0] > 0.05) & (got.rgb[:, 2] > 0.05)
    assert mixed.any()  # some rays cross both balls: the density-weighted colour matters
    for part in parts:  # each part is evaluated only inside its own box
        seen = torch.cat(part.points)
        assert ((seen >= part.aabb[0] - 1e-6) & (seen <= part.aabb[1] + 1e-6)).all()


def test_volumetric_composition_shows_the_nearer_part():
    parts, T_obj_part = two_parts()  # blue sits 8 cm further along +z
    composition = compose_parts(parts, [None, None], T_obj_part)
    toward_plus_z = rays_along_z([[0.0, 0.0]] * 2)  # meets red first
    toward_minus_z = Rays(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.0, 0.0, -1.0]]), torch.ones(1))  # blue first
    out = render_rays(composition, toward_plus_z, composition.aabb, grid=composition, step=STEP, outputs=("rgb", "depth", "opacity"))
    torch.testing.assert_close(out.rgb[0], torch.tensor([1.0, 0.0, 0.0]), atol=1e-3, rtol=0)  # T < 1e-3 left
    # surface at 0.96; with sigma = 200 the expected depth lies 1 / sigma behind it
    assert (out.depth / out.opacity)[0].item() == pytest.approx(0.96 + 1 / 200, abs=2 * STEP)
    out = render_rays(composition, toward_minus_z, composition.aabb, grid=composition, step=STEP)
    torch.testing.assert_close(out.rgb[0], torch.tensor([0.0, 0.0, 1.0]), atol=1e-3, rtol=0)


def test_the_composition_as_its_own_occupancy_changes_no_pixel():
    parts, T_obj_part = two_parts()
    composition = compose_parts(parts, [None, None], T_obj_part)
    camera, T_cam_obj = camera_looking_at_origin(distance=0.4, width=40, height=30)
    exact = {"step": STEP, "outputs": ("rgb", "depth", "opacity"), "transmittance_eps": 1e-30}  # no early stop
    with_grid = render_image(composition, camera, T_cam_obj, aabb=BOX, grid=composition, **exact)
    without = render_image(composition, camera, T_cam_obj, aabb=BOX, **exact)
    for name in exact["outputs"]:
        torch.testing.assert_close(with_grid[name], without[name])
    assert (with_grid["opacity"] > 0.5).sum() > 50
    rays = camera.rays().transform(invert_pose(T_cam_obj))
    skipping = render_rays(composition, rays, BOX, grid=composition, **exact)
    assert skipping.n_samples < 0.5 * render_rays(composition, rays, BOX, **exact).n_samples


def test_the_composition_answers_the_occupancy_protocol():
    parts, T_obj_part = two_parts()
    composition = compose_parts(parts, [None, None], T_obj_part)
    torch.testing.assert_close(composition.bounds(), composition.aabb)
    x = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.08], [0.0, 0.0, 0.2], [0.06, 0.0, 0.0]])
    assert composition.occupied(x).tolist() == [True, True, False, False]  # 0.06 > the red box's 0.05
    rays = rays_along_z([[0.0, 0.0], [0.08, 0.0]], z0=-0.1)  # the second passes beside both (rotated) boxes
    t = torch.tensor([[0.1, 0.18, 0.3], [0.1, 0.18, 0.3]])
    along = composition.along(rays.origins, rays.directions)
    assert along(t).tolist() == [[True, True, False], [False, False, False]]
    assert along.select(torch.tensor([1]))(t[1:]).tolist() == [[False, False, False]]


# --------------------------------------------------------------------------------------------
# The bundled clamp and the articulated field built from its parts

CLAMP = Path(__file__).resolve().parents[1] / "models" / "clamp.narf"


@pytest.fixture(scope="module")
def clamp():
    from narf_core.bundle import load_bundle

    return load_bundle(CLAMP)


def clamp_view(model) -> tuple[Pinhole, torch.Tensor, torch.Tensor]:
    camera = Pinhole.primesense(64, 48)
    center = ((model.aabb[0] + model.aabb[1]) / 2).double()
    T_obj_cam = look_at(center + torch.tensor([0.2, -0.25, 0.15], dtype=torch.float64), center, torch.tensor([0, 0, 1.0], dtype=torch.float64))
    return camera, invert_pose(T_obj_cam).float(), (model.lower + model.upper) / 2


def test_the_bundled_clamp_loads_and_renders_in_both_modes(clamp):
    camera, T_cam_obj, theta = clamp_view(clamp)
    images = {mode: clamp.render(T_cam_obj, theta, camera, outputs=("rgb", "opacity"), mode=mode) for mode in ("narf", "parts")}
    for mode, out in images.items():
        assert torch.isfinite(out["rgb"]).all() and (out["opacity"] > 0.5).sum() > 100, mode
    seen = [images[mode]["opacity"] > 0.5 for mode in ("narf", "parts")]
    assert (seen[0] & seen[1]).sum() / (seen[0] | seen[1]).sum() > 0.9  # the distilled field and the parts agree


def test_marching_an_articulated_field_only_along_its_parts_spans_renders_the_same(clamp, monkeypatch):
    """The marcher starts and ends each ray where the posed part grids can be occupied (their span):
    the same image as marching the whole box, from no more occupancy lookups (on the clamp the bar's
    occupied box is the object's, so no fewer either; parts apart from each other, as a gripper's, save some)."""
    from dataclasses import replace

    from narf_core import sampling
    from narf_core.fields import ArticulatedField
    from narf_core.fields.articulated import PosedGridRays

    field = ArticulatedField.from_parts(clamp.kinematics, clamp.part_fields, clamp.part_grids, clamp.aabb).eval().requires_grad_(False)
    model = replace(clamp, field=field)
    camera, T_cam_obj, theta = clamp_view(clamp)
    looked_up = []
    candidates = sampling._candidates
    monkeypatch.setattr(sampling, "_candidates", lambda live, width: looked_up.append(live.ids.numel() * width) or candidates(live, width))
    spans = model.render(T_cam_obj, theta, camera, outputs=("rgb", "opacity"), mode="narf")
    with_spans, looked_up[:] = sum(looked_up), []
    monkeypatch.delattr(PosedGridRays, "span")
    box = model.render(T_cam_obj, theta, camera, outputs=("rgb", "opacity"), mode="narf")
    assert (box["opacity"] > 0.5).sum() > 100 and 0 < with_spans <= sum(looked_up)
    torch.testing.assert_close(spans["rgb"], box["rgb"], rtol=0, atol=2e-3)
    torch.testing.assert_close(spans["opacity"], box["opacity"], rtol=0, atol=2e-3)


def test_an_articulated_field_from_the_clamps_parts_renders_like_parts_mode_with_the_same_gradients(clamp):
    """Images equal to float rounding; the gradient of a rendered loss with respect to θ and the
    camera pose is the one parts mode gives (FK inside the field is differentiable like the URDF's)."""
    from dataclasses import replace

    from narf_core.fields import ArticulatedField

    field = ArticulatedField.from_parts(clamp.kinematics, clamp.part_fields, clamp.part_grids, clamp.aabb).eval().requires_grad_(False)
    model = replace(clamp, field=field)
    camera, T_cam_obj, theta = clamp_view(clamp)
    narf = model.render(T_cam_obj, theta, camera, outputs=("rgb", "opacity"), mode="narf")
    parts = model.render(T_cam_obj, theta, camera, outputs=("rgb", "opacity"), mode="parts")
    assert (parts["opacity"] > 0.5).sum() > 100
    torch.testing.assert_close(narf["rgb"], parts["rgb"], rtol=0, atol=2e-3)
    torch.testing.assert_close(narf["opacity"], parts["opacity"], rtol=0, atol=2e-3)

    pixels = torch.stack(torch.meshgrid(torch.arange(16, 48), torch.arange(12, 36), indexing="xy"), -1).reshape(-1, 2)
    rays_cam = camera.rays(pixels)
    gradients = {}
    for mode in ("narf", "parts"):
        xi = torch.zeros(6, requires_grad=True)
        th = theta.clone().requires_grad_(True)
        T_obj_cam = invert_pose(T_cam_obj) @ se3_exp(xi)
        rays = Rays(T_obj_cam[:3, 3].expand(len(pixels), 3), rays_cam.directions @ T_obj_cam[:3, :3].T, rays_cam.z_per_t)
        out = model.render_rays(rays, th, mode=mode, outputs=("rgb", "opacity"))
        (out.rgb.sum() + out.opacity.sum()).backward()
        gradients[mode] = torch.cat([xi.grad, th.grad])
    assert gradients["parts"].abs().max() > 0
    torch.testing.assert_close(gradients["narf"], gradients["parts"], rtol=0.02, atol=1e-3 * float(gradients["parts"].abs().max()))


def test_an_articulated_fields_posed_grids_read_each_part_grid_in_its_own_frame(clamp):
    """``PosedGrids.occupied`` (all part grids in one flat table, the index summed in float32) is, point by point,
    any part's own grid read in that part's frame at θ: inside and outside the boxes, and at a cell corner and the
    far corner (the last cell of the flat table's part) of every part's grid."""
    from narf_core.fields import ArticulatedField
    from narf_core.geometry import transform_points

    field = ArticulatedField.from_parts(clamp.kinematics, clamp.part_fields, clamp.part_grids, clamp.aabb)
    theta = clamp.lower + (clamp.upper - clamp.lower) * 0.3
    g = torch.Generator().manual_seed(5)
    x = clamp.aabb[0] - 0.01 + torch.rand(100_000, 3, generator=g) * (clamp.aabb[1] - clamp.aabb[0] + 0.02)
    T_part_obj = field.part_from_object(theta, 1)
    grids = field.part_grids()
    corners = [transform_points(torch.linalg.inv(T_part_obj[i]), gr.aabb[0] + gr.cell_size * torch.tensor(idx))
               for i, gr in enumerate(grids) for idx in ([3.0, 5.0, 2.0], gr.occupancy.shape)]  # corner, far corner
    x = torch.cat([x, torch.stack(corners)])
    own = torch.stack([gr.occupied(transform_points(T_part_obj[i], x)) for i, gr in enumerate(grids)], -1).any(-1)
    held = field.occupancy(theta).occupied(x)
    assert 1000 < int(own.sum()) < len(x) - 1000
    assert int((held != own).sum()) <= 2  # a point on a cell face may round to either side


def test_an_articulated_fields_occupied_near_holds_every_point_within_a_block_of_an_occupied_one(clamp):
    """``PosedGrids.occupied_near`` (a tracked frame's samples near an occupied cell, narf_core.track): every point
    ``occupied`` holds, every point moved from one by less than a block (``_BLOCK`` cells of its part's grid)
    along an axis of that grid, and far fewer points of the box than it holds not."""
    from narf_core.fields import ArticulatedField
    from narf_core.fields.articulated import _BLOCK

    field = ArticulatedField.from_parts(clamp.kinematics, clamp.part_fields, clamp.part_grids, clamp.aabb)
    theta = (clamp.lower + clamp.upper) / 2
    grids = field.occupancy(theta)
    g = torch.Generator().manual_seed(3)
    x = clamp.aabb[0] + torch.rand(200_000, 3, generator=g) * (clamp.aabb[1] - clamp.aabb[0])
    occupied, near = grids.occupied(x), grids.occupied_near(x)
    assert 1000 < int(occupied.sum()) and bool(near[occupied].all())
    assert int(near.sum()) < 0.5 * len(x)
    # the smallest block of any part's grid: a move shorter than it along any direction in the object frame (the
    # parts posed by FK at θ, turned) is shorter than a block along each axis of every part's grid
    block = min(float(gr.cell_size.min()) for gr in field.part_grids()) * _BLOCK
    for axis in range(3):
        for sign in (-1.0, 1.0):
            moved = x[occupied].clone()
            moved[:, axis] += sign * 0.95 * block
            assert bool(grids.occupied_near(moved).all()), (axis, sign)
