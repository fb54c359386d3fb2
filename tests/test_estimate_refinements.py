"""Several refinements where one is least reliable (no depth, or a partially trusted mask) and the
choice among them on one fixed set of rays (``EstimateOptions.refinements``, issue #15); on the
analytic toy clamp of tests/test_estimate.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from torch import Tensor

import narf_core.estimate as estimate
from narf_core.estimate import EstimateInputError, EstimateOptions, refine
from tests.test_estimate import ASSETS, CAMERA, TRUTH, SliderField, make_model, observe, perturbed, view

pytest_plugins = ("conftest_model",)  # tiny_bundle, tiny_dataset (the CLI test)

# (rgb_polish off: these are the refinements' tests; tests/test_estimate_polish.py has the polish's)
FAST = dict(iterations=30, rays_per_iteration=256, theta_starts=2, uncertainty=False, early_stop=False, rgb_polish=0)


@pytest.fixture(scope="module")
def model():
    return make_model(SliderField(), ASSETS)


@pytest.fixture(scope="module")
def scene(model):
    T = view()
    image, mask, depth = observe(model, T, TRUTH)
    return T, image, mask, depth, perturbed(T, 8, 0.012, seed=3)


def spy_on_choice(monkeypatch) -> list[tuple[Tensor, Tensor]]:
    """Every call of the choice among refinements: its rows ``[R, d]`` and their losses ``[R]``."""
    calls = []
    real = estimate._fixed_rays_loss

    def spy(loss_fn, obs, camera, param, params, rng, n=0):
        losses = real(loss_fn, obs, camera, param, params, rng, n)
        if n == estimate._CHOICE_RAYS:
            calls.append((param.poses(params), losses))
        return losses

    monkeypatch.setattr(estimate, "_fixed_rays_loss", spy)
    return calls



def test_without_depth_the_estimate_of_lowest_loss_among_the_refinements_is_kept(model, scene, monkeypatch):
    """Three refinements from the same starts, each on its own rays (the second on one pyramid
    level): they end apart, and the one returned is the row of lowest loss on the common rays;
    the iterations reported are all three runs'."""
    T, image, mask, _, T0 = scene
    calls = spy_on_choice(monkeypatch)
    options = EstimateOptions.robust(refinements=3, **FAST)
    result = refine(model, image, mask, CAMERA, T0, options=options, ground_truth=(T, TRUTH))
    assert len(calls) == 1
    poses, losses = calls[0]
    assert poses.shape[0] == 3 and bool(torch.isfinite(losses).all())
    assert float((poses[0] - poses[1]).abs().max()) > 1e-5  # other rays, another pyramid: another trajectory
    best = int(losses.argmin())
    np.testing.assert_allclose(result.T_cam_obj, poses[best].numpy(), atol=1e-6)
    assert result.iterations == 3 * options.iterations
    assert result.metrics["add"] < 0.01


def test_the_first_refinement_is_the_single_run_and_depth_keeps_one(model, scene, monkeypatch):
    """``refinements`` 0 and 1 give the same estimate bit for bit, and the first of several runs
    is that run; with a depth image and a mask trusted in full only one refinement runs, whatever
    the option says; with the mask trusted partially, several."""
    T, image, mask, depth, T0 = scene
    one = refine(model, image, mask, CAMERA, T0, options=EstimateOptions.robust(rgb_refinements=0, **FAST))
    same = refine(model, image, mask, CAMERA, T0, options=EstimateOptions.robust(rgb_refinements=0, refinements=1, **FAST))
    np.testing.assert_array_equal(one.T_cam_obj, same.T_cam_obj)
    calls = spy_on_choice(monkeypatch)
    refine(model, image, mask, CAMERA, T0, options=EstimateOptions.robust(rgb_refinements=0, refinements=2, **FAST))
    np.testing.assert_allclose(calls[0][0][0].numpy(), one.T_cam_obj, atol=1e-9)
    calls.clear()
    with_depth = [refine(model, image, mask, CAMERA, T0, depth=depth, options=EstimateOptions.robust(refinements=k, **FAST))
                  for k in (0, 3)]
    assert not calls
    np.testing.assert_array_equal(with_depth[0].T_cam_obj, with_depth[1].T_cam_obj)
    assert with_depth[1].iterations == FAST["iterations"]
    partial = EstimateOptions.robust(refinements=3, mask_trust="partial", **FAST)
    result = refine(model, image, mask, CAMERA, T0, depth=depth, options=partial)
    assert len(calls) == 1 and calls[0][0].shape[0] == 3 and result.iterations == 3 * FAST["iterations"]


