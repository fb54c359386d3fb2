"""``mode: auto``: training records both render modes, ``auto`` follows the rule of narf_core/modes.py,
and every place that takes a mode (refiner, tracker, CLI, API, client) says which mode ran and why."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

pytest_plugins = ("conftest_model",)

from narf_core import modes  # noqa: E402
from narf_core.bundle import NarfModel, load_bundle, read_metadata, save_bundle  # noqa: E402
from narf_core.checks import InputError  # noqa: E402
from narf_core.data.dataset import Dataset  # noqa: E402
from narf_core.estimate import EstimateInputError, EstimateOptions, refine  # noqa: E402
from narf_core.modes import RECORD_KEY, choose_mode, measure_modes  # noqa: E402
from tests.test_cli_model import run  # noqa: E402

ASSETS = Path(__file__).parent / "assets"


def record(narf_ms: float, parts_ms: float, narf_db: tuple[float, float], parts_db: tuple[float, float]) -> dict:
    """A measurement like training's: test and novel splits, PSNR per split, times per image."""
    splits = {}
    for split, n, p in zip(("test", "novel"), narf_db, parts_db):
        splits[split] = {"narf": {"psnr": n, "mse": 10 ** (-n / 10), "ms_per_image": narf_ms},
                         "parts": {"psnr": p, "mse": 10 ** (-p / 10), "ms_per_image": parts_ms}}
    return {"width": 48, "height": 36, "views": 8, "threads": 1, "splits": splits}


@pytest.fixture(scope="module")
def bundle_with(tiny_bundle, tmp_path_factory):
    """``bundle_with(record, parts=True)``: the tiny model saved again with ``record`` (``None``: no
    record) and with or without its part fields, loaded back from the file."""
    folder = tmp_path_factory.mktemp("bundles")
    count = iter(range(1000))

    def make(rec: dict | None, *, parts: bool = True) -> tuple[NarfModel, Path]:
        model = load_bundle(tiny_bundle)
        model.metadata.pop(RECORD_KEY, None)
        if rec is not None:
            model.metadata[RECORD_KEY] = rec
        if not parts:
            model.part_fields = model.part_grids = None
        path = save_bundle(folder / f"m{next(count)}.narf", model)
        return load_bundle(path), path

    return make


@pytest.fixture(scope="module")
def frame(tiny_dataset):
    """The largest test view of the tiny dataset: (dataset, frame, images)."""
    dataset = Dataset.open(tiny_dataset)
    best = max(dataset.frames("test"), key=lambda f: int((dataset.load(f).labels > 0).sum()))
    return dataset, best, dataset.load(best)


# --------------------------------------------------------------------------------------------
# the record training writes


def test_training_records_both_modes_on_the_held_out_splits(tiny_bundle, tiny_dataset):
    from narf_core.evaluate import evaluate_render

    rec = read_metadata(tiny_bundle)[RECORD_KEY]
    assert (rec["width"], rec["height"], rec["threads"], rec["views"]) == (48, 36, 1, modes.MEASURE_VIEWS)
    assert set(rec["splits"]) == {"test", "novel"} and rec["seconds"] > 0
    model, dataset = load_bundle(tiny_bundle), Dataset.open(tiny_dataset)
    for split, by_mode in rec["splits"].items():
        assert set(by_mode) == {"narf", "parts"}
        for mode, f in by_mode.items():
            assert f["ms_per_image"] > 0 and f["psnr"] == pytest.approx(-10 * math.log10(f["mse"]))
            again = evaluate_render(model, dataset, split=split, mode=mode, limit=rec["views"])
            assert f["mse"] == pytest.approx(again.mse, rel=1e-4)  # the same views, the same renders
    about = model.describe()
    assert about[RECORD_KEY] == rec
    assert about["auto_mode"] == dict(zip(("mode", "reason"), choose_mode(model)))


def test_measure_modes_of_a_bundle_without_parts_has_narf_only(bundle_with, tiny_dataset):
    model, _ = bundle_with(None, parts=False)
    threads = torch.get_num_threads()
    rec = measure_modes(model, Dataset.open(tiny_dataset), splits=("novel", "train"), views=2)
    assert torch.get_num_threads() == threads  # measured on one thread, then restored
    assert set(rec["splits"]) == {"novel", "train"} and rec["views"] == 2
    assert all(set(by_mode) == {"narf"} for by_mode in rec["splits"].values())
    assert measure_modes(model, Dataset.open(tiny_dataset), splits=()) is None


# --------------------------------------------------------------------------------------------
# the rule


