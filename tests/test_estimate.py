"""The refiner on an analytic toy clamp: a textured bar and a jaw sliding along it (prismatic).

The fields are written by hand (boxes with a linear density ramp at their faces), so the rendered
observation is exact and the optimum is known. Images are 64x48 (about 4.5 mm per pixel at the
object), so "recovered" means an ADD of a few millimetres.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from narf_core.bundle import NarfModel
from narf_core.estimate import EstimateInputError, EstimateOptions, EstimateResult, _level, refine
from narf_core.geometry import Pinhole, invert_pose, look_at, so3_exp
from narf_core.kinematics import KinematicTree
from narf_core.render import OccupancyGrid

BAR_HALF = (0.08, 0.02, 0.01)
JAW_HALF = (0.01, 0.03, 0.01)
JAW_Y = 0.05  # the jaw link's origin in the bar frame at θ = 0
RAMP = 0.006  # density ramps from 0 to full over this distance across a face
DENSITY = 3000.0
LOWER, UPPER = -0.06, 0.06
TRUTH = {"slide": 0.012}
FAST = dict(iterations=80, rays_per_iteration=512, lr_pose=0.02)
ASSETS = Path(__file__).parent / "assets"


def _ramp_box(x: Tensor, half: tuple[float, ...]) -> Tensor:
    return ((x.new_tensor(half) - x.abs()) / RAMP + 0.5).clamp(0, 1).prod(-1)


def bar(x: Tensor) -> tuple[Tensor, Tensor]:
    """The bar in its own frame: ``x [n,3] -> (σ [n], rgb [n,3])``."""
    one = torch.ones_like(x[:, 0])
    rgb = torch.stack([0.5 + 0.4 * torch.sin(60 * x[:, 0]), 0.3 + 0.2 * torch.cos(90 * x[:, 1] + 40 * x[:, 2]), 0.6 * one], -1)
    return DENSITY * _ramp_box(x, BAR_HALF), rgb


def jaw(x: Tensor) -> tuple[Tensor, Tensor]:
    """The jaw in its own frame."""
    one = torch.ones_like(x[:, 0])
    rgb = torch.stack([0.9 * one, 0.5 + 0.4 * torch.sin(120 * x[:, 1] + 80 * x[:, 0]), 0.1 * one], -1)
    return DENSITY * _ramp_box(x, JAW_HALF), rgb


class SliderField(nn.Module):
    """The configuration field ``F(x, d, θ)``: bar plus jaw moved by θ, densities added."""

    def forward(self, x: Tensor, d: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
        s_bar, c_bar = bar(x)
        shift = torch.stack([theta[:, 0], torch.full_like(theta[:, 0], JAW_Y), torch.zeros_like(theta[:, 0])], -1)
        s_jaw, c_jaw = jaw(x - shift)
        sigma = s_bar + s_jaw
        return sigma, (s_bar[:, None] * c_bar + s_jaw[:, None] * c_jaw) / sigma.clamp_min(1e-8)[:, None]


class PartField(nn.Module):
    """A rigid part field ``(x, d, None) -> (σ, rgb)`` with its box."""

    def __init__(self, fn, half: tuple[float, ...]) -> None:
        super().__init__()
        self.fn = fn
        self.register_buffer("aabb", torch.tensor([[-h - RAMP for h in half], [h + RAMP for h in half]]))

    def forward(self, x: Tensor, d: Tensor, theta: Tensor | None) -> tuple[Tensor, Tensor]:
        return self.fn(x)


class FlakyField(SliderField):
    """Returns NaN densities on the calls numbered in ``bad`` (``None``: on every call)."""

    def __init__(self, bad: range | None) -> None:
        super().__init__()
        self.bad, self.calls = bad, 0

    def forward(self, x, d, theta):
        self.calls += 1
        sigma, rgb = super().forward(x, d, theta)
        if self.bad is None or self.calls in self.bad:
            sigma = torch.full_like(sigma, math.nan)
        return sigma, rgb


def make_model(field: nn.Module, assets: Path = ASSETS, *, parts: bool = False) -> NarfModel:
    kin = KinematicTree.from_urdf(assets / "estimate_slider.urdf")
    aabb = torch.tensor([[-0.09, -0.03, -0.02], [0.09, 0.09, 0.02]])
    grid = OccupancyGrid.from_field(SliderField(), aabb, 24, theta_samples=torch.linspace(LOWER, UPPER, 13)[:, None])
    part_fields = [PartField(bar, BAR_HALF), PartField(jaw, JAW_HALF)] if parts else None
    part_grids = [OccupancyGrid.full(f.aabb, 8) for f in part_fields] if parts else None
    return NarfModel("slider", kin, field, grid, part_fields=part_fields, part_grids=part_grids, step=0.003)


@pytest.fixture(scope="module")
def model() -> NarfModel:
    return make_model(SliderField(), ASSETS, parts=True)


CAMERA = Pinhole.primesense(64, 48)


def view(eye=(0.08, -0.15, 0.18)) -> np.ndarray:
    """``T_cam_obj`` of a camera at ``eye`` looking at the middle of the toy, z up."""
    f64 = dict(dtype=torch.float64)
    T_world_cam = look_at(torch.tensor(eye, **f64), torch.tensor([0.0, 0.03, 0.0], **f64), torch.tensor([0.0, 0.0, 1.0], **f64))
    return invert_pose(T_world_cam).numpy()


def observe(model: NarfModel, T: np.ndarray, joints: dict, camera: Pinhole = CAMERA):
    """uint8 image, bool mask and depth of the toy at ``T``, ``joints``."""
    out = model.render(torch.as_tensor(T, dtype=torch.float32), model.joint_vector(joints), camera, outputs=("rgb", "opacity", "depth"))
    return (out["rgb"].numpy() * 255).round().astype(np.uint8), out["opacity"].numpy() > 0.5, out["depth"].numpy()


def perturbed(T: np.ndarray, degrees: float, metres: float, seed: int) -> np.ndarray:
    """``T`` turned by ``degrees`` about a random axis through the toy's middle and moved by ``metres``."""
    rng = np.random.default_rng(seed)
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    R = so3_exp(torch.as_tensor(axis / np.linalg.norm(axis) * math.radians(degrees))).numpy()
    centre = T[:3, :3] @ np.array([0.0, 0.03, 0.0]) + T[:3, 3]
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = R @ (T[:3, 3] - centre) + centre + shift / np.linalg.norm(shift) * metres
    return out


def loss_problem(model: NarfModel, T: np.ndarray, image, mask, depth, options: EstimateOptions, levels: int = 2):
    """What the refiner's choices work on, for a view of the toy: the mask box's observation, the
    parameterisation around ``T``, the loss of ``options`` and the row ``[1, d]`` of ``T`` at ``TRUTH``'s joints."""
    from narf_core.estimate import _Loss, _mask_box, _observation, _Parameterisation

    obs = _observation(image, mask, depth, _mask_box(mask, options.box_margin), levels, "cpu")
    param = _Parameterisation.around(torch.from_numpy(T), model)
    loss_fn = _Loss(model, options, param.radius, True, CAMERA)
    row = torch.cat([torch.zeros(1, 6, dtype=torch.float64), param.u_of(model.joint_vector(TRUTH)[None].double())], 1)
    return obs, param, loss_fn, row


def assert_finite(result: EstimateResult) -> None:
    assert np.isfinite(result.T_cam_obj).all() and np.isfinite(result.quaternion).all()
    assert all(math.isfinite(v) for v in result.joints.values())
    assert all(math.isfinite(loss) and math.isfinite(t) for loss, t in result.trace)
    json.dumps(result.to_dict(), allow_nan=False)


# --- recovery -------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["narf", "parts"])
def test_recovers_pose_and_joint_from_10deg_2cm(model, mode):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    T0 = perturbed(T, 10, 0.02, seed=1)
    result = refine(model, image, mask, CAMERA, T0, options=EstimateOptions(mode=mode, **FAST), ground_truth=(T, TRUTH))
    start = refine(model, image, mask, CAMERA, T0, options=EstimateOptions(iterations=0), ground_truth=(T, TRUTH))
    assert_finite(result)
    assert start.metrics["add"] > 0.02
    assert result.metrics["add"] < 0.006, result.metrics
    assert result.metrics["joint_error/slide"] < 0.004
    assert result.metrics["add<1cm"] == 1.0
    assert result.loss < start.loss / 10
    assert result.status in ("converged", "max_iterations")
    assert np.allclose(result.T_cam_obj[:3, :3] @ result.T_cam_obj[:3, :3].T, np.eye(3), atol=1e-9)


@pytest.mark.parametrize("limit", [LOWER, UPPER])
def test_reaches_a_joint_limit_and_never_passes_it(model, limit):
    T = view()
    truth = {"slide": limit}
    image, mask, _ = observe(model, T, truth)
    start = {"slide": limit - math.copysign(0.012, limit)}
    options = EstimateOptions(record_every=1, **FAST)
    result = refine(model, image, mask, CAMERA, T, joints_init=start, options=options, ground_truth=(T, truth))
    assert abs(result.joints["slide"] - limit) < 0.002
    assert len(result.history) == result.iterations
    assert all(LOWER <= s.joints["slide"] <= UPPER for s in result.history + [result])


