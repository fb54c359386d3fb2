"""The Gauss-Newton refiner and the covariance of an estimate, on the analytic toy clamp of
tests/test_estimate.py (exact renders, known optimum), on exactly linear problems (the covariance in
closed form) and on the bundled clamp."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import asdict, replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from narf_core import gauss_newton
from narf_core.estimate import (
    MODEL_ERROR,
    EstimateInputError,
    EstimateOptions,
    Uncertainty,
    chi2_quantile,
    local_error,
    model_error,
    model_error_covariance,
    line_of_sight,
    rotation_spread,
    nees,
    _error_class,
    refine,
)
from narf_core.geometry import Pinhole
from tests.test_estimate import ASSETS, CAMERA, LOWER, TRUTH, UPPER, SliderField, make_model, observe, perturbed, view

pytest_plugins = ("conftest_model",)  # tiny_bundle, tiny_dataset (the CLI test)

GN = dict(adam_iterations=0, iterations=25, rays_per_iteration=512)  # Levenberg-Marquardt alone
NO_FLOOR = dict(sigma_floor_position=0.0, sigma_floor_rotation=0.0, sigma_floor_joint=0.0)  # the statistical Σ only


@pytest.fixture(scope="module")
def model():
    toy = make_model(SliderField(), ASSETS, parts=True)
    toy.metadata["uncertainty"] = {"pixels": dict.fromkeys(MODEL_ERROR["pixels"], 0.0)}  # exact renders: no model error
    return toy


def test_gauss_newton_recovers_the_toy_from_10deg_2cm(model):
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    T0 = perturbed(T, 10, 0.02, seed=1)
    options = EstimateOptions.preset("gauss-newton", **GN)
    result = refine(model, image, mask, CAMERA, T0, depth=depth, options=options, ground_truth=(T, TRUTH))
    start = refine(model, image, mask, CAMERA, T0, options=EstimateOptions(iterations=0), ground_truth=(T, TRUTH))
    assert start.metrics["add"] > 0.02
    assert result.metrics["add"] < 0.006, result.metrics
    assert result.metrics["joint_error/slide"] < 0.004
    assert result.iterations <= GN["iterations"]
    json.dumps(result.to_dict(), allow_nan=False)


def test_gauss_newton_by_differences_recovers_the_toy_too(model):
    """``jacobian = "differences"`` (central differences of the render in every parameter) reaches the same
    answer as the field's derivatives from 10° / 2 cm off."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    options = EstimateOptions.preset("gauss-newton", jacobian="differences", **GN)
    result = refine(model, image, mask, CAMERA, perturbed(T, 10, 0.02, seed=1), depth=depth, options=options,
                    ground_truth=(T, TRUTH))
    assert result.metrics["add"] < 0.006, result.metrics
    assert result.metrics["joint_error/slide"] < 0.004
    with pytest.raises(EstimateInputError, match="jacobian"):
        EstimateOptions(jacobian="secant")


def test_the_difference_jacobian_is_the_renders_central_differences(model):
    """``Problem.difference_residuals``: every row's residuals as :meth:`Problem.residuals` gives them, and
    column ``j`` of its Jacobian the residuals of the row moved by ``+h`` and ``-h`` in parameter ``j``
    (``_DIFFERENCE_STEPS``) over ``2h``, for two rows at once (the shifted copies of each row kept apart);
    where the toy's surface is smooth at that scale, close to the field's derivatives."""
    from narf_core.estimate import _observation, _mask_box, _Parameterisation

    T = torch.as_tensor(view(), dtype=torch.float64)
    image, mask, depth = observe(model, view(), TRUTH)
    options = EstimateOptions.preset("gauss-newton", mode="narf")
    param = _Parameterisation.around(T, model)
    chain = gauss_newton.Chain.of(param)
    problem = gauss_newton.Problem(model, options, param.radius, True)
    obs = _observation(image, mask, depth, _mask_box(mask, options.box_margin), 1, "cpu")
    index = torch.arange(0, obs.pixels.shape[0], 7)
    rays = CAMERA.rays(obs.pixels[index].to(torch.float32))
    target = obs.levels[-1]
    theta = param.u_of(model.joint_vector(TRUTH).double()[None])
    p = torch.cat([torch.tensor([[0.0] * 6, [0.01, -0.02, 0.0, 0.01, 0.0, -0.02]], dtype=torch.float64),
                   theta.expand(2, -1)], dim=1)
    diff = problem.difference_residuals(chain, p, rays, target, index)
    plain = problem.residuals(chain, p, rays, target, index, False)
    torch.testing.assert_close(diff.r, plain.r)
    assert torch.equal(diff.used, plain.used)
    steps = [gauss_newton._DIFFERENCE_STEPS[0]] * 3 + [gauss_newton._DIFFERENCE_STEPS[1]] * 3 + [
        gauss_newton._DIFFERENCE_STEPS[2]] * (p.shape[1] - 6)
    for j, h in enumerate(steps):
        e = torch.zeros_like(p)
        e[:, j] = h
        ahead, behind = (problem.residuals(chain, p + s * e, rays, target, index, False).r for s in (1, -1))
        torch.testing.assert_close(diff.J[..., j], (ahead - behind) / (2 * h), rtol=1e-6, atol=1e-6)
    derivatives = problem.residuals(chain, p, rays, target, index, True).J
    cosines = [float(a @ b / (a.norm() * b.norm())) for a, b in
               ((diff.J[..., j].flatten(), derivatives[..., j].flatten()) for j in range(p.shape[1]))]
    assert min(cosines) > 0.7 and sum(cosines) / len(cosines) > 0.85, cosines  # the toy's surface seen between samples


