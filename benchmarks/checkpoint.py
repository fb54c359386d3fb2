"""Scene logs: a long benchmark run stopped part-way resumes where it stopped.

``narf bench estimate`` and ``narf bench shift`` refine hundreds of scenes (an hour and more on two
cores); their tables are written once at the end. Each block of scenes (a tool, split, condition,
input, preset and scale) appends every finished scene's row to its own JSON-lines file under
``<out>/scenes/`` as it finishes; the same command run again reads the rows back instead of refining
those scenes again, and the logs are removed once the run's results are written.

A log's first line is its block's key: the refiner's options, the perturbation, the seed, the
model's weights (the bundle's tensor checksum), the dataset, and a digest of the code that
computes the rows (``narf_core`` and ``benchmarks``). A log under another key (other options, a
retrained model, an edited refiner) is started again, so a resumed table never mixes rows of two
different runs. A reused row keeps the seconds measured when it was refined.

One run at a time per ``--work`` folder (:func:`sole_run`): a second one started there would find its
logs removed by the first when that finishes, and the two would write over each other's data and results.
"""

from __future__ import annotations

import hashlib
import json
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any

FOLDER = "scenes"


@lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 (hex) over the source files that compute a scene's row (``narf_core`` and
    ``benchmarks``), in path order: any edit starts the logs again."""
    import narf_core

    digest = hashlib.sha256()
    for package in (Path(narf_core.__file__).resolve().parent, Path(__file__).resolve().parent):
        for path in sorted(package.rglob("*.py")):
            digest.update(f"{package.name}/{path.relative_to(package)}".encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def model_digest(model: Any) -> str | None:
    """The bundle's tensor checksum (verified when it was loaded), or ``None`` for a model never saved."""
    checksum = (getattr(model, "metadata", None) or {}).get("checksum") or {}
    return checksum.get("tensors")


class SceneLog:
    """The finished rows of one block of scenes, keyed by frame id, kept in ``path`` (JSON lines).

    ``key`` (JSON-able) identifies the block; a file under another key, or one that cannot be read,
    is started again."""

    def __init__(self, path: Path, key: Mapping[str, Any]) -> None:
        self.path = Path(path)
        self.key = json.loads(json.dumps(dict(key), sort_keys=True, default=str))
        self.rows: dict[int, dict] = self._read()
        self.resumed = len(self.rows)
        # written again whole: the key, and only the rows read back (not a line the stop cut short)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text("".join(json.dumps(x) + "\n" for x in ({"key": self.key}, *self.rows.values())))

    def _read(self) -> dict[int, dict]:
        try:
            lines = self.path.read_text().splitlines()
        except OSError:
            return {}
        rows: dict[int, dict] = {}
        try:
            if not lines or json.loads(lines[0]).get("key") != self.key:
                return {}
            for line in lines[1:]:
                row = json.loads(line)
                rows[int(row["frame"])] = row
        except (ValueError, KeyError, TypeError, AttributeError):
            pass  # a line cut short by the stop: the rows before it stand
        return rows

    def get(self, frame_id: int) -> dict | None:
        return self.rows.get(int(frame_id))

    def add(self, row: dict) -> dict:
        """Keep a finished scene's row (written and flushed before the next scene starts); returns it as
        the log reads it back (JSON types), so fresh and resumed rows are alike."""
        text = json.dumps(row)
        row = json.loads(text)
        self.rows[int(row["frame"])] = row
        with self.path.open("a") as f:
            f.write(text + "\n")
            f.flush()
        return row

    def note(self, total: int) -> None:
        """One line on stderr where rows were read back, so a resumed run says so (the key holds the block's
        frames, so they are some of its ``total``)."""
        if self.resumed:
            print(f"narf bench: resuming {self.path.name}: {self.resumed} of {total} scenes from "
                  f"{self.path}", file=sys.stderr)


def scene_log(out_dir: Path, tool: str, block: str, key: Mapping[str, Any], model: Any) -> SceneLog | None:
    """The log of ``block`` (a file name: split, condition, preset, ...) of ``tool`` under
    ``out_dir/scenes``; its key adds the model's and the code's digests to ``key``. ``None`` for a model
    without a checksum (never saved: a later run could not tell it from a retrained one)."""
    digest = model_digest(model)
    if digest is None:
        return None
    full = {**key, "tool": tool, "model": digest, "code": code_digest()}
    return SceneLog(Path(out_dir) / FOLDER / tool / f"{block}.jsonl", full)


def remove_logs(out_dir: Path) -> None:
    """Remove the scene logs of a finished run (its results are written)."""
    import shutil

    shutil.rmtree(Path(out_dir) / FOLDER, ignore_errors=True)


@contextmanager
def sole_run(work: Path) -> Iterator[None]:
    """Hold the benchmarks' lock on the folder ``work`` (``fcntl.flock`` on ``work/.lock``) for the block;
    where another process holds it, a ``ValueError`` naming the folder at once, before any work. The lock
    goes with the process that holds it: a run stopped or killed never leaves it behind."""
    import fcntl

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    with (work / ".lock").open("a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"--work {work}: another narf benchmark is running on this folder (the two runs' data, "
                             "scene logs and results would collide); wait for it to finish or give another --work") from None
        yield
