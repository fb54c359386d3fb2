"""``EstimateOptions.slide_share``: an estimate left slid along the object's longest axis (an occluder over one
end, a segmenter's blob at the other) is scored against its slid copies, and refined once more from a copy
that scores lower (issue #15); on the analytic toy clamp of tests/test_estimate.py, whose bar is longest
along its x axis."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
import torch

import narf_core.estimate as estimate
from narf_core.estimate import EstimateInputError, EstimateOptions, refine
from tests.test_estimate import CAMERA, TRUTH, loss_problem, make_model, observe, spy_on_renders, view, SliderField

LENGTH = 0.18  # the toy's box along x, its longest side
# One Levenberg-Marquardt iteration damped so hard that it barely moves: the refinement ends where it starts, as
# one stuck in a minimum along the axis does; the pose starts and the other estimates are off, so that only the
# slide's second refinement can move it (align_start, which would move the start onto the mask, is off too, and so
# is the starts' fit to the depth's points, which moves it back along the bar). The mask is trusted partially, as
# where a depth image contradicts it (the slide runs only there), with one θ start.
STUCK = dict(iterations=1, damping=1e6, uncertainty=False, theta_starts=1, pose_starts=1, refinements=1,
             align_start=False, mask_trust="partial", partial_theta_starts=1, surface_fit_iterations=0)


@pytest.fixture(scope="module")
def model():
    return make_model(SliderField())


def slid(T: np.ndarray, metres: float) -> np.ndarray:
    """``T`` moved by ``metres`` along the object's own x axis."""
    out = T.copy()
    out[:3, 3] += T[:3, :3] @ np.array([metres, 0.0, 0.0])
    return out


def test_the_slid_copies_move_along_the_object_s_longest_axis_only(model):
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    options = EstimateOptions.gauss_newton()
    _, param, _, row = loss_problem(model, T, image, mask, depth, options)
    row = row.clone()
    row[0, :6] = torch.tensor([0.05, -0.02, 0.03, 0.1, -0.2, 0.05], dtype=torch.float64)  # some pose off the truth
    copies = estimate._slid_rows(model, param, row, 0.05)
    T_row = param.poses(row)[0].numpy()
    for copy, steps in zip(param.poses(copies).numpy(), (-2, -1, 1, 2)):
        np.testing.assert_allclose(copy, slid(T_row, steps * 0.05 * LENGTH), atol=1e-12)
    assert torch.equal(param.thetas(copies), param.thetas(row).expand(4, -1))


def test_an_estimate_stuck_along_the_axis_is_refined_again_from_the_copy_that_scores_lower(model, monkeypatch):
    """From a start 1.8 cm along the bar a refinement that cannot move ends there; its copy slid back scores
    lower, the second refinement from it ends at the truth, that estimate is returned with both refinements'
    iterations, and every ray traced stays within ``max_rays``."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    options = EstimateOptions.gauss_newton(**STUCK)
    assert options.slide_share == estimate.GN_SLIDE_SHARE == 0.05
    start = slid(T, 2 * 0.05 * LENGTH)
    stuck = refine(model, image, mask, CAMERA, start, joints_init=TRUTH, depth=depth,
                   options=replace(options, slide_share=0.0), ground_truth=(T, TRUTH))
    calls = spy_on_renders(model, monkeypatch)
    found = refine(model, image, mask, CAMERA, start, joints_init=TRUTH, depth=depth, options=options,
                   ground_truth=(T, TRUTH))
    assert stuck.metrics["add"] > 0.015  # without the slide it stays where it started
    assert found.metrics["add"] < 0.001 and found.loss < stuck.loss
    assert found.iterations == 2 * stuck.iterations
    assert sum(n for n, _, _ in calls) <= options.max_rays(depth=True)


def test_an_estimate_no_copy_undercuts_is_returned_unchanged(model, monkeypatch):
    """At the truth every slid copy scores higher: no second refinement, and the estimate is the one without the
    option, to the bit."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    options = EstimateOptions.gauss_newton(**{**STUCK, "iterations": 5, "damping": 1e-3})
    refinements = []
    real = estimate._gauss_newton_refinement
    monkeypatch.setattr(estimate, "_gauss_newton_refinement", lambda *a: refinements.append(1) or real(*a))
    on = refine(model, image, mask, CAMERA, T, joints_init=TRUTH, depth=depth, options=options)
    assert len(refinements) == 1
    off = refine(model, image, mask, CAMERA, T, joints_init=TRUTH, depth=depth, options=replace(options, slide_share=0))
    assert np.array_equal(on.T_cam_obj, off.T_cam_obj) and on.joints == off.joints and on.iterations == off.iterations


def test_a_fully_trusted_mask_is_not_slid(model, monkeypatch):
    """The stuck estimate of the test above with the mask trusted in full (its outline holds both ends): no copy
    is scored, and the estimate is the one without the option, to the bit."""
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    options = EstimateOptions.gauss_newton(**{**STUCK, "mask_trust": "full"})
    scored = []
    monkeypatch.setattr(estimate, "_slid_rows", lambda *a: scored.append(1))
    start = slid(T, 2 * 0.05 * LENGTH)
    full = refine(model, image, mask, CAMERA, start, joints_init=TRUTH, depth=depth, options=options)
    off = refine(model, image, mask, CAMERA, start, joints_init=TRUTH, depth=depth, options=replace(options, slide_share=0))
    assert not scored and np.array_equal(full.T_cam_obj, off.T_cam_obj)


def test_the_slide_is_counted_in_max_rays_where_the_mask_may_be_trusted_partially_and_its_share_is_bounded():
    on, off = EstimateOptions.gauss_newton(), EstimateOptions.gauss_newton(slide_share=0)
    assert on.max_rays() > off.max_rays()  # with a depth image "auto" may trust the mask partially
    assert on.max_rays(depth=False) == off.max_rays(depth=False)  # without one it trusts it in full
    partial = EstimateOptions.robust(mask_trust="partial")
    assert replace(partial, slide_share=0.05).max_rays(False) > partial.max_rays(False)
    for bad in (-0.01, 0.3):
        with pytest.raises(EstimateInputError, match=re.escape("options.slide_share must be in [0, 0.25]")):
            EstimateOptions(slide_share=bad)
