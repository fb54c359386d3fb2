"""Render error of a model on a dataset split, with the time it took (``narf eval``, ``narf bench render``).

The error is the paper's per-pixel MSE over the full image, RGB in [0, 1]: the render (on black)
against the observation masked by the object's labels (``P_rgb * P_mask``, the paper's eq. 1), so
background pixels count and must be empty in the render.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from narf_core.bundle import NarfModel
from narf_core.data.dataset import Dataset
from narf_core.metrics import psnr_from_mse


@dataclass
class RenderScore:
    """Mean per-pixel MSE and PSNR over ``n`` images, and the median milliseconds per render."""

    split: str
    mode: str
    mse: float
    psnr: float
    n: int
    ms_per_image: float
    width: int
    height: int
    per_image_mse: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "per_image_mse"}


def evaluate_render(
    model: NarfModel,
    dataset: Dataset,
    *,
    split: str = "test",
    mode: str = "narf",
    limit: int | None = None,
    progress: bool = False,
    cpu_time: bool = False,
) -> RenderScore:
    """Render every frame of ``split`` (the first ``limit``) and compare with the masked observation
    (``progress``: a progress bar on stderr). ``ms_per_image``: the median wall time, or with ``cpu_time``
    (and the model on the CPU) the rendering thread's own CPU time, which other processes on the cores
    do not inflate (a GPU's render is timed on the wall clock whatever ``cpu_time``: the thread waits)."""
    if limit is not None and limit < 1:
        raise ValueError(f"limit must be a positive number of frames, got {limit}")
    frames = dataset.frames(split)[:limit]
    if not frames:
        raise ValueError(f"dataset {dataset.root} has no frames in split {split!r}")
    camera = dataset.camera
    clock = time.thread_time if cpu_time and model.aabb.device.type == "cpu" else time.perf_counter
    errors, times = [], []
    for frame in tqdm(frames, desc=f"eval {split} {mode} {camera.width}x{camera.height}", disable=not progress, leave=False):
        images = dataset.load(frame)
        mask = (images.labels > 0)[..., None]
        target = images.rgb.astype(np.float32) / 255 * mask
        theta = model.joint_vector(frame.joints)
        T = torch.as_tensor(frame.T_cam_obj, dtype=torch.float32)
        t0 = clock()
        rgb = model.render(T, theta, camera, outputs=("rgb",), mode=mode)["rgb"].cpu()  # (a GPU's work done)
        times.append(clock() - t0)
        errors.append(float(((rgb.numpy() - target) ** 2).mean()))
    mse = float(np.mean(errors))
    return RenderScore(
        split=split,
        mode=mode,
        mse=mse,
        psnr=float(psnr_from_mse(mse)),
        n=len(frames),
        ms_per_image=1000 * float(np.median(times)),
        width=camera.width,
        height=camera.height,
        per_image_mse=errors,
    )
