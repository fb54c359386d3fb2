"""The model's surface points fitted to a depth image's points (narf_core.surface_fit) and the tracker's use of
it, on the bundled clamp and frames our generator draws (pybullet)."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def clamp(bundled_clamp):
    return bundled_clamp


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Four smooth RGB-D frames of the clamp at 160x120: the dataset and its (label, observation) pairs."""
    pytest.importorskip("pybullet")
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.sequence import synthesize_sequence
    from narf_core.track_io import load_frames

    dataset = Dataset.open(synthesize_sequence("clamp", tmp_path_factory.mktemp("fit") / "clamp", 4, events=False,
                                               supersample=1))
    labels = dataset.frames()
    return dataset, list(zip(labels, load_frames(dataset, labels)))


def _off(label, shift_m=(0.004, -0.003, 0.005), turn_rad=(0.0, 0.05, 0.03), jaw_m=0.015):
    """The label's pose turned about the camera's origin and shifted, and its jaw opened by ``jaw_m``."""
    import torch

    from narf_core.geometry import so3_exp

    T = np.array(label.T_cam_obj, dtype=np.float64)
    start = T.copy()
    start[:3, :3] = so3_exp(torch.tensor(turn_rad, dtype=torch.float64)).numpy() @ T[:3, :3]
    start[:3, 3] += shift_m
    return start, {"jaw_opening": label.joints["jaw_opening"] + jaw_m}


def _errors(clamp, T, joints, label) -> tuple[float, float, float]:
    """Position (m), rotation (rad) and jaw (m) error of an estimate against the label."""
    from narf_core.estimate import local_error

    e = local_error(T, joints, np.asarray(label.T_cam_obj), label.joints, clamp)
    return float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:6])), abs(float(e[6]))


def test_the_fit_brings_pose_and_jaw_to_the_observed_points(clamp, frames) -> None:
    """From 7-8 mm, 3.3° and a jaw 15 mm too open, five iterations land within 3 mm, 2° and 6 mm on every frame,
    a single one less far: point-to-point pairs move a fraction of the way each (linear convergence), and the
    tracker's photometric iterations finish from there."""
    from narf_core.surface_fit import SurfaceFitOptions, surface_fit

    dataset, pairs = frames
    for label, observed in pairs:
        start, jaw = _off(label)
        before = _errors(clamp, start, jaw, label)
        one, five = (surface_fit(clamp, dataset.camera, start, jaw, observed.mask, observed.depth,
                                 SurfaceFitOptions(iterations=n)) for n in (1, 5))
        after_one = _errors(clamp, one.T_cam_obj, one.joints, label)
        after = _errors(clamp, five.T_cam_obj, five.joints, label)
        assert before[0] > 0.007 and before[1] > np.radians(3) and before[2] > 0.014, before
        assert after[0] < 0.003 and after[1] < np.radians(2) and after[2] < 0.006, after
        assert all(a < b for a, b in zip(after, after_one)) and all(a < b for a, b in zip(after_one, before)), (
            before, after_one, after)
        assert five.pairs >= 20 and 0 < five.rms_m < 0.03
        assert clamp.kinematics.lower[0] <= five.joints["jaw_opening"] <= clamp.kinematics.upper[0]


def test_points_far_from_the_model_do_not_move_the_fit(clamp, frames) -> None:
    """A stray blob in the mask whose depth lies 20 cm behind the tool (a segmenter's mistake on the table) is
    left out: with every observed point taken, the fit is the clean mask's to rounding."""
    from narf_core.surface_fit import SurfaceFitOptions, surface_fit

    dataset, pairs = frames
    label, observed = pairs[1]
    start, jaw = _off(label)
    options = SurfaceFitOptions(iterations=3, observed_points=10**6)
    clean = surface_fit(clamp, dataset.camera, start, jaw, observed.mask, observed.depth, options)
    mask = np.asarray(observed.mask).copy()
    depth = np.asarray(observed.depth, dtype=np.float32).copy()
    blob = np.zeros_like(mask, dtype=bool)
    blob[:12, :12] = True  # the image's corner: the clamp is in the middle of the view
    assert not (np.asarray(observed.mask) > 0.5)[blob].any()
    mask[blob] = 1
    depth[blob] = float(np.median(depth[np.asarray(observed.mask) > 0.5])) + 0.2
    stray = surface_fit(clamp, dataset.camera, start, jaw, mask, depth, options)
    np.testing.assert_allclose(stray.T_cam_obj, clean.T_cam_obj, atol=1e-9)
    assert stray.joints["jaw_opening"] == pytest.approx(clean.joints["jaw_opening"], abs=1e-9)
    assert stray.pairs == clean.pairs


