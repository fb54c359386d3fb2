"""``narf bench track``: tracking error and speed on synthetic sequences, side by side.

Per tool with a model, per image size (160x120; 640x480, where the refiner only traces rays in the
mask's box) and per modality (RGB-D, RGB only): a smooth sequence (``narf synth --sequence N
--smooth``, written once into the work folder) is tracked from its first frame's label, taken as
exact (``TrackOptions.first_frame = "warm"``: the first frame is tracked like the others, from the
label at rest), and the report gives frames per second (frames over the summed tracking time of
every frame, the first included; and over the CPU time of this process, which on a
machine shared with other CPU-bound work says what the tracker does alone), ADD and joint error
per frame (mean, 95th percentile, max, over frames whose status is not ``lost``), the number of
``lost`` frames and of re-initialisations, and the NEES coverage (the share of frames with a
covariance whose normalised error lies inside the 95% region: 0.95 when Σ is calibrated). The
per-frame settings head the table; ``--band-m`` marches only a band around the model's surface
(``EstimateOptions.band_m``), to compare with the whole box, and ``--march iteration`` marches at
every iteration instead of sampling the band found once per frame (``TrackOptions.march``);
``--no-depth-align`` leaves the prediction where the motion model puts it (``TrackOptions.depth_align``);
``--surface-fit-iterations 0`` leaves out its fit to the depth's points (``TrackOptions.surface_fit_iterations``);
``--no-occluder-test`` trusts the mask in full with depth, also on the rays where the depth shows an occluder
(``TrackOptions.occluder_test``); ``--hidden-joint-sigma 0`` leaves a joint the mask hides free
(``TrackOptions.hidden_joint_sigma``). With
``--events`` the sequence with a glance away and an occluding bar is tracked as well. ``--seed`` picks the
sequences' seeds (default 0), so that other motions of the same tools can be tracked; the result names them.
``--ray-seeds`` tracks each sequence once per seed of the tracker's ray draws (``TrackOptions.seed``, default 0):
a track without depth can end in either of two regimes by the draw alone, so one track says little about a
tool's mean. Where a cell holds several tracks (several seeds), a second table gives over them the mean of the
tracks' mean ADD, the tracks over 1 cm, the worst track and the lost frames.
``--images`` picks what is tracked of each sequence: ``pybullet`` (the frames as synthesised, the renderer that drew
the training views) and any of ``narf restyle``'s conditions (the same frames path-traced with Mitsuba in one scene
for the whole sequence, then that condition's sensor, depth and mask faults; written once beside the sequence,
``<sequence>-restyled/<condition>``; the events sequences' occluding bar is not in the path-traced scene). The error
against time is plotted per run (``<work>/track/<tool>-<size>-<modality>.png``) and every per-frame row is kept in
``<work>/track/result.json``. With ``--service-clients N``, N clients track the 160x120 sequence at
once through ``POST /v1/track`` on a loopback server, and each one's frames per second is reported.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from narf_benchmarks.load import describe_machine, machine
from narf_core.bundle import NarfModel, load_bundle
from narf_core.data.dataset import Dataset
from narf_core.estimate import chi2_quantile, local_error
from narf_core.track import TrackOptions, sigma_scale, track
from narf_core.track_io import load_frames, score, sequence_frames

SIZES = ((160, 120), (640, 480))
MODALITIES = ("rgbd", "rgb")


def sequence(work: Path, tool: str, size: tuple[int, int], frames: int, events: bool, seed: int = 0) -> Path:
    """The sequence dataset for one setting under ``work/sequences``, synthesised on first use
    (:func:`~narf_core.data.synth.sequence.sequence_once`: benchmarks started side by side on one ``work``
    folder, or one stopped halfway, never read or overwrite a sequence another is writing)."""
    from narf_core.data.synth.sequence import sequence_once

    out = work / "sequences" / f"{tool}-{size[0]}x{size[1]}-{frames}{'-events' if events else ''}{f'-s{seed}' if seed else ''}"
    return sequence_once(tool, out, frames, size=size, seed=seed, events=events)


def run_one(model: NarfModel, dataset: Dataset, rgb_only: bool, options: TrackOptions) -> dict:
    """Track a whole sequence from its first label; per-frame rows and the summary figures."""
    frames = sequence_frames(dataset)
    rows = []
    bound = chi2_quantile(0.95, 6 + len(model.joints))
    observed = list(load_frames(dataset, frames, rgb_only=rgb_only))  # read first: only tracking is timed
    results = track(model, iter(observed), dataset.camera, frames[0].T_cam_obj, frames[0].joints, options)
    for frame in frames:
        cpu = time.process_time()
        result = next(results)
        row = {"frame": frame.id, "time": result.time, "status": result.status, "seconds": result.seconds,
               "cpu_seconds": time.process_time() - cpu, **score(model, frame, result), "nees": None}
        if result.covariance is not None:
            e = local_error(result.T_cam_obj, result.joints, frame.T_cam_obj, frame.joints, model)
            row["nees"] = float(e @ np.linalg.pinv(result.covariance, hermitian=True) @ e)
        rows.append(row)
    held = [r for r in rows if r["status"] != "lost"]

    def stats(key: str) -> dict[str, float] | None:
        values = np.array([r[key] for r in held])
        if not len(values):
            return None
        return {"mean": float(values.mean()), "p95": float(np.percentile(values, 95)), "max": float(values.max())}

    nees = [r["nees"] for r in held if r["nees"] is not None]
    tracked = rows[1:]  # after the first frame (a multi-start initialisation unless options.first_frame is "warm")
    return {
        "frames": len(rows),
        "frames_per_second": len(rows) / sum(r["seconds"] for r in rows),
        "frames_per_second_tracking": len(tracked) / sum(r["seconds"] for r in tracked) if tracked else None,
        "frames_per_cpu_second_tracking": len(tracked) / sum(r["cpu_seconds"] for r in tracked) if tracked else None,
        "first_frame_seconds": rows[0]["seconds"],
        "add_m": stats("add_m"),
        **{key: stats(key) for key in rows[0] if key.startswith("joint_error/")},
        "joint_types": {j.name: j.type for j in model.joints},
        "sigma_scale": sigma_scale(model, options, not rgb_only, dataset.camera),
        "lost": sum(r["status"] == "lost" for r in rows),
        "reinitialised": sum(r["status"] == "reinitialised" for r in rows[1:]),
        "uncertain": sum(r["status"] == "uncertain" for r in rows),
        "nees_coverage_95": float(np.mean(np.array(nees) <= bound)) if nees else None,
        "rows": rows,
    }


def plot(rows: list[dict], title: str, path: Path) -> Path:
    """ADD (cm) and the per-frame time (ms) against the sequence's time, lost frames marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["time"] for r in rows]
    fig, (a, b) = plt.subplots(2, 1, figsize=(7, 4.5), sharex=True)
    a.plot(t, [r["add_m"] * 100 for r in rows], lw=1)
    lost = [r for r in rows if r["status"] == "lost"]
    if lost:
        a.scatter([r["time"] for r in lost], [r["add_m"] * 100 for r in lost], c="r", s=8, label="lost")
        a.legend()
    a.set_ylabel("ADD (cm)")
    a.set_title(title)
    b.plot(t, [r["seconds"] * 1000 for r in rows], lw=1)
    b.set_ylabel("ms per frame")
    b.set_yscale("log")
    b.set_xlabel("time (s)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def images_of(source: Path, images: str, spp: int = 32, seed: int = 0) -> Dataset:
    """The sequence at ``source`` as ``images`` gives it: ``pybullet`` (as synthesised) or path-traced under one
    of :data:`narf_core.data.synth.faults.CONDITIONS` (scene and faults from ``seed``; made once,
    ``<source>-restyled/<condition>``)."""
    dataset = Dataset.open(source)
    if images == "pybullet":
        return dataset
    from narf_benchmarks.shift import shifted_sets

    size = (dataset.camera.width, dataset.camera.height)
    return shifted_sets(dataset, source.parent / f"{source.name}-restyled", [f.id for f in dataset.frames()],
                        conditions=(images,), size=size, spp=spp, seed=seed)[images]


def run(models: dict[str, NarfModel], work: Path, *, frames: int, sizes=SIZES, modalities=MODALITIES,
        events: bool = False, options: TrackOptions | None = None, seeds: tuple[int, ...] = (0,),
        images: tuple[str, ...] = ("pybullet",), spp: int = 32, ray_seeds: tuple[int, ...] = (0,)) -> dict:
    """Every tool x size x modality (x smooth/events) x ``images`` (:func:`images_of`) on the sequences
    synthesised with each of ``seeds``, each tracked once per seed of the ray draws (``ray_seeds``, as
    ``options.seed``); returns the summary (rows saved beside it)."""
    options = options or TrackOptions(first_frame="warm")
    out_dir = work / "track"
    runs = []
    for tool, model in models.items():
        for size, seed in itertools.product(sizes, seeds):
            for with_events, kind in itertools.product((False, True) if events else (False,), images):
                dataset = images_of(sequence(work, tool, size, frames, with_events, seed=seed), kind, spp, seed)
                for modality, ray_seed in itertools.product(modalities, ray_seeds):
                    start = time.perf_counter()
                    one = run_one(model, dataset, modality == "rgb", replace(options, seed=ray_seed))
                    name = (f"{tool}-{size[0]}x{size[1]}-{modality}{'-events' if with_events else ''}"
                            + ("" if kind == "pybullet" else f"-{kind}") + (f"-s{seed}" if seed else "")
                            + (f"-r{ray_seed}" if ray_seed else ""))
                    one.update({"tool": tool, "size": list(size), "modality": modality, "events": with_events,
                                "images": kind, "seed": seed, "ray_seed": ray_seed,
                                "wall_seconds": time.perf_counter() - start,
                                "plot": str(plot(one["rows"], name, out_dir / f"{name}.png"))})
                    runs.append(one)
                    print(f"narf bench track: {name}: {one['frames_per_second']:.1f} frames/s, ADD mean "
                          f"{one['add_m']['mean'] * 100:.2f} cm, lost {one['lost']}", file=sys.stderr)
    per_frame = {}
    device = next(iter(models.values())).aabb.device if models else "cpu"  # the frames' budget depends on it
    for modality in modalities:
        step = options.step_options(modality == "rgbd", device)
        own = {tool: j for tool, model in models.items() if (j := options.jacobian_for(modality == "rgbd", model))
               != step.jacobian}  # a model's calibration chose another (TrackOptions.jacobian_rgb "auto")
        rays = {tool: r for tool, model in models.items() if (r := options.rays_for(modality == "rgbd", device, model))
                != step.rays_per_iteration}  # likewise the rays with depth (TrackOptions.rays_per_iteration 0)
        huber = {tool: h for tool, model in models.items() if (h := options.step_options(
            modality == "rgbd", device, model).robust_scale) != step.robust_scale}  # and the Huber scale with depth
        per_frame[modality] = {"solver": options.solver_for(modality == "rgbd"), "iterations": step.iterations,
                               "rays_per_iteration": step.rays_per_iteration, "jacobian": step.jacobian,
                               "jacobian_once": step.jacobian_once, "jacobian_own": own, "rays_own": rays,
                               "robust_scale": step.robust_scale, "robust_scale_own": huber}
    result = {"frames": frames, "seeds": list(seeds), "ray_seeds": list(ray_seeds), "options": options.__dict__,
              "per_frame": per_frame, "runs": runs, "over_tracks": over_tracks(runs),
              "machine": machine(models.values())}
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "result.json").write_text(json.dumps(result, indent=1))
    return result


