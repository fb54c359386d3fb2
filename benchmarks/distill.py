"""``narf bench distill``: stage 2 streamed against the paper's pool of composited views, per second.

The paper distils the part composition from 5000 composited images rendered once. ``narf train``
streams instead: every step renders fresh rays of fresh cameras and configurations. Both start
from the same part fields (a bundle's) and a fresh configuration field, and get the same wall-clock
budget, the pool's rendering included; the result is each variant's render error on the test and
novel splits (``narf`` mode) at a few points along the budget: error against training time.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path

from narf_core.bundle import NarfModel
from narf_core.data.dataset import Dataset
from narf_core.evaluate import evaluate_render
from narf_core.fields import make_field
from narf_core.fields.composed import ComposedField
from narf_core.train.pipeline import TrainConfig, distill


def run(
    model: NarfModel,
    dataset: Dataset,
    *,
    out_dir: Path,
    budgets_s: tuple[float, ...] = (60.0, 180.0),
    composites: tuple[int, ...] = (0, 5000),
    images: int = 12,
    progress: bool = True,
) -> dict:
    """Distil ``model``'s part fields for each budget and variant (``composites = 0``: streamed);
    writes ``distill.json`` and ``distill.md`` into ``out_dir``. Each budget is a fresh run."""
    if not model.has_parts:
        raise ValueError(f"model {model.name!r} has no part fields to distil from")
    out_dir.mkdir(parents=True, exist_ok=True)
    teacher = ComposedField(model.part_fields, model.part_grids, model.kinematics.part_poses)
    rows = []
    for n in composites:
        for budget in budgets_s:
            config = TrainConfig(composites=n, distill_steps=10**9)
            student = make_field(_distilled_config(model))
            with tempfile.TemporaryDirectory() as work:
                seconds = distill(
                    student, teacher, model.grid, model.aabb, model.lower, model.upper, config,
                    Path(work) / "distill.ckpt", budget, progress,
                )
            candidate = replace(model, field=student.eval().requires_grad_(False))
            row = {"composites": n, "budget_s": budget, "seconds": seconds}
            for split in ("test", "novel"):
                score = evaluate_render(candidate, dataset, split=split, limit=images)
                row[split] = {"mse": score.mse, "psnr": score.psnr, "n": score.n}
            rows.append(row)
    result = {"model": model.name, "rows": rows}
    (out_dir / "distill.json").write_text(json.dumps(result, indent=1))
    (out_dir / "distill.md").write_text(markdown(result))
    return result


def _distilled_config(model: NarfModel) -> dict:
    """The config of a fresh distilled field: the model's own, or for an articulated model the paper's
    K-planes field over its box and limits."""
    config = model.field.config()
    if config.get("arch") != "articulated":
        return config
    return {"arch": "kplanes", "aabb": config["aabb"], "theta_lower": config["theta_lower"], "theta_upper": config["theta_upper"]}


def markdown(result: dict) -> str:
    lines = [
        f"Stage 2 of `{result['model']}` from its part fields: streamed rays (composites 0) against a pool "
        "of composited views rendered first (the paper: 5000), same wall-clock budget.",
        "",
        "| composites | budget (s) | seconds spent | test PSNR (dB) | novel PSNR (dB) | novel MSE |",
        "|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['composites']} | {r['budget_s']:g} | {r['seconds']:.0f} | {r['test']['psnr']:.2f} "
            f"| {r['novel']['psnr']:.2f} | {r['novel']['mse']:.5f} |"
        )
    return "\n".join(lines) + "\n"
