"""The Gauss-Newton refiner and the covariance of an estimate, on the analytic toy clamp of
tests/test_estimate.py (exact renders, known optimum) and on the bundled clamp."""

from __future__ import annotations

import json
import math
from dataclasses import asdict

import numpy as np
import pytest
import torch

from narf_core.estimate import (
    EstimateInputError,
    EstimateOptions,
    Uncertainty,
    chi2_quantile,
    local_error,
    nees,
    refine,
)
from tests.test_estimate import ASSETS, CAMERA, TRUTH, SliderField, make_model, observe, perturbed, view

GN = dict(adam_iterations=0, iterations=25, rays_per_iteration=512)  # Levenberg-Marquardt alone
NO_FLOOR = dict(sigma_floor_position=0.0, sigma_floor_rotation=0.0, sigma_floor_joint=0.0)  # the statistical Σ only


@pytest.fixture(scope="module")
def model():
    return make_model(SliderField(), ASSETS, parts=True)


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


def test_covariance_is_symmetric_psd_and_shrinks_with_depth_and_rays(model):
    T = view()
    image, mask, depth = observe(model, T, TRUTH)

    def unc(**kw) -> Uncertainty:
        options = EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0, uncertainty_patch=1, **NO_FLOOR, **kw)
        return refine(model, image, mask, CAMERA, T, joints_init=TRUTH, options=options).uncertainty

    few = unc(uncertainty_rays=200)
    many = unc(uncertainty_rays=4096)
    for u in (few, many):
        S = u.covariance
        assert S.shape == (7, 7) and np.allclose(S, S.T)
        assert np.linalg.eigvalsh(S).min() >= -1e-12 * np.abs(S).max()
        assert np.allclose(np.sqrt(np.diag(S))[:3], u.position_sigma_m)
        assert set(u.joint_sigma) == {"slide"} and u.dof > 0 and u.residual_variance > 0
    # More rays, same residual variance scale: smaller σ (variance scaled by the residuals it sees).
    assert np.trace(many.covariance[:3, :3]) / many.residual_variance < np.trace(few.covariance[:3, :3]) / few.residual_variance
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
    """The jaw outside the image: θ does not change any ray, Σ stays finite with θ's σ near its prior."""
    T = view()
    joints = {"slide": 0.06}
    image, mask, _ = observe(model, T, joints)
    # Hide the jaw: keep only the bar's pixels (the left part of the object in this view).
    cols = np.nonzero(mask.any(0))[0]
    mask[:, (cols[0] + cols[-1]) // 2 :] = False
    options = EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0, box_margin=0.0, **NO_FLOOR)
    u = refine(model, image, mask, CAMERA, T, joints_init=joints, options=options).uncertainty
    assert np.isfinite(u.covariance).all()
    assert u.joint_sigma["slide"] > 0.001


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
        (dict(ray_sampling="random"), "options.ray_sampling must be one of uniform, edges"),
        (dict(depth_sigma=-0.1), "options.depth_sigma must be >= 0"),
        (dict(uncertainty_patch=0), "options.uncertainty_patch must be in [1, 64]"),
        (dict(adam_iterations=-1), "options.adam_iterations must be >= 0"),
    ],
)
def test_bad_solver_options_are_refused(kwargs, message):
    with pytest.raises(EstimateInputError, match=message.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        EstimateOptions(**kwargs)
    with pytest.raises(EstimateInputError, match="options.preset must be one of paper, robust, gauss-newton"):
        EstimateOptions.preset("newton")


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


def test_the_model_error_floor_adds_to_the_diagonal(model):
    T = view()
    image, mask, _ = observe(model, T, TRUTH)
    run = lambda **kw: refine(model, image, mask, CAMERA, T, joints_init=TRUTH,  # noqa: E731
                              options=EstimateOptions.preset("gauss-newton", adam_iterations=0, iterations=0, **kw)).uncertainty
    bare, floored = run(**NO_FLOOR), run(sigma_floor_position=0.003, sigma_floor_rotation=0.02, sigma_floor_joint=0.1)
    added = np.diag(floored.covariance - bare.covariance)
    assert np.allclose(added, [0.003**2] * 3 + [0.02**2] * 3 + [(0.1 * (0.06 - -0.06)) ** 2])


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
