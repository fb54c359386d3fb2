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
:func:`draw_ahead` draws them in a process of their own while the fields train; and where cores are free when
the fit starts, its tracks (each on one thread) run side by side in processes of their own.
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
               jacobian_rgb: str | None = None, rays: int = 0, huber: float = 0.0) -> list[float]:
    """The default tracker over the sequence ``dataset`` from its first label; per frame with a
    covariance, the NEES of its true error under the frame's Σ before the tracker's factor (``sigma_scale``
    1: the NEES at the factor used times its square)."""
    return track_errors(model, dataset, rgb_only, seed, jacobian_rgb, rays, huber)[0]


def track_errors(model: NarfModel, dataset: Dataset, rgb_only: bool, seed: int = 0,
                 jacobian_rgb: str | None = None, rays: int = 0, huber: float = 0.0) -> tuple[list[float], list[float]]:
    """:func:`track_nees` and, per frame not lost, the ADD (m); without depth with the frame Jacobian
    ``jacobian_rgb`` (None: the default tracker's for this model), with ``rays`` per iteration (0: the solver's own,
    not the model's choice: the one being made) and with depth at the Huber scale ``huber`` (0: the preset's, not
    the model's choice)."""
    from narf_core.estimate import local_error
    from narf_core.track import RETRY_SIGMA_SCALE, SIGMA_SCALE, TrackOptions, track
    from narf_core.track_io import load_frames, score, sequence_frames

    # A fixed factor per modality, not the model's own (the one being fitted); with depth the one the default
    # tracker judges its second round at (RETRY_SIGMA_SCALE, which a set factor replaces): the same estimates.
    fixed = {"rgbd": RETRY_SIGMA_SCALE[TrackOptions().solver_for(True)],
             "rgb": SIGMA_SCALE[TrackOptions().solver_for(False)]["rgb"]}
    scale = fixed["rgb" if rgb_only else "rgbd"]
    preset = TrackOptions().step_options(True).robust_scale  # not the model's own: the one being chosen
    options = TrackOptions(first_frame="warm", seed=seed, sigma_scale=fixed["rgbd"], sigma_scale_rgb=fixed["rgb"],
                           rays_per_iteration=rays or TrackOptions().rays_for(not rgb_only), robust_scale=huber or preset,
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


class _Tracks:
    """The fit's tracks (:func:`track_errors`, each a :class:`~concurrent.futures.Future`): in this process as they
    are asked for, or with ``workers`` > 1 and the bundle's ``path`` in that many processes of their own (spawned,
    one torch thread each as the tracker runs by default, each loading the bundle once). Every track is
    deterministic: the same errors wherever it runs."""

    def __init__(self, model: NarfModel, path: Path | None, workers: int) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.model = model
        self.pool = None
        if workers > 1 and path is not None:
            self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                            initializer=_load_worker, initargs=(str(path),))

    def submit(self, folder: Path, rgb_only: bool, jacobian: str, rays: int = 0, huber: float = 0.0):
        from concurrent.futures import Future

        if self.pool is not None:
            return self.pool.submit(_worker_track, str(folder), rgb_only, jacobian, rays, huber)
        done: Future = Future()
        with torch_threads(1):
            done.set_result(track_errors(self.model, Dataset.open(folder), rgb_only, jacobian_rgb=jacobian, rays=rays,
                                         huber=huber))
        return done

    def __enter__(self) -> _Tracks:
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


_worker_model: NarfModel | None = None


def _load_worker(path: str) -> None:
    global _worker_model
    import torch

    from narf_core.bundle import load_bundle

    torch.set_num_threads(1)
    _worker_model = load_bundle(Path(path), "cpu")


def _worker_track(folder: str, rgb_only: bool, jacobian: str, rays: int = 0,
                  huber: float = 0.0) -> tuple[list[float], list[float]]:
    assert _worker_model is not None, "the worker loads its bundle first"
    return track_errors(_worker_model, Dataset.open(Path(folder)), rgb_only, jacobian_rgb=jacobian, rays=rays,
                        huber=huber)


