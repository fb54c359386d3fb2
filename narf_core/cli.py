"""The ``narf`` command (DESIGN §7).

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
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import narf_core

EXIT_ERROR = 2  # bad input, as argparse uses for bad arguments
EXIT_INTERRUPTED = 130
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError)
NOISE_PRESETS = ("none", "paper")  # generate.NOISE_PRESETS, named here so that --help imports no pybullet


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``narf`` with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
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
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_synth,):
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


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{value} is not a positive integer")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is negative")
    return value


def _non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number >= 0")
    return value


def _folder_size(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


# ---------------------------------------------------------------------------------------------
# narf synth


def _add_synth(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "synth",
        help="render a synthetic dataset of a tool or any URDF with pybullet",
        description=(
            "Render a dataset (DESIGN §3) of a procedural tool or a URDF with pybullet's CPU renderer: "
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
    arg("--tool", required=True, metavar="NAME|PATH.urdf", help="clamp, lineman-a, lineman-b, longnose or a URDF")
    arg("--out", required=True, type=Path, metavar="DIR", help="dataset folder to create (new or empty)")
    arg("--size", nargs=2, type=_positive_int, default=(160, 120), metavar=("W", "H"), help="default: 160 120")
    arg("--views", type=_positive_int, default=200, metavar="N", help="train images (default: %(default)s); "
        "test and novel get max(17, N // 4) each")
    arg("--seed", type=_non_negative_int, default=0, help="random seed (default: %(default)s)")
    arg("--background", action="store_true", help="render a textured table under the object (background)")
    arg("--overwrite", action="store_true", help="replace the dataset already in --out")
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
    out = synthesize(
        args.tool,
        args.out,
        size=tuple(args.size),
        views=args.views,
        seed=args.seed,
        noise=noise if noise.active else None,
        background=args.background,
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


def _synth_summary(r: dict[str, Any]) -> str:
    frames = r["frames"]
    return (
        f"wrote {sum(frames.values())} frames (train {frames['train']}, test {frames['test']}, "
        f"novel {frames['novel']}) of {r['tool']} at {r['size'][0]}x{r['size'][1]} to {r['dataset']} "
        f"in {r['seconds']:.1f} s ({r['bytes'] / 1e6:.1f} MB)"
    )


if __name__ == "__main__":
    sys.exit(main())
