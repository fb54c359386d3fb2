"""The ``narf`` command (docs/design.md §7).

Each subcommand is a pair of small functions: ``_add_<name>(subparsers)`` declares its arguments
and ``_run_<name>(args) -> int`` does the work. :func:`main` turns expected errors (``ValueError``
and its subclasses, such as ``DatasetError`` and ``UrdfError``, and ``OSError``) into one line
``narf <command>: error: ...`` on stderr and exit code 2, never a traceback. Commands that report
a result print it for people, or as one JSON object on stdout with ``--json``; progress bars go to
stderr.

Heavy modules (torch, pybullet) are imported inside the ``_run_*`` functions, so ``narf --help``
is instant and a command works without the extras other commands need.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import narf_core
from narf_core.threads import AUTO, choose_threads, parse_threads, prefer_passive_wait

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel
    from narf_core.checks import InputError

EXIT_ERROR = 2  # bad input, as argparse uses for bad arguments
EXIT_INTERRUPTED = 130
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError)
THREADS_ENV = "NARF_THREADS"
DEVICE_ENV = "NARF_DEVICE"  # as the service's setting
AUTO_THREADS_MAX = 1  # what `--threads auto` takes at most: see _threads_for
NOISE_PRESETS = ("none", "paper")  # generate.NOISE_PRESETS, named here so that --help imports no pybullet
MODES = ("auto", "narf", "parts")  # narf_core.modes.MODES, named here so that --help imports no numpy
PRESET_NAMES = ("auto", "paper", "robust", "gauss-newton")  # narf_core.estimate.PRESET_NAMES, likewise
TRACK_SOLVER_CHOICES = ("auto", "adam", "gauss-newton")  # narf_core.track.TRACK_SOLVERS, likewise
TRACK_ITERATIONS = "2 gauss-newton (3 without depth), 6 adam"  # narf_core.track.budget_text(), likewise
TRACK_AUTO_SOLVER = "gauss-newton, with depth and without"  # narf_core.track.auto_solver_text(), likewise
JACOBIANS = ("derivatives", "differences")  # narf_core.estimate.JACOBIANS, likewise
# narf_core.track.jacobian_text(), likewise
TRACK_JACOBIAN = "differences with depth, derivatives without, or what the model's tracker calibration chose"
MODE_HELP = ("render mode: narf (the configuration field), parts (the composed part fields) or auto (default: "
             "the better one by the measurement training recorded in the bundle)")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``narf`` with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    prefer_passive_wait()  # before anything imports torch (libgomp reads it once)
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # as typed, for the provenance of what it writes
    try:
        import torch

        torch.set_num_threads(_threads_for(args))
        return args.run(args)
    except EXPECTED_ERRORS as e:
        return _fail(args.command, e)
    except KeyboardInterrupt:
        print(f"narf {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="narf",
        description="Render-and-compare pose and configuration estimation for articulated objects (NARF22).",
    )
    parser.add_argument("--version", action="version", version=f"narf {narf_core.__version__}")
    parser.add_argument(
        "--threads", type=_threads, default=os.environ.get(THREADS_ENV, AUTO), metavar="N|auto",
        help=f"CPU threads for torch (default: ${THREADS_ENV}, else 'auto': one, as every command's parallel "
             "regions gain less from a second thread than waking it costs). Idle threads sleep instead of "
             "spinning (OMP_WAIT_POLICY=PASSIVE unless set), so a busy machine slows the command down instead "
             "of stalling it",
    )
    parser.add_argument(
        "--device", default=os.environ.get(DEVICE_ENV, "cpu"), metavar="cpu|cuda[:N]",
        help=f"torch device that render, estimate, track, eval, serve and the benchmarks load models and render on "
             f"(default: ${DEVICE_ENV}, else cpu); training runs on the CPU",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_synth, _add_restyle, _add_train, _add_points, _add_eval, _add_render, _add_estimate, _add_track,
                _add_bench, _add_serve):
        add(commands)
    return parser


def _fail(command: str, error: BaseException) -> int:
    message = " ".join(str(error).split()) or type(error).__name__
    if isinstance(error, OSError) and error.filename is not None and str(error.filename) not in message:
        message = f"{error.filename}: {message}"
    print(f"narf {command}: error: {message}", file=sys.stderr)
    return EXIT_ERROR


def _emit(args: argparse.Namespace, result: dict[str, Any], human: Callable[[dict[str, Any]], str]) -> None:
    """Print a command's result: JSON with ``--json``, else the ``human`` summary."""
    print(json.dumps(result, indent=2) if args.json else human(result))


def _add_json_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object on stdout")


def _mode_arg(model: Any, requested: str) -> tuple[str, str]:
    """``(mode, reason)`` that ``--mode`` comes to for ``model`` (:func:`narf_core.modes.choose_mode`);
    a mode the model lacks is an error naming the flag."""
    from narf_core.modes import choose_mode

    return choose_mode(model, requested, field="--mode")


def _mode_line(result: dict[str, Any]) -> str:
    """A second line saying why ``auto`` chose the result's mode (nothing for a mode asked by name)."""
    reason = result.get("mode_reason")
    return "" if reason in (None, "requested") else f"\nmode {result['mode']} (auto): {reason}"


def _threads_for(args: argparse.Namespace) -> int:
    """torch threads for a command: ``--threads``, or with ``auto`` the free cores
    (:func:`~narf_core.threads.choose_threads`), at most ``AUTO_THREADS_MAX``.

    Rendering, refining, tracking and training run parallel regions of a few thousand rays each; with
    idle threads sleeping between them (the passive wait policy a shared machine needs), waking a second
    thread costs more than it saves (``narf bench`` figures in the README; training on 2 cores, docs/benchmarks.md).
    """
    threads = choose_threads(args.threads)
    return min(threads, AUTO_THREADS_MAX) if args.threads == AUTO else threads


