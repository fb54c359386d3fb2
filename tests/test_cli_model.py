"""``narf train / eval / render / estimate / bench render`` on the tiny model: results on good input;
on bad input exit code 2 and one line ``narf <command>: error: ...`` on stderr, never a traceback."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

pytest_plugins = ("conftest_model",)

from narf_core.bundle import load_bundle, save_bundle  # noqa: E402
from narf_core.cli import main  # noqa: E402
from narf_core.data.dataset import Dataset  # noqa: E402
from narf_core.estimate import RGB_POLISH  # noqa: E402
from narf_core.geometry import pose_to_position_quaternion  # noqa: E402
from narf_core.modes import choose_mode  # noqa: E402


def run(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:  # argparse
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_error(capsys, command: str, argv: list, *words: str) -> str:
    """``narf argv`` fails with exit code 2 and one error line naming ``words``; returns that line."""
    code, out, err = run(capsys, *argv)
    assert code == 2, (out, err)
    assert "Traceback" not in err and out == ""
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith(f"narf {command}: error: ")]
    assert len(errors) == 1 and errors[0] == lines[-1], err
    for w in words:
        assert w in errors[0], errors[0]
    return errors[0]


def pose_json(T: np.ndarray) -> str:
    return json.dumps({"matrix": np.asarray(T).tolist()})


@pytest.fixture(scope="module")
def view(tiny_dataset, tmp_path_factory):
    """The test frame where the object is largest, as the files ``narf estimate`` reads."""
    dataset = Dataset.open(tiny_dataset)
    frame = max(dataset.frames("test"), key=lambda f: int((dataset.load(f).labels > 0).sum()))
    images = dataset.load(frame)
    folder = tmp_path_factory.mktemp("view")
    Image.fromarray(images.rgb).save(folder / "rgb.png")
    Image.fromarray(((images.labels > 0) * 255).astype(np.uint8)).save(folder / "mask.png")
    K = dataset.camera.K
    return {
        "rgb": folder / "rgb.png",
        "mask": folder / "mask.png",
        "K": f"{float(K[0, 0])},{float(K[1, 1])},{float(K[0, 2])},{float(K[1, 2])}",
        "T": frame.T_cam_obj,
        "joints": frame.joints,
        "folder": folder,
        "pixels": int((images.labels > 0).sum()),
    }


# ---------------------------------------------------------------------------------------------
# narf train


@pytest.mark.slow
def test_train_writes_a_bundle_with_its_command(capsys, tiny_dataset, tmp_path):
    out = tmp_path / "m.narf"
    argv = ["train", tiny_dataset, "--out", out, "--part-steps", "1", "--distill-steps", "1", "--batch-rays", "64",
            "--no-parts", "--sparsity-weight", "0.05", "--exclusion-weight", "0.5", "--track-sequences", "0"]
    code, stdout, err = run(capsys, *argv)
    assert code == 0, err
    assert stdout.startswith(f"wrote {out} (")
    assert stdout.splitlines()[-1] == "mode auto renders narf: the model has no part fields, so the configuration field"
    model = load_bundle(out)
    assert not model.has_parts
    provenance = model.metadata["provenance"]
    assert provenance["command"] == "narf " + " ".join(str(a) for a in argv)  # what was typed, not pytest's argv
    assert provenance["config"]["part_steps"] == 1 and provenance["config"]["keep_parts"] is False
    assert provenance["config"]["sparsity_weight"] == 0.05  # the flag, not the default
    assert provenance["config"]["exclusion_weight"] == 0.5
    assert provenance["config"]["track_sequences"] == 0 and "uncertainty" not in model.metadata
    from narf_core.data.dataset import Dataset

    camera = Dataset.open(tiny_dataset).camera
    assert model.metadata["training_camera"] == {"width": camera.width, "height": camera.height,
                                                 "fx": float(camera.K[0, 0]), "fy": float(camera.K[1, 1])}
    assert not (tmp_path / "m.narf.work").exists()


def test_train_refuses_a_missing_dataset(capsys, tmp_path):
    assert_error(capsys, "train", ["train", tmp_path / "nope", "--out", tmp_path / "m.narf"], str(tmp_path / "nope"))


@pytest.mark.parametrize("flag", ["--sparsity-weight", "--exclusion-weight"])
def test_train_names_the_flag_of_a_bad_term_weight(capsys, tiny_dataset, tmp_path, flag):
    assert_error(capsys, "train", ["train", tiny_dataset, "--out", tmp_path / "m.narf", flag, "-1"],
                 f"{flag} must be >= 0")


# ---------------------------------------------------------------------------------------------
# narf eval


@pytest.mark.slow
def test_eval_json(capsys, tiny_bundle, tiny_dataset):
    code, stdout, err = run(capsys, "eval", tiny_bundle, tiny_dataset, "--split", "novel", "--limit", "3", "--json")
    assert code == 0, err
    r = json.loads(stdout)
    assert (r["mode"], r["mode_reason"]) == choose_mode(load_bundle(tiny_bundle))  # --mode auto by default
    assert r["split"] == "novel" and r["n"] == 3 and (r["width"], r["height"]) == (48, 36)
    assert 0 < r["mse"] < 0.05 and r["psnr"] == pytest.approx(-10 * np.log10(r["mse"]))


@pytest.mark.slow
def test_eval_human_line(capsys, tiny_bundle, tiny_dataset):
    code, stdout, _ = run(capsys, "eval", tiny_bundle, tiny_dataset, "--mode", "parts", "--limit", "2")
    assert code == 0
    assert stdout.startswith("test (parts, 48x36): MSE ") and "N 2" in stdout and stdout.count("\n") == 1


@pytest.mark.slow
def test_eval_refuses_a_missing_dataset(capsys, tiny_bundle, tmp_path):
    assert_error(capsys, "eval", ["eval", tiny_bundle, tmp_path / "nope"], str(tmp_path / "nope"), "not a dataset folder")


def test_eval_refuses_a_corrupt_model(capsys, tiny_dataset, tmp_path):
    bad = tmp_path / "bad.narf"
    bad.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00not json at all!")
    assert_error(capsys, "eval", ["eval", bad, tiny_dataset], str(bad), "not a NARF model bundle")


# ---------------------------------------------------------------------------------------------
# narf render


@pytest.mark.slow
def test_render_json_writes_png_of_the_asked_size(capsys, tiny_bundle, view, tmp_path):
    out, depth = tmp_path / "r" / "rgb.png", tmp_path / "d.png"
    code, stdout, err = run(
        capsys, "render", tiny_bundle, "--pose", pose_json(view["T"]), "--joints", "pivot=0.6", "--size", "64", "40",
        "--out", out, "--depth", depth, "--json",
    )
    assert code == 0, err
    r = json.loads(stdout)
    assert r["rgb"] == str(out) and r["depth"] == str(depth) and r["ms"] > 0
    assert r["joints"] == {"pivot": pytest.approx(0.6)}
    with Image.open(out) as im:
        assert im.size == (64, 40) and im.mode == "RGB"
        assert np.asarray(im).max() > 0  # the object is in view
    with Image.open(depth) as im:
        assert im.size == (64, 40) and np.asarray(im).dtype == np.uint16


@pytest.mark.slow
def test_render_with_intrinsics_a_quaternion_pose_and_parts(capsys, tiny_bundle, view, tmp_path):
    position, quaternion = pose_to_position_quaternion(torch.as_tensor(view["T"]))
    pose = json.dumps({"position": position.tolist(), "orientation": quaternion.tolist()})
    pose_file = tmp_path / "pose.json"
    pose_file.write_text(pose)
    out = tmp_path / "rgb.png"
    code, stdout, err = run(capsys, "render", tiny_bundle, "--pose", pose_file, "--K", view["K"], "--size", "48", "36",
                            "--mode", "parts", "--joints", json.dumps(view["joints"]), "--out", out)
    assert code == 0, err
    assert stdout.startswith(f"wrote {out} in ")
    rendered = np.asarray(Image.open(out))
    mask = np.asarray(Image.open(view["mask"])) > 0
    assert rendered.shape == (36, 48, 3)
    assert rendered[mask].max() > 0 and rendered[~mask].mean() < rendered[mask].mean()  # at the labelled place


@pytest.mark.parametrize(
    ("pose", "words"),
    [
        ('{"matrix": [[1, 0, 0, 0]', ["--pose", "invalid JSON"]),
        ("no-such-file.json", ["--pose", "neither JSON nor a JSON file"]),
        ('{"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}', ["--pose", "4x4"]),
        ('{"matrix": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]}', ["--pose", "not orthonormal"]),
        ('{"matrix": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]}', ["--pose", "reflection"]),
        ('{"matrix": [[1, 0, 0, NaN], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]}', ["--pose", "NaN"]),
        ('{"position": [0, 0, Infinity], "orientation": [0, 0, 0, 1]}', ["--pose", "NaN or infinite"]),
        ('{"position": [0, 0, 0.5], "orientation": [0, 0, 0, 2]}', ["--pose", "unit quaternion"]),
        ('{"position": [0, 0, 0.5]}', ["--pose", "expected"]),
        ('"text"', ["--pose", "neither JSON"]),
    ],
)
@pytest.mark.slow
def test_render_refuses_a_bad_pose(capsys, tiny_bundle, tmp_path, pose, words):
    assert_error(capsys, "render", ["render", tiny_bundle, "--pose", pose, "--out", tmp_path / "x.png"], *words)
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize(
    ("joints", "words"),
    [
        ("nope=0.1", ["unknown joint", "'nope'", "pivot"]),
        ("pivot=2", ["'pivot'", "outside its limits"]),
        ("pivot=-0.5", ["'pivot'", "outside its limits"]),
        ("pivot=nan", ["'pivot'", "finite"]),
        ("pivot=abc", ["--joints", "'pivot'", "non-numeric"]),
        ("pivot", ["--joints", "name=value"]),
        ('{"pivot": "x"}', ["--joints", "non-numeric"]),
    ],
)
@pytest.mark.slow
def test_render_refuses_bad_joints(capsys, tiny_bundle, view, tmp_path, joints, words):
    argv = ["render", tiny_bundle, "--pose", pose_json(view["T"]), "--joints", joints, "--out", tmp_path / "x.png"]
    assert_error(capsys, "render", argv, *words)


@pytest.mark.parametrize(
    ("K", "words"),
    [("1,2,3", ["--K", "fx,fy,cx,cy"]), ("0,40,24,18", ["--K", "positive focal"]), ("[[1, 0], [0, 1]]", ["--K", "3x3"]),
     ("40,40,nan,18", ["--K"])],
)
@pytest.mark.slow
def test_render_refuses_bad_intrinsics(capsys, tiny_bundle, view, tmp_path, K, words):
    argv = ["render", tiny_bundle, "--pose", pose_json(view["T"]), "--K", K, "--out", tmp_path / "x.png"]
    assert_error(capsys, "render", argv, *words)


@pytest.mark.slow
def test_render_refuses_a_missing_or_corrupt_model(capsys, tiny_bundle, view, tmp_path):
    pose = pose_json(view["T"])
    missing = tmp_path / "missing.narf"
    assert_error(capsys, "render", ["render", missing, "--pose", pose, "--out", tmp_path / "x.png"], str(missing),
                 "no such model file")
    corrupt = tmp_path / "corrupt.narf"
    raw = tiny_bundle.read_bytes()
    corrupt.write_bytes(raw[: len(raw) // 2])  # the header whole, the weights cut
    assert_error(capsys, "render", ["render", corrupt, "--pose", pose, "--out", tmp_path / "x.png"], str(corrupt),
                 "corrupt model bundle")
    parts_free = tmp_path / "narf-only.narf"
    save_bundle(parts_free, dataclasses.replace(load_bundle(tiny_bundle), part_fields=None, part_grids=None))
    assert_error(capsys, "render", ["render", parts_free, "--pose", pose, "--mode", "parts", "--out", tmp_path / "x.png"],
                 "needs part fields", "--no-parts")


# ---------------------------------------------------------------------------------------------
# narf estimate


def estimate_argv(bundle, view, **overrides) -> list:
    T_init = np.array(view["T"], dtype=np.float64)
    T_init[:3, 3] += [0.004, -0.003, 0.01]
    args = {"--image": view["rgb"], "--mask": view["mask"], "--K": view["K"], "--init-pose": pose_json(T_init),
            "--iterations": "4", **overrides}
    return ["estimate", bundle, *[x for kv in args.items() for x in kv]]


@pytest.mark.slow
def test_estimate_json_with_ground_truth_reports_add(capsys, tiny_bundle, view):
    gt = json.dumps({"pose": {"matrix": np.asarray(view["T"]).tolist()}, "joints": view["joints"]})
    code, stdout, err = run(capsys, *estimate_argv(tiny_bundle, view, **{"--gt": gt, "--init-joints": "pivot=0.3"}),
                            "--json")
    assert code == 0, err
    r = json.loads(stdout)
    assert np.asarray(r["pose"]["matrix"]).shape == (4, 4) and len(r["pose"]["orientation"]) == 4
    assert set(r["joints"]) == {"pivot"} and 0.0 <= r["joints"]["pivot"] <= 0.6
    # The default preset, auto, without --depth: robust, whose Adam iterations its polish follows where Adam's
    # silhouette explains the mask (not after these 4).
    assert r["preset"] == "robust" and 4 <= r["iterations"] <= 4 + RGB_POLISH and r["status"] in ("converged", "max_iterations")
    metrics = r["metrics"]
    assert 0 <= metrics["add"] < 0.1  # metres: 1.2 cm off at the start; the tiny model's loss is least centimetres off
    assert "add_s" in metrics and np.isfinite(metrics["add_s"])
    u = r["uncertainty"]  # every estimate carries its covariance (6 pose + 1 joint)
    assert np.asarray(u["covariance"]).shape == (7, 7) and len(u["position_sigma_m"]) == 3 and u["dof"] > 0
    assert set(u["joint_sigma"]) == {"pivot"} and np.isfinite(metrics["nees"])


@pytest.mark.slow
def test_estimate_human_summary(capsys, tiny_bundle, view):
    code, stdout, err = run(capsys, *estimate_argv(tiny_bundle, view, **{"--iterations": "0"}))
    assert code == 0, err
    assert "after 0 iterations" in stdout and "pivot=" in stdout and "position [" in stdout
    assert "σ position [" in stdout and "] mm, rotation [" in stdout


@pytest.mark.slow
def test_estimate_gauss_newton_preset(capsys, tiny_bundle, view):
    code, stdout, err = run(capsys, *estimate_argv(tiny_bundle, view, **{"--iterations": "2"}), "--preset", "gauss-newton",
                            "--json")
    assert code == 0, err
    r = json.loads(stdout)
    # 2 per refinement: the given pose's and, where its estimate misses the mask, the pose starts' (pose_starts_overlap)
    # and (no depth image here) a second estimate's from the given pose (refinements)
    assert r["iterations"] <= 3 * 2 and r["uncertainty"] is not None
    assert_error(capsys, "estimate", [*estimate_argv(tiny_bundle, view), "--preset", "newton"], "--preset")


@pytest.mark.slow
def test_estimate_sets_a_refiner_option_on_top_of_the_preset(capsys, tiny_bundle, view):
    """``--set OPTION=JSON`` reaches the refiner over the flags (one iteration where ``--iterations`` says 4); an
    unknown option, a value that is not JSON or one the options refuse is one error line naming it."""
    code, stdout, err = run(capsys, *estimate_argv(tiny_bundle, view), "--preset", "gauss-newton", "--set", "iterations=1",
                            "--set", 'ray_sampling="edges"', "--set", "refinements=1", "--set", "rgb_refinements=1", "--set", "pose_starts_overlap=0",
                            "--json")
    assert code == 0, err
    assert json.loads(stdout)["iterations"] == 1
    assert_error(capsys, "estimate", [*estimate_argv(tiny_bundle, view), "--set", "nope=1"], "--set 'nope=1'")
    assert_error(capsys, "estimate", [*estimate_argv(tiny_bundle, view), "--set", "ray_sampling=edges"], "not JSON")
    assert_error(capsys, "estimate", [*estimate_argv(tiny_bundle, view), "--set", 'ray_sampling="sideways"'],
                 "ray_sampling")


@pytest.mark.slow
def test_estimate_refuses_a_mask_of_another_size(capsys, tiny_bundle, view, tmp_path):
    mask = tmp_path / "mask.png"
    Image.fromarray(np.full((20, 30), 255, np.uint8)).save(mask)
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--mask": mask}), "30x20", "48x36")


@pytest.mark.slow
def test_estimate_refuses_an_empty_mask(capsys, tiny_bundle, view, tmp_path):
    mask = tmp_path / "mask.png"
    Image.fromarray(np.zeros((36, 48), np.uint8)).save(mask)
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--mask": mask}), "mask is empty")


@pytest.mark.slow
def test_estimate_refuses_bad_inputs(capsys, tiny_bundle, view, tmp_path):
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--K": "40,40"}), "--K")
    not_png = tmp_path / "x.png"
    not_png.write_text("text")
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--image": not_png}), "--image", "not an image")
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--image": tmp_path / "none.png"}), "none.png")
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--init-joints": "pivot=9"}), "'pivot'", "limits")
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--gt": '{"joints": {}}'}), "--gt")
    nan_pose = '{"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, NaN], [0, 0, 0, 1]]}'
    assert_error(capsys, "estimate", estimate_argv(tiny_bundle, view, **{"--init-pose": nan_pose}), "--init-pose", "NaN")
    assert_error(capsys, "estimate", estimate_argv(tmp_path / "m.narf", view), "no such model file")


# ---------------------------------------------------------------------------------------------
# narf bench render --quick


@pytest.mark.slow
def test_bench_render_quick_on_a_folder_of_models(capsys, tiny_bundle, tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(tiny_bundle, models / "longnose.narf")
    work = tmp_path / "work"
    code, stdout, err = run(capsys, "bench", "render", "--quick", "--json", "--models", models, "--work", work)
    assert code == 0, err
    result = json.loads(stdout)
    rows = result["rows"]
    assert {(r["split"], r["mode"]) for r in rows} == {(s, m) for s in ("test", "novel") for m in ("narf", "parts")}
    assert all(r["tool"] == "longnose" and r["n"] == 4 and (r["width"], r["height"]) == (160, 120) for r in rows)
    assert all(np.isfinite(r["mse"]) and r["paper_mse"] is not None for r in rows)
    sweep = result["step_sweep"]["longnose"]
    assert [s["samples_per_diagonal"] for s in sweep] == [64, 128, 256]
    assert json.loads((work / "render.json").read_text()) == result
    assert (work / "render.md").read_text().startswith("| tool |") and (work / "render_error_vs_time.png").stat().st_size
    assert not (work / "models").exists()  # nothing was trained


def test_bench_render_quick_without_models_is_an_error(capsys, tmp_path):
    empty = tmp_path / "models"
    empty.mkdir()
    assert_error(capsys, "bench", ["bench", "render", "--quick", "--models", empty, "--work", tmp_path / "w"],
                 "no models", str(empty))
    assert_error(capsys, "bench", ["bench", "render", "--quick", "--tools", "clamp", "--models", empty, "--work",
                                   tmp_path / "w"], str(empty / "clamp.narf"))


@pytest.mark.slow
def test_bench_render_quick_with_noise_is_an_error(capsys, tiny_bundle, tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(tiny_bundle, models / "longnose.narf")
    assert_error(capsys, "bench", ["bench", "render", "--quick", "--noise", "--models", models, "--work", tmp_path / "w"],
                 "--noise")
    assert not (tmp_path / "w").exists()


def test_render_bench_quick_version_keeps_the_rest_of_the_config():
    from narf_benchmarks.render import RenderBenchConfig

    base = RenderBenchConfig(tools=("clamp",), models={"clamp": Path("m/clamp.narf")}, train_budget_s=5.0)
    quick = base.quick_version()
    assert quick.sizes == ((160, 120),) and quick.splits == ("test", "novel") and quick.images_per_split == 4
    assert quick.step_sweep == (64, 128, 256) and quick.views == 24 and quick.quick
    assert quick.tools == base.tools and quick.models == base.models and quick.modes == base.modes
    assert base.sizes == ((160, 120), (640, 480)) and not base.quick  # the original is unchanged