def track_calibration(tracks: _Tracks, cameras: dict[str, list[Path]], modalities=("rgbd", "rgb")) -> dict:
    """``metadata["uncertainty"]["track"]`` less its seeds: per camera (``cameras``: the sequences' folders at the
    views' camera under ``""``, and at a finer one under ``"fine"``) and per modality the factor on a warm-started
    frame's σ (:func:`narf_core.track.sigma_scale`) fitted on the pooled frames of its sequences (one camera, its
    focal length ``fx`` in pixels), and at the views' camera the solver, the frame Jacobian, the rays and the Huber
    scale it was fitted with (``solvers``: the default tracker's for that modality; ``jacobians``: with depth the
    default tracker's and without, where its ``jacobian_rgb`` is "auto", the one whose frames' mean ADD on the first
    sequence at the views' camera is lower by :data:`~narf_core.track.DIFFERENCES_GAIN`, both means under
    ``rgb_add_m``; ``rays``: with depth, where the default tracker leaves them to the model,
    :data:`~narf_core.track.FEWER_RAYS` where the frames' mean ADD over every sequence at the views' camera stays
    within :data:`~narf_core.track.FEWER_RAYS_LOSS` of the solver's own budget's and that one's within
    :data:`~narf_core.track.TRACK_HELD` of the object's diameter, else that budget, both means under
    ``rgbd_add_m``, every sequence once more: a single sequence's track is one draw; ``robust_scale``: with depth,
    where the default tracker leaves it to the model, :data:`~narf_core.track.WIDE_HUBER` where the tracks on the
    rays kept do not hold within :data:`~narf_core.track.TRACK_HELD` of the diameter and that scale's frames' mean
    ADD, every sequence once more, comes out below :data:`~narf_core.track.WIDE_HUBER_GAIN` of theirs, else the
    preset's, both means under ``rgbd_huber_add_m`` where tried; training's time being the issue's too, the
    Jacobian's choice takes one sequence; the finer camera's fit takes what was chosen). Every track that waits on
    nothing is asked for first, so that ``tracks``' workers run side by side."""
    from narf_core.estimate import JACOBIANS
    from narf_core.track import (
        DIFFERENCES_GAIN, FEWER_RAYS, FEWER_RAYS_LOSS, TRACK_HELD, WIDE_HUBER, WIDE_HUBER_GAIN, TrackOptions,
    )

    default = TrackOptions()
    auto = "rgb" in modalities and default.jacobian_rgb == "auto" and default.solver_for(False) == "gauss-newton"
    budget = default.rays_for(True)  # the solver's own, not a model's
    newton = "rgbd" in modalities and default.solver_for(True) == "gauss-newton"
    fewer = newton and not default.rays_per_iteration and FEWER_RAYS < budget
    preset = default.step_options(True).robust_scale  # not a model's: the one a wider scale is measured against
    wider = newton and not default.robust_scale and WIDE_HUBER != preset
    asked: dict = {}

    def ask(camera: str, modality: str, i: int, jacobian: str, rays: int = 0, huber: float = 0.0):
        key = (camera, modality, i, jacobian, rays, huber)
        if key not in asked:
            asked[key] = tracks.submit(cameras[camera][i], modality == "rgb", jacobian, rays, huber)
        return asked[key]

    def mean_add(futures) -> float:  # over the frames of the tracks, pooled
        adds = [a for f in futures for a in f.result()[1]]
        return float(np.mean(adds)) if adds else math.inf

    def holds(mean: float) -> bool:  # a track whose frames' mean ADD stays within TRACK_HELD of the diameter
        return mean <= TRACK_HELD * tracks.model.diameter

    views = range(len(cameras[""]))
    chosen = {"rgbd": default.jacobian_for(True), "rgb": default.jacobian_for(False)}
    rays = {"rgbd": budget, "rgb": 0}
    huber = {"rgbd": 0.0, "rgb": 0.0}  # 0: the preset's
    both = {n: [ask("", "rgbd", i, chosen["rgbd"], n) for i in views] for n in (budget, FEWER_RAYS)} if fewer else {}
    firsts = {j: ask("", "rgb", 0, j) for j in JACOBIANS} if auto else {}
    for camera, folders in cameras.items():
        for modality in modalities:
            if (modality == "rgbd" and not (fewer or wider)) or (modality == "rgb" and not auto):
                for i in range(len(folders)):
                    ask(camera, modality, i, chosen[modality], rays[modality])
    rays_mean = huber_mean = mean = None
    if fewer:  # both budgets at the views' camera
        rays_mean = {str(n): mean_add(f) for n, f in both.items()}
        own = rays_mean[str(budget)]
        rays["rgbd"] = FEWER_RAYS if holds(own) and rays_mean[str(FEWER_RAYS)] <= FEWER_RAYS_LOSS * own else budget
    if wider:  # on the rays kept, where their tracks do not hold, the wider scale too
        kept = mean_add([ask("", "rgbd", i, chosen["rgbd"], rays["rgbd"]) for i in views])
        if not holds(kept):
            huber_mean = {str(preset): kept,
                          str(WIDE_HUBER): mean_add([ask("", "rgbd", i, chosen["rgbd"], rays["rgbd"], WIDE_HUBER)
                                                     for i in views])}
            huber["rgbd"] = WIDE_HUBER if huber_mean[str(WIDE_HUBER)] < WIDE_HUBER_GAIN * kept else 0.0
    if fewer or wider:  # then the finer camera's with what was chosen
        for camera, folders in cameras.items():
            for i in range(len(folders)):
                ask(camera, "rgbd", i, chosen["rgbd"], rays["rgbd"], huber["rgbd"])
    if auto:  # both Jacobians on the first sequence (one more track), then the rest with the one chosen
        mean = {j: mean_add([f]) for j, f in firsts.items()}
        chosen["rgb"] = "differences" if mean["differences"] < DIFFERENCES_GAIN * mean["derivatives"] else "derivatives"
        for camera, folders in cameras.items():
            for i in range(len(folders)):
                ask(camera, "rgb", i, chosen["rgb"])
    out: dict = {}
    for camera, folders in cameras.items():
        fit: dict = {"fx": float(Dataset.open(folders[0]).camera.K[0, 0])}
        for modality in modalities:
            if camera == "" and modality == "rgb" and mean is not None:
                fit["rgb_add_m"] = mean
            if camera == "" and modality == "rgbd" and rays_mean is not None:
                fit["rgbd_add_m"] = rays_mean
            if camera == "" and modality == "rgbd" and huber_mean is not None:
                fit["rgbd_huber_add_m"] = huber_mean
            nees = [n for i in range(len(folders))
                    for n in asked[(camera, modality, i, chosen[modality], rays[modality], huber[modality])].result()[0]]
            fit[modality] = fit_track_scale(nees, 6 + len(tracks.model.joints))
            fit[f"{modality}_frames"] = len(nees)
        if camera == "":
            out = {"solvers": {m: default.solver_for(m == "rgbd") for m in modalities},
                   "jacobians": {m: chosen[m] for m in modalities},
                   **({"rays": {"rgbd": rays["rgbd"]}} if "rgbd" in modalities else {}),
                   **({"robust_scale": {"rgbd": huber["rgbd"] or preset}}
                      if "rgbd" in modalities else {}), **fit}
        else:
            out[camera] = fit
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
                      frames: int = SEQUENCE_FRAMES, bundle: Path | None = None, workers: int = 1) -> dict:
    """The model's own tracker factors (:func:`track_calibration`) on smooth sequences of ``tool`` of
    ``seeds`` at ``size`` (its views' camera) and, under ``fine``, at :func:`fine_size` (where
    :func:`narf_core.track.sigma_scale` interpolates between the two cameras), drawn into ``work``; with
    the ``seeds``. With ``workers`` > 1 and the model's ``bundle`` file, its tracks run in that many processes
    (the same factors). A ``ValueError`` where a modality held no frame."""
    from concurrent.futures.process import BrokenProcessPool

    cameras = {"": sequence_folders(tool, size, work, seeds, frames)}
    fine = fine_size(size)
    if fine is not None:
        cameras["fine"] = sequence_folders(tool, fine, work, seeds, frames)
    try:
        with _Tracks(model, bundle, min(workers, 2 * len(seeds) * len(cameras))) as tracks:
            out = track_calibration(tracks, cameras)
    except BrokenProcessPool:  # a worker died (killed, out of memory): the tracks again, here
        with _Tracks(model, None, 1) as tracks:
            out = track_calibration(tracks, cameras)
    return {**out, "seeds": list(seeds)}


def dataset_tool(dataset: Dataset) -> str | None:
    """The object that drew ``dataset`` (a procedural object's name or a URDF that still exists), from its
    generator's record; None for a dataset that does not name one (real images)."""
    tool = dataset.generator.get("tool")
    if not isinstance(tool, str) or (tool.endswith(".urdf") and not Path(tool).is_file()):
        return None
    return tool