def test_adam_warm_start_then_gauss_newton(model):
    """``adam_iterations``: Adam first (all θ starts), then Gauss-Newton on the fine level; the record
    counts both."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    T0 = perturbed(T, 10, 0.02, seed=1)
    options = EstimateOptions.preset("gauss-newton", adam_iterations=40, iterations=6, rays_per_iteration=512,
                                     lr_pose=0.02)
    result = refine(model, image, mask, CAMERA, T0, depth=depth, options=options, ground_truth=(T, TRUTH))
    assert result.metrics["add"] < 0.006, result.metrics
    assert 40 < result.iterations <= 46 and len(result.trace) == result.iterations


def test_covariance_is_symmetric_psd_and_shrinks_with_depth(model):
    T = view()
    image, mask, depth = observe(model, T, TRUTH)

    def unc(**kw) -> Uncertainty:
        options = EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0, uncertainty_patch=1, **NO_FLOOR, **kw)
        return refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=options).uncertainty

    few = unc(uncertainty_rays=700)
    many = unc(uncertainty_rays=4096)
    for u in (few, many):
        S = u.covariance
        assert S.shape == (7, 7) and np.allclose(S, S.T)
        assert np.linalg.eigvalsh(S).min() >= -1e-12 * np.abs(S).max()
        assert np.allclose(np.sqrt(np.diag(S))[:3], u.position_sigma_m)
        assert set(u.joint_sigma) == {"slide"} and u.dof > 0 and u.residual_variance > 0
    # A subsample estimates the whole box's information (not that of the rays it drew, which would
    # give about sqrt(1453 / 700) = 1.44x the σ): the same σ within the sampling error (700 of the
    # box's 1453 rays, 8 draws: 4-19 % in median per draw, 35 % at the 90th percentile).
    ratio = np.sqrt(np.diag(few.covariance) / np.diag(many.covariance))
    assert np.median(np.abs(ratio - 1)) < 0.3, ratio
    with_depth = refine(model, image, mask, CAMERA, T, joints_init=TRUTH, depth=depth,
                        options=EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0, uncertainty_patch=1, **NO_FLOOR)).uncertainty
    # Depth adds information: with the same residual variance σ² the precision can only grow.
    info = lambda u: np.linalg.inv(u.covariance) * u.residual_variance  # noqa: E731
    assert np.trace(info(with_depth)[:3, :3]) > np.trace(info(many)[:3, :3])


def test_nees_coverage_near_95_percent_with_known_gaussian_noise(model):
    """Independent Gaussian pixel noise, the truth as the start: the error of the refined estimate
    lies inside the 95 % region in about 95 % of the trials."""
    T = view()
    out = model.render(torch.as_tensor(T, dtype=torch.float32), model.joint_vector(TRUTH), CAMERA, outputs=("rgb", "opacity"))
    image = (out["rgb"].numpy() * 255).round().astype(np.uint8)
    mask = out["opacity"].numpy() > 1e-3  # every pixel the object touches: the masked image is the render
    bound = chi2_quantile(0.95, 7)
    inside = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        # No noise where it would clip at 0 or 255 (a clipped noise is not zero-mean).
        noise = rng.normal(0, 8, image.shape) * ((image > 30) & (image < 225))
        noisy = np.clip(image.astype(np.float64) + noise, 0, 255).round().astype(np.uint8)
        options = EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=12, theta_starts=1, coarse_to_fine=1,
                                         robust_loss="none", rays_per_iteration=4096, uncertainty_patch=1, seed=seed,
                                         silhouette_weight=0.0, **NO_FLOOR)
        result = refine(model, noisy, mask, CAMERA, T, joints_init=TRUTH, options=options, ground_truth=(T, TRUTH))
        inside.append(result.metrics["nees"] <= bound)
    assert 0.75 <= np.mean(inside) <= 1.0, inside


def test_unobserved_joint_gets_a_large_finite_sigma(model):
    """The jaw outside the image: θ does not change any ray, Σ stays finite with θ's σ near its prior,
    and the result says the joint is a guess (``unobserved_joint``); with the jaw in view it does not."""
    from narf_core.estimate import UNOBSERVED_SHARE

    T = view()
    joints = {"slide": 0.06}
    image, full, _ = observe(model, T, joints)
    # Hide the jaw: keep only the bar's pixels (the left part of the object in this view).
    cols = np.nonzero(full.any(0))[0]
    mask = full.copy()
    mask[:, (cols[0] + cols[-1]) // 2 :] = False
    options = EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0, box_margin=0.0, **NO_FLOOR)
    hidden = refine(model, image, mask, CAMERA, T, joints_init=joints, options=options)
    u = hidden.uncertainty
    assert np.isfinite(u.covariance).all()
    half = (UPPER - LOWER) / 2
    assert u.joint_sigma["slide"] >= UNOBSERVED_SHARE * half  # the prior's half range is what bounds it
    (warning,) = [w for w in hidden.warnings if w.startswith("unobserved_joint: slide: ")]
    assert f"over a range of {2 * half * 1000:.1f} mm" in warning
    seen = refine(model, image, full, CAMERA, T, joints_init=joints, options=options)
    assert seen.uncertainty.joint_sigma["slide"] < 0.1 * half
    assert not [w for w in seen.warnings if w.startswith("unobserved_joint")]
    # A large model error widens Σ past the threshold, but the view still constrains the jaw: not flagged.
    own = model.metadata["uncertainty"]
    model.metadata["uncertainty"] = {"pixels": dict.fromkeys(MODEL_ERROR["pixels"], 50.0)}
    try:
        wide = refine(model, image, full, CAMERA, T, joints_init=joints, options=options)
    finally:
        model.metadata["uncertainty"] = own
    assert wide.uncertainty.joint_sigma["slide"] >= UNOBSERVED_SHARE * half
    assert wide.uncertainty.view_joint_sigma["slide"] == pytest.approx(seen.uncertainty.joint_sigma["slide"], rel=1e-6)
    assert not [w for w in wide.warnings if w.startswith("unobserved_joint")]
    # A tracked frame says the same, whichever refiner ran it (the frame refiner adds no such warning of its
    # own), once, after the input checks' warnings; its result and the service's answer carry them.
    from narf_core.track import TrackResult, _warnings
    from service.schemas import TrackResponse

    checks = ["clipped: 12% of the mask's pixels are clipped"]
    assert _warnings(model, replace(hidden, warnings=checks), checks) == checks + [warning]
    assert _warnings(model, replace(hidden, warnings=checks + [warning]), checks) == checks + [warning]
    assert _warnings(model, replace(hidden, warnings=[]), checks) == checks + [warning]  # the frame's checks kept
    assert _warnings(model, replace(seen, warnings=checks), checks) == checks
    frame = TrackResult(0.0, "tracking", T, joints, 1.0, 0.0, 0, 0.0, warnings=checks + [warning])
    assert frame.to_dict()["warnings"] == checks + [warning] and TrackResult(0.0, "lost", T, joints, None, None, 0,
                                                                               0.0).warnings == []
    assert TrackResponse.model_fields["warnings"].default_factory is list


def test_a_non_finite_render_in_the_covariance_pass_gives_no_uncertainty(model, monkeypatch):
    """The estimate stands; a covariance that cannot be computed is ``None`` (JSON null), never NaN."""
    from narf_core import gauss_newton

    residuals = gauss_newton.Problem.residuals

    def nan_jacobians(self, *args, **kwargs):
        out = residuals(self, *args, **kwargs)
        return gauss_newton.Residuals(out.r * math.nan, out.J, out.used) if out.J is not None else out

    monkeypatch.setattr(gauss_newton.Problem, "residuals", nan_jacobians)  # iterations=0: only the Σ pass asks for J
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    result = refine(model, image, mask, CAMERA, T, joints_init=TRUTH,
                    options=EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0))
    assert result.uncertainty is None and result.status == "max_iterations"
    assert json.loads(json.dumps(result.to_dict(), allow_nan=False))["uncertainty"] is None


def test_nees_is_zero_at_the_truth_and_grows_with_the_error(model):
    T = view()
    u = Uncertainty.from_covariance(np.diag([1e-6] * 3 + [1e-4] * 3 + [1e-6]), ["slide"], 1.0, 10)
    assert nees(u, T, TRUTH, T, TRUTH, model) == pytest.approx(0, abs=1e-12)
    moved = T.copy()
    moved[0, 3] += 0.002
    e = local_error(moved, TRUTH, T, TRUTH, model)
    assert np.allclose(e[:3], [-0.002, 0, 0]) and np.allclose(e[3:], 0)
    assert nees(u, moved, TRUTH, T, TRUTH, model) == pytest.approx(4.0)
    assert math.isnan(nees(None, T, TRUTH, T, TRUTH, model))  # no covariance: no NEES


def test_chi2_quantile_matches_tables():
    assert chi2_quantile(0.95, 1) == pytest.approx(3.841, abs=1e-3)
    assert chi2_quantile(0.95, 7) == pytest.approx(14.067, abs=1e-3)
    assert chi2_quantile(0.95, 10) == pytest.approx(18.307, abs=1e-3)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(solver="lbfgs"), "options.solver must be one of adam, gauss-newton"),
        (dict(robust_loss="l1"), "options.robust_loss must be one of none, huber, cauchy"),
        (dict(robust_scale=0.0), "options.robust_scale must be > 0"),
        (dict(damping=-1.0), "options.damping must be in [0, 1e6]"),
        (dict(ray_sampling="random"), "options.ray_sampling must be one of uniform, stratified, edges"),
        (dict(depth_sigma=-0.1), "options.depth_sigma must be >= 0"),
        (dict(uncertainty_patch=0), "options.uncertainty_patch must be in [1, 64]"),
        (dict(adam_iterations=-1), "options.adam_iterations must be >= 0"),
    ],
)
def test_bad_solver_options_are_refused(kwargs, message):
    with pytest.raises(EstimateInputError, match=message.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        EstimateOptions(**kwargs)
    with pytest.raises(EstimateInputError, match="options.preset must be one of auto, paper, robust, gauss-newton"):
        EstimateOptions.preset("newton")


def test_the_preset_auto_is_gauss_newton_with_depth_and_robust_without():
    from narf_core import cli
    from narf_core.estimate import PRESET_NAMES, choose_preset

    assert choose_preset("auto", True)[0] == "gauss-newton" and choose_preset("auto", False)[0] == "robust"
    assert choose_preset("paper", True) == ("paper", "requested") and choose_preset("robust", False)[1] == "requested"
    assert EstimateOptions.preset("auto", depth=True, iterations=7) == EstimateOptions.preset("gauss-newton", iterations=7)
    assert EstimateOptions.preset("auto", depth=False) == EstimateOptions.preset("robust")
    with pytest.raises(EstimateInputError, match="options.preset 'auto' depends on the view") as refused:
        EstimateOptions.preset("auto")
    assert refused.value.field == "options.preset"
    with pytest.raises(EstimateInputError, match="options.preset must be one of auto, paper"):
        choose_preset("fast", True)
    assert cli.PRESET_NAMES == PRESET_NAMES  # named there so that --help imports no torch


def test_preset_round_trips_and_keeps_paper_free_of_extras():
    gn = EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=7)
    assert gn.solver == "gauss-newton" and gn.iterations == 7 and gn.robust_loss == "huber"
    assert EstimateOptions(**json.loads(json.dumps(asdict(gn)))) == gn
    paper = EstimateOptions.preset("paper")
    assert paper.solver == "adam" and paper.robust_loss == "none" and not paper.photometric_compensation
    assert paper.occlusion_margin == 0 and paper.depth_sigma == 0 and paper.ray_sampling == "uniform"


def test_robustness_options_run_and_stay_finite(model):
    """Gain/bias compensation (on an image made darker), occlusion reasoning, the depth noise model and
    edge sampling: each runs, and compensation recovers the toy under a global gain."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    dark = (image.astype(np.float64) * 0.7 + 10).clip(0, 255).astype(np.uint8)
    T0 = perturbed(T, 5, 0.01, seed=2)
    base = dict(GN, theta_starts=1)
    plain = refine(model, dark, mask, CAMERA, T0, options=EstimateOptions.preset("gauss-newton", **base), ground_truth=(T, TRUTH))
    comp = refine(model, dark, mask, CAMERA, T0, ground_truth=(T, TRUTH),
                  options=EstimateOptions.preset("gauss-newton", photometric_compensation=True, **base))
    assert comp.metrics["add"] < 0.006 and comp.metrics["add"] <= plain.metrics["add"] + 1e-3
    extras = EstimateOptions.preset("gauss-newton", occlusion_margin=0.01, depth_sigma=0.002, ray_sampling="edges",
                                    robust_loss="cauchy", **base)
    occluded = depth.copy()
    occluded[: depth.shape[0] // 3] = np.where(depth[: depth.shape[0] // 3] > 0, 0.05, 0)  # a near occluder
    result = refine(model, image, mask, CAMERA, T0, depth=occluded, options=extras, ground_truth=(T, TRUTH))
    assert result.metrics["add"] < 0.008, result.metrics
    json.dumps(result.to_dict(), allow_nan=False)


def test_a_partly_trusted_mask_weighs_the_residuals_as_adams_loss_does():
    """``mask_trust`` "partial" (a segmenter's mask, an occluder): on the mask's edge band the render is
    compared with the unmasked image and neither the silhouette nor the depth counts; outside the mask
    the residuals weigh ``outside_weight`` (square root on the residual, the weight on its square),
    fully where the sensor sees past the render, not at all where something stands in front of it.
    The weights are :func:`narf_core.estimate._outside_weight`'s, as in Adam's loss."""
    from narf_core.estimate import _Target

    radius, margin = 0.05, 0.01
    # rays: inside the mask; on its edge band; outside with the observed depth behind the render; outside
    # with it in front; outside with no depth
    P = torch.tensor([[[0.5, 0.4, 0.3, 0.9, 0.9 * 0.60], [0.2, 0.2, 0.2, 0.6, 0.6 * 0.61],
                       [0.3, 0.3, 0.3, 0.8, 0.8 * 0.60], [0.3, 0.3, 0.3, 0.8, 0.8 * 0.60],
                       [0.1, 0.2, 0.3, 0.7, 0.7 * 0.60]]], dtype=torch.float64)
    rgb = torch.tensor([[0.6, 0.4, 0.2], [0.0, 0.0, 0.0], [0.0] * 3, [0.0] * 3, [0.0] * 3], dtype=torch.float64)
    mask = torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    depth = torch.tensor([0.62, 0.61, 0.60 + 2 * margin, 0.60 - 2 * margin, 0.0], dtype=torch.float64)
    image = torch.tensor([[0.6, 0.4, 0.2], [0.5, 0.6, 0.7], [0.1] * 3, [0.1] * 3, [0.1] * 3], dtype=torch.float64)
    band = torch.tensor([False, True, False, False, False])
    target = _Target(rgb, mask, depth, 1, band, image)
    opts = EstimateOptions.preset("gauss-newton", mask_trust="partial", outside_weight=0.3, silhouette_weight=2.0,
                                  depth_weight=4.0)
    problem = gauss_newton.Problem(None, opts, radius, uses_depth=True)
    M, y, used = problem._linear_map(P, target, torch.arange(5))
    r, used = ((M @ P[..., None])[..., 0] - y)[0], used[0]
    op = P[0, :, 3]
    expected_colour = P[0, :, :3] - torch.stack([rgb[0], op[1] * image[1], rgb[2], rgb[3], rgb[4]])
    weight = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.3], dtype=torch.float64).sqrt()
    torch.testing.assert_close(r[:, :3], expected_colour * weight[:, None])
    torch.testing.assert_close(r[:, 3], math.sqrt(2.0) * (op - mask) * weight * torch.tensor([1.0, 0, 1, 1, 1]))
    torch.testing.assert_close(r[0, 4], 2.0 / radius * (P[0, 0, 4] - op[0] * depth[0]))
    assert r[1:, 4].abs().max() == 0  # no depth residual on the edge nor outside the mask
    assert used.tolist() == [[True] * 5, [True, True, True, False, False], [True, True, True, True, False],
                             [False] * 5, [True, True, True, True, False]]
    # at the full weight outside the mask, with depth, only the occluder's ray (in front of the render) loses it
    whole = gauss_newton.Problem(None, replace(opts, outside_weight=1.0), radius, uses_depth=True)
    M, y, used = whole._linear_map(P, target, torch.arange(5))
    r1 = ((M @ P[..., None])[..., 0] - y)[0]
    occluder_weight = torch.tensor([1.0, 1, 1, 0, 1], dtype=torch.float64)
    torch.testing.assert_close(r1[:, :3], expected_colour * occluder_weight[:, None])
    assert used[0, :, 3].tolist() == [True, False, True, False, True]
    full = gauss_newton.Problem(None, replace(opts, mask_trust="full"), radius, uses_depth=True)
    M, y, used = full._linear_map(P, _Target(rgb, mask, depth, 1), torch.arange(5))
    assert bool(used[0, :, :4].all()) and used[0, :, 4].tolist() == [True, False, False, False, False]


