"""Training: the pipeline's bundle sees the object where the labels are, runs resume where they
stopped, and the pieces (composition, union occupancy, loss, resumable stages) are exact."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
import torch
from torch import nn

pytest.register_assert_rewrite("conftest_model")
pytest_plugins = ("conftest_model",)

from conftest_model import tiny_config  # noqa: E402
from narf_core.bundle import load_bundle  # noqa: E402
from narf_core.data.dataset import Dataset  # noqa: E402
from narf_core.fields.composed import ComposedField, union_occupancy  # noqa: E402
from narf_core.geometry import Rays, transform_points  # noqa: E402
from narf_core.kinematics import KinematicTree  # noqa: E402
from narf_core.render import OccupancyGrid, RenderOutput, ray_aabb  # noqa: E402
from narf_core.train import pipeline  # noqa: E402
from narf_core.train.distill import random_views, rays_through_box  # noqa: E402
from narf_core.train.loop import run_stage  # noqa: E402
from narf_core.train.parts import RayTargets, part_boxes, part_rays, surface_incidence  # noqa: E402
from narf_core.train.pipeline import TrainConfig, TrainError, TrainInputError, ray_loss, train  # noqa: E402

# ---------------------------------------------------------------------------------------------
# The trained tiny model


def mask_iou(model, dataset: Dataset, split: str, mode: str) -> tuple[float, float]:
    """Mean IoU of ``opacity > 0.5`` with the labelled mask over ``split``; mean opacity off the mask."""
    ious, outside = [], []
    for frame in dataset.frames(split):
        labels = dataset.load(frame).labels > 0
        T = torch.as_tensor(frame.T_cam_obj, dtype=torch.float32)
        opacity = model.render(T, model.joint_vector(frame.joints), dataset.camera, outputs=("opacity",), mode=mode)
        seen = opacity["opacity"].numpy() > 0.5
        ious.append((seen & labels).sum() / (seen | labels).sum())
        outside.append(float(opacity["opacity"].numpy()[~labels].mean()))
    return float(np.mean(ious)), float(np.mean(outside))


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["narf", "parts"])
@pytest.mark.parametrize("split", ["test", "novel"])
def test_the_trained_model_is_opaque_where_the_labels_are(tiny_model, tiny_dataset, mode, split):
    """30 steps per stage on 8 images of 48x36: the objects cover 4 to 20 pixels, and the renders
    at unseen views (test) and configurations (novel) overlap them with a mean IoU of 0.44-0.71
    (measured; 15 steps per stage give 0.0-0.05, an untrained field 0)."""
    iou, outside = mask_iou(tiny_model, Dataset.open(tiny_dataset), split, mode)
    assert iou > 0.35
    assert outside < 0.02  # and the background stays (nearly) empty


@pytest.mark.slow
def test_the_bundle_records_what_was_trained(tiny_bundle):
    model = load_bundle(tiny_bundle)
    provenance = model.metadata["provenance"]
    assert provenance["config"] == json_config(tiny_config())
    timings = provenance["timings_s"]
    assert set(timings) == {"part0_s", "part1_s", "distill_s"} and all(t > 0 for t in timings.values())
    assert model.has_parts and len(model.part_fields) == 2
    assert model.grid.resolution[0] == 32  # grid_resolution along the longest axis
    assert not (tiny_bundle.parent / f"{tiny_bundle.name}.work").exists()  # removed once the bundle exists


@pytest.mark.slow
def test_training_fits_the_trackers_own_factor_on_sequences_of_its_object(tiny_dataset, tmp_path, monkeypatch):
    """With ``track_sequences`` N, training tracks N smooth sequences of the dataset's object (seeds 1..N) at
    its camera and at one 4x finer, and stores per modality the smallest factor whose 95 % regions hold 95 %
    of the frames' errors, which the tracker then applies (between the two cameras on the power that joins
    them); a dataset that does not name its object keeps the pooled factor."""
    import json
    import shutil

    from narf_core.geometry import Pinhole
    from narf_core.estimate import JACOBIANS
    from narf_core.track import (DIFFERENCES_GAIN, FEWER_RAYS, FEWER_RAYS_LOSS, SIGMA_SCALE, TRACK_HELD, WIDE_HUBER,
                                 WIDE_HUBER_GAIN, TrackOptions, sigma_scale)
    from narf_core.train import track_sigma
    from narf_core.train.track_sigma import calibrate_tracker, dataset_tool, fine_size, fit_track_scale, track_nees

    pooled = []  # per fit, whether its tracks ran in processes of their own

    class Tracks(track_sigma._Tracks):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            pooled.append(self.pool is not None)

    monkeypatch.setattr(track_sigma, "_Tracks", Tracks)
    monkeypatch.setattr(pipeline, "free_cores", lambda *a, **k: 2)  # two cores free when the fit starts
    config = tiny_config(part_steps=40, distill_steps=40, field="articulated", track_sequences=1)
    model = load_bundle(train(tiny_dataset, tmp_path / "m.narf", config, progress=False))
    assert pooled == [True]
    fitted = model.metadata["uncertainty"]["track"]
    camera = Dataset.open(tiny_dataset).camera
    assert fine_size((48, 36)) == (192, 144) and fine_size((160, 120)) == (640, 480) and fine_size((640, 480)) is None
    assert fitted["seeds"] == [1] and fitted["fx"] == float(camera.K[0, 0])
    assert fitted["fine"]["fx"] == pytest.approx(4 * float(camera.K[0, 0]))
    for fit in (fitted, fitted["fine"]):
        assert fit["rgbd_frames"] > 30 and fit["rgb_frames"] > 30  # most of the 60 frames held
    assert fitted["solvers"] == {"rgbd": TrackOptions().solver_for(True), "rgb": TrackOptions().solver_for(False)}
    # without depth, the Jacobian whose frames came out nearer (the differences only by DIFFERENCES_GAIN)
    means = fitted["rgb_add_m"]
    assert set(means) == set(JACOBIANS) and all(0 < m < math.inf for m in means.values())
    assert fitted["jacobians"] == {"rgbd": TrackOptions().jacobian, "rgb": "differences" if means["differences"]
                                   < DIFFERENCES_GAIN * means["derivatives"] else "derivatives"}
    assert TrackOptions().jacobian_for(False, model) == fitted["jacobians"]["rgb"]
    # with depth, the fewer rays where their frames came out within FEWER_RAYS_LOSS of the solver's own budget's,
    # those held within TRACK_HELD of the diameter
    budget, means = TrackOptions().rays_for(True), fitted["rgbd_add_m"]
    assert set(means) == {str(budget), str(FEWER_RAYS)} and all(0 < m < math.inf for m in means.values())
    fewer = (means[str(FEWER_RAYS)] <= FEWER_RAYS_LOSS * means[str(budget)]
             and means[str(budget)] <= TRACK_HELD * model.diameter)
    assert fitted["rays"] == {"rgbd": FEWER_RAYS if fewer else budget}
    assert TrackOptions().rays_for(True, "cpu", model) == fitted["rays"]["rgbd"]
    # and on the rays kept, where their tracks do not hold within TRACK_HELD of the diameter, the wider Huber scale
    # too, kept where its frames came out below WIDE_HUBER_GAIN of the preset's
    preset, tried = TrackOptions().step_options(True).robust_scale, fitted.get("rgbd_huber_add_m")
    assert (tried is not None) == (means[str(fitted["rays"]["rgbd"])] > TRACK_HELD * model.diameter)
    wide = tried is not None and tried[str(WIDE_HUBER)] < WIDE_HUBER_GAIN * tried[str(preset)]
    assert fitted["robust_scale"] == {"rgbd": WIDE_HUBER if wide else preset}
    assert TrackOptions().step_options(True, "cpu", model).robust_scale == fitted["robust_scale"]["rgbd"]
    assert "track_sigma_s" in model.metadata["provenance"]["timings_s"]
    assert not (tmp_path / "m.narf.work").exists()
    # The factor is the fit of the frames' NEES on the same sequence (drawn again: the same frames), its tracks
    # here in this process where training's ran in two of their own: the same fit to the digit.
    again = calibrate_tracker(model, dataset_tool(Dataset.open(tiny_dataset)), (48, 36), tmp_path / "again", [1])
    assert pooled == [True, False]
    nees = track_nees(model, Dataset.open(tmp_path / "again" / "sequence-48x36-60-s1"), rgb_only=False,
                      rays=fitted["rays"]["rgbd"], huber=fitted["robust_scale"]["rgbd"])
    assert again == fitted and fitted["rgbd"] == fit_track_scale(nees, 7) and len(nees) == fitted["rgbd_frames"]
    for depth, key in ((True, "rgbd"), (False, "rgb")):
        assert sigma_scale(model, TrackOptions(), depth) == fitted[key]
        assert sigma_scale(model, TrackOptions(), depth, camera) == pytest.approx(fitted[key])
        finer = Pinhole(camera.K * torch.tensor([[4.0], [4.0], [1.0]]), 192, 144)
        assert sigma_scale(model, TrackOptions(), depth, finer) == pytest.approx(fitted["fine"][key])
        twice = Pinhole(camera.K * torch.tensor([[2.0], [2.0], [1.0]]), 96, 72)  # between: the geometric mean
        assert sigma_scale(model, TrackOptions(), depth, twice) == pytest.approx(
            math.sqrt(fitted[key] * fitted["fine"][key]))
    # A dataset that does not say which object drew it: no sequences, the pooled factor.
    shutil.copytree(tiny_dataset, tmp_path / "unnamed")
    scene = json.loads((tmp_path / "unnamed" / "scene.json").read_text())
    scene["generator"] = {}
    (tmp_path / "unnamed" / "scene.json").write_text(json.dumps(scene))
    assert dataset_tool(Dataset.open(tmp_path / "unnamed")) is None
    bare = load_bundle(train(tmp_path / "unnamed", tmp_path / "bare.narf", dataclasses.replace(config, part_steps=5,
                                                                                                distill_steps=5)))
    assert "uncertainty" not in bare.metadata
    assert sigma_scale(bare, TrackOptions(), True) == SIGMA_SCALE[TrackOptions().solver_for(True)]["rgbd"]


@pytest.mark.parametrize("fewer_add, diameter, chosen", [(0.0011, 0.2, 512), (0.0012, 0.2, 768), (0.0011, 0.05, 768)])
def test_the_fit_takes_fewer_rays_with_depth_only_where_their_frames_come_out_as_near(tiny_dataset, fewer_add, diameter,
                                                                                       chosen):
    """With depth the fit tracks its sequences at the views' camera on the solver's own rays and on FEWER_RAYS, keeps
    the fewer where their frames' mean ADD stays within FEWER_RAYS_LOSS of the others' (1.1 mm against 1 mm: yes,
    1.2: no) and those hold within TRACK_HELD of the diameter (1 mm of 20 cm: yes, of 5 cm: no), fits every
    RGB-D factor on tracks of the rays it kept (the finer camera's on those alone) and records
    both means; without depth the solver's own."""
    from concurrent.futures import Future

    from narf_core.track import FEWER_RAYS, FEWER_RAYS_LOSS, TRACK_HELD, WIDE_HUBER, TrackOptions
    from narf_core.train.track_sigma import fit_track_scale, track_calibration

    budget, jacobian = TrackOptions().rays_for(True), TrackOptions().jacobian
    assert (budget, FEWER_RAYS, FEWER_RAYS_LOSS, TRACK_HELD) == (768, 512, 1.15, 0.01)
    calls = []

    class Tracks:  # a track's NEES say which rays it ran on: 1 on the solver's own, 4 on the fewer
        model = type("Model", (), {"joints": [object()], "diameter": diameter})()

        def submit(self, folder, rgb_only, jacobian, rays=0, huber=0.0):
            calls.append((rgb_only, jacobian, rays, huber))
            done = Future()
            add = fewer_add if not rgb_only and rays == FEWER_RAYS else 0.001
            done.set_result(([4.0 if rays == FEWER_RAYS else 1.0] * 10, [add] * 10))
            return done

    two = [tiny_dataset, tiny_dataset]  # two sequences (one folder twice) at each camera
    fit = track_calibration(Tracks(), {"": two, "fine": two})
    assert fit["rays"] == {"rgbd": chosen}
    assert fit["rgbd_add_m"] == {"768": pytest.approx(0.001), "512": pytest.approx(fewer_add)}
    assert fit["rgbd"] == fit["fine"]["rgbd"] == fit_track_scale([4.0 if chosen == FEWER_RAYS else 1.0] * 20, 7)
    rgbd = [c for c in calls if not c[0]]
    # both on the views' camera's sequences, asked before anything waits; where the solver's own do not hold (1 mm of
    # 5 cm) the wider Huber scale on them (no better here: not kept); then the finer camera's on the rays kept
    wide = [(False, jacobian, budget, WIDE_HUBER)] * 2 if diameter * TRACK_HELD < 0.001 else []
    assert rgbd == ([(False, jacobian, budget, 0.0)] * 2 + [(False, jacobian, FEWER_RAYS, 0.0)] * 2 + wide
                    + [(False, jacobian, chosen, 0.0)] * 2)
    assert fit["robust_scale"] == {"rgbd": TrackOptions().step_options(True).robust_scale}
    assert all(c[2] == 0 for c in calls if c[0])  # without depth: the solver's own
    calls.clear()  # a fit without depth tracks nothing with depth and records no rays
    assert "rays" not in track_calibration(Tracks(), {"": two}, modalities=("rgb",)) and all(c[0] for c in calls)


@pytest.mark.parametrize("kept_add, wide_add, diameter, chosen", [
    (0.004, 0.003, 0.2, 0.3),  # 2 % of the diameter: tried, and 0.75 of the preset's: kept
    (0.004, 0.0036, 0.2, 0.1),  # tried, 0.9 of the preset's: not kept
    (0.001, 0.0005, 0.2, 0.1),  # 0.5 % of the diameter: the track holds, not tried
])
def test_the_fit_takes_the_wider_huber_scale_with_depth_only_where_the_track_wanders_and_it_pays(
        tiny_dataset, kept_add, wide_add, diameter, chosen):
    """With depth, where the tracks on the rays kept do not hold within TRACK_HELD of the diameter, the fit tracks the
    views' camera's sequences once more at WIDE_HUBER, keeps it where their frames' mean ADD comes out below
    WIDE_HUBER_GAIN of the preset's, fits every RGB-D factor on tracks at the scale it kept (the finer camera's on
    those alone) and records both means; where the tracks hold it tracks nothing more and records the preset's."""
    from concurrent.futures import Future

    from narf_core.track import TRACK_HELD, WIDE_HUBER, WIDE_HUBER_GAIN, TrackOptions
    from narf_core.train.track_sigma import fit_track_scale, track_calibration

    budget, jacobian = TrackOptions().rays_for(True), TrackOptions().jacobian
    preset = TrackOptions().step_options(True).robust_scale
    assert (WIDE_HUBER, WIDE_HUBER_GAIN, preset) == (0.3, 0.85, 0.1)
    calls = []

    class Tracks:  # the fewer rays come out far worse (never kept); a track's NEES say its Huber scale: 9 at the wide
        model = type("Model", (), {"joints": [object()], "diameter": diameter})()

        def submit(self, folder, rgb_only, jacobian, rays=0, huber=0.0):
            calls.append((rgb_only, rays, huber))
            done = Future()
            add = 0.001 if rgb_only else kept_add * (10 if rays != budget else 1) if not huber else wide_add
            done.set_result(([9.0 if huber else 1.0] * 10, [add] * 10))
            return done

    two = [tiny_dataset, tiny_dataset]  # two sequences (one folder twice) at each camera
    fit = track_calibration(Tracks(), {"": two, "fine": two})
    assert fit["rays"] == {"rgbd": budget} and fit["robust_scale"] == {"rgbd": chosen}
    tried = kept_add > TRACK_HELD * diameter
    assert fit.get("rgbd_huber_add_m") == ({"0.1": pytest.approx(kept_add), "0.3": pytest.approx(wide_add)} if tried
                                           else None)
    assert fit["rgbd"] == fit["fine"]["rgbd"] == fit_track_scale([9.0 if chosen == WIDE_HUBER else 1.0] * 20, 7)
    wide = [(False, budget, WIDE_HUBER)] * 2 if tried else []
    finer = [(False, budget, WIDE_HUBER if chosen == WIDE_HUBER else 0.0)] * 2
    # after the two budgets' on the views' camera: the wide scale's there where tried, then the finer camera's
    assert [c for c in calls if not c[0]][4:] == wide + finer
    assert all(c[2] == 0.0 for c in calls if c[0])  # without depth: the preset's


def test_the_fits_sequences_drawn_ahead_in_their_own_process_are_the_ones_the_fit_draws(tmp_path, monkeypatch):
    """Where a core is free beside the training's threads, the sequences the tracker's factor is fitted on
    (the object's camera and the 4x finer one) are drawn in a process of their own, file for file as the fit
    would draw them; where none is, nothing is started and the fit draws them itself."""
    pytest.importorskip("pybullet")
    from narf_core.train import track_sigma

    monkeypatch.setattr("narf_core.threads.free_cores", lambda *a, **k: torch.get_num_threads() + 1)
    drawing = track_sigma.draw_ahead("clamp", (32, 24), tmp_path / "ahead", [1, 2], frames=3)
    assert drawing is not None and drawing.daemon
    drawing.join(timeout=300)
    assert drawing.exitcode == 0
    here = [f for size in ((32, 24), (128, 96)) for f in track_sigma.sequence_folders("clamp", size, tmp_path / "here",
                                                                                       [1, 2], frames=3)]
    assert len(here) == 4
    for folder in here:
        files = sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file())
        assert len(files) > 3 * 3
        for name in files:
            assert (tmp_path / "ahead" / folder.name / name).read_bytes() == (folder / name).read_bytes(), name
    monkeypatch.setattr("narf_core.threads.free_cores", lambda *a, **k: torch.get_num_threads())
    assert track_sigma.draw_ahead("clamp", (32, 24), tmp_path / "none", [1], frames=3) is None
    assert not (tmp_path / "none").exists()