def _threads(text: str) -> int | str:
    try:
        return parse_threads(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _number(kind: type, lowest: float, strict: bool, what: str) -> Callable[[str], Any]:
    """An argparse type: ``kind(text)``, finite, and ``> lowest`` (``strict``) or ``>= lowest``."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if not (value > lowest if strict else value >= lowest) or value == float("inf"):
            raise argparse.ArgumentTypeError(f"{text} is not {what}")
        return value

    return parse


_positive_int = _number(int, 0, True, "a positive integer")
_non_negative_int = _number(int, 0, False, "an integer >= 0")
_non_negative_float = _number(float, 0.0, False, "a finite number >= 0")
_positive_float = _number(float, 0.0, True, "a finite number > 0")


def _folder_size(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


# ---------------------------------------------------------------------------------------------
# narf synth


def _add_synth(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "synth",
        help="render a synthetic dataset of a tool or any URDF with pybullet",
        description=(
            "Render a dataset (docs/design.md §3) of a procedural tool or a URDF with pybullet's CPU renderer: "
            "RGB, metric depth and per-link labels from robot-head-like viewpoints, in the paper's "
            "splits: train (few configurations), test (same configurations, other views) and novel "
            "(configurations absent from train). Deterministic from --seed."
        ),
        epilog=(
            "Label noise models hand-labelled data: it changes the written poses, joint values, masks "
            "and depth, never the RGB; the clean ground truth is kept under clean/ and in scene.json "
            "(generator.clean_frames). '--noise paper' is rot 2 deg, trans 5 mm, theta 0.02, mask 1 px, "
            "depth 2 mm; the --noise-* flags override single values."
        ),
    )
    arg = parser.add_argument
    arg("--tool", required=True, metavar="NAME|PATH.urdf",
        help="clamp, lineman-a, lineman-b, longnose, lamp, gripper, cabinet or a URDF")
    arg("--out", required=True, type=Path, metavar="DIR", help="dataset folder to create (new or empty)")
    arg("--size", nargs=2, type=_positive_int, default=(160, 120), metavar=("W", "H"),
        help="default: 160 120; for a finer camera without depth, views of its own size sharpen the model's "
        "outline, which sets the distance there (640 480 for a 640x480 camera: docs/benchmarks.md, sessions 48 "
        "and 51)")
    arg("--views", type=_positive_int, default=200, metavar="N", help="train images (default: %(default)s); "
        "test and novel get max(17, N // 4) each")
    arg("--seed", type=_non_negative_int, default=0, help="random seed (default: %(default)s)")
    arg("--background", action="store_true", help="render a textured table under the object (background)")
    arg("--supersample", type=_positive_int, default=3, metavar="S", help="S x S colour samples per pixel, odd "
        "(default: %(default)s; 1 = TinyRenderer's aliased point samples)")
    arg("--overwrite", action="store_true", help="replace the dataset already in --out")
    seq = parser.add_argument_group("sequences (for tracking)").add_argument
    seq("--sequence", type=_positive_int, metavar="FRAMES", help="write a video-like sequence of FRAMES frames "
        "instead of the splits: a smooth camera path around the object (at most 30 cm/s and 60 deg/s) while the "
        "joints open and close, frames in time order in the test split with a 'time' in seconds")
    seq("--fps", type=float, default=30.0, help="frame rate of --sequence (default: %(default)s)")
    seq("--smooth", action="store_true", help="no events in --sequence: by default the camera glances away (the "
        "object leaves the view) once and a bar sweeps across the object (partial occlusion)")
    noise = parser.add_argument_group("label noise").add_argument
    noise("--noise", choices=NOISE_PRESETS, default="none", help="preset (default: %(default)s)")
    noise("--noise-rot-deg", type=_non_negative_float, metavar="DEG", help="pose rotation, std per axis")
    noise("--noise-trans-mm", type=_non_negative_float, metavar="MM", help="pose translation, std per axis")
    noise("--noise-theta", type=_non_negative_float, metavar="X", help="joint values, std in the joint's unit")
    noise("--noise-mask-px", type=_non_negative_int, metavar="PX", help="largest mask erosion/dilation radius")
    noise("--noise-depth", type=_non_negative_float, metavar="M", help="depth, std in metres")
    _add_json_flag(parser)
    parser.set_defaults(run=_run_synth)


def _run_synth(args: argparse.Namespace) -> int:
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.generate import NoiseOptions, synthesize

    base = NoiseOptions.preset(args.noise)
    overrides = {
        "rot_deg": args.noise_rot_deg,
        "trans_mm": args.noise_trans_mm,
        "theta": args.noise_theta,
        "mask_px": args.noise_mask_px,
        "depth_m": args.noise_depth,
    }
    noise = replace(base, **{k: v for k, v in overrides.items() if v is not None})
    start = time.perf_counter()
    if args.sequence is not None:
        return _run_synth_sequence(args, noise.active, start)
    out = synthesize(
        args.tool,
        args.out,
        size=tuple(args.size),
        views=args.views,
        seed=args.seed,
        noise=noise if noise.active else None,
        background=args.background,
        supersample=args.supersample,
        overwrite=args.overwrite,
        progress=True,
    )
    seconds = time.perf_counter() - start
    dataset = Dataset.open(out)
    result = {
        "dataset": str(out),
        "tool": args.tool,
        "size": list(args.size),
        "frames": {split: len(dataset.frames(split)) for split in ("train", "test", "novel")},
        "links": dataset.links,
        "joints": dataset.joints,
        "noise": dataset.generator.get("noise"),
        "seconds": round(seconds, 3),
        "bytes": _folder_size(out),
    }
    _emit(args, result, _synth_summary)
    return 0


def _run_synth_sequence(args: argparse.Namespace, noisy: bool, start: float) -> int:
    from narf_core.data.synth.sequence import synthesize_sequence

    if noisy:
        raise ValueError("--sequence writes clean labels; label noise (--noise*) is not supported there")
    if args.sequence < 2:
        raise ValueError(f"--sequence needs at least 2 frames, got {args.sequence}")
    out = synthesize_sequence(args.tool, args.out, args.sequence, size=tuple(args.size), seed=args.seed, fps=args.fps,
                              events=not args.smooth, background=args.background, supersample=args.supersample,
                              overwrite=args.overwrite, progress=True)
    info = json.loads((out / "scene.json").read_text())["generator"]["sequence"]
    result = {
        "dataset": str(out), "tool": args.tool, "size": list(args.size), "frames": args.sequence, "fps": args.fps,
        "events": not args.smooth, "peak_speed_m_s": round(info["peak_speed_m_s"], 4),
        "peak_turn_deg_s": round(info["peak_turn_deg_s"], 2),
        "frames_out_of_view": sum(not f["in_view"] for f in info["per_frame"]),
        "frames_occluded": sum(f["occluded"] > 0 for f in info["per_frame"]),
        "seconds": round(time.perf_counter() - start, 3), "bytes": _folder_size(out),
    }
    _emit(args, result, lambda r: (
        f"wrote a {r['frames']}-frame sequence of {r['tool']} at {r['size'][0]}x{r['size'][1]}, {r['fps']:g} fps "
        f"(peak {r['peak_speed_m_s']:.2f} m/s, {r['peak_turn_deg_s']:.0f} deg/s; {r['frames_out_of_view']} frames "
        f"out of view, {r['frames_occluded']} occluded) to {r['dataset']} in {r['seconds']:.1f} s"))
    return 0


def _synth_summary(r: dict[str, Any]) -> str:
    frames = r["frames"]
    return (
        f"wrote {sum(frames.values())} frames (train {frames['train']}, test {frames['test']}, "
        f"novel {frames['novel']}) of {r['tool']} at {r['size'][0]}x{r['size'][1]} to {r['dataset']} "
        f"in {r['seconds']:.1f} s ({r['bytes'] / 1e6:.1f} MB)"
    )



# ---------------------------------------------------------------------------------------------
# narf restyle

CONDITIONS = ("lighting", "noise", "depth", "mask", "occlusion-20", "occlusion-40", "all")  # faults.CONDITIONS


def _add_restyle(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "restyle",
        help="re-render a dataset's frames with Mitsuba (lights, gloss, clutter) plus sensor and segmenter faults",
        description=(
            "Path-trace the frames of DATASET (same object, poses and joints) with Mitsuba 3: random lights "
            "(environment, area, point, sun; colour temperature), glossy materials, a textured ground plane, "
            "clutter and shadows. Depth holds the table and clutter too; labels mark the tool's visible pixels. "
            "Then each condition adds its faults (noise: exposure, white balance, blur, shot/read noise, JPEG; "
            "depth: stereo noise growing with z^2, holes at edges and thin parts, 1 mm steps; mask: erosion/"
            "dilation, a missing or extra blob, a soft edge; occlusion-20/-40: an occluder hiding that share of "
            "the tool; all: noise, depth, mask and occlusion-20). Writes OUT/<condition>/ datasets and caches the "
            "renders in OUT/renders/. Deterministic from --seed. Needs the realism extra (mitsuba)."
        ),
    )
    arg = parser.add_argument
    arg("dataset", type=Path, help="source dataset (narf synth)")
    arg("--out", required=True, type=Path, metavar="DIR")
    arg("--size", nargs=2, type=_positive_int, default=None, metavar=("W", "H"),
        help="image size (K scaled; default: the dataset's)")
    arg("--conditions", nargs="+", choices=CONDITIONS, default=["lighting"], metavar="NAME",
        help=f"one or more of {', '.join(CONDITIONS)} (default: lighting)")
    arg("--splits", nargs="+", choices=("train", "test", "novel"), default=None, help="default: every split")
    arg("--limit", type=_positive_int, default=None, metavar="N", help="only the first N frames of each split")
    arg("--seed", type=_non_negative_int, default=0)
    arg("--spp", type=_positive_int, default=32, help="path-tracing samples per pixel (default: %(default)s)")
    arg("--overwrite", action="store_true", help="replace datasets already in OUT/<condition>/")
    _add_json_flag(parser)
    parser.set_defaults(run=_run_restyle)


def _run_restyle(args: argparse.Namespace) -> int:
    import torch

    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.restyle import mitsuba, restyle

    mitsuba()  # one error line, before any work, when the extra is missing
    import drjit

    drjit.set_thread_count(torch.get_num_threads())  # Mitsuba's render threads follow --threads
    frame_ids = None
    if args.limit is not None:
        source = Dataset.open(args.dataset)
        splits = args.splits or ("train", "test", "novel")
        frame_ids = [f.id for split in splits for f in source.frames(split)[: args.limit]]
    start = time.perf_counter()
    out = restyle(args.dataset, args.out, conditions=tuple(args.conditions), size=args.size, seed=args.seed,
                  spp=args.spp, splits=tuple(args.splits) if args.splits else None, frame_ids=frame_ids,
                  overwrite=args.overwrite, progress=True)
    first = Dataset.open(next(iter(out.values())))
    result = {"datasets": {name: str(path) for name, path in out.items()}, "frames": len(first),
              "size": [first.camera.width, first.camera.height], "spp": args.spp,
              "seconds": round(time.perf_counter() - start, 3)}
    _emit(args, result, lambda r: f"wrote {len(r['datasets'])} dataset(s) of {r['frames']} frames at "
          f"{r['size'][0]}x{r['size'][1]} ({', '.join(r['datasets'])}) to {args.out} in {r['seconds']:.1f} s")
    return 0


# ---------------------------------------------------------------------------------------------
# Inputs shared by render and estimate: poses, joints, intrinsics (JSON text or a JSON file)


def _json_arg(text: str, what: str) -> Any:
    """``text`` as JSON, or the JSON in the file it names."""
    source = text
    if not text.lstrip().startswith(("{", "[")):
        path = Path(text)
        if not path.is_file():
            raise ValueError(f"{what}: {text!r} is neither JSON nor a JSON file")
        source = path.read_text()
    try:
        return json.loads(source)
    except json.JSONDecodeError as e:
        raise ValueError(f"{what}: invalid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None


def _pose_arg(text: str, what: str):
    """A pose from ``{"matrix": 4x4}`` or ``{"position": [x,y,z], "orientation": [qx,qy,qz,qw]}``,
    checked by :func:`narf_core.checks.check_pose`."""
    import numpy as np

    from narf_core.checks import ROTATION_TOLERANCE, check_pose

    value = _json_arg(text, what)
    if isinstance(value, dict) and "pose" in value:
        value = value["pose"]
    if isinstance(value, list):
        value = {"matrix": value}
    if not isinstance(value, dict):
        raise ValueError(f"{what}: expected {{'matrix': 4x4}} or {{'position', 'orientation'}}")
    if "matrix" in value:
        T = np.asarray(value["matrix"], dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"{what}: matrix must be 4x4, got shape {T.shape}")
    elif "position" in value and "orientation" in value:
        p = np.asarray(value["position"], dtype=np.float64)
        q = np.asarray(value["orientation"], dtype=np.float64)
        if p.shape != (3,) or q.shape != (4,):
            raise ValueError(f"{what}: position needs 3 values and orientation 4 (qx, qy, qz, qw)")
        if not np.isfinite(q).all() or abs(np.linalg.norm(q) - 1) > ROTATION_TOLERANCE:
            raise ValueError(f"{what}: orientation must be a unit quaternion, got norm {np.linalg.norm(q):.4g}")
        T = _pose_from(p, q)
    else:
        raise ValueError(f"{what}: expected {{'matrix': 4x4}} or {{'position', 'orientation'}}")
    return check_pose(T, what)


def _pose_from(position, orientation):
    import torch

    from narf_core.geometry import pose_from_position_quaternion

    return pose_from_position_quaternion(
        torch.as_tensor(position, dtype=torch.float64), torch.as_tensor(orientation, dtype=torch.float64)
    ).numpy()


def _joints_arg(text: str | None, what: str = "--joints") -> dict[str, float] | None:
    """``name=value,name=value`` or a JSON object."""
    if text is None:
        return None
    if text.lstrip().startswith("{") or Path(text).is_file():
        value = _json_arg(text, what)
        if isinstance(value, dict) and "joints" in value and isinstance(value["joints"], dict):
            value = value["joints"]
        if not isinstance(value, dict):
            raise ValueError(f"{what}: expected a JSON object {{name: value}}")
        items = value.items()
    else:
        items = []
        for part in text.split(","):
            name, sep, number = part.partition("=")
            if not sep:
                raise ValueError(f"{what}: expected name=value pairs separated by commas, got {part!r}")
            items.append((name.strip(), number))
    out = {}
    for name, number in items:
        try:
            out[str(name)] = float(number)
        except (TypeError, ValueError):
            raise ValueError(f"{what}: joint {name!r} has a non-numeric value {number!r}") from None
    return out


def _camera_arg(K_text: str, width: int, height: int):
    """A :class:`~narf_core.geometry.Pinhole` from ``fx,fy,cx,cy`` or a JSON 3x3 matrix."""
    import numpy as np
    import torch

    from narf_core.geometry import Pinhole

    if K_text.lstrip().startswith("[") or Path(K_text).is_file():
        K = np.asarray(_json_arg(K_text, "--K"), dtype=np.float64)
    else:
        try:
            fx, fy, cx, cy = (float(v) for v in K_text.split(","))
        except ValueError:
            raise ValueError(f"--K: expected fx,fy,cx,cy or a JSON 3x3 matrix, got {K_text!r}") from None
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"--K: expected a 3x3 matrix with positive focal lengths, got {K.tolist()}")
    return Pinhole(torch.as_tensor(K, dtype=torch.float32), width, height)


def _read_image(path: Path, what: str, mode: str | None = None):
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.array(im.convert(mode) if mode else im)
    except UnidentifiedImageError:
        raise ValueError(f"{what}: {path} is not an image PIL can read") from None


# ---------------------------------------------------------------------------------------------
# narf train


def _add_train(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "train",
        help="train a model (part fields, then the configuration field) from a dataset",
        description=(
            "Stage 1 trains one radiance field per rigid part on the dataset's train split; stage 2 "
            "makes the configuration field F(x, d, theta): by default the articulated field (the part "
            "fields' features looked up in each part's frame, posed by the URDF's forward kinematics inside "
            "the field: seconds), or with --field distilled the paper's field, distilled from renders of "
            "the composed parts. Writes one .narf bundle. Resumable: an interrupted run leaves MODEL.narf.work/ "
            "and running the same command again continues from its last checkpoint."
        ),
    )
    arg = parser.add_argument
    arg("dataset", type=Path, help="dataset folder written by narf synth")
    arg("--out", required=True, type=Path, metavar="MODEL.narf", help="bundle to write")
    arg("--arch", choices=("kplanes", "fastnerf"), default="kplanes", help="field architecture (default: %(default)s)")
    arg("--field", choices=("articulated", "distilled"), default="articulated",
        help="configuration field (default: %(default)s; articulated needs --arch kplanes and a joint, "
             "else the distilled field is trained)")
    arg("--budget", type=_non_negative_float, metavar="SECONDS", help="time cap of the two training stages "
        "(the modes' measurement and the tracker's fit after them take 1-2 min more on one thread)")
    arg("--part-steps", type=_positive_int, metavar="N", help="stage-1 steps per part")
    arg("--distill-steps", type=_positive_int, metavar="N", help="stage-2 steps")
    arg("--batch-rays", type=_positive_int, metavar="N", help="rays per step")
    arg("--composites", type=_non_negative_int, metavar="N", help="stage 2 on N pre-rendered composite views "
        "(the paper: 5000) instead of fresh rays every step (0, the default)")
    arg("--free-space-weight", type=float, metavar="W", help="stage 1's free-space term: the "
        "opacity a part renders in front of the depth measured on any labelled pixel (0, the default: off)")
    arg("--sparsity-weight", type=float, metavar="W", help="stage 1's sparsity term: the opacity a part "
        "renders at random points of its box away from its own surfaces, so that it leaves empty what no "
        "training view shows (default 0.1; 0: off)")
    arg("--exclusion-weight", type=float, metavar="W", help="stage 1's exclusion term: the opacity a part "
        "renders on the other parts' surfaces at the training configurations, where parts that touch in every "
        "training view would otherwise run on into each other (default 1; 0: off)")
    arg("--no-parts", action="store_true", help="leave the part fields out of the bundle (no 'parts' mode)")
    arg("--track-sequences", type=_non_negative_int, metavar="N", help="fit the tracker's own factor on σ on N "
        "smooth 60-frame sequences of the dataset's object, about half a minute each (default 3; 0: the pooled "
        "factor)")
    arg("--seed", type=_non_negative_int, default=0)
    parser.set_defaults(run=_run_train)


def _run_train(args: argparse.Namespace) -> int:
    from narf_core.train.pipeline import TrainConfig, TrainInputError, train

    overrides = {"part_steps": args.part_steps, "distill_steps": args.distill_steps, "batch_rays": args.batch_rays,
                 "composites": args.composites, "free_space_weight": args.free_space_weight,
                 "sparsity_weight": args.sparsity_weight, "exclusion_weight": args.exclusion_weight,
                 "track_sequences": args.track_sequences}
    try:
        config = TrainConfig(arch=args.arch, field=args.field, budget_s=args.budget, seed=args.seed, keep_parts=not args.no_parts)
        config = replace(config.for_arch(), **{k: v for k, v in overrides.items() if v is not None})
    except TrainInputError as e:
        raise _flag_error(e, {"budget_s": "budget"}) from None
    start = time.perf_counter()
    out = train(args.dataset, args.out, config, command=shlex.join(["narf", *args.argv]), progress=True)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - start:.0f} s")
    from narf_core.bundle import load_bundle

    model = load_bundle(out)
    _print_auto_mode(model)
    _print_track_sigma(model)
    return 0


def _print_track_sigma(model: NarfModel) -> None:
    """The tracker's own factors on σ that training fitted, if it did."""
    fitted = (model.metadata.get("uncertainty") or {}).get("track")
    for fit in (fitted, (fitted or {}).get("fine")):
        if fit:
            print(f"  tracker's factor on σ at fx {fit['fx']:g} px: RGB-D {fit['rgbd']:g}, RGB only {fit['rgb']:g} "
                  f"(fitted on {fit['rgbd_frames']} / {fit['rgb_frames']} frames of {len(fitted['seeds'])} sequences)")
    means = (fitted or {}).get("rgb_add_m")
    if means:  # the frame Jacobian without depth it measured (TrackOptions.jacobian_rgb "auto" takes it)
        print(f"  tracker's Jacobian without depth: {fitted['jacobians']['rgb']} (mean ADD on those frames "
              + ", ".join(f"{m * 100:.2f} cm by {j}" for j, m in means.items()) + ")")
    means = (fitted or {}).get("rgbd_add_m")
    if means:  # the rays per iteration with depth it measured (TrackOptions.rays_per_iteration 0 takes them)
        print(f"  tracker's rays per iteration with depth: {fitted['rays']['rgbd']} (mean ADD on those frames "
              + ", ".join(f"{m * 100:.3f} cm on {n}" for n, m in means.items()) + ")")
    means = (fitted or {}).get("rgbd_huber_add_m")
    if means:  # the Huber scale with depth it measured (TrackOptions.robust_scale 0 takes it)
        print(f"  tracker's Huber scale with depth: {fitted['robust_scale']['rgbd']:g} (mean ADD on those frames "
              + ", ".join(f"{m * 100:.3f} cm at {s}" for s, m in means.items()) + ")")


def _print_auto_mode(model: NarfModel) -> None:
    """The held-out measurement of each render mode in ``model`` and the mode ``auto`` takes, and why."""
    from narf_core.modes import RECORD_KEY, choose_mode, describe_record

    for line in describe_record(model.metadata.get(RECORD_KEY)):
        print(f"  {line}")
    mode, reason = choose_mode(model)
    print(f"mode auto renders {mode}: {reason}")


# ---------------------------------------------------------------------------------------------
# narf eval


def _add_eval(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "eval",
        help="render error (per-pixel MSE, PSNR) and time of a model on a dataset split",
        description=(
            "Renders every frame of a split at its labelled pose and configuration and compares it "
            "with the observation masked by the labels (the paper's per-pixel MSE over the full "
            "image, RGB in [0, 1]). Prints MSE, PSNR, N and the median milliseconds per image."
        ),
    )
    arg = parser.add_argument
    arg("model", type=Path, metavar="MODEL.narf")
    arg("dataset", type=Path)
    arg("--split", choices=("train", "test", "novel"), default="test")
    arg("--mode", choices=MODES, default="auto", help=MODE_HELP)
    arg("--limit", type=_positive_int, metavar="N", help="only the first N frames")
    arg("--clean", action="store_true", help="score against the clean ground truth of a noisy dataset")
    arg("--record-modes", action="store_true",
        help="first measure both render modes on the dataset's test and novel views as `narf train` does, and "
             "write the measurement into MODEL.narf (for bundles trained before it existed); `auto` then uses it")
    _add_json_flag(parser)
    parser.set_defaults(run=_run_eval)


def _run_eval(args: argparse.Namespace) -> int:
    from narf_core.bundle import load_bundle
    from narf_core.data.dataset import Dataset
    from narf_core.evaluate import evaluate_render

    model = load_bundle(args.model, args.device)
    dataset = Dataset.open(args.dataset, clean=args.clean)
    recorded = None
    if args.record_modes:
        from narf_core.bundle import save_bundle
        from narf_core.modes import RECORD_KEY, describe_record, measure_modes

        recorded = measure_modes(model, dataset)
        if recorded is None:
            raise ValueError(f"--record-modes: dataset {args.dataset} has no test or novel frames to measure on")
        model.metadata[RECORD_KEY] = recorded
        save_bundle(args.model, model)
        if not args.json:
            print("\n".join([f"recorded in {args.model}:", *(f"  {line}" for line in describe_record(recorded))]))
    mode, reason = _mode_arg(model, args.mode)
    score = evaluate_render(model, dataset, split=args.split, mode=mode, limit=args.limit, progress=True)
    result = {**score.summary(), "mode_reason": reason, **({"mode_measurement": recorded} if recorded else {})}
    _emit(args, result, lambda r: (
        f"{r['split']} ({r['mode']}, {r['width']}x{r['height']}): MSE {r['mse']:.5f}  PSNR {r['psnr']:.2f} dB  "
        f"N {r['n']}  {r['ms_per_image']:.1f} ms/image" + _mode_line(r)))
    return 0


# ---------------------------------------------------------------------------------------------
# narf points


def _add_points(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "points", help="add the dense surface points that depth is fitted to, to a bundle saved without them",
        description="Sample a few millimetres apart the meshes of the URDF the model was trained on (checked against "
                    "the bundle's own points) and write the bundle with them (models trained now keep them already).",
    )
    arg = parser.add_argument
    arg("model", type=Path, metavar="MODEL.narf")
    arg("--urdf", required=True, type=Path, metavar="URDF", help="the training data's object.urdf, its meshes beside it")
    arg("--out", type=Path, metavar="OUT.narf", help="where to write (default: over MODEL.narf)")
    _add_json_flag(parser)
    parser.set_defaults(run=_run_points)


def _run_points(args: argparse.Namespace) -> int:
    from narf_core.bundle import load_bundle, save_bundle, with_dense_points

    model = with_dense_points(load_bundle(args.model), args.urdf)
    out = save_bundle(args.out or args.model, model)
    result = {"out": str(out), "points": {name: len(p) for name, p in model.dense_points.items()}}
    _emit(args, result, lambda r: f"wrote {r['out']}: " + ", ".join(f"{n} {c}" for n, c in r["points"].items())
          + " dense points")
    return 0


# ---------------------------------------------------------------------------------------------
# narf render


def _add_render(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "render", help="render a model at a pose and configuration to PNG",
        description="Render RGB (and optionally depth as 16-bit PNG millimetres, 0 = none) of a model.",
    )
    arg = parser.add_argument
    arg("model", type=Path, metavar="MODEL.narf")
    arg("--pose", required=True, metavar="JSON|FILE", help="T_cam_obj: {\"matrix\": 4x4} or {\"position\", \"orientation\"}")
    arg("--joints", metavar="NAME=V,...|JSON", help="joint values (default: mid-range)")
    arg("--K", metavar="FX,FY,CX,CY|JSON", help="intrinsics (default: Primesense-like scaled to --size)")
    arg("--size", nargs=2, type=_positive_int, default=(160, 120), metavar=("W", "H"))
    arg("--mode", choices=MODES, default="auto", help=MODE_HELP)
    arg("--out", required=True, type=Path, metavar="PNG")
    arg("--depth", type=Path, metavar="PNG", help="also write depth (uint16 millimetres)")
    _add_json_flag(parser)
    parser.set_defaults(run=_run_render)


def _run_render(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from PIL import Image

    from narf_core.bundle import load_bundle
    from narf_core.data.dataset import write_png_depth
    from narf_core.geometry import Pinhole

    width, height = args.size
    camera = _camera_arg(args.K, width, height) if args.K else Pinhole.primesense(width, height)
    T = _pose_arg(args.pose, "--pose")
    model = load_bundle(args.model, args.device)
    mode, reason = _mode_arg(model, args.mode)
    theta = model.joint_vector(_joints_arg(args.joints), field="--joints")
    outputs = ("rgb", "depth") if args.depth else ("rgb",)
    start = time.perf_counter()
    images = model.render(torch.as_tensor(T, dtype=torch.float32), theta, camera, outputs=outputs, mode=mode)
    ms = 1000 * (time.perf_counter() - start)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((images["rgb"].cpu().numpy() * 255 + 0.5).astype(np.uint8)).save(args.out)
    if args.depth:
        write_png_depth(args.depth, images["depth"].cpu().numpy())
    result = {"rgb": str(args.out), "depth": str(args.depth) if args.depth else None, "ms": round(ms, 2),
              "joints": model.joint_dict(theta), "mode": mode, "mode_reason": reason}
    _emit(args, result, lambda r: f"wrote {r['rgb']}" + (f" and {r['depth']}" if r["depth"] else "")
          + f" in {r['ms']:.1f} ms ({r['mode']})" + _mode_line(r))
    return 0


# ---------------------------------------------------------------------------------------------
# narf estimate


def _add_estimate(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "estimate", help="refine pose and joint configuration from an image, a mask and an initial pose",
        description=(
            "iNeRF-style render-and-compare: Adam on a left-multiplied se(3) pose increment and the "
            "joint values (kept inside their limits) through the model's renderer, from an initial "
            "pose. Defaults follow the paper: 150 iterations, masked photometric MSE."
        ),
    )
    arg = parser.add_argument
    arg("model", type=Path, metavar="MODEL.narf")
    arg("--image", required=True, type=Path, metavar="PNG")
    arg("--mask", required=True, type=Path, metavar="PNG", help="object mask (non-zero = object)")
    arg("--K", required=True, metavar="FX,FY,CX,CY|JSON")
    arg("--init-pose", required=True, metavar="JSON|FILE", help="initial T_cam_obj")
    arg("--init-joints", metavar="NAME=V,...|JSON", help="initial joint values (default: mid-range)")
    arg("--depth", type=Path, metavar="PNG", help="observed depth, uint16 millimetres (0 = none)")
    arg("--gt", metavar="JSON|FILE", help="ground truth {\"pose\": ..., \"joints\": {...}}: report ADD and joint error")
    arg("--iterations", type=_non_negative_int, metavar="N")
    arg("--mode", choices=MODES, default="auto", help=MODE_HELP)
    arg("--preset", choices=PRESET_NAMES, default="auto",
        help="auto (default): gauss-newton with --depth, robust without; paper: the paper's loss and settings; "
             "robust: adds silhouette and depth (with --depth) terms, several joint starts and coarse-to-fine; "
             "gauss-newton: the same terms with a Levenberg-Marquardt solver and Huber weights")
    arg("--pose-starts", type=_positive_int, metavar="N",
        help="the given pose and N - 1 turned by 30 deg, scored before refining (at most 11; default: the "
             "preset's, 1); robust with 9 finds the pose from 30 deg / 6 cm off")
    arg("--refinements", type=_positive_int, metavar="N",
        help="without --depth, or with a mask the depth contradicts: N refinements, the one of lowest loss "
             "on one fixed set of rays kept (at most 8; default 1, robust without --depth 3); N times the time")
    arg("--set", action="append", default=[], metavar="OPTION=JSON",
        help="set one of the refiner's options on top of the preset, e.g. --set ray_sampling='\"edges\"' for an "
             "object whose moving parts cover a few pixels (repeatable; over the flags above)")
    _add_json_flag(parser)
    parser.set_defaults(run=_run_estimate)


def option_overrides(items: list[str]) -> dict:
    """``["name=JSON", ...]`` (``--set``) as ``{name: value}`` for :class:`~narf_core.estimate.EstimateOptions`;
    a ``ValueError`` naming the bad item, or the option whose value the options refuse."""
    from dataclasses import fields

    from narf_core.estimate import EstimateOptions

    names = {f.name for f in fields(EstimateOptions)}
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or name not in names:
            raise ValueError(f"--set {item!r}: expected OPTION=JSON with OPTION one of the refiner's options")
        try:
            out[name] = json.loads(text)
        except json.JSONDecodeError:
            raise ValueError(f"--set {item!r}: the value is not JSON (strings need quotes: {name}='\"...\"')") from None
    EstimateOptions(**out)  # a bad value is an EstimateInputError (a ValueError) naming the option
    return out


def _run_estimate(args: argparse.Namespace) -> int:
    import numpy as np

    from narf_core.bundle import load_bundle
    from narf_core.data.dataset import read_depth
    from narf_core.estimate import EstimateOptions, choose_preset, refine

    image = _read_image(args.image, "--image", "RGB")
    mask = _read_image(args.mask, "--mask")
    if mask.ndim == 3:
        mask = mask[..., 0]
    depth = read_depth(args.depth) if args.depth else None
    camera = _camera_arg(args.K, image.shape[1], image.shape[0])
    T_init = _pose_arg(args.init_pose, "--init-pose")
    ground_truth = None
    if args.gt:
        gt = _json_arg(args.gt, "--gt")
        if not isinstance(gt, dict) or "pose" not in gt:
            raise ValueError("--gt: expected {\"pose\": ..., \"joints\": {...}}")
        ground_truth = (_pose_arg(json.dumps(gt["pose"]), "--gt pose"), _joints_arg(json.dumps(gt.get("joints", {})), "--gt joints"))
    chosen = {"iterations": args.iterations, "pose_starts": args.pose_starts, "refinements": args.refinements,
              "rgb_refinements": args.refinements}
    preset, preset_reason = choose_preset(args.preset, depth is not None)
    options = EstimateOptions.preset(preset, **{"mode": args.mode, **{k: v for k, v in chosen.items() if v is not None},
                                                **option_overrides(args.set)})
    model = load_bundle(args.model, args.device)
    _mode_arg(model, args.mode)  # a mode the model lacks, named as the flag
    result = refine(model, image, mask > 0, camera, T_init, joints_init=_joints_arg(args.init_joints, "--init-joints"),
                    depth=depth, options=options, ground_truth=ground_truth)
    out = {
        "pose": {"matrix": np.asarray(result.T_cam_obj).tolist(), "position": list(map(float, result.position)),
                 "orientation": list(map(float, result.quaternion))},
        "joints": result.joints, "loss": result.loss, "iterations": result.iterations,
        "seconds": round(result.seconds, 3), "status": result.status,
        "recovered_non_finite": result.recovered_non_finite, "metrics": result.metrics,
        "warnings": list(result.warnings),
        "uncertainty": None if result.uncertainty is None else result.uncertainty.to_dict(),
        "mode": result.mode, "mode_reason": result.mode_reason, "preset": preset, "preset_reason": preset_reason,
    }

    def human(r: dict[str, Any]) -> str:
        p = r["pose"]["position"]
        lines = [f"{r['status']} after {r['iterations']} iterations in {r['seconds']:.2f} s ({r['preset']}, {r['mode']}), "
                 f"loss {r['loss']}" + _mode_line(r),
                 f"position [{p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}] m, joints " +
                 ", ".join(f"{k}={v:.4f}" for k, v in r["joints"].items())]
        if r["metrics"]:
            lines.append("metrics: " + ", ".join(f"{k}={v:.4g}" for k, v in r["metrics"].items() if isinstance(v, (int, float))))
        u = r["uncertainty"]
        if u:
            lines.append(
                "σ position [" + ", ".join(f"{1000 * s:.2f}" for s in u["position_sigma_m"]) + "] mm, rotation ["
                + ", ".join(f"{math.degrees(s):.2f}" for s in u["rotation_sigma_rad"]) + "] deg, joints "
                + ", ".join(f"{k}={v:.4g}" for k, v in u["joint_sigma"].items())
            )
        lines += [f"warning: {w}" for w in r["warnings"]]
        return "\n".join(lines)

    _emit(args, out, human)
    return 0


# ---------------------------------------------------------------------------------------------
# narf track


def _flag_error(error: InputError, renamed: Mapping[str, str] | None = None) -> ValueError:
    """The core's error on ``options.<name>`` as one about the flag the user typed: ``--<name> <reason>``,
    the name with dashes (or as ``renamed`` maps it)."""
    name = (error.field or "options").removeprefix("options.")
    return ValueError(f"--{(renamed or {}).get(name, name.replace('_', '-'))} {error.reason}")


OUTSIDE_WEIGHT_HELP = ("without depth, weigh the rays outside the mask this much (TrackOptions.outside_weight_rgb; "
                       "default 1, the mask trusted in full; 0.3 where a hand or a fixture stays in front of the tool)")


def _add_track(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "track", help="track pose and joints over a sequence (narf synth --sequence), one row per frame",
        description=(
            "Warm-started render-and-compare over a sequence in time order: a constant-velocity prediction, a few "
            "refiner iterations per frame, a lost-track test (mask overlap, covariance) and re-initialisation with "
            "the multi-start refiner. Prints one row per frame (status: tracking, uncertain, lost, reinitialised) "
            "with its error against the sequence's labels."
        ),
    )
    arg = parser.add_argument
    arg("model", type=Path, metavar="MODEL.narf")
    arg("sequence", type=Path, metavar="SEQUENCE", help="a dataset whose frames carry times (narf synth --sequence)")
    arg("--init-pose", required=True, metavar="JSON|FILE|label|detect",
        help="T_cam_obj at the first frame (rough is fine), 'label' for the first frame's label, or 'detect' to "
             "find it in the first frame (its mask, and depth unless --rgb-only)")
    arg("--init-joints", metavar="NAME=V,...|JSON", help="joints at the first frame (default: the label with "
        "--init-pose label, else mid-range)")
    arg("--rgb-only", action="store_true", help="ignore the sequence's depth")
    arg("--limit", type=_positive_int, metavar="N", help="only the first N frames")
    arg("--iterations", type=_positive_int, metavar="N", help="refiner iterations per frame (default: the "
        f"solver's, {TRACK_ITERATIONS})")
    arg("--solver", choices=TRACK_SOLVER_CHOICES, default="auto",
        help=f"refiner per frame (default: %(default)s, {TRACK_AUTO_SOLVER})")
    arg("--mode", choices=MODES, default="auto", help=MODE_HELP)
    arg("--outside-weight-rgb", type=_non_negative_float, metavar="W", help=OUTSIDE_WEIGHT_HELP)
    arg("--video", type=Path, metavar="OUT.gif", help="write the frames with the model's silhouette over them")
    _add_json_flag(parser)
    parser.set_defaults(run=_run_track)


def _run_track(args: argparse.Namespace) -> int:
    import numpy as np

    from narf_core.bundle import load_bundle
    from narf_core.data.dataset import Dataset
    from narf_core.track import TrackInputError, TrackOptions, track
    from narf_core.track_io import load_frames, overlay, score, sequence_frames, write_video

    if args.video is not None and args.video.suffix.lower() != ".gif":
        raise ValueError(f"--video: {args.video.name}: only .gif is supported (no video codec is installed)")
    dataset = Dataset.open(args.sequence)
    frames = sequence_frames(dataset, limit=args.limit)
    model = load_bundle(args.model, args.device)
    if args.init_pose == "label":
        T_first, joints_first = frames[0].T_cam_obj, frames[0].joints
    elif args.init_pose == "detect":  # no pose: found in the first frame (narf_core/detect.py)
        from narf_core.detect import detect

        first = next(load_frames(dataset, frames[:1], rgb_only=args.rgb_only))
        found = detect(model, dataset.camera, first.image, first.mask, first.depth)
        T_first, joints_first = found.T_cam_obj, found.joints
    else:
        T_first, joints_first = _pose_arg(args.init_pose, "--init-pose"), None
    if args.init_joints:
        joints_first = _joints_arg(args.init_joints, "--init-joints")
    try:
        options = TrackOptions(solver=args.solver, mode=args.mode,
                               **({"iterations": args.iterations} if args.iterations else {}),
                               **({} if args.outside_weight_rgb is None else {"outside_weight_rgb": args.outside_weight_rgb}))
    except TrackInputError as e:
        raise _flag_error(e) from None
    mode, reason = _mode_arg(model, args.mode)
    if not args.json:
        print(f"render mode {mode}" + ("" if reason == "requested" else f" (auto): {reason}"), flush=True)
    rows, pictures = [], []
    start = time.perf_counter()
    results = track(model, load_frames(dataset, frames, rgb_only=args.rgb_only), dataset.camera, T_first,
                    joints_first, options)
    for frame, result in zip(frames, results):
        row = {"frame": frame.id, **result.to_dict(), **score(model, frame, result)}
        rows.append(row)
        if not args.json:
            print(f"{frame.id:5d} {result.time:7.3f}s {result.status:13s} ADD {row['add_m'] * 100:6.2f} cm  "
                  + " ".join(f"{j.name}={result.joints[j.name]:.4f}" for j in model.joints)
                  + f"  {result.seconds * 1000:6.1f} ms" + (f"  ({result.reason})" if result.reason else ""), flush=True)
            for warning in result.warnings:
                print(f"      warning: {warning}", flush=True)
        if args.video is not None:
            pictures.append(overlay(model, dataset.camera, dataset.load(frame).rgb, result))
    seconds = time.perf_counter() - start
    held = [r["add_m"] for r in rows if r["status"] != "lost"]
    summary = {
        "frames": len(rows), "seconds": round(seconds, 3), "mode": mode, "mode_reason": reason,
        "frames_per_second": round(len(rows) / sum(r["seconds"] for r in rows), 2),
        "statuses": {s: sum(r["status"] == s for r in rows) for s in ("tracking", "uncertain", "lost", "reinitialised")},
        "add_m": {"mean": float(np.mean(held)), "p95": float(np.percentile(held, 95)), "max": float(np.max(held))}
        if held else None,
        "video": str(write_video(args.video, pictures, 1 / max(np.median(np.diff([f.time for f in frames])), 1e-3)))
        if args.video is not None and pictures else None,
    }
    if args.json:
        print(json.dumps({"summary": summary, "frames": rows}, indent=1))
    else:
        add_m = summary["add_m"]
        print(f"{summary['frames']} frames, {summary['frames_per_second']:.1f} frames/s tracking, statuses "
              f"{summary['statuses']}" + (f", ADD mean {add_m['mean'] * 100:.2f} cm, p95 {add_m['p95'] * 100:.2f} cm, "
                                          f"max {add_m['max'] * 100:.2f} cm" if add_m else "")
              + (f", video {summary['video']}" if summary["video"] else ""))
    return 0


# ---------------------------------------------------------------------------------------------
# narf bench


def _add_bench(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "bench", help="benchmarks: error and run time side by side (render, estimate, distill, service)",
        description="Benchmarks shaped like the paper's tables, with run time beside every error figure.",
    )
    parser.add_argument(
        "--busy", type=_non_negative_int, default=0, metavar="N",
        help="run N other CPU-bound processes during the benchmark (a shared machine); threads are "
             "chosen after they start",
    )
    which = parser.add_subparsers(dest="bench", required=True, metavar="WHAT")
    for name, help_text in (
        ("render", "Table I: render MSE/PSNR and ms per image per object, split and mode"),
        ("estimate", "Table II: ADD and per-joint error per object, split and mode, with seconds per scene"),
    ):
        sub = which.add_parser(name, help=help_text, description=help_text)
        sub.add_argument("--work", type=Path, default=Path("runs/bench"), help="folder for data, models and results")
        sub.add_argument("--tools", nargs="+", default=None, metavar="TOOL")
        sub.add_argument("--noise", action="store_true", help="also on datasets with label noise")
        sub.add_argument("--quick", action="store_true", help="reduced run on the bundled demo model(s), no training")
        sub.add_argument("--models", type=Path, default=Path("models"), help="bundled models (for --quick)")
        _add_json_flag(sub)
        sub.set_defaults(run=_run_bench_render if name == "render" else _run_bench_estimate)
    sub = which.add_parser(
        "distill", help="stage 2 streamed vs the paper's pool of composited views: render error per second",
        description="Distils a bundle's part fields again into a fresh configuration field, streamed and from "
                    "a pool of composited views, each for the same wall-clock budgets, and scores both.",
    )
    sub.add_argument("model", type=Path, metavar="MODEL.narf", help="a bundle with part fields")
    sub.add_argument("dataset", type=Path, help="dataset to score on (test and novel splits)")
    sub.add_argument("--budgets", type=_non_negative_float, nargs="+", default=[60.0, 180.0], metavar="SECONDS")
    sub.add_argument("--composites", type=_positive_int, default=5000, help="views in the pool (the paper: 5000)")
    sub.add_argument("--work", type=Path, default=Path("runs/bench"), help="folder for the results")
    _add_json_flag(sub)
    sub.set_defaults(run=_run_bench_distill)
    sub = which.add_parser(
        "shift", help="Table II on path-traced images with sensor, depth, mask and occlusion faults",
        description="Restyles the test and novel frames with Mitsuba (narf restyle) at the camera's native size, "
                    "then runs the estimate protocol per condition, input (rgb, rgbd), preset and perturbation "
                    "scale: ADD, share under 1 cm, per-joint error and seconds per scene. Needs the realism extra.",
    )
    sub.add_argument("--work", type=Path, default=Path("runs/bench"), help="folder for data, models and results")
    sub.add_argument("--tools", nargs="+", default=None, metavar="TOOL", help="default: the bundled models")
    sub.add_argument("--models", type=Path, default=Path("models"), help="bundled models")
    sub.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS), metavar="NAME")
    sub.add_argument("--inputs", nargs="+", choices=("rgb", "rgbd"), default=["rgb", "rgbd"])
    sub.add_argument("--splits", nargs="+", choices=("test", "novel"), default=["test", "novel"])
    sub.add_argument("--scenes", type=_positive_int, default=17, help="per split (default: %(default)s)")
    sub.add_argument("--scales", type=_non_negative_float, nargs="+", default=[1.0, 3.0],
                     help="perturbation scales (default: 1 3)")
    sub.add_argument("--presets", nargs="+", default=None, metavar="PRESET", help="default: every refiner preset")
    sub.add_argument("--set", action="append", default=[], metavar="OPTION=JSON",
                     help="override a refiner option in every preset, e.g. --set ray_sampling='\"edges\"' (repeatable)")
    sub.add_argument("--ray-seeds", type=_non_negative_int, nargs="+", default=None, metavar="R",
                     help="refine every scene once per seed of the refiner's ray draws (EstimateOptions.seed; "
                          "default: the protocol's 0), a row each and one pooled: without depth one draw's mean "
                          "can be twice another's")
    sub.add_argument("--size", nargs=2, type=_positive_int, default=(640, 480), metavar=("W", "H"))
    sub.add_argument("--spp", type=_positive_int, default=16, help="path-tracing samples per pixel")
    sub.add_argument("--quick", action="store_true", help="3 scenes of the first split at the first scale")
    _add_json_flag(sub)
    sub.set_defaults(run=_run_bench_shift)
    sub = which.add_parser("service", help="requests/s and latency of /v1/render and /v1/estimate under load")
    sub.add_argument("--models", type=Path, default=Path("models"))
    sub.add_argument("--clients", type=_positive_int, default=8)
    sub.add_argument("--requests", type=_positive_int, default=200)
    sub.add_argument("--duration", type=_non_negative_float, default=30.0, metavar="SECONDS")
    sub.add_argument("--estimate-clients", type=_positive_int, default=16)
    _add_json_flag(sub)
    sub.set_defaults(run=_run_bench_service)
    sub = which.add_parser("hostile", help="/healthz latency while the service refuses hostile bodies and serves "
                                           "estimates; how fast abandoned estimates leave the queue")
    sub.add_argument("--models", type=Path, default=Path("models"))
    sub.add_argument("--estimates", type=_non_negative_int, default=4)
    sub.add_argument("--hostile-mb", type=_non_negative_float, default=30.0)
    sub.add_argument("--cancel-clients", type=_positive_int, default=16)
    _add_json_flag(sub)
    sub.set_defaults(run=_run_bench_hostile)
    sub = which.add_parser("viewer", help="web viewer: joint slider to new image on screen, in headless chromium")
    sub.add_argument("--models", type=Path, default=Path("models"))
    sub.add_argument("--drags", type=_positive_int, default=20, help="slider moves timed one by one")
    sub.add_argument("--size", nargs=2, type=_positive_int, default=(160, 120), metavar=("W", "H"))
    _add_json_flag(sub)
    sub.set_defaults(run=_run_bench_viewer)
    sub = which.add_parser("track", help="tracking: frames/s beside ADD and joint error per frame, lost tracks, "
                                         "NEES coverage, on synthetic sequences (RGB-D and RGB, 160x120 and 640x480)")
    sub.add_argument("--work", type=Path, default=Path("runs/bench"), help="folder for sequences and results")
    sub.add_argument("--models", type=Path, default=Path("models"), help="folder of the tools' models")
    sub.add_argument("--tools", nargs="+", default=None, metavar="TOOL", help="default: every model in --models")
    sub.add_argument("--frames", type=_positive_int, default=150, help="frames per sequence (default: %(default)s)")
    sub.add_argument("--size", dest="sizes", nargs=2, type=_positive_int, action="append", metavar=("W", "H"),
                     help="image size, repeatable (default: 160 120 and 640 480)")
    sub.add_argument("--modalities", nargs="+", choices=("rgbd", "rgb"), default=["rgbd", "rgb"])
    sub.add_argument("--events", action="store_true", help="also sequences with a glance away and an occluder")
    sub.add_argument("--seed", type=_non_negative_int, nargs="+", default=[0], metavar="S",
                     help="seeds of the synthesised sequences, one or more (default: 0)")
    sub.add_argument("--ray-seeds", type=_non_negative_int, nargs="+", default=[0], metavar="R",
                     help="track each sequence once per seed of the tracker's ray draws (TrackOptions.seed; "
                          "default: 0): without depth a track can end in either of two regimes by the draw alone")
    sub.add_argument("--images", nargs="+", choices=("pybullet", *CONDITIONS), default=["pybullet"],
                     metavar="KIND", help="what is tracked of each sequence: pybullet (as synthesised) and/or the "
                     "same frames path-traced under a narf restyle condition (one scene per sequence; made once, "
                     "needs the realism extra): " + ", ".join(CONDITIONS) + " (default: pybullet)")
    sub.add_argument("--spp", type=_positive_int, default=32, help="path-tracing samples per pixel for --images "
                     "(default: %(default)s)")
    sub.add_argument("--iterations", type=_positive_int, metavar="N", help="refiner iterations per frame "
                     f"(default: the solver's, {TRACK_ITERATIONS})")
    sub.add_argument("--rays", type=_positive_int, metavar="N",
                     help="rays per iteration (default: the solver's; with depth what each model's tracker "
                          "calibration chose)")
    sub.add_argument("--huber", type=_positive_float, metavar="S",
                     help="with depth, the frames' Huber scale (residual units; default: the preset's, or what each "
                          "model's tracker calibration chose)")
    sub.add_argument("--solver", choices=TRACK_SOLVER_CHOICES, default=None,
                     help=f"per-frame solver (default: the tracker's, auto: {TRACK_AUTO_SOLVER})")
    sub.add_argument("--band-m", type=_non_negative_float, metavar="M",
                     help="march only this far around the model's surface (0: the whole box; default: the tracker's)")
    sub.add_argument("--march", choices=("frame", "iteration"), default=None,
                     help="find each ray's samples once per frame (no marching) or march at every iteration "
                          "(default: the tracker's, frame)")
    sub.add_argument("--outside-weight-rgb", type=_non_negative_float, metavar="W",
                     help=OUTSIDE_WEIGHT_HELP)
    sub.add_argument("--jacobian", choices=JACOBIANS, default=None,
                     help="a Gauss-Newton frame's Jacobian: the field's derivatives at the samples or central "
                          f"differences of the render over about a sample spacing (default: {TRACK_JACOBIAN})")
    sub.add_argument("--jacobian-every-iteration", dest="jacobian_once", action="store_const", const=False,
                     default=None, help="with depth, take a Gauss-Newton frame's Jacobian again at every iteration "
                                        "(TrackOptions.jacobian_once off: once a frame by default; to compare)")
    sub.add_argument("--no-depth-align", dest="depth_align", action="store_false",
                     help="with depth, do not first move the prediction along the line of sight onto the observed "
                          "depth (TrackOptions.depth_align; to compare)")
    sub.add_argument("--surface-fit-iterations", type=_non_negative_int, default=None, metavar="N",
                     help="with depth, iterations of the prediction's fit to the observed depth's points in pose and "
                          "joints (TrackOptions.surface_fit_iterations; 0: off, to compare; default: the tracker's)")
    sub.add_argument("--no-occluder-test", dest="occluder_test", action="store_const", const=False, default=None,
                     help="with depth, trust the mask in full, also where the depth shows an occluder in front of the "
                          "render outside it (TrackOptions.occluder_test; to compare)")
    sub.add_argument("--hidden-joint-sigma", type=_non_negative_float, default=None, metavar="S",
                     help="with depth, hold a joint the mask hardly shows at the prediction to it by this σ, a share "
                          "of its half range (TrackOptions.hidden_joint_sigma; 0: free, to compare; default: the "
                          "tracker's)")
    sub.add_argument("--service-clients", type=_non_negative_int, default=0, metavar="N",
                     help="also N clients tracking at once through POST /v1/track on a loopback server")
    _add_json_flag(sub)
    sub.set_defaults(run=_run_bench_track)
    which.choices["estimate"].add_argument(
        "--shift", action="store_true",
        help="on path-traced images with sensor, depth, mask and occlusion faults: `narf bench shift` with its defaults",
    )
    which.choices["estimate"].add_argument("--presets", nargs="+", choices=PRESET_NAMES[1:],
                                           metavar="PRESET", help="refiner presets (default: all)")
    which.choices["estimate"].add_argument("--scenes", type=_positive_int, metavar="N",
                                           help="scenes per split (default: 17, 3 with --quick)")
    which.choices["estimate"].add_argument("--scales", type=_non_negative_float, nargs="+", metavar="X",
                                           help="perturbation sweep, multiples of 10 deg / 2 cm (default: 1 2 3)")
    which.choices["estimate"].add_argument("--pose-starts", type=_positive_int, metavar="N",
                                           help="every preset's pose_starts: the given pose and N - 1 turned by 30 deg "
                                                "(at most 11; default: each preset's, 1)")
    which.choices["estimate"].add_argument("--set", action="append", default=[], metavar="OPTION=JSON",
                                           help="override a refiner option in every preset, e.g. --set slide_share=0 "
                                                "(repeatable; over --pose-starts)")
    which.choices["estimate"].add_argument("--seed", type=_non_negative_int, metavar="S",
                                           help="the scenes, their perturbed starts and the refiner's rays (default: 0)")
    which.choices["estimate"].add_argument("--modes", nargs="+", choices=MODES[1:], metavar="MODE",
                                           help="render modes to refine in, of narf and parts (default: both; "
                                                "--quick: the first)")
    for sub in which.choices.values():  # last, so that it covers every benchmark declared above
        sub.set_defaults(run=_under_load(sub.get_default("run")))


