"""Radiance fields: encodings, the K-planes, FastNeRF and articulated fields, their configs, gradients and a tiny fit."""

import json
import math

import pytest
import torch
import torch.nn.functional as F

from narf_core.fields import ArticulatedField, FastNeRFField, KPlanesField, RadianceField, make_field
from narf_core.fields import articulated
from narf_core.fields.articulated import chain_spec
from narf_core.fields.base import SIGMA_MAX_LOG, trunc_exp
from narf_core.fields.encodings import frequency_encoding, frequency_encoding_size, sample_plane, spherical_harmonics
from narf_core.fields.composed import ComposedField, compose_parts
from narf_core.fields.kplanes import total_variation
from narf_core.geometry import Rays
from narf_core.kinematics import KinematicTree
from narf_core.render import render_rays
from narf_core.sampling import ray_aabb

pytest_plugins = ("conftest_model",)

AABB = [[-0.1, -0.05, -0.02], [0.1, 0.05, 0.02]]
SMALL = {
    "kplanes": {"resolution": (8, 16), "theta_resolution": (4, 8), "features": 4, "hidden": 16},
    "fastnerf": {"pos_width": 16, "pos_layers": 2, "dir_width": 8, "dir_layers": 1, "components": 4},
}


def small_field(arch: str, k: int, **kw) -> RadianceField:
    limits = {} if k == 0 else {"theta_lower": [-1.0] * k, "theta_upper": [0.5] * k}
    return make_field({"arch": arch, "aabb": AABB, **limits, **SMALL[arch], **kw})


def points(n: int, dtype=torch.float32, seed: int = 0) -> torch.Tensor:
    box = torch.tensor(AABB, dtype=dtype)
    u = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    return box[0] + u * (box[1] - box[0])


# --------------------------------------------------------------------------------------------
# Encodings


def test_frequency_encoding_values():
    x = torch.tensor([[0.5, -1.0]])
    out = frequency_encoding(x, 2)
    assert out.shape == (1, frequency_encoding_size(2, 2)) == (1, 10)
    # layout: x, sin(2^l pi x) channel-major, cos(...)
    expected_sin = [math.sin(math.pi * 0.5), math.sin(2 * math.pi * 0.5), math.sin(-math.pi), math.sin(-2 * math.pi)]
    torch.testing.assert_close(out[0, :2], x[0])
    torch.testing.assert_close(out[0, 2:6], torch.tensor(expected_sin), atol=1e-6, rtol=0)
    torch.testing.assert_close(out[0, 6:], torch.tensor([0.0, -1.0, -1.0, 1.0]), atol=1e-6, rtol=0)


def test_spherical_harmonics_known_values_and_sizes():
    d = torch.tensor([[0.0, 0.0, 1.0]])
    sh = spherical_harmonics(d, 2)
    torch.testing.assert_close(sh, torch.tensor([[0.28209479, 0.0, 0.48860251, 0.0]]))
    assert [spherical_harmonics(d, g).shape[1] for g in range(5)] == [0, 1, 4, 9, 16]
    with pytest.raises(ValueError, match="degree"):
        spherical_harmonics(d, 5)


def test_spherical_harmonics_are_orthonormal_on_the_sphere():
    d = F.normalize(torch.randn(200_000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1)
    sh = spherical_harmonics(d, 4)
    gram = 4 * math.pi * sh.T @ sh / d.shape[0]  # Monte-Carlo integral over the sphere
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


def test_sample_plane_matches_grid_sample(dtype):
    plane = torch.randn(5, 7, 3, dtype=dtype)
    coords = torch.rand(50, 2, dtype=dtype) * 2.4 - 1.2
    ref = F.grid_sample(plane.permute(2, 0, 1)[None], coords[None, None], align_corners=True, padding_mode="border")
    close = {"atol": 3e-5, "rtol": 0}  # coordinates are pulled 1e-6 off the border (about 1e-5 texel here)
    torch.testing.assert_close(sample_plane(plane, coords), ref[0, :, 0].T, **close)
    # corners of the plane are its corner texels
    corners = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]], dtype=dtype)
    expected = torch.stack([plane[0, 0], plane[0, -1], plane[-1, 0], plane[-1, -1]])
    torch.testing.assert_close(sample_plane(plane, corners), expected, **close)