def test_the_options_floors_add_to_the_diagonal(model):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    run = lambda **kw: refine(model, image, mask, CAMERA, T, joints_init=TRUTH,  # noqa: E731
                              options=EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0, **kw)).uncertainty
    bare, floored = run(**NO_FLOOR), run(sigma_floor_position=0.003, sigma_floor_rotation=0.02, sigma_floor_joint=0.1)
    added = np.diag(floored.covariance - bare.covariance)
    assert np.allclose(added, [0.003**2] * 3 + [0.02**2] * 3 + [(0.1 * (0.06 - -0.06)) ** 2])


def test_model_error_scales_with_the_pixel_and_the_fit(model):
    """σ of the model's error: ``pixels`` footprints in position, that over the radius in rotation,
    the prismatic joint like a position; a fit with 2x the colour variance gets 2^exponent the σ; a
    bundle's own calibration replaces the defaults; the class follows the loss and the solver."""
    calibrated = SimpleNamespace(metadata={}, joints=model.joints)
    reference = MODEL_ERROR["reference_variance"]
    sd = model_error(calibrated, "shape", 0.004, 0.1, reference).numpy()
    position = MODEL_ERROR["pixels"]["shape"] * 0.004
    assert np.allclose(sd, [position] * 3 + [position / 0.1] * 3 + [position])
    worse = model_error(calibrated, "shape", 0.004, 0.1, 2 * reference).numpy()
    assert np.allclose(worse / sd, 2 ** MODEL_ERROR["exponent"])
    assert np.allclose(model_error(calibrated, "shape", 0.008, 0.1, reference).numpy(), 2 * sd)  # twice the distance
    own = SimpleNamespace(metadata={"uncertainty": {"pixels": {"shape": 2 * MODEL_ERROR["pixels"]["shape"]}}},
                          joints=model.joints)
    assert np.allclose(model_error(own, "shape", 0.004, 0.1, reference).numpy(), 2 * sd)
    assert np.allclose(model_error(own, "colour", 0.004, 0.1, reference).numpy(),  # the other classes stay
                       model_error(calibrated, "colour", 0.004, 0.1, reference).numpy())
    assert not model_error(model, "shape", 0.004, 0.1, reference).any()  # the exact toy's bundle: none
    assert _error_class(EstimateOptions.preset("paper"), uses_depth=False) == "colour"
    assert _error_class(EstimateOptions.preset("robust"), uses_depth=False) == "silhouette"
    assert _error_class(EstimateOptions.preset("gauss-newton"), uses_depth=False) == "silhouette"
    assert _error_class(EstimateOptions.preset("paper", depth_weight=1.0), uses_depth=True) == "shape"
    assert _error_class(EstimateOptions.preset("gauss-newton"), uses_depth=True) == "shape-gauss-newton"


