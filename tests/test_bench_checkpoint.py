"""Scene logs (benchmarks/checkpoint.py): a benchmark stopped part-way resumes where it stopped, and never
mixes in rows of another run."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from narf_benchmarks import estimate as bench_estimate
from narf_benchmarks.checkpoint import FOLDER, SceneLog, code_digest, scene_log, sole_run
from narf_core.data.dataset import DatasetWriter, FrameImages, read_urdf
from tests.test_estimate import ASSETS, CAMERA, TRUTH, SliderField, make_model, observe, view

EYES = ((0.08, -0.15, 0.18), (0.12, -0.13, 0.16), (0.05, -0.17, 0.2))


@pytest.fixture
def model():
    return make_model(SliderField(), ASSETS)


@pytest.fixture
def saved(model):
    """The toy model as if loaded from a bundle: its tensors' checksum in the metadata."""
    model.metadata = {**(model.metadata or {}), "checksum": {"algorithm": "sha256", "tensors": "toy-weights"}}
    return model


def _toy_set(model, root):
    with DatasetWriter(root, read_urdf(ASSETS / "estimate_slider.urdf"), CAMERA) as writer:
        for eye in EYES:
            T = view(eye)
            image, mask, _ = observe(model, T, TRUTH)
            writer.add("test", FrameImages(image, None, mask.astype(np.uint8)), T, TRUTH)
    return root


def _counting(monkeypatch, stop_at: int | None = None) -> list[int]:
    """Count the benchmark's refinements; raise KeyboardInterrupt at the ``stop_at``-th (a user's Ctrl-C)."""
    calls, real = [], bench_estimate.refine

    def refine(*args, **kwargs):
        calls.append(1)
        if stop_at is not None and len(calls) == stop_at:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(bench_estimate, "refine", refine)
    return calls


def test_a_stopped_bench_estimate_resumes_where_it_stopped(saved, tmp_path, monkeypatch):
    root, out = _toy_set(saved, tmp_path / "toy"), tmp_path / "out"
    kwargs = dict(out_dir=out, splits=("test",), scenes=3, iterations=2, modes=("narf",), presets=("paper",),
                  scale_sweep=(1.0,), progress=False)
    _counting(monkeypatch, stop_at=3)
    with pytest.raises(KeyboardInterrupt):
        bench_estimate.run({"toy": saved}, {"toy": root}, **kwargs)
    (log,) = (out / FOLDER / "toy").glob("*.jsonl")
    lines = log.read_text().splitlines()
    assert json.loads(lines[0])["key"]["code"] == code_digest() and len(lines) == 3  # the key, two finished scenes
    done = [json.loads(line) for line in lines[1:]]

    calls = _counting(monkeypatch)
    result = bench_estimate.run({"toy": saved}, {"toy": root}, **kwargs)
    assert len(calls) == 1  # only the scene the stop interrupted
    (row,) = result["table"]
    assert row["scenes"] == 3
    assert row["scenes_detail"][:2] == done  # read back, not refined again
    assert not (out / FOLDER).exists()  # the results are written: the logs are gone
    assert (out / "estimate.json").exists()

    calls = _counting(monkeypatch)
    bench_estimate.run({"toy": saved}, {"toy": root}, **kwargs)
    assert len(calls) == 3  # a finished run is not a cache: run again, it measures again


def test_rows_of_other_options_are_not_reused(saved, tmp_path, monkeypatch):
    root, out = _toy_set(saved, tmp_path / "toy"), tmp_path / "out"
    kwargs = dict(out_dir=out, splits=("test",), scenes=3, modes=("narf",), presets=("paper",), scale_sweep=(1.0,),
                  progress=False)
    _counting(monkeypatch, stop_at=3)
    with pytest.raises(KeyboardInterrupt):
        bench_estimate.run({"toy": saved}, {"toy": root}, iterations=2, **kwargs)
    calls = _counting(monkeypatch)
    bench_estimate.run({"toy": saved}, {"toy": root}, iterations=3, **kwargs)
    assert len(calls) == 3


def test_a_log_cut_short_keeps_its_whole_lines_and_another_key_starts_again(tmp_path):
    path = tmp_path / "block.jsonl"
    log = SceneLog(path, {"options": {"iterations": 2}})
    assert log.add({"frame": 4, "add": np.float64(0.01), "along_run": []}) == {"frame": 4, "add": 0.01, "along_run": []}
    log.add({"frame": 7, "add": 0.02})
    path.write_text(path.read_text()[:-8])  # stopped while writing the last row
    again = SceneLog(path, {"options": {"iterations": 2}})
    assert again.resumed == 1 and again.get(4) == {"frame": 4, "add": 0.01, "along_run": []} and again.get(7) is None
    again.add({"frame": 7, "add": 0.03})  # refined again after the stop, appended after whole lines only
    assert {f: r["add"] for f, r in SceneLog(path, {"options": {"iterations": 2}}).rows.items()} == {4: 0.01, 7: 0.03}
    other = SceneLog(path, {"options": {"iterations": 3}})
    assert other.resumed == 0 and other.get(4) is None
    assert json.loads(path.read_text().splitlines()[0]) == {"key": {"options": {"iterations": 3}}}


def test_a_model_never_saved_is_not_logged(model, saved, tmp_path):
    """Without the bundle's checksum a later process could not tell the model from a retrained one."""
    assert scene_log(tmp_path, "toy", "test-narf-paper", {"seed": 0}, saved) is not None
    model.metadata = {k: v for k, v in (model.metadata or {}).items() if k != "checksum"}
    assert scene_log(tmp_path / "unsaved", "toy", "test-narf-paper", {"seed": 0}, model) is None
    assert not (tmp_path / "unsaved").exists()


def test_one_benchmark_run_per_work_folder(tmp_path, capsys):
    """While another process holds a ``--work`` folder, ``narf bench render``, ``estimate``, ``shift`` and
    ``track`` there stop at once with one error line naming it (their scene logs, which a finished run removes, and
    results would collide); the lock goes with the process that held it."""
    from narf_core.cli import main as narf

    work = tmp_path / "work"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom narf_benchmarks.checkpoint import sole_run\n"
         "with sole_run(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(60)", str(work)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        for command in (["bench", "render", "--quick"], ["bench", "estimate", "--quick"], ["bench", "shift", "--quick"],
                        ["bench", "track", "--frames", "2"]):
            assert narf(["--threads", "1", *command, "--work", str(work), "--tools", "clamp"]) != 0
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith(f"narf bench: error: --work {work}: another narf "
                                                       "benchmark is running on this folder")
        assert sorted(p.name for p in work.iterdir()) == [".lock"]  # nothing was made
    finally:
        holder.kill()
        holder.wait()
    with sole_run(work):  # free again
        with pytest.raises(ValueError, match="another narf benchmark"), sole_run(work):
            pass