@pytest.mark.parametrize(
    ("rec", "mode", "words"),
    [
        (record(10, 20, (30.0, 29.0), (30.5, 29.5)), "narf", ["configuration field is faster", "10.0 ms", "20.0"]),
        (record(10, 20, (30.0, 29.0), (31.0, 30.0)), "narf", ["within 1 dB"]),  # exactly 1 dB: still within
        (record(10, 20, (30.0, 27.0), (30.5, 29.5)), "parts", ["narf is faster but 2.50 dB worse", "novel"]),
        (record(25, 20, (30.0, 29.0), (30.0, 29.0)), "parts", ["no faster", "25.0 ms", "20.0"]),
        (record(25, 20, (33.0, 32.0), (30.0, 29.0)), "narf", ["parts is faster but 3.00 dB worse"]),
    ],
)
def test_auto_picks_the_faster_mode_unless_it_is_worse_than_the_tolerance(bundle_with, rec, mode, words):
    model, _ = bundle_with(rec)
    chosen, reason = choose_mode(model, "auto")
    assert chosen == mode, reason
    for w in words:
        assert w in reason, reason
    assert choose_mode(model, "narf") == ("narf", "requested") and choose_mode(model, "parts") == ("parts", "requested")


def test_without_a_measurement_auto_renders_narf_and_says_why(bundle_with, tiny_model):
    model, _ = bundle_with(None)
    assert choose_mode(model) == ("narf", "no mode measurement in the bundle, so the configuration field "
                                          "(the paper's choice; `narf eval --record-modes` adds one)")
    broken, _ = bundle_with({"splits": {"test": {"narf": {"psnr": "x"}, "parts": {}}}})
    mode, reason = choose_mode(broken)
    assert mode == "narf" and reason.startswith("an unreadable mode measurement in the bundle")
    assert model.describe()["auto_mode"]["mode"] == "narf" and model.describe()[RECORD_KEY] is None


def test_a_bundle_without_parts_renders_narf_and_refuses_parts(bundle_with, frame):
    model, _ = bundle_with(record(25, 20, (30.0, 29.0), (30.0, 29.0)), parts=False)  # the record favours parts
    assert choose_mode(model) == ("narf", "the model has no part fields, so the configuration field")
    with pytest.raises(InputError) as info:
        choose_mode(model, "parts")
    assert info.value.field == "options.mode" and "lacks" in info.value.reason
    dataset, f, images = frame
    with pytest.raises(EstimateInputError) as info:
        refine(model, images.rgb, images.labels > 0, dataset.camera, f.T_cam_obj, options=EstimateOptions(mode="parts"))
    assert info.value.field == "options.mode" and str(info.value).startswith("options.mode 'parts' needs part fields")


def test_bad_mode_values_are_the_cores_error_naming_options_mode():
    from narf_core.track import TrackInputError, TrackOptions

    for options, error in ((EstimateOptions, EstimateInputError), (TrackOptions, TrackInputError)):
        assert options().mode == "auto"
        with pytest.raises(error) as info:
            options(mode="magic")
        assert info.value.field == "options.mode"
        assert info.value.reason == "must be one of auto, narf, parts, got 'magic'"


# --------------------------------------------------------------------------------------------
# the refiner and the tracker report the mode that ran


def test_refine_and_track_run_the_chosen_mode_and_say_why(bundle_with, frame):
    from narf_core.track import TrackFrame, TrackOptions, TrackState, step

    model, _ = bundle_with(record(25, 20, (30.0, 29.0), (30.0, 29.0)))  # auto: parts
    dataset, f, images = frame
    mask = images.labels > 0
    fast = {"iterations": 1, "uncertainty": False}
    result = refine(model, images.rgb, mask, dataset.camera, f.T_cam_obj, options=EstimateOptions(**fast))
    assert result.mode == "parts" and "no faster" in result.mode_reason
    assert result.to_dict()["mode"] == "parts" and result.to_dict()["mode_reason"] == result.mode_reason
    explicit = refine(model, images.rgb, mask, dataset.camera, f.T_cam_obj,
                      options=EstimateOptions(mode="narf", **fast))
    assert (explicit.mode, explicit.mode_reason) == ("narf", "requested")

    state = TrackState.initial(model, f.T_cam_obj, f.joints, 1.0)
    options = TrackOptions(iterations=1, reinit_iterations=1, uncertainty_rays=0)
    out, _ = step(model, dataset.camera, TrackFrame(images.rgb, mask, 1.0), state, options)
    assert (out.mode, out.to_dict()["mode"]) == ("parts", "parts") and "no faster" in out.mode_reason