def test_model_error_without_depth_is_longer_along_the_line_of_sight():
    """Without depth the position's model error along the line of sight is the across one times the
    distance over the radius (an outline's error read as the object's scale), across it unchanged, the
    rotation and joints as their σ; with depth the covariance is the diagonal of the σ."""
    box = SimpleNamespace(aabb=torch.tensor([[-0.06, -0.08, 0.0], [0.06, 0.08, 0.0]]))  # radius 0.1 m
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([0.3, 0.0, 0.4])  # 0.5 m away
    u, stretch = line_of_sight(box, T)
    assert torch.allclose(u, torch.tensor([0.6, 0.0, 0.8], dtype=torch.float64)) and stretch == pytest.approx(5.0)
    sd = torch.tensor([0.002, 0.002, 0.002, 0.02, 0.02, 0.02, 0.003], dtype=torch.float64)
    across = torch.tensor([0.8, 0.0, -0.6], dtype=torch.float64)
    for kind in ("silhouette", "colour"):
        cov = model_error_covariance(sd, kind, (u, stretch))
        assert float(u @ cov[:3, :3] @ u) == pytest.approx((0.002 * 5) ** 2)
        assert float(across @ cov[:3, :3] @ across) == pytest.approx(0.002**2)
        assert torch.allclose(cov[3:, 3:], torch.diag(sd[3:] ** 2)) and not cov[:3, 3:].any()
    for kind in ("shape", "shape-gauss-newton"):
        assert torch.allclose(model_error_covariance(sd, kind, (u, stretch)), torch.diag(sd**2))
    T[:3, 3] = torch.tensor([0.0, 0.0, 0.05])
    assert line_of_sight(box, T)[1] == 1.0  # nearer than its radius: never shorter along than across


def test_the_rotations_spread_is_the_turn_a_surface_error_means_for_the_objects_shape():
    """``rotation_spread``: a small turn ``ω`` about the box centre (camera axes) moves the bundled clamp's
    surface points by ``r² ωᵀ spread⁻¹ ω`` in the mean square (``r`` half the box's diagonal), whichever way
    the clamp is posed; every axis at least as wide as the isotropic σ, most about the clamp's long axis (its
    box's x); points on a line through the centre are held at MAX_ROTATION_SPREAD; the model error's
    rotation block takes it in place of the isotropic one."""
    from narf_core.band import surface_points
    from narf_core.bundle import load_bundle
    from narf_core.estimate import MAX_ROTATION_SPREAD
    from narf_core.geometry import so3_exp

    clamp = load_bundle(ASSETS.parent.parent / "models" / "clamp.narf")
    aabb = clamp.aabb.double()
    centre, r = (aabb[0] + aabb[1]) / 2, float((aabb[1] - aabb[0]).norm()) / 2
    theta = ((clamp.kinematics.lower + clamp.kinematics.upper) / 2).double()
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = so3_exp(torch.tensor([0.4, -1.1, 0.7], dtype=torch.float64))
    T[:3, 3] = torch.tensor([0.05, -0.02, 0.6], dtype=torch.float64)
    spread = rotation_spread(clamp, T, theta)
    points = surface_points(clamp, T[None], theta[None])[0]
    c = T[:3, :3] @ centre + T[:3, 3]
    for omega in torch.tensor([[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1e-4], [3e-5, -6e-5, 2e-5]], dtype=torch.float64):
        moved = (points - c) @ so3_exp(omega).T + c
        mean_square = float(((moved - points) ** 2).sum(-1).mean())
        assert mean_square == pytest.approx(r**2 * float(omega @ torch.linalg.solve(spread, omega)), rel=1e-3)
    widths = torch.linalg.eigvalsh(spread)
    assert float(widths[0]) >= 1.0 and float(widths[-1]) > 10.0  # about the long axis: over 3x the σ
    long_axis = T[:3, 0]  # the clamp's box is longest along its x
    assert float(long_axis @ spread @ long_axis) == pytest.approx(float(widths[-1]), rel=0.05)

    rod = SimpleNamespace(aabb=torch.tensor([[-0.1, -0.01, -0.01], [0.1, 0.01, 0.01]]), links=["rod"],
                          sample_points={"rod": torch.stack([torch.linspace(-0.1, 0.1, 50), torch.zeros(50),
                                                             torch.zeros(50)], -1)},
                          kinematics=SimpleNamespace(link_poses=lambda th: torch.eye(4, dtype=torch.float64)[None, None]))
    about_its_axis = rotation_spread(rod, torch.eye(4, dtype=torch.float64), torch.zeros(0, dtype=torch.float64))
    assert float(about_its_axis[0, 0]) == pytest.approx(MAX_ROTATION_SPREAD)
    assert float(torch.linalg.eigvalsh(about_its_axis)[0]) >= 1.0

    sd = torch.tensor([0.002] * 3 + [0.01] * 3 + [0.003], dtype=torch.float64)
    for kind in ("shape-gauss-newton", "silhouette"):
        cov = model_error_covariance(sd, kind, line_of_sight(clamp, T), spread)
        assert torch.allclose(cov[3:6, 3:6], 0.01**2 * spread)
        assert torch.allclose(cov[:3, :3], model_error_covariance(sd, kind, line_of_sight(clamp, T))[:3, :3])
        assert float(cov[6, 6]) == pytest.approx(0.003**2)


# --------------------------------------------------------------------------------------------
# The covariance's algebra on exactly linear problems: r = A δ - y at the estimate (δ = 0)