def test_a_start_exactly_at_a_limit_can_leave_it(model):
    T = view()
    truth = {"slide": UPPER - 0.012}
    image, mask, _ = observe(model, T, truth)
    result = refine(model, image, mask, CAMERA, T, joints_init={"slide": UPPER}, options=EstimateOptions(**FAST))
    assert abs(result.joints["slide"] - truth["slide"]) < 0.003


def test_object_partly_outside_the_image(model):
    T = view()
    T[0, 3] += 0.07  # the bar's far end leaves the image on the right
    image, mask, _ = observe(model, T, TRUTH)
    assert mask[:, -1].any() and 0 < mask.sum()
    result = refine(model, image, mask, CAMERA, perturbed(T, 5, 0.01, seed=2), options=EstimateOptions(**FAST), ground_truth=(T, TRUTH))
    assert_finite(result)
    assert result.metrics["add"] < 0.01


def test_no_overlap_returns_the_initial_pose_unchanged(model):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    far = T.copy()
    far[0, 3] += 1.0  # a metre to the side: no ray of the mask's box meets the object's box
    result = refine(model, image, mask, CAMERA, far, joints_init={"slide": 0.03}, ground_truth=(T, TRUTH))
    assert result.status == "no_overlap"
    assert np.array_equal(result.T_cam_obj, far)
    assert result.joints == {"slide": 0.03}
    assert result.loss is None and result.iterations == 0 and result.trace == []
    assert result.metrics["add"] > 0.5
    behind = T.copy()
    behind[2, 3] = -1.0  # behind the camera
    assert refine(model, image, mask, CAMERA, behind).status == "no_overlap"


# --- robustness -----------------------------------------------------------------------------


def test_flipped_object_near_180_degrees_stays_finite(model):
    T = view()
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # 180 deg about the bar's long axis: the far side shows
    T_flipped = T @ flip
    image, mask, _ = observe(model, T_flipped, TRUTH)
    turn = np.eye(4)
    turn[:3, :3] = so3_exp(torch.tensor([math.pi - 1e-4, 0.0, 0.0], dtype=torch.float64)).numpy()
    T0 = T_flipped @ turn  # starts upside down again: 179.99 deg off
    result = refine(model, image, mask, CAMERA, T0, options=EstimateOptions(iterations=20), ground_truth=(T_flipped, TRUTH))
    assert_finite(result)
    assert not result.recovered_non_finite
    assert math.isfinite(result.metrics["rotation_error_deg"]) and result.metrics["rotation_error_deg"] > 150
    near = refine(model, image, mask, CAMERA, perturbed(T_flipped, 5, 0.005, 3), options=EstimateOptions(**FAST), ground_truth=(T_flipped, TRUTH))
    assert near.metrics["add"] < 0.006


def test_transient_nan_in_the_field_is_recovered(model):
    flaky = make_model(FlakyField(bad=range(30, 33)))
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    result = refine(flaky, image, mask, CAMERA, perturbed(T, 10, 0.02, 1), options=EstimateOptions(**FAST), ground_truth=(T, TRUTH))
    assert flaky.field.calls > 40
    assert result.recovered_non_finite
    assert_finite(result)
    assert result.metrics["add"] < 0.01


def test_a_field_that_is_always_nan_gives_back_the_initial_pose(model):
    broken = make_model(FlakyField(bad=None))
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    T0 = perturbed(T, 10, 0.02, 1)
    result = refine(broken, image, mask, CAMERA, T0, options=EstimateOptions(**FAST))
    assert result.status == "non_finite" and result.recovered_non_finite
    assert np.array_equal(result.T_cam_obj, T0) and result.loss is None
    assert result.iterations < 20
    json.dumps(result.to_dict(), allow_nan=False)


def spy_on_renders(model: NarfModel, monkeypatch) -> list[tuple[int, Tensor, bool]]:
    """Record ``(rays, θ, with gradients)`` of every ``model.render_rays`` call from now on."""
    calls = []
    render_rays = model.render_rays

    def spy(rays, theta, **kw):
        calls.append((len(rays), theta.detach().clone(), torch.is_grad_enabled()))
        return render_rays(rays, theta, **kw)

    monkeypatch.setattr(model, "render_rays", spy)
    return calls


def starts_in(theta: Tensor) -> int:
    """How many configurations a render call carries: ``θ [k]`` is one, ``θ [n, k]`` one per ray."""
    return 1 if theta.dim() == 1 else len(torch.unique(theta, dim=0))


def test_theta_starts_run_as_one_batch_and_keep_the_best(model, monkeypatch):
    """Four joint starts find the joint where one start stays stuck. What the loop promises (and
    tuning keeps): every start in one render per iteration while several run, never more rays per
    start than ``rays_per_iteration`` (so ``iterations x rays_per_iteration x theta_starts`` bounds
    the loop's rays, as the service's work limit assumes), one start per stratum of the joint
    range, all starts compared on the same rays before the weaker ones are dropped, never a dropped
    one back, and the one kept the one nearest the truth."""
    T = view()
    truth, init = {"slide": -0.05}, {"slide": 0.05}  # the jaws do not overlap: the loss is flat in θ there
    image, mask, _ = observe(model, T, truth)
    one = refine(model, image, mask, CAMERA, T, joints_init=init, options=EstimateOptions(**{**FAST, "iterations": 30}), ground_truth=(T, truth))
    calls = spy_on_renders(model, monkeypatch)
    options = EstimateOptions(theta_starts=4, uncertainty=False, **FAST)  # no covariance pass: only the loop's renders
    four = refine(model, image, mask, CAMERA, T, joints_init=init, options=options, ground_truth=(T, truth))
    assert one.metrics["joint_error/slide"] > 0.05
    assert four.metrics["joint_error/slide"] < 0.003
    assert four.loss < one.loss / 10

    loop = [i for i, (_, _, grad) in enumerate(calls) if grad]  # the iterations' renders; comparisons need no gradient
    assert len(loop) == four.iterations  # one render per iteration, however many starts
    starts = [starts_in(calls[i][1]) for i in loop]
    assert starts[0] == 4 and starts[-1] == 1 and starts == sorted(starts, reverse=True)
    assert all(calls[i][0] <= s * options.rays_per_iteration for i, s in zip(loop, starts))
    first = torch.unique(calls[loop[0]][1]).tolist()
    assert init["slide"] == pytest.approx(first[-1], abs=1e-6)  # the given start is one of them ...
    assert sorted(int((v - LOWER) / (UPPER - LOWER) * 4) for v in first) == [0, 1, 2, 3]  # ... one per stratum
    alone = loop[starts.index(1)]
    between = calls[loop[starts.index(1) - 1] + 1 : alone]  # after the last batched iteration, before the first alone
    assert any(not grad and starts_in(theta) == 4 for _, theta, grad in between)  # the starts compared
    kept = float(calls[alone][1][0])
    assert LOWER <= kept <= LOWER + (UPPER - LOWER) / 4  # the truth's stratum: the best start went on

    calls.clear()
    options = EstimateOptions(theta_starts=2, iterations=3, mode="parts")
    parts = refine(model, image, mask, CAMERA, T, joints_init=init, options=options)
    (n_a, theta_a, _), (n_b, theta_b, _) = [c for c in calls if c[2]][:2]  # parts: one render per start
    assert theta_a.shape == theta_b.shape == (1,) and float(theta_a) != float(theta_b)
    assert n_a == n_b <= options.rays_per_iteration
    assert_finite(parts)


def turned(T: np.ndarray, axis: tuple[float, float, float], degrees: float) -> np.ndarray:
    """``T`` turned by ``degrees`` about the camera-frame ``axis`` through the toy's middle."""
    R = so3_exp(torch.tensor(axis, dtype=torch.float64) * math.radians(degrees)).numpy()
    centre = T[:3, :3] @ np.array([0.0, 0.03, 0.0]) + T[:3, 3]
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = R @ (T[:3, 3] - centre) + centre
    return out