def test_nothing_to_fit_leaves_the_start(clamp, frames) -> None:
    """No mask, no depth in it (holes: 0 and NaN) or no iterations: the start comes back, with no pairs."""
    from narf_core.surface_fit import SurfaceFitOptions, surface_fit

    dataset, pairs = frames
    label, observed = pairs[0]
    start, jaw = _off(label)
    depth = np.asarray(observed.depth, dtype=np.float32)
    holes = np.where(np.arange(depth.size).reshape(depth.shape) % 2 == 0, 0.0, np.nan).astype(np.float32)
    for mask, d, iterations in ((np.zeros_like(observed.mask), depth, 3), (observed.mask, holes, 3),
                                (observed.mask, depth, 0)):
        fit = surface_fit(clamp, dataset.camera, start, jaw, mask, d, SurfaceFitOptions(iterations=iterations))
        assert fit.pairs == 0 and np.isnan(fit.rms_m)
        np.testing.assert_array_equal(fit.T_cam_obj, start)
        assert fit.joints == pytest.approx(jaw)


def test_a_tracked_frame_follows_the_jaw_with_the_fit(clamp, frames) -> None:
    """One RGB-D tracker step from the true pose with the jaw a centimetre too open: with the fit (the default)
    the frame's jaw lands within 3.5 mm and nearer than without it (``surface_fit_iterations=0``), whose
    photometric iterations alone come up short."""
    from narf_core.track import TrackOptions, TrackState, step

    dataset, pairs = frames
    assert TrackOptions().surface_fit_iterations > 0
    for label, observed in (pairs[1], pairs[3]):
        errors = {}
        for iterations in (0, TrackOptions().surface_fit_iterations):
            state = TrackState.initial(clamp, np.asarray(label.T_cam_obj),
                                       {"jaw_opening": label.joints["jaw_opening"] + 0.01}, observed.time - 1 / 30,
                                       status="tracking")
            result, _ = step(clamp, dataset.camera, observed, state,
                             TrackOptions(uncertainty_rays=0, surface_fit_iterations=iterations))
            assert result.status == "tracking"
            errors[iterations] = abs(result.joints["jaw_opening"] - label.joints["jaw_opening"])
        fitted = errors[TrackOptions().surface_fit_iterations]
        assert fitted < 0.0035 and fitted < 0.6 * errors[0], errors


def test_the_fit_s_options_are_checked_and_named() -> None:
    """A bad iteration count is the option's error; ``narf bench track --surface-fit-iterations 0`` turns the fit
    off (to compare) and the table's caption says so, the default says nothing."""
    from narf_benchmarks.track import markdown
    from narf_core.cli import build_parser
    from narf_core.track import TrackInputError, TrackOptions

    for bad in (-1, 101, 2.5):
        with pytest.raises(TrackInputError, match=r"options\.surface_fit_iterations"):
            TrackOptions(surface_fit_iterations=bad)
    assert build_parser().parse_args(["bench", "track"]).surface_fit_iterations is None
    assert build_parser().parse_args(["bench", "track", "--surface-fit-iterations", "0"]).surface_fit_iterations == 0
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "track", "--surface-fit-iterations", "-1"])
    for iterations, said in ((TrackOptions().surface_fit_iterations, None), (0, "not fitted to the depth's points"),
                             (5, "fitted to the depth's points in 5 iterations")):
        options = TrackOptions(first_frame="warm", surface_fit_iterations=iterations).__dict__
        table = markdown({"frames": 3, "runs": [], "options": options})
        assert ("depth's points" in table) is (said is not None)
        assert said is None or said in table


