"""Tracking on datasets: a sequence's frames as :class:`~narf_core.track.TrackFrame`, scores
against its labels, and the overlay video (the model's silhouette over each frame)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from narf_core.bundle import NarfModel
from narf_core.data.dataset import Dataset, DatasetError, Frame
from narf_core.geometry import Pinhole
from narf_core.metrics import add, joint_errors
from narf_core.track import TrackFrame, TrackResult

STATUS_COLOURS = {"tracking": (40, 220, 60), "uncertain": (250, 200, 0), "lost": (240, 40, 40),
                  "reinitialised": (60, 140, 255)}


def sequence_frames(dataset: Dataset, *, limit: int | None = None) -> list[Frame]:
    """The frames of a sequence in time order (every frame must carry a ``time``, increasing)."""
    frames = dataset.frames()[:limit] if limit else dataset.frames()
    if not frames:
        raise DatasetError(f"{dataset.root}: no frames")
    missing = [f.id for f in frames if f.time is None]
    if missing:
        raise DatasetError(f"{dataset.root}: frame {missing[0]} has no 'time': not a sequence "
                           "(write one with narf synth --sequence)")
    for a, b in zip(frames, frames[1:]):
        if not b.time > a.time:  # type: ignore[operator]
            raise DatasetError(f"{dataset.root}: frame {b.id} at {b.time} s is not after frame {a.id} at {a.time} s")
    return frames


def load_frames(dataset: Dataset, frames: list[Frame], *, rgb_only: bool = False) -> Iterator[TrackFrame]:
    """Each frame's images as a :class:`TrackFrame` (read lazily, one at a time)."""
    for frame in frames:
        images = dataset.load(frame)
        yield TrackFrame(images.rgb, images.labels > 0, float(frame.time), None if rgb_only else images.depth)


def score(model: NarfModel, frame: Frame, result: TrackResult) -> dict[str, float]:
    """ADD (m) and per-joint errors of a result against the frame's labels."""
    kin = model.kinematics
    theta_true, theta_est = kin.joint_vector(frame.joints), kin.joint_vector(result.joints)
    out = {"add_m": float(add(model.sample_points, kin.link_poses(theta_true).numpy(), frame.T_cam_obj,
                              kin.link_poses(theta_est).numpy(), result.T_cam_obj, model.links))}
    errors = joint_errors(theta_true.numpy(), theta_est.numpy(), [j.type for j in model.joints])
    out.update({f"joint_error/{j.name}": float(e) for j, e in zip(model.joints, errors)})
    return out


def overlay(model: NarfModel, camera: Pinhole, image: np.ndarray, result: TrackResult) -> Image.Image:
    """The frame with the model's rendered silhouette at the result tinted in the status colour,
    and the status and time written in a corner."""
    colour = np.array(STATUS_COLOURS.get(result.status, (255, 255, 255)), dtype=np.float32)
    out = image.astype(np.float32)
    if result.status != "lost":
        theta = model.joint_vector(result.joints)
        T = torch.as_tensor(result.T_cam_obj, dtype=torch.float32)
        alpha = model.render(T, theta, camera, outputs=("opacity",))["opacity"].cpu().numpy()[..., None]
        out = out * (1 - 0.5 * alpha) + colour * 0.5 * alpha
    picture = Image.fromarray(np.clip(out, 0, 255).astype(np.uint8))
    ImageDraw.Draw(picture).text((2, 1), f"{result.time:6.2f}s {result.status}", fill=tuple(int(c) for c in colour))
    return picture


def write_video(path: Path, pictures: list[Image.Image], fps: float) -> Path:
    """Write ``pictures`` as an animated GIF (``.gif``); other suffixes are refused (no video codec
    is a dependency)."""
    if path.suffix.lower() != ".gif":
        raise ValueError(f"--video: {path.name}: only .gif is supported (no video codec is installed)")
    if not pictures:
        raise ValueError("--video: no frames to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    pictures[0].save(path, save_all=True, append_images=pictures[1:], duration=max(20, int(round(1000 / fps))), loop=0)
    return path