class LinearProblem:
    """Residuals ``r = -y`` with Jacobian ``A`` per box pixel (``A [N, 5, d]``, ``y [N, 5]``), all used:
    the Gauss-Newton covariance of such a problem is known in closed form."""

    def __init__(self, A: torch.Tensor, y: torch.Tensor, **options) -> None:
        self.A, self.y = A, y
        self.options = EstimateOptions(**options)

    def residuals(self, chain, p, rays, target, index, jacobian, group=1):
        used = torch.ones(1, len(index), 5, dtype=torch.bool)
        return gauss_newton.Residuals(-self.y[index][None], self.A[index][None], used)


def linear_case(N: int = 900, d: int = 7, seed: int = 0, side: int = 30):
    """A linear problem over a ``side x side`` box of pixels, with what :func:`gauss_newton.covariance` needs."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(N, 5, d, generator=g, dtype=torch.float64) * torch.rand(N, 1, 1, generator=g, dtype=torch.float64) * 3
    y = torch.randn(N, 5, generator=g, dtype=torch.float64) * 0.1
    v, u = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    obs = SimpleNamespace(pixels=torch.stack([u.reshape(-1), v.reshape(-1)], 1)[:N], levels=[None], importance=None)
    param = SimpleNamespace(radius=0.1, mid=torch.zeros(d - 6, dtype=torch.float64),
                            half=torch.full((d - 6,), 0.05, dtype=torch.float64))
    return A, y, obs, param


def linear_covariance(problem, obs, param, max_rays: int, patch: int = 1, seed: int = 0) -> gauss_newton.Covariance:
    d = problem.A.shape[-1]
    return gauss_newton.covariance(problem, obs, Pinhole.primesense(64, 48), param, torch.eye(4, dtype=torch.float64),
                                   torch.zeros(d - 6, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                                   max_rays, patch, torch.Generator().manual_seed(seed))


def test_covariance_of_a_linear_problem_is_the_closed_form():
    A, y, obs, param = linear_case()
    out = linear_covariance(LinearProblem(A, y), obs, param, max_rays=10_000)
    N, d = A.shape[0], A.shape[-1]
    variance = float((y**2).sum()) / (N * 5 - d)
    prior = torch.diag(torch.tensor([0.1**-2] * 3 + [1.0] * 3 + [0.05**-2], dtype=torch.float64))
    H = torch.einsum("nci,ncj->ij", A, A)
    assert out.variance == pytest.approx(variance, rel=1e-12) and out.dof == N * 5 - d
    assert torch.allclose(out.sigma, torch.linalg.inv(H / variance + prior), rtol=1e-9, atol=0)
    assert out.colour_variance == pytest.approx(float((y[:, :3] ** 2).mean()), rel=1e-12)


def test_linear_sandwich_is_the_closed_form():
    """``patch > 1``: ``A⁻¹ (Σ_c g_c g_cᵀ / σ⁴) A⁻¹`` with the scores summed per ``patch x patch`` square,
    its diagonal never below the independent-ray covariance's."""
    A, y, obs, param = linear_case()
    out = linear_covariance(LinearProblem(A, y), obs, param, max_rays=10_000, patch=3)
    N, d = A.shape[0], A.shape[-1]
    variance = float((y**2).sum()) / (N * 5 - d)
    prior = torch.diag(torch.tensor([0.1**-2] * 3 + [1.0] * 3 + [0.05**-2], dtype=torch.float64))
    inv = torch.linalg.inv(torch.einsum("nci,ncj->ij", A, A) / variance + prior)
    score = torch.einsum("nci,nc->ni", A, -y)
    square = (obs.pixels[:, 1] // 3) * 10 + obs.pixels[:, 0] // 3
    G = torch.zeros(100, d, dtype=torch.float64).index_add(0, square, score)
    robust = inv @ (G.T @ G / variance**2) @ inv
    sd = torch.maximum(robust.diagonal(), inv.diagonal()).sqrt()
    expected = robust / torch.outer(robust.diagonal().sqrt(), robust.diagonal().sqrt()) * torch.outer(sd, sd)
    assert torch.allclose(out.sigma, expected, rtol=1e-9, atol=0)


@pytest.mark.parametrize("patch", [1, 3])
def test_a_subsample_of_identical_rays_scales_to_the_whole_box_exactly(patch):
    """Every pixel alike: whatever is drawn, the weighted sums equal the box's (an N/n scaling), so Σ
    is the every-ray one to rounding (amplified by H's rank of 5 < d), not that of the n rays drawn
    (which is N/n = 9 times larger)."""
    A, y, obs, param = linear_case()
    A, y = A[:1].expand_as(A).clone(), y[:1].expand_as(y).clone()
    problem = LinearProblem(A, y)
    every = linear_covariance(problem, obs, param, max_rays=10_000, patch=patch).sigma
    for seed in range(3):
        sub = linear_covariance(problem, obs, param, max_rays=100, patch=patch, seed=seed).sigma
        assert torch.allclose(sub, every, rtol=1e-3, atol=0)


def test_the_weighted_subsample_of_the_information_is_unbiased():
    """Rays of unequal information drawn in proportion to an importance: the mean of the estimated
    ``H`` over many draws is the box's ``H`` (Horvitz-Thompson weights)."""
    A, y, obs, param = linear_case()
    importance = A.pow(2).sum((1, 2))[torch.randperm(len(A), generator=torch.Generator().manual_seed(1))]
    obs.importance = importance / importance.sum()  # a deliberately imperfect importance
    problem = LinearProblem(A, y)
    H = torch.einsum("nci,ncj->ij", A, A)
    draws = []
    for seed in range(400):
        index, cluster, weight = gauss_newton.cluster_sample(obs.pixels, obs.importance, 1, 150, torch.Generator().manual_seed(seed))
        info = gauss_newton.information(problem, obs, Pinhole.primesense(64, 48), None, None, index, cluster, weight)
        draws.append(info.H)
    mean = torch.stack(draws).mean(0)
    assert torch.allclose(mean.diagonal(), H.diagonal(), rtol=0.05)


def test_the_information_is_the_same_whatever_the_chunk_of_rays():
    """The rays are linearised a chunk at a time (to bound memory); every field is a sum over rays
    or over cluster scores, so the chunking must not change it, even with clusters split across chunks."""
    A, y, obs, param = linear_case()
    problem = LinearProblem(A, y)
    index, cluster, weight = gauss_newton.cluster_sample(obs.pixels, obs.importance, 2, 300, torch.Generator().manual_seed(0))
    whole = gauss_newton.information(problem, obs, Pinhole.primesense(64, 48), None, None, index, cluster, weight, chunk=len(index))
    split = gauss_newton.information(problem, obs, Pinhole.primesense(64, 48), None, None, index, cluster, weight, chunk=7)
    assert whole.B.abs().max() > 0 and whole.rss > 0
    torch.testing.assert_close(split.H, whole.H)
    torch.testing.assert_close(split.B, whole.B)
    assert split.rss == pytest.approx(whole.rss) and split.count == pytest.approx(whole.count)
    assert split.colour_ss == pytest.approx(whole.colour_ss) and split.colour_count == pytest.approx(whole.colour_count)
    assert whole.silhouette_count > 0
    assert split.silhouette_ss == pytest.approx(whole.silhouette_ss)
    assert split.silhouette_count == pytest.approx(whole.silhouette_count)


def test_the_silhouette_misfit_is_the_mean_squared_outline_difference():
    """The covariance reports the box's mean squared difference of opacity and mask: the silhouette
    residuals over the silhouette weight's root, squared and averaged (every ray drawn); 0 where the
    options have no silhouette term."""
    A, y, obs, param = linear_case()
    weighted = linear_covariance(LinearProblem(A, y, silhouette_weight=4.0), obs, param, max_rays=10_000)
    assert weighted.silhouette_misfit == pytest.approx(float((y[:, 3] ** 2).mean()) / 4.0, rel=1e-9)
    assert weighted.colour_variance == pytest.approx(float((y[:, :3] ** 2).mean()), rel=1e-9)
    assert linear_covariance(LinearProblem(A, y, silhouette_weight=0.0), obs, param, max_rays=10_000).silhouette_misfit == 0.0


def test_estimating_imports_neither_torch_dynamo_nor_sympy():
    """The Jacobians are plain reverse mode on scalar outputs: ``torch.func.jacfwd`` imported
    torch._dynamo (about 1.5 s and 66 MiB of resident memory in every process that estimates) and a
    batched or tensor ``grad_outputs`` imports sympy (0.5 s, 33 MiB)."""
    code = (
        "import sys, torch\n"
        "from tests.test_gauss_newton import *\n"
        "from tests.test_estimate import SliderField, make_model\n"
        "m = make_model(SliderField(), ASSETS)\n"
        "T = view(); image, mask, depth = observe(m, T, TRUTH)\n"
        "o = EstimateOptions.preset('gauss-newton', adam_iterations=0, iterations=2, theta_starts=1, coarse_to_fine=1)\n"
        "r = refine(m, image, mask, CAMERA, T, depth=depth, options=o)\n"
        "assert r.uncertainty is not None\n"
        "print('torch._dynamo' in sys.modules or 'sympy' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=str(ASSETS.parent.parent))
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "False"


def test_adam_runs_get_an_uncertainty_too(model):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    result = refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=EstimateOptions(iterations=2))
    assert result.uncertainty is not None and result.to_dict()["uncertainty"]["dof"] > 0
    off = refine(model, image, mask, CAMERA, T, options=EstimateOptions(iterations=2, uncertainty=False))
    assert off.uncertainty is None and off.to_dict()["uncertainty"] is None


@pytest.mark.slow
def test_gauss_newton_on_the_bundled_clamp(tmp_path):
    """The bundled clamp from the paper's perturbation (10 deg, 2 cm): a real improvement."""
    from narf_core.bundle import load_bundle
    from narf_core.geometry import Pinhole

    clamp = load_bundle(ASSETS.parent.parent / "models" / "clamp.narf")
    camera = Pinhole.primesense(160, 120)
    mid = {j.name: (j.lower + j.upper) / 2 for j in clamp.joints}
    truth = {j.name: j.lower + 0.3 * (j.upper - j.lower) for j in clamp.joints}
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.6]
    T[:3, :3] = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)
    out = clamp.render(torch.as_tensor(T, dtype=torch.float32), clamp.joint_vector(truth), camera, outputs=("rgb", "opacity", "depth"))
    image = (out["rgb"].numpy() * 255).round().astype(np.uint8)
    mask, depth = out["opacity"].numpy() > 0.5, out["depth"].numpy()
    T0 = perturbed(T, 10, 0.02, seed=3)
    start = refine(clamp, image, mask, camera, T0, joints_init=mid, options=EstimateOptions(iterations=0), ground_truth=(T, truth))
    result = refine(clamp, image, mask, camera, T0, joints_init=mid, depth=depth,
                    options=EstimateOptions.preset("gauss-newton"), ground_truth=(T, truth))
    assert result.metrics["add"] < start.metrics["add"] / 3, (start.metrics, result.metrics)
    assert result.uncertainty is not None and np.isfinite(result.uncertainty.covariance).all()