def test_pose_starts_widen_the_basin_at_the_cost_of_two_renders_without_gradients(model, monkeypatch):
    """35 deg out of the image plane is outside one start's basin; five pose starts (the given pose
    and four turned by 20 deg about the camera's x and y axes, each also moved onto the
    observation) find the truth. They cost one render of every (turn, θ) pair to align them and one
    of both versions to score them, on the same rays and without gradients; then the refinement
    runs every θ start from the given pose and from its best other pose, in one render per
    iteration, until the starts are pruned."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    start = turned(T, (0.0, -1.0, 0.0), 35.0)
    options = EstimateOptions.robust(depth_weight=1.0, uncertainty=False, **FAST)
    one = refine(model, image, mask, CAMERA, start, depth=depth, options=options, ground_truth=(T, TRUTH))
    calls = spy_on_renders(model, monkeypatch)
    wide = replace(options, pose_starts=5, pose_spread_deg=20.0)
    five = refine(model, image, mask, CAMERA, start, depth=depth, options=wide, ground_truth=(T, TRUTH))
    assert one.metrics["add"] > 0.008 and one.metrics["rotation_error_deg"] > 10
    assert five.metrics["add"] < 0.003 and five.metrics["rotation_error_deg"] < 3

    (n_aligned, theta_aligned, grad_a), (n_scored, theta_scored, grad_s) = calls[:2]
    assert not grad_a and not grad_s and starts_in(theta_scored) == starts_in(theta_aligned) == wide.theta_starts
    rays = n_aligned // (5 * wide.theta_starts)  # the same rays for every (turn, θ) pair ...
    assert n_aligned == 5 * wide.theta_starts * rays and n_scored == 2 * n_aligned and rays <= 1024  # ... both versions
    loop = [c for c in calls if c[2]]
    assert starts_in(loop[0][1]) == wide.theta_starts and len(loop) == five.iterations
    assert loop[0][0] == 2 * wide.theta_starts * (wide.rays_per_iteration // 2)  # two poses per θ, half the rays each
    assert n_aligned + n_scored + sum(n for n, _, _ in loop) <= wide.max_rays()
    most = max(wide.theta_starts, wide.partial_theta_starts)  # a partially trusted mask raises the θ starts
    loop_bound = wide.iterations * wide.rays_per_iteration * 4 * most  # the robust preset's box scale: 4
    choices = 5 * 2 * most * wide.eval_rays  # the pruning and the final choice, on eval_rays per start
    assert wide.max_rays() == 2 * loop_bound + 3 * 5 * most * 1024 + choices

    calls.clear()  # one pose start: no scoring, the loop's first render is the first call
    refine(model, image, mask, CAMERA, start, depth=depth, options=replace(options, iterations=2))
    assert calls[0][2]


@pytest.mark.parametrize("shift", [(0.03, 0.0, 0.0), (0.0, -0.02, 0.04), (0.02, 0.02, -0.03)])
def test_a_pose_start_centimetres_off_is_moved_onto_the_mask_and_the_depth(model, shift):
    """A pose start's alignment (the second candidate of every turn): its silhouette's centroid onto
    the mask's and its median depth onto the observed one, which brings a start 3-5 cm off to
    within 5 mm of the truth without changing its rotation."""
    from narf_core.estimate import _aligned

    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    start = T.copy()
    start[:3, 3] += shift
    obs, param, loss_fn, row = loss_problem(model, start, image, mask, depth, EstimateOptions.robust(depth_weight=1.0))
    moved = param.poses(_aligned(loss_fn, obs, CAMERA, param, row, torch.arange(len(obs.pixels)), CAMERA.rays(obs.pixels.float())))[0]
    assert np.linalg.norm(moved[:3, 3].numpy() - T[:3, 3]) < 0.005 < np.linalg.norm(shift) / 5
    assert torch.allclose(moved[:3, :3], torch.from_numpy(start[:3, :3]), atol=1e-9)


def test_align_start_begins_each_joint_start_from_the_moved_pose_where_it_scores_lower(model):
    """``align_start`` (on in ``gauss-newton``, off in the Adam presets): a given pose 4 cm off along the line of sight is
    replaced, for every θ start, by its copy moved onto the mask and the depth; without it the
    given pose stays. (The fit to the depth's points after it, on in ``gauss-newton``, is off here: it moves the
    configurations too; tests/test_surface_fit.py.)"""
    from narf_core.estimate import (_given_rows, _Loss, _mask_box, _observation, _Parameterisation, _start_rows,
                                    _theta_starts)

    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    start = T.copy()
    start[:3, 3] *= 1 + 0.04 / np.linalg.norm(T[:3, 3])
    options = EstimateOptions.gauss_newton(surface_fit_iterations=0)
    assert not any(EstimateOptions.preset(name).align_start for name in ("paper", "robust"))
    assert EstimateOptions.preset("gauss-newton").align_start
    obs = _observation(image, mask, depth, _mask_box(mask, options.box_margin), 2, "cpu")
    param = _Parameterisation.around(torch.from_numpy(start), model)
    thetas = _theta_starts(model.joint_vector(TRUTH).double(), param, options.theta_starts)
    for align, error in ((True, lambda e: e < 0.01), (False, lambda e: abs(e - 0.04) < 1e-9)):
        loss_fn = _Loss(model, replace(options, align_start=align), param.radius, True, CAMERA)
        rows = _start_rows(loss_fn, obs, CAMERA, param, _given_rows(loss_fn, obs, CAMERA, param, thetas))
        assert rows.shape == (options.theta_starts, 7)
        assert torch.equal(param.thetas(rows), thetas)  # the configurations stay
        distance = np.linalg.norm(param.poses(rows)[:, :3, 3].numpy() - T[:3, 3], axis=1)
        assert all(error(e) for e in distance), (align, distance)


def test_pose_starts_overlap_refines_from_the_pose_starts_only_where_the_estimate_misses_the_mask(model, monkeypatch):
    """``pose_starts_overlap`` (on in ``gauss-newton``): from a start 45 deg out of the image plane one refinement
    ends in a wrong minimum 7 cm off whose silhouette overlaps the mask little, and a second one from the turned
    pose starts finds the truth; both refinements' iterations count. From
    a close start the estimate explains the mask: no pose start is scored or refined, and the result is the
    single-start refinement's, to the bit."""
    from narf_core import estimate

    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    adaptive = EstimateOptions.gauss_newton(uncertainty=False)
    assert (adaptive.pose_starts, adaptive.pose_starts_overlap) == (estimate.GN_POSE_STARTS, estimate.GN_POSE_OVERLAP)
    assert EstimateOptions.robust().pose_starts_overlap == 0  # the Adam presets: one pose start
    single = replace(adaptive, pose_starts=1)
    overlaps, turned_rows = [], estimate._turned_rows
    silhouette_overlap = estimate._silhouette_overlap
    monkeypatch.setattr(estimate, "_silhouette_overlap", lambda *a: overlaps.append(silhouette_overlap(*a)) or overlaps[-1])
    turns = []
    monkeypatch.setattr(estimate, "_turned_rows", lambda *a: turns.append(len(a[4])) or turned_rows(*a))

    far = turned(T, (-1.0, 0.0, 0.0), 45.0)
    one = refine(model, image, mask, CAMERA, far, depth=depth, options=single, ground_truth=(T, TRUTH))
    assert one.metrics["add"] > 0.008 and not overlaps and not turns  # one pose start: no check, no turns
    two = refine(model, image, mask, CAMERA, far, depth=depth, options=adaptive, ground_truth=(T, TRUTH))
    assert len(overlaps) == 1 and overlaps[0] < adaptive.pose_starts_overlap and turns == [adaptive.theta_starts]
    assert two.metrics["add"] < 0.003 and two.metrics["rotation_error_deg"] < 3
    assert two.iterations > one.iterations

    overlaps.clear()
    turns.clear()
    close = perturbed(T, 5, 0.01, seed=1)
    near = refine(model, image, mask, CAMERA, close, depth=depth, options=adaptive, ground_truth=(T, TRUTH))
    plain = refine(model, image, mask, CAMERA, close, depth=depth, options=single, ground_truth=(T, TRUTH))
    assert len(overlaps) == 1 and overlaps[0] >= adaptive.pose_starts_overlap and not turns
    assert np.array_equal(near.T_cam_obj, plain.T_cam_obj) and near.joints == plain.joints
    assert near.iterations == plain.iterations and near.metrics["add"] < 0.003


def test_pose_starts_overlap_with_adam_finds_the_pose_within_max_rays(model, monkeypatch):
    """The option works with either solver: with Adam (whose iterations trace one render each) a start 45 deg
    out of the image plane ends 2 cm off, its silhouette beside the mask's, the turned starts' refinement comes
    within a few millimetres, and both refinements, the scoring, the check and the choice stay within
    ``max_rays``."""
    from narf_core import estimate

    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    start = turned(T, (-1.0, 0.0, 0.0), 45.0)
    options = EstimateOptions.robust(depth_weight=1.0, uncertainty=False, pose_starts=5, pose_spread_deg=20.0,
                                     pose_starts_overlap=0.8, **FAST)
    one = refine(model, image, mask, CAMERA, start, depth=depth, options=replace(options, pose_starts=1),
                 ground_truth=(T, TRUTH))
    turns, turned_rows = [], estimate._turned_rows
    monkeypatch.setattr(estimate, "_turned_rows", lambda *a: turns.append(len(a[4])) or turned_rows(*a))
    calls = spy_on_renders(model, monkeypatch)
    found = refine(model, image, mask, CAMERA, start, depth=depth, options=options, ground_truth=(T, TRUTH))
    assert one.metrics["add"] > 0.015 and turns == [options.theta_starts] and found.metrics["add"] < 0.006
    assert sum(n for n, _, _ in calls) <= options.max_rays()