@pytest.mark.slow
def test_the_articulated_field_is_trained_without_distillation_and_renders_like_the_parts(tiny_dataset, tmp_path):
    """``field="articulated"``: stage 2 copies the part fields into the configuration field (no
    distillation step runs), the bundle loads it back, and narf mode renders what parts mode renders."""
    config = tiny_config(field="articulated", part_steps=15)
    model = load_bundle(train(tiny_dataset, tmp_path / "articulated.narf", config, progress=False))
    assert model.field.config()["arch"] == "articulated" and model.metadata["field"]["arch"] == "articulated"
    assert set(model.metadata["provenance"]["timings_s"]) == {"part0_s", "part1_s", "articulated_s"}
    dataset = Dataset.open(tiny_dataset)
    for frame in dataset.frames("novel")[:3]:
        T, theta = torch.as_tensor(frame.T_cam_obj, dtype=torch.float32), model.joint_vector(frame.joints)
        narf, parts = (model.render(T, theta, dataset.camera, outputs=("rgb", "opacity"), mode=m) for m in ("narf", "parts"))
        torch.testing.assert_close(narf["rgb"], parts["rgb"], rtol=0, atol=2e-3)
        torch.testing.assert_close(narf["opacity"], parts["opacity"], rtol=0, atol=2e-3)