@pytest.mark.slow
def test_the_service_returns_the_uncertainty(model, tmp_path):
    """A real server on loopback with the real library: /v1/estimate with the gauss-newton preset
    answers an uncertainty the client reads as numpy; a bad solver name is a 422 naming the field."""
    from narf_client import InvalidInput, NarfClient, Uncertainty as ClientUncertainty
    from narf_service.app import create_app
    from narf_service.engine import Engine
    from narf_service.main import serve_in_thread
    from narf_service.registry import ModelRegistry
    from narf_service.settings import Settings

    settings = Settings(models_dir=tmp_path, workers=1, queue_size=2, torch_threads=1)
    app = create_app(settings, engine=Engine.narf_core(), registry=ModelRegistry(models={"slider": model}))
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    K = CAMERA.K.double().numpy()
    with serve_in_thread(app) as url, NarfClient(url) as narf:
        est = narf.estimate(image, mask, K, perturbed(T, 3, 0.005, seed=4), model="slider", depth=depth,
                            options={"preset": "gauss-newton", "theta_starts": 1, "coarse_to_fine": 1, "adam_iterations": 0},
                            iterations=4)
        assert isinstance(est.uncertainty, ClientUncertainty)
        assert est.uncertainty.covariance.shape == (7, 7) and np.allclose(est.uncertainty.covariance, est.uncertainty.covariance.T)
        assert est.uncertainty.position_sigma_m.shape == (3,) and set(est.uncertainty.joint_sigma) == {"slide"}
        assert est.uncertainty.dof > 0
        with pytest.raises(InvalidInput) as info:
            narf.estimate(image, mask, K, T, model="slider", options={"solver": "lbfgs"}, iterations=1)
        assert "solver" in info.value.field


def test_the_pose_jacobian_matches_autograd() -> None:
    """The central differences of ``T_obj_cam``'s top block in the pose columns agree with reverse mode
    (the exact derivative) to 1e-8, at rows away from the reference pose."""
    from narf_core.geometry import invert_pose, se3_exp

    g = torch.Generator().manual_seed(3)
    T_ref = se3_exp(torch.randn(1, 6, generator=g, dtype=torch.float64) * 0.5)[0]
    T_ref[:3, 3] += torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64)
    centre = torch.eye(4, dtype=torch.float64)
    centre[:3, 3] = torch.tensor([0.05, -0.02, 0.6], dtype=torch.float64)
    chain = gauss_newton.Chain(T_ref, centre, 0.15, torch.zeros(1, dtype=torch.float64),
                               torch.ones(1, dtype=torch.float64), True)
    p = torch.randn(3, 7, generator=g, dtype=torch.float64) * 0.1
    T_obj_cam, dT = chain.object_from_camera_jacobian(p)
    pose = p[:, :6].clone().requires_grad_(True)
    top = invert_pose(chain.poses(torch.cat([pose, p[:, 6:]], dim=1)))[:, :3, :].reshape(-1, 12)
    exact = torch.stack([torch.autograd.grad(top[:, i].sum(), pose, retain_graph=True)[0] for i in range(12)], 1)
    torch.testing.assert_close(T_obj_cam, invert_pose(chain.poses(p)), rtol=0, atol=1e-12)
    torch.testing.assert_close(dT, exact.reshape(-1, 3, 4, 6), rtol=0, atol=1e-8)
    assert float(exact.abs().max()) > 0.1  # not trivially zero


def _overshooting_run(model, monkeypatch, cache: bool) -> tuple[object, list[float], int]:
    """The toy refined with steps 64 times the LM step (most are rejected, so λ climbs); the answer, λ
    before every solve at the fine level, and how many Jacobians were rendered."""
    monkeypatch.setattr(gauss_newton, "_STEP_FACTORS", (64.0,))
    if not cache:
        monkeypatch.setattr(gauss_newton.GaussNewtonRun, "_linearise", lambda self, rays, target, index, group, along=False:
                            self.problem.residuals(self.chain, self.params, rays, target, index, True, group, along))
    lams, jacobians = [], [0]
    solve, residuals = gauss_newton.GaussNewtonRun._solve, gauss_newton.Problem.residuals

    def counted(self, chain, p, rays, target, index, jacobian, group=1, along_ray=False):
        jacobians[0] += int(jacobian)
        return residuals(self, chain, p, rays, target, index, jacobian, group, along_ray)

    def logged(self, H, g):
        lams.append(float(self.lam[0]))
        return solve(self, H, g)

    monkeypatch.setattr(gauss_newton.Problem, "residuals", counted)
    monkeypatch.setattr(gauss_newton.GaussNewtonRun, "_solve", logged)
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    options = EstimateOptions.preset("gauss-newton", **{**GN, "iterations": 12}, coarse_to_fine=1, theta_starts=1,
                                     early_stop=False, uncertainty=False)
    result = refine(model, image, mask, CAMERA, perturbed(T, 10, 0.02, seed=1), depth=depth, options=options)
    return result, lams, jacobians[0]