def test_a_cancelled_refinement_ends_the_series(model, scene, monkeypatch):
    """``should_stop`` during a refinement: no further runs, the status says why (in the second, the
    choice is between the first's estimate and the second's so far)."""
    _, image, mask, _, T0 = scene
    calls = spy_on_choice(monkeypatch)
    polls = iter([None] * 5 + ["cancelled"] * 1000)
    result = refine(model, image, mask, CAMERA, T0, options=EstimateOptions.robust(refinements=3, **FAST),
                    should_stop=lambda: next(polls))
    assert result.status == "cancelled" and result.iterations == 5 and not calls
    polls = iter([None] * (FAST["iterations"] + 5) + ["cancelled"] * 1000)  # in the second: a choice among two
    result = refine(model, image, mask, CAMERA, T0, options=EstimateOptions.robust(refinements=3, **FAST),
                    should_stop=lambda: next(polls))
    assert result.status == "cancelled" and result.iterations == FAST["iterations"] + 5
    assert len(calls) == 1 and calls[0][0].shape[0] == 2


def test_rgb_refinements_refine_three_times_without_a_depth_image_and_once_with_one(model, scene, monkeypatch):
    """``rgb_refinements`` 3 (the robust preset's before its polish): a view without a depth image gets 3
    refinements and the choice among them (``refinements`` may ask for more, not fewer); with a depth image
    (and the mask trusted in full) one, as before. The robust preset now polishes instead."""
    T, image, mask, depth, T0 = scene
    calls = spy_on_choice(monkeypatch)
    assert EstimateOptions.robust().rgb_refinements == 0 and EstimateOptions.robust().rgb_polish == estimate.RGB_POLISH
    options = EstimateOptions.robust(rgb_refinements=3, **FAST)
    assert options.refinements == 0
    rgb = refine(model, image, mask, CAMERA, T0, options=options, ground_truth=(T, TRUTH))
    assert len(calls) == 1 and calls[0][0].shape[0] == 3 and rgb.iterations == 3 * FAST["iterations"]
    calls.clear()
    more = refine(model, image, mask, CAMERA, T0, options=replace(options, refinements=4))
    assert len(calls) == 1 and calls[0][0].shape[0] == 4 and more.iterations == 4 * FAST["iterations"]
    calls.clear()
    rgbd = refine(model, image, mask, CAMERA, T0, depth=depth, options=options)
    assert not calls and rgbd.iterations == FAST["iterations"]


def test_gauss_newton_refines_twice_where_the_mask_is_partly_trusted(model, scene, monkeypatch):
    """The gauss-newton preset's ``refinements``: with a partly trusted mask two estimates, the first the
    single run's (uniform rays), the second on its own seed with half its rays on edges and no pose-start
    check, and the one of lower loss on the common rays is returned, the iterations of both reported. One
    estimate with the mask trusted in full and a depth image, or where the first one's silhouette overlaps
    the mask at least ``pose_starts_overlap``."""
    T, image, mask, depth, T0 = scene
    small = dict(iterations=20, rays_per_iteration=512, theta_starts=1, pose_starts=1, pose_starts_overlap=0.0,
                 align_start=False, uncertainty=False, early_stop=False)
    options = EstimateOptions.gauss_newton(mask_trust="partial", **small)
    assert options.refinements == 3 and options.ray_sampling == "uniform"  # no third: align_start is off
    samplings, real_index = set(), estimate._ray_index
    monkeypatch.setattr(estimate, "_ray_index",
                        lambda obs, opts, *a: samplings.add((opts.seed, opts.ray_sampling)) or real_index(obs, opts, *a))
    calls = spy_on_choice(monkeypatch)
    result = refine(model, image, mask, CAMERA, T0, depth=depth, options=options, ground_truth=(T, TRUTH))
    assert samplings == {(0, "uniform"), (1, "edges")}
    assert len(calls) == 1
    poses, losses = calls[0]
    assert poses.shape[0] == 2 and bool(torch.isfinite(losses).all())
    np.testing.assert_allclose(result.T_cam_obj, poses[int(losses.argmin())].numpy(), atol=1e-6)
    assert result.iterations == 2 * small["iterations"] and result.metrics["add"] < 0.01
    single = refine(model, image, mask, CAMERA, T0, depth=depth, options=replace(options, refinements=1))
    np.testing.assert_allclose(poses[0].numpy(), single.T_cam_obj, atol=1e-9)
    calls.clear()
    full = refine(model, image, mask, CAMERA, T0, depth=depth, options=replace(options, mask_trust="full"))
    assert not calls and full.iterations == small["iterations"]
    explained = refine(model, image, mask, CAMERA, T0, depth=depth,
                       options=replace(options, pose_starts_overlap=estimate.GN_POSE_OVERLAP))
    assert not calls and explained.iterations == small["iterations"]  # the first estimate overlaps the mask
    checks, real_check = [], estimate._adaptive_refinement  # the pose-start check: the first estimate's alone
    monkeypatch.setattr(estimate, "_adaptive_refinement", lambda *a: checks.append(1) or real_check(*a))
    wide = replace(options, pose_starts=estimate.GN_POSE_STARTS, pose_starts_overlap=0.999)  # (no estimate reaches it)
    refine(model, image, mask, CAMERA, T0, depth=depth, options=wide)
    assert len(checks) == 1 and len(calls) == 1