def test_an_unknown_configuration_field_is_refused_before_training():
    with pytest.raises(TrainError, match="options.field must be one of articulated, distilled, got 'nerf'"):
        tiny_config(field="nerf")


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("arch", "nerf", "must be one of kplanes, fastnerf"),
        ("part_steps", 0, "must be >= 1"),
        ("batch_rays", 2.5, "must be an integer"),
        ("lr", 0.0, "must be > 0"),
        ("grid_resolution", 1, "must be >= 2"),
        ("composites", -1, "must be >= 0"),
        ("free_space_weight", -1.0, "must be >= 0"),
        ("free_space_weight", float("nan"), "must be finite"),
        ("sparsity_weight", -0.1, "must be >= 0"),
        ("sparsity_points", 0, "must be >= 1"),
        ("exclusion_weight", -1.0, "must be >= 0"),
        ("exclusion_points", 0, "must be >= 1"),
        ("depth_weight", True, "must be a number"),
        ("distance", (1.0, 0.4), "must be (near, far) metres with 0 < near <= far"),
        ("distance", (0.4,), "must be (near, far)"),
        ("budget_s", -5.0, "must be None (no cap) or a finite number of seconds >= 0"),
        ("budget_s", float("inf"), "must be None"),
        ("keep_parts", 1, "must be true or false"),
        ("track_sequences", 17, "must be in [0, 16]"),
        ("track_sequences", -1, "must be in [0, 16]"),
    ],
)
def test_a_bad_training_setting_is_one_error_naming_its_field(field, value, reason):
    with pytest.raises(TrainInputError) as info:
        TrainConfig(**{field: value})
    assert info.value.field == f"options.{field}"
    assert str(info.value).startswith(f"options.{field} {reason}") and repr(value) in str(info.value)
    with pytest.raises(TrainInputError, match=f"options.{field}"):  # replace() checks again
        dataclasses.replace(TrainConfig(), **{field: value})


def test_the_cli_maps_a_bad_training_setting_to_one_line_naming_the_flag(tmp_path, capsys):
    from narf_core.cli import main

    assert main(["train", str(tmp_path / "data"), "--out", str(tmp_path / "x.narf"), "--free-space-weight", "-1"]) == 2
    err = capsys.readouterr().err
    assert err == "narf train: error: --free-space-weight must be >= 0, got -1.0\n"
    assert not (tmp_path / "x.narf.work").exists()  # refused before any work


def json_config(config: TrainConfig) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(config).items()}


# ---------------------------------------------------------------------------------------------
# Resume


@pytest.mark.slow
def test_an_interrupted_run_resumes_without_redoing_finished_parts(tiny_dataset, tmp_path, monkeypatch):
    config = tiny_config(part_steps=5, distill_steps=5)
    out = tmp_path / "m.narf"
    work = tmp_path / "m.narf.work"

    real_composite, calls = pipeline.composite_rays, {"distill": 0, "parts": 0}

    def interrupted_on_third_step(*args, **kwargs):
        calls["distill"] += 1
        if calls["distill"] == 3:
            raise KeyboardInterrupt
        return real_composite(*args, **kwargs)

    monkeypatch.setattr(pipeline, "composite_rays", interrupted_on_third_step)
    with pytest.raises(KeyboardInterrupt):
        train(tiny_dataset, out, config, progress=False)
    assert not out.exists()
    assert {"run.json", "part0.pt", "part1.pt", "union_grid.pt"} <= {p.name for p in work.iterdir()}
    finished = [torch.load(work / f"part{p}.pt", weights_only=True) for p in (0, 1)]
    union = torch.load(work / "union_grid.pt", weights_only=True)["grid"]

    with pytest.raises(TrainError, match="other settings") as info:  # a different run must not reuse the work
        train(tiny_dataset, out, dataclasses.replace(config, seed=1), progress=False)
    assert str(work) in str(info.value)

    real_train_part = pipeline._train_part

    def counted_train_part(*args, **kwargs):
        calls["parts"] += 1
        return real_train_part(*args, **kwargs)

    monkeypatch.setattr(pipeline, "composite_rays", real_composite)
    monkeypatch.setattr(pipeline, "_train_part", counted_train_part)
    monkeypatch.setattr(pipeline, "part_rays", lambda *a: pytest.fail("finished parts need no training rays"))
    resumed = train(tiny_dataset, out, dataclasses.replace(config, budget_s=600.0), progress=False)  # budget may change

    assert calls["parts"] == 0
    assert not work.exists()
    model = load_bundle(resumed)
    for part, saved in zip(model.part_fields, finished):
        assert all(torch.equal(v, saved["field"][k]) for k, v in part.state_dict().items())
    assert torch.equal(model.grid.occupancy, union.bool())
    assert model.metadata["provenance"]["timings_s"]["part0_s"] == pytest.approx(float(finished[0]["seconds"]))


def test_a_stage_resumes_from_its_checkpoint_to_the_same_weights(tmp_path):
    """Interrupted after 4 of 10 Adam steps and resumed, a stage ends with the uninterrupted weights."""

    def stage(checkpoint, stop_at=None, log=None):
        torch.manual_seed(0)
        module = nn.Linear(3, 1)
        optimizer = torch.optim.Adam(module.parameters(), lr=0.1)
        x, y = torch.linspace(-1, 1, 12).reshape(4, 3), torch.tensor([[1.0], [0.0], [2.0], [-1.0]])

        def step_fn(i):
            if i == stop_at:
                raise KeyboardInterrupt
            if log is not None:
                log.append(i)
            loss = ((module(x) - y) ** 2).mean() + 1e-3 * torch.randn(()).abs()  # uses the saved random state
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            return loss.item()

        result = run_stage("s", module, optimizer, step_fn, steps=10, budget_s=None, checkpoint=checkpoint,
                           checkpoint_every_s=0.0, progress=False)
        return module, result

    reference, _ = stage(tmp_path / "a.ckpt")
    with pytest.raises(KeyboardInterrupt):
        stage(tmp_path / "b.ckpt", stop_at=4)
    log: list[int] = []
    resumed, result = stage(tmp_path / "b.ckpt", log=log)
    assert log == [4, 5, 6, 7, 8, 9] and result.steps == 10
    assert torch.equal(resumed.weight, reference.weight) and torch.equal(resumed.bias, reference.bias)
    again, result = stage(tmp_path / "b.ckpt", log=log)  # finished: nothing is redone
    assert log == [4, 5, 6, 7, 8, 9] and result.steps == 10 and torch.equal(again.weight, reference.weight)