def test_a_rejected_step_reuses_the_linearisation_and_changes_nothing_else(model, monkeypatch):
    """After a rejected step the fine level's rays and parameters are the same, so the next iteration
    takes the last residuals and Jacobian instead of rendering them again: the same answer, fewer
    Jacobians."""
    cached, lams, cached_jacobians = _overshooting_run(model, monkeypatch, cache=True)
    monkeypatch.undo()
    fresh, fresh_lams, fresh_jacobians = _overshooting_run(model, monkeypatch, cache=False)
    assert lams == fresh_lams and cached.iterations == fresh.iterations == 12
    np.testing.assert_array_equal(cached.T_cam_obj, fresh.T_cam_obj)
    assert cached.joints == fresh.joints
    rejected = sum(b > a for a, b in zip(lams, lams[1:]))
    assert rejected >= 3, lams  # the overshoot is rejected
    assert cached_jacobians == fresh_jacobians - rejected


def test_lambda_grows_faster_with_every_rejection_in_a_row(model, monkeypatch):
    """Nielsen's rule: λ's factor doubles with each further rejection in a row (4, 8, 16, ...) and
    falls back to 4 after an accepted step, so a run stuck at a tiny λ reaches a useful one in a few
    iterations instead of one factor of 4 per iteration."""
    _, lams, _ = _overshooting_run(model, monkeypatch, cache=True)
    expected, streak = [], 0
    for a, b in zip(lams, lams[1:]):
        if b > a:  # a rejection: λ times 4, 8, 16, ... (unless at the cap)
            want = gauss_newton._LAMBDA_UP * gauss_newton._LAMBDA_UP_GROWTH ** streak
            expected.append((b / a, min(want, gauss_newton._LAMBDA_MAX / a)))
            streak += 1
        else:
            assert b == pytest.approx(a / gauss_newton._LAMBDA_DOWN) or a == gauss_newton._LAMBDA_MIN
            streak = 0
    assert len(expected) >= 3 and max(want for _, want in expected) >= 8, lams
    for got, want in expected:
        assert got == pytest.approx(want, rel=1e-9), lams


def test_the_along_ray_derivative_is_the_render_moved_along_its_rays(model):
    """Moving every ray's origin along the ray by one sample spacing (the same points, one sample on)
    changes the toy's render only in its premultiplied depth, by ``-opacity z_per_t`` per metre: the
    corrected ``dP/do`` says exactly that along the ray and keeps its part across the ray, where
    autograd's part along the ray (the slope between two samples) is off by up to twice that."""
    from narf_core.geometry import Rays, invert_pose

    T = torch.as_tensor(view(), dtype=torch.float64)
    theta = model.joint_vector(TRUTH).double()[None]
    problem = gauss_newton.Problem(model, EstimateOptions.preset("gauss-newton", mode="narf"), 0.1, True)
    v, u = torch.meshgrid(torch.arange(12.0, 36.0, 2.0), torch.arange(16.0, 48.0, 2.0), indexing="ij")
    rays = CAMERA.rays(torch.stack([u.flatten(), v.flatten()], -1))
    T_obj_cam = invert_pose(T)[None]
    P, (raw, _, _) = problem.predictions(rays, T_obj_cam, theta, True)
    _, (exact, _, _) = problem.predictions(rays, T_obj_cam, theta, True, along_ray=True)
    d = rays.directions.double() @ T_obj_cam[0, :3, :3].T  # object frame, unit
    hit = P[0, :, 3] > 0.99
    assert int(hit.sum()) >= 20
    along = torch.einsum("nci,ni->nc", exact[0], d)
    scale = float(raw.abs().max())  # the leaves are float32: agreement to about 1e-6 of the largest entry
    torch.testing.assert_close(along[:, :4], torch.zeros_like(along[:, :4]), rtol=0, atol=1e-5 * scale)
    torch.testing.assert_close(along[:, 4], -P[0, :, 3] * rays.z_per_t.double(), rtol=0, atol=1e-5 * scale)
    across = lambda J: J - torch.einsum("nci,ni->nc", J, d)[..., None] * d[:, None, :]  # noqa: E731
    torch.testing.assert_close(across(exact[0]), across(raw[0]), rtol=0, atol=1e-5 * scale)
    # The renders, every ray's origin moved half a sample spacing back and on along the ray.
    o = T_obj_cam[0, :3, 3].float().expand(len(rays), 3)
    moved = [model.render_rays(Rays(o + s * d.float(), d.float(), rays.z_per_t), theta[0].float(), mode="narf",
                               outputs=("rgb", "opacity", "depth")) for s in (-model.step / 2, model.step / 2)]
    fd = (moved[1].depth - moved[0].depth).double() / model.step
    torch.testing.assert_close(fd[hit], along[hit, 4], rtol=0, atol=0.02)
    assert float((moved[1].opacity - moved[0].opacity).abs()[hit].max()) < 1e-3
    raw_along = torch.einsum("nci,ni->nc", raw[0], d)[hit, 4]
    assert float((raw_along - fd[hit]).abs().max()) > 0.3  # the slope between samples: not the derivative


def test_only_a_pyramid_run_polishes(model, monkeypatch):
    """The polish (exact along-ray derivatives, trial steps up to 32x) runs once one start is left at a
    pyramid's fine level; a run without a pyramid keeps the plain iteration (a tracker's frame without
    depth asks for the polish: tests/test_track.py)."""
    calls = []
    exact = gauss_newton.along_ray_exact
    monkeypatch.setattr(gauss_newton, "along_ray_exact", lambda *a: calls.append(1) or exact(*a))
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    T0 = perturbed(T, 10, 0.02, seed=1)
    plain = EstimateOptions.preset("gauss-newton", **{**GN, "iterations": 6}, coarse_to_fine=1, theta_starts=1,
                                   uncertainty=False)
    refine(model, image, mask, CAMERA, T0, depth=depth, options=plain)
    assert calls == []
    refine(model, image, mask, CAMERA, T0, depth=depth, options=replace(plain, coarse_to_fine=2, iterations=12))
    assert len(calls) >= 3


@pytest.mark.slow
def test_narf_estimate_takes_pose_starts(capsys, monkeypatch, tiny_bundle, tiny_dataset, tmp_path_factory):
    """``narf estimate --pose-starts N`` reaches the refiner's options (what a user picks for a start up to
    30 deg / 6 cm off); a count outside [1, 11] is one error line naming it."""
    import narf_core.estimate as estimate
    from tests.test_cli_model import assert_error, estimate_argv, run
    from tests.test_cli_model import view as view_files

    files = view_files.__wrapped__(tiny_dataset, tmp_path_factory)
    seen, real = [], estimate.refine

    def spy(*args, options, **kwargs):
        seen.append(options)
        return real(*args, options=options, **kwargs)

    monkeypatch.setattr(estimate, "refine", spy)
    argv = estimate_argv(tiny_bundle, files, **{"--iterations": "1"})
    code, _, err = run(capsys, *argv, "--preset", "robust", "--pose-starts", "3", "--json")
    assert code == 0, err
    assert seen[-1].pose_starts == 3 and seen[-1].theta_starts == 4 and seen[-1].iterations == 1
    code, out, err = run(capsys, *argv, "--json")
    assert code == 0 and seen[-1].pose_starts == 1, err
    chosen = json.loads(out)  # the default preset, auto, on a view without --depth
    assert chosen["preset"] == "robust" and "no depth" in chosen["preset_reason"] and seen[-1].rgb_polish == estimate.RGB_POLISH
    assert_error(capsys, "estimate", [*argv, "--pose-starts", "0"], "--pose-starts")
    assert_error(capsys, "estimate", [*argv, "--pose-starts", "12"], "pose_starts")