def _cell(run: dict) -> tuple:
    """What a track is a repeat of: tool, size, images, input, events."""
    return run["tool"], tuple(run["size"]), run.get("images", "pybullet"), run["modality"], run["events"]


def over_tracks(runs: list[dict]) -> list[dict]:
    """Per cell (:func:`_cell`) of several tracks: their number, the mean over them of each track's mean ADD, the
    tracks whose mean ADD is over 1 cm, the worst track's, frames per second over all their frames and the lost
    frames (a track whose every frame was lost has no ADD: it counts as over 1 cm, not in the mean or the worst)."""
    cells: dict[tuple, list[dict]] = {}
    for r in runs:
        cells.setdefault(_cell(r), []).append(r)
    out = []
    for cell, group in cells.items():
        if len(group) < 2:
            continue
        adds = np.array([r["add_m"]["mean"] if r["add_m"] else np.inf for r in group])
        held = adds[np.isfinite(adds)]
        seconds = sum(r["frames"] / r["frames_per_second"] for r in group)
        out.append({"tool": cell[0], "size": list(cell[1]), "images": cell[2], "modality": cell[3], "events": cell[4],
                    "tracks": len(group), "add_mean_m": float(held.mean()) if len(held) else None,
                    "tracks_over_1cm": int((adds > 0.01).sum()),
                    "worst_track_add_m": float(held.max()) if len(held) else None,
                    "frames_per_second": sum(r["frames"] for r in group) / seconds,
                    "lost": sum(r["lost"] for r in group)})
    return out