def test_stage_one_rebuilds_the_grid_early_in_the_warm_up_then_every_200_steps():
    def rebuilt(steps: int) -> list[int]:
        return [i for i in range(1, steps + 1) if pipeline.refreshes_grid(i, steps)]

    assert rebuilt(800) == [50, 100, 150, 200, 400, 600]  # not at 800: the final grid is built after the stage
    assert rebuilt(400) == [50, 100, 300]
    assert rebuilt(30) == [7]  # a warm-up shorter than the early interval: one rebuild, where it ends


def test_a_zero_budget_runs_no_step(tmp_path):
    module = nn.Linear(1, 1)
    result = run_stage("s", module, torch.optim.SGD(module.parameters(), lr=1.0), lambda i: pytest.fail("stepped"),
                       steps=5, budget_s=0.0, checkpoint=tmp_path / "c.ckpt", progress=False)
    assert result.steps == 0 and math.isnan(result.loss)


# ---------------------------------------------------------------------------------------------
# Union occupancy and the configuration samples it is built from


@pytest.mark.slow
def test_union_occupancy_holds_every_part_at_random_configurations(tiny_model):
    """Points anywhere in any occupied part cell, moved by FK at configurations between the samples,
    land in occupied cells of the model's grid at that configuration (where inside the object's box)."""
    kin = tiny_model.kinematics
    grids, aabb = tiny_model.part_grids, tiny_model.aabb
    union = tiny_model.grid
    generator = torch.Generator().manual_seed(0)
    theta = kin.lower + (kin.upper - kin.lower) * torch.rand(64, 1, generator=generator, dtype=torch.float64)
    T_obj_part = kin.part_poses(theta).float()
    checked = 0
    for p, grid in enumerate(grids):
        cells = grid.occupancy.nonzero().float()
        assert len(cells) > 0
        points = grid.aabb[0] + (cells[:, None] + torch.rand(len(cells), 4, 3, generator=generator)) * grid.cell_size
        for T, th in zip(T_obj_part[:, p], theta.float()):
            x = transform_points(T, points.reshape(-1, 3))
            x = x[((x >= aabb[0]) & (x <= aabb[1])).all(-1)]
            assert bool(union.occupied(x, th).all())
            checked += len(x)
    assert checked > 100_000
    # and it is not simply the whole box (4 cells thick at this resolution, so the one-cell
    # dilation fills most of it)
    assert union.fraction < 0.9


def slide_x(theta: torch.Tensor) -> torch.Tensor:
    """Forward kinematics of one part slid by ``θ [..., 1]`` along x: ``T_obj_part [..., 1, 4, 4]``."""
    T = torch.eye(4, dtype=theta.dtype).expand(*theta.shape[:-1], 1, 4, 4).clone()
    T[..., 0, 0, 3] = theta[..., 0]
    return T


def one_cell_part() -> OccupancyGrid:
    """Cell (1, 1, 1) of a 4^3 grid over the unit cube: [0.25, 0.5]^3."""
    part = torch.zeros(4, 4, 4, dtype=torch.bool)
    part[1, 1, 1] = True
    return OccupancyGrid(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), part)


def dilated(x_cells: slice) -> torch.Tensor:
    splat = torch.zeros(4, 4, 4, dtype=torch.bool)
    splat[x_cells, 1:3, 1:3] = True
    return torch.nn.functional.max_pool3d(splat[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0


def test_union_occupancy_of_one_cell_moved_by_hand():
    """The cell at θ = 0 and θ = 0.25 (one cell along x): its centre and corners fall in object
    cells 1-2 (y, z) and 1-3 (x); the union is those, dilated by one cell."""
    aabb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    grid = union_occupancy([one_cell_part()], slide_x, torch.tensor([0.0]), torch.tensor([0.25]), aabb, 4,
                           bins=1, samples_per_bin=2)
    assert grid.occupancy.shape == (1, 4, 4, 4)
    assert torch.equal(grid.occupancy[0], dilated(slice(1, 4)))


def test_union_occupancy_per_configuration_bin():
    """Two bins over θ in [0, 0.5]: the cell at 0 and 0.25 (bin 0), at 0.25 and 0.5 (bin 1, where
    its far corners leave the box); a renderer at θ sees only its bin's cells."""
    aabb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    grid = union_occupancy([one_cell_part()], slide_x, torch.tensor([0.0]), torch.tensor([0.5]), aabb, 4,
                           bins=2, samples_per_bin=2)
    assert torch.equal(grid.occupancy[0], dilated(slice(1, 4)))
    assert torch.equal(grid.occupancy[1], dilated(slice(2, 4)))
    near_origin = torch.tensor([[0.1, 0.375, 0.375]])  # object cell (0, 1, 1)
    assert grid.occupied(near_origin, torch.tensor([0.1])).item()
    assert not grid.occupied(near_origin, torch.tensor([0.4])).item()
    assert grid.occupied(near_origin).item()  # the union over the bins


def test_union_occupancy_ignores_cells_moved_out_of_the_box():
    aabb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    part_grid = OccupancyGrid(aabb.clone(), torch.ones(2, 2, 2, dtype=torch.bool))
    far = union_occupancy([part_grid], slide_x, torch.tensor([5.0]), torch.tensor([6.0]), aabb, 8)
    assert not far.occupancy.any()


def test_the_cells_a_moved_box_touches_are_those_between_its_ends_in_every_grid_of_a_stack():
    """Boxes (some reaching three cells along an axis, some leaving the grid) under three poses, each pose's
    cells offset by its grid's start in a stack: the flat indices are every cell, cell by cell, that a box
    overlaps and the grid holds, in its pose's grid."""
    from narf_core.fields.composed import _touched_cells

    gen = torch.Generator().manual_seed(0)
    cells, origin, size = (5, 4, 6), torch.tensor([0.0, -1.0, 0.5]), torch.tensor([0.5, 0.25, 0.2])
    centres = origin - 0.4 + torch.rand(3, 40, 3, generator=gen) * (torch.tensor(cells) * size + 0.8)
    half = torch.tensor([[0.2, 0.1, 0.05], [0.6, 0.2, 0.15], [0.1, 0.3, 0.25]])  # in cells: up to 1.5 across
    base = torch.tensor([0, 120, 360])
    got = _touched_cells(centres, half, origin, size, cells, 0.0, base)
    expected = set()
    for c in range(3):
        for i, j, k in itertools.product(*(range(n) for n in cells)):
            lo = origin + torch.tensor([i, j, k]) * size
            if bool(((centres[c] - half[c] < lo + size) & (centres[c] + half[c] >= lo)).all(-1).any()):
                expected.add(int(base[c]) + (i * cells[1] + j) * cells[2] + k)
    assert len(expected) > 50 and sorted(set(got.tolist())) == sorted(expected)
    assert bool((((centres[1] + half[1] - origin) / size).floor() - ((centres[1] - half[1] - origin) / size).floor()
                 >= 2).any())  # boxes spanning three cells along an axis are among them


@pytest.mark.slow
def test_configuration_samples_move_no_part_more_than_a_cell(tiny_dataset):
    kin = KinematicTree.from_urdf(Dataset.open(tiny_dataset).urdf_path)
    boxes = part_boxes(kin)
    for cell in (0.02, 0.005, 0.001):
        theta = pipeline._theta_samples(kin, boxes, cell)
        assert theta[0, 0] == kin.lower[0] and theta[-1, 0] == kin.upper[0]  # limits included
        assert bool((theta[1:, 0] > theta[:-1, 0]).all())
        T = kin.part_poses(theta)
        for p, box in enumerate(boxes):
            corners = torch.cartesian_prod(*box.T.double())  # the 8 corners [8, 3]
            x = transform_points(T[:, p, None], corners[None])  # [m, 8, 3]
            move = float((x[1:] - x[:-1]).norm(dim=-1).max())
            assert move <= cell
        coarser = pipeline._theta_samples(kin, boxes, 2 * cell)
        assert len(coarser) < len(theta)  # no more samples than needed (each halving doubles them)
    assert len(pipeline._theta_samples(kin, boxes, 1e-9, max_total=100)) == 100  # capped: as many as fit


# ---------------------------------------------------------------------------------------------
# The composed field


class BoxField(nn.Module):
    """Density ``a + b * x[0]`` and one colour inside ``aabb`` (the composition only asks inside)."""

    def __init__(self, aabb, a: float, b: float, colour) -> None:
        super().__init__()
        self.aabb = torch.as_tensor(aabb, dtype=torch.float32)
        self.a, self.b, self.colour = a, b, torch.tensor(colour)

    def forward(self, x, d, theta):
        assert theta is None
        return self.a + self.b * x[:, 0], self.colour.to(x.dtype).expand(len(x), 3)


def two_boxes():
    """Part 0 fixed on [0,1]^3 (density 2, red); part 1 on [0,1]^3 slid by θ along x (density 3 + x, blue)."""
    unit = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]
    fields = [BoxField(unit, 2.0, 0.0, [1.0, 0.0, 0.0]), BoxField(unit, 3.0, 1.0, [0.0, 0.0, 1.0])]

    def part_poses(theta):
        T = torch.eye(4, dtype=theta.dtype).expand(*theta.shape[:-1], 2, 4, 4).clone()
        T[..., 1, 0, 3] = theta[..., 0]
        return T

    return ComposedField(fields, None, part_poses)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_composed_density_is_the_sum_of_the_parts_and_colour_their_weighted_mean(dtype):
    field = two_boxes()
    x = torch.tensor([[0.25, 0.5, 0.5], [0.75, 0.5, 0.5], [1.25, 0.5, 0.5], [2.0, 0.5, 0.5], [0.5, 2.0, 0.5]], dtype=dtype)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype).expand(5, 3)
    theta = torch.tensor([0.5], dtype=dtype)
    sigma, rgb = field(x, d, theta)
    # part 1 covers x in [0.5, 1.5] with density 3 + (x - 0.5)
    assert sigma.tolist() == pytest.approx([2.0, 2.0 + 3.25, 3.75, 0.0, 0.0])
    assert rgb[0].tolist() == [1.0, 0.0, 0.0] and rgb[2].tolist() == pytest.approx([0.0, 0.0, 1.0])
    assert rgb[1].tolist() == pytest.approx([2.0 / 5.25, 0.0, 3.25 / 5.25])
    assert rgb[3:].abs().max() == 0  # empty space: no colour, no NaN
    assert sigma.dtype == dtype and rgb.dtype == dtype