def test_the_refiner_fits_its_starts_to_the_depth(clamp, frames) -> None:
    """``gauss-newton``'s starts with depth are fitted to the observed points (``surface_fit_iterations``): asked for
    no iterations, the refiner answers its chosen start. From a pose about a centimetre and 2.4° off and a jaw 1.5 cm
    too open, that start lies within 8 mm and 4 mm of the jaw with the fit (5.5 and 2.1 here), and without it
    further (1.5 cm, the jaw 4 cm). The rows the fit moves map back to the same poses and configurations."""
    import torch

    from narf_core.estimate import EstimateInputError, EstimateOptions, _Parameterisation, refine
    from narf_core.geometry import se3_exp

    dataset, pairs = frames
    label, observed = pairs[3]
    off = se3_exp(torch.tensor([0.006, -0.004, 0.008, 0.03, -0.02, 0.02], dtype=torch.float64)).numpy()
    start, jaw = off @ np.asarray(label.T_cam_obj), {"jaw_opening": label.joints["jaw_opening"] + 0.015}
    assert EstimateOptions.gauss_newton().surface_fit_iterations > 0 and EstimateOptions().surface_fit_iterations == 0
    errors = {}
    for iterations in (0, EstimateOptions.gauss_newton().surface_fit_iterations):
        options = EstimateOptions.gauss_newton(iterations=0, uncertainty=False, surface_fit_iterations=iterations)
        result = refine(clamp, observed.image, observed.mask, dataset.camera, start, joints_init=jaw,
                        depth=observed.depth, options=options)
        errors[iterations] = _errors(clamp, result.T_cam_obj, result.joints, label)
    fitted = errors[EstimateOptions.gauss_newton().surface_fit_iterations]
    assert fitted[0] < 0.008 and fitted[2] < 0.004, errors
    assert fitted[0] < 0.6 * errors[0][0] and fitted[2] < 0.5 * errors[0][2], errors
    param = _Parameterisation.around(torch.as_tensor(start), clamp)
    rows = torch.tensor([[0.01, -0.02, 0.03, 0.05, -0.1, 0.02, 0.3], [0.0] * 7], dtype=torch.float64)
    back = param.rows_of(param.poses(rows), param.thetas(rows))
    torch.testing.assert_close(back, rows, atol=1e-12, rtol=0)
    with pytest.raises(EstimateInputError, match=r"options\.surface_fit_iterations"):
        EstimateOptions.gauss_newton(surface_fit_iterations=-1)


def test_starts_fitted_together_land_where_each_lands_alone(clamp, frames) -> None:
    """``fit_points`` fits several starts at once (the refiner's rows): each lands where it lands fitted alone, a start
    with nothing to pair (behind the camera) comes back as it was, and the others are not held up by it."""
    import torch

    from narf_core.surface_fit import SurfaceFitOptions, fit_points, observed_points

    dataset, pairs = frames
    label, observed = pairs[2]
    options = SurfaceFitOptions(iterations=4)
    points = observed_points(dataset.camera, observed.mask, observed.depth, options.observed_points)
    starts = [_off(label), _off(label, shift_m=(-0.005, 0.002, -0.004), turn_rad=(0.03, 0.0, -0.02), jaw_m=-0.01)]
    behind = np.array(label.T_cam_obj, dtype=np.float64)
    behind[2, 3] = -1.0
    T = torch.as_tensor(np.stack([s[0] for s in starts] + [behind]))
    theta = torch.tensor([[s[1]["jaw_opening"]] for s in starts] + [[label.joints["jaw_opening"]]], dtype=torch.float64)
    together = fit_points(clamp, dataset.camera, T, theta, points, options)
    for i in range(len(starts)):
        alone = fit_points(clamp, dataset.camera, T[i:i + 1], theta[i:i + 1], points, options)
        torch.testing.assert_close(together[0][i], alone[0][0], atol=1e-9, rtol=0)
        torch.testing.assert_close(together[1][i], alone[1][0], atol=1e-9, rtol=0)
        assert int(together[2][i]) == int(alone[2][0]) >= 20
    assert int(together[2][2]) == 0 and bool(torch.isnan(together[3][2]))
    assert torch.equal(together[0][2], T[2]) and torch.equal(together[1][2], theta[2])