def _seeds_text(seeds: list[int]) -> str:
    return f"seed {seeds[0]}" if len(seeds) == 1 else "seeds " + ", ".join(map(str, seeds))


def markdown(result: dict) -> str:
    """The summary as a table: error and speed side by side."""
    o = result["options"]
    band = f"marched through a {o['band_m'] * 100:g} cm band around the surface" if o["band_m"] else \
        "marched through the whole box"
    if not o["band_m"] and o.get("march") == "frame":
        band = "sampled in the band around the surface found once per frame (no marching)"
    lines = [
        f"Tracking, {result['frames']}-frame sequences (30 fps, {_seeds_text(result.get('seeds', [0]))}"
        + ("" if result.get("ray_seeds", [0]) == [0] else f"; rays drawn with {_seeds_text(result['ray_seeds'])}")
        + "), "
        f"from the first frame's label "
        f"({'as exact' if o.get('first_frame') == 'warm' else 'refined by the multi-start refiner'}); per frame "
        + "; ".join(f"{'with depth' if m == 'rgbd' else 'RGB only'} {p['iterations']} {p['solver']} iterations of "
                    f"{p['rays_per_iteration']} rays" + _enclosed(" (", _own_text(p.get("rays_own"), str), ")")
                    + (_jacobian_text(p) if p["solver"] == "gauss-newton" and "jacobian" in p else "")
                    + _huber_text(p, m)
                    for m, p in result.get("per_frame", {}).items())
        + f", {band}"
        + ("" if o.get("depth_align", True) else ", the prediction not aligned to the depth")
        + _surface_fit_text(o.get("surface_fit_iterations", TrackOptions.surface_fit_iterations))
        + ("" if o.get("occluder_test", True) else ", with depth the mask trusted in full (no occluder test)")
        + _hold_text(o.get("hidden_joint_sigma", TrackOptions.hidden_joint_sigma))
        + ("" if o.get("outside_weight_rgb", 1.0) >= 1 else
           f", without depth the rays outside the mask weighing {o['outside_weight_rgb']:g}")
        + "." + describe_machine(result.get("machine")),
        "",
        "| tool | size | images | input | events | frames/s (all / after the 1st) | frames per CPU second (after the 1st) "
        "| ADD mean / p95 / max (cm) | joint error mean / p95 / max | lost | re-init. | NEES 95% coverage (σ factor) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        add = r["add_m"]
        after = r["frames_per_second_tracking"]
        lines.append(
            f"| {r['tool']}{_repeat_cell(r, result)} | {r['size'][0]}x{r['size'][1]} "
            f"| {_images_cell(r.get('images', 'pybullet'))} "
            f"| {r['modality']} | {'yes' if r['events'] else 'no'} | "
            f"{r['frames_per_second']:.1f} / {after:.1f} | {r['frames_per_cpu_second_tracking']:.1f} | "
            + (f"{add['mean'] * 100:.2f} / {add['p95'] * 100:.2f} / {add['max'] * 100:.2f}" if add else "-") + " | "
            + _joint_cell(r)
            + f" | {r['lost']} | {r['reinitialised']} | "
            + (f"{r['nees_coverage_95']:.2f}" if r["nees_coverage_95"] is not None else "-")
            + (f" (×{r['sigma_scale']:.2f})" if r.get("sigma_scale") else "") + " |"
        )
    if result.get("over_tracks"):
        lines += ["", "Over the tracks of each cell (one per sequence seed and ray seed):", "",
                  "| tool | size | images | input | events | tracks | frames/s | ADD mean over the tracks (cm) "
                  "| tracks over 1 cm | worst track (cm) | lost frames |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for c in result["over_tracks"]:
            lines.append(
                f"| {c['tool']} | {c['size'][0]}x{c['size'][1]} | {_images_cell(c['images'])} | {c['modality']} | "
                f"{'yes' if c['events'] else 'no'} | {c['tracks']} | {c['frames_per_second']:.1f} | "
                + (f"{c['add_mean_m'] * 100:.2f}" if c["add_mean_m"] is not None else "-")
                + f" | {c['tracks_over_1cm']} | "
                + (f"{c['worst_track_add_m'] * 100:.2f}" if c["worst_track_add_m"] is not None else "-")
                + f" | {c['lost']} |")
    service = result.get("service")
    if service:
        lines += ["", f"Service, {service['clients']} clients tracking at once over POST /v1/track (160x120 RGB-D, "
                      f"{service['frames']} frames each): frames/s per client min {service['frames_per_second_min']:.2f}, "
                      f"mean {service['frames_per_second_mean']:.2f}; ADD mean per client "
                      + ", ".join(f"{c['add_mean_m'] * 100:.2f} cm" if "error" not in c else c["error"]
                                  for c in service["per_client"])
                      + "; ms per frame per client (tracker time in the server) "
                      + ", ".join(f"{c['frame_seconds_mean'] * 1000:.0f} ({c['tracker_seconds_mean'] * 1000:.0f})"
                                  for c in service["per_client"] if "error" not in c)]
    return "\n".join(lines)


def _surface_fit_text(iterations: int) -> str:
    """The caption's clause for ``TrackOptions.surface_fit_iterations`` where it is not the tracker's default."""
    if iterations == TrackOptions.surface_fit_iterations:
        return ""
    return (f", with depth the prediction fitted to the depth's points in {iterations} iterations" if iterations
            else ", with depth the prediction not fitted to the depth's points")


def _hold_text(sigma: float) -> str:
    """The caption's clause for ``TrackOptions.hidden_joint_sigma`` where it is not the tracker's default."""
    if sigma == TrackOptions.hidden_joint_sigma:
        return ""
    return f", a joint the mask hides held by {sigma:g} of its half range" if sigma else ", a joint the mask hides not held"


def _jacobian_text(per_frame: dict) -> str:
    """" (Jacobian by derivatives; by differences for lamp, its calibration's choice)", " (Jacobian by differences,
    once a frame)"."""
    return (f" (Jacobian by {per_frame['jacobian']}" + (", once a frame" if per_frame.get("jacobian_once") else "")
            + _enclosed("; ", _own_text(per_frame.get("jacobian_own"), lambda j: f"by {j}")) + ")")


def _huber_text(per_frame: dict, modality: str) -> str:
    """", Huber scale 0.3 for lamp, its calibration's choice" (with depth, where a model's calibration chose another
    than the frames'), ", Huber scale 0.2" (one set with ``--huber``); "" where every frame takes the preset's."""
    if modality != "rgbd" or "robust_scale" not in per_frame:
        return ""
    own = _own_text(per_frame.get("robust_scale_own"), lambda s: f"{s:g}")
    if per_frame["robust_scale"] != TrackOptions().step_options(True).robust_scale:
        return f", Huber scale {per_frame['robust_scale']:g}" + _enclosed(" (", own, ")")
    return _enclosed(", Huber scale ", own)


def _own_text(own: dict | None, what) -> str:
    """The models whose calibration chose otherwise, grouped by choice (``own``: tool -> choice, ``what`` its words):
    "by differences for lamp, its calibration's choice"; "" where none did."""
    grouped: dict = {}
    for tool, choice in (own or {}).items():
        grouped.setdefault(choice, []).append(tool)
    return "; ".join(f"{what(c)} for {', '.join(tools)}, {'its' if len(tools) == 1 else 'their'} calibration's choice"
                     for c, tools in grouped.items())


def _enclosed(before: str, text: str, after: str = "") -> str:
    """``text`` between ``before`` and ``after``, or nothing where it is empty."""
    return before + text + after if text else ""


def _repeat_cell(run: dict, result: dict) -> str:
    """`` (seed S, rays R)`` after the tool where the result holds several of either."""
    parts = ([f"seed {run['seed']}"] if len(result.get("seeds", [0])) > 1 else []) + (
        [f"rays {run['ray_seed']}"] if len(result.get("ray_seeds", [0])) > 1 else [])
    return f" ({', '.join(parts)})" if parts else ""


def _images_cell(images: str) -> str:
    return "pybullet" if images == "pybullet" else f"path-traced, {images}"


def _joint_cell(run: dict) -> str:
    """The first joint's error mean / p95 / max in mm (prismatic) or degrees (revolute); ``-`` without one."""
    name, joint = next(((k.split("/", 1)[1], v) for k, v in run.items() if k.startswith("joint_error/") and v),
                       (None, None))
    if joint is None:
        return "-"
    if run.get("joint_types", {}).get(name) == "prismatic":
        return " / ".join(f"{joint[k] * 1000:.1f}" for k in ("mean", "p95", "max")) + " mm"
    return " / ".join(f"{np.degrees(joint[k]):.2f}°" for k in ("mean", "p95", "max"))


def main(args: argparse.Namespace) -> int:
    """``narf bench track``: ``args`` has ``work``, ``models``, ``tools``, ``frames``, ``sizes``,
    ``modalities``, ``events``, ``seed`` (a list), ``ray_seeds``, ``images``, ``spp``, ``iterations``, ``rays``,
    ``huber``, ``solver``, ``band_m``, ``march``, ``depth_align``, ``surface_fit_iterations``, ``jacobian``,
    ``jacobian_once``, ``occluder_test``, ``hidden_joint_sigma``, ``service_clients``, ``json``."""
    tools = args.tools or sorted(p.stem for p in args.models.glob("*.narf"))
    models, missing = {}, []
    for tool in tools:
        path = args.models / f"{tool}.narf"
        if path.is_file():
            models[tool] = load_bundle(path, args.device)
        else:
            missing.append(tool)
    if not models:
        raise ValueError(f"no model to benchmark: {args.models} has no bundle for {', '.join(tools) or 'any tool'}")
    if missing:
        print(f"narf bench track: skipping {', '.join(missing)}: no model in {args.models}", file=sys.stderr)
    sizes = tuple(tuple(s) for s in args.sizes) if args.sizes else SIZES
    overrides = {"iterations": args.iterations, "rays_per_iteration": getattr(args, "rays", None),
                 "robust_scale": getattr(args, "huber", None),
                 "solver": getattr(args, "solver", None), "band_m": getattr(args, "band_m", None),
                 "march": getattr(args, "march", None), "depth_align": getattr(args, "depth_align", None),
                 "surface_fit_iterations": getattr(args, "surface_fit_iterations", None),
                 "jacobian": getattr(args, "jacobian", None), "jacobian_rgb": getattr(args, "jacobian", None),
                 "outside_weight_rgb": getattr(args, "outside_weight_rgb", None),
                 "jacobian_once": getattr(args, "jacobian_once", None),
                 "occluder_test": getattr(args, "occluder_test", None),
                 "hidden_joint_sigma": getattr(args, "hidden_joint_sigma", None)}
    options = TrackOptions(first_frame="warm", **{k: v for k, v in overrides.items() if v is not None})
    result = run(models, args.work, frames=args.frames, sizes=sizes, modalities=tuple(args.modalities),
                 events=args.events, options=options, seeds=tuple(getattr(args, "seed", None) or (0,)),
                 images=tuple(getattr(args, "images", None) or ("pybullet",)), spp=getattr(args, "spp", 32),
                 ray_seeds=tuple(getattr(args, "ray_seeds", None) or (0,)))
    if args.service_clients:
        tool = next(iter(models))
        dataset = Dataset.open(sequence(args.work, tool, (160, 120), args.frames, False, seed=result["seeds"][0]))
        result["service"] = service_run(args.models / f"{tool}.narf", dataset, args.service_clients,
                                        min(args.frames, 40))
    if args.json:
        print(json.dumps({**result, "runs": [{k: v for k, v in r.items() if k != "rows"} for r in result["runs"]]},
                         indent=1))
    else:
        print(markdown(result))
    return 0


def service_run(model_path: Path, dataset: Dataset, clients: int, frames: int) -> dict:
    """``clients`` threads each tracking the first ``frames`` frames of ``dataset`` through
    ``POST /v1/track`` on a server on loopback, run as its own process as deployed (``narf serve``
    with its defaults: one worker per core, the state in the token); frames per second per client,
    counted once every client has its first (initialising, multi-start) frame's answer, so that the
    figure is that of ``clients`` tracks at once rather than one track beside the others'
    initialisations, and the mean time between two of its answers beside the server's tracker time
    per frame (the rest is waiting for a worker, HTTP, decoding and the client's own work)."""
    import contextlib
    import os
    import shutil
    import tempfile
    import threading

    from narf_client import NarfClient, TrackFrame
    from narf_service.main import serve_process

    labels = sequence_frames(dataset)[:frames]
    sent = [TrackFrame(f.time, im.image, im.mask, im.depth) for f, im in zip(labels, load_frames(dataset, labels))]
    K = dataset.camera.K.double().numpy()
    model = load_bundle(model_path)
    name = model_path.stem
    per_client: list[dict] = [{} for _ in range(clients)]
    initialised = threading.Barrier(clients, timeout=600)

    def client(i: int) -> None:
        try:
            track_all(i)
        except Exception as e:  # noqa: BLE001 - reported in the result, beside the others' figures
            initialised.abort()  # (the others do not wait for this one)
            per_client[i] = {"error": f"{type(e).__name__}: {e}"}

    def track_all(i: int) -> None:
        with NarfClient(url, timeout=120) as narf:
            stamps, updates = [], []
            for update in narf.track(sent, K, labels[0].T_cam_obj, model=name, initial_joints=labels[0].joints):
                if not stamps:
                    with contextlib.suppress(threading.BrokenBarrierError):
                        initialised.wait()
                stamps.append(time.perf_counter())
                updates.append(update)
        # scored after the track, not between its frames: the benchmark's own work, off the cores the tracks share
        statuses, steps = [u.status for u in updates], [u.seconds for u in updates]
        errors = [score(model, label, _as_result(u))["add_m"] for label, u in zip(labels, updates)]
        per_client[i] = {"frames_per_second": (len(stamps) - 1) / (stamps[-1] - stamps[0]),
                         "lost": statuses.count("lost"), "add_mean_m": float(np.mean(errors)),
                         "frame_seconds_mean": (stamps[-1] - stamps[0]) / (len(stamps) - 1),
                         "tracker_seconds_mean": float(np.mean(steps[1:]))}

    env = {**os.environ, "NARF_STATE_KEY": "bench-track-key-0123456789"}
    with tempfile.TemporaryDirectory() as folder:
        shutil.copy(model_path, Path(folder) / model_path.name)  # serve this bundle alone
        with serve_process(["--models", folder], env) as url:
            threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
    fps = [c["frames_per_second"] for c in per_client if "frames_per_second" in c]
    return {"clients": clients, "frames": frames, "per_client": per_client,
            "failed_clients": sum("error" in c for c in per_client),
            "frames_per_second_min": min(fps, default=0.0), "frames_per_second_mean": float(np.mean(fps)) if fps else 0.0}


def _as_result(update):
    """A client update as what :func:`narf_core.track_io.score` reads (pose and joints)."""
    from types import SimpleNamespace

    return SimpleNamespace(T_cam_obj=np.asarray(update.pose.matrix), joints=update.joints)