def test_per_sample_configurations_move_each_sample_by_its_own():
    field = two_boxes()
    x = torch.tensor([[0.75, 0.5, 0.5]]).expand(3, 3)
    d = torch.zeros(3, 3)
    theta = torch.tensor([[0.0], [0.5], [0.9]])
    sigma, _ = field(x, d, theta)
    assert sigma.tolist() == pytest.approx([2.0 + 3.75, 2.0 + 3.25, 2.0])  # at θ = 0.9 part 1 starts at 0.9
    shared, _ = field(x, d, torch.tensor([[0.5]]).expand(3, 1))
    assert shared.tolist() == pytest.approx([5.25] * 3)  # equal rows take the one-pose path: same result


def test_composed_density_is_differentiable_in_the_configuration():
    field = two_boxes()
    theta = torch.tensor([[0.5], [0.25]], dtype=torch.float64, requires_grad=True)
    x = torch.tensor([[0.75, 0.5, 0.5], [0.75, 0.5, 0.5]], dtype=torch.float64)
    sigma, _ = field(x, torch.zeros_like(x), theta)
    sigma.sum().backward()
    assert theta.grad.flatten().tolist() == pytest.approx([-1.0, -1.0])  # d(3 + x - θ)/dθ


def test_composed_field_skips_samples_outside_part_grids():
    field = two_boxes()
    empty = OccupancyGrid(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), torch.zeros(2, 2, 2, dtype=torch.bool))
    field.grids = [None, empty]  # part 1 known empty: only part 0 is asked
    sigma, rgb = field(torch.tensor([[0.75, 0.5, 0.5]]), torch.zeros(1, 3), torch.tensor([0.5]))
    assert sigma.tolist() == [2.0] and rgb.tolist() == [[1.0, 0.0, 0.0]]


# ---------------------------------------------------------------------------------------------
# Training rays: stage 1 from the labels, stage 2 from random views of the object's box


@pytest.mark.slow
def test_part_rays_supervise_every_labelled_pixel_of_the_part_and_no_other(tiny_dataset):
    dataset = Dataset.open(tiny_dataset)
    kin = KinematicTree.from_urdf(dataset.urdf_path)
    rays, _ = part_rays(dataset, kin, part_boxes(kin))
    labels = np.stack([dataset.load(f).labels for f in dataset.frames("train")])
    for p, link in enumerate(dataset.links):  # one link per part here
        assert kin.parts[p] == [link]
        mine = rays[p].opacity == 1
        assert int(mine.sum()) == int((labels == p + 1).sum()) > 0  # every pixel of the part (inside its box)
        assert bool((rays[p].depth[mine] > 0).all()) and bool((rays[p].depth[~mine] == 0).all())
        assert int((~mine).sum()) <= int((labels == 0).sum())  # the rest is background crossing the box
        assert rays[p].rgb.min() >= 0 and rays[p].rgb.max() <= 1
        assert torch.allclose(rays[p].rays.directions.norm(dim=-1), torch.ones(len(rays[p])), atol=1e-5)
        assert bool((rays[p].incidence >= 0).all()) and bool((rays[p].incidence <= 1 + 1e-5).all())


@pytest.mark.slow
def test_occluder_rays_are_the_other_links_pixels_crossing_the_part_box(tiny_dataset):
    dataset = Dataset.open(tiny_dataset)
    kin = KinematicTree.from_urdf(dataset.urdf_path)
    boxes = part_boxes(kin)
    _, occluders = part_rays(dataset, kin, boxes)
    labels = np.stack([dataset.load(f).labels for f in dataset.frames("train")])
    for p in range(len(kin.parts)):  # one link per part here
        assert 0 < len(occluders[p]) <= int(((labels > 0) & (labels != p + 1)).sum())
        assert bool((occluders[p].depth > 0).all())
        _, _, hit = ray_aabb(occluders[p].rays.origins, occluders[p].rays.directions, boxes[p])
        assert bool(hit.all())
    # Without the free-space term: the same supervising rays, no occluders and no incidence computed
    plain, none = part_rays(dataset, kin, boxes, free_space=False)
    full, _ = part_rays(dataset, kin, boxes)
    assert none is None and all(r.incidence is None for r in plain)
    for p in range(len(kin.parts)):
        torch.testing.assert_close(plain[p].rgb, full[p].rgb)
        torch.testing.assert_close(plain[p].depth, full[p].depth)


def test_random_views_look_at_the_centre_from_the_shell():
    centre = torch.tensor([0.1, -0.2, 0.05])
    T = random_views(500, centre, (0.4, 1.0), torch.Generator().manual_seed(0))
    offset = centre - T[:, :3, 3]
    distance = offset.norm(dim=-1)
    assert bool(((distance >= 0.4 - 1e-5) & (distance <= 1.0 + 1e-5)).all())
    assert torch.allclose(T[:, :3, 2], offset / distance[:, None], atol=1e-5)  # optical axis at the centre
    R = T[:, :3, :3]
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3).expand(500, 3, 3), atol=1e-5)
    assert bool((torch.linalg.det(R) > 0.999).all())
    assert T[:, 2, 3].min() < centre[2] - 0.3 and T[:, 2, 3].max() > centre[2] + 0.3  # from below and above


def test_rays_through_box_all_cross_the_box():
    generator = torch.Generator().manual_seed(1)
    aabb = torch.tensor([[-0.1, -0.05, -0.01], [0.1, 0.05, 0.01]])
    T = random_views(8, torch.zeros(3), (0.4, 1.0), generator)
    rays, view = rays_through_box(T, aabb, 16, generator)
    assert len(rays) == 128 and view.tolist() == [v for v in range(8) for _ in range(16)]
    _, _, hit = ray_aabb(rays.origins, rays.directions, aabb)
    assert bool(hit.all())
    assert torch.equal(rays.origins, T[view, :3, 3])
    assert bool((rays.z_per_t > 0.9).all()) and bool((rays.z_per_t <= 1 + 1e-6).all())  # near the optical axis


