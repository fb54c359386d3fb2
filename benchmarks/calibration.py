"""Fit the model-error constants of an estimate's uncertainty (:data:`narf_core.estimate.MODEL_ERROR`)
on scenes the benchmarks do not use, and print the NEES coverage they give there.

    python -m narf_benchmarks.calibration --work runs/calibration [--write-bundle models/clamp.narf]

Data: ``narf bench estimate``'s protocol (10 deg / 2 cm perturbation, θ at mid-range) on a 160x120
dataset of seed 1 (its ``test`` and ``novel`` splits, every preset with the depth image and
without); the benchmarks use seed 0. ``--pool-track`` adds ``narf bench track``'s tracker on a 60-frame
sequence of seed 1, as :data:`~narf_core.estimate.MODEL_ERROR`'s defaults were fitted; the tracker has had
its own factor on σ since (``--tracker``, fitted after these constants on the bundle that holds them), so
by default its frames are left out and the single images alone set the classes they share with it. Per
scene or frame it keeps the true local error ``e`` (:func:`~narf_core.estimate.local_error`), the
statistical covariance at the estimate (no model error), the mean squared colour residual ``v``, the
pixel footprint at the object and the line of sight to it. The model error's σ is
``pixels · footprint · v / reference_variance`` (``exponent`` 1; without depth longer along the line
of sight: :func:`~narf_core.estimate.model_error_covariance`), ``reference_variance`` the median
``v`` of the ``shape`` class, and ``pixels`` per class of :func:`~narf_core.estimate._error_class`
the smallest whose 95 % regions hold 95 % of the class's errors. ``--inputs rgb`` (or ``rgbd``)
fits only the classes without depth (with it). ``--write-bundle`` stores the result in a bundle's
``metadata["uncertainty"]``.

    python -m narf_benchmarks.calibration --model M.narf --data DATASET [--write-bundle M.narf]

fits them on a labelled dataset of the model's own object instead (its ``test`` and ``novel`` splits, held
out from training): the way to a calibrated Σ for an object of your own (the defaults were fitted on
the clamp, those without depth on the clamp and lineman-a pooled).

    python -m narf_benchmarks.calibration --tracker --model M.narf --tool TOOL [--write-bundle M.narf]

fits only the tracker's own factor on a warm-started frame's σ (:func:`narf_core.track.sigma_scale`),
per modality (RGB-D, RGB only), for that model: its default tracker over smooth 60-frame sequences of
seeds 1-4 (``--track-seeds``) at 160x120 and at 640x480, the smallest factor (0.01 steps) whose 95 %
regions hold 95 % of the pooled frames' errors (:mod:`narf_core.train.track_sigma`, which ``narf train``
runs on seeds 1-3 of its dataset's object); ``--write-bundle`` stores it under
``metadata["uncertainty"]["track"]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from narf_core import estimate as E
from narf_core.bundle import NarfModel, load_bundle, save_bundle
from narf_core.data.dataset import Dataset
from narf_core.modes import choose_mode
from narf_core.geometry import Pinhole
from narf_core.threads import free_cores
from narf_core.train.track_sigma import COVERAGE, calibrate_tracker

PIXELS_GRID = np.geomspace(0.05, 50.0, 300)


def statistics(
    model: NarfModel, image: np.ndarray, mask: np.ndarray, depth: np.ndarray | None, camera: Pinhole,
    T: np.ndarray, joints: dict, options: E.EstimateOptions,
) -> dict:
    """What the uncertainty is made of at the estimate ``(T, joints)``: the statistical ``sigma``, the
    mean squared colour residual, the pixel footprint (m), the object's radius and the error class."""
    from narf_core.gauss_newton import Problem, covariance

    uses_depth = depth is not None and options.depth_weight > 0
    obs = E._observation(image, mask, depth if uses_depth else None, E._mask_box(mask, options.box_margin), 1,
                         model.aabb.device)
    T = torch.as_tensor(np.asarray(T, np.float64))
    param = E._Parameterisation.around(T, model)
    aabb = model.aabb.detach().double().cpu()
    centre = (aabb[0] + aabb[1]) / 2
    options = replace(options, mode=choose_mode(model, options.mode)[0])  # a Problem takes a resolved mode
    stat = covariance(Problem(model, options, param.radius, uses_depth), obs, camera, param, T,
                      model.kinematics.joint_vector(joints), centre, options.uncertainty_rays,
                      options.uncertainty_patch, torch.Generator().manual_seed(options.seed + 1))
    sight = E.line_of_sight(model, T)
    return {"sigma": stat.sigma.numpy(), "colour_variance": stat.colour_variance,
            "pixel_m": E.model_footprint(camera, T, centre, obs.shape), "radius": param.radius,
            "line_of_sight": sight[0].numpy(), "stretch": sight[1],
            "joint_speeds": E._joint_speeds(model, param.radius).numpy(), "class": E._error_class(options, uses_depth)}