def test_silhouette_overlap_is_near_one_at_the_truth_and_lower_beside_it(model):
    """The check behind ``pose_starts_overlap``: intersection over union of the rendered silhouette and the
    mask, on the same box rays for every row."""
    from narf_core.estimate import _silhouette_overlap

    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    obs, param, loss_fn, truth = loss_problem(model, T, image, mask, depth, EstimateOptions.gauss_newton())
    beside = truth.clone()
    beside[0, 0] = 0.02 / param.radius  # 2 cm along the camera's x axis
    at_truth = _silhouette_overlap(loss_fn, obs, CAMERA, param, truth)
    assert at_truth > 0.9 and _silhouette_overlap(loss_fn, obs, CAMERA, param, truth) == at_truth
    assert _silhouette_overlap(loss_fn, obs, CAMERA, param, beside) < 0.6


def test_a_candidate_that_draws_nothing_on_the_mask_is_not_chosen(model):
    """Drawing nothing costs no depth or edge-band residual: an estimate moved off the object (as one on
    a small, thin mask ended 60 cm behind the truth) can have the lowest loss where the depth image
    disagrees with every drawn pose, here by 3 cm. The choice between candidates (``_fixed_rays_loss``)
    passes it over while another draws the object on the mask, and keeps it where none does."""
    from narf_core.estimate import _fixed_rays_loss

    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    depth = np.where(depth > 0, depth + 0.03, 0.0).astype(depth.dtype)
    obs, param, loss_fn, truth = loss_problem(model, T, image, mask, depth, EstimateOptions.gauss_newton())
    away = truth.clone()
    away[0, 0] = 0.3 / param.radius  # 30 cm along the camera's x axis: out of the box
    rows = torch.cat([truth, away])
    index = torch.arange(obs.pixels.shape[0])
    loss, cover = loss_fn.terms(CAMERA.rays(obs.pixels.float()), obs.levels[-1], index, param.poses(rows),
                                param.thetas(rows))
    assert loss[1] < loss[0] and cover[0] > 0.9 and cover[1] == 0  # the hazard: nothing drawn scores lower
    chosen = _fixed_rays_loss(loss_fn, obs, CAMERA, param, rows, torch.Generator().manual_seed(0))
    assert torch.isfinite(chosen[0]) and chosen[1] == math.inf
    alone = _fixed_rays_loss(loss_fn, obs, CAMERA, param, away, torch.Generator().manual_seed(0))
    assert torch.isfinite(alone[0])


@pytest.mark.parametrize("robust_loss", ["huber", "none"])
def test_a_few_stray_depth_pixels_do_not_decide_the_choice(model, robust_loss):
    """The loss that chooses between estimates weighs the depth residuals with the solver's robust loss,
    as it does the colour and silhouette: a few of the mask's pixels reading 10 cm behind the object (a
    sensor's flying pixels, a segmenter's blob over the table) cost Huber's linear tail, so the truth
    keeps the lowest loss among poses 1 cm off; squared, they outweigh everything else, and a pose that
    draws less of them scores lower than the truth."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    stray = mask & (np.random.default_rng(0).random(mask.shape) < 0.02)
    assert 8 <= stray.sum() <= 0.05 * mask.sum()
    depth = np.where(stray, depth + 0.10, depth).astype(depth.dtype)
    obs, param, loss_fn, truth = loss_problem(model, T, image, mask, depth,
                                              EstimateOptions.gauss_newton(robust_loss=robust_loss), levels=1)
    rows = truth.repeat(7, 1)
    for i in range(6):  # ±1 cm along each camera axis
        rows[1 + i, i // 2] += (0.01 if i % 2 else -0.01) / param.radius
    loss, _ = loss_fn.terms(CAMERA.rays(obs.pixels.float()), obs.levels[-1], torch.arange(obs.pixels.shape[0]),
                            param.poses(rows), param.thetas(rows))
    assert (int(loss.argmin()) == 0) == (robust_loss == "huber"), loss


@pytest.mark.parametrize("levels", [1, 2, 3, 6])
@pytest.mark.parametrize("iterations", [1, 2, 7, 80, 150])
def test_coarse_levels_come_before_the_fine_one(iterations, levels):
    """The pyramid schedule: never back to a coarser level, the last iteration at the finest (the
    only level early stopping looks at), and at the paper's 150 iterations every level used."""
    schedule = [_level(i, iterations, levels) for i in range(iterations)]
    assert schedule == sorted(schedule) and all(0 <= level < levels for level in schedule)
    assert schedule[-1] == levels - 1
    if iterations >= 150:
        assert set(schedule) == set(range(levels))


def test_early_stop_stops_early_and_can_be_switched_off(model):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    options = EstimateOptions(iterations=100, rays_per_iteration=4096, patience=8)  # every pixel: a deterministic loss
    stopped = refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=options, ground_truth=(T, TRUTH))
    assert stopped.status == "converged" and stopped.iterations < 80
    assert stopped.metrics["add"] < 0.003
    full = refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=EstimateOptions(iterations=20, early_stop=False))
    assert full.status == "max_iterations" and full.iterations == 20 and len(full.trace) == 20


def test_robust_options_and_depth(model):
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    depth[::7] = np.nan  # missing returns
    options = EstimateOptions.robust(depth_weight=1.0, record_every=25, **FAST)
    result = refine(model, image, mask, CAMERA, perturbed(T, 10, 0.02, 4), depth=depth, options=options, ground_truth=(T, TRUTH))
    assert result.metrics["add"] < 0.006
    assert [s.iteration for s in result.history] == list(range(25, result.iterations + 1, 25))  # every 25th
    assert len(result.history) >= 2 and all(np.isfinite(s.T_cam_obj).all() for s in result.history)


# --- inputs and outputs ---------------------------------------------------------------------


def test_options_round_trip_through_json():
    options = EstimateOptions.robust(iterations=10, seed=3)
    assert EstimateOptions(**json.loads(json.dumps(asdict(options)))) == options
    assert options.theta_starts > 1 and options.silhouette_weight > 0 and options.coarse_to_fine > 1
    assert EstimateOptions().iterations == 150


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(iterations=-1), "options.iterations must be >= 0"),
        (dict(mode="mesh"), "options.mode must be one of auto, narf, parts"),
        (dict(lr_pose=0.0), "options.lr_pose must be > 0"),
        (dict(lr_theta=math.nan), "options.lr_theta must be finite"),
        (dict(rays_per_iteration=2.5), "options.rays_per_iteration must be an integer"),
        (dict(early_stop="yes"), "options.early_stop must be true or false"),
        (dict(theta_starts=0), "options.theta_starts must be in [1, 64]"),
        (dict(pose_starts=0), "options.pose_starts must be in [1, 11]"),
        (dict(pose_spread_deg=0.0), "options.pose_spread_deg must be in (0, 90] degrees"),
        (dict(pose_starts_overlap=1.0), "options.pose_starts_overlap must be in [0, 1)"),
        (dict(pose_starts_overlap=-0.1), "options.pose_starts_overlap must be in [0, 1)"),
    ],
)
def test_bad_options_are_refused(kwargs, message):
    with pytest.raises(EstimateInputError, match=re.escape(message)):
        EstimateOptions(**kwargs)


def test_float32_pose_and_float64_intrinsics_are_accepted(model):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    camera64 = Pinhole(CAMERA.K.double(), CAMERA.width, CAMERA.height)
    options = EstimateOptions(iterations=5, rays_per_iteration=256)
    a = refine(model, image, mask, camera64, T.astype(np.float32), joints_init=TRUTH, options=options)
    b = refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=options)
    assert a.T_cam_obj.dtype == np.float64 and np.abs(a.T_cam_obj - b.T_cam_obj).max() < 1e-5


def test_bad_inputs_raise_a_clear_error(model):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    one = np.zeros_like(mask)
    one[20, 30] = True
    nan_pose, sheared = T.copy(), T.copy()
    nan_pose[0, 3] = math.nan
    sheared[0, 1] += 0.2
    cases = [
        (dict(mask=np.zeros_like(mask)), "mask is empty"),
        (dict(mask=one), "mask has only 1 object pixel"),
        (dict(mask=mask[:, :-1]), "mask is 63x48 but image is 64x48"),
        (dict(image=image[..., :2]), r"image must be an RGB array \[H, W, 3\]"),
        (dict(image=image.astype(np.float32)), "image must be uint8"),
        (dict(camera=Pinhole.primesense(640, 480)), "camera is 640x480 but image is 64x48"),
        (dict(camera=Pinhole(Pinhole.primesense(640, 480).K, 64, 48)), "principal point .* outside the 64x48 image"),
        (dict(T_init=nan_pose), "T_init must be finite"),
        (dict(T_init=T[:3]), "T_init must be a 4x4 pose matrix"),
        (dict(T_init=sheared), "T_init has a rotation block that is not orthonormal"),
        (dict(joints_init={"slid": 0.0}), r"joints_init: unknown joint\(s\) \['slid'\]"),
        (dict(joints_init={"slide": 0.5}), "joints_init: joint 'slide': 0.5 is outside its limits"),
        (dict(depth=np.zeros((10, 10), np.float32)), r"depth must be \[H, W\]"),
        (dict(depth=-np.ones(mask.shape, np.float32)), "depth has negative values"),
        (dict(ground_truth=(T, {})), r"ground_truth.joints: missing value\(s\) for joint\(s\) \['slide'\]"),
        (dict(options=EstimateOptions(mode="parts"), model=make_model(SliderField())), "options.mode 'parts' needs part fields"),
    ]
    for override, message in cases:
        args = {"model": model, "image": image, "mask": mask, "camera": CAMERA, "T_init": T, **override}
        with pytest.raises(EstimateInputError, match=message):
            refine(**args)


