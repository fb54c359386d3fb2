"""The configuration fields side by side on one trained bundle: the bundle's own field, the composed
parts, and the articulated field built from those parts (issue #11).

``python -m narf_benchmarks.fields MODEL.narf DATASET [--images N] [--reps R]`` renders the first N
test and novel frames in each variant, interleaved R times (a shared machine drifts), and prints
PSNR with the median milliseconds per image: process CPU time (one thread, so it is the work done
whatever the load) and wall time, the best of the R passes. A bundle whose field is already
articulated is compared with its parts only (``narf`` and ``articulated`` are then the same field).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from narf_core.bundle import NarfModel, load_bundle
from narf_core.data.dataset import Dataset
from narf_core.fields import ArticulatedField
from narf_core.metrics import psnr_from_mse


def variants(model: NarfModel) -> dict[str, tuple[NarfModel, str]]:
    """``{name: (model, render mode)}``: ``narf`` (the bundle's field), ``parts``, ``articulated``."""
    if not model.has_parts:
        raise ValueError(f"model {model.name!r} has no part fields to compare with")
    out = {"parts": (model, "parts")}
    if model.field.config().get("arch") == "articulated":
        out["articulated"] = (model, "narf")
    else:
        field = ArticulatedField.from_parts(model.kinematics, model.part_fields, model.part_grids, model.aabb)
        out = {"narf": (model, "narf"), **out, "articulated": (replace(model, field=field.eval().requires_grad_(False)), "narf")}
    return out


def run(model: NarfModel, dataset: Dataset, *, images: int = 8, reps: int = 3) -> list[dict]:
    """One row per split and variant: ``psnr``, ``mse``, ``n``, ``cpu_ms`` and ``wall_ms`` per image."""
    torch.set_num_threads(1)
    candidates = variants(model)
    rows = []
    for split in ("test", "novel"):
        frames = dataset.frames(split)[:images]
        data = [(torch.as_tensor(f.T_cam_obj, dtype=torch.float32), model.joint_vector(f.joints), dataset.load(f)) for f in frames]
        best: dict[str, dict] = {}
        for _ in range(reps):
            for name, (candidate, mode) in candidates.items():
                errors, cpu, wall = [], [], []
                for T, theta, images_ in data:
                    c0, w0 = time.process_time(), time.perf_counter()
                    rgb = candidate.render(T, theta, dataset.camera, mode=mode)["rgb"].numpy()
                    cpu.append(time.process_time() - c0)
                    wall.append(time.perf_counter() - w0)
                    target = images_.rgb.astype(np.float32) / 255 * (images_.labels > 0)[..., None]
                    errors.append(float(((rgb - target) ** 2).mean()))
                row = best.setdefault(name, {"split": split, "variant": name, "n": len(data), "cpu_ms": np.inf, "wall_ms": np.inf})
                row["mse"] = float(np.mean(errors))
                row["psnr"] = float(psnr_from_mse(row["mse"]))
                row["cpu_ms"] = min(row["cpu_ms"], 1000 * float(np.median(cpu)))
                row["wall_ms"] = min(row["wall_ms"], 1000 * float(np.median(wall)))
        rows += best.values()
    return rows


def markdown(rows: list[dict], width: int, height: int) -> str:
    lines = [f"| split | field | PSNR (dB) | MSE | N | CPU ms / image | wall ms / image ({width}x{height}) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['split']} | {r['variant']} | {r['psnr']:.2f} | {r['mse']:.5f} | {r['n']} | {r['cpu_ms']:.1f} | {r['wall_ms']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m narf_benchmarks.fields", description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path, metavar="MODEL.narf")
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--images", type=int, default=8, help="first N frames of each split (default: %(default)s)")
    parser.add_argument("--reps", type=int, default=3, help="interleaved passes, best kept (default: %(default)s)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.images < 1 or args.reps < 1:
        parser.error("--images and --reps must be >= 1")
    dataset = Dataset.open(args.dataset)
    rows = run(load_bundle(args.model), dataset, images=args.images, reps=args.reps)
    print(json.dumps(rows, indent=1) if args.json else markdown(rows, dataset.camera.width, dataset.camera.height), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
