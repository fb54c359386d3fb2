"""The optimisation loop every stage shares: steps under a time budget, progress, atomic checkpoints.

A stage is resumable: its checkpoint holds the module's weights, the optimiser's state, the step
reached, the seconds spent and the random state. Killing the process at any moment loses at most
the steps since the last checkpoint; a finished stage is never redone.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn
from tqdm import tqdm


@dataclass
class StageResult:
    """What a finished stage reports: steps run, seconds spent, the last loss."""

    steps: int
    seconds: float
    loss: float


def save_atomic(obj: dict, path: Path) -> None:
    """``torch.save`` to a temporary file in the same folder, then rename it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def run_stage(
    name: str,
    module: nn.Module,
    optimizer: torch.optim.Optimizer,
    step_fn: Callable[[int], float],
    *,
    steps: int,
    budget_s: float | None,
    checkpoint: Path,
    checkpoint_every_s: float = 20.0,
    on_step: Callable[[int], None] | None = None,
    progress: bool = True,
    generator: torch.Generator | None = None,
) -> StageResult:
    """Run ``step_fn(step) -> loss`` until ``steps`` are done or ``budget_s`` seconds are spent.

    Resumes from ``checkpoint`` if it exists. ``on_step(step)`` runs after each step (schedules,
    occupancy refresh). ``generator``, the stage's own random stream (batches), is checkpointed
    too, so a resumed stage draws the batches an uninterrupted one would have. Returns when done;
    the checkpoint then marks the stage finished.
    """
    start_step, spent, loss = 0, 0.0, float("nan")
    if checkpoint.exists():
        state = torch.load(checkpoint, weights_only=True)
        module.load_state_dict(state["module"])
        optimizer.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng"])
        if generator is not None and "generator" in state:
            generator.set_state(state["generator"])
        start_step, spent, loss = int(state["step"]), float(state["seconds"]), float(state["loss"])
        if state["finished"]:
            return StageResult(start_step, spent, loss)

    def save(step: int, finished: bool) -> None:
        save_atomic(
            {
                "module": module.state_dict(),
                "optimizer": optimizer.state_dict(),
                "rng": torch.get_rng_state(),
                **({"generator": generator.get_state()} if generator is not None else {}),
                "step": step,
                "seconds": spent,
                "loss": loss,
                "finished": finished,
            },
            checkpoint,
        )

    bar = tqdm(total=steps, initial=start_step, desc=name, disable=not progress, leave=False, dynamic_ncols=True)
    t_last_save = time.perf_counter()
    step = start_step
    module.train()
    while step < steps and (budget_s is None or spent < budget_s):
        t0 = time.perf_counter()
        loss = step_fn(step)
        step += 1
        if on_step is not None:
            on_step(step)
        spent += time.perf_counter() - t0
        bar.update(1)
        if step % 20 == 0:
            bar.set_postfix(loss=f"{loss:.2e}")
        if time.perf_counter() - t_last_save > checkpoint_every_s:
            save(step, finished=False)
            t_last_save = time.perf_counter()
    bar.close()
    module.eval()
    save(step, finished=True)
    return StageResult(step, spent, loss)