def _under_load(run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``run`` beside ``args.busy`` CPU-bound processes, with torch's threads chosen once they run."""

    def run_under_load(args: argparse.Namespace) -> int:
        if not args.busy:
            return run(args)
        import torch

        from narf_benchmarks.load import busy_processes

        with busy_processes(args.busy):
            torch.set_num_threads(_threads_for(args))
            print(f"narf bench: {args.busy} busy process(es) running, torch threads {torch.get_num_threads()}",
                  file=sys.stderr)
            return run(args)

    return run_under_load


def _bench_tools(args: argparse.Namespace) -> tuple[str, ...]:
    if args.tools:
        return tuple(args.tools)
    if args.quick:
        return tuple(sorted(p.stem for p in args.models.glob("*.narf")))
    from narf_benchmarks.render import all_tools

    return all_tools()


def _run_bench_render(args: argparse.Namespace) -> int:
    from narf_benchmarks.checkpoint import sole_run
    from narf_benchmarks.render import RenderBenchConfig, markdown, run

    tools = _bench_tools(args)
    models = {t: args.models / f"{t}.narf" for t in tools if (args.models / f"{t}.narf").exists()}
    config = RenderBenchConfig(tools=tools, noise=args.noise, models=models, device=args.device)
    if args.quick:
        if not tools:
            raise ValueError(f"--quick: no models (*.narf) in {args.models}")
        missing = [str(args.models / f"{t}.narf") for t in tools if t not in models]
        if missing:
            raise ValueError(f"--quick evaluates bundled models only: no {', '.join(missing)}")
        config = config.quick_version()
    with sole_run(args.work):  # one run per --work: its data, models and results
        result = run(args.work, config)
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0


def _run_bench_estimate(args: argparse.Namespace) -> int:
    if args.shift:
        if args.noise:
            raise ValueError("--shift runs on restyled clean data; --noise (label noise) does not combine with it")
        argv = ["--device", args.device, "bench", "shift", "--work", str(args.work), "--models", str(args.models)]
        argv += ["--tools", *args.tools] if args.tools else []
        argv += ["--quick"] * args.quick + ["--json"] * args.json
        return _run_bench_shift(build_parser().parse_args(argv))
    from narf_benchmarks.checkpoint import sole_run
    from narf_benchmarks.estimate import main as bench_main

    with sole_run(args.work):  # one run per --work: its data, models, logs and results
        return bench_main(args)


def _run_bench_shift(args: argparse.Namespace) -> int:
    from narf_benchmarks.checkpoint import sole_run
    from narf_benchmarks.shift import main as bench_main

    with sole_run(args.work):
        return bench_main(args)


def _run_bench_distill(args: argparse.Namespace) -> int:
    from narf_benchmarks.distill import markdown, run
    from narf_core.bundle import load_bundle
    from narf_core.data.dataset import Dataset

    model, dataset = load_bundle(args.model), Dataset.open(args.dataset)
    result = run(model, dataset, out_dir=args.work / "distill", budgets_s=tuple(args.budgets),
                 composites=(0, args.composites))
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0


def _run_bench_track(args: argparse.Namespace) -> int:
    from narf_benchmarks.checkpoint import sole_run
    from narf_benchmarks.track import main as bench_main

    from narf_core.track import TrackInputError

    with sole_run(args.work):  # one run per --work: its sequences and result.json
        try:
            return bench_main(args)
        except TrackInputError as e:
            if not (e.field or "").startswith("options."):
                raise
            raise _flag_error(e, {"rays_per_iteration": "rays", "robust_scale": "huber"}) from None


def _run_bench_service(args: argparse.Namespace) -> int:
    from narf_benchmarks.service import markdown, run

    result = run(models_dir=args.models, clients=args.clients, requests=args.requests, duration_s=args.duration,
                 estimate_clients=args.estimate_clients)
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0


def _run_bench_viewer(args: argparse.Namespace) -> int:
    from narf_benchmarks.viewer import chromium_path, markdown, run

    if chromium_path() is None:
        raise ValueError("no chromium executable (apt-get install chromium, or set NARF_CHROMIUM)")
    result = run(args.models, drags=args.drags, size=tuple(args.size))
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0


def _run_bench_hostile(args: argparse.Namespace) -> int:
    from narf_benchmarks.service_hostile import markdown, run

    result = run(args.models, estimates=args.estimates, hostile_mb=args.hostile_mb, cancel_clients=args.cancel_clients)
    print(json.dumps(result, indent=1) if args.json else markdown(result))
    return 0


# ---------------------------------------------------------------------------------------------
# narf serve


def _add_serve(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "serve", help="serve the models of a folder over HTTP (/v1/render, /v1/estimate)",
        description="Start the FastAPI service (uvicorn) on loopback by default. Settings also come from "
                    "NARF_* environment variables (see the README).",
    )
    arg = parser.add_argument
    arg("--models", type=Path, default=None, metavar="DIR", help="folder of .narf bundles (default: ./models)")
    arg("--host", default="127.0.0.1")
    arg("--port", type=_non_negative_int, default=8000)
    arg("--token-file", type=Path, default=None, metavar="FILE",
        help="require the bearer token this file holds (default: NARF_TOKEN or NARF_TOKEN_FILE, else no auth)")
    arg("--token", default=None, help=argparse.SUPPRESS)  # refused: a secret on the command line shows in `ps`
    arg("--state-key-file", type=Path, default=None, metavar="FILE",
        help="key signing /v1/track state tokens, shared by every replica (default: NARF_STATE_KEY or "
             "NARF_STATE_KEY_FILE, else a random key per process)")
    parser.set_defaults(run=_run_serve)


def _run_serve(args: argparse.Namespace) -> int:
    from narf_service.main import serve

    if args.token is not None:
        raise ValueError("--token would show the secret to every user in `ps`; "
                         "set NARF_TOKEN or write it to a file for --token-file")
    extra = {} if args.state_key_file is None else {"state_key_file": args.state_key_file}
    serve(models_dir=args.models, host=args.host, port=args.port, token_file=args.token_file, device=args.device,
          **extra)
    return 0


if __name__ == "__main__":
    sys.exit(main())