def scene_rows(
    model: NarfModel, dataset: Dataset, scenes: int, inputs: tuple[str, ...] = ("rgbd", "rgb")
) -> list[dict]:
    """Every preset on ``scenes`` frames of each of the dataset's ``test`` and ``novel`` splits, with the
    depth image (``rgbd`` in ``inputs``; a preset without a depth term only without) and without (``rgb``)."""
    from narf_benchmarks.estimate import _preset_options, perturb_pose, pick_frames

    aabb = model.aabb.double()
    centre = ((aabb[0] + aabb[1]) / 2).numpy()
    rows = []
    for split in ("test", "novel"):
        for frame in pick_frames(dataset, split, scenes, 0):
            images = dataset.load(frame)
            mask = images.labels > 0
            for preset, given in ((p, g) for g in inputs for p in E.PRESETS):
                depth = images.depth if given == "rgbd" else None
                options = _preset_options(preset, 150, uncertainty=False)
                if given == "rgbd" and options.depth_weight == 0:
                    continue  # an estimate without depth whatever it is given: its row is an "rgb" one
                T_init = perturb_pose(frame.T_cam_obj, centre, 10.0, 0.02, np.random.default_rng([0, frame.id]))
                result = E.refine(model, images.rgb, mask, dataset.camera, T_init, depth=depth, options=options)
                rows.append({"preset": preset if given == "rgbd" else f"{preset} (rgb)", "split": split,
                             "frame": frame.id,
                             "e": E.local_error(result.T_cam_obj, result.joints, frame.T_cam_obj, frame.joints, model),
                             **statistics(model, images.rgb, mask, depth, dataset.camera, result.T_cam_obj,
                                          result.joints, options)})
    return rows


def track_rows(model: NarfModel, dataset: Dataset) -> list[dict]:
    """The default tracker (RGB-D) over a sequence; one row per frame it did not lose."""
    from narf_core.track import TrackOptions, track
    from narf_core.track_io import load_frames, sequence_frames

    options = TrackOptions(uncertainty_rays=0)
    frames = sequence_frames(dataset)
    rows = []
    results = track(model, load_frames(dataset, frames), dataset.camera, frames[0].T_cam_obj, frames[0].joints, options)
    for i, (frame, result) in enumerate(zip(frames, results)):
        if result.status == "lost":
            continue
        images = dataset.load(frame)
        step = options.reinit_options() if i == 0 or result.status == "reinitialised" else options.step_options(True)
        step = replace(step, uncertainty=True, uncertainty_rays=TrackOptions().uncertainty_rays)
        rows.append({"preset": "track", "split": "sequence", "frame": frame.id,
                     "e": E.local_error(result.T_cam_obj, result.joints, frame.T_cam_obj, frame.joints, model),
                     **statistics(model, images.rgb, images.labels > 0, images.depth, dataset.camera,
                                  result.T_cam_obj, result.joints, step)})
    return rows


def model_sigma(row: dict, calibration: dict) -> np.ndarray:
    """The model error's σ ``[6 + k]`` of one row under ``calibration``: the refiner's own
    (:func:`~narf_core.estimate.model_error_sigma`)."""
    return E.model_error_sigma(calibration, row["class"], row["pixel_m"], row["radius"], row["colour_variance"],
                               torch.as_tensor(row["joint_speeds"])).numpy()


def model_covariance(row: dict, calibration: dict) -> np.ndarray:
    """The model error's covariance ``[6+k, 6+k]`` of one row under ``calibration``: the refiner's own
    (:func:`~narf_core.estimate.model_error_covariance`)."""
    return E.model_error_covariance(torch.as_tensor(model_sigma(row, calibration)), row["class"],
                                    (torch.as_tensor(row["line_of_sight"]), row["stretch"])).numpy()


def inside(row: dict, calibration: dict) -> bool:
    """Whether the row's true error lies inside the 95 % region of its calibrated covariance."""
    S = row["sigma"] + model_covariance(row, calibration)
    e = np.asarray(row["e"])
    return float(e @ np.linalg.pinv(S, hermitian=True) @ e) <= E.chi2_quantile(COVERAGE, len(e))


def fit(rows: list[dict], kinds: tuple[str, ...] | None = None) -> dict:
    """``MODEL_ERROR``'s constants from ``rows`` (see the module docstring), only the ``pixels`` of the
    classes ``kinds`` where given (the others and the reference as in ``MODEL_ERROR``)."""
    shape = [r["colour_variance"] for r in rows if r["class"] == "shape"]
    reference = float(np.median(shape)) if shape and kinds is None else E.MODEL_ERROR["reference_variance"]
    calibration = {"reference_variance": reference, "exponent": 1.0, "pixels": dict(E.MODEL_ERROR["pixels"])}
    for kind in kinds or tuple(calibration["pixels"]):
        group = [r for r in rows if r["class"] == kind]
        for pixels in PIXELS_GRID if group else ():
            calibration["pixels"][kind] = float(pixels)  # the grid's largest where none holds the share
            if np.mean([inside(r, calibration) for r in group]) >= COVERAGE:
                break
        else:
            if group:
                print(f"calibration: no factor up to {PIXELS_GRID[-1]:g} pixels holds {COVERAGE:.0%} of the "
                      f"{kind!r} errors; kept the largest", file=sys.stderr)
    return calibration


