"""Sequences (narf synth --sequence), the tracker (narf_core.track) and narf track, on the bundled clamp."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from narf_core.cli import main as narf

ROOT = Path(__file__).resolve().parent.parent
CLAMP = ROOT / "models" / "clamp.narf"


@pytest.fixture(scope="module")
def clamp(bundled_clamp):
    return bundled_clamp


@pytest.fixture(scope="module")
def clamp_sequence(tmp_path_factory) -> Path:
    """Eight smooth frames of the clamp at 160x120 (the model's training size)."""
    pytest.importorskip("pybullet")
    from narf_core.data.synth.sequence import synthesize_sequence

    return synthesize_sequence("clamp", tmp_path_factory.mktemp("seq") / "clamp", 8, events=False, supersample=1)


# A usual colour residual over that of clamp_sequence's frames (aliased point samples: about 0.026, over
# TrackOptions.usual_residual), for tests of what σ does below it.
ALIASED_USUAL_RESIDUAL = 0.03


# --------------------------------------------------------------------------------------------
# sequences


def test_sequence_is_smooth_timed_and_has_its_events(tmp_path: Path) -> None:
    pytest.importorskip("pybullet")
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.sequence import camera_speeds, synthesize_sequence

    out = synthesize_sequence("clamp", tmp_path / "seq", 160, size=(40, 30), seed=1, supersample=1)
    dataset = Dataset.open(out)
    frames = dataset.frames()
    times = np.array([f.time for f in frames])
    assert [f.split for f in frames] == ["test"] * 160
    np.testing.assert_allclose(times, np.arange(160) / 30.0)
    speed, turn = camera_speeds(np.stack([f.T_cam_obj for f in frames]), times)
    assert speed.max() <= 0.30 + 1e-6 and turn.max() <= 60.0 + 1e-6  # the issue's hand-held limits
    assert speed.max() > 0.02 and turn.max() > 10  # and it does move
    jaw = np.array([f.joints["jaw_opening"] for f in frames])
    assert jaw.max() - jaw.min() > 0.05  # the jaw opens and closes
    per_frame = dataset.generator["sequence"]["per_frame"]
    assert not per_frame[0]["in_view"] or per_frame[0]["object_pixels"] > 0
    out_of_view = [i for i, f in enumerate(per_frame) if not f["in_view"]]
    assert out_of_view and out_of_view[0] > 0  # the camera glances away after the start
    for i in out_of_view:
        assert not dataset.load(frames[i]).labels.any()
    occluded = [i for i, f in enumerate(per_frame) if 0 < f["occluded"] < 1]
    assert occluded  # the bar hides part of the object


def test_smooth_sequence_keeps_the_object_in_view(tmp_path: Path) -> None:
    pytest.importorskip("pybullet")
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.sequence import synthesize_sequence

    out = synthesize_sequence("clamp", tmp_path / "seq", 20, size=(40, 30), events=False, supersample=1)
    dataset = Dataset.open(out)
    assert all(f["in_view"] and f["occluded"] == 0 for f in dataset.generator["sequence"]["per_frame"])
    assert all(dataset.load(f).labels.any() for f in dataset.frames())


def test_the_bar_covers_its_columns_inside_the_image_only() -> None:
    """The occluding bar, a fifth of the width, sweeps in from beyond the left edge and out beyond the right:
    beside the image it covers nothing (a negative end once wrapped round and hid most of the image)."""
    from narf_core.data.synth.bar import bar_columns

    assert bar_columns(160, 0.5) == slice(64, 96)
    assert bar_columns(160, -0.05) == slice(0, 8) and bar_columns(160, 1.05) == slice(152, 160)
    for beside in (-0.3, -0.1, 1.1, 1.3):
        assert len(range(160)[bar_columns(160, beside)]) == 0


def test_a_cached_sequence_with_events_but_no_bar_record_is_drawn_again(tmp_path: Path) -> None:
    """``sequence_once`` (the benchmarks' cache) keeps a whole sequence, but draws again one with events that
    does not record its occluding bar (an older narf's: its restyled frames would lack the bar)."""
    pytest.importorskip("pybullet")
    import json

    from narf_core.data.synth.sequence import sequence_once

    for events in (True, False):
        out = sequence_once("clamp", tmp_path / f"seq-{events}", 3, size=(32, 24), events=events)
        scene = json.loads((out / "scene.json").read_text())
        assert all(("occluder" in p) and (p["occluder"] is not None) == events
                   for p in scene["generator"]["sequence"]["per_frame"])
        for p in scene["generator"]["sequence"]["per_frame"]:
            del p["occluder"]
        scene["generator"]["marked"] = True  # to tell the kept file from one drawn again
        (out / "scene.json").write_text(json.dumps(scene))
        sequence_once("clamp", out, 3, size=(32, 24), events=events)
        again = json.loads((out / "scene.json").read_text())["generator"]
        assert ("marked" in again) == (not events)
        assert events is False or all(p["occluder"] is not None for p in again["sequence"]["per_frame"])


WITHOUT_GENERATOR = """
import sys
from pathlib import Path
for name in ("pybullet", "pybullet_utils", "shapely", "mapbox_earcut"):
    sys.modules[name] = None  # as where the synth extra is not installed (a GPU machine, the service's image)
from narf_core.data.synth.sequence import sequence_once
try:
    print(sequence_once("clamp", Path(sys.argv[1]), 3, size=(32, 24), events=False))
except ImportError as e:
    print("ImportError", e.name)
"""


def test_a_cached_sequence_reads_without_the_generators_packages(tmp_path: Path) -> None:
    """``narf bench track`` on sequences drawn elsewhere (carried to a machine without pybullet or shapely):
    ``sequence_once`` finds a whole sequence without importing the generator, and asks for it only to draw one."""
    pytest.importorskip("pybullet")
    import subprocess
    import sys

    from narf_core.data.synth.sequence import sequence_once

    out = sequence_once("clamp", tmp_path / "seq", 3, size=(32, 24), events=False)
    scene = (out / "scene.json").read_bytes()

    def probe(folder: Path) -> str:
        run = subprocess.run([sys.executable, "-c", WITHOUT_GENERATOR, str(folder)], capture_output=True, text=True,
                             timeout=120, cwd=Path(__file__).resolve().parent.parent)
        assert run.returncode == 0, run.stderr
        return run.stdout.strip().splitlines()[-1]

    assert probe(out) == str(out)
    assert (out / "scene.json").read_bytes() == scene  # read, not drawn again
    assert probe(tmp_path / "missing") in {"ImportError shapely", "ImportError pybullet"}  # drawing one needs them


def test_a_large_object_is_framed_as_its_single_views_are(tmp_path: Path) -> None:
    """The cabinet, whose views have camera distances of their own (it overflows the rig's at 0.4 m), is
    seen from as much farther in a sequence: whole in every frame, where the tools' 0.55 m cut it off
    at the border in all of them; and from its front, as its views are; the tools and a URDF of one's
    own keep the path as it is."""
    pytest.importorskip("pybullet")
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.sequence import SequencePath, folded, framed_path, synthesize_sequence

    path = SequencePath()
    assert framed_path("clamp", path) is path and framed_path(tmp_path / "own.urdf", path) is path
    far = framed_path("cabinet", path)
    assert far.distance == pytest.approx(path.distance * 1.5)
    assert far.distance_sway == pytest.approx(path.distance_sway * 1.5)
    # It stands against a wall: the orbit turns back at 75° either side of its front, 10-50° above it.
    assert far.azimuth_range_deg == (-75.0, 75.0) and path.azimuth_range_deg is None
    assert (far.elevation_deg, far.elevation_sway_deg) == (30.0, 15.0)
    assert [folded(a, (-75.0, 75.0)) for a in (0.0, 80.0, -80.0, 310.0)] == [0.0, 70.0, -70.0, 10.0]
    azimuths, elevations = [], []
    for t in np.linspace(0.0, 40.0, 400):  # 800° of the free orbit at its 20°/s
        T = far.camera(float(t), np.zeros(3), 1e-6, np.zeros(8), 0.0)
        eye = -T[:3, :3].T @ T[:3, 3]
        azimuths.append(math.degrees(math.atan2(eye[1], eye[0])))
        elevations.append(math.degrees(math.asin(eye[2] / np.linalg.norm(eye))))
    assert -75.0 - 1e-3 <= min(azimuths) < -70.0 and 70.0 < max(azimuths) <= 75.0 + 1e-3
    assert 15.0 - 1e-3 <= min(elevations) < 16.0 and 44.0 < max(elevations) <= 45.0 + 1e-3
    out = synthesize_sequence("cabinet", tmp_path / "seq", 6, size=(80, 60), events=False, supersample=1)
    dataset = Dataset.open(out)
    assert dataset.generator["sequence"]["path"]["distance"] == pytest.approx(far.distance)
    for frame in dataset.frames():
        labels = dataset.load(frame).labels > 0
        assert labels.any() and not (labels[0].any() or labels[-1].any() or labels[:, 0].any() or labels[:, -1].any())


def test_datasets_without_times_still_read(tmp_path: Path, clamp_sequence: Path) -> None:
    """scene.json without "time" (every dataset before sequences) reads, with time None; a bad time is named."""
    import shutil

    from narf_core.data.dataset import Dataset, DatasetError

    copy = tmp_path / "old"
    shutil.copytree(clamp_sequence, copy)
    scene = json.loads((copy / "scene.json").read_text())
    for frame in scene["frames"]:
        del frame["time"]
    (copy / "scene.json").write_text(json.dumps(scene))
    assert all(f.time is None for f in Dataset.open(copy).frames())
    scene["frames"][2]["time"] = "soon"
    (copy / "scene.json").write_text(json.dumps(scene))
    with pytest.raises(DatasetError, match=r"frames\[2\]\.time"):
        Dataset.open(copy)


def test_synth_sequence_cli(tmp_path: Path, capsys) -> None:
    pytest.importorskip("pybullet")
    code = narf(["synth", "--tool", "clamp", "--out", str(tmp_path / "s"), "--sequence", "6", "--size", "40", "30",
                 "--supersample", "1", "--smooth", "--json"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["frames"] == 6 and result["frames_out_of_view"] == 0 and result["peak_speed_m_s"] <= 0.3
    assert narf(["synth", "--tool", "clamp", "--out", str(tmp_path / "t"), "--sequence", "4", "--noise", "paper"]) == 2
    assert "narf synth: error: --sequence writes clean labels" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# the tracker


def _frames(dataset, frames, rgb_only=False):
    from narf_core.track_io import load_frames

    return list(load_frames(dataset, frames, rgb_only=rgb_only))


@pytest.mark.slow
@pytest.mark.parametrize("rgb_only", [False, True], ids=["rgbd", "rgb"])
def test_track_follows_the_clamp(clamp, clamp_sequence: Path, rgb_only: bool) -> None:
    import torch

    from narf_core.data.dataset import Dataset
    from narf_core.geometry import se3_exp
    from narf_core.track import TrackOptions, track
    from narf_core.track_io import score, sequence_frames

    dataset = Dataset.open(clamp_sequence)
    frames = sequence_frames(dataset)
    rough = se3_exp(torch.tensor([0.01, -0.005, 0.01, 0.03, -0.02, 0.02], dtype=torch.float64)).numpy() @ frames[0].T_cam_obj
    results = list(track(clamp, _frames(dataset, frames, rgb_only), dataset.camera, rough, None,
                         TrackOptions(uncertainty_rays=256)))
    assert results[0].status == "reinitialised"
    # Held throughout; a frame may be `uncertain` only for its covariance (σ near the 2 cm limit on this
    # short, unsupersampled fixture), never for what it explains of the mask.
    assert all(r.status == "tracking" or (r.status, r.reason) == ("uncertain", "large covariance") for r in results[1:])
    errors = [score(clamp, f, r)["add_m"] for f, r in zip(frames, results)]
    assert np.mean(errors) < (0.015 if rgb_only else 0.01) and max(errors) < 0.025
    jaw = [abs(r.joints["jaw_opening"] - f.joints["jaw_opening"]) for f, r in zip(frames, results)]
    assert max(jaw) < 0.02
    assert all(r.uncertainty is not None and np.isfinite(r.covariance).all() for r in results)
    budget = TrackOptions().step_options(not rgb_only).iterations  # the frame's solver's own: 2 gauss-newton, 6 adam
    assert all(r.iterations == budget for r in results[1:])  # a few iterations per frame


def test_track_bad_input_and_faults(clamp, clamp_sequence: Path) -> None:
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackFrame, TrackInputError, TrackOptions, TrackState, step

    dataset = Dataset.open(clamp_sequence)
    frame0 = dataset.frames()[0]
    images = dataset.load(frame0)
    camera = dataset.camera
    options = TrackOptions(iterations=2, rays_per_iteration=64, uncertainty_rays=0, reinit_iterations=4,
                           reinit_theta_starts=1)
    state = TrackState.initial(clamp, frame0.T_cam_obj, frame0.joints, 0.0, status="tracking")
    result, after = step(clamp, camera, TrackFrame(images.rgb, images.labels > 0, 0.0, images.depth), state, options)
    assert result.status in ("tracking", "uncertain") and after.time == 0.0

    with pytest.raises(TrackInputError, match="time order"):  # the same time again
        step(clamp, camera, TrackFrame(images.rgb, images.labels > 0, 0.0, images.depth), after, options)
    with pytest.raises(TrackInputError, match="frame.time"):
        step(clamp, camera, TrackFrame(images.rgb, images.labels > 0, math.nan), after, options)
    nan_state = TrackState(after.T_cam_obj, after.joints, after.time, after.anchor_time, np.array([np.nan] * 6))
    with pytest.raises(TrackInputError, match="state.velocity"):
        step(clamp, camera, TrackFrame(images.rgb, images.labels > 0, 1.0), nan_state, options)
    with pytest.raises(TrackInputError, match="mask must be"):
        step(clamp, camera, TrackFrame(images.rgb, images.labels[:10] > 0, 1.0), after, options)

    # a missing mask, then an empty one: lost, keeping the last estimate; the state stays usable
    lost, s1 = step(clamp, camera, TrackFrame(images.rgb, None, 0.033), after, options)
    assert lost.status == "lost" and "no mask" in lost.reason
    np.testing.assert_array_equal(lost.T_cam_obj, after.T_cam_obj)
    lost, s2 = step(clamp, camera, TrackFrame(images.rgb, np.zeros_like(images.labels), 0.066), s1, options)
    assert lost.status == "lost" and "not in view" in lost.reason and s2.lost_frames == 2
    # the mask comes back: the multi-start refiner takes over (never 'tracking' straight after 'lost')
    back, s3 = step(clamp, camera, TrackFrame(images.rgb, images.labels > 0, 0.1), s2, options)
    assert back.status in ("reinitialised", "lost") and np.isfinite(back.T_cam_obj).all()
    # a long gap since the last estimate: no constant-velocity prediction across it
    gap, _ = step(clamp, camera, TrackFrame(images.rgb, images.labels > 0, 5.0), after, options)
    assert gap.status in ("reinitialised", "lost") and "since the last estimate" in gap.reason
    # depth missing in the middle: RGB only for that frame, still tracked
    rgb_only, _ = step(clamp, camera, TrackFrame(images.rgb, images.labels > 0, 0.033), after, options)
    assert rgb_only.status in ("tracking", "uncertain") and all(math.isfinite(v) for v in rgb_only.joints.values())


def test_band_and_frame_options_are_validated() -> None:
    from narf_core.estimate import EstimateInputError, EstimateOptions
    from narf_core.track import TrackInputError, TrackOptions

    for bad in (-0.01, 0.0005, 2.0, math.nan):
        with pytest.raises(EstimateInputError, match=r"options\.band_m"):
            EstimateOptions(band_m=bad)
        with pytest.raises(TrackInputError, match=r"options\.band_m"):
            TrackOptions(band_m=bad)
    with pytest.raises(EstimateInputError, match=r"options\.eval_rays must be >= 16"):
        EstimateOptions(eval_rays=8)
    with pytest.raises(TrackInputError, match=r"options\.eval_rays must be >= 16"):
        TrackOptions(eval_rays=0)
    assert EstimateOptions.preset("paper").band_m == 0  # off in the paper's protocol
    step = TrackOptions(band_m=0.02, eval_rays=512).step_options(True)
    assert step.band_m == 0.02 and step.eval_rays == 512


def test_march_option_is_validated_and_band_parts_or_gauss_newton_march_per_iteration(clamp, clamp_sequence: Path,
                                                                                      monkeypatch) -> None:
    """The frame's band without marching (``refine_frame``) serves either solver; a band or parts mode
    runs :func:`refine` with the frame's solver (gauss-newton with depth, as here, unless asked)."""
    from narf_core import track as track_module
    from narf_core.data.dataset import Dataset
    from narf_core.track import MARCHES, TrackFrame, TrackInputError, TrackOptions, TrackState, step

    with pytest.raises(TrackInputError, match=r"options\.march must be one of frame, iteration"):
        TrackOptions(march="once")
    for bad in (-1.0, math.nan):
        with pytest.raises(TrackInputError, match=r"options\.distance_prior_rgb must be"):
            TrackOptions(distance_prior_rgb=bad)
        with pytest.raises(TrackInputError, match=r"options\.occlusion_margin must be"):
            TrackOptions(occlusion_margin=bad)
    with_occluders = TrackOptions(occlusion_margin=0.02)
    assert with_occluders.step_options(True).occlusion_margin == 0.02
    assert with_occluders.reinit_options().occlusion_margin == 0.0  # never from a start far off
    assert TrackOptions().march == "frame" and MARCHES == ("frame", "iteration")
    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    observed = TrackFrame(images.rgb, images.labels > 0, frame.time, images.depth)
    used = []
    real_frame, real_refine = track_module.refine_frame, track_module.refine
    monkeypatch.setattr(track_module, "refine_frame", lambda *a, **k: used.append("frame") or real_frame(*a, **k))
    monkeypatch.setattr(track_module, "refine",
                        lambda *a, **k: used.append(f"iteration {k['options'].solver}") or real_refine(*a, **k))
    for options, expected in ((TrackOptions(), "frame"), (TrackOptions(solver="adam"), "frame"),
                              (TrackOptions(march="iteration"), "iteration gauss-newton"),
                              (TrackOptions(band_m=0.01), "iteration gauss-newton"),
                              (TrackOptions(mode="parts", solver="adam"), "iteration adam")):
        state = TrackState.initial(clamp, frame.T_cam_obj, frame.joints, frame.time - 0.033, status="tracking")
        result, _ = step(clamp, dataset.camera, observed, state, TrackOptions(**{**options.__dict__, "iterations": 2,
                                                                                 "uncertainty_rays": 0}))
        assert used[-1] == expected and result.status == "tracking"


def _box_rays_and_band(clamp, clamp_sequence: Path, index: int):
    """Frame ``index``'s label ``T [4,4]``, ``θ [k]``, the camera rays of its box and their band
    ``(near, far)`` at the label (as a warm-started frame takes it at the prediction)."""
    import torch

    from narf_core.band import ray_band
    from narf_core.data.dataset import Dataset
    from narf_core.render import box_pixels
    from narf_core.track import _FRAME_MARGIN_M

    dataset = Dataset.open(clamp_sequence)
    camera = dataset.camera
    frame = dataset.frames()[index]
    T = torch.tensor(frame.T_cam_obj)
    theta = clamp.kinematics.joint_vector(frame.joints).float()
    rays_cam = camera.rays(box_pixels(camera, T.float(), clamp.aabb))
    with torch.no_grad():
        near, far = ray_band(clamp, camera, rays_cam, T[None], theta[None].double(), _FRAME_MARGIN_M)
    return T, theta, rays_cam, near.double(), far.double()


def test_frame_band_renders_what_the_march_renders(clamp, clamp_sequence: Path) -> None:
    """A frame's samples (the lattice in the band around the surface points at the prediction, kept
    where the occupancy holds at the pose) render what a full march renders, at the prediction and at
    poses moved by the prediction's error and more, where the march takes other samples."""
    import torch

    from narf_core.compositing import composite
    from narf_core.estimate import _object_rays
    from narf_core.geometry import se3_exp
    from narf_core.track import frame_band, occupied

    T, theta, rays_cam, near, far = _box_rays_and_band(clamp, clamp_sequence, 3)
    with torch.no_grad():
        band = frame_band(near, far, clamp.step)
        assert len(band) < 0.25 * len(rays_cam) * float((clamp.aabb[1] - clamp.aabb[0]).norm()) / clamp.step
        outputs = ("rgb", "opacity", "depth")
        for move in (0.0, 0.001, 0.003):  # metres along each camera axis
            pose = se3_exp(torch.tensor([move, -move, move, 0.0, 0.0, 0.0], dtype=torch.float64)) @ T
            rays = _object_rays(rays_cam, pose[None])
            full = clamp.render_rays(rays, theta, outputs=outputs)
            kept = composite(clamp.field, rays, occupied(clamp.grid, rays, band, theta), theta=theta, outputs=outputs)
            assert float(full.opacity.max()) > 0.99
            assert float((kept.opacity - full.opacity).abs().mean()) < 1e-3
            assert float((kept.opacity - full.opacity).abs().max()) < 0.1
            assert float((kept.rgb - full.rgb).abs().mean()) < 1e-3
            solid = full.opacity > 0.99
            assert float((kept.depth[solid] - full.depth[solid]).abs().max()) < 0.01 * float(full.depth[solid].max())
        assert len(frame_band(near[:4], near[:4], clamp.step)) == 0  # an empty band: no sample


def test_visible_samples_render_what_every_sample_renders(clamp, clamp_sequence: Path) -> None:
    """The samples light reaches (the field evaluated at every other one, without a graph) are far
    fewer than the frame's band holds and render the same (a few thousandths at most)."""
    import torch

    from narf_core.compositing import composite
    from narf_core.estimate import _object_rays
    from narf_core.sampling import Samples
    from narf_core.track import frame_band, occupied, visible

    T, theta, rays_cam, near, far = _box_rays_and_band(clamp, clamp_sequence, 2)
    with torch.no_grad():
        rays = _object_rays(rays_cam, T[None])
        every = occupied(clamp.grid, rays, frame_band(near, far, clamp.step), theta)
        seen = visible(clamp.field, rays, every, theta)
        outputs = ("rgb", "opacity", "depth")
        full = composite(clamp.field, rays, every, theta=theta, outputs=outputs)
        kept = composite(clamp.field, rays, seen, theta=theta, outputs=outputs)
    assert float(full.opacity.max()) > 0.99
    assert len(seen) < 0.8 * len(every)  # the samples behind the surface go
    assert set(seen.ray.tolist()) <= set(every.ray.tolist())
    for name in outputs:
        assert float((getattr(kept, name) - getattr(full, name)).abs().max()) < 5e-3, name
    empty = Samples(every.ray[:0], every.t[:0], every.delta[:0])
    assert len(visible(clamp.field, rays, empty, theta)) == 0


@pytest.mark.parametrize("field_kind", ["kplanes", "articulated"])
def test_a_frames_shifted_rows_render_as_each_row_alone(clamp, clamp_sequence: Path, field_kind: str) -> None:
    """A Jacobian by differences renders a frame's rays at several poses a sample spacing or so apart in one
    batch (``FrameProblem``, several rows, in two rounds from row 0's reach; with an articulated field only the
    band's samples near an occupied cell at row 0 are asked about): every row as the row's own band renders it
    alone (to a few thousandths: each row's samples light reaches, as
    test_visible_samples_render_what_every_sample_renders). A trial step's single row on the same rays goes in
    rounds from that reach too, and renders as it alone does."""
    import dataclasses

    import torch

    from narf_core.compositing import composite
    from narf_core.estimate import _object_rays
    from narf_core.fields import ArticulatedField
    from narf_core.geometry import se3_exp
    from narf_core.track import FrameProblem, TrackOptions, frame_band, occupied

    model = clamp
    if field_kind == "articulated":  # the field narf train builds for an object of several parts
        field = ArticulatedField.from_parts(clamp.kinematics, clamp.part_fields, clamp.part_grids, clamp.aabb)
        model = dataclasses.replace(clamp, field=field.eval().requires_grad_(False))
    T, theta, rays_cam, near, far = _box_rays_and_band(model, clamp_sequence, 2)
    field, grid = model._field_for("narf", theta)
    assert hasattr(grid, "occupied_near") is (field_kind == "articulated")
    problem = FrameProblem(model, TrackOptions().step_options(True), 0.1, True, near=near, far=far, field=field,
                           grid=grid, prune=True)
    problem.index = torch.arange(len(rays_cam))
    # about as far as a Jacobian's rows move the object (TrackOptions' differences: a hundredth of its radius and
    # of a radian about its centre), in its own frame
    shifts = [torch.zeros(6), torch.tensor([0.0, 0.0, 0.0015, 0, 0, 0]), torch.tensor([0.001, 0, 0, 0, 0.01, 0]),
              torch.tensor([0.0, -0.0015, 0.0, 0.01, 0, -0.01])]
    poses = torch.stack([T @ se3_exp(x.double()) for x in shifts])
    rays = _object_rays(rays_cam, poses)  # row-major: every row's n rays in turn
    n, rows, outputs = len(rays_cam), len(shifts), ("rgb", "opacity", "depth")

    def alone(pose):
        own = _object_rays(rays_cam, pose[None])
        out = composite(field, own, occupied(grid, own, frame_band(near, far, model.step), theta), theta=theta,
                        outputs=outputs)
        return torch.cat([out.rgb, out.opacity[:, None], out.depth[:, None]], -1)

    with torch.no_grad():
        batch = problem._render(rays, theta.expand(len(rays), -1), rows, n, outputs, None).reshape(rows, n, 5)
        assert problem.reach is not None and problem.reach[0] is problem.index
        for row in range(rows):
            P = alone(poses[row])
            assert float(P[:, 3].max()) > 0.99
            assert float((batch[row] - P).abs().max()) < 5e-3, row
        assert float((batch[1] - batch[0]).abs().max()) > 0.1  # the rows differ
        trial = se3_exp(torch.tensor([0.002, 0.001, -0.002, 0.02, 0.0, 0.01], dtype=torch.float64)) @ T
        single = problem._render(_object_rays(rays_cam, trial[None]), theta.expand(n, -1), 1, n, outputs, None)
        assert float((single - alone(trial)).abs().max()) < 5e-3


def test_first_frame_warm_and_sigma_scale(clamp, clamp_sequence: Path) -> None:
    """``first_frame = "warm"`` tracks the first frame from the given pose like any other (no
    multi-start); a warm-started frame's Σ is the refiner's times ``sigma_scale``² (RGB-D) or
    ``sigma_scale_rgb``² (RGB only), the estimate unchanged; the options are validated."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import FIRST_FRAMES, TrackFrame, TrackInputError, TrackOptions, TrackState, step, track
    from narf_core.track_io import load_frames, score, sequence_frames

    with pytest.raises(TrackInputError, match=r"options\.first_frame must be one of multi-start, warm"):
        TrackOptions(first_frame="label")
    for name in ("sigma_scale", "sigma_scale_rgb"):
        with pytest.raises(TrackInputError, match=rf"options\.{name} must be >= 0 \(0 = the model's own\)"):
            TrackOptions(**{name: -1.0})
    assert TrackOptions().first_frame == "multi-start" and FIRST_FRAMES == ("multi-start", "warm")
    dataset = Dataset.open(clamp_sequence)
    frames = sequence_frames(dataset)[:3]
    options = TrackOptions(first_frame="warm", iterations=3, rays_per_iteration=256, uncertainty_rays=64)
    results = list(track(clamp, load_frames(dataset, frames), dataset.camera, frames[0].T_cam_obj, frames[0].joints,
                         options))
    assert results[0].status == "tracking"  # (σ from 64 rays may pass the 2 cm limit on a later frame)
    assert all(r.status == "tracking" or (r.status, r.reason) == ("uncertain", "large covariance") for r in results)
    assert all(r.iterations == options.iterations for r in results)  # the first frame too: no multi-start
    assert all(score(clamp, f, r)["add_m"] < 0.01 for f, r in zip(frames, results))

    images = dataset.load(frames[1])
    for depth, field in ((images.depth, "sigma_scale"), (None, "sigma_scale_rgb")):
        observed = TrackFrame(images.rgb, images.labels > 0, frames[1].time, depth)
        answers = []
        for scale in (1.0, 2.0):
            state = TrackState.initial(clamp, frames[1].T_cam_obj, frames[1].joints, frames[0].time, status="tracking")
            answers.append(step(clamp, dataset.camera, observed, state, TrackOptions(
                iterations=2, rays_per_iteration=128, uncertainty_rays=64, **{field: scale}))[0])
        np.testing.assert_allclose(answers[1].T_cam_obj, answers[0].T_cam_obj)
        np.testing.assert_allclose(answers[1].covariance, 4 * answers[0].covariance)
        np.testing.assert_allclose(answers[1].uncertainty["position_sigma_m"],
                                   2 * np.asarray(answers[0].uncertainty["position_sigma_m"]))


def test_a_frame_with_depth_trusts_the_mask_as_its_options_say(clamp, clamp_sequence: Path, monkeypatch) -> None:
    """``refine_frame`` resolves ``mask_trust`` "auto" as ``refine`` does: in full under an exact mask, partially
    (with the preset's edge band) where the depth shows an occluder in front of what the mask leaves out. The
    tracker's own frames with depth pass :data:`~narf_core.track.DEPTH_MASK_TRUST`'s options (no band, the rays
    outside the mask at full weight but an occluder's): a hand over half the clamp, the mask its visible part,
    leaves that frame at the label, where the mask trusted in full (``occluder_test`` off) pulls the hidden end
    out from under the hand."""
    from dataclasses import replace

    from narf_core import estimate
    from narf_core.data.dataset import Dataset
    from narf_core.track import DEPTH_MASK_TRUST, TrackOptions, refine_frame
    from narf_core.track_io import score

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    mask = images.labels > 0
    cols = np.nonzero(mask.any(0))[0]
    hand = np.zeros_like(mask)
    hand[:, cols[int(0.5 * len(cols))]:] = True  # a hand over the last half of the clamp's columns
    occluded = images.depth.copy()
    occluded[hand & (occluded > 0)] = float(images.depth[mask].min()) - 0.05
    bands = []
    real = estimate._observation
    monkeypatch.setattr(estimate, "_observation", lambda *a: bands.append(a[-1]) or real(*a))
    options = TrackOptions(rays_per_iteration=256, uncertainty_rays=0)
    tracker, in_full = options.step_options(True), replace(options, occluder_test=False).step_options(True)
    assert (tracker.mask_trust, tracker.mask_band_px, tracker.outside_weight) == ("partial", 0, 1.0)
    assert DEPTH_MASK_TRUST["mask_trust"] == "partial" and in_full.mask_trust == "full"
    preset = estimate.EstimateOptions.gauss_newton()
    auto = replace(tracker, mask_trust="auto", mask_band_px=preset.mask_band_px, outside_weight=preset.outside_weight)
    assert auto.mask_band_px > 0
    cases = ((auto, mask, images.depth), (auto, mask & ~hand, occluded),
             (replace(auto, mask_trust="partial"), mask & ~hand, occluded), (tracker, mask & ~hand, occluded),
             (in_full, mask & ~hand, occluded))
    results = [refine_frame(clamp, dataset.camera, images.rgb, m, d, frame.T_cam_obj, frame.joints, o)
               for o, m, d in cases]
    assert bands == [0, auto.mask_band_px, auto.mask_band_px, 0, 0]
    np.testing.assert_allclose(results[1].T_cam_obj, results[2].T_cam_obj)  # "auto" there is "partial"
    add = [score(clamp, frame, r)["add_m"] for r in results[3:]]
    assert add[0] < 0.0002 < 0.0005 < add[1], add  # metres


def test_a_joint_whose_part_the_mask_leaves_out_has_its_prior_sigma(clamp, clamp_sequence: Path) -> None:
    """The jaw's pixels taken out of the mask (an occluder over it, a missed blob): the share of the jaw's surface
    points inside the mask falls under :data:`~narf_core.estimate.HIDDEN_SHARE` and the joint's σ grows by its
    half range, in a single image's Σ and a tracked frame's (where the tracker's factor on σ leaves that term
    as it is), with the ``unobserved_joint`` warning; with the whole mask the share is nearly one and neither."""
    from narf_core.data.dataset import Dataset
    from narf_core.estimate import HIDDEN_SHARE, UNOBSERVED_CODE, EstimateOptions, refine
    from narf_core.track import TrackFrame, TrackOptions, TrackState, step

    dataset = Dataset.open(clamp_sequence)
    frames = dataset.frames()
    images = dataset.load(frames[1])
    jaw = images.labels == dataset.links.index("moving_jaw") + 1
    assert jaw.sum() > 20
    whole = images.labels > 0
    half = float(clamp.kinematics.upper[0] - clamp.kinematics.lower[0]) / 2
    single = EstimateOptions.preset("gauss-newton", iterations=2, rays_per_iteration=128, uncertainty_rays=256)
    sigmas, warned = [], []
    for mask in (whole, whole & ~jaw):
        result = refine(clamp, images.rgb, mask, dataset.camera, frames[1].T_cam_obj, joints_init=frames[1].joints,
                        depth=images.depth, options=single)
        sigmas.append(result.uncertainty.joint_sigma["jaw_opening"])
        warned.append(any(w.startswith(f"{UNOBSERVED_CODE}: jaw_opening: the mask shows under {HIDDEN_SHARE:.0%} of the "
                                       "part it moves") for w in result.warnings))
        unseen = result.uncertainty.unseen_variance
        assert unseen[:6].tolist() == [0.0] * 6
        assert unseen[6] == (pytest.approx(half**2) if mask is not whole else 0.0)
    assert sigmas[0] < 0.2 * half and sigmas[1] >= half
    assert warned == [False, True]
    options = TrackOptions(iterations=1, rays_per_iteration=128, uncertainty_rays=256, sigma_scale=0.5)
    state = TrackState.initial(clamp, frames[0].T_cam_obj, frames[0].joints, frames[0].time, status="tracking")
    for mask, hidden in ((whole, False), (whole & ~jaw, True)):
        frame = TrackFrame(images.rgb, mask, float(frames[1].time), images.depth)
        answer = step(clamp, dataset.camera, frame, state, options)[0]
        sigma = answer.uncertainty["joint_sigma"]["jaw_opening"]
        assert (sigma >= half) == hidden, sigma  # the half range unscaled by the factor 0.5
        assert any(w.startswith(f"{UNOBSERVED_CODE}: jaw_opening") for w in answer.warnings) == hidden


def test_a_joint_the_mask_leaves_out_is_held_to_its_prediction(clamp, clamp_sequence: Path, monkeypatch) -> None:
    """A warm-started frame whose mask leaves the jaw out (an occluder over it, in front in the depth) holds the
    jaw to the prediction by ``hidden_joint_sigma`` (a share of its half range, through θ = mid + half sin u): the
    frame's prior takes that σ for the jaw, none where the whole mask shows it nor without depth. Held tightly (a
    thousandth) the jaw then ends within 0.2 mm of a prediction 3 mm off the label, where unheld (σ 0) or seen whole
    it moves back over a millimetre (the configuration field's other parts, still in view, tell something of it)."""
    import torch

    from narf_core import gauss_newton
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackOptions, _warm_refine

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    jaw = images.labels == dataset.links.index("moving_jaw") + 1
    for _ in range(8):  # and 8 pixels round it, so that the prediction's jaw lies under it too
        jaw = jaw | np.roll(jaw, 1, 0) | np.roll(jaw, -1, 0) | np.roll(jaw, 1, 1) | np.roll(jaw, -1, 1)
    whole = images.labels > 0
    occluded = images.depth.copy()
    occluded[jaw] = float(images.depth[whole].min()) - 0.05  # something in front of the jaw
    predicted = {"jaw_opening": frame.joints["jaw_opening"] + 0.003}
    held = []
    real = gauss_newton.GaussNewtonRun.hold_to
    monkeypatch.setattr(gauss_newton.GaussNewtonRun, "hold_to", lambda run, c, s: held.append(s) or real(run, c, s))
    options = TrackOptions(rays_per_iteration=256, uncertainty_rays=0)
    ends = {}
    for name, mask, depth, sigma in (("whole", whole, images.depth, 0.001), ("held", whole & ~jaw, occluded, 0.001),
                                     ("free", whole & ~jaw, occluded, 0.0), ("rgb", whole & ~jaw, None, 0.001)):
        result = _warm_refine(clamp, dataset.camera, images.rgb, mask, depth, frame.T_cam_obj, predicted,
                              TrackOptions(**{**options.__dict__, "hidden_joint_sigma": sigma}))
        ends[name] = abs(result.joints["jaw_opening"] - predicted["jaw_opening"])
    assert [bool(torch.isfinite(s[6:]).all()) for s in held] == [False, True, False, False]  # not without depth
    assert held[1][6] >= 0.001  # σ in u: 0.001 / cos u
    assert ends["held"] < 2e-4 < 1e-3 < min(ends["free"], ends["whole"]), ends


def test_model_error_footprint_is_never_finer_than_the_reference_box(clamp, clamp_sequence: Path, monkeypatch) -> None:
    """A mask box larger than the reference box (:data:`~narf_core.estimate.ROBUST_BOX_PX`: a finer camera)
    scales the pixel footprint of the model's error by the box's size over it, whatever the preset's own
    ``reference_box_px`` (which sets rays, not the model's error): the model is no more exact than the
    views it was fitted on."""
    from dataclasses import replace

    from narf_core import estimate
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackOptions, refine_frame

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    mask = images.labels > 0
    seen = []
    real = estimate.model_error
    monkeypatch.setattr(estimate, "model_error", lambda *a: seen.append(a[2]) or real(*a))
    base = TrackOptions(iterations=1, rays_per_iteration=64, uncertainty_rays=64).step_options(True)
    box = estimate._mask_box(mask, base.box_margin)
    side = max(box[2] - box[0], box[3] - box[1])
    assert side < estimate.ROBUST_BOX_PX  # this 160x120 view: the camera's own footprint
    for reference_box_px, robust_box_px in ((0, estimate.ROBUST_BOX_PX), (20, estimate.ROBUST_BOX_PX), (0, 20)):
        monkeypatch.setattr(estimate, "ROBUST_BOX_PX", robust_box_px)
        result = refine_frame(clamp, dataset.camera, images.rgb, mask, images.depth, frame.T_cam_obj, frame.joints,
                              replace(base, reference_box_px=reference_box_px))
        assert result.uncertainty is not None
    assert seen[1] == pytest.approx(seen[0], rel=0.05)  # (the estimates differ a little)
    assert seen[2] == pytest.approx(seen[0] * side / 20, rel=0.05)


def test_a_frame_with_depth_counts_the_model_error_in_training_pixels(clamp, clamp_sequence: Path, monkeypatch) -> None:
    """With depth a tracked frame's model error is counted in pixels no finer than the training views'
    (:func:`~narf_core.estimate.trained_footprint`; the bundled clamp records none: the reference camera's);
    without depth, and where the training views are no coarser than the camera, in the camera's own.
    The same whichever refiner runs the frame: ``refine`` (a model whose ``auto`` mode is ``parts``) as
    ``refine_frame``; a single-image estimate keeps the camera's own."""
    from dataclasses import replace

    from narf_core import estimate
    from narf_core.data.dataset import Dataset
    from narf_core.estimate import EstimateOptions, refine
    from narf_core.track import TrackOptions, refine_frame

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    mask = images.labels > 0
    assert "training_camera" not in clamp.metadata
    assert estimate.REFERENCE_TRAINING_FX == pytest.approx(float(dataset.camera.K[0, 0]))  # trained on such views
    seen = []
    real = estimate.model_error
    monkeypatch.setattr(estimate, "model_error", lambda *a: seen.append(a[2]) or real(*a))
    for coarser in (1.0, 4.0):
        monkeypatch.setattr(estimate, "REFERENCE_TRAINING_FX", float(dataset.camera.K[0, 0]) / coarser)
        for depth in (images.depth, None):
            options = TrackOptions(iterations=1, rays_per_iteration=64, uncertainty_rays=64).step_options(depth is not None)
            result = refine_frame(clamp, dataset.camera, images.rgb, mask, depth, frame.T_cam_obj, frame.joints, options)
            assert result.uncertainty is not None
    own = seen[0]
    assert seen[1] == pytest.approx(own, rel=0.05)  # without depth: the camera's own
    assert seen[2] == pytest.approx(4 * own, rel=0.05)  # with depth: the training views' pixel, 4x coarser
    assert seen[3] == pytest.approx(own, rel=0.05)
    seen.clear()
    options = TrackOptions(iterations=1, rays_per_iteration=64, uncertainty_rays=64).step_options(True)
    single = EstimateOptions.preset("gauss-newton", iterations=1, rays_per_iteration=64, uncertainty_rays=64)
    for opts in (replace(options, mode="parts"), single):
        result = refine(clamp, images.rgb, mask, dataset.camera, frame.T_cam_obj, joints_init=frame.joints,
                        depth=images.depth, options=opts)
        assert result.uncertainty is not None
    assert seen[0] == pytest.approx(4 * own, rel=0.05)  # the tracker's frame in parts mode, through refine
    assert seen[1] == pytest.approx(own, rel=0.05)  # one image, many iterations: the camera's own


def test_model_error_grows_only_above_the_usual_residual(clamp) -> None:
    """``usual`` (the tracker's ``usual_residual`` with depth): a colour residual up to it gives the
    model's error at its reference (pixel footprints alone), above it the error grows in proportion;
    0 leaves the calibration's own reference and scaling."""
    from narf_core.estimate import MODEL_ERROR, EstimateInputError, EstimateOptions, model_error

    at_usual = model_error(clamp, "shape", 0.004, 0.1, 0.03, usual=0.03)
    assert float(at_usual[0]) == pytest.approx(MODEL_ERROR["pixels"]["shape"] * 0.004)
    for below in (0.0, 0.001, 0.02):
        assert _close(model_error(clamp, "shape", 0.004, 0.1, below, usual=0.03), at_usual)
    assert _close(model_error(clamp, "shape", 0.004, 0.1, 0.09, usual=0.03), 3 * at_usual)
    reference = MODEL_ERROR["reference_variance"]
    assert _close(model_error(clamp, "shape", 0.004, 0.1, 0.5 * reference), 0.5 * at_usual)  # (usual 0)
    with pytest.raises(EstimateInputError, match=r"options\.uncertainty_usual_residual must be >= 0"):
        EstimateOptions(uncertainty_usual_residual=-1.0)


def test_model_error_grows_with_the_square_of_a_silhouette_misfit_above_the_usual(clamp) -> None:
    """``usual_silhouette`` (the tracker's ``usual_silhouette`` with depth): a silhouette misfit up to it
    leaves the model's error as the colour residual gives it; above it the error grows with the
    misfit's ratio to it squared, unless the colour's growth is the larger; 0 turns it off."""
    from narf_core.estimate import SILHOUETTE_EXPONENT, EstimateInputError, EstimateOptions, model_error

    at_usual = model_error(clamp, "shape", 0.004, 0.1, 0.03, usual=0.03)
    for misfit in (0.0, 0.02, 0.05):
        assert _close(model_error(clamp, "shape", 0.004, 0.1, 0.03, 0.03, misfit, 0.05), at_usual)
    assert _close(model_error(clamp, "shape", 0.004, 0.1, 0.03, 0.03, 0.1, 0.05), 2**SILHOUETTE_EXPONENT * at_usual)
    assert _close(model_error(clamp, "shape", 0.004, 0.1, 0.3, 0.03, 0.1, 0.05), 10 * at_usual)  # colour's 10x wins
    assert _close(model_error(clamp, "shape", 0.004, 0.1, 0.03, 0.03, 0.5, 0.0), at_usual)  # off
    assert _close(model_error(clamp, "shape", 0.004, 0.1, 0.03, 0.03, float("nan"), 0.05), at_usual)
    with pytest.raises(EstimateInputError, match=r"options\.uncertainty_usual_silhouette must be >= 0"):
        EstimateOptions(uncertainty_usual_silhouette=-0.1)


def _close(a, b) -> bool:
    return bool(np.allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=0))


def test_depth_frame_sigma_is_in_pixel_footprints_below_the_usual_residual(clamp, clamp_sequence: Path) -> None:
    """With depth a warm-started frame's position σ is its ``sigma_scale`` times the model's error in
    pixel footprints at the object (its colour residual is below ``usual_residual`` on the clamp's
    own render at ALIASED_USUAL_RESIDUAL, over the fixture's aliased frames') plus the small
    statistical part, and no smaller on a darkened image (a larger residual); without depth the refiner's
    Σ follows the residual from the calibration's reference, and grows on the darkened image."""
    from narf_core.data.dataset import Dataset
    from narf_core.estimate import _error_class, model_error
    from narf_core.track import TrackFrame, TrackInputError, TrackOptions, TrackState, sigma_scale, step

    with pytest.raises(TrackInputError, match=r"options\.usual_residual must be >= 0"):
        TrackOptions(usual_residual=-0.1)
    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    options = TrackOptions(iterations=2, rays_per_iteration=128, uncertainty_rays=64,
                           usual_residual=ALIASED_USUAL_RESIDUAL)
    assert options.step_options(True).uncertainty_usual_residual == options.usual_residual > 0
    assert options.step_options(False).uncertainty_usual_residual == 0
    sigmas = {}
    for depth in (images.depth, None):
        for gain in (1.0, 0.5):
            image = (images.rgb * gain).astype(np.uint8)
            state = TrackState.initial(clamp, frame.T_cam_obj, frame.joints, frame.time - 1 / 30, status="tracking")
            result = step(clamp, dataset.camera, TrackFrame(image, images.labels > 0, frame.time, depth), state, options)[0]
            sigmas[depth is None, gain] = np.asarray(result.uncertainty["position_sigma_m"])
            if depth is not None and gain == 1.0:
                aabb = clamp.aabb.double().numpy()
                centre_depth = float(result.T_cam_obj[2, :3] @ ((aabb[0] + aabb[1]) / 2) + result.T_cam_obj[2, 3])
                pixel = centre_depth / float(dataset.camera.K[0, 0])
                kind = _error_class(options.step_options(True), True)
                expected = sigma_scale(clamp, options, True) * float(model_error(clamp, kind, pixel, 1.0, 0.0, usual=1.0)[0])
                assert expected <= sigmas[False, 1.0].min() and sigmas[False, 1.0].max() <= 1.3 * expected
    assert sigmas[False, 0.5].min() >= 0.95 * sigmas[False, 1.0].min()
    assert (sigmas[True, 0.5] > 1.5 * sigmas[True, 1.0]).all()  # RGB only: the colour residual scales σ
    assert sigmas[True, 1.0][2] > 1.5 * sigmas[True, 1.0][:2].max()  # and the distance is the least certain


def test_depth_frame_sigma_grows_where_the_mask_disagrees_with_the_outline(clamp, clamp_sequence: Path) -> None:
    """With depth, a mask with a segmenter's extra blob beside the tool over a dark patch (the colours
    barely see it: the render's background is dark too, but the outline misfits the mask by more than
    ``usual_silhouette``) widens the frame's σ by the misfit's ratio squared; the exact mask (a misfit
    below it) leaves σ as it is without the rule, and 0 turns the rule off."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import RETRY_SIGMA_SCALE, TrackFrame, TrackInputError, TrackOptions, TrackState, sigma_scale, step

    with pytest.raises(TrackInputError, match=r"options\.usual_silhouette must be >= 0"):
        TrackOptions(usual_silhouette=-0.1)
    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    exact = images.labels > 0
    rows, cols = np.nonzero(exact)
    blob = exact.copy()
    height, width = rows.max() - rows.min() + 1, cols.max() - cols.min() + 1
    blob[rows.min():rows.min() + height // 2, cols.max() + 1:cols.max() + 1 + width // 3] = True
    image = images.rgb.copy()
    image[blob & ~exact] = 0
    sigma = {}
    for name, mask in (("exact", exact), ("blob", blob)):
        for usual in (0.02, 0.0):
            options = TrackOptions(iterations=2, rays_per_iteration=128, uncertainty_rays=256, usual_silhouette=usual,
                                   retry_uncertain=False, usual_residual=ALIASED_USUAL_RESIDUAL)
            state = TrackState.initial(clamp, frame.T_cam_obj, frame.joints, frame.time - 1 / 30, status="tracking")
            result = step(clamp, dataset.camera, TrackFrame(image, mask, frame.time, images.depth), state, options)[0]
            sigma[name, usual] = np.asarray(result.uncertainty["position_sigma_m"])
    assert np.allclose(sigma["exact", 0.02], sigma["exact", 0.0], rtol=1e-9)
    assert (sigma["blob", 0.02] > 2 * sigma["blob", 0.0]).all()
    assert np.allclose(sigma["blob", 0.0], sigma["exact", 0.0], rtol=0.5)  # the colours alone hardly see the blob
    # The second round (retry_uncertain) judges the colours' growth alone: a limit between the blob frame's σ
    # without the silhouette's growth and with it (at the retry's own factor) starts no second round.
    own = sigma_scale(clamp, TrackOptions(), True, dataset.camera)
    limit = 2.5 * float(sigma["blob", 0.0].max()) * RETRY_SIGMA_SCALE["gauss-newton"] / own
    assert float(sigma["blob", 0.02].min()) * RETRY_SIGMA_SCALE["gauss-newton"] / own > limit
    options = TrackOptions(iterations=2, rays_per_iteration=128, uncertainty_rays=256, max_position_sigma_m=limit,
                           usual_residual=ALIASED_USUAL_RESIDUAL)
    state = TrackState.initial(clamp, frame.T_cam_obj, frame.joints, frame.time - 1 / 30, status="tracking")
    assert step(clamp, dataset.camera, TrackFrame(image, blob, frame.time, images.depth), state, options)[0].iterations == 2


def test_a_frame_whose_sigma_passes_the_limits_gets_a_second_round(clamp, clamp_sequence: Path) -> None:
    """With depth, a warm-started frame whose Σ passes the limits (``max_position_sigma_m``, here
    set below any σ) runs its iterations twice, the second round from where the first ended, and
    ends closer to the truth than one round from a start 1.5 cm off; never without depth, nor with
    ``retry_uncertain`` off. The fit to the depth's points is off: the rounds are what is compared (from 1.5 cm
    along the bar three of its iterations leave 1.3 cm, and the rounds after them end within a millimetre of
    each other)."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackFrame, TrackOptions, TrackState, step
    from narf_core.track_io import score

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    T_off = np.array(frame.T_cam_obj, dtype=np.float64)
    T_off[:3, 3] += np.array([0.015, 0.0, 0.0])  # across the line of sight: no depth alignment catches it
    fast = dict(solver="adam", iterations=3, rays_per_iteration=256, uncertainty_rays=64, max_position_sigma_m=1e-6,
                surface_fit_iterations=0)
    runs = {}
    for depth in (images.depth, None):
        for retry in (True, False):
            state = TrackState.initial(clamp, T_off, frame.joints, frame.time - 1 / 30, status="tracking")
            result = step(clamp, dataset.camera, TrackFrame(images.rgb, images.labels > 0, frame.time, depth), state,
                          TrackOptions(retry_uncertain=retry, **fast))[0]
            runs[depth is None, retry] = (result.iterations, score(clamp, frame, result)["add_m"])
    assert runs[False, True][0] == 6 and runs[False, False][0] == 3
    assert runs[True, True][0] == runs[True, False][0] == 3
    assert runs[False, True][1] < runs[False, False][1]


def test_frame_and_iteration_marching_give_the_same_step(clamp, clamp_sequence: Path) -> None:
    """A warm-started Adam step without marching (march "frame") lands where the refiner that marches
    every iteration lands: the same rays, the same loss, renders equal up to the march's early stop.
    Both start from the prediction itself (the move onto the depth and the fit to its points before either,
    the same for both, are tested on their own: below and in tests/test_surface_fit.py)."""
    from narf_core.data.dataset import Dataset
    from narf_core.geometry import se3_exp
    from narf_core.track import TrackOptions, TrackState, step
    from narf_core.track_io import sequence_frames

    dataset = Dataset.open(clamp_sequence)
    frames = sequence_frames(dataset)
    import torch

    off = se3_exp(torch.tensor([0.004, -0.003, 0.005, 0.02, -0.01, 0.015], dtype=torch.float64)).numpy()
    for i in (2, 5):
        observed = _frames(dataset, frames[i:i + 1])[0]
        answers = []
        for march in ("frame", "iteration"):
            state = TrackState.initial(clamp, off @ frames[i].T_cam_obj, frames[i].joints, frames[i - 1].time,
                                       status="tracking")
            options = TrackOptions(march=march, solver="adam", depth_align=False, retry_uncertain=False,
                                   surface_fit_iterations=0)  # one round
            result, _ = step(clamp, dataset.camera, observed, state, options)
            assert result.status in ("tracking", "uncertain") and result.uncertainty is not None
            answers.append(result)
        assert np.abs(answers[0].T_cam_obj - answers[1].T_cam_obj).max() < 5e-4
        assert abs(answers[0].joints["jaw_opening"] - answers[1].joints["jaw_opening"]) < 5e-4
        assert answers[0].loss == pytest.approx(answers[1].loss, rel=0.02)
        s0, s1 = (np.sqrt(np.diag(r.covariance)) for r in answers)
        np.testing.assert_allclose(s0, s1, rtol=0.1)


def test_distance_prior_holds_the_line_of_sight_distance(clamp, clamp_sequence: Path) -> None:
    """Without depth, Adam's prior holds the box centre's distance along the line of sight to the
    prediction's, and leaves the other directions to the image."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackOptions, _centre, refine_frame

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[4]
    images = dataset.load(frame)
    truth = np.asarray(frame.T_cam_obj)
    centre = truth[:3, :3] @ _centre(clamp) + truth[:3, 3]
    view = centre / np.linalg.norm(centre)
    predicted = truth.copy()
    predicted[:3, 3] += 0.01 * view + 0.004 * np.cross(view, [0.0, 1.0, 0.0])  # 1 cm too far, 4 mm aside
    options = TrackOptions(solver="adam").step_options(False)
    moved = {}
    for weight in (0.0, 1e4):
        result = refine_frame(clamp, dataset.camera, images.rgb, images.labels > 0, None, predicted, frame.joints,
                              options, weight)
        shift = (result.T_cam_obj[:3, :3] @ _centre(clamp) + result.T_cam_obj[:3, 3]) - (centre + predicted[:3, 3]
                                                                                        - truth[:3, 3])
        moved[weight] = (abs(float(shift @ view)), float(np.linalg.norm(shift - (shift @ view) * view)))
    assert moved[1e4][0] < 0.001 < moved[0.0][0]  # held along the line of sight ...
    assert moved[1e4][1] > 0.002  # ... while the image still moves it sideways


def test_depth_aligned_closes_the_gap_along_the_line_of_sight(clamp, clamp_sequence: Path) -> None:
    """A prediction 1 cm too far (and 3 mm aside) is moved back along the line of sight to the box
    centre by the observed depth, nothing sideways; without a usable depth it stays where it was."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import _centre, depth_aligned, depth_offset

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[3]
    images = dataset.load(frame)
    mask, depth = images.labels > 0, images.depth
    truth = np.asarray(frame.T_cam_obj)
    centre = truth[:3, :3] @ _centre(clamp) + truth[:3, 3]
    view = centre / np.linalg.norm(centre)
    aside = 0.003 * np.cross(view, [0.0, 1.0, 0.0])
    for along in (0.01, -0.01):
        predicted = truth.copy()
        predicted[:3, 3] += along * view + aside
        offset = depth_offset(clamp, dataset.camera, predicted, frame.joints, mask, depth)
        assert offset is not None and np.sign(offset) == -np.sign(along)
        moved = depth_aligned(clamp, dataset.camera, predicted, frame.joints, mask, depth)
        error = (moved[:3, 3] - truth[:3, 3]) - aside
        assert abs(float(error @ view)) < 0.002  # the centimetre closed ...
        assert np.linalg.norm(error - (error @ view) * view) < 5e-4  # ... along the line of sight only
        np.testing.assert_array_equal(moved[:3, :3], predicted[:3, :3])
    for unusable in (np.full_like(depth, np.nan), np.zeros_like(depth)):  # no return anywhere
        assert depth_offset(clamp, dataset.camera, predicted, frame.joints, mask, unusable) is None
        np.testing.assert_array_equal(depth_aligned(clamp, dataset.camera, predicted, frame.joints, mask, unusable),
                                      predicted)
    behind = truth.copy()
    behind[:3, 3] *= -1  # the object behind the camera: nothing to compare, nothing moved
    np.testing.assert_array_equal(depth_aligned(clamp, dataset.camera, behind, frame.joints, mask, depth), behind)


def test_depth_offset_of_a_deep_object_counts_the_surface_the_camera_sees(tmp_path: Path) -> None:
    """The cabinet at its true poses: the observed depth lies on the model's surface (offset 0). Its
    500 surface points per part leave most cells with only a point of its far side or of a drawer
    inside, centimetres behind; counted, they put it 2-3 cm nearer than it is."""
    pytest.importorskip("pybullet")
    from types import SimpleNamespace

    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.sequence import synthesize_sequence
    from narf_core.kinematics import KinematicTree
    from narf_core.track import depth_offset

    out = synthesize_sequence("cabinet", tmp_path / "seq", 4, size=(80, 60), events=False, supersample=1)
    dataset = Dataset.open(out)
    kinematics = KinematicTree.from_urdf(out / "object.urdf")
    # depth_offset reads only the kinematics and the surface points (no field): the bundle's own
    model = SimpleNamespace(kinematics=kinematics, links=list(dataset.links), sample_points=kinematics.sample_points())
    for frame in dataset.frames():
        images = dataset.load(frame)
        offset = depth_offset(model, dataset.camera, np.asarray(frame.T_cam_obj), frame.joints, images.labels > 0,
                              images.depth)
        assert offset is not None and abs(offset) < 0.003


def test_front_cells_keep_a_sloped_surface_and_drop_what_lies_behind_it() -> None:
    """A plane at 45° across the grid is seen everywhere; a cell 4 cm behind its neighbours is not."""
    from narf_core.track import _front_cells

    cell_angle = 0.01  # rad: 1 cm per cell at 1 m
    slope = 1.0 + cell_angle * np.arange(12)[None, :].repeat(8, axis=0)  # z rising a cell's width per cell
    assert _front_cells(slope, cell_angle).all()
    hidden = slope.copy()
    hidden[4, 6] += 0.04
    hidden[0, 0] = np.inf  # no point there: nothing to compare, and it hides nothing
    front = _front_cells(hidden, cell_angle)
    assert not front[4, 6] and front.sum() == hidden.size - 1


def test_tracker_aligns_the_prediction_to_the_depth(clamp, clamp_sequence: Path) -> None:
    """From a state 1.5 cm too far along the line of sight, one RGB-D frame lands within millimetres
    with ``depth_align`` (the default); without it, a frame whose Jacobian is the field's derivatives stays
    about a centimetre off (they see the depth's change along a ray only between two samples), one by
    differences (the default) lands within millimetres too: within 3 mm taken at every iteration, within 5 with
    the frame's first kept (``jacobian_once``, the default; from a centimetre and a half off the chord's steps
    come up shorter). The fit to the depth's points (on by default) is off here: it closes that gap as well
    (tests/test_surface_fit.py)."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackInputError, TrackOptions, TrackState, _centre, step

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[3]
    observed = _frames(dataset, [frame], False)[0]
    truth = np.asarray(frame.T_cam_obj)
    centre = truth[:3, :3] @ _centre(clamp) + truth[:3, 3]
    view = centre / np.linalg.norm(centre)
    start = truth.copy()
    start[:3, 3] += 0.015 * view
    along = {}
    for align, jacobian, once in ((True, "differences", True), (True, "derivatives", False),
                                  (False, "differences", False), (False, "derivatives", False),
                                  (False, "differences", True)):
        state = TrackState.initial(clamp, start, frame.joints, observed.time - 1 / 30, status="tracking")
        options = TrackOptions(depth_align=align, uncertainty_rays=0, jacobian=jacobian, jacobian_once=once,
                               surface_fit_iterations=0)
        result, _ = step(clamp, dataset.camera, observed, state, options)
        assert result.status == "tracking"
        centre_now = result.T_cam_obj[:3, :3] @ _centre(clamp) + result.T_cam_obj[:3, 3]
        along[align, jacobian, once] = abs(float((centre_now - centre) @ view))
    assert TrackOptions().jacobian == "differences" and TrackOptions().jacobian_once
    assert along[True, "differences", True] < 0.003 and along[True, "derivatives", False] < 0.003, along
    assert along[False, "differences", False] < 0.003 and along[False, "derivatives", False] > 0.008, along
    assert along[False, "differences", True] < 0.005, along
    with pytest.raises(TrackInputError, match=r"options\.depth_align"):
        TrackOptions(depth_align="yes")


def test_band_renders_what_the_whole_box_renders(clamp, clamp_sequence: Path) -> None:
    """Marching only the band around the surface points (and no ray that none projects near) gives the
    full march's image of the clamp's box, from fewer live rays; a pose half behind the camera gets no band."""
    import torch

    from narf_core.band import ray_band
    from narf_core.data.dataset import Dataset
    from narf_core.estimate import _object_rays
    from narf_core.geometry import se3_exp
    from narf_core.render import box_pixels

    dataset = Dataset.open(clamp_sequence)
    camera = dataset.camera
    frame = dataset.frames()[3]
    moved = se3_exp(torch.tensor([0.01, -0.01, 0.02, 0.1, -0.2, 0.1], dtype=torch.float64)) @ torch.tensor(frame.T_cam_obj)
    for T, theta in ((torch.tensor(frame.T_cam_obj), clamp.kinematics.joint_vector(frame.joints)),
                     (moved, clamp.kinematics.joint_vector({"jaw_opening": clamp.joints[0].upper}))):
        rays_cam = camera.rays(box_pixels(camera, T.float(), clamp.aabb))
        rays = _object_rays(rays_cam, T[None])
        near, far = ray_band(clamp, camera, rays_cam, T[None], theta[None], 0.01)
        outputs = ("rgb", "opacity", "depth")
        with torch.no_grad():
            full = clamp.render_rays(rays, theta.float(), outputs=outputs)
            band = clamp.render_rays(rays, theta.float(), outputs=outputs, t_range=(near, far))
        culled = far <= near
        assert culled.float().mean() > 0.3  # most of the box's rays are never marched
        assert float(full.opacity[culled].max()) < 0.5 and float(full.opacity[~culled].max()) > 0.99
        assert float((band.opacity - full.opacity).abs().mean()) < 1e-3
        assert float(((band.opacity - full.opacity).abs() > 0.05).float().mean()) < 2e-3
        assert float((band.rgb - full.rgb).abs().mean()) < 1e-3
    behind = torch.tensor(frame.T_cam_obj)
    behind[2, 3] = 0.0  # the camera inside the object: no band can be trusted
    assert ray_band(clamp, camera, camera.rays(torch.zeros(4, 2)), behind[None], theta[None], 0.01) is None


@pytest.mark.parametrize("preset, mode", [("robust", "narf"), ("robust", "parts"), ("gauss-newton", "narf")])
def test_refine_with_the_band_on_several_starts(clamp, clamp_sequence: Path, preset: str, mode: str) -> None:
    """The band goes with every start's rays (one batch in narf mode, one call per start in parts
    mode, the Gauss-Newton residuals): a short multi-start refine from the label stays near it."""
    from narf_core.data.dataset import Dataset
    from narf_core.estimate import EstimateOptions, refine
    from narf_core.track_io import score

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[2]
    images = dataset.load(frame)
    options = EstimateOptions.preset(preset, band_m=0.01, iterations=4, theta_starts=2, mode=mode,
                                     rays_per_iteration=256, uncertainty=False)
    result = refine(clamp, images.rgb, images.labels > 0, dataset.camera, frame.T_cam_obj,
                    joints_init=frame.joints, depth=images.depth, options=options)
    assert result.status in ("max_iterations", "converged") and result.loss is not None and np.isfinite(result.loss)
    assert score(clamp, frame, result)["add_m"] < 0.01


def test_track_with_the_band_follows_the_clamp(clamp, clamp_sequence: Path) -> None:
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackOptions, TrackState, step
    from narf_core.track_io import score, sequence_frames

    dataset = Dataset.open(clamp_sequence)
    frames = sequence_frames(dataset)[:5]
    options = TrackOptions(band_m=0.01, uncertainty_rays=0)
    state = TrackState.initial(clamp, frames[0].T_cam_obj, frames[0].joints, frames[0].time, status="tracking")
    errors = []
    for frame, observed in zip(frames, _frames(dataset, frames)):
        result, state = step(clamp, dataset.camera, observed, state, options)
        assert result.status == "tracking"
        errors.append(score(clamp, frame, result)["add_m"])
    assert np.mean(errors) < 0.006 and max(errors) < 0.01


def test_overlap_separates_right_from_wrong(clamp, clamp_sequence: Path) -> None:
    """The surface points' overlap with the mask: near one at the label, low when moved 8 cm or half the mask is
    gone; with depth, the points off the mask that a reading stands in front of (an occluder's) are left out of
    ``inside``, and a pose behind the observed surface scores as without depth."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import overlap

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[0]
    mask = dataset.load(frame).labels > 0
    assert overlap(clamp, dataset.camera, mask, frame.T_cam_obj, frame.joints) > 0.9
    moved = frame.T_cam_obj.copy()
    moved[0, 3] += 0.08
    assert overlap(clamp, dataset.camera, mask, moved, frame.joints) < 0.5
    half = mask.copy()
    half[:, : int(np.median(np.nonzero(mask)[1]))] = False  # an occluder over the left half of the object
    assert overlap(clamp, dataset.camera, half, frame.T_cam_obj, frame.joints) < 0.75
    # with depth, the points the occluder stands in front of are left out: the label explains what is seen
    depth = dataset.load(frame).depth.copy()
    occluder = mask & ~half
    depth[occluder] = float(depth[mask].min()) - 0.05
    assert overlap(clamp, dataset.camera, half, frame.T_cam_obj, frame.joints, depth) > 0.9
    assert overlap(clamp, dataset.camera, mask, frame.T_cam_obj, frame.joints, dataset.load(frame).depth) > 0.9
    assert overlap(clamp, dataset.camera, half, moved, frame.joints, depth) < 0.5  # a wrong pose stays wrong
    # a pose behind the observed surface: its points on the mask count as before, it is no occluder's
    back = frame.T_cam_obj.copy()
    back[:3, 3] *= 1.05
    true_depth = dataset.load(frame).depth
    assert overlap(clamp, dataset.camera, mask, back, frame.joints, true_depth) == pytest.approx(
        overlap(clamp, dataset.camera, mask, back, frame.joints))


@pytest.mark.slow
def test_narf_track_cli_rows_and_gif(tmp_path: Path, clamp_sequence: Path, capsys) -> None:
    gif = tmp_path / "overlay.gif"
    code = narf(["--threads", "1", "track", str(CLAMP), str(clamp_sequence), "--init-pose", "label", "--limit", "4",
                 "--iterations", "4", "--video", str(gif), "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["frame"] for r in out["frames"]] == [0, 1, 2, 3]
    assert all(r["status"] != "lost" and r["add_m"] < 0.02 for r in out["frames"])
    assert out["summary"]["frames"] == 4 and out["summary"]["video"] == str(gif)
    from PIL import Image

    with Image.open(gif) as im:
        assert im.n_frames == 4 and im.size == (160, 120)


def test_narf_track_cli_errors(tmp_path: Path, clamp_sequence: Path, capsys) -> None:
    assert narf(["track", str(CLAMP), str(clamp_sequence), "--init-pose", "{\"matrix\": [[1]]}"]) == 2
    assert "narf track: error: --init-pose" in capsys.readouterr().err
    assert narf(["track", str(CLAMP), str(clamp_sequence), "--init-pose", "label", "--video", str(tmp_path / "a.mp4")]) == 2
    assert "only .gif" in capsys.readouterr().err
    assert narf(["track", str(CLAMP), str(clamp_sequence), "--init-pose", "label", "--outside-weight-rgb", "1.5"]) == 2
    err = capsys.readouterr().err
    assert "narf track: error: --outside-weight-rgb must be in [0, 1]" in err and len(err.strip().splitlines()) == 1
    bench = ["bench", "track", "--work", str(tmp_path / "bench"), "--models", str(CLAMP.parent), "--tools", "clamp"]
    assert narf([*bench, "--outside-weight-rgb", "2"]) == 2  # the bench's flag too, not the core's option name
    assert capsys.readouterr().err.strip() == ("narf bench: error: --outside-weight-rgb must be in [0, 1] "
                                               "(1 = the mask trusted in full), got 2.0")
    # frames out of order in the sequence itself
    import shutil

    copy = tmp_path / "shuffled"
    shutil.copytree(clamp_sequence, copy)
    scene = json.loads((copy / "scene.json").read_text())
    scene["frames"][3]["time"] = 0.0
    (copy / "scene.json").write_text(json.dumps(scene))
    assert narf(["track", str(CLAMP), str(copy), "--init-pose", "label"]) == 2
    assert "is not after frame" in capsys.readouterr().err


def test_ros_node_covariance_is_about_the_pose_origin() -> None:
    """The example node's conversion of Σ (about the box centre) to PoseWithCovariance (about the origin)."""
    import importlib.util

    from narf_client import Pose

    spec = importlib.util.spec_from_file_location("ros2_node_track", ROOT / "examples" / "ros2_node.py")
    node = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(node)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(7, 7))
    cov = A @ A.T * 1e-4
    T = np.eye(4)
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T[:3, :3] = Q if np.linalg.det(Q) > 0 else -Q
    T[:3, 3] = [0.1, -0.05, 0.6]
    centre = np.array([0.08, -0.05, 0.0])
    ros_cov = np.array(node.covariance_to_ros(cov, Pose(T), centre)).reshape(6, 6)
    # the same map by finite differences: move the centre by dc and turn by dw about it
    import torch

    from narf_core.geometry import so3_exp

    def origin(delta):
        R = so3_exp(torch.from_numpy(delta[3:])).numpy() @ T[:3, :3]
        c = T[:3, :3] @ centre + T[:3, 3] + delta[:3]
        return np.concatenate([c - R @ centre, delta[3:]])

    eps = 1e-6
    J = np.stack([(origin(eps * e) - origin(-eps * e)) / (2 * eps) for e in np.eye(6)], axis=1)
    np.testing.assert_allclose(ros_cov, J @ cov[:6, :6] @ J.T, atol=1e-9)
    assert node.stamp_seconds(type("T", (), {"sec": 3, "nanosec": 500_000_000})()) == 3.5


def test_concurrent_tracking_steps_with_covariance(clamp, clamp_sequence: Path) -> None:
    """The service runs frames of different tracks on several worker threads at once; the covariance's
    forward-mode Jacobian must not trip over another thread's (forward AD levels are process-wide)."""
    import threading

    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackFrame, TrackOptions, TrackState, step

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[0]
    images = dataset.load(frame)
    options = TrackOptions(iterations=2, rays_per_iteration=64, uncertainty_rays=64)
    failures, covariances = [], []

    def worker() -> None:
        try:
            for k in range(3):
                state = TrackState.initial(clamp, frame.T_cam_obj, frame.joints, 0.0, status="tracking")
                result, _ = step(clamp, dataset.camera, TrackFrame(images.rgb, images.labels > 0, 0.0, images.depth),
                                 state, options)
                covariances.append(result.covariance)
        except Exception as e:  # noqa: BLE001 - collected for the assertion
            failures.append(repr(e))

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert failures == [] and len(covariances) == 12 and all(c is not None for c in covariances)


def test_bench_track_can_leave_the_depth_alignment_off() -> None:
    """``narf bench track --no-depth-align`` runs the tracker without it (to compare), and its table says so; the
    same for ``--outside-weight-rgb``, ``--no-occluder-test`` and ``--hidden-joint-sigma``."""
    from narf_benchmarks.track import markdown
    from narf_core.cli import build_parser
    from narf_core.track import TrackOptions

    assert build_parser().parse_args(["bench", "track"]).depth_align is True
    assert build_parser().parse_args(["bench", "track", "--no-depth-align"]).depth_align is False
    for align in (True, False):
        table = markdown({"frames": 3, "runs": [], "options": TrackOptions(first_frame="warm", depth_align=align).__dict__})
        assert ("not aligned to the depth" in table) is not align
    # and --outside-weight-rgb: the frames without depth trusting the mask partially, said in the table
    assert build_parser().parse_args(["bench", "track", "--outside-weight-rgb", "0.3"]).outside_weight_rgb == 0.3
    for weight in (1.0, 0.3):
        table = markdown({"frames": 3, "runs": [], "options": TrackOptions(outside_weight_rgb=weight).__dict__})
        assert ("outside the mask weighing 0.3" in table) is (weight < 1)
    # and --no-occluder-test: with depth the mask trusted in full, said in the table
    assert build_parser().parse_args(["bench", "track"]).occluder_test is None
    assert build_parser().parse_args(["bench", "track", "--no-occluder-test"]).occluder_test is False
    for test in (True, False):
        table = markdown({"frames": 3, "runs": [], "options": TrackOptions(occluder_test=test).__dict__})
        assert ("no occluder test" in table) is not test
    # and --hidden-joint-sigma: a joint the mask hides held otherwise than by default, or not at all
    assert build_parser().parse_args(["bench", "track", "--hidden-joint-sigma", "0"]).hidden_joint_sigma == 0.0
    for sigma, said in ((TrackOptions.hidden_joint_sigma, None), (0.0, "not held"), (0.05, "held by 0.05")):
        table = markdown({"frames": 3, "runs": [], "options": TrackOptions(hidden_joint_sigma=sigma).__dict__})
        assert ("the mask hides" in table) is (said is not None) and (said is None or said in table)


def test_bench_track_takes_the_frames_jacobian() -> None:
    """``narf bench track --jacobian`` sets a Gauss-Newton frame's Jacobian with depth and without (to compare),
    and the table names it; the CLI offers the refiner's choices and names the tracker's defaults (without
    importing torch for ``--help``)."""
    from narf_benchmarks.track import markdown
    from narf_core import cli
    from narf_core.estimate import JACOBIANS
    from narf_core.track import TrackInputError, TrackOptions, jacobian_text

    assert cli.JACOBIANS == JACOBIANS and cli.TRACK_JACOBIAN == jacobian_text()
    assert _bench_track_args(["--jacobian", "derivatives"]).jacobian == "derivatives"
    assert _bench_track_args([]).jacobian is None  # the tracker's own
    assert _bench_track_args([]).jacobian_once is None  # the tracker's own: once a frame with depth
    assert _bench_track_args(["--jacobian-every-iteration"]).jacobian_once is False
    for jacobian in JACOBIANS:
        for once in (True, False):
            options = TrackOptions(jacobian=jacobian, jacobian_rgb=jacobian, jacobian_once=once)
            per_frame = {m: {"solver": "gauss-newton", "iterations": 2, "rays_per_iteration": 768,
                             "jacobian": (step := options.step_options(m == "rgbd")).jacobian,
                             "jacobian_once": step.jacobian_once} for m in ("rgbd", "rgb")}
            table = markdown({"frames": 3, "runs": [], "options": options.__dict__, "per_frame": per_frame})
            assert table.count(f"(Jacobian by {jacobian}, once a frame)") == int(once)  # with depth
            assert table.count(f"(Jacobian by {jacobian})") == 2 - int(once)
    with pytest.raises(TrackInputError, match="jacobian_rgb"):
        TrackOptions(jacobian_rgb="secant")


def test_a_frame_without_depth_takes_the_jacobian_its_models_calibration_chose(clamp, capsys) -> None:
    """``TrackOptions.jacobian_rgb`` "auto" (the default) takes the Jacobian the model's tracker calibration chose
    without depth (``uncertainty.track.jacobians``), else the derivatives; a set one overrides it, and the frames
    with depth keep ``jacobian``. A factor fitted with another Jacobian than the frame's is not the model's own."""
    import copy

    from narf_benchmarks.track import markdown
    from narf_core.track import JACOBIAN_RGB, SIGMA_SCALE, TrackOptions, calibrated_jacobian, sigma_scale

    def own_metadata():  # the bundled clamp with metadata of its own to change
        model = copy.copy(clamp)
        model.metadata = copy.deepcopy(clamp.metadata)
        return model

    auto = TrackOptions()
    unchosen = own_metadata()  # a bundle calibrated before the choice
    unchosen.metadata.setdefault("uncertainty", {}).setdefault("track", {}).pop("jacobians", None)
    assert auto.jacobian_rgb == "auto" and calibrated_jacobian(unchosen, "rgb") is None
    assert auto.step_options(False, "cpu", unchosen).jacobian == JACOBIAN_RGB == "derivatives"
    chose = own_metadata()
    chose.metadata.setdefault("uncertainty", {})["track"] = {
        "rgbd": 0.5, "rgb": 2.0, "solvers": {"rgbd": "gauss-newton", "rgb": "gauss-newton"},
        "jacobians": {"rgbd": "differences", "rgb": "differences"}}
    assert calibrated_jacobian(chose, "rgb") == "differences"
    assert auto.step_options(False, "cpu", chose).jacobian == "differences"
    assert auto.step_options(True, "cpu", chose).jacobian == auto.jacobian == "differences"
    assert TrackOptions(jacobian_rgb="derivatives").step_options(False, "cpu", chose).jacobian == "derivatives"
    # the model's factor where the frame takes the Jacobian it was fitted with, else the pooled one
    assert sigma_scale(chose, auto, False) == 2.0 and sigma_scale(chose, auto, True) == 0.5
    assert sigma_scale(chose, TrackOptions(jacobian_rgb="derivatives"), False) == SIGMA_SCALE["gauss-newton"]["rgb"]
    assert sigma_scale(chose, TrackOptions(jacobian="derivatives"), True) == SIGMA_SCALE["gauss-newton"]["rgbd"]
    # the benchmark's table names a model's own choice
    per_frame = {"rgb": {"solver": "gauss-newton", "iterations": 3, "rays_per_iteration": 768,
                         "jacobian": "derivatives", "jacobian_own": {"lamp": "differences"}}}
    table = markdown({"frames": 3, "runs": [], "options": auto.__dict__, "per_frame": per_frame})
    assert "(Jacobian by derivatives; by differences for lamp, its calibration's choice)" in table
    # and `narf train` prints what its calibration measured
    from narf_core.cli import _print_track_sigma

    chose.metadata["uncertainty"]["track"].update(fx=134.0, rgbd_frames=180, rgb_frames=179, seeds=[1, 2, 3],
                                                  rgb_add_m={"derivatives": 0.052, "differences": 0.0107})
    _print_track_sigma(chose)
    assert ("tracker's Jacobian without depth: differences (mean ADD on those frames 5.20 cm by derivatives, "
            "1.07 cm by differences)") in capsys.readouterr().out


def test_a_frame_with_depth_takes_the_rays_its_models_calibration_chose(clamp, capsys) -> None:
    """``TrackOptions.rays_per_iteration`` 0 (the default) takes, with depth on the CPU, the rays per iteration the
    model's tracker calibration chose (``uncertainty.track.rays``), else the solver's own; a set number overrides it,
    a GPU takes its own, a frame without depth the solver's. A factor fitted on other rays than the frame's is not
    the model's own."""
    import copy

    from narf_benchmarks.track import markdown
    from narf_core.cli import _print_track_sigma
    from narf_core.track import BUDGETS, FEWER_RAYS, GPU_RAYS, SIGMA_SCALE, TrackOptions, calibrated_rays, sigma_scale

    chose = copy.copy(clamp)
    chose.metadata = copy.deepcopy(clamp.metadata)
    chose.metadata.setdefault("uncertainty", {})["track"] = {
        "rgbd": 0.5, "rgb": 2.0, "solvers": {"rgbd": "gauss-newton", "rgb": "gauss-newton"},
        "jacobians": {"rgbd": "differences", "rgb": "derivatives"}, "rays": {"rgbd": FEWER_RAYS}}
    auto, own = TrackOptions(), BUDGETS["gauss-newton"][1]
    assert calibrated_rays(chose) == FEWER_RAYS != own and calibrated_rays(clamp) in (None, own)
    assert auto.step_options(True, "cpu", chose).rays_per_iteration == FEWER_RAYS
    assert auto.step_options(False, "cpu", chose).rays_per_iteration == own
    assert auto.step_options(True, "cpu").rays_per_iteration == own  # no model: the solver's own
    assert auto.rays_for(True, "cuda", chose) == GPU_RAYS["gauss-newton"]
    assert TrackOptions(rays_per_iteration=1024).step_options(True, "cpu", chose).rays_per_iteration == 1024
    # the model's factor where the frame takes the rays it was fitted on, else the pooled one
    assert sigma_scale(chose, auto, True) == 0.5 and sigma_scale(chose, auto, False) == 2.0
    assert sigma_scale(chose, TrackOptions(rays_per_iteration=own), True) == SIGMA_SCALE["gauss-newton"]["rgbd"]
    assert sigma_scale(chose, TrackOptions(rays_per_iteration=own), False) == 2.0  # fitted on its own rays
    # the benchmark's caption names a model's own choice, and `narf train` prints what it measured
    per_frame = {"rgbd": {"solver": "gauss-newton", "iterations": 2, "rays_per_iteration": own,
                          "jacobian": "differences", "rays_own": {"gripper": FEWER_RAYS}}}
    table = markdown({"frames": 3, "runs": [], "options": auto.__dict__, "per_frame": per_frame})
    assert f"2 gauss-newton iterations of {own} rays ({FEWER_RAYS} for gripper, its calibration's choice)" in table
    chose.metadata["uncertainty"]["track"].update(fx=134.0, rgbd_frames=180, rgb_frames=179, seeds=[1, 2, 3],
                                                  rgbd_add_m={str(own): 0.00055, str(FEWER_RAYS): 0.00058})
    _print_track_sigma(chose)
    assert (f"tracker's rays per iteration with depth: {FEWER_RAYS} (mean ADD on those frames 0.055 cm on {own}, "
            f"0.058 cm on {FEWER_RAYS})") in capsys.readouterr().out


def test_a_frame_with_depth_takes_the_huber_scale_its_models_calibration_chose(clamp, capsys) -> None:
    """``TrackOptions.robust_scale`` 0 (the default) takes, for a Gauss-Newton frame with depth, the Huber scale the
    model's tracker calibration chose (``uncertainty.track.robust_scale``), else the preset's; a set scale overrides
    it, a frame without depth keeps the preset's. A factor fitted at another scale than the frame's is not the
    model's own."""
    import copy

    from narf_benchmarks.track import markdown
    from narf_core.cli import _print_track_sigma
    from narf_core.track import SIGMA_SCALE, WIDE_HUBER, TrackInputError, TrackOptions, calibrated_huber, sigma_scale

    chose = copy.copy(clamp)
    chose.metadata = copy.deepcopy(clamp.metadata)
    chose.metadata.setdefault("uncertainty", {})["track"] = {
        "rgbd": 0.5, "rgb": 2.0, "solvers": {"rgbd": "gauss-newton", "rgb": "gauss-newton"},
        "jacobians": {"rgbd": "differences", "rgb": "derivatives"}, "robust_scale": {"rgbd": WIDE_HUBER}}
    auto, preset = TrackOptions(), TrackOptions().step_options(True).robust_scale
    assert calibrated_huber(chose) == WIDE_HUBER != preset and calibrated_huber(clamp) in (None, preset)
    assert auto.step_options(True, "cpu", chose).robust_scale == WIDE_HUBER
    assert auto.step_options(False, "cpu", chose).robust_scale == TrackOptions().step_options(False).robust_scale
    assert auto.step_options(True, "cpu").robust_scale == preset  # no model: the preset's
    assert TrackOptions(robust_scale=0.2).step_options(True, "cpu", chose).robust_scale == 0.2
    assert TrackOptions(solver="adam").huber_for(True, chose) is None  # measured with Gauss-Newton's frames
    with pytest.raises(TrackInputError, match="robust_scale"):
        TrackOptions(robust_scale=-1.0)
    # the model's factor where the frame takes the scale it was fitted at, else the pooled one
    assert sigma_scale(chose, auto, True) == 0.5 and sigma_scale(chose, auto, False) == 2.0
    assert sigma_scale(chose, TrackOptions(robust_scale=preset), True) == SIGMA_SCALE["gauss-newton"]["rgbd"]
    assert sigma_scale(chose, TrackOptions(robust_scale=preset), False) == 2.0  # without depth: the preset's anyway
    # the benchmark's caption names a model's own choice and a set one, and `narf train` prints what it measured
    per_frame = {"rgbd": {"solver": "gauss-newton", "iterations": 2, "rays_per_iteration": 768,
                          "jacobian": "differences", "robust_scale": preset, "robust_scale_own": {"lamp": WIDE_HUBER}}}
    table = markdown({"frames": 3, "runs": [], "options": auto.__dict__, "per_frame": per_frame})
    assert "(Jacobian by differences), Huber scale 0.3 for lamp, its calibration's choice" in table
    per_frame["rgbd"].update(robust_scale=0.2, robust_scale_own={})
    table = markdown({"frames": 3, "runs": [], "options": auto.__dict__, "per_frame": per_frame})
    assert "(Jacobian by differences), Huber scale 0.2" in table and "calibration's choice" not in table
    chose.metadata["uncertainty"]["track"].update(fx=134.0, rgbd_frames=180, rgb_frames=179, seeds=[1, 2, 3],
                                                  rgbd_huber_add_m={"0.1": 0.0140, "0.3": 0.0065})
    _print_track_sigma(chose)
    assert ("tracker's Huber scale with depth: 0.3 (mean ADD on those frames 1.400 cm at 0.1, 0.650 cm at 0.3)"
            in capsys.readouterr().out)


def _bench_track_args(extra: list[str]):
    from narf_core.cli import build_parser

    return build_parser().parse_args(["bench", "track", *extra])


def _bench_sequence(work: str) -> str:
    from narf_benchmarks.track import sequence

    return str(sequence(Path(work), "clamp", (80, 60), 6, False, seed=3))


def test_bench_track_sequences_written_side_by_side_stay_whole(tmp_path: Path, monkeypatch) -> None:
    """Two benchmarks asking for one missing sequence at once (two processes) both get it whole: each
    writes a folder of its own and renames it into place, so neither reads nor deletes the other's
    frames (before, one run stopped at "frames[3].rgb: file not found"). An older run's unfinished
    folder (frames, no scene.json) is replaced, and a whole one is reused as it is."""
    import multiprocessing

    from narf_core.data.dataset import Dataset

    stale = tmp_path / "sequences" / "clamp-80x60-6-s3"
    (stale / "rgb").mkdir(parents=True)
    (stale / "rgb" / "000000.png").write_bytes(b"half written")
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        paths = pool.map(_bench_sequence, [str(tmp_path)] * 2)
    assert paths[0] == paths[1] == str(stale)
    dataset = Dataset.open(stale)
    assert len(dataset.frames()) == 6 and all(dataset.load(f).labels.any() for f in dataset.frames())
    assert sorted(p.name for p in (tmp_path / "sequences").iterdir()) == [stale.name]  # no folder left behind
    written = (stale / "scene.json").stat().st_mtime_ns
    assert _bench_sequence(str(tmp_path)) == str(stale) and (stale / "scene.json").stat().st_mtime_ns == written

    from narf_core.data.synth import sequence as synth

    folders = []
    real = synth.synthesize_sequence
    monkeypatch.setattr(synth, "synthesize_sequence", lambda tool, out, *a, **k: folders.append(Path(out)) or real(
        tool, out, *a, **k))
    other = _bench_sequence(str(tmp_path / "other"))
    assert len(folders) == 1 and folders[0].parent == Path(other).parent and folders[0] != Path(other)
    assert not folders[0].exists() and Dataset.open(other).frames()  # written aside, then renamed into place


def test_bench_track_tracks_the_sequence_of_the_seed_asked(tmp_path: Path, capfd) -> None:
    """``narf bench track --seed S`` synthesises and tracks the seed-S sequence (its own folder, its own
    motion) and its result and table name the seed; a negative or non-integer seed is one error line."""
    pytest.importorskip("pybullet")
    from narf_benchmarks.track import markdown
    from narf_core.data.dataset import Dataset

    first_poses, tables = {}, {}
    for seed in (0, 1):
        code = narf(["--threads", "1", "bench", "track", "--work", str(tmp_path), "--models", str(CLAMP.parent),
                     "--tools", "clamp", "--frames", "2", "--size", "32", "24", "--modalities", "rgbd",
                     "--seed", str(seed), "--json"])
        out, err = capfd.readouterr()
        assert code == 0, err
        result = json.loads(out)
        assert result["seeds"] == [seed] and [r["frames"] for r in result["runs"]] == [2]
        first_poses[seed] = Dataset.open(tmp_path / "sequences" / ("clamp-32x24-2" + ("-s1" if seed else ""))
                                         ).frames()[0].T_cam_obj
        tables[seed] = markdown(result)
    assert sorted(p.name for p in (tmp_path / "sequences").iterdir()) == ["clamp-32x24-2", "clamp-32x24-2-s1"]
    assert not np.allclose(first_poses[0], first_poses[1], atol=1e-3)
    assert "seed 0)" in tables[0] and "seed 1)" in tables[1]
    assert result["machine"]["device"] == "cpu" and result["machine"]["cores"] >= 1
    assert "Measured on cpu, load " in tables[1]

    for bad, reason in (("-1", "-1 is not an integer >= 0"), ("1.5", "'1.5' is not an integer")):
        with pytest.raises(SystemExit) as exited:
            narf(["bench", "track", "--work", str(tmp_path), "--seed", bad])
        _, err = capfd.readouterr()
        lines = [line for line in err.splitlines() if line.strip()]
        assert exited.value.code == 2 and "Traceback" not in err
        assert [line for line in lines if "error" in line] == [f"narf bench track: error: argument --seed: {reason}"]
        assert lines[-1] == f"narf bench track: error: argument --seed: {reason}"


def test_sigma_scale_grows_at_a_camera_finer_than_the_training_views(clamp, monkeypatch) -> None:
    """SIGMA_SCALE's factor is the training views' resolution's; a camera ``r`` times finer (fx over
    theirs) multiplies it by ``r ** SIGMA_SCALE_FINER`` (fitted with depth, Gauss-Newton: 0, no growth; the
    law checked with 0.37), a coarser one leaves it; an option is taken as it is, a model's own factor by the same law
    from the camera it was fitted at (``fx``), or as it is where it does not name one, or, fitted at a
    finer camera too, by the power that joins its two fits up to that camera."""
    from narf_core.geometry import Pinhole
    from narf_core.track import SIGMA_SCALE, SIGMA_SCALE_FINER, TrackOptions, sigma_scale

    monkeypatch.setitem(clamp.metadata, "uncertainty", {k: v for k, v in clamp.metadata.get("uncertainty", {}).items()
                                                          if k != "track"})
    base = SIGMA_SCALE["gauss-newton"]
    fine, same, coarse = Pinhole.primesense(640, 480), Pinhole.primesense(160, 120), Pinhole.primesense(80, 60)
    assert sigma_scale(clamp, TrackOptions(), True, fine) == pytest.approx(base["rgbd"])  # the fitted law: no growth
    monkeypatch.setitem(SIGMA_SCALE_FINER["gauss-newton"], "rgbd", 0.37)  # the law itself, with a growth
    assert sigma_scale(clamp, TrackOptions(), True, fine) == pytest.approx(base["rgbd"] * 4**0.37)
    for camera in (same, coarse, None):
        assert sigma_scale(clamp, TrackOptions(), True, camera) == pytest.approx(base["rgbd"])
    assert sigma_scale(clamp, TrackOptions(), False, fine) == pytest.approx(base["rgb"])  # no law fitted without depth
    assert sigma_scale(clamp, TrackOptions(sigma_scale=0.7), True, fine) == 0.7
    monkeypatch.setitem(clamp.metadata["uncertainty"], "track", {"rgbd": 1.3, "solvers": {"rgbd": "gauss-newton"}})
    assert sigma_scale(clamp, TrackOptions(), True, fine) == 1.3
    fitted_at = float(Pinhole.primesense(320, 240).K[0, 0])
    clamp.metadata["uncertainty"]["track"]["fx"] = fitted_at
    assert sigma_scale(clamp, TrackOptions(), True, fine) == pytest.approx(1.3 * 2 ** SIGMA_SCALE_FINER[
        "gauss-newton"]["rgbd"])
    for camera in (same, None):
        assert sigma_scale(clamp, TrackOptions(), True, camera) == 1.3
    # Fitted at a finer camera too (``fine``): the power that joins the two fits, for either modality.
    fitted_fine = float(Pinhole.primesense(1280, 960).K[0, 0])
    clamp.metadata["uncertainty"]["track"] = {"rgbd": 1.3, "rgb": 2.0, "fx": fitted_at,
                                              "solvers": {"rgbd": "gauss-newton", "rgb": "gauss-newton"},
                                              "fine": {"fx": fitted_fine, "rgbd": 0.325, "rgb": 2.0}}
    assert sigma_scale(clamp, TrackOptions(), True, fine) == pytest.approx(0.65)  # halfway (x2 of x4): 1.3 / 2
    for finest in (Pinhole.primesense(1280, 960), Pinhole.primesense(2560, 1920)):  # finer still: the finer fit's
        assert sigma_scale(clamp, TrackOptions(), True, finest) == pytest.approx(0.325)
    assert sigma_scale(clamp, TrackOptions(), False, fine) == pytest.approx(2.0)
    assert sigma_scale(clamp, TrackOptions(), True, same) == 1.3  # coarser than the fit: the fit's


def test_sigma_scale_is_the_option_else_the_models_own_else_the_pooled_one(clamp, clamp_sequence: Path,
                                                                             monkeypatch) -> None:
    """A warm-started frame's factor on σ: ``TrackOptions.sigma_scale`` / ``sigma_scale_rgb`` where
    set (> 0), else the bundle's ``metadata["uncertainty"]["track"]`` (fitted per model) where it was
    fitted with the frame's solver (Adam where the bundle does not say), else :data:`SIGMA_SCALE`'s for
    that solver. The model's own factor scales Σ and never changes the track: the second round for a Σ
    over the limits is judged at the factor it was tuned with, ``RETRY_SIGMA_SCALE`` (here, Adam's
    frames: σ 5-6 mm at 3.0, over a 4 mm limit, and 2-3 mm at the model's 1.3)."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import SIGMA_SCALE, TrackFrame, TrackOptions, TrackState, sigma_scale, step

    own = {"rgbd": 1.3, "rgb": 2.6}
    assert TrackOptions().sigma_scale == TrackOptions().sigma_scale_rgb == 0
    assert [TrackOptions().solver_for(depth) for depth in (True, False)] == ["gauss-newton", "gauss-newton"]
    monkeypatch.setitem(clamp.metadata, "uncertainty", {k: v for k, v in clamp.metadata.get("uncertainty", {}).items()
                                                          if k != "track"})
    for solver in ("auto", "adam", "gauss-newton"):
        for depth, key in ((True, "rgbd"), (False, "rgb")):
            options = TrackOptions(solver=solver)
            assert sigma_scale(clamp, options, depth) == SIGMA_SCALE[options.solver_for(depth)][key]
    monkeypatch.setitem(clamp.metadata["uncertainty"], "track", own)  # fitted with Adam (no solvers named)
    for depth, key in ((True, "rgbd"), (False, "rgb")):
        assert sigma_scale(clamp, TrackOptions(solver="adam"), depth) == own[key]
        assert sigma_scale(clamp, TrackOptions(solver="gauss-newton"), depth) == SIGMA_SCALE["gauss-newton"][key]
        assert sigma_scale(clamp, TrackOptions(sigma_scale=0.7, sigma_scale_rgb=0.9), depth) == (0.7 if depth else 0.9)
    monkeypatch.setitem(clamp.metadata["uncertainty"], "track", {**own, "solvers": {"rgbd": "gauss-newton", "rgb": "adam"}})
    assert sigma_scale(clamp, TrackOptions(), True) == own["rgbd"]
    assert sigma_scale(clamp, TrackOptions(), False) == SIGMA_SCALE["gauss-newton"]["rgb"]  # fitted with another solver
    assert sigma_scale(clamp, TrackOptions(solver="adam"), False) == own["rgb"]
    monkeypatch.setitem(clamp.metadata["uncertainty"], "track", {**own, "solvers": {"rgbd": "gauss-newton", "rgb": "gauss-newton"}})
    assert sigma_scale(clamp, TrackOptions(), True) == own["rgbd"] and sigma_scale(clamp, TrackOptions(), False) == own["rgb"]
    monkeypatch.setitem(clamp.metadata["uncertainty"], "track", own)

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    observed = TrackFrame(images.rgb, images.labels > 0, frame.time, images.depth)
    # (usual_residual: the σ above were measured at 0.02; this fixture's aliased frames' colour residual, about
    # 0.026, lies over the default)
    options = TrackOptions(solver="adam", iterations=2, rays_per_iteration=128, uncertainty_rays=64,
                           max_position_sigma_m=0.004, usual_residual=0.02)
    answers = []
    for track_factor in (own, None):
        monkeypatch.setitem(clamp.metadata["uncertainty"], "track", track_factor)
        state = TrackState.initial(clamp, frame.T_cam_obj, frame.joints, frame.time - 1 / 30, status="tracking")
        answers.append(step(clamp, dataset.camera, observed, state, options)[0])
    assert answers[0].iterations == answers[1].iterations == 2 * options.iterations  # a second round in both
    np.testing.assert_allclose(answers[0].T_cam_obj, answers[1].T_cam_obj)
    np.testing.assert_allclose(answers[0].covariance, (own["rgbd"] / SIGMA_SCALE["adam"]["rgbd"]) ** 2 * answers[1].covariance)
    assert max(answers[0].uncertainty["position_sigma_m"]) < options.max_position_sigma_m
    assert answers[0].status == "tracking" and answers[1].status == "uncertain"


def test_the_trackers_factor_is_fitted_to_hold_the_share_asked_and_stored_beside_the_rest(clamp, tmp_path: Path) -> None:
    """``narf_core.train.track_sigma.fit_track_scale``: the smallest factor (0.01 steps) whose 95 %
    regions hold the share asked of the errors (a factor ``s`` divides a NEES by ``s²``);
    ``write_calibration`` stores it in the bundle's ``metadata["uncertainty"]["track"]`` and keeps the
    model-error constants there, which :func:`~narf_core.track.sigma_scale` then reads."""
    from narf_benchmarks.calibration import write_calibration
    from narf_core.train.track_sigma import fit_track_scale
    from narf_core.bundle import load_bundle, save_bundle
    from narf_core.estimate import chi2_quantile
    from narf_core.track import TrackOptions, sigma_scale

    bound = chi2_quantile(0.95, 7)
    nees = [0.1 * bound] * 18 + [4.0 * bound, 9.0 * bound]  # at factor 2 the 19th holds, at 3 all 20
    assert fit_track_scale(nees, 7, share=0.95) == pytest.approx(2.0)
    assert fit_track_scale(nees, 7, share=1.0) == pytest.approx(3.0)
    assert fit_track_scale(nees, 7, share=0.9) == pytest.approx(0.32)  # sqrt(0.1) = 0.316 -> 0.32
    assert fit_track_scale([1e-9], 7) == pytest.approx(0.01)
    with pytest.raises(ValueError, match="no tracked frame"):
        fit_track_scale([], 7)

    path = tmp_path / "clamp.narf"
    save_bundle(path, clamp)
    write_calibration(path, None, {"pixels": {"shape": 0.5}})
    fitted = {"rgbd": 1.7, "rgb": 2.2, "solvers": {"rgbd": "gauss-newton", "rgb": "gauss-newton"}}
    write_calibration(path, "track", fitted)
    stored = load_bundle(path)
    assert stored.metadata["uncertainty"]["pixels"] == {"shape": 0.5}
    assert stored.metadata["uncertainty"]["track"] == fitted
    assert sigma_scale(stored, TrackOptions(), True) == 1.7 and sigma_scale(stored, TrackOptions(), False) == 2.2


def test_bench_track_repeats_each_sequence_per_ray_seed_and_sums_up_the_tracks(tmp_path: Path, capfd) -> None:
    """``narf bench track --seed 0 1 --ray-seeds 0 1`` tracks both sequences once per seed of the ray draws
    (``TrackOptions.seed``, which moves an RGB-only track), names each track's seeds, and the second table
    gives over a cell's four tracks the mean of their mean ADD, the worst and those over 1 cm."""
    pytest.importorskip("pybullet")
    from narf_benchmarks.track import markdown

    code = narf(["--threads", "1", "bench", "track", "--work", str(tmp_path), "--models", str(CLAMP.parent),
                 "--tools", "clamp", "--frames", "2", "--size", "64", "48", "--modalities", "rgb",
                 "--seed", "0", "1", "--ray-seeds", "0", "1", "--json"])
    out, err = capfd.readouterr()
    assert code == 0, err
    result = json.loads(out)
    runs = result["runs"]
    assert [(r["seed"], r["ray_seed"]) for r in runs] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert result["seeds"] == [0, 1] and result["ray_seeds"] == [0, 1]
    adds = [r["add_m"]["mean"] for r in runs]
    assert adds[0] != adds[1] or adds[2] != adds[3]  # the ray draw moves a track without depth
    [cell] = result["over_tracks"]
    assert cell["tracks"] == 4 and cell["modality"] == "rgb" and cell["size"] == [64, 48]
    assert cell["add_mean_m"] == pytest.approx(float(np.mean(adds)))
    assert cell["worst_track_add_m"] == pytest.approx(max(adds))
    assert cell["tracks_over_1cm"] == sum(a > 0.01 for a in adds)
    table = markdown(result)
    assert "seeds 0, 1; rays drawn with seeds 0, 1)" in table
    assert "| clamp (seed 1, rays 0) | 64x48 |" in table
    assert f"| clamp | 64x48 | pybullet | rgb | no | 4 | {cell['frames_per_second']:.1f} | {np.mean(adds) * 100:.2f} |" in table


def test_bench_track_sums_up_a_cell_whose_track_was_lost_throughout() -> None:
    """A track with every frame lost has no ADD: it counts among the cell's tracks over 1 cm, not in its mean or
    worst, and the table prints what there is (a cell of one track gets no summary)."""
    from narf_benchmarks.track import markdown, over_tracks
    from narf_core.track import TrackOptions

    def run(add, lost, seed):
        return {"tool": "clamp", "size": [160, 120], "images": "pybullet", "modality": "rgb", "events": False,
                "frames": 10, "frames_per_second": 5.0, "lost": lost, "seed": seed, "ray_seed": 0,
                "add_m": None if add is None else {"mean": add, "p95": add, "max": add}}

    [cell] = over_tracks([run(0.004, 0, 0), run(None, 10, 1), run(0.02, 2, 2), {**run(0.5, 0, 0), "tool": "x"}])
    assert cell["tracks"] == 3 and cell["tracks_over_1cm"] == 2 and cell["lost"] == 12
    assert cell["add_mean_m"] == pytest.approx(0.012) and cell["worst_track_add_m"] == pytest.approx(0.02)
    assert cell["frames_per_second"] == pytest.approx(5.0)
    [alone] = over_tracks([run(None, 10, 0), run(None, 10, 1)])
    assert alone["add_mean_m"] is None and alone["worst_track_add_m"] is None and alone["tracks_over_1cm"] == 2
    table = markdown({"frames": 10, "runs": [], "seeds": [0, 1], "over_tracks": [alone],
                      "options": TrackOptions(first_frame="warm").__dict__})
    assert "| clamp | 160x120 | pybullet | rgb | no | 2 | 5.0 | - | 2 | - | 20 |" in table


def test_bench_track_prints_joint_errors_in_mm_or_degrees() -> None:
    """``narf bench track``'s table gives a prismatic joint's error in mm and a revolute one's in
    degrees (the result keeps metres and radians), and beside the NEES coverage the factor on σ it was
    measured at."""
    from narf_benchmarks.track import markdown
    from narf_core.track import TrackOptions

    def run(joint_type: str, error: float) -> dict:
        stats = {"mean": error, "p95": 2 * error, "max": 3 * error}
        return {"tool": "t", "size": [160, 120], "modality": "rgbd", "events": False, "frames_per_second": 10.0,
                "frames_per_second_tracking": 10.0, "frames_per_cpu_second_tracking": 10.0, "lost": 0,
                "reinitialised": 0, "nees_coverage_95": 0.95, "add_m": {"mean": 0.01, "p95": 0.02, "max": 0.03},
                "joint_error/j": stats, "joint_types": {"j": joint_type}, "sigma_scale": 0.3}

    table = markdown({"frames": 3, "options": TrackOptions(first_frame="warm").__dict__,
                      "runs": [run("prismatic", 0.0009), run("revolute", math.radians(0.57))]})
    assert "| 0.9 / 1.8 / 2.7 mm |" in table
    assert "| 0.57° / 1.14° / 1.71° |" in table
    assert table.count("| 0 | 0 | 0.95 (×0.30) |") == 2


def test_without_depth_only_a_large_box_prunes_the_unreached_samples(clamp, clamp_sequence: Path, monkeypatch) -> None:
    """Without depth a warm-started frame's iterations keep only the samples light reaches
    (:func:`~narf_core.track.visible`) where the mask's box is larger than the reference box
    (:data:`~narf_core.estimate.ROBUST_BOX_PX`: a finer camera), whatever the preset's own
    ``reference_box_px`` (0 for the tracker's Gauss-Newton), and keep every sample at the reference
    size (where the RGB-only track is bistable); with depth always."""
    from dataclasses import replace

    from narf_core import estimate, track
    from narf_core.data.dataset import Dataset

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[1]
    images = dataset.load(frame)
    calls = []
    real = track.visible
    monkeypatch.setattr(track, "visible", lambda *a, **k: calls.append(1) or real(*a, **k))
    options = replace(track.TrackOptions(iterations=2, rays_per_iteration=64, uncertainty_rays=0).step_options(False),
                      reference_box_px=0)
    box = estimate._mask_box(images.labels > 0, options.box_margin)
    assert max(box[2] - box[0], box[3] - box[1]) < estimate.ROBUST_BOX_PX  # this 160x120 view: the reference size
    for depth, reference, robust_box_px, pruned in ((None, 0, estimate.ROBUST_BOX_PX, False),
                                                    (None, 20, estimate.ROBUST_BOX_PX, False), (None, 0, 20, True),
                                                    (images.depth, 0, estimate.ROBUST_BOX_PX, True)):
        calls.clear()
        monkeypatch.setattr(estimate, "ROBUST_BOX_PX", robust_box_px)
        result = track.refine_frame(clamp, dataset.camera, images.rgb, images.labels > 0, depth, frame.T_cam_obj,
                                    frame.joints, replace(options, reference_box_px=reference))
        assert result.status == "max_iterations"
        assert (len(calls) == options.iterations) is pruned and (len(calls) == 0) is not pruned, \
            (depth is None, reference, robust_box_px)


def test_gauss_newton_frame_reaches_the_label_from_an_offset_without_marching(clamp, clamp_sequence: Path,
                                                                              monkeypatch) -> None:
    """With depth the default frame is Levenberg-Marquardt on the frame's band (``FrameProblem``: no
    marching): from a start 3.5 mm and 0.8° off five iterations, not held to that start by the prior
    (test_with_depth_a_frame_is_held_to_the_prediction_by_its_own_looser_prior), land within half the
    start's error of the label, with a finite Σ (over a sequence, two per frame settle at about a millimetre:
    test_track_follows_the_clamp and ``narf bench track``); one start only. The frame's Jacobian is taken once
    (``jacobian_once``: the later iterations keep it, with the residuals where they are), or with
    ``jacobian_once`` off at every iteration that starts from a new point; either way it lands there."""
    from types import SimpleNamespace

    import torch

    from narf_core import sampling
    from narf_core.data.dataset import Dataset
    from narf_core.geometry import Rays, se3_exp
    from narf_core.track import FrameProblem, TrackOptions, TrackState, step
    from narf_core.track_io import score, sequence_frames

    dataset = Dataset.open(clamp_sequence)
    frames = sequence_frames(dataset)
    off = se3_exp(torch.tensor([0.002, -0.0015, 0.0025, 0.01, -0.005, 0.0075], dtype=torch.float64)).numpy()
    marched, jacobians = [], []
    monkeypatch.setattr(sampling.Marcher, "rounds", lambda *a, **k: marched.append(1))
    differences = FrameProblem.difference_residuals
    monkeypatch.setattr(FrameProblem, "difference_residuals", lambda *a, **k: jacobians.append(1) or differences(*a, **k))
    assert TrackOptions().jacobian_once and TrackOptions().step_options(True).jacobian_once
    assert not TrackOptions().step_options(False).jacobian_once  # without depth: at every iteration
    for i, once in ((2, True), (5, True), (5, False)):
        observed = _frames(dataset, frames[i:i + 1])[0]
        state = TrackState.initial(clamp, off @ frames[i].T_cam_obj, frames[i].joints, frames[i - 1].time,
                                   status="tracking")
        start = score(clamp, frames[i], SimpleNamespace(T_cam_obj=state.T_cam_obj, joints=state.joints))["add_m"]
        jacobians.clear()
        result, _ = step(clamp, dataset.camera, observed, state,
                         TrackOptions(iterations=5, frame_prior_position_m=0.0, jacobian_once=once))
        assert result.status == "tracking" and result.iterations == 5
        assert score(clamp, frames[i], result)["add_m"] < 0.5 * start, (i, start)
        assert np.isfinite(result.covariance).all()
        assert (len(jacobians) == 1) if once else (3 <= len(jacobians) <= 5), (i, once, len(jacobians))
    assert not marched
    problem = FrameProblem(clamp, TrackOptions().step_options(True), 0.1, True)
    with pytest.raises(ValueError, match="box pixels"):  # no box pixels set: no rays of its own
        problem._fixed_samples(Rays(torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2)), torch.zeros(2, 1), True)


def test_without_depth_the_gauss_newton_frame_polishes_its_distance_held_to_the_prediction(clamp, clamp_sequence: Path) -> None:
    """Without depth a frame's Levenberg-Marquardt iterations polish (exact along-ray derivatives, longer
    trial steps): from the label moved 1 cm along the line of sight, the default budget without depth
    (three iterations) comes back within 5 mm, with the tracker's prior towards the prediction as without,
    where the plain iteration, whose Jacobian has the silhouette's scale too steep, stays 8 mm or more away (the drift of
    an RGB-only track along the line of sight); a prior of 0.1 mm and 1e-4 rad holds it where it started."""
    from dataclasses import replace

    from narf_core.data.dataset import Dataset
    from narf_core.track import RGB_ITERATIONS, TrackOptions, _centre, refine_frame

    dataset = Dataset.open(clamp_sequence)
    centre = _centre(clamp)
    options = replace(TrackOptions().step_options(False), uncertainty=False)
    assert options.solver == "gauss-newton" and options.iterations == RGB_ITERATIONS["gauss-newton"]
    default = (TrackOptions().frame_prior_position_m_rgb, np.radians(TrackOptions().frame_prior_rotation_deg_rgb))
    for frame in (dataset.frames()[0], dataset.frames()[4]):
        images = dataset.load(frame)
        T = frame.T_cam_obj
        C = T[:3, :3] @ centre + T[:3, 3]
        view = C / np.linalg.norm(C)
        for offset in (0.01, -0.01):
            T0 = T.copy()
            T0[:3, 3] += offset * view
            along = {}
            for polish, prior in ((False, None), (True, None), (True, default), (True, (1e-4, 1e-4))):
                result = refine_frame(clamp, dataset.camera, images.rgb, images.labels > 0, None, T0, frame.joints,
                                      options, polish=polish, prior=prior)
                along[polish, prior] = abs(float((result.T_cam_obj[:3, :3] @ centre + result.T_cam_obj[:3, 3] - C) @ view))
                turned = np.degrees(np.arccos(np.clip((np.trace(T0[:3, :3].T @ result.T_cam_obj[:3, :3]) - 1) / 2, -1, 1)))
                if prior == (1e-4, 1e-4):  # held to the prediction: no move along the line of sight, no turn
                    assert along[polish, prior] > 0.009 and turned < 0.1, (frame.id, offset, along, turned)
            assert along[True, None] < 0.005 and along[True, default] < 0.005, (frame.id, offset, along)
            assert along[False, None] > 0.008, (frame.id, offset, along)


def test_with_depth_a_frame_is_held_to_the_prediction_by_its_own_looser_prior(clamp, clamp_sequence) -> None:
    """With depth a tracked frame is held to the prediction by ``frame_prior_position_m`` /
    ``frame_prior_rotation_deg`` (1 cm, 5° by default): from the label moved 5 mm across the line of sight,
    the frame's two iterations come half way back or more with the default prior, as without one; a prior
    of a micrometre and 1e-4° (weighed against thousands of depth and colour residuals) keeps it at the
    prediction."""
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackInputError, TrackOptions, _centre, _warm_refine

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[2]
    images = dataset.load(frame)
    centre = _centre(clamp)
    T = frame.T_cam_obj
    C = T[:3, :3] @ centre + T[:3, 3]
    T0 = T.copy()
    across = np.cross(C / np.linalg.norm(C), [0.0, 1.0, 0.0])
    T0[:3, 3] += 0.005 * across / np.linalg.norm(across)
    off, moved = {}, {}
    for name, prior in (("default", {}), ("none", {"frame_prior_position_m": 0.0}),
                        ("tight", {"frame_prior_position_m": 1e-6, "frame_prior_rotation_deg": 1e-4})):
        result = _warm_refine(clamp, dataset.camera, images.rgb, images.labels > 0, images.depth, T0, frame.joints,
                              TrackOptions(uncertainty_rays=0, **prior))
        estimate = result.T_cam_obj[:3, :3] @ centre + result.T_cam_obj[:3, 3]
        off[name] = float(np.linalg.norm(estimate - C))
        moved[name] = float(np.linalg.norm(estimate - (T0[:3, :3] @ centre + T0[:3, 3])))
    assert TrackOptions().frame_prior_position_m == 0.01 and TrackOptions().frame_prior_rotation_deg == 5.0
    assert off["default"] < 0.003 and abs(off["default"] - off["none"]) < 0.0005, off
    assert moved["tight"] < 0.2 * moved["none"], (off, moved)
    for name in ("frame_prior_position_m", "frame_prior_rotation_deg"):
        with pytest.raises(TrackInputError, match=name):
            TrackOptions(**{name: -1.0})


def test_without_depth_the_velocity_along_the_line_of_sight_keeps_its_own_weight(clamp) -> None:
    """``_blended_velocity``: the box centre's velocity moves towards the measured one by the weight, its
    part along the line of sight by its own weight (without depth ``velocity_smoothing_along_rgb``, 0: the
    prediction keeps the last distance); the same weight for both is the plain blend."""
    from narf_core.track import TrackInputError, TrackOptions, TrackState, _blended_velocity, _centre

    before = TrackState(np.eye(4), {"jaw_opening": 0.0}, 0.0, 0.0, np.array([0.01, 0.0, 0.02, 0.0, 0.1, 0.0]))
    T = np.eye(4)
    T[:3, 3] = [0.003, 0.001, 0.5] - _centre(clamp)  # the centre 0.5 m ahead, moved 3 mm right, 1 mm down
    dt = 0.1
    centre = T[:3, 3] + _centre(clamp)
    view = centre / np.linalg.norm(centre)
    measured = (centre - _centre(clamp)) / dt
    plain = _blended_velocity(clamp, before, T, dt, 0.6, 0.6)
    np.testing.assert_allclose(plain[:3], 0.6 * measured + 0.4 * before.velocity[:3])
    np.testing.assert_allclose(plain[3:], 0.4 * before.velocity[3:], atol=1e-12)  # no turn measured
    held = _blended_velocity(clamp, before, T, dt, 0.6, 0.0)
    assert held[:3] @ view == pytest.approx(before.velocity[:3] @ view)
    across = lambda v: v - (v @ view) * view  # noqa: E731
    np.testing.assert_allclose(across(held[:3]), across(plain[:3]), atol=1e-12)
    assert TrackOptions().velocity_smoothing_along_rgb == 0.0
    with pytest.raises(TrackInputError, match="velocity_smoothing_along_rgb"):
        TrackOptions(velocity_smoothing_along_rgb=1.5)
    for name in ("frame_prior_position_m_rgb", "frame_prior_rotation_deg_rgb"):
        with pytest.raises(TrackInputError, match=name):
            TrackOptions(**{name: -1.0})


def test_cli_track_solver_choices_are_the_trackers() -> None:
    """``narf track`` / ``narf bench track --solver`` offer the tracker's solvers (named in the CLI so that
    ``--help`` imports no torch)."""
    from narf_core import cli
    from narf_core.track import TRACK_SOLVERS

    assert cli.TRACK_SOLVER_CHOICES == TRACK_SOLVERS


def test_cli_track_iterations_help_names_the_trackers_budgets() -> None:
    from narf_core import cli
    from narf_core.track import AUTO_SOLVER, BUDGETS, RGB_ITERATIONS, auto_solver_text, budget_text

    assert cli.TRACK_AUTO_SOLVER == auto_solver_text()
    assert all(solver in auto_solver_text() for solver in AUTO_SOLVER.values())

    assert cli.TRACK_ITERATIONS == budget_text(0) == (f"{BUDGETS['gauss-newton'][0]} gauss-newton "
                                                      f"({RGB_ITERATIONS['gauss-newton']} without depth), "
                                                      f"{BUDGETS['adam'][0]} adam")
    assert budget_text(1) == f"{BUDGETS['gauss-newton'][1]} gauss-newton, {BUDGETS['adam'][1]} adam"


def test_a_gpu_frame_takes_more_rays_unless_the_options_name_them() -> None:
    import torch

    from narf_core.track import BUDGETS, GPU_RAYS, RGB_ITERATIONS, TrackOptions

    gauss_newton, adam = TrackOptions(solver="gauss-newton"), TrackOptions(solver="adam")
    assert gauss_newton.step_options(True).rays_per_iteration == BUDGETS["gauss-newton"][1]
    assert gauss_newton.step_options(True, torch.device("cpu")).rays_per_iteration == BUDGETS["gauss-newton"][1]
    on_gpu = gauss_newton.step_options(False, "cuda:0")
    assert on_gpu.rays_per_iteration == GPU_RAYS["gauss-newton"] > BUDGETS["gauss-newton"][1]
    assert on_gpu.iterations == RGB_ITERATIONS["gauss-newton"]  # only the rays change (a frame without depth)
    assert gauss_newton.step_options(True, "cuda").iterations == BUDGETS["gauss-newton"][0]
    assert gauss_newton.step_options(False).iterations == RGB_ITERATIONS["gauss-newton"] != BUDGETS["gauss-newton"][0]
    assert adam.step_options(False).iterations == BUDGETS["adam"][0]  # Adam's frames: one budget
    assert TrackOptions(solver="gauss-newton", iterations=5).step_options(False).iterations == 5
    assert adam.step_options(True, "cuda").rays_per_iteration == BUDGETS["adam"][1]  # not measured: as on the CPU
    named = TrackOptions(solver="gauss-newton", rays_per_iteration=512)
    assert named.step_options(True, "cuda").rays_per_iteration == 512


def test_without_depth_the_limit_along_the_line_of_sight_is_the_model_errors_stretch() -> None:
    """A frame without depth may be the stretch (distance over radius) times ``max_position_sigma_m``
    uncertain along its line of sight, as its model error is; across it, and with depth on any camera
    axis, the limit itself holds."""
    import torch

    from narf_core.track import TrackOptions, _too_uncertain

    options = TrackOptions(max_position_sigma_m=0.02)
    u = np.array([0.0, 0.6, 0.8])
    across = np.array([1.0, 0.0, 0.0])

    def info(along_m: float, across_m: float) -> dict:
        cov = np.zeros((7, 7))
        cov[:3, :3] = along_m**2 * np.outer(u, u) + across_m**2 * np.outer(across, across)
        return {"covariance": cov.tolist(), "position_sigma_m": np.sqrt(np.diag(cov)[:3]).tolist(),
                "rotation_sigma_rad": [0.01] * 3}

    sight = (torch.tensor(u), 5.0)
    assert not _too_uncertain(info(0.09, 0.01), options, sight)  # 9 cm along: under 5 x 2 cm
    assert _too_uncertain(info(0.11, 0.01), options, sight)
    assert _too_uncertain(info(0.01, 0.03), options, sight)  # across: the limit itself
    assert _too_uncertain(info(0.09, 0.01), options)  # with depth: 5.4 cm on the z axis
    assert not _too_uncertain(info(0.015, 0.015), options)


def test_the_rotations_limit_holds_with_the_objects_shape_taken_out() -> None:
    """A frame's rotation Σ widened about one axis by the object's shape (``spread``) passes the limit where
    the σ with the spread taken out is within it, and fails where that is over it."""
    import torch

    from narf_core.track import TrackOptions, _too_uncertain

    options = TrackOptions(max_rotation_sigma_deg=10.0)
    axis = np.array([0.0, 0.6, 0.8])
    spread = np.eye(3) + 15.0 * np.outer(axis, axis)  # 4x the σ about that axis

    def info(sigma_deg: float) -> dict:
        cov = np.zeros((6, 6))
        cov[3:6, 3:6] = math.radians(sigma_deg) ** 2 * spread
        return {"covariance": cov.tolist(), "position_sigma_m": [0.001] * 3,
                "rotation_sigma_rad": np.sqrt(np.diag(cov)[3:6]).tolist()}

    assert _too_uncertain(info(8.0), options)  # 8° times up to 4 about that axis
    assert not _too_uncertain(info(8.0), options, spread=torch.tensor(spread))
    assert _too_uncertain(info(11.0), options, spread=torch.tensor(spread))


def test_bench_track_tracks_path_traced_images_of_its_sequences(tmp_path: Path, capfd) -> None:
    """``narf bench track --images pybullet depth`` tracks each sequence as synthesised and path-traced with
    the depth faults (one restyled set beside the sequence, reused by a second run), and the table names the
    images; an unknown kind is one error line."""
    pytest.importorskip("pybullet")
    pytest.importorskip("mitsuba")
    from narf_benchmarks.track import markdown
    from narf_core.data.dataset import Dataset

    args = ["--threads", "1", "bench", "track", "--work", str(tmp_path), "--models", str(CLAMP.parent), "--tools",
            "clamp", "--frames", "2", "--size", "32", "24", "--modalities", "rgbd", "--images", "pybullet", "depth",
            "--spp", "2", "--json"]
    code = narf(args)
    out, err = capfd.readouterr()
    assert code == 0, err
    result = json.loads(out)
    assert [(r["images"], r["frames"]) for r in result["runs"]] == [("pybullet", 2), ("depth", 2)]
    restyled = tmp_path / "sequences" / "clamp-32x24-2-restyled" / "depth"
    source, faulty = Dataset.open(tmp_path / "sequences" / "clamp-32x24-2"), Dataset.open(restyled)
    assert [f.time for f in faulty.frames()] == [f.time for f in source.frames()]
    assert faulty.generator["condition"] == "depth" and faulty.generator["restyle"]["spp"] == 2
    assert not np.array_equal(faulty.load(faulty.frames()[0]).depth, source.load(source.frames()[0]).depth)
    table = markdown(result)
    assert "| clamp | 32x24 | pybullet | rgbd |" in table and "| clamp | 32x24 | path-traced, depth | rgbd |" in table
    written = (restyled / "scene.json").stat().st_mtime_ns
    assert narf(args) == 0 and (restyled / "scene.json").stat().st_mtime_ns == written
    capfd.readouterr()
    with pytest.raises(SystemExit) as exited:
        narf(["bench", "track", "--images", "sunny"])
    _, err = capfd.readouterr()
    assert exited.value.code == 2 and "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("narf bench track: error: argument --images: invalid choice: 'sunny'")


def test_colour_gain_at_measures_a_change_of_light_and_a_frame_compares_at_it(clamp, clamp_sequence: Path) -> None:
    """At the label the model's colour fits the image's with a gain of about one per channel, and the same
    image darkened per channel by that much more; a frame without depth refined on the darkened image from
    the label moved 5 mm sideways ends with a lower loss where its render is compared times that gain."""
    from dataclasses import replace

    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackOptions, colour_gain_at, refine_frame

    dataset = Dataset.open(clamp_sequence)
    frame = dataset.frames()[3]
    images = dataset.load(frame)
    mask = images.labels > 0
    own = colour_gain_at(clamp, dataset.camera, images.rgb, mask, frame.T_cam_obj, frame.joints)
    np.testing.assert_allclose(own, 1.0, atol=0.08)
    scale = np.array([0.6, 0.8, 0.95])
    dark = np.round(images.rgb * scale).astype(np.uint8)
    gain = colour_gain_at(clamp, dataset.camera, dark, mask, frame.T_cam_obj, frame.joints)
    np.testing.assert_allclose(gain / own, scale, rtol=0.02)
    assert colour_gain_at(clamp, dataset.camera, dark, np.zeros_like(mask), frame.T_cam_obj, frame.joints) is None

    T0 = frame.T_cam_obj.copy()
    T0[0, 3] += 0.005
    options = replace(TrackOptions().step_options(False), uncertainty=False)
    plain = refine_frame(clamp, dataset.camera, dark, mask, None, T0, frame.joints, options, polish=True)
    lit = refine_frame(clamp, dataset.camera, dark, mask, None, T0, frame.joints,
                       replace(options, colour_gain=tuple(gain)), polish=True)
    assert lit.loss < 0.7 * plain.loss, (lit.loss, plain.loss)


def test_a_track_without_depth_carries_the_colour_gain_of_its_frames(clamp, clamp_sequence: Path, monkeypatch) -> None:
    """Frames without depth darkened per channel: the carried gain moves from ones to the frames' own (the
    mean of the fits over the first frames, then a step of colour_rate_rgb), every tracked frame counted, and
    the frames after the first compare the render times it; below the gate (colour_gate_rgb) it is fitted but
    not applied; off (colour_rate_rgb 0) and with depth it stays at ones."""
    import narf_core.track as track_module
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackFrame, TrackOptions, TrackState, step
    from narf_core.track_io import sequence_frames

    dataset = Dataset.open(clamp_sequence)
    frames = sequence_frames(dataset)[:5]
    scale = np.array([0.6, 0.8, 0.95])
    observed = [dataset.load(f) for f in frames]
    compared = []  # the colour gain of every frame's refinement
    refine_frame = track_module.refine_frame
    monkeypatch.setattr(track_module, "refine_frame",
                        lambda *a, **k: compared.append(a[7].colour_gain) or refine_frame(*a, **k))

    def carried(depth: bool, **options) -> TrackState:
        compared.clear()
        state = TrackState.initial(clamp, frames[0].T_cam_obj, frames[0].joints, frames[0].time, status="tracking")
        for f, images in zip(frames, observed):
            frame = TrackFrame(np.round(images.rgb * scale).astype(np.uint8), images.labels > 0, f.time,
                               images.depth if depth else None)
            result, state = step(clamp, dataset.camera, frame, state, TrackOptions(uncertainty_rays=0, **options))
            assert result.status == "tracking", (f.id, result.reason)
        return state

    on = carried(depth=False)
    assert on.colour_frames == len(frames)
    np.testing.assert_allclose(on.colour_gain, scale, atol=0.08)
    assert compared[0] == (1.0, 1.0, 1.0) and all(np.abs(np.array(g) - scale).max() < 0.1 for g in compared[1:])
    gated = carried(depth=False, colour_gate_rgb=0.5)
    np.testing.assert_allclose(gated.colour_gain, scale, atol=0.08)
    assert compared == [(1.0, 1.0, 1.0)] * len(frames)
    for off in (carried(depth=False, colour_rate_rgb=0.0), carried(depth=True)):
        assert off.colour_gain.tolist() == [1.0, 1.0, 1.0] and off.colour_frames == 0


def test_colour_gain_and_rate_are_validated() -> None:
    from narf_core.estimate import EstimateInputError, EstimateOptions
    from narf_core.track import TrackInputError, TrackOptions, TrackState

    assert EstimateOptions(colour_gain=[0.9, 1, 1.1]) == EstimateOptions(colour_gain=(0.9, 1.0, 1.1))
    for bad in ((0.4, 1.0, 1.0), (1.0, 1.0), ("a", 1.0, 1.0), (True, 1.0, 1.0), 1.0):
        with pytest.raises(EstimateInputError, match="colour_gain"):
            EstimateOptions(colour_gain=bad)
    for bad in (-0.1, 1.5):
        with pytest.raises(TrackInputError, match="colour_rate_rgb"):
            TrackOptions(colour_rate_rgb=bad)
        with pytest.raises(TrackInputError, match="colour_gate_rgb"):
            TrackOptions(colour_gate_rgb=bad)
    from narf_core.bundle import load_bundle

    clamp = load_bundle(CLAMP)
    T = np.eye(4)
    T[2, 3] = 0.5
    state = TrackState.initial(clamp, T, None, 1.0)
    state.check(clamp)
    for gain, frames in ((np.array([1.0, np.nan, 1.0]), 0), (np.array([3.0, 1.0, 1.0]), 0), (np.ones(3), -1)):
        state.colour_gain, state.colour_frames = gain, frames
        with pytest.raises(TrackInputError, match="state.colour"):
            state.check(clamp)


def test_without_depth_a_frame_may_trust_the_mask_outside_itself_less() -> None:
    """``outside_weight_rgb`` below one: a frame without depth trusts the mask partially (its rays outside the
    mask weigh that much, no edge band, no extra configuration starts); at the default the preset's own trust
    ("auto": in full without depth); with depth :data:`~narf_core.track.DEPTH_MASK_TRUST`'s whatever the option
    (partial, no band, every ray outside the mask at its full weight but an occluder's), or in full without the
    occluder test."""
    from narf_core.estimate import EstimateOptions
    from narf_core.track import DEPTH_MASK_TRUST, TrackInputError, TrackOptions

    partial = TrackOptions(outside_weight_rgb=0.3).step_options(False)
    assert (partial.mask_trust, partial.outside_weight, partial.mask_band_px, partial.partial_theta_starts) == (
        "partial", 0.3, 0, 0)
    preset = EstimateOptions.gauss_newton()
    default = TrackOptions().step_options(False)
    assert (default.mask_trust, default.outside_weight, default.mask_band_px) == (
        preset.mask_trust, preset.outside_weight, preset.mask_band_px)
    with_depth = TrackOptions(outside_weight_rgb=0.3).step_options(True)
    assert (with_depth.mask_trust, with_depth.mask_band_px, with_depth.outside_weight,
            with_depth.partial_theta_starts) == ("partial", 0, 1.0, 0) == tuple(DEPTH_MASK_TRUST.values())
    in_full = TrackOptions(outside_weight_rgb=0.3, occluder_test=False).step_options(True)
    assert (in_full.mask_trust, in_full.outside_weight) == ("full", preset.outside_weight)
    with pytest.raises(TrackInputError, match="outside_weight_rgb"):
        TrackOptions(outside_weight_rgb=1.5)


def test_bench_track_service_clients_track_at_once_through_a_real_server(clamp_sequence: Path) -> None:
    """``narf bench track --service-clients N``: N clients track the sequence at once through ``POST /v1/track`` on a
    server started on loopback as deployed; each gets an answer for every frame, scored against the labels, with its
    rate beside the server's tracker time."""
    from narf_benchmarks.track import service_run
    from narf_core.data.dataset import Dataset

    result = service_run(CLAMP, Dataset.open(clamp_sequence), 2, 4)
    assert result["clients"] == 2 and result["failed_clients"] == 0, result
    for client in result["per_client"]:
        assert client["lost"] == 0 and client["add_mean_m"] < 0.005, client
        assert client["frames_per_second"] > 0 and 0 < client["tracker_seconds_mean"] < client["frame_seconds_mean"]