def test_gauss_newton_refines_a_third_time_from_unaligned_starts_where_the_mask_is_partly_trusted(
    model, scene, monkeypatch
):
    """With a partly trusted mask and ``align_start``, the preset's third estimate is the first one again (its
    rays, uniform) from the starts ``align_start`` had not moved onto the mask's centroid and depth (an
    occluder moves the centroid, and the moved start with it): the first estimate starts from the moved rows,
    the third from the given pose, and the lowest loss of the three on the common rays is returned. Where no
    start had moved (the given pose scored lower), or with the mask trusted in full, no third."""
    T, image, mask, depth, _ = scene
    T0 = T.copy()
    T0[0, 3] += 0.03  # 3 cm beside the truth: the start moved onto the mask's centroid scores lower
    small = dict(iterations=8, rays_per_iteration=256, theta_starts=1, pose_starts=1, pose_starts_overlap=0.0,
                 uncertainty=False, early_stop=False, surface_fit_iterations=0)  # (the fit would move the given rows)
    options = EstimateOptions.gauss_newton(mask_trust="partial", **small)
    assert options.align_start and options.refinements == 3
    starts, real = [], estimate._gauss_newton_refinement

    def spy(model, o, obs, camera, param, loss_fn, rows, *rest):  # each refinement's options and start rows
        starts.append((o.seed, o.ray_sampling, o.align_start, rows.clone()))
        return real(model, o, obs, camera, param, loss_fn, rows, *rest)

    monkeypatch.setattr(estimate, "_gauss_newton_refinement", spy)
    calls = spy_on_choice(monkeypatch)
    result = refine(model, image, mask, CAMERA, T0, depth=depth, options=options, ground_truth=(T, TRUTH))
    assert [s[:3] for s in starts] == [(0, "uniform", True), (1, "edges", True), (0, "uniform", False)]
    moved, given = starts[0][3], starts[2][3]
    assert bool(moved[:, :3].abs().sum() > 0.1) and torch.equal(given[:, :6], torch.zeros_like(given[:, :6]))
    assert torch.equal(starts[1][3], moved)  # the edge estimate keeps the moved start
    poses, losses = calls[0]
    assert len(calls) == 1 and poses.shape[0] == 3 and bool(torch.isfinite(losses).all())
    np.testing.assert_allclose(result.T_cam_obj, poses[int(losses.argmin())].numpy(), atol=1e-6)
    assert result.iterations == 3 * small["iterations"]
    starts.clear()
    with monkeypatch.context() as m:  # a moved copy that scores no lower than the given pose: nothing moved
        m.setattr(estimate, "_aligned", lambda loss_fn, obs, camera, param, rows, *a: rows.clone())
        refine(model, image, mask, CAMERA, T0, depth=depth, options=options)
    assert [s[2] for s in starts] == [True, True] and not bool(starts[0][3][:, :6].any())
    starts.clear()
    refine(model, image, mask, CAMERA, T0, depth=depth, options=replace(options, mask_trust="full"))
    assert len(starts) == 1