def coverage(rows: list[dict], calibration: dict) -> dict[str, float]:
    """The share of rows inside their 95 % region, per preset (and the tracker)."""
    return {p: float(np.mean([inside(r, calibration) for r in rows if r["preset"] == p]))
            for p in sorted({r["preset"] for r in rows})}


def write_calibration(path: Path, key: str | None, value: dict) -> None:
    """Store ``value`` under the bundle's ``metadata["uncertainty"][key]`` (``key`` None: the
    constants themselves), keeping what else it holds."""
    target = load_bundle(path)
    own = dict(target.metadata.get("uncertainty") or {})
    own.update({key: value} if key else value)
    target.metadata["uncertainty"] = own
    save_bundle(path, target)


def main(argv: list[str] | None = None) -> int:
    from narf_benchmarks.track import sequence
    from narf_core.data.synth.generate import synthesize

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("runs/calibration"))
    parser.add_argument("--model", type=Path, default=Path("models/clamp.narf"))
    parser.add_argument("--tool", default="clamp", help="the procedural object whose data is synthesised")
    parser.add_argument("--data", type=Path,
                        help="a labelled dataset of the model's object (its test and novel splits) instead of "
                             "synthesised data: an object of your own; then the tracker's frames are not used")
    parser.add_argument("--scenes", type=int, default=17, help="per split")
    parser.add_argument("--frames", type=int, default=60, help="of --pool-track's and --tracker's sequences")
    parser.add_argument("--seed", type=int, default=1, help="of the data (the benchmarks use 0)")
    parser.add_argument("--inputs", nargs="+", choices=("rgbd", "rgb"), default=["rgbd", "rgb"],
                        help="the estimates fitted: with the depth image, without; only the classes these "
                             "reach are fitted (the others and the reference stay MODEL_ERROR's)")
    parser.add_argument("--write-bundle", type=Path, help="store the constants in this bundle's metadata")
    parser.add_argument("--pool-track", action="store_true",
                        help="pool the tracker's frames on a --frames sequence of --seed with the single images "
                             "(with rgbd; how MODEL_ERROR's defaults were fitted): by default left out, the "
                             "tracker's own factor being fitted after with --tracker")
    parser.add_argument("--tracker", action="store_true",
                        help="fit only the tracker's factors on σ, on smooth sequences of --track-seeds")
    parser.add_argument("--track-seeds", type=int, nargs="+", default=[1, 2, 3, 4],
                        help="of the sequences (the benchmark uses 0)")
    args = parser.parse_args(argv)
    if args.pool_track:
        clash = "--data" if args.data is not None else "--tracker" if args.tracker else (
            None if "rgbd" in args.inputs else "--inputs rgb")
        if clash:
            parser.error(f"--pool-track: not with {clash} (it pools a synthesised track's RGB-D frames with the "
                         "single images)")
    model = load_bundle(args.model)
    if args.tracker:
        factors = calibrate_tracker(model, args.tool, (160, 120), args.work / f"track-{Path(args.tool).stem}",
                                    args.track_seeds, args.frames,  # one folder per object: its own sequences
                                    bundle=args.model, workers=free_cores())  # its tracks on the free cores
        print(json.dumps({"track": factors}, indent=1))
        if args.write_bundle:
            write_calibration(args.write_bundle, "track", factors)
        return 0
    if args.data is not None:
        try:
            rows = scene_rows(model, Dataset.open(args.data), args.scenes, tuple(args.inputs))
        except (OSError, ValueError) as e:
            parser.error(f"--data {args.data}: {e}")
    else:
        root = args.work / f"{args.tool}-160x120-seed{args.seed}"
        if not (root / "scene.json").exists():
            synthesize(args.tool, root, size=(160, 120), views=24, seed=args.seed)
        rows = scene_rows(model, Dataset.open(root), args.scenes, tuple(args.inputs))
        if args.pool_track:  # (with rgbd: checked above)
            rows += track_rows(model, Dataset.open(sequence(args.work, args.tool, (160, 120), args.frames, False,
                                                            seed=args.seed)))
    calibration = fit(rows, None if len(args.inputs) == 2 else tuple(sorted({r["class"] for r in rows})))
    print(json.dumps({"calibration": calibration, "coverage_95_on_fit_data": coverage(rows, calibration),
                      "rows": len(rows)}, indent=1))
    if args.write_bundle:
        write_calibration(args.write_bundle, None, calibration)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
