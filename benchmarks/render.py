"""``narf bench render``: the paper's Table I on our data, with run time beside every error.

For each object (the four tools and the multi-joint objects), split (train / test / novel) and render
mode (``narf``, ``parts``): per-pixel MSE, PSNR, N and milliseconds per image, at the dataset size
(default 160x120) and at 640x480; per object the configuration field's speed-up over the composed
parts, its PSNR gap and the mode ``auto`` picks; a sweep of the ray-marching step (samples per ray)
plotted as error against run time; optionally the same on datasets with label noise. Missing
datasets are synthesised and missing models trained into the work folder, so the full run is one
command; ``--quick`` uses the bundled demo models only.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

from narf_core.bundle import NarfModel, load_bundle
from narf_core.data.dataset import Dataset
from narf_core.evaluate import evaluate_render
from narf_core.modes import choose_mode

SPLITS = ("train", "test", "novel")
PAPER_MSE = {  # Table I of the paper (real data)
    "clamp": {"test": 0.03343, "train": 0.03234, "novel": 0.13245},
    "lineman-a": {"test": 0.02991, "train": 0.02941, "novel": 0.10136},
    "lineman-b": {"test": 0.06348, "train": 0.06318, "novel": 0.12500},
    "longnose": {"test": 0.08045, "train": 0.07900, "novel": 0.10241},
}


def all_tools() -> tuple[str, ...]:
    """Every procedural object ``narf synth --tool`` knows (the 1-DoF tools and the multi-joint objects)."""
    from narf_core.data.synth.tools import TOOLS

    return TOOLS


@dataclass
class RenderBenchConfig:
    tools: tuple[str, ...] = field(default_factory=all_tools)
    splits: tuple[str, ...] = SPLITS
    modes: tuple[str, ...] = ("narf", "parts")
    sizes: tuple[tuple[int, int], ...] = ((160, 120), (640, 480))
    noise: bool = False
    images_per_split: int | None = None
    step_sweep: tuple[float, ...] = (64, 128, 256, 512)
    views: int = 200
    train_budget_s: float | None = None
    quick: bool = False
    models: dict[str, Path] = field(default_factory=dict)
    device: str = "cpu"  # where the models are loaded and render

    def quick_version(self) -> RenderBenchConfig:
        """The reduced run of ``--quick``: the given (bundled) models only, never training, at the
        dataset size only, on 4 images of the test and novel splits of 24-view datasets, with a
        3-step marching sweep."""
        if self.noise:
            raise ValueError("the quick run evaluates the bundled models, trained without label noise: leave out --noise")
        return replace(
            self, sizes=self.sizes[:1], splits=("test", "novel"), images_per_split=4, step_sweep=(64, 128, 256),
            views=24, quick=True,
        )


def _dataset(work: Path, tool: str, size: tuple[int, int], views: int, noise: bool) -> Dataset:
    from narf_core.data.synth.generate import NoiseOptions, synthesize

    name = f"{tool}-{size[0]}x{size[1]}{'-noise' if noise else ''}"
    root = work / "data" / name
    if not (root / "scene.json").exists():
        synthesize(tool, root, size=size, views=views, seed=0, noise=NoiseOptions.preset("paper") if noise else None)
    return Dataset.open(root)


def _model(work: Path, tool: str, dataset: Dataset, config: RenderBenchConfig, noise: bool) -> NarfModel:
    from narf_core.train.pipeline import TrainConfig, train

    if tool in config.models and not noise:
        return load_bundle(config.models[tool], config.device)
    if config.quick:
        raise ValueError(f"the quick run trains nothing, and no model was given for {tool!r}")
    path = work / "models" / f"{tool}{'-noise' if noise else ''}.narf"
    if not path.exists():
        train(dataset.root, path, TrainConfig(budget_s=config.train_budget_s), command="narf bench render", progress=True)
    return load_bundle(path, config.device)


def step_sweep(model: NarfModel, dataset: Dataset, divisions: tuple[float, ...], limit: int) -> list[dict]:
    """Error and time for several marching steps (aabb diagonal / division): error against run time."""
    diagonal = float((model.aabb[1] - model.aabb[0]).norm())
    base = model.step
    rows = []
    try:
        for div in divisions:
            model.step = diagonal / div
            score = evaluate_render(model, dataset, split="test", limit=limit)
            rows.append({"samples_per_diagonal": div, "mse": score.mse, "psnr": score.psnr, "ms_per_image": score.ms_per_image})
    finally:
        model.step = base
    return rows


def run(work: Path, config: RenderBenchConfig) -> dict:
    """Run the benchmark; writes ``render.json``, ``render.md`` and ``render_error_vs_time.png`` in ``work``."""
    work.mkdir(parents=True, exist_ok=True)
    rows, sweeps, auto = [], {}, {}
    for noise in (False, True) if config.noise else (False,):
        for tool in config.tools:
            for size in config.sizes:
                dataset = _dataset(work, tool, size, config.views, noise)
                model = _model(work, tool, _dataset(work, tool, config.sizes[0], config.views, noise), config, noise)
                auto[f"{tool}{' (noise)' if noise else ''}"] = dict(zip(("mode", "reason"), choose_mode(model)))
                for mode in config.modes if model.has_parts else ("narf",):
                    for split in config.splits:
                        score = evaluate_render(
                            model, dataset, split=split, mode=mode, limit=config.images_per_split, progress=True
                        )
                        rows.append({"tool": tool, "noise": noise, **score.summary(), "paper_mse": PAPER_MSE.get(tool, {}).get(split)})
                if size == config.sizes[0]:
                    sweeps[f"{tool}{' (noise)' if noise else ''}"] = step_sweep(model, dataset, config.step_sweep, limit=config.images_per_split or 8)
    result = {"rows": rows, "modes": mode_summary(rows), "auto": auto, "step_sweep": sweeps}
    (work / "render.json").write_text(json.dumps(result, indent=1))
    (work / "render.md").write_text(markdown(result))
    plot(sweeps, work / "render_error_vs_time.png")
    return result


def mode_summary(rows: list[dict]) -> list[dict]:
    """Per tool, noise and size where both modes ran: each mode's mean ms per image over the splits,
    ``speedup`` (parts' time over narf's) and ``psnr_gap_db`` (narf's PSNR minus parts', per split)."""
    groups: dict[tuple, dict[str, dict[str, dict]]] = {}
    for r in rows:
        groups.setdefault((r["tool"], r["noise"], r["width"], r["height"]), {}).setdefault(r["mode"], {})[r["split"]] = r
    out = []
    for (tool, noise, width, height), modes in groups.items():
        if set(modes) != {"narf", "parts"}:
            continue
        ms = {m: sum(r["ms_per_image"] for r in by_split.values()) / len(by_split) for m, by_split in modes.items()}
        gap = {split: modes["narf"][split]["psnr"] - r["psnr"] for split, r in modes["parts"].items() if split in modes["narf"]}
        out.append({"tool": tool, "noise": noise, "width": width, "height": height, "narf_ms": ms["narf"],
                    "parts_ms": ms["parts"], "speedup": ms["parts"] / ms["narf"], "psnr_gap_db": gap})
    return out


def markdown(result: dict) -> str:
    """Table I's shape: tool, split, then MSE, PSNR, N and ms per image for each mode and size; then
    per object the configuration field's speed-up over the composed parts, its PSNR gap per split
    and the mode ``auto`` picks from the bundle's measurement."""
    lines = [
        "| tool | noise | split | mode | size | MSE | PSNR (dB) | N | ms/image | paper MSE |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        paper = f"{r['paper_mse']:.5f}" if r["paper_mse"] is not None else "-"
        lines.append(
            f"| {r['tool']} | {'yes' if r['noise'] else 'no'} | {r['split']} | {r['mode']} | {r['width']}x{r['height']} "
            f"| {r['mse']:.5f} | {r['psnr']:.2f} | {r['n']} | {r['ms_per_image']:.1f} | {paper} |"
        )
    lines += ["", "Configuration field (narf) against composed parts, per object and size; `auto`: the bundle's choice "
              "(narf_core/modes.py):", "",
              "| tool | noise | size | narf ms/image | parts ms/image | narf speed-up | narf − parts PSNR (dB) | auto |",
              "|---|---|---|---|---|---|---|---|"]
    for m in result.get("modes", []):
        gap = ", ".join(f"{split} {g:+.2f}" for split, g in m["psnr_gap_db"].items())
        pick = result.get("auto", {}).get(f"{m['tool']}{' (noise)' if m['noise'] else ''}", {}).get("mode", "-")
        lines.append(f"| {m['tool']} | {'yes' if m['noise'] else 'no'} | {m['width']}x{m['height']} | {m['narf_ms']:.1f} "
                     f"| {m['parts_ms']:.1f} | {m['speedup']:.2f}x | {gap} | {pick} |")
    for name, a in result.get("auto", {}).items():
        lines.append(f"\n`auto` renders {name} in {a['mode']} mode: {a['reason']}.")
    lines += ["", "Error against run time (test split, marching step = box diagonal / samples):", "",
              "| model | samples per diagonal | MSE | PSNR (dB) | ms/image |", "|---|---|---|---|---|"]
    for name, sweep in result["step_sweep"].items():
        for s in sweep:
            lines.append(f"| {name} | {s['samples_per_diagonal']:.0f} | {s['mse']:.5f} | {s['psnr']:.2f} | {s['ms_per_image']:.1f} |")
    return "\n".join(lines) + "\n"


def plot(sweeps: dict[str, list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, sweep in sweeps.items():
        ax.plot([s["ms_per_image"] for s in sweep], [s["psnr"] for s in sweep], "o-", label=name)
        for s in sweep:
            ax.annotate(f"{s['samples_per_diagonal']:.0f}", (s["ms_per_image"], s["psnr"]), fontsize=7)
    ax.set_xlabel("ms per image (CPU)")
    ax.set_ylabel("PSNR, test split (dB)")
    ax.set_title("Render error against run time (marching step sweep)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