def test_rigid_object_without_joints(tmp_path):
    urdf = (ASSETS / "estimate_slider.urdf").read_text()
    rigid = urdf[: urdf.index('  <link name="jaw">')] + "</robot>\n"
    (tmp_path / "bar.urdf").write_text(rigid)
    kin = KinematicTree.from_urdf(tmp_path / "bar.urdf")
    field = PartField(bar, BAR_HALF)
    rigid_model = NarfModel("bar", kin, field, OccupancyGrid.full(field.aabb, 8), step=0.003)
    T = view()
    image, mask, _ = observe(rigid_model, T, {})
    options = EstimateOptions(theta_starts=3, **FAST)  # no joint: one start
    result = refine(rigid_model, image, mask, CAMERA, perturbed(T, 10, 0.02, 5), options=options, ground_truth=(T, {}))
    assert result.joints == {} and result.metrics["add_s"] < 0.006, result.metrics


# --- the benchmark protocol -----------------------------------------------------------------


def test_perturbation_is_azimuth_elevation_about_the_centre_and_bounded():
    from benchmarks.estimate import perturb_pose

    T = view()
    centre = np.array([0.0, 0.03, 0.0])
    rng = np.random.default_rng(0)
    for _ in range(50):
        T0 = perturb_pose(T, centre, 10.0, 0.02, rng)
        R = T0[:3, :3] @ T[:3, :3].T  # the rotation applied in the camera frame
        assert math.degrees(math.acos(min(1.0, (np.trace(R) - 1) / 2))) <= 10 * math.sqrt(2) + 1e-9
        assert abs(R[1, 0]) < 1e-12  # Ry(azimuth) @ Rx(elevation): the camera's x axis stays in the xz plane
        moved = (T0[:3, :3] @ centre + T0[:3, 3]) - (T[:3, :3] @ centre + T[:3, 3])
        assert np.linalg.norm(moved) <= 0.02 + 1e-12
    assert np.array_equal(perturb_pose(T, centre, 0.0, 0.0, rng), T)