def test_sample_plane_gradients_are_exact():
    plane = torch.randn(4, 6, 3, dtype=torch.float64, requires_grad=True)
    coords = (torch.rand(30, 2, dtype=torch.float64) * 1.9 - 0.95).requires_grad_(True)
    assert torch.autograd.gradcheck(sample_plane, (plane, coords))


def test_sample_plane_gradient_at_and_beyond_the_border():
    plane = torch.arange(12.0, dtype=torch.float64).reshape(3, 4, 1)  # value = 4 * row + col
    coords = torch.tensor([[1.0, 0.0], [-1.0, 1.0], [1.5, 0.0]], dtype=torch.float64, requires_grad=True)
    sample_plane(plane, coords).sum().backward()
    # d value / d u = 1 per column = (W - 1) / 2 per normalised unit; one-sided at the edge, 0 beyond
    close = {"atol": 0, "rtol": 1e-5}
    torch.testing.assert_close(coords.grad[:, 0], torch.tensor([1.5, 1.5, 0.0], dtype=torch.float64), **close)
    torch.testing.assert_close(coords.grad[1, 1], torch.tensor(4.0, dtype=torch.float64), **close)


def test_sample_plane_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\[H, W, F\]"):
        sample_plane(torch.zeros(1, 5, 2), torch.zeros(3, 2))
    with pytest.raises(ValueError, match=r"\[n, 2\]"):
        sample_plane(torch.zeros(4, 5, 2), torch.zeros(3, 3))


# --------------------------------------------------------------------------------------------
# Both architectures


def test_trunc_exp_is_finite_with_a_gradient_for_huge_inputs():
    raw = torch.tensor([-1e4, 0.0, 20.0, 1e4], requires_grad=True)
    sigma = trunc_exp(raw)
    sigma.sum().backward()
    assert torch.isfinite(sigma).all() and torch.isfinite(raw.grad).all()
    sigma = sigma.detach()
    assert sigma[0] == 0 and float(sigma[-1]) == pytest.approx(math.exp(SIGMA_MAX_LOG), rel=1e-5)
    assert raw.grad[-1] > 0  # still pushed down when saturated


@pytest.mark.parametrize("arch", ["kplanes", "fastnerf"])
@pytest.mark.parametrize("k", [0, 1, 2])
def test_field_shapes_dtypes_and_ranges(arch, k, dtype):
    field = small_field(arch, k)
    x = points(64, dtype)
    d = F.normalize(torch.randn(64, 3, dtype=dtype), dim=-1)
    theta = None if k == 0 else torch.full((k,), -0.2, dtype=dtype)
    sigma, rgb = field(x, d, theta)
    assert sigma.shape == (64,) and rgb.shape == (64, 3)
    assert sigma.dtype == rgb.dtype == torch.float32  # fields compute in their parameters' dtype
    assert (sigma >= 0).all() and torch.isfinite(sigma).all()
    assert ((rgb > 0) & (rgb < 1)).all()
    torch.testing.assert_close(field.density_only(x, theta), sigma)
    if k:  # per-sample theta gives the same as a shared one
        torch.testing.assert_close(field(x, d, theta.expand(64, k))[0], sigma)
    assert field.n_theta == k


@pytest.mark.parametrize("arch", ["kplanes", "fastnerf"])
def test_gradients_wrt_x_and_theta_are_finite_including_at_the_limits(arch):
    field = small_field(arch, 1)
    with torch.no_grad():  # make the planes/weights non-trivial so gradients are not accidentally 0
        for p in field.parameters():
            p.add_(0.3 * torch.randn_like(p))
    x = points(32).requires_grad_(True)
    d = F.normalize(torch.randn(32, 3), dim=-1)
    theta = torch.tensor([-1.0] * 16 + [0.5] * 16)[:, None].requires_grad_(True)  # exactly at the limits
    sigma, rgb = field(x, d, theta)
    (sigma.sum() + rgb.sum()).backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(theta.grad).all()
    assert x.grad.abs().sum() > 0 and theta.grad.abs().sum() > 0
    assert (theta.grad != 0).float().mean() > 0.5  # one-sided slope at the limit, not a dead clamp


