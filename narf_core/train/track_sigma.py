"""A model's own factor on the tracker's σ, fitted on smooth sequences of its object.

A warm-started frame's covariance (:func:`narf_core.track.sigma_scale`) is scaled by a factor that
makes its 95 % regions hold 95 % of the true errors. The pooled factors (:data:`narf_core.track.SIGMA_SCALE`)
were fitted on a few tools; a model whose error differs from theirs (a thinner part, a coarser fit)
is covered more or less than 95 % by them. Where the dataset says which object it drew (a procedural
tool or a URDF: ``generator.tool``), training draws ``sequences`` smooth sequences of it (seeds 1, 2,
...; the benchmarks' is seed 0) at the dataset's camera, tracks them from their first label with the
default tracker, RGB-D and RGB only, and keeps per modality the smallest factor (0.01 steps) whose
regions hold 95 % of the pooled frames' errors: ``metadata["uncertainty"]["track"]``. Without depth it tracks
the first with both Jacobians and keeps the one the tracker should take for this model (``jacobians``: the
differences where they lower the frames' mean ADD below :data:`~narf_core.track.DIFFERENCES_GAIN` of the
derivatives', ``rgb_add_m`` both means); the same again at
a camera's native 640x480 (four times finer than 160x120 views), where a model's σ need not follow the
pooled factor's growth with the camera's fineness.

Drawing the finer sequences costs as much as tracking them (pybullet's renderer, one core, holding
Python's lock: a cabinet's three take three minutes). Where a core is free beside the training's threads,
:func:`draw_ahead` draws them in a process of their own while the fields train.
"""

from __future__ import annotations

import math
from multiprocessing.process import BaseProcess
from pathlib import Path

import numpy as np

from narf_core.bundle import NarfModel
from narf_core.data.dataset import Dataset
from narf_core.threads import torch_threads

COVERAGE = 0.95
SEQUENCE_FRAMES = 60
FINE_WIDTH = 640


def track_nees(model: NarfModel, dataset: Dataset, rgb_only: bool, seed: int = 0,
               jacobian_rgb: str | None = None) -> list[float]:
    """The default tracker over the sequence ``dataset`` from its first label; per frame with a
    covariance, the NEES of its true error under the frame's Σ before the tracker's factor (``sigma_scale``
    1: the NEES at the factor used times its square)."""
    return track_errors(model, dataset, rgb_only, seed, jacobian_rgb)[0]


def track_errors(model: NarfModel, dataset: Dataset, rgb_only: bool, seed: int = 0,
                 jacobian_rgb: str | None = None) -> tuple[list[float], list[float]]:
    """:func:`track_nees` and, per frame not lost, the ADD (m); without depth with the frame Jacobian
    ``jacobian_rgb`` (None: the default tracker's for this model)."""
    from narf_core.estimate import local_error
    from narf_core.track import SIGMA_SCALE, TrackOptions, track
    from narf_core.track_io import load_frames, score, sequence_frames

    pooled = {key: SIGMA_SCALE[TrackOptions().solver_for(key == "rgbd")][key] for key in ("rgbd", "rgb")}
    scale = pooled["rgb" if rgb_only else "rgbd"]  # the pooled factor: the track does not see a model's own
    options = TrackOptions(first_frame="warm", seed=seed, sigma_scale=pooled["rgbd"], sigma_scale_rgb=pooled["rgb"],
                           **({"jacobian_rgb": jacobian_rgb} if jacobian_rgb else {}))
    frames = sequence_frames(dataset)
    nees, adds = [], []
    for frame, result in zip(frames, track(model, load_frames(dataset, frames, rgb_only=rgb_only), dataset.camera,
                                           frames[0].T_cam_obj, frames[0].joints, options)):
        if result.status != "lost":
            adds.append(score(model, frame, result)["add_m"])
        if result.status != "lost" and result.covariance is not None:
            e = local_error(result.T_cam_obj, result.joints, frame.T_cam_obj, frame.joints, model)
            nees.append(float(e @ np.linalg.pinv(result.covariance, hermitian=True) @ e) * scale**2)
    return nees, adds


def fit_track_scale(nees: list[float], dof: int, share: float = COVERAGE) -> float:
    """The smallest factor on σ (0.01 steps) whose 95 % regions hold ``share`` of the errors whose
    NEES at factor 1 are ``nees`` (a factor ``s`` divides each NEES by ``s²``). Steps finer than the
    factor's own spread from one set of sequences to another: a coarser step rounded up over-covers."""
    from narf_core.estimate import chi2_quantile

    if not nees:
        raise ValueError("no tracked frame with a covariance to fit the factor on")
    needed = float(np.quantile(np.asarray(nees), share, method="inverted_cdf"))
    return max(0.01, math.ceil(round(100 * math.sqrt(needed / chi2_quantile(COVERAGE, dof)), 9)) / 100)