# --------------------------------------------------------------------------------------------
# the API and the client, on a real server on loopback


@pytest.fixture(scope="module")
def server(bundle_with, tmp_path_factory) -> Iterator[str]:
    from narf_service.app import create_app
    from narf_service.main import serve_in_thread
    from narf_service.registry import ModelRegistry
    from narf_service.settings import Settings

    models = {"partsfast": bundle_with(record(25, 20, (30.0, 29.0), (30.0, 29.0)))[0],
              "noparts": bundle_with(None, parts=False)[0]}
    settings = Settings(models_dir=tmp_path_factory.mktemp("models"), workers=1, queue_size=4, torch_threads=1,
                        state_key="s" * 24)
    with serve_in_thread(create_app(settings, registry=ModelRegistry(models=models))) as url:
        yield url


def test_the_api_and_the_client_report_the_chosen_mode(server, frame):
    from narf_client import InvalidInput, NarfClient, TrackFrame

    dataset, f, images = frame
    K = dataset.camera.K.double().numpy()
    mask = images.labels > 0
    with NarfClient(server, retries=0) as client:
        view = client.render("partsfast", f.T_cam_obj, K, 48, 36, joints=f.joints)
        assert view.mode == "parts" and "no faster" in view.mode_reason
        assert client.render("partsfast", f.T_cam_obj, K, 48, 36, mode="narf").mode_reason == "requested"
        assert client.render("noparts", f.T_cam_obj, K, 48, 36).mode == "narf"
        est = client.estimate(images.rgb, mask, K, f.T_cam_obj, model="partsfast", iterations=1,
                              options={"uncertainty": False})
        assert est.mode == "parts" and "no faster" in est.mode_reason
        est = client.estimate(images.rgb, mask, K, f.T_cam_obj, model="noparts", iterations=1,
                              options={"mode": "auto", "uncertainty": False})
        assert (est.mode, est.mode_reason) == ("narf", "the model has no part fields, so the configuration field")
        update = client.track_step(TrackFrame(1.0, images.rgb, None), K, model="partsfast", initial_pose=f.T_cam_obj,
                                   options={"iterations": 1, "uncertainty": False})  # no mask: lost at once
        assert update.status == "lost" and update.mode == "parts" and "no faster" in update.mode_reason
        info = client.model("partsfast")
        assert info.metadata[RECORD_KEY]["splits"]["test"]["parts"]["ms_per_image"] == 20
        assert info.auto_mode == "parts" and "no faster" in info.auto_mode_reason
        listed = {m.name: (m.auto_mode, m.auto_mode_reason) for m in client.models()}
        assert listed["noparts"] == ("narf", "the model has no part fields, so the configuration field")

        with pytest.raises(InvalidInput) as e:
            client.estimate(images.rgb, mask, K, f.T_cam_obj, model="noparts", iterations=1, options={"mode": "parts"})
        assert e.value.field == "request.options.mode" and "lacks" in str(e.value)
        with pytest.raises(InvalidInput) as e:
            client.estimate(images.rgb, mask, K, f.T_cam_obj, model="noparts", iterations=1, options={"mode": "magic"})
        assert e.value.field == "request.options.mode"
        with pytest.raises(InvalidInput) as e:
            client.render("noparts", f.T_cam_obj, K, 48, 36, mode="parts")
        assert e.value.field == "mode" and "lacks" in str(e.value)
        with pytest.raises(InvalidInput) as e:
            client.track_step(TrackFrame(1.0, images.rgb, mask), K, model="noparts", initial_pose=f.T_cam_obj,
                              options={"mode": "parts"})
        assert e.value.field == "request.options.mode"


# --------------------------------------------------------------------------------------------
# the CLI


def test_the_cli_takes_auto_by_default_and_says_which_mode_ran(capsys, bundle_with, frame, tmp_path):
    from narf_core.cli import MODES

    assert MODES == modes.MODES  # (named in the CLI so that --help imports no numpy)
    model, path = bundle_with(record(25, 20, (30.0, 29.0), (30.0, 29.0)))
    _, f, _ = frame
    pose = json.dumps({"matrix": np.asarray(f.T_cam_obj).tolist()})
    code, out, err = run(capsys, "--threads", "1", "render", path, "--pose", pose, "--size", "48", "36",
                         "--out", tmp_path / "a.png", "--json")
    assert code == 0, err
    r = json.loads(out)
    assert (r["mode"], r["mode_reason"]) == choose_mode(model) and r["mode"] == "parts"
    code, out, err = run(capsys, "--threads", "1", "render", path, "--pose", pose, "--size", "48", "36",
                         "--out", tmp_path / "a.png")
    assert code == 0 and out.splitlines()[1].startswith("mode parts (auto): the configuration field is no faster")

    _, no_parts = bundle_with(None, parts=False)
    code, out, err = run(capsys, "render", no_parts, "--pose", pose, "--out", tmp_path / "b.png", "--mode", "parts")
    assert code == 2 and out == "" and "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("narf render: error: --mode 'parts' needs part fields")