def test_dense_points_keep_the_fit_at_the_truth(clamp, frames) -> None:
    """Fitted from the labels, the bundle's dense points (5 mm apart) stay within 0.6 mm, 0.4° and a jaw 0.5 mm of
    them; its 500 points a link (the bar's about 7 mm apart) pair each observed point with a surface point up to
    half that spacing off, and move the pose further on every frame."""
    import dataclasses

    from narf_core.surface_fit import SurfaceFitOptions, surface_fit

    dataset, pairs = frames
    sparse = dataclasses.replace(clamp, dense_points={})
    assert len(clamp.dense_points["bar"]) > 4 * len(clamp.sample_points["bar"])
    for label, observed in pairs:
        errors = {}
        for name, model in (("dense", clamp), ("sparse", sparse)):
            fit = surface_fit(model, dataset.camera, np.asarray(label.T_cam_obj), label.joints, observed.mask,
                              observed.depth, SurfaceFitOptions(iterations=10))
            errors[name] = _errors(clamp, fit.T_cam_obj, fit.joints, label)
        position, rotation, jaw = errors["dense"]
        assert position < 0.0006 and rotation < np.radians(0.4) and jaw < 0.0005, errors
        assert position < errors["sparse"][0], errors


def test_the_refiner_fits_its_final_estimate_to_the_depth_where_it_trusts_the_mask(clamp, frames) -> None:
    """``gauss-newton`` with depth fits its final estimate too (``surface_polish_iterations``): from a pose a
    centimetre and 2.4° off and a jaw 1.5 cm too open, the polished estimate lies nearer the label in position,
    rotation and jaw than the same refinement unpolished (here 0.9 mm, 0.5° and 1.6 mm), within 0.5 mm and a jaw
    0.8 mm (here 0.17 mm, 0.27° and 0.54 mm). Where the mask is trusted partially (a
    segmenter's or an occluder's mask) the estimate is left as refined, and asked for no iterations the refiner
    still answers its start."""
    import torch

    from narf_core.estimate import EstimateInputError, EstimateOptions, refine
    from narf_core.geometry import se3_exp

    dataset, pairs = frames
    label, observed = pairs[0]
    off = se3_exp(torch.tensor([0.006, -0.004, 0.008, 0.03, -0.02, 0.02], dtype=torch.float64)).numpy()
    start, jaw = off @ np.asarray(label.T_cam_obj), {"jaw_opening": label.joints["jaw_opening"] + 0.015}
    polish = EstimateOptions.gauss_newton().surface_polish_iterations
    assert polish > 0 and EstimateOptions().surface_polish_iterations == 0

    def estimate(**options):
        result = refine(clamp, observed.image, observed.mask, dataset.camera, start, joints_init=jaw,
                        depth=observed.depth, options=EstimateOptions.gauss_newton(uncertainty=False, **options))
        return result, _errors(clamp, result.T_cam_obj, result.joints, label)

    (plain, unpolished), (polished, errors) = estimate(surface_polish_iterations=0), estimate()
    assert errors[0] < 0.0005 and errors[2] < 0.0008, (errors, unpolished)
    assert all(e < u for e, u in zip(errors, unpolished)), (errors, unpolished)
    assert np.isfinite(polished.loss) and polished.status == plain.status
    partial = [estimate(mask_trust="partial", surface_polish_iterations=n)[0] for n in (0, polish)]
    assert np.array_equal(partial[0].T_cam_obj, partial[1].T_cam_obj) and partial[0].joints == partial[1].joints
    asked = [estimate(iterations=0, surface_polish_iterations=n)[0] for n in (0, polish)]
    assert np.array_equal(asked[0].T_cam_obj, asked[1].T_cam_obj)
    with pytest.raises(EstimateInputError, match=r"options\.surface_polish_iterations"):
        EstimateOptions.gauss_newton(surface_polish_iterations=101)