def test_kplanes_theta_gradient_matches_finite_differences():
    field = small_field("kplanes", 1).double()
    with torch.no_grad():
        for p in field.parameters():
            p.add_(0.3 * torch.randn_like(p))
    x = points(8, torch.float64)
    theta = torch.tensor([-0.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: field.density_only(x, t), (theta,))


@pytest.mark.parametrize("arch", ["kplanes", "fastnerf"])
def test_config_round_trip_rebuilds_the_same_field(arch):
    field = small_field(arch, 1, **({"dir_degree": 2} if arch == "kplanes" else {}))
    config = json.loads(json.dumps(field.config()))  # JSON-able
    clone = make_field(config)
    assert type(clone) is {"kplanes": KPlanesField, "fastnerf": FastNeRFField}[arch]
    clone.load_state_dict(field.state_dict())
    x, d = points(16), F.normalize(torch.randn(16, 3), dim=-1)
    theta = torch.tensor([0.1])
    for a, b in zip(field(x, d, theta), clone(x, d, theta)):
        torch.testing.assert_close(a, b)
    assert clone.config() == config


def test_make_field_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown field architecture 'nerf'"):
        make_field({"arch": "nerf", "aabb": AABB})
    with pytest.raises(ValueError, match="needs an 'aabb'"):
        make_field({"arch": "kplanes"})
    with pytest.raises(ValueError, match="invalid 'kplanes' field config.*bogus"):
        make_field({"arch": "kplanes", "aabb": AABB, "bogus": 1})
    with pytest.raises(ValueError, match="max > min"):
        make_field({"arch": "kplanes", "aabb": [[0, 0, 0], [1, 0, 1]]})
    with pytest.raises(ValueError, match="upper > lower"):
        make_field({"arch": "fastnerf", "aabb": AABB, "theta_lower": [1.0], "theta_upper": [1.0]})
    with pytest.raises(ValueError, match="resolution"):
        make_field({"arch": "kplanes", "aabb": AABB, "resolution": [8, 16], "theta_resolution": [8]})


def test_theta_shape_errors():
    field = small_field("kplanes", 2)
    x = points(4)
    with pytest.raises(ValueError, match="needs a configuration"):
        field.density_only(x, None)
    with pytest.raises(ValueError, match=r"theta must be \[2\] or \[4, 2\]"):
        field.density_only(x, torch.zeros(3))
    with pytest.raises(ValueError, match="takes no configuration"):
        small_field("kplanes", 0).density_only(x, torch.zeros(1))


@pytest.mark.parametrize("arch", ["kplanes", "fastnerf"])
def test_untrained_fields_are_nearly_empty(arch):
    field = small_field(arch, 1)
    box = torch.tensor(AABB)
    diag = box[1] - box[0]
    rays = Rays(box[0][None] - 0.01 * diag, (diag / diag.norm())[None], torch.ones(1))  # the box diagonal
    out = render_rays(field, rays, box, theta=torch.zeros(1), step=float(diag.norm()) / 128, outputs=("opacity",))
    assert 0.02 < float(out.opacity.detach()) < 0.2


def test_kplanes_planes_init_and_total_variation():
    field = small_field("kplanes", 1)
    spatial = [p for p, (a, b) in zip(field.planes, field.pairs * 2) if b < 3]
    with_theta = [p for p, (a, b) in zip(field.planes, field.pairs * 2) if b >= 3]
    assert len(spatial) == 6 and len(with_theta) == 6
    assert all(((p >= 0.1) & (p <= 0.5)).all() for p in spatial)
    assert all((p == 1).all() for p in with_theta)
    assert total_variation(torch.ones(4, 5, 2)) == 0
    ramp = torch.arange(5.0)[None, :, None].expand(4, 5, 1)  # +1 per column
    assert total_variation(ramp) == pytest.approx(1.0)
    with torch.no_grad():
        assert float(field.regularization()) == pytest.approx(field.tv_weight * float(field.total_variation()))


def test_kplanes_spatial_planes_have_about_cubic_cells():
    field = make_field({"arch": "kplanes", "aabb": AABB, "resolution": [64], "theta_resolution": [8]})
    shapes = {pair: tuple(p.shape[:2]) for pair, p in zip(field.pairs, field.planes)}
    assert shapes[(0, 1)] == (32, 64) and shapes[(0, 2)] == (13, 64) and shapes[(1, 2)] == (13, 32)


# --------------------------------------------------------------------------------------------
# K-planes fits a tiny configuration-dependent scene


def _sphere_targets(rays: Rays, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact colour and opacity of a sphere at the origin of radius 0.02 + 0.03 theta, colour by height."""
    r = 0.02 + 0.03 * theta[:, 0]
    b = (rays.origins * rays.directions).sum(-1)
    c = (rays.origins**2).sum(-1) - r**2
    disc = b**2 - c
    hit = disc > 0
    t = -b - disc.clamp_min(0).sqrt()
    p = rays.origins + t[:, None] * rays.directions
    rgb = torch.stack([0.5 + 0.45 * p[:, 2] / r, 0.3 + 0 * r, 0.8 - 0.5 * theta[:, 0]], dim=-1)
    return torch.where(hit[:, None], rgb, 0.0), hit.float()


def _random_rays(n: int, g: torch.Generator) -> tuple[Rays, torch.Tensor]:
    eye = F.normalize(torch.randn(n, 3, generator=g), dim=-1) * 0.3
    target = (torch.rand(n, 3, generator=g) - 0.5) * 0.1
    d = F.normalize(target - eye, dim=-1)
    return Rays(eye, d, torch.ones(n)), torch.rand(n, 1, generator=g)


def test_kplanes_fits_a_theta_dependent_sphere():
    torch.manual_seed(0)
    box = torch.tensor([[-0.05] * 3, [0.05] * 3])
    field = KPlanesField(box, [0.0], [1.0], resolution=(16, 32), theta_resolution=(4, 8), features=8, hidden=32)
    step = float((box[1] - box[0]).norm()) / 48
    opt = torch.optim.Adam(field.parameters(), lr=0.03, eps=1e-15)
    decay = torch.optim.lr_scheduler.ExponentialLR(opt, 0.99)
    g = torch.Generator().manual_seed(0)
    for _ in range(200):
        rays, theta = _random_rays(512, g)
        rgb, opacity = _sphere_targets(rays, theta)
        out = render_rays(field, rays, box, theta=theta, step=step, outputs=("rgb", "opacity"), jitter=True, generator=g)
        loss = ((out.rgb - rgb) ** 2).mean() + ((out.opacity - opacity) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        decay.step()
    rays, theta = _random_rays(2000, torch.Generator().manual_seed(99))  # held-out views and theta
    rgb, _ = _sphere_targets(rays, theta)
    with torch.no_grad():
        out = render_rays(field, rays, box, theta=theta, step=step)
    psnr = -10 * math.log10(float(((out.rgb - rgb) ** 2).mean()))
    assert psnr > 25  # 26.6 dB; the error is mostly at the silhouette (31+ dB elsewhere)


# --------------------------------------------------------------------------------------------
# The articulated field: part K-planes posed by the forward kinematics inside the field

MIMIC_URDF = """<robot name="mimic">
  <link name="root"/><link name="a"/><link name="b"/>
  <joint name="drive" type="revolute"><parent link="root"/><child link="a"/><origin xyz="0.01 0 0.02" rpy="0.1 0 0.3"/>
    <axis xyz="0 0 1"/><limit lower="-0.8" upper="1.2" effort="1" velocity="1"/></joint>
  <joint name="follow" type="prismatic"><parent link="a"/><child link="b"/><axis xyz="1 0 0"/>
    <mimic joint="drive" multiplier="-0.5" offset="0.1"/></joint>
</robot>"""


def articulated_field(kin, **kw) -> ArticulatedField:
    """An untrained articulated field on ``kin`` with small random planes (every part over AABB)."""
    p = len(kin.part_names)
    field = ArticulatedField(
        AABB, kin.lower.tolist(), kin.upper.tolist(), chain=chain_spec(kin), part_aabbs=[AABB] * p,
        grid_shapes=[[4, 3, 2]] * p, resolution=(8, 16), features=4, hidden=16, **kw,
    )
    with torch.no_grad():
        field.atlas.uniform_(0.1, 0.9)
    return field


def _reverse_mode_jacobian(field, x: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``∂(σ, colour)/∂(x, θ) [n, 4, 3 + k]`` by one backward pass per output."""
    x, theta = x.clone().requires_grad_(True), theta.clone().requires_grad_(True)
    sigma, rgb = field(x, torch.zeros_like(x), theta)
    values = torch.cat([sigma[:, None], rgb], 1)
    return torch.stack([torch.cat(torch.autograd.grad(values[:, c].sum(), (x, theta), retain_graph=True), 1)
                        for c in range(4)], 1)


def _assert_jacobian_is_reverse_mode(field, x: torch.Tensor, theta: torch.Tensor, tolerance: float) -> None:
    values, derivatives = field.jacobian(x, theta)
    with torch.no_grad():
        sigma, rgb = field(x, torch.zeros_like(x), theta)
    torch.testing.assert_close(values, torch.cat([sigma[:, None], rgb], 1))
    expected = _reverse_mode_jacobian(field, x, theta)
    assert derivatives.shape == expected.shape
    for c in range(4):
        error = (derivatives[:, c] - expected[:, c]).norm() / expected[:, c].norm()
        assert expected[:, c].norm() > 0 and error < tolerance, (c, float(error))


def test_articulated_field_jacobian_is_its_reverse_mode_derivative():
    """The articulated field's derivatives in x and θ (forward differences along the lookup coordinates'
    exact tangents, each sample's parts fixed) agree with reverse mode through the field, for one θ and
    for one θ per sample (in runs, as a Gauss-Newton Jacobian's rays have them), on a revolute + mimic
    prismatic chain whose parts all move with the joint."""
    torch.manual_seed(0)  # the decoders' initialisation
    field = articulated_field(KinematicTree.from_urdf_string(MIMIC_URDF))
    box = torch.tensor(AABB)
    x = box[0] + (box[1] - box[0]) * torch.rand(3000, 3, generator=torch.Generator().manual_seed(3))
    theta = torch.tensor([0.4])
    # differences inside the texels, in float32 (the atlas's dtype): what is left is rounding and the decoder's kinks
    _assert_jacobian_is_reverse_mode(field, x, theta.expand(len(x), 1), 0.04)
    runs = torch.cat([torch.full((1500, 1), 0.4), torch.full((1500, 1), -0.3)])
    _assert_jacobian_is_reverse_mode(field, x, runs, 0.04)
    values, derivatives = field.jacobian(x[:0], theta)
    assert values.shape == (0, 4) and derivatives.shape == (0, 4, 4)


def test_in_texel_steps_keep_every_lookup_in_its_cell_where_there_is_room():
    """A step moves every coordinate by at most half its room to the next texel centre (forward or backward,
    where there is more), never beyond ``cap`` texels in the fastest coordinate, at least ``least``; a row
    that does not move steps 1."""
    from narf_core.fields.encodings import in_texel_step

    g = torch.Generator().manual_seed(5)
    texel = torch.rand(2000, 4, generator=g, dtype=torch.float64) * 50
    rate = torch.randn(2000, 4, generator=g, dtype=torch.float64)
    rate[:10] = 0.0
    step = in_texel_step(texel, rate, cap=0.05, least=1e-3)
    assert torch.equal(step[:10], torch.ones(10, dtype=torch.float64))
    moved = texel[10:] + step[10:, None] * rate[10:]
    fastest = (step[10:].abs() * rate[10:].abs().amax(1))
    assert bool((fastest <= 0.05 + 1e-12).all()) and bool((fastest >= 1e-3 - 1e-12).all())
    roomy = fastest > 1e-3 + 1e-9  # above the floor: inside the cell
    assert bool(torch.equal(moved.floor()[roomy], texel[10:].floor()[roomy]))
    assert roomy.float().mean() > 0.5 and bool((step[10:] < 0).any()) and bool((step[10:] > 0).any())


def test_kplanes_field_jacobian_is_its_reverse_mode_derivative():
    """The K-planes configuration field's derivatives in x and θ agree with reverse mode, θ at a limit
    too (a backward difference there); a view-dependent field has none."""
    torch.manual_seed(0)
    field = KPlanesField(AABB, [0.0], [1.0], resolution=(8, 16), theta_resolution=(4, 8), features=4, hidden=16)
    with torch.no_grad():
        for plane in field.planes:
            plane.uniform_(0.1, 0.9)
    field = field.double()  # float64: the differences' rounding out of the way (what is left: the decoder's
    # kinks, and the few samples whose grids' edges lie too close together for a step between them)
    g, box = torch.Generator().manual_seed(4), torch.tensor(AABB, dtype=torch.float64)
    x = box[0] + (box[1] - box[0]) * torch.rand(3000, 3, generator=g, dtype=torch.float64)
    theta = torch.rand(3000, 1, generator=g, dtype=torch.float64)
    theta[:100] = 1.0
    _assert_jacobian_is_reverse_mode(field, x, theta, 0.02)
    assert field.supports_jacobian
    view = KPlanesField(AABB, [0.0], [1.0], resolution=(8, 16), theta_resolution=(4, 8), dir_degree=2)
    assert not view.supports_jacobian
    with pytest.raises(ValueError, match="view direction"):
        view.jacobian(x, theta)


@pytest.mark.parametrize("urdf", ["articulated.urdf", "synth_articulated.urdf", "mimic"])
def test_articulated_field_kinematics_match_the_urdf(assets, urdf):
    """FK inside the field (revolute, prismatic, continuous, fixed chains, mimic joints) gives the
    kinematic tree's part poses, for one θ and for a batch."""
    kin = KinematicTree.from_urdf_string(MIMIC_URDF) if urdf == "mimic" else KinematicTree.from_urdf(assets / urdf, load_meshes=False)
    field = articulated_field(kin)
    g = torch.Generator().manual_seed(0)
    theta = kin.lower + (kin.upper - kin.lower) * torch.rand(5, kin.n_joints, generator=g, dtype=torch.float64)
    expected = kin.part_poses(theta).float()
    torch.testing.assert_close(field.part_poses(theta.float()), expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(field.part_poses(theta[2].float()), expected[2], atol=1e-5, rtol=0)


@pytest.mark.parametrize("urdf", ["synth_articulated.urdf", "mimic"])
@pytest.mark.parametrize("runs", [1, 3])
def test_rows_of_one_configuration_get_each_their_own_theta_derivative(assets, urdf, runs, monkeypatch):
    """Rows in runs of one θ (a render's samples, start by start) are looked up one run at a time, yet
    each row's θ, a leaf of its own, gets the derivative of that row alone, as looking every row up
    with its own FK gives: a Gauss-Newton Jacobian needs each ray's ∂/∂θ, not the run's total."""
    kin = KinematicTree.from_urdf_string(MIMIC_URDF) if urdf == "mimic" else KinematicTree.from_urdf(assets / urdf, load_meshes=False)
    field = articulated_field(kin)
    g = torch.Generator().manual_seed(1)
    n = 60
    x, d = points(n), torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    values = kin.lower + (kin.upper - kin.lower) * torch.rand(runs, kin.n_joints, generator=g, dtype=torch.float64)
    theta = values.float().repeat_interleave(n // runs, 0)
    weights = torch.randn(n, 4, generator=g)

    def evaluate():
        th = theta.clone().requires_grad_(True)
        sigma, rgb = field(x, d, th)
        out = torch.cat([sigma[:, None], rgb], -1)
        return out.detach(), torch.autograd.grad((out * weights).sum(), th)[0]

    out, grad = evaluate()
    assert int((grad.abs().sum(-1) > 0).sum()) > 2 * runs  # rows of moving parts see θ, not one row per run
    monkeypatch.setattr(articulated, "_MAX_RUNS", 0)  # every row through its own FK
    out_rows, grad_rows = evaluate()
    torch.testing.assert_close(out, out_rows, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grad, grad_rows, rtol=1e-4, atol=1e-5)



def test_the_composition_gives_rows_of_one_configuration_each_their_own_theta_derivative(tiny_model):
    """Equal rows of θ that are leaves of their own (a Jacobian's per-ray θ) each get the derivative of
    their own sample, as evaluating every sample alone gives, not the total on one row."""
    model = tiny_model
    field = ComposedField(model.part_fields, model.part_grids, model.kinematics.part_poses)
    g = torch.Generator().manual_seed(0)
    theta = (model.lower + model.upper) / 2
    x = model.aabb[0] + (model.aabb[1] - model.aabb[0]) * torch.rand(4000, 3, generator=g)
    x = x[field(x, torch.zeros_like(x), theta)[0] > 0][:24]
    assert x.shape[0] == 24
    d = torch.zeros_like(x)
    rows = theta.expand(len(x), -1).clone().requires_grad_(True)
    grad = torch.autograd.grad(field(x, d, rows)[0].sum(), rows)[0]
    alone = []
    for i in range(len(x)):
        one = theta.clone().requires_grad_(True)
        alone.append(torch.autograd.grad(field(x[i:i + 1], d[i:i + 1], one)[0].sum(), one)[0])
    torch.testing.assert_close(grad, torch.stack(alone), rtol=1e-4, atol=1e-6)
    assert int((grad.abs().sum(-1) > 0).sum()) > 1

def test_articulated_field_config_round_trip_and_errors(assets):
    kin = KinematicTree.from_urdf(assets / "synth_articulated.urdf", load_meshes=False)
    field = articulated_field(kin)
    config = json.loads(json.dumps(field.config()))
    rebuilt = make_field(config)
    rebuilt.load_state_dict(field.state_dict())
    x, theta = points(64), torch.tensor([0.05, 0.3])
    torch.testing.assert_close(rebuilt(x, torch.zeros_like(x), theta), field(x, torch.zeros_like(x), theta))
    with pytest.raises(ValueError, match="needs joint limits"):
        make_field({**config, "theta_lower": None, "theta_upper": None})
    with pytest.raises(ValueError, match="one box and one grid shape per part: the chain has 3 parts"):
        make_field({**config, "part_aabbs": config["part_aabbs"][:2]})
    driven = [5 if i == 1 else i for i in config["chain"]["theta_index"]]
    with pytest.raises(ValueError, match="joint 1 is driven by theta\\[5\\]"):
        make_field({**config, "chain": {**config["chain"], "theta_index": driven}})
    with pytest.raises(ValueError, match="theta must be \\[2\\] or \\[64, 2\\]"):
        field(x, torch.zeros_like(x), torch.zeros(3))


def test_posed_grids_span_holds_every_occupied_point_along_a_ray(assets):
    """Along each ray, every point the posed part grids call occupied lies within the ray's span (its
    segments through the parts' occupied boxes, narrowed on coarse blocks of the grids), and a ray with
    an empty span meets no occupied cell: the marcher starts and ends each ray there. The lookup along
    rays (one pass per part and axis) is the pointwise occupancy."""
    kin = KinematicTree.from_urdf(assets / "synth_articulated.urdf", load_meshes=False)
    p = len(kin.part_names)
    field = ArticulatedField(
        AABB, kin.lower.tolist(), kin.upper.tolist(), chain=chain_spec(kin), part_aabbs=[AABB] * p,
        grid_shapes=[[40, 20, 8]] * p, resolution=(8, 16), features=4, hidden=16,
    )
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for i in range(p):  # a few small occupied clusters per part
            grid = getattr(field, f"grid_{i}")
            grid.copy_(F.max_pool3d((torch.rand(grid.shape, generator=g) < 0.0005).float()[None], 3, 1, 1)[0].to(torch.uint8))
    theta = kin.lower.float() + (kin.upper - kin.lower).float() * 0.3
    origins = torch.randn(400, 3, generator=g) * 0.05
    directions = F.normalize(torch.randn(400, 3, generator=g), dim=-1)
    occupancy = field.occupancy(theta)
    rays = occupancy.along(origins, directions)
    near, far = rays.span()
    t = torch.linspace(0, 0.6, 6000).expand(400, -1)
    occupied = rays(t)
    assert occupied.any(1).sum() > 20 and (near > far).sum() > 50  # rays that meet parts and rays that miss them
    assert not (occupied & ((t < near[:, None]) | (t > far[:, None]))).any()
    box_near, box_far, box_hit = ray_aabb(rays.c, rays.cd, field.part_lookup().boxes)  # the occupied boxes alone
    box_near, box_far = torch.where(box_hit, box_near, math.inf).amin(-1), torch.where(box_hit, box_far, -math.inf).amax(-1)
    narrowed = (near > far) | (far - near < 0.8 * (box_far - box_near))
    assert (box_hit.any(-1) & narrowed).sum() > 20  # the blocks narrow the spans of rays through the boxes
    pointwise = occupancy.occupied((origins[:, None] + t[..., None] * directions[:, None]).reshape(-1, 3))
    assert (pointwise.reshape(t.shape) != occupied).float().mean() < 1e-4  # cell faces may round either way


def test_posed_grids_bounds_are_the_box_of_the_posed_occupied_cells_at_each_configuration(assets):
    """The posed grids' box is the object-frame box around every part's occupied cells posed by FK, at
    each θ asked (a render asks twice for the same θ and gets the same box; another θ gets its own),
    and per ray the box over every ray's θ."""
    kin = KinematicTree.from_urdf(assets / "synth_articulated.urdf", load_meshes=False)
    p = len(kin.part_names)
    shape = [20, 10, 4]
    field = ArticulatedField(
        AABB, kin.lower.tolist(), kin.upper.tolist(), chain=chain_spec(kin), part_aabbs=[AABB] * p,
        grid_shapes=[shape] * p, resolution=(8, 16), features=4, hidden=16,
    )
    lo, size = torch.tensor(AABB[0]), (torch.tensor(AABB[1]) - torch.tensor(AABB[0])) / torch.tensor(shape)
    cells = [torch.tensor([3 + 5 * i, 2 + 3 * i, i % 4]) for i in range(p)]  # one occupied cell per part
    with torch.no_grad():
        for i, cell in enumerate(cells):
            grid = getattr(field, f"grid_{i}")
            grid.zero_()
            grid[tuple(cell)] = 1

    def expected(theta):
        corners = torch.stack([lo + (cell + torch.tensor([i >> 2 & 1, i >> 1 & 1, i & 1])) * size for cell in cells for i in range(8)])
        T = kin.part_poses(theta.double()).float().reshape(-1, p, 4, 4)  # [m, p, 4, 4]
        posed = (T[:, :, None, :3, :3] @ corners.reshape(p, 8, 3, 1))[..., 0] + T[:, :, None, :3, 3]
        return torch.stack([posed.reshape(-1, 3).amin(0), posed.reshape(-1, 3).amax(0)])

    thetas = [(kin.lower + (kin.upper - kin.lower) * a).float() for a in (0.1, 0.9)]
    occupancy = field.occupancy(thetas[0])
    for theta in (thetas[0], thetas[1], thetas[0]):
        box = occupancy.bounds(theta)
        torch.testing.assert_close(box, expected(theta), atol=1e-5, rtol=0)
        assert torch.equal(occupancy.bounds(theta.clone()), box)
    assert torch.equal(occupancy.bounds(), occupancy.bounds(thetas[0]))
    assert not torch.allclose(expected(thetas[0]), expected(thetas[1]), atol=1e-3)
    per_ray = torch.stack(thetas)
    torch.testing.assert_close(occupancy.bounds(per_ray), expected(per_ray), atol=1e-5, rtol=0)
    runs = torch.stack([thetas[i] for i in (0, 0, 1, 1, 1, 0)])  # rays in runs, a θ coming back
    torch.testing.assert_close(occupancy.bounds(runs), expected(per_ray), atol=1e-5, rtol=0)
    # every ray at one θ (a Jacobian's per-ray leaves): that θ's box
    assert torch.equal(occupancy.bounds(thetas[1].expand(5, -1).clone()), occupancy.bounds(thetas[1]))


def test_distinct_rows_are_torch_unique_rows():
    """The rows' distinct values, sorted as ``torch.unique(dim=0)`` gives them, whatever their order."""
    g = torch.Generator().manual_seed(0)
    values = torch.rand(4, 3, generator=g)
    for order in ([0, 0, 1, 1, 2, 3, 3], [3, 1, 3, 1, 0], [2] * 9, [0]):
        rows = values[order]
        assert torch.equal(articulated._distinct_rows(rows), torch.unique(rows, dim=0))


@pytest.mark.slow
def test_articulated_field_renders_what_the_composed_parts_render(tiny_model, tiny_dataset):
    """Built from the trained model's part fields, the articulated field gives the composition's
    density and colour (to float rounding) at points of every part, at the limits and mid-range,
    for a shared θ and one per sample; its posed occupancy is the parts' occupancy."""
    model = tiny_model
    field = ArticulatedField.from_parts(model.kinematics, model.part_fields, model.part_grids, model.aabb).eval()
    g = torch.Generator().manual_seed(0)
    for theta in (model.lower, (model.lower + model.upper) / 2, model.upper):
        composition = compose_parts(model.part_fields, model.part_grids, model.kinematics.part_poses(theta.double()).float())
        x = model.aabb[0] + (model.aabb[1] - model.aabb[0]) * torch.rand(100000, 3, generator=g)
        occupied = composition.occupied(x)
        assert torch.equal(field.occupancy(theta).occupied(x), occupied)
        x = x[occupied]
        assert x.shape[0] > 100
        d = torch.nn.functional.normalize(torch.randn(x.shape, generator=g), dim=-1)
        with torch.no_grad():
            sigma, rgb = composition(x, d)
            for th in (theta, theta.expand(x.shape[0], -1).clone()):
                s, c = field(x, d, th)
                torch.testing.assert_close(s, sigma, rtol=1e-2, atol=1e-3)
                torch.testing.assert_close(c, rgb, rtol=0, atol=1e-3)
            torch.testing.assert_close(field.density_only(x, theta), s)
