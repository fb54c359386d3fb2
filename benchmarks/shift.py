"""``narf bench shift``: Table II's protocol on physically-based test images with real-sensor faults.

The models are trained on pybullet TinyRenderer images with perfect depth and masks; here the same
objects, poses and configurations are path-traced by Mitsuba (:mod:`narf_core.data.synth.restyle`:
other lights, gloss, shadows, a table and clutter) at the camera's native size, and each condition
of :data:`narf_core.data.synth.faults.CONDITIONS` adds faults: ``lighting`` (none), ``noise``
(exposure, white balance, blur, shot/read noise, JPEG), ``depth`` (stereo noise, holes, 1 mm steps),
``mask`` (erosion/dilation, a missing or extra blob, a soft edge), ``occlusion-20`` and
``occlusion-40`` (that share of the tool hidden; the mask is the visible part) and ``all`` (noise,
depth, mask and occlusion-20).

Per tool, condition, split, input (``rgb``: no depth given; ``rgbd``), preset and perturbation
scale, the scenes are refined with :func:`narf_benchmarks.estimate.run_scenes` (the protocol of
``narf bench estimate``: starts perturbed by ±10 deg and ≤ 2 cm times the scale, θ at mid-range)
and scored against the ground truth: ADD mean/std, share under 1 cm, per-joint error (m or deg),
where the error lies (the mean displacement of the surface points along the line of sight, and
across it: an RGB-only view constrains the distance least), seconds per scene, and how many frames
drew each observation warning (:func:`narf_core.observation.check_observation`). ``--set
OPTION=JSON`` changes one refiner option in every preset (A/B runs of a single option). The
issue's targets are checked in the table.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from narf_benchmarks.checkpoint import remove_logs
from narf_benchmarks.estimate import (
    _preset_options,
    _pyplot,
    pick_frames,
    run_scenes,
    scenes_log,
    summarise,
    unobserved_note,
)
from narf_benchmarks.load import describe_machine, machine
from narf_core.bundle import NarfModel
from narf_core.cli import option_overrides
from narf_core.data.dataset import Dataset, FrameImages
from narf_core.estimate import PRESETS
from narf_core.observation import check_observation

INPUTS = ("rgb", "rgbd")
ALL_CONDITIONS = ("lighting", "noise", "depth", "mask", "occlusion-20", "occlusion-40", "all")
# issue #15's targets: (condition, input) -> (ADD mean at most, share under 1 cm at least), at scale 1
TARGETS = {
    ("lighting", "rgb"): (0.006, 0.95),
    ("depth", "rgbd"): (0.004, None),
    ("all", "rgb"): (0.010, 0.90),
    ("all", "rgbd"): (0.010, 0.90),
}


class _WithoutDepth:
    """A dataset whose frames load without depth (the RGB-only input); everything else delegates."""

    def __init__(self, dataset: Dataset) -> None:
        self._dataset = dataset

    def __getattr__(self, name: str):
        return getattr(self._dataset, name)

    def load(self, frame) -> FrameImages:
        images = self._dataset.load(frame)
        return FrameImages(images.rgb, None, images.labels)


def shifted_sets(
    source: Dataset, out: Path, frame_ids: list[int], *, conditions: tuple[str, ...], size: tuple[int, int],
    spp: int, seed: int, progress: bool = True,
) -> dict[str, Dataset]:
    """The restyled datasets of ``frame_ids``, one per condition, made (or remade) in ``out`` unless
    ``out/<condition>`` already holds these frames (and maybe more: pick yours with
    :func:`source_frames`) rendered with the same settings and faults (:data:`faults.VERSION`). A set
    remade for frames it lacks keeps the frames it held (one split's run after the other's does not
    drop the first's)."""
    from narf_core.data.synth import faults
    from narf_core.data.synth.restyle import restyle

    def held(name: str) -> set[int] | None:
        """The source frames ``out/<name>`` holds, where made with these settings and faults; else None."""
        try:
            g = Dataset.open(out / name).generator.get("restyle", {})
        except (ValueError, OSError):
            return None
        same = (g.get("size") == list(size) and g.get("spp") == spp and g.get("seed") == seed
                and g.get("faults_version", 1) == faults.VERSION)
        return set(g.get("source_frames") or []) if same else None

    sets = {name: held(name) for name in conditions}
    missing = tuple(name for name in conditions if sets[name] is None or not set(frame_ids) <= sets[name])
    if missing:
        known = {f.id for f in source.frames()}
        kept = set().union(*(sets[name] or set() for name in missing)) & known
        restyle(source.root, out, conditions=missing, size=size, seed=seed, spp=spp,
                frame_ids=sorted(set(frame_ids) | kept), overwrite=True, progress=progress)
    return {name: Dataset.open(out / name) for name in conditions}


def source_frames(dataset: Dataset, split: str, source_ids: set[int]) -> list:
    """The frames of a restyled ``dataset`` in ``split`` drawn from the source frames ``source_ids``."""
    origin = {f["id"]: f["source_id"] for f in dataset.generator.get("frames", [])}
    return [f for f in dataset.frames(split) if origin.get(f.id, f.id) in source_ids]


def warning_counts(dataset: Dataset, frames: list | None = None) -> dict[str, int]:
    """How many ``frames`` of ``dataset`` (default: all) draw each observation warning code (depth
    checked at the true distance)."""
    counts: dict[str, int] = {}
    for frame in dataset.frames() if frames is None else frames:
        images = dataset.load(frame)
        for w in check_observation(images.rgb, images.labels > 0, images.depth, dataset.camera,
                                   expected_depth_m=float(frame.T_cam_obj[2, 3])):
            code = w.split(":", 1)[0]
            counts[code] = counts.get(code, 0) + 1
    return counts


def run(
    models: dict[str, NarfModel],
    sources: dict[str, Dataset],
    *,
    out_dir: str | Path,
    conditions: tuple[str, ...] = ALL_CONDITIONS,
    inputs: tuple[str, ...] = INPUTS,
    splits: tuple[str, ...] = ("test", "novel"),
    scenes: int = 17,
    scales: tuple[float, ...] = (1.0, 3.0),
    presets: tuple[str, ...] = PRESETS,
    size: tuple[int, int] = (640, 480),
    spp: int = 16,
    iterations: int = 150,
    seed: int = 0,
    overrides: dict | None = None,
    ray_seeds: tuple[int, ...] | None = None,
    progress: bool = True,
) -> dict:
    """Run the shifted protocol; writes ``shift.json``, ``shift.md`` and ``shift.png`` into ``out_dir``.

    ``models`` and ``sources`` (the tool's pybullet dataset) are keyed by tool. The shifted sets are
    cached under ``out_dir/data/<tool>-<W>x<H>-spp<N>-seed<S>/``. ``overrides``: refiner options set
    in every preset (:class:`~narf_core.estimate.EstimateOptions` fields). ``ray_seeds``: every block
    refined once per seed of the refiner's ray draws (``EstimateOptions.seed``; default: ``seed``) from the
    same starts, a row each and, with several, a row ``"pooled"`` over all their scenes: without depth a
    scene's end depends on its rays, and one draw's mean can be twice another's (docs/benchmarks.md).
    """
    overrides = dict(overrides or {})
    ray_seeds = tuple(ray_seeds) if ray_seeds else (seed,)
    if len(ray_seeds) > 1 and "seed" in overrides:
        raise ValueError("--ray-seeds and --set seed=... both set the refiner's seed: give one")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    config = {"conditions": list(conditions), "inputs": list(inputs), "splits": list(splits), "scenes": scenes,
              "scales": list(scales), "presets": list(presets), "size": list(size), "spp": spp,
              "iterations": iterations, "seed": seed, "ray_seeds": list(ray_seeds),
              "overrides": overrides, "trained_on": {tool: trained_on(model) for tool, model in models.items()},
              "options": {p: asdict(_preset_options(p, iterations, **overrides)) for p in presets}}
    table, warnings = [], []
    for tool, model in models.items():
        source = sources[tool]
        picked = {split: pick_frames(source, split, scenes, seed) for split in splits if source.frames(split)}
        ids = sorted(f.id for frames in picked.values() for f in frames)
        root = out_dir / "data" / f"{tool}-{size[0]}x{size[1]}-spp{spp}-seed{seed}"
        sets = shifted_sets(source, root, ids, conditions=conditions, size=size, spp=spp, seed=seed, progress=progress)
        for condition, dataset in sets.items():
            mine = {split: source_frames(dataset, split, {f.id for f in frames}) for split, frames in picked.items()}
            every = [f for frames in mine.values() for f in frames]
            warnings.append({"tool": tool, "condition": condition, "frames": len(every),
                             "warnings": warning_counts(dataset, every)})
            for split, frames in mine.items():
                for kind in inputs:
                    view = dataset if kind == "rgbd" else _WithoutDepth(dataset)
                    for preset in presets:
                        for scale in scales:
                            block = f"{condition}-{split}-{kind}-{preset}-x{scale:g}"
                            every_draw = []
                            for rays in ray_seeds:
                                options = _preset_options(preset, iterations, **{"seed": rays, **overrides})
                                log = scenes_log(out_dir, tool, block + ("" if rays == seed else f"-r{rays}"), model,
                                                 view, frames, options, scale=scale, seed=seed)
                                rows = run_scenes(model, view, frames, options, scale=scale, seed=seed,
                                                  progress=progress, log=log)
                                every_draw += rows
                                table.append({"tool": tool, "condition": condition, "split": split, "input": kind,
                                              "preset": preset, "scale": scale, "ray_seed": options.seed,
                                              **summarise(model, rows), "scenes_detail": rows})
                            if len(ray_seeds) > 1:
                                table.append({"tool": tool, "condition": condition, "split": split, "input": kind,
                                              "preset": preset, "scale": scale, "ray_seed": "pooled",
                                              **summarise(model, every_draw)})
    result = {"config": config, "table": table, "warnings": warnings, "machine": machine(models.values())}
    (out_dir / "shift.json").write_text(json.dumps(result, indent=1))
    (out_dir / "shift.md").write_text(markdown(result))
    remove_logs(out_dir)
    plot(result, out_dir / "shift.png")
    return result


def trained_on(model: NarfModel) -> str:
    """The size of the views ``model`` was trained on (``WxH``, its bundle's ``training_camera``), or ``not
    recorded``: a field trained on coarser views than the test's draws a softer outline, which without
    depth moves the estimate along the line of sight (docs/benchmarks.md, session 48)."""
    camera = model.metadata.get("training_camera")
    return f"{camera['width']}x{camera['height']}" if camera else "not recorded"


def _target(row: dict) -> str:
    """The issue's target for the row and whether it is met, or ``-``."""
    goal = TARGETS.get((row["condition"], row["input"])) if row["scale"] == 1 else None
    if goal is None:
        return "-"
    add_max, share_min = goal
    ok = row["add_mean_m"] <= add_max and (share_min is None or row["add<1cm"] >= share_min)
    text = f"≤ {100 * add_max:.1f} cm" + (f", ≥ {100 * share_min:.0f}%" if share_min is not None else "")
    return f"{text}: {'met' if ok else 'NOT met'}"


def _view(row: dict) -> str:
    """Mean |displacement along the line of sight| / mean displacement across it, in cm, or ``-``."""
    if "along_view_abs_mean_m" not in row:
        return "-"
    return f"{100 * row['along_view_abs_mean_m']:.2f} / {100 * row['across_view_mean_m']:.2f}"


def _joints(row: dict) -> str:
    parts = []
    for name, j in row["joints"].items():
        scale, unit = (1000.0, "mm") if j["unit"] == "m" else (1.0, "deg")
        parts.append(f"{name} {scale * j['mean']:.1f} ± {scale * j['std']:.1f} {unit}{unobserved_note(j, scale, unit, 1)}")
    return "<br>".join(parts) or "-"


def markdown(result: dict) -> str:
    """One row per tool, condition, split, input, preset and scale; then the warnings per condition."""
    c = result["config"]
    lines = [
        f"Shifted test sets (Mitsuba path tracing at {c['size'][0]}x{c['size'][1]}, {c['spp']} spp, plus faults): "
        f"up to {c['scenes']} scenes per split, starts perturbed by ±10 deg / ≤ 2 cm times the scale, θ at "
        f"mid-range, {c['iterations']} iterations (a Gauss-Newton preset keeps its own count). `rgb`: no depth "
        "given; `rgbd`: the (faulty) depth too." + _trained_sentence(c) + describe_machine(result.get("machine")),
        "",
        "| tool | condition | split | input | preset | scale | N | ADD (cm) | ADD < 1 cm | per joint "
        "| along / across view (cm) | s/scene | target |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    draws = len(c.get("ray_seeds", [0])) > 1
    for r in result["table"]:
        preset = f"{r['preset']}, rays {r['ray_seed']}" if draws else r["preset"]
        lines.append(
            f"| {r['tool']} | {r['condition']} | {r['split']} | {r['input']} | {preset} | {r['scale']:g}x "
            f"| {r['scenes']} | {100 * r['add_mean_m']:.2f} ± {100 * r['add_std_m']:.2f} | {100 * r['add<1cm']:.0f}% "
            f"| {_joints(r)} | {_view(r)} | {r['seconds_mean']:.2f} | {_target(r)} |"
        )
    lines += ["", "Observation warnings (frames of each set that draw them):", "",
              "| tool | condition | frames | warnings |", "|---|---|---|---|"]
    for w in result["warnings"]:
        text = ", ".join(f"{code} {n}" for code, n in sorted(w["warnings"].items())) or "none"
        lines.append(f"| {w['tool']} | {w['condition']} | {w['frames']} | {text} |")
    return "\n".join(lines) + "\n"


def _trained_sentence(config: dict) -> str:
    """`` Models trained on views of: tool WxH, ...`` (with its leading space), or empty for results without it."""
    trained = config.get("trained_on")
    if not trained:
        return ""
    return " Models trained on views of: " + ", ".join(f"{tool} {size}" for tool, size in trained.items()) + "."


def plot(result: dict, path: Path) -> None:
    """Left: mean ADD per condition (scale 1), one line per tool, input and preset; right: ADD
    against seconds per scene for every row."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    conditions = result["config"]["conditions"]
    keys = sorted({(r["tool"], r["input"], r["preset"]) for r in result["table"]})
    for key in keys:
        rows = [r for r in result["table"] if (r["tool"], r["input"], r["preset"]) == key and r["scale"] == 1]
        ys = [np.mean([r["add_mean_m"] for r in rows if r["condition"] == c] or [np.nan]) * 100 for c in conditions]
        style = "o-" if key[1] == "rgbd" else "s--"
        left.plot(range(len(conditions)), ys, style, label=" ".join(key))
        pts = [r for r in result["table"] if (r["tool"], r["input"], r["preset"]) == key]
        right.scatter([r["seconds_mean"] for r in pts], [100 * r["add_mean_m"] for r in pts], s=14, label=" ".join(key))
    left.set_xticks(range(len(conditions)), conditions, rotation=30)
    left.set_ylabel("mean ADD (cm), scale 1x")
    right.set_xlabel("seconds per scene (wall)")
    right.set_ylabel("mean ADD (cm)")
    for ax in (left, right):
        ax.axhline(1.0, color="grey", lw=0.8, ls="--")
        ax.grid(alpha=0.3)
    left.legend(fontsize=7)
    right.legend(fontsize=7)
    fig.suptitle("Refinement on shifted (path-traced, faulty) observations")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(args: argparse.Namespace) -> int:
    """``narf bench shift``: ``args`` has ``work``, ``tools``, ``models``, ``quick``, ``conditions``,
    ``inputs``, ``splits``, ``scenes``, ``scales``, ``presets``, ``size``, ``spp``, ``json``."""
    from narf_benchmarks.estimate import _prepare
    from narf_core.data.synth.restyle import mitsuba

    import drjit
    import torch

    mitsuba()  # a clear error before any work when the realism extra is missing
    drjit.set_thread_count(torch.get_num_threads())  # Mitsuba renders with as many threads as torch
    presets = tuple(args.presets or PRESETS)
    overrides = option_overrides(getattr(args, "set", []) or [])
    unknown = [p for p in presets if p not in PRESETS]
    if unknown:
        raise ValueError(f"--presets: unknown {unknown}; the refiner's presets are {', '.join(PRESETS)}")
    if args.tools:
        tools = tuple(args.tools)
    else:
        tools = tuple(sorted(p.stem for p in args.models.glob("*.narf")))
    if not tools:
        raise ValueError(f"no model to benchmark: {args.models} has no *.narf and no --tools were named")
    scenes, scales, splits = args.scenes, tuple(args.scales), tuple(args.splits)
    if args.quick:
        scenes, scales, splits = min(scenes, 3), scales[:1], splits[:1]
    models, sources = {}, {}
    prepare_args = argparse.Namespace(work=args.work, models=args.models, quick=False, device=args.device)
    for tool in tools:
        pair = _prepare(prepare_args, tool, False)
        models[tool], sources[tool] = pair
    result = run(models, sources, out_dir=args.work / "shift", conditions=tuple(args.conditions),
                 inputs=tuple(args.inputs), splits=splits, scenes=scenes, scales=scales, presets=presets,
                 size=tuple(args.size), spp=args.spp, overrides=overrides,
                 ray_seeds=tuple(getattr(args, "ray_seeds", None) or ()))
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0