# ---------------------------------------------------------------------------------------------
# The loss


def hand_batch():
    rays = Rays(torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0]] * 2), torch.ones(2))
    targets = RayTargets(rays, torch.tensor([[1.0, 0.5, 0.0], [0.2, 0.2, 0.2]]), torch.tensor([1.0, 0.0]),
                         torch.tensor([2.0, 0.0]))
    opacity = torch.tensor([0.5, 0.25], requires_grad=True)
    out = RenderOutput(rgb=torch.tensor([[0.5, 0.5, 0.5], [0.1, 0.0, 0.0]]), depth=torch.tensor([1.5, 0.3]), opacity=opacity)
    return out, targets


def test_ray_loss_terms_by_hand():
    out, targets = hand_batch()
    # colour against the target premultiplied by its opacity: ray 1's target is black
    rgb = ((0.5 - 1.0) ** 2 + 0 + 0.5**2 + 0.1**2 + 0 + 0) / 6
    opacity = ((0.5 - 1.0) ** 2 + 0.25**2) / 2
    depth = abs(1.5 - 2.0 * 0.5)  # only ray 0 has a depth; compared opacity-weighted
    config = TrainConfig(opacity_weight=1.0, depth_weight=0.1)
    assert ray_loss(out, targets, config).item() == pytest.approx(rgb + opacity + 0.1 * depth)
    weighted = TrainConfig(opacity_weight=3.0, depth_weight=2.0)
    assert ray_loss(out, targets, weighted).item() == pytest.approx(rgb + 3.0 * opacity + 2.0 * depth)


def test_ray_loss_without_depth_and_its_opacity_gradient():
    out, targets = hand_batch()
    targets = RayTargets(targets.rays, targets.rgb, targets.opacity, torch.zeros(2))
    loss = ray_loss(out, targets, TrainConfig(opacity_weight=1.0, depth_weight=5.0))
    assert loss.item() == pytest.approx((0.25 + 0.25 + 0.01) / 6 + (0.25 + 0.0625) / 2)
    loss.backward()
    assert out.opacity.grad.tolist() == pytest.approx([2 * (0.5 - 1.0) / 2, 2 * 0.25 / 2])


def test_the_depth_term_pulls_no_gradient_through_opacity():
    out, targets = hand_batch()
    ray_loss(out, targets, TrainConfig(opacity_weight=0.0, depth_weight=1.0)).backward()
    assert out.opacity.grad.abs().max() == 0  # the target depth is scaled by a detached opacity


def test_train_config_for_fastnerf_lowers_the_learning_rate():
    assert TrainConfig(arch="fastnerf").for_arch().lr == 5e-4
    assert TrainConfig().for_arch() == TrainConfig()


@pytest.mark.slow
def test_composites_pool_renders_the_teacher_once(tiny_dataset, tmp_path, monkeypatch):
    """``composites=N``: the paper's fixed pool of N composited views, rendered before stage 2 starts."""
    real_composite, views = pipeline.composite_rays, []

    def counted(*args, **kwargs):
        views.append(kwargs["n_views"])
        return real_composite(*args, **kwargs)

    monkeypatch.setattr(pipeline, "composite_rays", counted)
    config = tiny_config(part_steps=5, distill_steps=7, composites=10, views_per_batch=4)
    train(tiny_dataset, tmp_path / "m.narf", config, progress=False)
    assert views == [4, 4, 2]  # 10 views in chunks, then the 7 steps only sample the pool
    assert (tmp_path / "m.narf").exists()


@pytest.mark.slow
def test_distill_benchmark_compares_stream_and_pool_for_the_same_budget(tiny_model, tiny_dataset, tmp_path):
    from benchmarks.distill import run

    result = run(tiny_model, Dataset.open(tiny_dataset), out_dir=tmp_path, budgets_s=(1.5,), composites=(0, 40), images=2,
                 progress=False)
    assert [(r["composites"], r["budget_s"]) for r in result["rows"]] == [(0, 1.5), (40, 1.5)]
    for row in result["rows"]:
        assert 1.5 <= row["seconds"] < 5  # the pool's rendering counts against the budget
        assert row["test"]["n"] == row["novel"]["n"] == 2 and math.isfinite(row["novel"]["psnr"])
    assert "| 40 | 1.5 |" in (tmp_path / "distill.md").read_text()


@pytest.mark.slow
def test_fields_benchmark_puts_the_articulated_field_beside_the_bundles_field_and_the_parts(tiny_model, tiny_dataset):
    from benchmarks.fields import markdown, run

    rows = run(tiny_model, Dataset.open(tiny_dataset), images=2, reps=1)
    assert [(r["split"], r["variant"]) for r in rows] == [
        (split, name) for split in ("test", "novel") for name in ("narf", "parts", "articulated")
    ]
    for split in ("test", "novel"):
        by_name = {r["variant"]: r for r in rows if r["split"] == split}
        # built from the parts, the articulated field renders their images (to float rounding)
        assert by_name["articulated"]["psnr"] == pytest.approx(by_name["parts"]["psnr"], abs=0.05)
        assert all(r["n"] == 2 and r["cpu_ms"] > 0 and math.isfinite(r["psnr"]) for r in by_name.values())
    assert "| novel | articulated |" in markdown(rows, 48, 36)


# ---------------------------------------------------------------------------------------------
# The free-space term: the space in front of a measured surface is carved


class Slabs(nn.Module):
    """Grey density ``exp(log_sigma[0])`` on ``z`` in [0.3, 0.4) (a false floor) and ``exp(log_sigma[1])``
    on [0.6, 0.7) (the true surface); empty elsewhere."""

    def __init__(self, log_sigma=(5.0, 5.0)):
        super().__init__()
        self.log_sigma = nn.Parameter(torch.tensor(log_sigma))

    def forward(self, x, d, theta=None):
        z = x[:, 2]
        sigma = self.log_sigma.exp()
        density = torch.where((z >= 0.3) & (z < 0.4), sigma[0], 0.0) + torch.where((z >= 0.6) & (z < 0.7), sigma[1], 0.0)
        return density, torch.full_like(x, 0.5)


SLAB_BOX = torch.tensor([[-0.1, -0.1, 0.0], [0.1, 0.1, 1.0]])


def rays_along_z(n: int) -> Rays:
    """``n`` rays along +z from z = -0.5 (so camera z = t = the ray's z + 0.5)."""
    origins = torch.stack([torch.linspace(-0.05, 0.05, n), torch.zeros(n), torch.full((n,), -0.5)], dim=-1)
    return Rays(origins, torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3), torch.ones(n))


def test_free_space_loss_is_the_opacity_in_front_of_the_measured_surface():
    field = Slabs((math.log(5.0), math.log(5.0)))
    rays = rays_along_z(3)
    depth = torch.tensor([1.1, 0.7, 0.85])  # the true surface; in front of both slabs; inside the false floor
    opacity = [pipeline.free_space_loss(field, pipeline.FreeRays(rays[i : i + 1], depth[i : i + 1]), SLAB_BOX, None, 0.01).item()
               for i in range(3)]
    assert opacity[0] == pytest.approx(1 - math.exp(-5.0 * 0.1), abs=0.04)  # the false floor, not the true surface
    assert opacity[1] == 0.0
    assert opacity[2] == pytest.approx(1 - math.exp(-5.0 * (0.35 - pipeline.FREE_SPACE_MARGIN - 0.3)), abs=0.04)


def test_the_free_space_ends_the_margin_from_the_surface_along_its_normal():
    """Seen at incidence |cos| = c the free space ends FREE_SPACE_MARGIN / c before the surface along
    the ray (the margin along the normal), so a surface seen edge-on keeps its density ramp."""
    field = Slabs((math.log(20.0), math.log(20.0)))
    rays = rays_along_z(3)
    free = pipeline.FreeRays(rays, torch.full((3,), 0.85), torch.tensor([1.0, 0.2, 0.0]))  # inside the false floor
    ends = 0.85 - pipeline.FREE_SPACE_MARGIN / torch.tensor([1.0, 0.2, pipeline.MIN_INCIDENCE])
    torch.testing.assert_close(pipeline.free_space_end(free), ends)
    opacity = [pipeline.free_space_loss(field, free[i : i + 1], SLAB_BOX, None, 0.01).item() for i in range(3)]
    for got, end in zip(opacity, ends.tolist()):  # the false floor starts at t = 0.8
        assert got == pytest.approx(1 - math.exp(-20.0 * max(end - 0.8, 0.0)), abs=0.04)
    assert opacity[0] > opacity[1] + 0.1 and opacity[2] < 0.01


