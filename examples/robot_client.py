"""What a robot does with the NARF service: look at an object, then estimate its pose and joints.

    python examples/robot_client.py --url http://127.0.0.1:8000 [--model clamp] [--size 160 120]

Renders a view of the model at a known pose and configuration (standing in for a camera's RGB-D
image and its segmentation mask), perturbs the pose by 10 degrees and 2 cm (the paper's protocol),
asks the service to estimate pose and joints from the view (the ``auto`` preset unless ``--preset``
names another: Gauss-Newton with the depth image, ``robust`` with ``--no-depth``), and prints the ADD,
the joint errors and the time.
Needs only the client package (httpx, numpy, pillow): ``pip install -e clients/python``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np
from narf_client import NarfClient, NarfError, Pose


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: the rotation by ``angle`` radians about the unit ``axis``."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def perturb(T: np.ndarray, degrees: float, metres: float, rng: np.random.Generator) -> np.ndarray:
    """``T`` turned by ``degrees`` about a random axis and moved ``metres`` in a random direction."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    out = T.copy()
    out[:3, :3] = rotation(axis / np.linalg.norm(axis), math.radians(degrees)) @ T[:3, :3]
    out[:3, 3] += metres * shift / np.linalg.norm(shift)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000")
    parser.add_argument(
        "--token", default=os.environ.get("NARF_TOKEN") or None, help="bearer token if required (default: $NARF_TOKEN)"
    )
    parser.add_argument("--model", default=None, help="default: the first served model")
    parser.add_argument("--size", type=int, nargs=2, default=(160, 120), metavar=("W", "H"))
    parser.add_argument("--iterations", type=int, default=None, help="default: the preset's")
    parser.add_argument("--preset", choices=("auto", "gauss-newton", "robust", "paper"), default="auto",
                        help="the refiner's options (default: auto, which the server resolves per view)")
    parser.add_argument("--no-depth", action="store_true", help="estimate from RGB alone")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the server to be ready")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    width, height = args.size

    with NarfClient(args.url, args.token) as narf:
        deadline = time.monotonic() + args.wait
        while not narf.ready():
            if time.monotonic() > deadline:
                print(f"error: {args.url} is not ready after {args.wait} s", file=sys.stderr)
                return 1
            time.sleep(1.0)
        try:
            model = narf.model(args.model or narf.models()[0].name)
            # A camera like a Primesense at this size, looking at the object from about 3 diameters.
            f = 536.5 * width / 640
            K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
            centre = model.bounds.mean(axis=0)
            diameter = float(np.linalg.norm(model.bounds[1] - model.bounds[0]))
            T_true = np.eye(4)
            T_true[:3, :3] = rotation(np.array([1.0, 0.0, 0.0]), -0.5)
            T_true[:3, 3] = [0, 0, 2 * diameter * f / min(width, height)] - T_true[:3, :3] @ centre
            joints_true = {j.name: float(rng.uniform(j.lower, j.upper)) for j in model.joints}

            view = narf.render(model.name, T_true, K, width, height, joints=joints_true, outputs=("rgb", "depth", "opacity"))
            T_init = perturb(T_true, 10.0, 0.02, rng)
            start = time.perf_counter()
            est = narf.estimate(
                view.rgb,
                view.opacity > 0.5,
                K,
                Pose(T_init),
                model=model.name,
                initial_joints=model.mid_joints,
                depth=None if args.no_depth else view.depth,
                iterations=args.iterations,
                options={"preset": args.preset},
                ground_truth=(T_true, joints_true),
            )
            elapsed = time.perf_counter() - start
        except NarfError as e:
            print(f"error: {e}", file=sys.stderr)
            return 1

    metrics = est.metrics or {}
    if args.json:
        print(json.dumps({
            "model": model.name, "status": est.status, "iterations": est.iterations, "loss": est.loss,
            "joints_true": joints_true, "joints": est.joints, "metrics": metrics,
            "seconds": est.seconds, "round_trip_seconds": elapsed, "preset": est.preset,
        }))
        return 0

    def show(key: str, scale: float, unit: str) -> str:
        value = metrics.get(key)
        return "n/a" if value is None else f"{value * scale:.2f} {unit}"

    print(f"model {model.name}: {len(model.links)} links, joints {', '.join(j.name for j in model.joints) or 'none'}")
    print(f"status {est.status} after {est.iterations} iterations ({est.preset}: {est.preset_reason}), final loss {est.loss}")
    print(f"ADD {show('add', 100, 'cm')} (started 10 deg and 2 cm off)")
    for j in model.joints:
        revolute = j.type == "revolute"
        print(f"joint {j.name}: error {show(f'joint_error/{j.name}', 180 / math.pi if revolute else 1000, 'deg' if revolute else 'mm')}")
    print(f"time: {est.seconds:.2f} s refining, {elapsed:.2f} s round trip")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
