"""``narf bench estimate``: the paper's pose + configuration experiment (Table II) on our data.

Protocol (NARF22 §IV-C): per tool, ``scenes`` frames of the ``test`` split (and separately of
``novel``) picked with a fixed seed; the initial pose is the labelled pose perturbed by a rotation
uniform within ±10 deg in azimuth and elevation (about the camera's vertical and horizontal axes,
through the object's centre) and a translation of length uniform in [0, 2 cm] in a uniform
direction; θ starts at mid-range for every joint; 150 Adam iterations. Each scene is refined with
two presets of options: ``paper`` (the paper's masked photometric loss) and ``robust`` (plus
silhouette and depth terms, 4 joint starts, coarse-to-fine). Reported per object (the tools and the
multi-joint objects), split, render mode and preset: ADD mean/std, the error of every joint,
mean/std (m or deg; the table in mm or deg), success rates (ADD < 1 cm, ADD < 10% of the
diameter) and seconds per scene; the error along the iterations and along wall time (poses
recorded every few iterations); and a sweep of the perturbation size (1x, 2x, 3x) per preset.

With datasets written with label noise, the refiner sees the noisy labels (mask and initial pose)
and is scored against the generator's clean ground truth.

:func:`run` takes models and datasets; :func:`main` (behind the CLI) first synthesises missing
datasets and trains missing models in the work folder (the layout ``narf bench render`` uses), or
with ``--quick`` takes the bundled models and small datasets.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from narf_benchmarks.checkpoint import SceneLog, remove_logs, scene_log
from narf_benchmarks.load import describe_machine, machine
from narf_core.bundle import NarfModel, load_bundle
from narf_core.cli import option_overrides
from narf_core.data.dataset import Dataset, Frame
from narf_core.estimate import PRESETS, UNOBSERVED_CODE, EstimateOptions, EstimateResult, chi2_quantile, refine
from narf_core.geometry import so3_exp, transform_points
from narf_core.metrics import add
from narf_core.modes import choose_mode

PAPER_TABLE_II = {"clamp": {"add_m": (0.0107, 0.0043), "configuration_error_m": (0.0073, 0.0065)}}
RECORD_EVERY = 10  # iterations between recorded poses for the error-vs-iterations curves
SWEEP_FIGURES = ("add_mean_m", "add<1cm", "add<0.1d", "seconds_mean", "iterations_mean")


def perturb_pose(
    T_cam_obj: np.ndarray, centre_obj: np.ndarray, rotation_deg: float, translation_m: float, rng: np.random.Generator
) -> np.ndarray:
    """``T_cam_obj [4,4]`` moved as in the paper's protocol.

    Azimuth and elevation uniform in ``±rotation_deg`` (rotations about the camera's y and x axes,
    through the object's centre ``centre_obj [3]`` given in the object frame), then a translation of
    length uniform in ``[0, translation_m]`` in a direction uniform on the sphere.
    """
    azimuth, elevation = np.radians(rng.uniform(-rotation_deg, rotation_deg, size=2))
    R = so3_exp(torch.tensor([0.0, azimuth, 0.0], dtype=torch.float64)) @ so3_exp(
        torch.tensor([elevation, 0.0, 0.0], dtype=torch.float64)
    )
    T = torch.as_tensor(T_cam_obj, dtype=torch.float64)
    c = transform_points(T, torch.as_tensor(centre_obj, dtype=torch.float64))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    shift = torch.as_tensor(direction * rng.uniform(0.0, translation_m))
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = R @ (T[:3, 3] - c) + c + shift
    return out.numpy()


def pick_frames(dataset: Dataset, split: str, scenes: int, seed: int) -> list[Frame]:
    """``scenes`` frames of ``split`` chosen with ``seed`` (all of them if there are fewer), in id order."""
    frames = dataset.frames(split)
    if not frames:
        raise ValueError(f"dataset {dataset.root} has no frames in split {split!r}")
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(frames), size=min(scenes, len(frames)), replace=False)
    return [frames[i] for i in sorted(chosen)]


def _clean_frames(dataset: Dataset) -> dict[int, Frame]:
    """The ground truth to score against: the generator's clean frames where labels are noisy."""
    clean = Dataset.open(dataset.root, clean=True) if dataset.noisy else dataset
    return {f.id: f for f in clean.frames()}


def _add_along_run(
    model: NarfModel, result: EstimateResult, truth: Frame, T_init: np.ndarray
) -> list[tuple[int, float, float]]:
    """``(iteration, seconds, ADD)`` at the start (mid-range θ) and at every recorded snapshot of a run."""
    kin = model.kinematics
    links_true = kin.link_poses(kin.joint_vector(truth.joints)).numpy()

    def add_at(T: np.ndarray, links: np.ndarray) -> float:
        return float(add(model.sample_points, links_true, truth.T_cam_obj, links, T, model.links))

    rows = [(0, 0.0, add_at(T_init, kin.link_poses(kin.mid_configuration()).numpy()))]
    for s in result.history:
        rows.append((s.iteration, s.seconds, add_at(s.T_cam_obj, kin.link_poses(kin.joint_vector(s.joints)).numpy())))
    return rows


def _has_points(model: NarfModel) -> bool:
    return any(len(points) for points in model.sample_points.values())


def view_errors(model: NarfModel, T_est: np.ndarray, joints_est: Mapping[str, float], truth: Frame) -> dict[str, float]:
    """How the estimate's surface points sit against the truth's, seen from the camera: the mean
    displacement ``mean(p_est - p_true)`` split into its component along the line of sight to the
    true points' centroid (signed, metres; positive = estimated too far) and the rest (across it).
    RGB-only refinement leaves the first nearly unconstrained (a scale change of the silhouette)."""
    from narf_core.metrics import _camera_points

    kin = model.kinematics
    true = _camera_points(model.sample_points, kin.link_poses(kin.joint_vector(truth.joints)).numpy(),
                          truth.T_cam_obj, model.links, "true")
    est = _camera_points(model.sample_points, kin.link_poses(kin.joint_vector(dict(joints_est))).numpy(),
                         T_est, model.links, "est")
    shift = (est - true).mean(0)
    sight = true.mean(0) / np.linalg.norm(true.mean(0))
    along = float(shift @ sight)
    return {"along_view_m": along, "across_view_m": float(np.linalg.norm(shift - along * sight))}


def run_scenes(
    model: NarfModel,
    dataset: Dataset,
    frames: Sequence[Frame],
    options: EstimateOptions,
    *,
    scale: float = 1.0,
    perturbation: tuple[float, float] = (10.0, 0.02),
    seed: int = 0,
    progress: bool = False,
    log: SceneLog | None = None,
) -> list[dict]:
    """Refine every frame from a perturbed start; one JSON-able row per scene.

    The perturbation of a scene depends only on ``seed`` and the frame id, so runs with other
    options or modes start from the same poses. ``log``: each finished row is kept there as it
    finishes, and a scene it already holds is not refined again (a stopped run resumes).
    """
    from tqdm import tqdm

    truth = _clean_frames(dataset)
    aabb = model.aabb.double().cpu()
    centre = ((aabb[0] + aabb[1]) / 2).numpy()
    rows = []
    if log is not None:
        log.note(len(frames))
    for frame in tqdm(frames, desc=f"{model.name} {options.mode} x{scale:g}", disable=not progress, leave=False):
        kept = log.get(frame.id) if log is not None else None
        if kept is not None:
            rows.append(kept)
            continue
        images = dataset.load(frame)
        rng = np.random.default_rng([seed, frame.id])
        T_init = perturb_pose(frame.T_cam_obj, centre, perturbation[0] * scale, perturbation[1] * scale, rng)
        gt = truth[frame.id]
        result = refine(
            model,
            images.rgb,
            images.labels > 0,
            dataset.camera,
            T_init,
            depth=images.depth,
            options=options,
            ground_truth=(gt.T_cam_obj, gt.joints),
        )
        rows.append({
            "frame": frame.id,
            "status": result.status,
            "iterations": result.iterations,
            "seconds": result.seconds,
            "loss": result.loss,
            "metrics": result.metrics,
            "warnings": list(result.warnings),
            **(view_errors(model, result.T_cam_obj, result.joints, gt) if _has_points(model) else {}),
            "along_run": _add_along_run(model, result, gt, T_init) if options.record_every else [],
        })
        if log is not None:
            rows[-1] = log.add(rows[-1])
    return rows


def scenes_log(
    out_dir: Path, tool: str, block: str, model: NarfModel, dataset: Dataset, frames: Sequence[Frame],
    options: EstimateOptions, *, scale: float = 1.0, perturbation: tuple[float, float] = (10.0, 0.02), seed: int = 0,
) -> SceneLog | None:
    """The :class:`~narf_benchmarks.checkpoint.SceneLog` of one block of :func:`run_scenes` under ``out_dir``,
    keyed by everything its rows depend on: the options, the starts, the frames and the data they are read from
    (``None`` for a model never saved: :func:`~narf_benchmarks.checkpoint.scene_log`)."""
    generator = hashlib.sha256(json.dumps(dataset.generator, sort_keys=True, default=str).encode()).hexdigest()
    key = {"options": asdict(options), "scale": scale, "perturbation": list(perturbation), "seed": seed,
           "frames": [f.id for f in frames], "view": type(dataset).__name__,
           "dataset": {"root": str(Path(dataset.root).resolve()), "generator": generator}}
    return scene_log(out_dir, tool, block, key, model)


def _preset_options(preset: str, iterations: int, /, **overrides) -> EstimateOptions:
    """A preset's options with ``overrides``; the protocol's ``iterations`` applies to the Adam presets (the
    Gauss-Newton preset keeps its own), and an ``iterations`` among ``overrides`` (``--set``) to any."""
    options = EstimateOptions.preset(preset, **overrides)
    if options.solver == "gauss-newton" or "iterations" in overrides:
        return options
    return EstimateOptions.preset(preset, iterations=iterations, **overrides)


def summarise(model: NarfModel, rows: list[dict]) -> dict:
    """Table II's figures over scenes: ADD (m), per-joint error (m or deg), success rates, seconds."""
    adds = np.array([r["metrics"]["add"] for r in rows])
    out = {
        "scenes": len(rows),
        "add_mean_m": float(adds.mean()),
        "add_std_m": float(adds.std()),
        "add_s_mean_m": float(np.mean([r["metrics"]["add_s"] for r in rows])),
        "add<1cm": float(np.mean([r["metrics"]["add<1cm"] for r in rows])),
        "add<0.1d": float(np.mean([r["metrics"]["add<0.1d"] for r in rows])),
        "seconds_mean": float(np.mean([r["seconds"] for r in rows])),
        "iterations_mean": float(np.mean([r["iterations"] for r in rows])),
        "no_overlap": sum(r["status"] == "no_overlap" for r in rows),
        "joints": {},
    }
    if all("along_view_m" in r for r in rows):  # where the error lies: along the line of sight or across it
        out["along_view_abs_mean_m"] = float(np.mean([abs(r["along_view_m"]) for r in rows]))
        out["across_view_mean_m"] = float(np.mean([r["across_view_m"] for r in rows]))
    # Calibration: the share of scenes whose true error lies inside the estimate's 95 % region.
    bound = chi2_quantile(0.95, 6 + len(model.joints))
    nees = [r["metrics"].get("nees") for r in rows]
    nees = [v for v in nees if v is not None and np.isfinite(v)]
    out["nees_median"] = float(np.median(nees)) if nees else None
    out["nees_inside_95"] = float(np.mean([v <= bound for v in nees])) if nees else None
    for joint in model.joints:
        errors = np.array([r["metrics"][f"joint_error/{joint.name}"] for r in rows])
        unit = "m" if joint.type == "prismatic" else "deg"
        if unit == "deg":
            errors = np.degrees(errors)
        out["joints"][joint.name] = {"unit": unit, "mean": float(errors.mean()), "std": float(errors.std())}
        # the scenes whose estimate said the view hardly constrains this joint (narf_core.estimate.unobserved_joints)
        flagged = np.array([any(w.startswith(f"{UNOBSERVED_CODE}: {joint.name}: ") for w in r.get("warnings", []))
                            for r in rows], dtype=bool)
        if flagged.any():
            seen = errors[~flagged]
            out["joints"][joint.name].update({
                "unobserved": int(flagged.sum()),
                "observed_mean": float(seen.mean()) if len(seen) else None,
                "observed_std": float(seen.std()) if len(seen) else None,
            })
    return out


def _curve(rows: list[dict], iterations: int) -> dict:
    """Mean ADD (and seconds) at iteration 0 and every ``RECORD_EVERY``; a run that stopped early
    counts with its final estimate from then on."""
    steps = list(range(0, iterations + 1, RECORD_EVERY))
    at = np.zeros((len(rows), len(steps), 2))
    for i, row in enumerate(rows):
        seen = {it: (sec, value) for it, sec, value in row["along_run"]}
        at[i] = [seen.get(step, (row["seconds"], row["metrics"]["add"])) for step in steps]
    return {"iteration": steps, "seconds_mean": at[..., 0].mean(0).tolist(), "add_mean_m": at[..., 1].mean(0).tolist()}


def _as_model(item: NarfModel | str | Path) -> NarfModel:
    return item if isinstance(item, NarfModel) else load_bundle(item)


def _as_dataset(item: Dataset | str | Path) -> Dataset:
    return item if isinstance(item, Dataset) else Dataset.open(item)


def _pairs(models, datasets) -> list[tuple[str, NarfModel, Dataset]]:
    """``(tool, model, dataset)``: mappings paired by key, sequences in order."""
    if isinstance(models, Mapping) != isinstance(datasets, Mapping):
        raise ValueError("give models and datasets both as mappings (by tool) or both as sequences (in order)")
    if isinstance(models, Mapping):
        missing = sorted(set(models) ^ set(datasets))
        if missing:
            raise ValueError(f"models and datasets must name the same tools; unmatched: {missing}")
        keys = list(models)
        return [(k, _as_model(models[k]), _as_dataset(datasets[k])) for k in keys]
    if len(models) != len(datasets):
        raise ValueError(f"got {len(models)} models but {len(datasets)} datasets; pair them one to one")
    pairs = []
    for m, d in zip(models, datasets):
        model = _as_model(m)
        pairs.append((model.name, model, _as_dataset(d)))
    return pairs


def run(
    models: Mapping[str, NarfModel | str | Path] | Sequence[NarfModel | str | Path],
    datasets: Mapping[str, Dataset | str | Path] | Sequence[Dataset | str | Path],
    *,
    out_dir: str | Path,
    splits: tuple[str, ...] = ("test", "novel"),
    scenes: int | None = None,
    perturbation: tuple[float, float] = (10.0, 0.02),
    scale_sweep: tuple[float, ...] = (1.0, 2.0, 3.0),
    iterations: int = 150,
    modes: tuple[str, ...] = ("narf", "parts"),
    presets: tuple[str, ...] = PRESETS,
    seed: int = 0,
    quick: bool = False,
    progress: bool = True,
    overrides: Mapping[str, object] | None = None,
) -> dict:
    """Run the protocol; writes ``estimate.json``, ``estimate.md`` and ``estimate_*.png`` into ``out_dir``.

    ``models`` and ``datasets`` pair one model with one dataset (mappings by tool name, or sequences
    in order; paths are opened). The table has one row per tool, split, render mode and refiner
    preset (:meth:`EstimateOptions.preset`); the curves and the perturbation sweep (every preset,
    ``perturbation * scale``) use the first split and the first mode the model renders.
    ``perturbation`` is ``(degrees, metres)``; ``scenes`` defaults to the paper's 17 (3 with
    ``quick``); ``quick`` runs the first split and the first mode only and the sweep at its smallest
    and largest scale. ``overrides`` (option fields such as ``pose_starts``) apply to every preset.
    Modes a model cannot render
    (``parts`` without part fields) and splits a dataset lacks are skipped and listed under ``skipped``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scenes = scenes if scenes is not None else (3 if quick else 17)
    overrides = dict(overrides or {})
    if quick:
        modes, splits = modes[:1], splits[:1]
        scale_sweep = tuple(sorted({min(scale_sweep), max(scale_sweep)}))
    config = {
        "splits": list(splits), "scenes": scenes, "perturbation_deg_m": list(perturbation),
        "scale_sweep": list(scale_sweep), "iterations": iterations, "modes": list(modes), "presets": list(presets),
        "seed": seed, "quick": quick, "overrides": overrides,
        "options": {name: asdict(_preset_options(name, iterations, **overrides)) for name in presets},
    }
    table, curves, sweep, skipped = [], {}, [], []
    jacobian: dict[str, dict] = {}  # tool -> CPU seconds per Gauss-Newton Jacobian, by method
    auto: dict[str, dict] = {}  # tool -> the mode `auto` refines it in, and why
    pairs = _pairs(models, datasets)
    for tool, model, dataset in pairs:
        auto[tool] = dict(zip(("mode", "reason"), choose_mode(model)))
        first: dict[str, list[dict]] = {}  # preset -> rows of the first split and mode (reused by the sweep)
        sweep_frames, sweep_mode = None, None
        for split in splits:
            if not dataset.frames(split):
                skipped.append({"tool": tool, "split": split, "reason": "the dataset has no frames in this split"})
                continue
            frames = pick_frames(dataset, split, scenes, seed)
            for mode in modes:
                if mode == "parts" and not model.has_parts:
                    skipped.append({"tool": tool, "mode": mode, "reason": "the model has no part fields"})
                    continue
                sweep_frames, sweep_mode = (frames, mode) if sweep_mode is None else (sweep_frames, sweep_mode)
                for preset in presets:
                    options = _preset_options(preset, iterations, **overrides, mode=mode, record_every=RECORD_EVERY,
                                              seed=seed)
                    log = scenes_log(out_dir, tool, f"{split}-{mode}-{preset}", model, dataset, frames, options,
                                     perturbation=perturbation, seed=seed)
                    rows = run_scenes(model, dataset, frames, options, perturbation=perturbation, seed=seed,
                                      progress=progress, log=log)
                    table.append({"tool": tool, "split": split, "mode": mode, "preset": preset, **summarise(model, rows),
                                  "scenes_detail": rows})
                    if frames is sweep_frames:
                        curves[f"{tool} {mode} {preset}"] = _curve(rows, iterations)
                        if mode == sweep_mode:
                            first[preset] = rows
        for preset in presets if sweep_mode else ():
            options = _preset_options(preset, iterations, **overrides, mode=sweep_mode, seed=seed)
            for scale in scale_sweep:
                if scale == 1:
                    rows = first[preset]  # the same runs as the table's (same starts and seeds)
                else:
                    log = scenes_log(out_dir, tool, f"sweep-{sweep_mode}-{preset}-x{scale:g}", model, dataset,
                                     sweep_frames, options, scale=scale, perturbation=perturbation, seed=seed)
                    rows = run_scenes(model, dataset, sweep_frames, options, scale=scale, perturbation=perturbation,
                                      seed=seed, progress=progress, log=log)
                s = summarise(model, rows)
                sweep.append({"tool": tool, "mode": sweep_mode, "preset": preset, "scale": scale,
                              "rotation_deg": perturbation[0] * scale, "translation_m": perturbation[1] * scale,
                              **{k: s[k] for k in SWEEP_FIGURES}})
        if "gauss-newton" in presets and sweep_frames:
            from narf_benchmarks.jacobian import measure

            jacobian[tool] = measure(model, dataset, sweep_frames[0])
    result = {"config": config, "table": table, "curves": curves, "sweep": sweep, "skipped": skipped,
              "paper": PAPER_TABLE_II, "jacobian": jacobian, "auto": auto, "machine": machine(m for _, m, _ in pairs)}
    (out_dir / "estimate.json").write_text(json.dumps(result, indent=1))
    (out_dir / "estimate.md").write_text(markdown(result))
    remove_logs(out_dir)
    plot_curves(curves, out_dir / "estimate_error_vs_iterations.png")
    plot_sweep(sweep, out_dir / "estimate_sweep.png")
    return result


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"


def unobserved_note(joint: dict, scale: float, unit: str, digits: int = 2) -> str:
    """`` (N flagged unobserved; the others mean ± std unit)`` for a joint of :func:`summarise` that some
    scenes' estimates flagged (``unobserved_joint``), else empty."""
    if not joint.get("unobserved"):
        return ""
    rest = ("" if joint["observed_mean"] is None else
            f"; the others {scale * joint['observed_mean']:.{digits}f} ± {scale * joint['observed_std']:.{digits}f} {unit}")
    return f" ({joint['unobserved']} flagged unobserved{rest})"


def _fmt_joints(joints: dict) -> str:
    """Each joint's error, mean ± std: prismatic joints in mm, revolute ones in degrees; where some scenes'
    estimates flagged the joint unobserved, how many, and the error over the others."""
    def one(j: dict) -> str:
        scale, unit = (1000, "mm") if j["unit"] == "m" else (1, j["unit"])
        return f"{scale * j['mean']:.2f} ± {scale * j['std']:.2f} {unit}{unobserved_note(j, scale, unit)}"

    return "<br>".join(f"{name}: {one(j)}" for name, j in joints.items()) or "-"


def markdown(result: dict) -> str:
    """Table II's shape per tool, split, mode and preset, the paper's clamp row, and the perturbation sweep."""
    c = result["config"]
    lines = [
        f"Pose + configuration refinement: {c['scenes']} scenes per tool and split, initial pose perturbed by "
        f"±{c['perturbation_deg_m'][0]:g} deg (azimuth, elevation) and ≤ {100 * c['perturbation_deg_m'][1]:g} cm, "
        f"θ at mid-range, {c['iterations']} iterations. Presets: `paper` = the paper's masked photometric loss "
        "and settings; `robust` = plus silhouette and depth terms, 4 joint starts, coarse-to-fine; "
        "`gauss-newton` = the same terms, Levenberg-Marquardt with Huber weights, its own iteration count. "
        "'inside 95 % region': share of scenes whose true error lies inside the estimate's χ² 95 % region."
        + describe_machine(result.get("machine"))
        + "".join(f" Every preset with `{k}: {v}`." for k, v in c.get("overrides", {}).items()),
        "",
        "| tool | split | mode | preset | N | ADD (cm) | per-joint error | ADD < 1 cm | ADD < 10% d "
        "| s/scene | iterations | inside 95 % region | NEES median |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["table"]:
        lines.append(
            f"| {r['tool']} | {r['split']} | {r['mode']} | {r['preset']} | {r['scenes']} "
            f"| {100 * r['add_mean_m']:.2f} ± {100 * r['add_std_m']:.2f} | {_fmt_joints(r['joints'])} "
            f"| {100 * r['add<1cm']:.0f}% | {100 * r['add<0.1d']:.0f}% | {r['seconds_mean']:.2f} | {r['iterations_mean']:.0f} "
            f"| {_pct(r.get('nees_inside_95'))} | {_num(r.get('nees_median'))} |"
        )
    for tool, p in result["paper"].items():
        lines.append(
            f"| {tool} (paper: real data, GPU, FastNeRF) | test | narf | paper | 17 "
            f"| {100 * p['add_m'][0]:.2f} ± {100 * p['add_m'][1]:.2f} "
            f"| {1000 * p['configuration_error_m'][0]:.2f} ± {1000 * p['configuration_error_m'][1]:.2f} mm | - | - | - | 150 | - | - |"
        )
    lines += [
        "",
        "Perturbation sweep (first split and mode):",
        "",
        "| tool | mode | preset | rotation (deg) | translation (cm) | ADD (cm) | ADD < 1 cm | ADD < 10% d | s/scene |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in result["sweep"]:
        lines.append(
            f"| {s['tool']} | {s['mode']} | {s['preset']} | ±{s['rotation_deg']:g} "
            f"| ≤ {100 * s['translation_m']:g} | {100 * s['add_mean_m']:.2f} | {100 * s['add<1cm']:.0f}% "
            f"| {100 * s['add<0.1d']:.0f}% | {s['seconds_mean']:.2f} |"
        )
    if result.get("jacobian"):
        from narf_benchmarks.jacobian import markdown as jacobian_markdown

        lines += jacobian_markdown(result["jacobian"])
    for tool, a in result.get("auto", {}).items():
        lines.append(f"\n`auto` refines {tool} in {a['mode']} mode: {a['reason']}.")
    for s in result["skipped"]:
        what = s.get("mode") or f"split {s['split']}"
        lines.append(f"\nSkipped {s['tool']} / {what}: {s['reason']}.")
    return "\n".join(lines) + "\n"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_curves(curves: dict[str, dict], path: Path) -> None:
    """Mean ADD against iterations and against wall time, one line per tool and mode."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for name, c in curves.items():
        left.plot(c["iteration"], [100 * v for v in c["add_mean_m"]], "o-", ms=3, label=name)
        right.plot(c["seconds_mean"], [100 * v for v in c["add_mean_m"]], "o-", ms=3, label=name)
    left.set_xlabel("iteration")
    right.set_xlabel("seconds (wall)")
    left.set_ylabel("mean ADD (cm)")
    for ax in (left, right):
        ax.axhline(1.0, color="grey", lw=0.8, ls="--")
        ax.grid(alpha=0.3)
    left.legend(fontsize=8)
    fig.suptitle("Refinement error along the run")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_sweep(sweep: list[dict], path: Path) -> None:
    """Success rate (ADD < 10% d) and seconds against the perturbation scale, one line per tool and preset."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for key in sorted({(s["tool"], s["preset"]) for s in sweep}):
        rows = sorted((s for s in sweep if (s["tool"], s["preset"]) == key), key=lambda s: s["scale"])
        label = f"{key[0]} {key[1]}"
        style = "s--" if key[1] == "paper" else "o-"
        left.plot([s["scale"] for s in rows], [100 * s["add<0.1d"] for s in rows], style, label=label)
        right.plot([s["scale"] for s in rows], [s["seconds_mean"] for s in rows], style, label=label)
    left.set_ylabel("success, ADD < 10% diameter (%)")
    right.set_ylabel("seconds per scene (wall)")
    for ax in (left, right):
        ax.set_xlabel("perturbation scale (1 = 10 deg, 2 cm)")
        ax.grid(alpha=0.3)
    left.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _prepare(args: argparse.Namespace, tool: str, noise: bool) -> tuple[NarfModel, Dataset] | None:
    """The model and the 160x120 dataset of a tool, made if missing (``None``: no bundled model in quick mode)."""
    suffix = "-noise" if noise else ""
    root = args.work / "data" / f"{tool}-160x120{suffix}{'-quick' if args.quick else ''}"
    if not (root / "scene.json").exists():  # the generator (pybullet) only where data is missing
        from narf_core.data.synth.generate import NoiseOptions, synthesize

        synthesize(tool, root, size=(160, 120), views=24 if args.quick else 200, seed=0,
                   noise=NoiseOptions.preset("paper") if noise else None, progress=True)
    bundled = args.models / f"{tool}.narf"
    if args.quick or (bundled.exists() and not noise):
        return (load_bundle(bundled, args.device), Dataset.open(root)) if bundled.exists() else None
    path = args.work / "models" / f"{tool}{suffix}.narf"
    if not path.exists():
        from narf_core.train.pipeline import train

        train(root, path, command="narf bench estimate", progress=True)
    return load_bundle(path, args.device), Dataset.open(root)


def run_arguments(args: argparse.Namespace) -> dict:
    """The keyword arguments of :func:`run` that the command line chose (the rest keep their defaults)."""
    chosen = {k: v for k, v in (("presets", tuple(getattr(args, "presets", None) or ())),
                                ("scale_sweep", tuple(getattr(args, "scales", None) or ())),
                                ("scenes", getattr(args, "scenes", None)),
                                ("modes", tuple(getattr(args, "modes", None) or ()))) if v}
    if getattr(args, "seed", None) is not None:
        chosen["seed"] = args.seed
    overrides = {} if getattr(args, "pose_starts", None) is None else {"pose_starts": args.pose_starts}
    overrides.update(option_overrides(getattr(args, "set", None) or []))
    if overrides:
        chosen["overrides"] = overrides
    return chosen


def main(args: argparse.Namespace) -> int:
    """``narf bench estimate``: ``args`` has ``work``, ``tools``, ``noise``, ``quick``, ``models``, ``json``
    and optionally ``presets``, ``scales`` (the perturbation sweep), ``scenes`` (per split), ``modes`` (the
    render modes), ``seed`` (the frames, the starts and the refiner's), ``pose_starts`` (every preset's
    option) and ``set`` (``--set``: any option of every preset, over ``pose_starts``)."""
    chosen = run_arguments(args)  # a bad --set is refused before any data is made
    if args.tools:
        tools = tuple(args.tools)
    elif args.quick:
        tools = tuple(sorted(p.stem for p in args.models.glob("*.narf")))
    else:
        from narf_benchmarks.render import all_tools

        tools = all_tools()
    models, datasets, missing = {}, {}, []
    for noise in (False, True) if args.noise else (False,):
        for tool in tools:
            pair = _prepare(args, tool, noise)
            name = f"{tool} (noise)" if noise else tool
            if pair is None:
                missing.append(name)
                continue
            models[name], datasets[name] = pair
    if not models:
        names = ", ".join(missing) or "any tool"
        raise ValueError(f"no model to benchmark: {args.models} has no bundled model for {names}")
    if missing:
        print(f"narf bench estimate: skipping {', '.join(missing)}: no bundled model in {args.models}", file=sys.stderr)
    result = run(models, datasets, out_dir=args.work / "estimate", quick=args.quick, **chosen)
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0