def test_bench_estimate_takes_modes_from_the_command_line(model, tmp_path, capsys):
    """``narf bench estimate --modes parts`` refines in that mode alone (so a run over trained models can
    leave out the slower one); a mode that is not a render mode is one error line naming the option."""
    from benchmarks.estimate import run, run_arguments
    from narf_core.cli import build_parser
    from narf_core.data.dataset import DatasetWriter, FrameImages, read_urdf
    from tests.test_cli_model import assert_error

    chosen = run_arguments(build_parser().parse_args(["bench", "estimate", "--modes", "parts", "--scales", "1"]))
    assert chosen == {"modes": ("parts",), "scale_sweep": (1.0,)}
    assert "modes" not in run_arguments(build_parser().parse_args(["bench", "estimate"]))
    assert_error(capsys, "bench estimate", ["bench", "estimate", "--modes", "auto"], "--modes")
    root = tmp_path / "toy"
    with DatasetWriter(root, read_urdf(ASSETS / "estimate_slider.urdf"), CAMERA) as writer:
        T = view((0.08, -0.15, 0.18))
        image, mask, _ = observe(model, T, TRUTH)
        writer.add("test", FrameImages(image, None, mask.astype(np.uint8)), T, TRUTH)
    result = run({"toy": model}, {"toy": root}, out_dir=tmp_path / "out", splits=("test",), scenes=1, iterations=2,
                 presets=("paper",), progress=False, **chosen)
    assert result["config"]["modes"] == ["parts"]
    assert [(row["mode"], row["preset"]) for row in result["table"]] == [("parts", "paper")]
    assert {s["mode"] for s in result["sweep"]} == {"parts"}


def _run_with_costs(costs: list[float]) -> gauss_newton.GaussNewtonRun:
    """A bare run whose starts (row ``i``: ``p[0] = i``) have robust cost ``costs[i]`` on any rays."""

    class Costs:
        def residuals(self, chain, p, rays, target, index, jacobian):
            r = torch.tensor(costs, dtype=torch.float64)[p[:, 0].long()].mul(2).sqrt()  # cost = r² / 2
            return gauss_newton.Residuals(r[:, None, None], None, torch.ones(len(p), 1, 1, dtype=torch.bool))

    run = object.__new__(gauss_newton.GaussNewtonRun)
    run.problem, run.chain, run.rng = Costs(), None, torch.Generator().manual_seed(0)
    run.obs, run.camera = SimpleNamespace(pixels=torch.zeros(8, 2), levels=[None]), SimpleNamespace(rays=lambda px: px)
    run.opts = SimpleNamespace(robust_loss="none", robust_scale=1.0)
    run.params = torch.zeros(len(costs), 7, dtype=torch.float64)
    run.params[:, 0] = torch.arange(len(costs))
    run.lam, run.lam_up = torch.arange(len(costs), dtype=torch.float64), torch.ones(len(costs), dtype=torch.float64)
    return run


def test_the_pruning_keeps_the_starts_tied_with_the_lowest_cost():
    """At the pruning every start within ``tie`` times the lowest cost goes on, lowest first, with its own
    λ; ``tie`` 1 keeps the lowest alone (the last pruning, and the rule before ties were kept)."""
    run = _run_with_costs([30.0, 40.0, 29.0, 33.0, 34.0])
    run._keep_best_starts(1.15)  # 29 * 1.15 = 33.35
    assert run.params[:, 0].tolist() == [2, 0, 3] and run.lam.tolist() == [2, 0, 3]
    assert torch.equal(run.best_params, run.params)
    run._keep_best_starts(1.0)
    assert run.params[:, 0].tolist() == [2]
    clear = _run_with_costs([50.0, 20.0, 40.0])
    clear._keep_best_starts(1.15)
    assert clear.params[:, 0].tolist() == [1]


def test_tied_starts_go_on_until_the_last_pruning(model, monkeypatch):
    """Starts tied at a third of the iterations go on together, and the lowest goes on alone from
    ``_LAST_PRUNE_SHARE`` of them; with no tie one start goes on from the first pruning."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    T0 = perturbed(T, 10, 0.02, seed=1)
    options = EstimateOptions.preset("gauss-newton", iterations=12, early_stop=False, uncertainty=False)
    keep = gauss_newton.GaussNewtonRun._keep_best_starts
    for tie, expected in ((1e9, [(4, 4), (6, 4)]), (1.0, [(4, 4)])):
        calls = []

        def spy(self, t, keep=keep):
            calls.append((self.iteration, len(self.params)))
            keep(self, t)

        monkeypatch.setattr(gauss_newton, "_PRUNE_TIE", tie)
        monkeypatch.setattr(gauss_newton.GaussNewtonRun, "_keep_best_starts", spy)
        result = refine(model, image, mask, CAMERA, T0, depth=depth, options=options, ground_truth=(T, TRUTH))
        assert calls == expected and result.iterations == 12
        assert result.metrics["add"] < 0.02, result.metrics


def test_bench_estimate_counts_the_scenes_that_flag_a_joint_unobserved(model, tmp_path):
    """A scene whose mask leaves the jaw out is flagged (``unobserved_joint``); the table counts it and
    gives the joint's error over the other scenes beside the error over all."""
    from benchmarks import shift
    from benchmarks.estimate import _fmt_joints, run_scenes, summarise
    from narf_core.data.dataset import Dataset, DatasetWriter, FrameImages, read_urdf

    root = tmp_path / "toy"
    with DatasetWriter(root, read_urdf(ASSETS / "estimate_slider.urdf"), CAMERA) as writer:
        for hide in (False, True):
            T = view()
            joints = {"slide": 0.06 if hide else 0.0}  # the protocol starts the jaw mid-range
            image, mask, _ = observe(model, T, joints)
            if hide:  # only the bar's left third: from mid-range the jaw stays out of it
                cols = np.nonzero(mask.any(0))[0]
                mask[:, cols[0] + (cols[-1] - cols[0]) // 3 :] = False
            writer.add("test", FrameImages(image, None, mask.astype(np.uint8)), T, joints)
    dataset = Dataset.open(root)
    options = EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=2, box_margin=0.0, theta_starts=1,
                                     refinements=0, pose_starts=1)
    rows = run_scenes(model, dataset, dataset.frames("test"), options, scale=0.0)
    assert [any(w.startswith("unobserved_joint: slide: ") for w in r["warnings"]) for r in rows] == [False, True]
    slide = summarise(model, rows)["joints"]["slide"]
    assert slide["unobserved"] == 1
    assert slide["observed_mean"] == pytest.approx(rows[0]["metrics"]["joint_error/slide"])
    assert slide["mean"] == pytest.approx(np.mean([r["metrics"]["joint_error/slide"] for r in rows]))
    seen = 1000 * slide["observed_mean"]
    assert f"(1 flagged unobserved; the others {seen:.2f} ± 0.00 mm)" in _fmt_joints({"slide": slide})
    row = {"joints": {"slide": slide}}
    assert f"slide {1000 * slide['mean']:.1f} ± " in shift._joints(row) and f"the others {seen:.1f} ± 0.0 mm)" in shift._joints(row)