def plane_depth(camera, normal: torch.Tensor, offset: float) -> torch.Tensor:
    """``[H*W]`` camera z of the plane ``normal . x = offset`` (camera frame) on each pixel's ray."""
    rays = camera.rays()
    t = offset / (rays.directions @ normal)
    return t * rays.z_per_t


def test_surface_incidence_is_the_cosine_between_ray_and_plane_normal_and_skips_depth_edges():
    from narf_core.geometry import Pinhole

    camera = Pinhole(torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]), 32, 24)
    rays = camera.rays()
    normal = torch.nn.functional.normalize(torch.tensor([0.0, -0.8, -0.6]), dim=0)  # a floor seen from above, tilted
    depth = plane_depth(camera, normal, -0.5)
    truth = (rays.directions @ normal).abs()
    torch.testing.assert_close(surface_incidence(rays, depth, 24, 32), truth, atol=1e-4, rtol=0)
    # the left half 20 cm further (a depth edge down the middle): each side keeps its own normal
    wall = torch.tensor([0.0, 0.0, -1.0])
    left = (torch.arange(24 * 32) % 32) < 16
    stepped = torch.where(left, plane_depth(camera, wall, -0.9), depth)
    got = surface_incidence(rays, stepped, 24, 32)
    torch.testing.assert_close(got[left], (rays.directions[left] @ wall).abs(), atol=1e-4, rtol=0)
    torch.testing.assert_close(got[~left], truth[~left], atol=1e-4, rtol=0)
    # no depth, or a pixel whose neighbours along an axis have none: unknown (0)
    lone = torch.zeros(24 * 32)
    lone[5 * 32 + 7] = 0.8
    lone[5 * 32 + 8 : 5 * 32 + 10] = 0.8  # a row segment: no neighbour above or below
    assert bool((surface_incidence(rays, lone, 24, 32) == 0).all())


def test_the_free_space_term_carves_a_false_floor_that_hides_the_surface():
    """A false floor in front of the measured surface, opaque enough to stop the march
    (transmittance < 1e-3), meets the colour and opacity targets; trained with the free-space term the
    floor is emptied and the rays end on the true surface."""
    field = Slabs()
    rays = rays_along_z(16)
    targets = RayTargets(rays, torch.full((16, 3), 0.5), torch.ones(16), torch.full((16,), 1.1))
    free = pipeline.free_rays(targets, pipeline.FreeRays(rays[:0], torch.zeros(0)), 0, torch.Generator())
    config = TrainConfig(free_space_weight=1.0)
    optimizer = torch.optim.Adam(field.parameters(), lr=0.1)

    def render():
        return pipeline.render_rays(field, rays, SLAB_BOX, step=0.01, outputs=("rgb", "opacity", "depth"), jitter=True)

    before = pipeline.free_space_loss(field, free, SLAB_BOX, None, 0.01).item()
    assert before > 0.99
    for _ in range(60):
        loss = ray_loss(render(), targets, config) + config.free_space_weight * pipeline.free_space_loss(field, free, SLAB_BOX, None, 0.01)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        out = render()
        assert pipeline.free_space_loss(field, free, SLAB_BOX, None, 0.01).item() < 0.05
    assert bool((out.opacity > 0.95).all())
    assert (out.depth / out.opacity).mean().item() == pytest.approx(1.1, abs=0.02)  # the true surface's front


# ---------------------------------------------------------------------------------------------
# The sparsity term: what no ray reaches is left empty


def test_sparsity_loss_is_the_mean_opacity_of_one_step_at_random_points_of_the_box():
    field = Slabs((math.log(20.0), math.log(5.0)))  # slabs on a tenth of the box's z each
    got = pipeline.sparsity_loss(field, SLAB_BOX, 0.01, 20000, torch.Generator().manual_seed(0)).item()
    expected = 0.1 * (1 - math.exp(-20.0 * 0.01)) + 0.1 * (1 - math.exp(-5.0 * 0.01))
    assert got == pytest.approx(expected, rel=0.05)
    empty = Slabs((-30.0, -30.0))
    assert pipeline.sparsity_loss(empty, SLAB_BOX, 0.01, 1000, torch.Generator()).item() < 1e-9


def test_the_sparsity_term_empties_what_the_rays_never_reach_and_keeps_the_surface():
    """Rays that stop on the front slab (opaque, the measured surface) never reach the slab behind it,
    which the ray loss leaves as it is: a part hidden in every view by another. With the sparsity
    term the hidden slab empties and the rays still end, opaque, on the front one."""
    field = Slabs((math.log(200.0), math.log(200.0)))
    rays = rays_along_z(16)
    targets = RayTargets(rays, torch.full((16, 3), 0.5), torch.ones(16), torch.full((16,), 0.8))  # the front slab
    config = TrainConfig(sparsity_weight=0.1)
    optimizer = torch.optim.Adam(field.parameters(), lr=0.1)
    generator = torch.Generator().manual_seed(0)

    def render():
        return pipeline.render_rays(field, rays, SLAB_BOX, step=0.01, outputs=("rgb", "opacity", "depth"), jitter=True)

    def step(sparsity: bool) -> None:
        loss = ray_loss(render(), targets, config)
        if sparsity:
            loss = loss + config.sparsity_weight * pipeline.sparsity_loss(field, SLAB_BOX, 0.01, 4096, generator)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    for _ in range(60):
        step(False)
    assert field.log_sigma[1].item() == pytest.approx(math.log(200.0))  # without the term: no gradient behind
    for _ in range(60):
        step(True)
    with torch.no_grad():
        out = render()
    sigma = field.log_sigma.exp()
    assert sigma[1].item() < 5.0 < 30.0 < sigma[0].item()  # behind: emptied; in front: still opaque
    assert bool((out.opacity > 0.95).all())
    assert (out.depth / out.opacity).mean().item() == pytest.approx(0.8, abs=0.02)


def test_the_sparsity_term_leaves_the_measured_surface_alone():
    """The cells within SURFACE_CELLS of a surface point the part's own pixels measured are left out of
    the sparsity term (a softer surface would take the march more samples to stop); no depth, no cells."""
    rays = rays_along_z(16)  # camera z = t = the ray's z + 0.5
    targets = RayTargets(rays, torch.full((16, 3), 0.5), torch.ones(16), torch.full((16,), 1.105))  # at z = 0.605
    surface = pipeline.observed_surface(targets, SLAB_BOX, 100)  # cells of 1 cm along z: the point's is [0.6, 0.61)
    margin = pipeline.SURFACE_CELLS * 0.01
    probe = torch.tensor([[0.0, 0.0, 0.605], [0.0, 0.0, 0.605 + margin], [0.0, 0.0, 0.605 - margin],
                          [0.0, 0.0, 0.35], [0.0, 0.0, 0.605 + margin + 0.01]])
    assert surface.occupied(probe).tolist() == [True, True, True, False, False]

    def shell(x, d, theta=None):  # density on the measured surface's cells alone
        return 20.0 * surface.occupied(x).float(), torch.full_like(x, 0.5)

    whole = pipeline.sparsity_loss(shell, SLAB_BOX, 0.01, 20000, torch.Generator().manual_seed(0)).item()
    away = pipeline.sparsity_loss(shell, SLAB_BOX, 0.01, 20000, torch.Generator().manual_seed(0), surface).item()
    assert whole > 0.001 and away == 0.0
    slabs = Slabs((math.log(20.0), -30.0))  # the front slab alone, far from the surface: all of it counts
    front = pipeline.sparsity_loss(slabs, SLAB_BOX, 0.01, 20000, torch.Generator().manual_seed(0), surface).item()
    assert front == pytest.approx(0.1 * (1 - math.exp(-20.0 * 0.01)), rel=0.05)
    no_depth = RayTargets(rays, targets.rgb, targets.opacity, torch.zeros(16))
    assert pipeline.observed_surface(no_depth, SLAB_BOX, 100) is None