def test_benchmark_writes_table_curves_and_sweep(model, tmp_path):
    from benchmarks.estimate import run
    from narf_core.data.dataset import DatasetWriter, FrameImages, read_urdf

    root = tmp_path / "toy"
    with DatasetWriter(root, read_urdf(ASSETS / "estimate_slider.urdf"), CAMERA) as writer:
        for eye in [(0.08, -0.15, 0.18), (-0.1, -0.12, 0.2), (0.05, 0.2, 0.22)]:
            T = view(eye)
            image, mask, _ = observe(model, T, TRUTH)
            writer.add("test", FrameImages(image, None, mask.astype(np.uint8)), T, TRUTH)
    result = run({"toy": model}, {"toy": root}, out_dir=tmp_path / "out", scenes=2, iterations=12, scale_sweep=(1.0,))
    assert [(r["tool"], r["split"], r["mode"], r["preset"], r["scenes"]) for r in result["table"]] == [
        ("toy", "test", mode, preset, 2) for mode in ("narf", "parts") for preset in ("paper", "robust", "gauss-newton")
    ]
    assert result["skipped"] == [{"tool": "toy", "split": "novel", "reason": "the dataset has no frames in this split"}]
    row = result["table"][0]
    assert row["add_mean_m"] > 0 and 0 <= row["add<0.1d"] <= 1 and row["joints"]["slide"]["unit"] == "m"
    curve = result["curves"]["toy narf paper"]
    assert curve["iteration"] == [0, 10] and curve["seconds_mean"][0] == 0 and curve["add_mean_m"][0] > 0.005
    assert [(s["preset"], s["scale"]) for s in result["sweep"]] == [("paper", 1.0), ("robust", 1.0), ("gauss-newton", 1.0)]
    assert all(0 <= r["nees_inside_95"] <= 1 for r in result["table"])
    assert result["sweep"][1]["add_mean_m"] == result["table"][1]["add_mean_m"]  # the table's runs, reused
    for name in ("estimate.json", "estimate.md", "estimate_error_vs_iterations.png", "estimate_sweep.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    assert json.loads((tmp_path / "out" / "estimate.json").read_text())["config"]["scenes"] == 2
    assert "| toy | test | narf | robust | 2 |" in (tmp_path / "out" / "estimate.md").read_text()
    assert result["machine"]["device"] == "cpu" and "Measured on cpu, load " in (tmp_path / "out" / "estimate.md").read_text()


def test_max_rays_bounds_every_preset_including_the_box_scale_and_adam_warm_start():
    # Adam: every iteration's rays for every start, the pruning (eval_rays per start) and the final choice of
    # the last and best rows (twice eval_rays per start), then the covariance (uncertainty_rays squares of 4 x 4).
    paper = EstimateOptions.preset("paper")
    starts, evaluated = paper.theta_starts, paper.eval_rays
    covariance = paper.uncertainty_rays * 16
    assert paper.max_rays() == paper.iterations * paper.rays_per_iteration * starts + 5 * starts * evaluated + covariance
    assert replace(paper, uncertainty=False).max_rays() == paper.max_rays() - covariance
    assert replace(paper, adam_iterations=20).max_rays() == paper.max_rays()  # the Gauss-Newton warm start's alone
    robust = EstimateOptions.preset("robust")  # a box larger than the reference draws up to 4x the rays
    most = max(robust.theta_starts, robust.partial_theta_starts)  # a partially trusted mask raises the θ starts
    assert robust.max_rays() == (robust.iterations * robust.rays_per_iteration * 4 * most + 5 * most * evaluated
                                 + robust.uncertainty_rays * 16)
    # Gauss-Newton, 25 iterations of 1024 rays: one start alone renders the linearisation and up to 6 trial
    # steps (the polish); several render both and up to 3 trial steps, on half the rays each, and are pruned
    # on up to 4096 rays at iteration 8 and at every one from 12 on while they tie (15 times). Then the
    # final choice of the last and best rows on eval_rays, and the covariance: at most uncertainty_rays
    # squares of 4 x 4 pixels.
    preset = EstimateOptions.preset("gauss-newton")
    # (the preset's partial trust, refinements and 8 starts where its configuration search runs: below)
    # (and its slide along the object's axis: below)
    # (and its fit of the final estimate to the depth's points: below)
    gauss = replace(preset, mask_trust="full", refinements=0, search_theta_starts=0, slide_share=0.0,
                    surface_polish_iterations=0)
    assert gauss.iterations == 25
    rays, iterations, covariance = gauss.rays_per_iteration, gauss.iterations, gauss.uncertainty_rays * 16

    def run(starts: int) -> int:
        return iterations * max(7 * rays, starts * rays // 2 * 4) + (15 * starts * 4096 if starts > 1 else 0)

    single = replace(gauss, theta_starts=1, pose_starts=1, align_start=False)
    assert single.max_rays() == iterations * 7 * rays + 2 * gauss.eval_rays + covariance
    assert replace(single, coarse_to_fine=1).max_rays() == single.max_rays() - iterations * 3 * rays  # no polish
    assert replace(single, uncertainty=False).max_rays() == single.max_rays() - covariance
    warm = replace(gauss, adam_iterations=20, align_start=False, pose_starts=1)  # Adam's 20, pruning, final choice
    assert warm.max_rays() == 4 * (20 * rays + 3 * gauss.eval_rays) + run(4) + 2 * 4 * gauss.eval_rays + covariance
    assert replace(warm, align_start=True).max_rays() == warm.max_rays() + 3 * 4 * 1024  # the alignment, then 2 x 4 scored
    # The preset's pose starts, refined only where the first estimate misses the mask: the given pose's 4 starts, then
    # 2 turned ones for each (all at once: 1 each), their scoring, the overlap check and the choice between both.
    every = replace(gauss, pose_starts_overlap=0.0)
    scoring = 3 * (9 + 1) * 4 * 1024
    assert every.max_rays() == scoring + run(8) + 2 * 8 * gauss.eval_rays + covariance
    choices = (2 * 4 + 1 + 2 * (1 + 8)) * gauss.eval_rays  # the first run's rows, the check, both estimates' rows
    assert gauss.max_rays() == scoring + run(4) + run(8) + choices + covariance
    # The final estimate fitted to the depth's points (surface_polish_iterations): its loss on eval_rays, with a depth
    # image and a mask that may be trusted in full.
    polished = replace(gauss, surface_polish_iterations=5)
    assert polished.max_rays() == gauss.max_rays() + gauss.eval_rays
    assert polished.max_rays(depth=False) == gauss.max_rays(depth=False)
    assert replace(polished, mask_trust="partial").max_rays() == replace(gauss, mask_trust="partial").max_rays()
    # The slide, only where the mask is trusted partially (below): the estimate and its four slid copies scored,
    # one more refinement from one start and the choice between both estimates.
    slide = 9 * gauss.eval_rays + run(1)
    assert replace(gauss, slide_share=0.05).max_rays() == gauss.max_rays()
    # Two whole estimates (refinements), the second on edge rays from the given pose alone (4 starts, no pose
    # starts), the overlap check before it and the choice between them: counted with a depth image too (one
    # found unusable leaves the view without). A fully trusted mask has no third kind of estimate.
    two = replace(gauss, refinements=2)
    edges = run(4) + 2 * 4 * gauss.eval_rays
    assert two.max_rays(depth=False) == two.max_rays() == gauss.max_rays() + edges + gauss.eval_rays + 2 * 16384
    assert replace(gauss, refinements=3).max_rays() == two.max_rays()
    # The preset trusts the mask partially where a depth image contradicts it, with 8 θ starts and three
    # estimates, the third the first from unaligned starts (its pose starts' scoring again, no alignment):
    # counted with depth; without one nothing contradicts the mask.
    assert preset.mask_trust == "auto" and preset.partial_theta_starts == 8 and preset.refinements == 3
    partial = 3 * 9 * 8 * 1024 + run(8) + run(16) + (2 * 8 + 1 + 2 * (1 + 16)) * gauss.eval_rays
    edges = run(8) + 2 * 8 * gauss.eval_rays
    polish = gauss.eval_rays  # "auto": trusted in full where the depth agrees
    assert preset.max_rays() == (3 * 8 * 1024 + 2 * partial + edges + gauss.eval_rays + 3 * 16384 + slide + polish
                                 + covariance)
    # Without one, the bound counts the 8 starts of an object whose configuration search runs (three joints or more).
    assert preset.search_theta_starts == 8
    assert preset.max_rays(depth=False) == replace(two, theta_starts=8).max_rays(depth=False)
    assert replace(preset, theta_search=0).max_rays(depth=False) == two.max_rays(depth=False)


@pytest.mark.parametrize("preset", ["paper", "robust"])
def test_max_rays_bounds_every_ray_an_adam_refinement_traces(model, monkeypatch, preset):
    """Every render of an Adam refinement stays within ``max_rays``: the iterations, the pruning, the final
    choice of the last and best rows and the covariance. With few iterations of few rays the last two are
    most of the work (the bound once counted the iterations alone)."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    options = EstimateOptions.preset(preset, iterations=6, rays_per_iteration=64, early_stop=False)
    calls = spy_on_renders(model, monkeypatch)
    result = refine(model, image, mask, CAMERA, turned(T, (0.0, 0.0, 1.0), 5.0), depth=depth, options=options)
    traced = sum(n for n, _, _ in calls)
    loop = options.iterations * options.rays_per_iteration * options.theta_starts * 4  # the box scale's 4 at most
    assert result.uncertainty is not None and result.iterations == options.iterations
    assert loop < traced <= options.max_rays()


@pytest.mark.parametrize("starts", ["one", "the preset's", "a partly trusted mask"])
def test_max_rays_bounds_every_ray_a_gauss_newton_refinement_traces(model, monkeypatch, starts):
    """Every render of a ``gauss-newton`` refinement run to its last iteration stays within ``max_rays``:
    the scoring, the linearisations, the trial steps, the prunings, the final choice, the slide along the
    object's axis and the covariance.
    From a start 45 deg out of the image plane the preset refines twice (``pose_starts_overlap``); one
    start renders at least one trial step per iteration besides its linearisation. With a partly trusted
    mask, 8 configuration starts and two more estimates where the first misses the mask (``refinements``)."""
    from narf_core import estimate

    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    if starts == "one":
        overrides = dict(theta_starts=1, pose_starts=1, align_start=False, iterations=12, rays_per_iteration=128)
    elif starts == "the preset's":
        overrides = dict(iterations=6, rays_per_iteration=256)
    else:
        overrides = dict(iterations=6, rays_per_iteration=256, mask_trust="partial", pose_starts_overlap=0.999)
    options = EstimateOptions.gauss_newton(early_stop=False, **overrides)
    turns, turned_rows = [], estimate._turned_rows
    monkeypatch.setattr(estimate, "_turned_rows", lambda *a: turns.append(len(a[4])) or turned_rows(*a))
    calls = spy_on_renders(model, monkeypatch)
    result = refine(model, image, mask, CAMERA, turned(T, (-1.0, 0.0, 0.0), 45.0), depth=depth, options=options)
    traced = sum(n for n, _, _ in calls)
    assert result.uncertainty is not None and result.mode == "narf"
    assert traced <= options.max_rays()
    if starts == "one":
        trial_steps = [n for n, _, grad in calls if not grad and n == options.rays_per_iteration]
        assert result.iterations == options.iterations <= len(trial_steps)
        assert traced > options.iterations * options.rays_per_iteration  # what one render per iteration would be
    elif starts == "the preset's":
        assert turns == [options.theta_starts] and result.iterations == 2 * options.iterations  # both refinements
    else:  # the first estimate's two refinements, the second estimate's one, the third's two (unaligned starts)
        assert turns == [options.partial_theta_starts] * 2 and result.iterations == 5 * options.iterations


def test_bench_estimate_takes_pose_starts_options_and_seed_from_the_command_line(model, tmp_path):
    from benchmarks.estimate import run, run_arguments
    from narf_core.cli import build_parser
    from narf_core.data.dataset import DatasetWriter, FrameImages, read_urdf

    args = build_parser().parse_args(["bench", "estimate", "--pose-starts", "3", "--seed", "2", "--scales", "1"])
    chosen = run_arguments(args)
    assert chosen == {"scale_sweep": (1.0,), "seed": 2, "overrides": {"pose_starts": 3}}
    assert run_arguments(build_parser().parse_args(["bench", "estimate"])) == {}
    both = ["bench", "estimate", "--pose-starts", "3", "--set", "slide_share=0", "--set", "pose_starts=5"]
    assert run_arguments(build_parser().parse_args(both)) == {"overrides": {"pose_starts": 5, "slide_share": 0}}
    with pytest.raises(ValueError, match="--set 'slide=0'"):
        run_arguments(build_parser().parse_args(["bench", "estimate", "--set", "slide=0"]))
    root = tmp_path / "toy"
    with DatasetWriter(root, read_urdf(ASSETS / "estimate_slider.urdf"), CAMERA) as writer:
        T = view((0.08, -0.15, 0.18))
        image, mask, _ = observe(model, T, TRUTH)
        writer.add("test", FrameImages(image, None, mask.astype(np.uint8)), T, TRUTH)
    result = run({"toy": model}, {"toy": root}, out_dir=tmp_path / "out", scenes=1, iterations=2, modes=("narf",),
                 presets=("paper", "gauss-newton"), progress=False, **chosen)
    assert result["config"]["seed"] == 2 and result["config"]["overrides"] == {"pose_starts": 3}
    assert {name: o["pose_starts"] for name, o in result["config"]["options"].items()} == {"paper": 3, "gauss-newton": 3}
    report = (tmp_path / "out" / "estimate.md").read_text()
    assert "Every preset with `pose_starts: 3`." in report
    jacobian = result["jacobian"]["toy"]  # the Gauss-Newton Jacobian's ways, timed
    assert jacobian["reverse_s"] > 0 and jacobian["fixed_samples"] > 0 and jacobian["fixed_reverse_s"] > 0
    assert jacobian["field_s"] is None and jacobian["fixed_field_s"] is None  # the toy's field has no jacobian of its own
    assert "On the tracker's fixed samples" in report


def test_theta_starts_with_several_joints_of_mixed_units_form_a_latin_hypercube():
    """With k joints (radians and metres mixed), every joint's start values fall one per stratum of its
    range (the given value's stratum included), the given configuration comes first, and the
    parameterisation maps every start back to itself inside the limits."""
    from narf_core.estimate import _U_LIMIT, _Parameterisation, _theta_starts

    lower = torch.tensor([-0.5, -0.2, 0.0, 0.0], dtype=torch.float64)  # two revolute (rad), two prismatic (m)
    upper = torch.tensor([0.5, 0.8, 0.16, 0.04], dtype=torch.float64)
    param = _Parameterisation(torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64), 0.3,
                              (lower + upper) / 2, (upper - lower) / 2)
    theta0 = torch.tensor([-0.45, 0.62, 0.01, 0.02], dtype=torch.float64)
    for count in (2, 4, 8):
        starts = _theta_starts(theta0, param, count)
        assert starts.shape == (count, 4)
        assert torch.equal(starts[0], theta0)
        strata = ((starts - lower) / (upper - lower) * count).floor().clamp(0, count - 1).long()
        for j in range(4):
            assert sorted(strata[:, j].tolist()) == list(range(count)), (count, j, strata[:, j])
        assert len({tuple(row.tolist()) for row in starts}) == count
        back = param.thetas(torch.cat([torch.zeros(count, 6, dtype=torch.float64), param.u_of(starts)], 1))
        # u keeps _U_LIMIT inside ±π/2, so a start within half_range * (1 - cos _U_LIMIT) of a limit moves there
        assert bool(((back - starts).abs() <= (upper - lower) / 2 * (1 - math.cos(_U_LIMIT)) + 1e-12).all())
        assert bool(((back >= lower) & (back <= upper)).all())


CHAIN_URDF = """<?xml version="1.0"?>
<robot name="chain">
  <link name="base"/><link name="upper"/><link name="lower"/>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0.04 0 0"/><axis xyz="0 0 1"/><limit lower="-1.2" upper="1.2"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="lower"/>
    <origin xyz="0.1 0 0"/><axis xyz="0 0 1"/><limit lower="-1.2" upper="1.2"/></joint>
</robot>
"""


def _chain(tmp_path):
    """A thin two-joint arm (a 4 cm base bar, then two 10 cm links, 1 cm wide) as the search sees it: its
    kinematics, surface points along the bars, and its box."""
    from types import SimpleNamespace

    path = tmp_path / "chain.urdf"
    path.write_text(CHAIN_URDF)
    kin = KinematicTree.from_urdf(path)
    g = torch.Generator().manual_seed(0)

    def bar(x0, x1, n=400):
        along = x0 + (x1 - x0) * torch.rand(n, generator=g, dtype=torch.float64)
        return torch.stack([along, (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 0.01,
                            (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 0.01], -1).numpy()

    points = {"base": bar(-0.04, 0.04), "upper": bar(0.0, 0.1), "lower": bar(0.0, 0.1)}
    aabb = torch.tensor([[-0.25, -0.25, -0.01], [0.25, 0.25, 0.01]])
    return SimpleNamespace(kinematics=kin, links=kin.links, sample_points=points, aabb=aabb)


def test_theta_search_finds_a_thin_chain_s_configuration_that_the_spread_starts_miss(tmp_path):
    """Two revolute joints, 1 cm wide links seen from above (2 pixels wide), the truth far from
    mid-range: the search's best configuration lies within 0.2 rad of the truth in both joints and
    nearer than any of the spread starts, its rows stay inside the limits, and without the option
    (or with one joint) the starts are the spread ones."""
    from types import SimpleNamespace

    from narf_core.estimate import (_given_rows, _observation, _Parameterisation, _start_rows, _theta_search,
                                    _theta_starts)

    chain = _chain(tmp_path)
    kin = chain.kinematics
    camera = Pinhole.primesense(128, 96)
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, 0.6)  # 0.6 m in front of the camera, the arm in the image plane
    truth = torch.tensor([0.6, -1.05], dtype=torch.float64)
    dense = {link: np.repeat(p, 4, 0) + np.random.default_rng(1).normal(0, 0.002, (4 * len(p), 3))
             for link, p in chain.sample_points.items()}
    links = kin.link_poses(truth).numpy()
    mask = np.zeros((camera.height, camera.width), bool)
    for i, link in enumerate(kin.links):
        X = (T @ links[i] @ np.c_[dense[link], np.ones(len(dense[link]))].T).T[:, :3]
        uv, _ = camera.project(torch.from_numpy(X))
        u, v = uv.numpy().T.astype(int)
        mask[v.clip(0, camera.height - 1), u.clip(0, camera.width - 1)] = True
    obs = _observation(np.zeros((*mask.shape, 3), np.uint8), mask, None, (0, 0, camera.width, camera.height), 1, "cpu")
    param = _Parameterisation.around(torch.from_numpy(T), chain)
    loss_fn = SimpleNamespace(model=chain, options=EstimateOptions(theta_search=16, theta_starts=4), uses_depth=False)
    theta0 = kin.mid_configuration()
    found = param.thetas(_theta_search(loss_fn, obs, camera, param, theta0, 16, 4))
    assert found.shape == (4, 2)
    assert bool(((found >= kin.lower) & (found <= kin.upper)).all())
    assert float((found[0] - truth).abs().max()) < 0.2, found[0]
    spread = _theta_starts(theta0, param, 4)
    assert float((found[0] - truth).norm()) < float((spread - truth).norm(dim=-1).min())
    rows = _start_rows(loss_fn, obs, camera, param, _given_rows(loss_fn, obs, camera, param, spread))  # the option on
    assert torch.allclose(param.thetas(rows), found)
    loss_fn.options = EstimateOptions(theta_starts=4)  # off: the spread starts
    rows = _start_rows(loss_fn, obs, camera, param, _given_rows(loss_fn, obs, camera, param, spread))
    assert torch.allclose(param.thetas(rows), spread, atol=1e-9)


def test_the_gauss_newton_preset_refines_a_start_per_corner_of_the_joint_box_where_its_search_runs(model, monkeypatch):
    """``search_theta_starts``: where the configuration search runs (two joints or more), at least one start
    per corner of the joint box up to that many, the partial mask's own rule beside it; a one-joint object
    keeps ``theta_starts`` (its refinement runs the preset's 4); the option is checked."""
    import narf_core.estimate as estimate

    preset = EstimateOptions.preset("gauss-newton")
    assert (preset.theta_starts, preset.search_theta_starts, preset.theta_search) == (4, 8, 16)
    starts = estimate._configuration_starts
    # one start per corner of the joint box, up to 8: two joints keep 4, three or more run 8
    assert [starts(preset, False, joints) for joints in (1, 2, 3, 8)] == [4, 4, 8, 8]
    assert [starts(preset, True, joints) for joints in (1, 2, 3, 8)] == [8, 8, 8, 8]  # partial_theta_starts
    assert starts(replace(preset, theta_search=0), False, 3) == 4
    assert starts(replace(preset, search_theta_starts=12), True, 4) == 12
    assert starts(replace(preset, search_theta_starts=0), False, 3) == 4
    assert starts(replace(preset, theta_starts=6), False, 2) == 6
    with pytest.raises(EstimateInputError, match=re.escape("options.search_theta_starts must be in [0, 64]")):
        EstimateOptions(search_theta_starts=65)
    seen = []
    given_rows = estimate._given_rows
    monkeypatch.setattr(estimate, "_given_rows", lambda *a: seen.append(len(a[-1])) or given_rows(*a))
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    refine(model, image, mask, CAMERA, T, options=replace(preset, iterations=2, uncertainty=False, refinements=0,
                                                         pose_starts=1, align_start=False))
    assert seen == [4]  # one joint: no search, the preset's own 4


def test_theta_search_option_is_checked_and_on_in_the_robust_preset():
    with pytest.raises(EstimateInputError, match=re.escape("options.theta_search must be in [0, 256] (0 = off)")):
        EstimateOptions(theta_search=-1)
    assert EstimateOptions.robust().theta_search == 16
    assert EstimateOptions().theta_search == 0  # the paper's protocol: the spread starts


def _chain_view(chain, camera: Pinhole, T: np.ndarray, theta: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The mask ``[H, W]`` and z-depth ``[H, W]`` (0 off the mask, the nearest point's z on it) of the
    chain of :func:`_chain` at pose ``T`` and configuration ``theta``, drawn from dense surface points."""
    rng = np.random.default_rng(1)
    links = chain.kinematics.link_poses(theta).numpy()
    mask = np.zeros((camera.height, camera.width), bool)
    depth = np.full((camera.height, camera.width), np.inf, np.float32)
    for i, link in enumerate(chain.links):
        points = np.repeat(chain.sample_points[link], 4, 0) + rng.normal(0, 0.002, (4 * len(chain.sample_points[link]), 3))
        X = (T @ links[i] @ np.c_[points, np.ones(len(points))].T).T[:, :3]
        uv, _ = camera.project(torch.from_numpy(X))
        u, v = uv.numpy().T.astype(int)
        keep = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        mask[v[keep], u[keep]] = True
        np.minimum.at(depth, (v[keep], u[keep]), X[keep, 2].astype(np.float32))
    return mask, np.where(mask, depth, 0).astype(np.float32)


def test_back_projected_points_project_back_onto_their_pixels_and_skip_missing_depth():
    from narf_core.estimate import _back_projected

    camera = Pinhole.primesense(128, 96)
    K = camera.K.double()
    uv = torch.tensor([[10.5, 20.5], [64.0, 48.0], [120.5, 3.5]], dtype=torch.float64)
    z = torch.tensor([0.5, 0.0, 1.25], dtype=torch.float64)
    X = _back_projected(K, uv, z)
    assert X.shape == (2, 3)
    assert torch.allclose(X[:, 2], z[[0, 2]])
    back = (K[:2, :2] @ (X[:, :2] / X[:, 2:])[..., None])[..., 0] + K[:2, 2]
    assert torch.allclose(back, uv[[0, 2]], atol=1e-9)


def test_search_with_depth_holds_the_distance_and_starts_gauss_newton_at_the_fitted_pose(tmp_path):
    """The chain seen with a depth image, the given pose 6 cm too far along the line of sight and the
    configuration far from mid-range: the observed surface in the search's score makes the true distance
    score lower than the far one (the silhouette alone barely tells them apart); the search's best row
    then lies within 1.5 cm of the true distance and 0.25 rad of the true joints. Gauss-Newton starts
    from the fitted poses, Adam from the given one (zero pose columns), and without depth nothing
    of the pose is kept."""
    from types import SimpleNamespace

    from narf_core.estimate import (_camera_points, _chamfer, _given_rows, _observation, _Parameterisation,
                                    _search_fit, _start_rows, _surface_sample, _theta_search)

    chain = _chain(tmp_path)
    kin = chain.kinematics
    camera = Pinhole.primesense(128, 96)
    T_true = np.eye(4)
    T_true[:3, 3] = (0.0, 0.0, 0.6)
    truth = torch.tensor([0.6, -1.05], dtype=torch.float64)
    mask, depth = _chain_view(chain, camera, T_true, truth)
    T_far = T_true.copy()
    T_far[2, 3] += 0.06
    box = (0, 0, camera.width, camera.height)
    obs = _observation(np.zeros((*mask.shape, 3), np.uint8), mask, depth, box, 1, "cpu")
    param = _Parameterisation.around(torch.from_numpy(T_far), chain)
    gauss = EstimateOptions(solver="gauss-newton", theta_search=16, theta_starts=4)
    loss_fn = SimpleNamespace(model=chain, options=gauss, uses_depth=True)

    fit = _search_fit(loss_fn, obs, camera, torch.Generator().manual_seed(3))
    assert fit.cloud is not None and len(fit.cloud) > 50
    points, link_of = _surface_sample(chain, 64, torch.Generator().manual_seed(0))
    rows = torch.cat([torch.zeros(2, 6, dtype=torch.float64), param.u_of(truth).expand(2, -1)], 1)
    rows[0, 2] = -0.06 / param.radius  # the true distance (the camera's z is the centre frame's z)
    with_cloud = _chamfer(fit, _camera_points(chain, param, rows, points, link_of))
    assert float(with_cloud[1] - with_cloud[0]) > 2.0, with_cloud  # pixels
    fit.cloud = None
    silhouette = _chamfer(fit, _camera_points(chain, param, rows, points, link_of))
    assert float(silhouette[1] - silhouette[0]) < float(with_cloud[1] - with_cloud[0]) / 2, silhouette

    found = _theta_search(loss_fn, obs, camera, param, kin.mid_configuration(), 16, 4)
    assert found.shape == (4, 8)
    z = param.poses(found[:1])[0, 2, 3]
    assert abs(float(z) - 0.6) < 0.015, float(z)
    assert float((param.thetas(found[:1])[0] - truth).abs().max()) < 0.25, param.thetas(found[:1])
    loss_fn.options = replace(gauss, solver="adam")
    adam_rows = _theta_search(loss_fn, obs, camera, param, kin.mid_configuration(), 16, 4)
    assert torch.equal(adam_rows[:, :6], torch.zeros(4, 6, dtype=torch.float64))
    loss_fn.options, loss_fn.uses_depth = gauss, False
    no_depth = _theta_search(loss_fn, obs, camera, param, kin.mid_configuration(), 16, 4)
    assert torch.equal(no_depth[:, :6], torch.zeros(4, 6, dtype=torch.float64))

    # align_start leaves the search's kept poses as they are (the loss, here not callable, scores nothing)
    loss_fn.options, loss_fn.uses_depth = replace(gauss, align_start=True), True
    given = _given_rows(loss_fn, obs, camera, param, kin.mid_configuration().expand(4, -1))
    assert torch.equal(_start_rows(loss_fn, obs, camera, param, given), found)


def test_the_gauss_newton_preset_searches_configurations():
    assert EstimateOptions.gauss_newton().theta_search == 16
    assert EstimateOptions.gauss_newton(theta_search=0).theta_search == 0


def test_model_error_of_a_revolute_joint_is_the_position_over_how_fast_it_moves_the_surface(tmp_path):
    """A joint's σ is the position's σ over the speed at which it moves its points: the chain's distal
    elbow (one 10 cm link) gets a wider angle than its shoulder (both links), both wider than the
    position over the object's radius; without surface points the radius is used."""
    from types import SimpleNamespace

    from narf_core.bundle import JointSpec
    from narf_core.estimate import MODEL_ERROR, model_error

    chain = _chain(tmp_path)
    joints = [JointSpec(j.name, j.type, j.lower, j.upper) for j in chain.kinematics.movable]
    model = SimpleNamespace(metadata={}, joints=joints, kinematics=chain.kinematics, sample_points=chain.sample_points)
    sd = model_error(model, "shape", 0.004, 0.25, MODEL_ERROR["reference_variance"]).numpy()
    position = MODEL_ERROR["pixels"]["shape"] * 0.004
    speeds = chain.kinematics.surface_speeds(chain.sample_points).numpy()
    assert np.allclose(sd[:6], [position] * 3 + [position / 0.25] * 3)
    assert np.allclose(sd[6:], position / speeds)
    assert sd[7] > sd[6] > position / 0.25
    assert 0.04 < speeds[1] < 0.07  # the elbow: one 10 cm link's points, 0-10 cm from its axis
    from narf_benchmarks.calibration import model_sigma
    from narf_core.estimate import _joint_speeds

    row = {"colour_variance": MODEL_ERROR["reference_variance"], "pixel_m": 0.004, "radius": 0.25, "class": "shape",
           "joint_speeds": _joint_speeds(model, 0.25).numpy()}
    assert np.allclose(model_sigma(row, MODEL_ERROR), sd)  # the calibration fits the σ the refiner reports
    from narf_benchmarks.calibration import model_covariance
    from narf_core.estimate import model_error_covariance

    u = np.array([0.0, 0.6, 0.8])
    rgb = {**row, "class": "silhouette", "line_of_sight": u, "stretch": 2.4}
    assert np.allclose(model_covariance(rgb, MODEL_ERROR), model_error_covariance(
        model_error(model, "silhouette", 0.004, 0.25, MODEL_ERROR["reference_variance"]), "silhouette",
        (torch.as_tensor(u), 2.4)).numpy())  # and its covariance, along the line of sight too
    bare = SimpleNamespace(metadata={}, joints=joints, kinematics=chain.kinematics, sample_points={})
    assert np.allclose(model_error(bare, "shape", 0.004, 0.25, MODEL_ERROR["reference_variance"]).numpy()[6:],
                       position / 0.25)


def test_trained_footprint_is_a_pixel_of_the_training_views_at_the_object():
    """The bundle's own training camera where it records one, else the 160x120 views the defaults were fitted on."""
    from types import SimpleNamespace

    from narf_core.estimate import REFERENCE_TRAINING_FX, trained_footprint

    T = torch.eye(4, dtype=torch.float64)
    T[2, 3] = 0.6
    centre = torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)
    assert REFERENCE_TRAINING_FX == pytest.approx(float(Pinhole.primesense(160, 120).K[0, 0]))
    unrecorded = SimpleNamespace(metadata={})
    assert trained_footprint(unrecorded, T, centre) == pytest.approx(0.7 / REFERENCE_TRAINING_FX)
    fine = SimpleNamespace(metadata={"training_camera": {"width": 640, "height": 480, "fx": 536.5, "fy": 536.5}})
    assert trained_footprint(fine, T, centre) == pytest.approx(0.7 / 536.5)


def test_model_footprint_is_never_finer_than_in_a_reference_box():
    """The model's error is counted in pixels at the object, never finer than in a mask box of the
    reference size: the same view on a camera four times finer (a box four times larger) keeps the footprint."""
    from narf_core.estimate import ROBUST_BOX_PX, model_footprint

    T = torch.eye(4, dtype=torch.float64)
    T[2, 3] = 0.6
    centre = torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)
    coarse = Pinhole(torch.tensor([[140.0, 0, 80], [0, 140.0, 60], [0, 0, 1]]), 160, 120)
    fine = Pinhole(torch.tensor([[560.0, 0, 320], [0, 560.0, 240], [0, 0, 1]]), 640, 480)
    box = (ROBUST_BOX_PX // 2, ROBUST_BOX_PX)
    assert model_footprint(coarse, T, centre, box) == pytest.approx(0.7 / 140)
    assert model_footprint(fine, T, centre, (4 * box[0], 4 * box[1])) == pytest.approx(0.7 / 140)
    assert model_footprint(fine, T, centre, box) == pytest.approx(0.7 / 560)  # a small box: the camera's own
