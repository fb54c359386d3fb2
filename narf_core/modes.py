"""Which render mode serves a model: the measurement training records, and the rule ``auto`` follows.

A model renders in one of :data:`RENDER_MODES`: ``narf`` (the configuration field F(x, d, θ)) or
``parts`` (the part fields composed through the URDF's forward kinematics; only in bundles that
keep them). Which one is better depends on the object: the configuration field is the faster one
on the paper's 1-DoF tools, but need not be on every object. So training measures both on the
held-out views (:func:`measure_modes`) and records the figures in the bundle's metadata under
:data:`RECORD_KEY`; every place that takes a mode (the refiner, the tracker, the renderer, the CLI,
the API) also takes ``auto`` (the default) and resolves it with :func:`choose_mode`, which says
which mode it chose and why.

The rule of ``auto``, in this order:
  1. a bundle without part fields renders ``narf`` (the only mode it has);
  2. a bundle without a (readable) measurement renders ``narf``, the paper's choice;
  3. otherwise the faster mode (fewer ms per image: each split's median, averaged), unless its
     PSNR is more than :data:`PSNR_TOLERANCE_DB` below the other mode's on any measured split:
     then the other one. Where the configuration field is no faster than the composed parts,
     ``auto`` therefore picks ``parts``, and its reason says so.

Record (JSON, in the bundle's metadata; the tensor checksum does not cover it)::

    {"width": W, "height": H, "views": n, "threads": 1, "seconds": s (the measurement's),
     "splits": {"test": {"narf": {"psnr": dB, "mse": m, "ms_per_image": ms}, "parts": {...}}, "novel": {...}}}
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from narf_core.checks import InputError
from narf_core.threads import torch_threads

if TYPE_CHECKING:
    from narf_core.bundle import NarfModel
    from narf_core.data.dataset import Dataset

RENDER_MODES = ("narf", "parts")
MODES = ("auto", *RENDER_MODES)
RECORD_KEY = "mode_measurement"
PSNR_TOLERANCE_DB = 1.0  # the faster mode may be this much worse (PSNR, any measured split) and still be chosen
HELD_OUT_SPLITS = ("test", "novel")
MEASURE_VIEWS = 8  # views per split; the time is their median, after one warm-up render


def choose_mode(
    model: Any, requested: str = "auto", *, field: str = "options.mode", error: type[InputError] = InputError
) -> tuple[str, str]:
    """``(mode, reason)``: the render mode ``requested`` (one of :data:`MODES`) comes to for ``model``.

    ``model`` needs ``name``, ``has_parts`` and ``metadata`` (a :class:`~narf_core.bundle.NarfModel`).
    Raises ``error`` naming ``field`` for a mode that is not one of :data:`MODES`, or ``parts`` on
    a model without part fields.
    """
    if requested not in MODES:
        reason = f"must be one of {', '.join(MODES)}, got {requested!r}"
        raise error(f"{field} {reason}", field, reason)
    if requested == "parts" and not model.has_parts:
        reason = (f"'parts' needs part fields, which model {model.name!r} lacks (trained with --no-parts); "
                  "use 'narf' or 'auto'")
        raise error(f"{field} {reason}", field, reason)
    if requested != "auto":
        return requested, "requested"
    if not model.has_parts:
        return "narf", "the model has no part fields, so the configuration field"
    figures = _figures(model.metadata.get(RECORD_KEY))
    if figures is None:
        why = "no mode measurement" if model.metadata.get(RECORD_KEY) is None else "an unreadable mode measurement"
        return "narf", (f"{why} in the bundle, so the configuration field (the paper's choice; "
                        "`narf eval --record-modes` adds one)")
    return _rule(figures, model.metadata[RECORD_KEY])


def measure_modes(
    model: NarfModel,
    dataset: Dataset,
    *,
    splits: Sequence[str] = HELD_OUT_SPLITS,
    views: int = MEASURE_VIEWS,
    progress: bool = False,
) -> dict | None:
    """The record of :data:`RECORD_KEY` (see the module docstring): PSNR, MSE and median ms per image
    of every mode ``model`` has, on the first ``views`` frames (or all, if fewer) of each of
    ``splits`` the dataset has, rendered at the dataset's size on one thread (on the CPU, timed in that
    thread's CPU time, which other processes on the cores do not inflate: the choice is the model's,
    not the load of the machine it was trained on; docs/benchmarks.md, session 33). ``None`` when no
    split has frames."""
    import time

    import torch

    from narf_core.evaluate import evaluate_render

    started = time.perf_counter()
    present = [s for s in splits if dataset.frames(s)]
    if not present:
        return None
    modes = RENDER_MODES if model.has_parts else ("narf",)
    with torch_threads(1):  # the figure a user compares: not the share of a shared machine's cores
        first = dataset.frames(present[0])[0]
        T = torch.as_tensor(first.T_cam_obj, dtype=torch.float32)
        for mode in modes:  # warm-up: allocations and the first-call costs stay out of the times
            model.render(T, model.joint_vector(first.joints), dataset.camera, mode=mode)
        record: dict[str, Any] = {"width": dataset.camera.width, "height": dataset.camera.height,
                                  "views": min(views, *(len(dataset.frames(s)) for s in present)), "threads": 1,
                                  "splits": {}}
        for split in present:
            record["splits"][split] = {}
            for mode in modes:
                score = evaluate_render(model, dataset, split=split, mode=mode, limit=views, progress=progress,
                                        cpu_time=True)
                record["splits"][split][mode] = {"psnr": _finite(score.psnr), "mse": score.mse,
                                                 "ms_per_image": score.ms_per_image}
    record["seconds"] = time.perf_counter() - started  # the measurement's own cost, warm-up included
    return record


def describe_record(record: Any) -> list[str]:
    """One line per measured split: each mode's PSNR and ms per image (for the CLI); ``[]`` for a
    missing or unreadable record."""
    try:
        return [f"{split}: " + "; ".join(f"{mode} {float(f['psnr']):.2f} dB, {float(f['ms_per_image']):.1f} ms/image"
                                          for mode, f in modes.items())
                for split, modes in record["splits"].items()]
    except (TypeError, KeyError, ValueError, AttributeError):
        return []


def _finite(psnr: float) -> float:
    """PSNR as a JSON-safe number: a perfect render (infinite PSNR) is capped at 100 dB."""
    return psnr if math.isfinite(psnr) else 100.0


def _figures(record: Any) -> dict[str, dict[str, dict[str, float]]] | None:
    """``{split: {mode: {psnr, mse, ms_per_image}}}`` of a record holding both render modes on every
    split, with finite positive times and finite PSNRs; ``None`` for anything else."""
    if not isinstance(record, Mapping) or not isinstance(record.get("splits"), Mapping) or not record["splits"]:
        return None
    out = {}
    for split, modes in record["splits"].items():
        if not isinstance(modes, Mapping) or set(modes) != set(RENDER_MODES):
            return None
        out[str(split)] = {}
        for mode in RENDER_MODES:
            f = modes[mode]
            try:
                psnr, mse, ms = float(f["psnr"]), float(f["mse"]), float(f["ms_per_image"])
            except (TypeError, KeyError, ValueError):
                return None
            if not (math.isfinite(psnr) and math.isfinite(mse) and math.isfinite(ms) and ms > 0):
                return None
            out[str(split)][mode] = {"psnr": psnr, "mse": mse, "ms_per_image": ms}
    return out


def _rule(figures: dict[str, dict[str, dict[str, float]]], record: Mapping) -> tuple[str, str]:
    """The third step of the module docstring's rule on a well-formed record."""
    ms = {mode: sum(s[mode]["ms_per_image"] for s in figures.values()) / len(figures) for mode in RENDER_MODES}
    fast = "narf" if ms["narf"] <= ms["parts"] else "parts"
    slow = "parts" if fast == "narf" else "narf"
    drops = {split: s[slow]["psnr"] - s[fast]["psnr"] for split, s in figures.items()}
    split, drop = max(drops.items(), key=lambda kv: kv[1])
    where = f"{record.get('width')}x{record.get('height')}, one thread"
    speed = f"{ms['narf']:.1f} ms per image against {ms['parts']:.1f} for parts ({where})"
    if drop > PSNR_TOLERANCE_DB:
        return slow, (f"{fast} is faster but {drop:.2f} dB worse than {slow} on the {split} views "
                      f"(more than {PSNR_TOLERANCE_DB:g} dB); narf {speed}")
    if fast == "parts":
        return "parts", f"the configuration field is no faster than the composed parts: narf {speed}"
    within = f"PSNR within {PSNR_TOLERANCE_DB:g} dB of parts on every measured split"
    return "narf", f"the configuration field is faster, narf {speed}, and its {within}"