def track_calibration(model: NarfModel, datasets: list[Dataset], modalities=("rgbd", "rgb"),
                      jacobians: dict[str, str] | None = None) -> dict:
    """``metadata["uncertainty"]["track"]``: per modality the factor on a warm-started frame's σ
    (:func:`narf_core.track.sigma_scale`) fitted on the pooled frames of ``datasets``' sequences (one
    camera, its focal length ``fx`` in pixels), and the solver and the frame Jacobian it was fitted with
    (``solvers``: the default tracker's for that modality; ``jacobians``: given, else with depth the default
    tracker's and without, where its ``jacobian_rgb`` is "auto", the one whose frames' mean ADD on the first
    sequence is lower by :data:`~narf_core.track.DIFFERENCES_GAIN`, both means under ``rgb_add_m``: one track more
    than the fit itself, training's time being the issue's too)."""
    from narf_core.estimate import JACOBIANS
    from narf_core.track import DIFFERENCES_GAIN, TrackOptions

    def pooled(rgb_only: bool, jacobian: str, sets: list[Dataset]) -> list[float]:
        return [n for dataset in sets for n in track_errors(model, dataset, rgb_only, jacobian_rgb=jacobian)[0]]

    default = TrackOptions()
    out: dict = {"solvers": {}, "jacobians": {}, "fx": float(datasets[0].camera.K[0, 0])}
    for modality in modalities:
        depth, given = modality == "rgbd", (jacobians or {}).get(modality)
        if (given is None and not depth and default.jacobian_rgb == "auto"
                and default.solver_for(False) == "gauss-newton"):  # both on the first sequence (one more track)
            first = {j: track_errors(model, datasets[0], True, jacobian_rgb=j) for j in JACOBIANS}
            mean = {j: float(np.mean(adds)) if adds else math.inf for j, (_, adds) in first.items()}
            chosen = "differences" if mean["differences"] < DIFFERENCES_GAIN * mean["derivatives"] else "derivatives"
            nees = first[chosen][0] + pooled(True, chosen, datasets[1:])
            out["rgb_add_m"] = mean
        else:
            chosen = given or default.jacobian_for(depth)
            nees = pooled(not depth, chosen, datasets)
        out[modality] = fit_track_scale(nees, 6 + len(model.joints))
        out[f"{modality}_frames"] = len(nees)
        out["solvers"][modality] = default.solver_for(depth)
        out["jacobians"][modality] = chosen
    return out


def fine_size(size: tuple[int, int]) -> tuple[int, int] | None:
    """The finer camera a factor is also fitted at: ``size`` times the whole number nearest to reach
    :data:`FINE_WIDTH` pixels across, at most 4 (a camera's native 640x480 for 160x120 training views);
    None where ``size`` is that fine already."""
    k = min(4, round(FINE_WIDTH / size[0]))
    return (size[0] * k, size[1] * k) if k > 1 else None


def sequence_folders(tool: str, size: tuple[int, int], work: Path, seeds: list[int],
                     frames: int = SEQUENCE_FRAMES) -> list[Path]:
    """Smooth sequences of ``tool`` (a procedural object's name or a URDF) of ``seeds`` at ``size``, drawn
    into ``work`` where missing (:func:`~narf_core.data.synth.sequence.sequence_once`)."""
    from narf_core.data.synth.sequence import sequence_once

    return [sequence_once(tool, Path(work) / f"sequence-{size[0]}x{size[1]}-{frames}-s{seed}", frames, size=size,
                          seed=seed, events=False) for seed in seeds]


def draw_ahead(tool: str, size: tuple[int, int], work: Path, seeds: list[int],
               frames: int = SEQUENCE_FRAMES) -> BaseProcess | None:
    """Start drawing the sequences :func:`calibrate_tracker` tracks (``tool`` at ``size`` and at
    :func:`fine_size`, ``seeds``, into ``work``) in a daemon process of its own, where the cores free now
    (:func:`~narf_core.threads.free_cores`) outnumber this process's torch threads; None where none is.
    The fit then finds them drawn, or draws what is missing itself (each sequence is whole or absent:
    :func:`~narf_core.data.synth.sequence.sequence_once`); join the process before it does."""
    import multiprocessing

    import torch

    from narf_core.threads import free_cores

    if free_cores() <= torch.get_num_threads():
        return None
    fine = fine_size(size)
    sizes = [size] if fine is None else [size, fine]
    process = multiprocessing.get_context("spawn").Process(
        target=_draw, args=(tool, sizes, str(work), list(seeds), frames), name="narf-draw-sequences", daemon=True)
    process.start()
    return process


def _draw(tool: str, sizes: list[tuple[int, int]], work: str, seeds: list[int], frames: int) -> None:
    with torch_threads(1):  # one core: the one that was free
        for size in sizes:
            sequence_folders(tool, size, Path(work), seeds, frames)


def calibrate_tracker(model: NarfModel, tool: str, size: tuple[int, int], work: Path, seeds: list[int],
                      frames: int = SEQUENCE_FRAMES) -> dict:
    """The model's own tracker factors (:func:`track_calibration`) on smooth sequences of ``tool`` of
    ``seeds`` at ``size`` (its views' camera) and, under ``fine``, at :func:`fine_size` (where
    :func:`narf_core.track.sigma_scale` interpolates between the two cameras), drawn into ``work``; with
    the ``seeds``. A ``ValueError`` where a modality held no frame."""
    def fitted(at: tuple[int, int], jacobians: dict[str, str] | None = None) -> dict:
        datasets = [Dataset.open(f) for f in sequence_folders(tool, at, work, seeds, frames)]
        with torch_threads(1):  # as the tracker runs by default (small work): the fit does not follow the machine
            return track_calibration(model, datasets, jacobians=jacobians)

    out = {**fitted(size), "seeds": list(seeds)}
    fine = fine_size(size)
    if fine is not None:  # with the Jacobians chosen at the views' camera
        out["fine"] = {k: v for k, v in fitted(fine, out["jacobians"]).items() if k not in ("solvers", "jacobians")}
    return out


def dataset_tool(dataset: Dataset) -> str | None:
    """The object that drew ``dataset`` (a procedural object's name or a URDF that still exists), from its
    generator's record; None for a dataset that does not name one (real images)."""
    tool = dataset.generator.get("tool")
    if not isinstance(tool, str) or (tool.endswith(".urdf") and not Path(tool).is_file()):
        return None
    return tool