def test_the_sparsity_term_leaves_the_parts_own_urdf_surface_alone(tiny_dataset):
    """``part_surface_points``: every part's visual meshes in its own frame (inside its box), at least a
    point per ``spacing`` squared of area; ``observed_surface`` keeps their cells out of the sparsity term
    too, so a stretch of a part that no view shows (a jaw inside the clamp's body) is not emptied."""
    from narf_core.train.parts import part_surface_points

    kin = KinematicTree.from_urdf(Dataset.open(tiny_dataset).urdf_path)
    meshes = kin.visual_meshes()
    for p, box in enumerate(part_boxes(kin)):
        points = part_surface_points(kin, p, 0.005)
        area = sum(meshes[link].area for link in kin.parts[p] if link in meshes)
        assert len(points) >= area / 0.005**2
        assert bool(((points >= box[0]) & (points <= box[1])).all())
        rays = rays_along_z(4)
        unmeasured = RayTargets(rays, torch.zeros(4, 3), torch.ones(4), torch.zeros(4))  # no depth anywhere
        assert pipeline.observed_surface(unmeasured, box, 64) is None
        surface = pipeline.observed_surface(unmeasured, box, 64, points)
        assert bool(surface.occupied(points).all())
        inside = box[0] + torch.rand(4000, 3, generator=torch.Generator().manual_seed(p)) * (box[1] - box[0])
        assert 0.0 < surface.occupied(inside).float().mean().item() < 1.0  # the rest of the box still counts


# The exclusion term: no part where another's surface stands at the training configurations


def test_exclusion_points_are_the_other_parts_surface_away_from_the_parts_own(tmp_path, assets, monkeypatch):
    """Longnose pliers closed (its training configuration): the lower half's jaw lies beside the upper's,
    inside the upper half's box. The upper half's exclusion points are the lower half's surface points at
    that configuration (in the upper half's frame), inside its box and more than a grid cell from its own
    surface; they move with the configuration. The clamp's bar passes through its jaw's mesh: none of the jaw's
    points lies inside the jaw's own meshes. A part with no other part has none."""
    from narf_core.data.synth import tools
    from narf_core.train.parts import part_meshes, part_surface_points

    kin = KinematicTree.from_urdf(tools.build_tool("longnose", tmp_path))
    upper, lower = kin.part_names.index("upper_half"), kin.part_names.index("lower_half")
    box = part_boxes(kin)[upper]
    resolution = 64
    cell = float((box[1] - box[0]).min()) / resolution
    closed = torch.tensor([[0.02]], dtype=torch.float64)
    points = pipeline.exclusion_points(kin, upper, box, resolution, closed)
    assert len(points) > 1000
    assert bool(((points >= box[0]) & (points <= box[1])).all())
    some = points[:: max(1, len(points) // 1000)]
    own = part_surface_points(kin, upper, cell)
    assert torch.cdist(some, own).min().item() > cell  # a whole cell from the part's own surface at least
    T = kin.part_poses(closed[0])
    lower_in_upper = torch.linalg.inv(T[upper]) @ T[lower]
    theirs = transform_points(lower_in_upper.float(), part_surface_points(kin, lower, cell))
    assert torch.cdist(some, theirs).min(dim=1).values.max().item() < 1e-4  # each one on the lower half's surface
    opened = pipeline.exclusion_points(kin, upper, box, resolution, torch.tensor([[0.5]], dtype=torch.float64))
    assert len(opened) != len(points) or not torch.equal(opened, points)
    both = pipeline.exclusion_points(kin, upper, box, resolution, torch.cat([closed, closed.new_tensor([[0.5]])]))
    assert len(both) == len(points) + len(opened)
    clamp = KinematicTree.from_urdf(tools.build_tool("clamp", tmp_path))  # its bar's mesh runs through the jaw's
    jaw = clamp.part_names.index("moving_jaw")
    from trimesh.ray.ray_util import contains_points

    def inside_jaw(x):  # the implementation's fixed-direction test (trimesh's own retries an open mesh at random)
        return sum(contains_points(m.ray, x.double().numpy(), check_direction=pipeline._INSIDE_RAY)
                   for m in part_meshes(clamp, jaw)).astype(bool)

    jaw_box, slid = part_boxes(clamp)[jaw], torch.tensor([[0.05]])
    in_jaw = pipeline.exclusion_points(clamp, jaw, jaw_box, resolution, slid)
    assert len(in_jaw) > 1000 and not inside_jaw(in_jaw).any()
    monkeypatch.setattr(pipeline, "part_meshes", lambda kin, part: [])  # no inside test: the jaw would be carved
    assert inside_jaw(pipeline.exclusion_points(clamp, jaw, jaw_box, resolution, slid)).mean() > 0.2
    monkeypatch.undo()
    rigid = KinematicTree.from_urdf(assets / "fixed_chain.urdf")  # one part: no other to exclude
    assert len(pipeline.exclusion_points(rigid, 0, box, resolution, torch.zeros(1, 0, dtype=torch.float64))) == 0


def test_the_exclusion_term_empties_a_part_where_another_stands():
    """A part's field runs on behind its measured surface (the back slab, which no ray reaches: another part
    stands there in every view). ``exclusion_loss`` is the mean opacity of one step at the points; with the
    term on those points the back slab empties while the rays still end, opaque, on the front one."""
    field = Slabs((math.log(200.0), math.log(200.0)))
    rays = rays_along_z(16)
    targets = RayTargets(rays, torch.full((16, 3), 0.5), torch.ones(16), torch.full((16,), 0.8))  # the front slab
    config = TrainConfig()
    generator = torch.Generator().manual_seed(0)
    behind = torch.stack([torch.zeros(200), torch.zeros(200), torch.linspace(0.61, 0.69, 200)], dim=-1)
    cell = torch.full((3,), 0.01)
    got = pipeline.exclusion_loss(field, behind, 0.01, 512, generator, cell).item()
    assert got == pytest.approx(1 - math.exp(-200.0 * 0.01), rel=0.05)  # a few jittered out of the slab
    optimizer = torch.optim.Adam(field.parameters(), lr=0.1)
    for _ in range(60):
        out = pipeline.render_rays(field, rays, SLAB_BOX, step=0.01, outputs=("rgb", "opacity", "depth"), jitter=True)
        loss = ray_loss(out, targets, config)
        loss = loss + config.exclusion_weight * pipeline.exclusion_loss(field, behind, 0.01, 512, generator, cell)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        out = pipeline.render_rays(field, rays, SLAB_BOX, step=0.01, outputs=("opacity", "depth"))
    sigma = field.log_sigma.exp()
    assert sigma[1].item() < 5.0 < 30.0 < sigma[0].item()
    assert bool((out.opacity > 0.95).all())


def test_free_rays_are_the_batch_rays_with_a_depth_and_drawn_occluders():
    rays = rays_along_z(4)
    batch = RayTargets(rays, torch.zeros(4, 3), torch.tensor([1.0, 0.0, 1.0, 1.0]), torch.tensor([0.9, 0.0, 0.0, 1.2]))
    occluders = pipeline.FreeRays(rays_along_z(2), torch.tensor([0.25, 0.5]))
    free = pipeline.free_rays(batch, occluders, 5, torch.Generator().manual_seed(0))
    assert len(free) == 7 and free.depth[:2].tolist() == pytest.approx([0.9, 1.2])
    assert set(free.depth[2:].tolist()) <= {0.25, 0.5}
    assert torch.equal(free.rays.origins[:2], rays.origins[[0, 3]])
    assert free.incidence is None  # none known: every surface as if seen face-on
    batch.incidence = torch.tensor([0.5, 0.0, 0.0, 0.25])
    free = pipeline.free_rays(batch, occluders, 5, torch.Generator().manual_seed(0))
    assert free.incidence.tolist() == [0.5, 0.25, 1, 1, 1, 1, 1]


@pytest.mark.slow
def test_training_with_the_free_space_term_runs_it_every_step_and_sees_the_object(tiny_dataset, tmp_path, monkeypatch):
    calls = []
    loss = pipeline.free_space_loss
    monkeypatch.setattr(pipeline, "free_space_loss", lambda field, free, *a: calls.append(len(free)) or loss(field, free, *a))
    config = tiny_config(field="articulated", free_space_weight=1.0)
    model = load_bundle(train(tiny_dataset, tmp_path / "free.narf", config, progress=False))
    assert model.metadata["provenance"]["config"]["free_space_weight"] == 1.0
    assert len(calls) == 2 * config.part_steps and min(calls) > 0  # every step of both parts
    iou, outside = mask_iou(model, Dataset.open(tiny_dataset), "test", "narf")
    assert iou > 0.35 and outside < 0.02
