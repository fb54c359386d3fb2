"""``EstimateOptions.rgb_polish``: Levenberg-Marquardt iterations after Adam, from its estimate, on one fixed
set of rays, where a view comes without a depth image (the analytic toy clamp of tests/test_estimate.py)."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from narf_core.estimate import EstimateInputError, EstimateOptions, refine
from narf_core.gauss_newton import _POLISH_STEP_FACTORS, _STEP_FACTORS
from tests.test_estimate import CAMERA, TRUTH
from tests.test_estimate_refinements import model, scene  # noqa: F401 (the toy and its view 8 deg / 1.2 cm off)

# Adam stopped early and short: 6 iterations from 8 deg / 1.2 cm off leave the estimate millimetres away, its
# silhouette still off the mask (overlap 0.74), so the polish is let run whatever the overlap.
SHORT = dict(iterations=6, rays_per_iteration=256, theta_starts=1, rgb_refinements=1, uncertainty=False,
             early_stop=False, polish_overlap=0.0)


def test_the_polish_takes_adam_s_estimate_to_the_bottom_of_the_loss(model, scene):
    T, image, mask, _, T0 = scene
    adam = refine(model, image, mask, CAMERA, T0, options=EstimateOptions.robust(rgb_polish=0, **SHORT),
                  ground_truth=(T, TRUTH))
    options = EstimateOptions.robust(rgb_polish=40, polish_rays=2048, **SHORT)
    polished = refine(model, image, mask, CAMERA, T0, options=options, ground_truth=(T, TRUTH))
    assert adam.metrics["add"] > 0.004  # Adam alone stopped short
    assert polished.metrics["add"] < min(0.002, adam.metrics["add"] / 3), (adam.metrics, polished.metrics)
    assert polished.metrics["joint_error/slide"] < 0.002
    assert polished.loss < adam.loss
    assert SHORT["iterations"] < polished.iterations <= SHORT["iterations"] + 40  # the polish's count too
    assert len(polished.trace) == polished.iterations and polished.status in ("converged", "max_iterations")
    assert np.allclose(polished.T_cam_obj[:3, :3] @ polished.T_cam_obj[:3, :3].T, np.eye(3), atol=1e-9)


def test_no_iterations_leave_the_start_unpolished(model, scene):
    T, image, mask, _, T0 = scene
    result = refine(model, image, mask, CAMERA, T0, options=EstimateOptions.robust(**{**SHORT, "iterations": 0}))
    assert result.iterations == 0 and np.allclose(result.T_cam_obj, T0)


def test_a_view_with_depth_is_not_polished(model, scene):
    T, image, mask, depth, T0 = scene
    options = EstimateOptions.robust(rgb_polish=40, polish_rays=2048, **SHORT)
    rgbd = refine(model, image, mask, CAMERA, T0, depth=depth, options=options)
    plain = refine(model, image, mask, CAMERA, T0, depth=depth, options=replace(options, rgb_polish=0))
    assert rgbd.iterations == plain.iterations == SHORT["iterations"]
    assert np.array_equal(rgbd.T_cam_obj, plain.T_cam_obj)


def test_the_polish_keeps_adam_s_estimate_where_its_own_loss_is_higher(model, scene, monkeypatch):
    """The choice compares both on the same rays: a polish that went astray is not returned."""
    T, image, mask, _, T0 = scene
    options = EstimateOptions.robust(rgb_polish=3, polish_rays=512, **SHORT)
    adam = refine(model, image, mask, CAMERA, T0, options=replace(options, rgb_polish=0))
    from narf_core import gauss_newton

    real = gauss_newton.GaussNewtonRun.optimise

    def astray(self, snapshot=None):
        real(self, snapshot)
        self.best_params = self.best_params.clone()
        self.best_params[:, :3] += 0.5  # half a radius off
        self.params = self.best_params

    monkeypatch.setattr(gauss_newton.GaussNewtonRun, "optimise", astray)
    kept = refine(model, image, mask, CAMERA, T0, options=options)
    assert np.allclose(kept.T_cam_obj, adam.T_cam_obj, atol=1e-12)
    assert kept.iterations > adam.iterations


def test_a_cancelled_polish_returns_the_better_estimate_so_far_and_says_so(model, scene):
    T, image, mask, _, T0 = scene
    polls = iter([None] * (SHORT["iterations"] + 2) + ["cancelled"] * 1000)
    options = EstimateOptions.robust(rgb_polish=40, polish_rays=2048, **SHORT)
    result = refine(model, image, mask, CAMERA, T0, options=options, should_stop=lambda: next(polls))
    assert result.status == "cancelled"
    assert result.iterations == SHORT["iterations"] + 2  # the polish polls before each of its iterations
    assert np.isfinite(result.T_cam_obj).all()


def test_a_mask_the_render_cannot_explain_is_not_polished(model, scene):
    """After 40 Adam iterations the silhouette explains the exact mask (overlap 0.95) and the polish runs. With
    half the mask cut away (an occluder, a segmenter's miss) Adam's silhouette overlaps it far less than
    ``polish_overlap``, and the polish, which would shrink the silhouette onto it, does not run; told to run
    whatever the overlap (0), it does."""
    _, image, mask, _, T0 = scene
    options = EstimateOptions.robust(rgb_polish=40, polish_rays=2048, **{**SHORT, "iterations": 40})
    options = replace(options, polish_overlap=EstimateOptions().polish_overlap)
    assert options.polish_overlap == 0.9
    assert refine(model, image, mask, CAMERA, T0, options=options).iterations > 40
    cut = mask.copy()
    columns = np.nonzero(mask.any(axis=0))[0]
    cut[:, (columns[0] + columns[-1]) // 2:] = False
    kept = refine(model, image, cut, CAMERA, T0, options=options)
    adam = refine(model, image, cut, CAMERA, T0, options=replace(options, rgb_polish=0))
    assert kept.iterations == adam.iterations == 40
    assert np.array_equal(kept.T_cam_obj, adam.T_cam_obj)
    forced = refine(model, image, cut, CAMERA, T0, options=replace(options, polish_overlap=0.0))
    assert forced.iterations > 40


def test_max_rays_bounds_the_rays_a_polished_refinement_traces(model, scene, monkeypatch):
    _, image, mask, _, T0 = scene
    options = EstimateOptions.robust(rgb_polish=40, polish_rays=2048, **SHORT)
    plain = replace(options, rgb_polish=0)
    steps = max(len(_POLISH_STEP_FACTORS), len(_STEP_FACTORS))
    assert options.max_rays(depth=False) == plain.max_rays(depth=False) + 40 * 2048 * (1 + steps) + 3 * options.eval_rays
    assert options.max_rays(depth=True) == plain.max_rays(depth=True)
    rays = []
    real = model.render_rays
    monkeypatch.setattr(model, "render_rays", lambda r, *a, **k: rays.append(len(r)) or real(r, *a, **k))
    refine(model, image, mask, CAMERA, T0, options=options)
    assert 0 < sum(rays) <= options.max_rays(depth=False)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(rgb_polish=-1), "options.rgb_polish must be in [0, 1000]"),
        (dict(rgb_polish=10, solver="gauss-newton"), "options.rgb_polish is for the adam solver"),
        (dict(polish_rays=8), "options.polish_rays must be >= 16"),
        (dict(polish_overlap=1.5), "options.polish_overlap must be in [0, 1]"),
    ],
)
def test_bad_polish_options_are_refused(kwargs, message):
    with pytest.raises(EstimateInputError, match=re.escape(message)):
        EstimateOptions(**kwargs)