def test_eval_records_the_measurement_into_an_old_bundle(capsys, bundle_with, tiny_dataset):
    model, path = bundle_with(None)  # a bundle from before the measurement existed
    assert choose_mode(model)[1].startswith("no mode measurement")
    code, out, err = run(capsys, "--threads", "1", "eval", path, tiny_dataset, "--record-modes", "--limit", "2", "--json")
    assert code == 0, err
    r = json.loads(out)
    saved = load_bundle(path)  # checksum verified again at load
    assert saved.metadata[RECORD_KEY] == r["mode_measurement"]
    assert set(r["mode_measurement"]["splits"]) == {"test", "novel"}
    assert (r["mode"], r["mode_reason"]) == choose_mode(saved) and not r["mode_reason"].startswith("no mode")


# --------------------------------------------------------------------------------------------
# benchmarks on an object with several joints


@pytest.mark.slow
def test_benchmarks_cover_an_object_with_two_joints(tiny_dataset, tmp_path):
    """``narf bench render`` and ``narf bench estimate`` on a prismatic + revolute object (tests/assets):
    a row per split and mode, the error of each joint in its unit, the mode ``auto`` picks."""
    pytest.importorskip("pybullet")
    from conftest_model import TINY_SIZE, TINY_VIEWS, tiny_config
    from narf_benchmarks import estimate as bench_estimate
    from narf_benchmarks import render as bench_render
    from narf_core.data.synth.generate import synthesize
    from narf_core.train.pipeline import train

    work = tmp_path / "work"
    size = f"{TINY_SIZE[0]}x{TINY_SIZE[1]}"
    root = synthesize(ASSETS / "synth_articulated.urdf", work / "data" / f"slider-{size}", size=TINY_SIZE,
                      views=TINY_VIEWS, seed=0)
    path = train(root, tmp_path / "slider.narf", tiny_config(), progress=False)
    model = load_bundle(path)
    assert [j.name for j in model.joints] == ["slide", "lever"]
    assert set(model.metadata[RECORD_KEY]["splits"]) == {"test", "novel"}

    config = bench_render.RenderBenchConfig(tools=("slider",), sizes=(TINY_SIZE,), splits=("test", "novel"),
                                            images_per_split=2, step_sweep=(64,), views=TINY_VIEWS, quick=True,
                                            models={"slider": path})
    result = bench_render.run(work, config)
    every = {(s, m) for s in ("test", "novel") for m in ("narf", "parts")}
    assert {(r["split"], r["mode"]) for r in result["rows"]} == every
    (summary,) = result["modes"]
    narf = [r for r in result["rows"] if r["mode"] == "narf"]
    assert summary["narf_ms"] == pytest.approx(np.mean([r["ms_per_image"] for r in narf]))
    assert set(summary["psnr_gap_db"]) == {"test", "novel"}
    assert result["auto"]["slider"] == dict(zip(("mode", "reason"), choose_mode(model)))
    assert f"| slider | no | {size} |" in (work / "render.md").read_text()

    out = bench_estimate.run({"slider": model}, {"slider": root}, out_dir=tmp_path / "est", splits=("test",), scenes=1,
                             iterations=3, scale_sweep=(1.0,), presets=("paper",))
    rows = out["table"]
    assert [r["mode"] for r in rows] == ["narf", "parts"]
    for r in rows:
        assert {name: j["unit"] for name, j in r["joints"].items()} == {"slide": "m", "lever": "deg"}
        assert all(np.isfinite(j["mean"]) for j in r["joints"].values()) and r["seconds_mean"] > 0
    text = (tmp_path / "est" / "estimate.md").read_text()
    slide_mm = 1000 * rows[0]["joints"]["slide"]["mean"]
    assert f"slide: {slide_mm:.2f} ± " in text and "<br>lever: " in text and " deg" in text
    for name, after in (("slide", " mm<br>lever: "), ("lever", " deg |")):  # a tiny model may flag a joint unobserved
        joint = rows[0]["joints"][name]
        assert (f" ({joint['unobserved']} flagged unobserved" if joint.get("unobserved") else after) in text
    assert out["auto"]["slider"]["mode"] == choose_mode(model)[0]