def test_max_rays_bounds_the_rays_traced_without_a_depth_image(model, scene, monkeypatch):
    """Without a depth image the bound counts ``rgb_refinements`` runs of ``theta_starts`` (a partially
    trusted mask needs a depth, unless asked for) and the choice's rays; with one, as many runs as
    ``refinements``. The rays an RGB-only refinement renders stay within its bound."""
    options = EstimateOptions.robust(rgb_refinements=3, rgb_polish=0)
    one = replace(options, rgb_refinements=0)
    loop = options.iterations * options.rays_per_iteration * estimate._MAX_BOX_SCALE

    def run(starts: int) -> int:  # one refinement: its iterations, its pruning and its final choice
        return loop * starts + 3 * starts * options.eval_rays

    def after(starts: int) -> int:  # once per estimate: the final choice and the covariance
        return 2 * starts * options.eval_rays + options.uncertainty_rays * options.uncertainty_patch**2

    most = options.partial_theta_starts
    assert options.max_rays() == one.max_rays() == run(most) + after(most)  # with depth: one refinement
    assert one.max_rays(depth=False) == run(options.theta_starts) + after(options.theta_starts)
    assert options.max_rays(depth=False) == (3 * run(options.theta_starts) + 3 * estimate._CHOICE_RAYS
                                             + after(options.theta_starts))
    partial = replace(options, mask_trust="partial")
    assert partial.max_rays(depth=False) == 3 * run(most) + 3 * estimate._CHOICE_RAYS + after(most)
    T, image, mask, _, T0 = scene
    rays = []
    real = model.render_rays
    monkeypatch.setattr(model, "render_rays", lambda r, *a, **k: rays.append(len(r)) or real(r, *a, **k))
    small = EstimateOptions.robust(rgb_refinements=3, **FAST)
    refine(model, image, mask, CAMERA, T0, options=small)
    three = sum(rays)
    rays.clear()
    refine(model, image, mask, CAMERA, T0, options=replace(small, rgb_refinements=0))
    assert 0 < sum(rays) <= replace(small, rgb_refinements=0).max_rays(depth=False)
    assert 2.5 * sum(rays) < three <= small.max_rays(depth=False)  # three runs' work, within the bound


def test_max_rays_counts_every_refinement_and_the_choice():
    options = EstimateOptions.robust()
    several = replace(options, refinements=3)
    once = 2 * options.partial_theta_starts * options.eval_rays + options.uncertainty_rays * options.uncertainty_patch**2
    assert several.max_rays() == 3 * (options.max_rays() - once) + 3 * estimate._CHOICE_RAYS + once
    assert replace(options, refinements=1).max_rays() == options.max_rays()
    with pytest.raises(EstimateInputError, match="options.refinements"):
        EstimateOptions(refinements=9)
    with pytest.raises(EstimateInputError, match="options.refinements"):
        EstimateOptions(refinements=-1)
    with pytest.raises(EstimateInputError, match="options.rgb_refinements"):
        EstimateOptions(rgb_refinements=9)


@pytest.mark.slow
def test_narf_estimate_takes_refinements(capsys, monkeypatch, tiny_bundle, tiny_dataset, tmp_path_factory):
    """``narf estimate --refinements N`` reaches the refiner's options; a count outside [1, 8] is one
    error line naming it."""
    from tests.test_cli_model import assert_error, estimate_argv, run, view

    seen, real = [], estimate.refine
    monkeypatch.setattr(estimate, "refine", lambda *a, options, **k: seen.append(options) or real(*a, options=options, **k))
    argv = estimate_argv(tiny_bundle, view.__wrapped__(tiny_dataset, tmp_path_factory), **{"--iterations": "1"})
    # The default preset, auto, on a view without --depth: robust, one refinement (and its polish).
    for extra, refinements in ((["--preset", "robust", "--refinements", "2"], (2, 2)), ([], (0, 0)),
                               (["--preset", "paper"], (0, 0))):
        code, _, err = run(capsys, *argv, *extra, "--json")
        assert code == 0 and (seen[-1].refinements, seen[-1].rgb_refinements) == refinements, err
        assert seen[-1].iterations == 1
    assert seen[0].theta_starts == 4  # the preset's, with the option on top
    assert_error(capsys, "estimate", [*argv, "--refinements", "0"], "--refinements")
    assert_error(capsys, "estimate", [*argv, "--refinements", "9"], "refinements")


def test_the_tracker_and_the_detector_refine_once_per_image_without_depth():
    """A tracked frame, a re-initialisation and a detector's candidate keep one refinement, unpolished, without a
    depth image or with a partly trusted mask (the robust preset's rgb_refinements and rgb_polish and
    gauss-newton's refinements are a single image's extra cost, not a frame's)."""
    from narf_core.detect import DetectOptions
    from narf_core.track import TrackOptions

    track = TrackOptions()
    for options in (track.step_options(depth=False), track.step_options(depth=True), track.reinit_options(),
                    DetectOptions(preset="robust").refine_options(), DetectOptions(preset="gauss-newton").refine_options()):
        assert options.rgb_refinements == 0 and options.refinements == 0 and options.rgb_polish == 0
        assert options.max_rays(depth=False) <= options.max_rays(depth=True)
