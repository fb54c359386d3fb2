"""``evaluate_render``: the paper's per-pixel MSE against the masked observation, exactly, with its PSNR and timing."""

from __future__ import annotations

import json
import math
import shutil
import time

import numpy as np
import pytest
import torch

pytest_plugins = ("conftest_model",)

from narf_core.data.dataset import Dataset  # noqa: E402
from narf_core.evaluate import evaluate_render  # noqa: E402
from narf_core.metrics import psnr_from_mse  # noqa: E402


def key(T) -> bytes:
    """A frame's identity: its pose as float32 bytes (``evaluate_render`` passes float32)."""
    return np.asarray(T, dtype=np.float32).tobytes()


class MaskedTruth:
    """A stand-in model whose render is the masked observation of each frame plus ``offset``."""

    def __init__(self, dataset: Dataset, offset: float) -> None:
        self.targets = {}
        for frame in dataset.frames():
            images = dataset.load(frame)
            masked = images.rgb.astype(np.float32) / 255 * (images.labels > 0)[..., None]
            self.targets[key(frame.T_cam_obj)] = masked
        self.offset = offset
        self.calls: list[tuple] = []
        self.thetas: list[float] = []

    def joint_vector(self, joints):
        return torch.tensor([joints["pivot"]])

    def render(self, T_cam_obj, theta, camera, *, outputs, mode):
        self.calls.append((tuple(outputs), mode, camera.width, camera.height))
        self.thetas.append(float(theta[0]))
        target = self.targets[key(T_cam_obj.numpy())]
        return {"rgb": torch.from_numpy(target + self.offset)}


@pytest.mark.parametrize(("offset", "mse"), [(0.0, 0.0), (0.1, 0.01), (-0.25, 0.0625)])
def test_the_error_is_the_per_pixel_mse_against_the_masked_observation(tiny_dataset, offset, mse):
    dataset = Dataset.open(tiny_dataset)
    model = MaskedTruth(dataset, offset)
    score = evaluate_render(model, dataset, split="novel", mode="parts", limit=5)
    assert score.mse == pytest.approx(mse, rel=1e-5, abs=1e-12)
    assert score.psnr == (math.inf if mse == 0 else pytest.approx(-10 * math.log10(mse), rel=1e-5))
    assert score.n == 5 and len(score.per_image_mse) == 5
    assert model.calls == [(("rgb",), "parts", 48, 36)] * 5
    assert model.thetas == pytest.approx([f.joints["pivot"] for f in dataset.frames("novel")[:5]])
    assert score.split == "novel" and score.mode == "parts" and (score.width, score.height) == (48, 36)


def test_the_frames_are_rendered_at_their_own_pose_and_configuration(tiny_dataset):
    dataset = Dataset.open(tiny_dataset)
    model = MaskedTruth(dataset, 0.0)
    frames = dataset.frames("test")
    wrong = {key(f.T_cam_obj): model.targets[key(g.T_cam_obj)] for f, g in zip(frames, frames[1:] + frames[:1])}
    model.targets.update(wrong)  # every frame now renders its neighbour's view
    assert evaluate_render(model, dataset, split="test").mse > 1e-4


class WaitingTruth(MaskedTruth):
    """:class:`MaskedTruth` on the CPU whose render also waits (as a thread that other processes keep
    off the cores): wall time passes that is not the render's work."""

    aabb = torch.zeros(2, 3)

    def render(self, T_cam_obj, theta, camera, *, outputs, mode):
        time.sleep(0.03)
        return super().render(T_cam_obj, theta, camera, outputs=outputs, mode=mode)


def test_cpu_time_leaves_out_the_time_the_render_waits(tiny_dataset):
    """``cpu_time`` (what ``measure_modes`` takes, so that ``auto`` is not chosen by a busy machine's
    load): the rendering thread's own CPU time; without it the wall clock, waits included."""
    dataset = Dataset.open(tiny_dataset)
    model = WaitingTruth(dataset, 0.0)
    assert evaluate_render(model, dataset, split="test", limit=3).ms_per_image >= 30
    assert evaluate_render(model, dataset, split="test", limit=3, cpu_time=True).ms_per_image < 10


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["narf", "parts"])
def test_the_tiny_model_gets_a_finite_score_over_the_whole_split(tiny_model, tiny_dataset, mode):
    dataset = Dataset.open(tiny_dataset)
    score = evaluate_render(tiny_model, dataset, split="test", mode=mode)
    assert score.n == len(dataset.frames("test")) == 17
    assert math.isfinite(score.mse) and 0 < score.mse < 0.05  # the object covers only a few pixels
    assert score.psnr == psnr_from_mse(score.mse) and math.isfinite(score.psnr)
    assert score.mse == pytest.approx(float(np.mean(score.per_image_mse)))
    assert score.ms_per_image > 0
    summary = score.summary()
    assert "per_image_mse" not in summary and summary["n"] == 17
    json.dumps(summary)


@pytest.mark.slow
def test_one_frame_scored_by_hand(tiny_model, tiny_dataset):
    dataset = Dataset.open(tiny_dataset)
    frame = dataset.frames("novel")[0]
    images = dataset.load(frame)
    rgb = tiny_model.render(torch.as_tensor(frame.T_cam_obj, dtype=torch.float32), tiny_model.joint_vector(frame.joints),
                            dataset.camera)["rgb"].numpy()
    target = images.rgb / 255.0 * (images.labels > 0)[..., None]
    score = evaluate_render(tiny_model, dataset, split="novel", limit=1)
    assert score.n == 1
    assert score.mse == pytest.approx(float(((rgb - target) ** 2).mean()), rel=1e-5)


def test_a_split_without_frames_is_a_value_error(tiny_dataset, tmp_path):
    root = tmp_path / "no-novel"
    shutil.copytree(tiny_dataset, root)
    scene = json.loads((root / "scene.json").read_text())
    scene["frames"] = [f for f in scene["frames"] if f["split"] != "novel"]
    (root / "scene.json").write_text(json.dumps(scene))
    dataset = Dataset.open(root)
    with pytest.raises(ValueError, match=r"no frames in split 'novel'") as info:
        evaluate_render(MaskedTruth(dataset, 0.0), dataset, split="novel")
    assert str(root) in str(info.value)


@pytest.mark.parametrize("limit", [0, -1])
def test_a_limit_below_one_is_a_value_error(tiny_dataset, limit):
    dataset = Dataset.open(tiny_dataset)
    with pytest.raises(ValueError, match=f"limit must be a positive number of frames, got {limit}"):
        evaluate_render(MaskedTruth(dataset, 0.0), dataset, limit=limit)


def test_an_unknown_split_is_a_value_error(tiny_dataset):
    dataset = Dataset.open(tiny_dataset)
    with pytest.raises(ValueError, match="unknown split 'val'"):
        evaluate_render(MaskedTruth(dataset, 0.0), dataset, split="val")
