"""``narf synth``: a dataset on good input; one error line, exit code 2 and no traceback on bad."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("pybullet")

from narf_core.cli import main  # noqa: E402
from narf_core.data.dataset import Dataset  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ARTICULATED_URDF = Path(__file__).parent / "assets" / "synth_articulated.urdf"


def run(capfd, *argv: str) -> tuple[int, str, str]:
    """``narf`` in-process; stdout and stderr captured at the file-descriptor level (pybullet's C
    code writes there)."""
    try:
        code = main(list(argv))
    except SystemExit as e:  # argparse
        code = e.code
    out, err = capfd.readouterr()
    return code, out, err


def assert_one_error_line(code: int, err: str, fragment: str) -> None:
    assert code == 2
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("narf synth: error: ")]
    assert len(errors) == 1 and errors[0] == lines[-1], err
    assert fragment in errors[0]


def test_synth_json(capfd, tmp_path):
    out = tmp_path / "ds"
    code, stdout, err = run(
        capfd, "synth", "--tool", str(ARTICULATED_URDF), "--out", str(out), "--size", "32", "24", "--views", "3",
        "--seed", "1", "--noise", "paper", "--noise-mask-px", "2", "--json",
    )
    assert code == 0, err
    result = json.loads(stdout)  # nothing else on stdout: pybullet's own output is kept off it
    assert result["frames"] == {"train": 3, "test": 17, "novel": 17}
    assert result["noise"] == {"rot_deg": 2.0, "trans_mm": 5.0, "theta": 0.02, "mask_px": 2, "depth_m": 0.002}
    assert result["bytes"] > 0 and result["dataset"] == str(out)
    assert "Traceback" not in err and "37/37" in err  # the progress bar finished
    ds = Dataset.open(out)
    assert ds.noisy and ds.generator["seed"] == 1 and ds.generator["size"] == [32, 24]


def test_synth_human_summary(capfd, tmp_path):
    code, stdout, _ = run(capfd, "synth", "--tool", str(ARTICULATED_URDF), "--out", str(tmp_path / "d"), "--size", "24", "16", "--views", "1")
    assert code == 0
    assert stdout.startswith("wrote 35 frames (train 1, test 17, novel 17)") and stdout.count("\n") == 1


def test_help_explains_itself(capfd):
    code, stdout, _ = run(capfd, "synth", "--help")
    assert code == 0
    for words in ("--tool", "--noise-rot-deg", "novel", "clean/"):
        assert words in stdout


def test_noise_choices_are_the_presets():
    from narf_core.cli import NOISE_PRESETS
    from narf_core.data.synth import generate

    assert NOISE_PRESETS == tuple(generate.NOISE_PRESETS)


def bad_urdfs(tmp_path: Path) -> dict[str, Path]:
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot name='r'><link name='a'>")
    missing_mesh = tmp_path / "missing_mesh.urdf"
    missing_mesh.write_text("<robot name='r'><link name='a'><visual><geometry><mesh filename='meshes/gone.obj'/></geometry></visual></link></robot>")
    return {"broken": broken, "missing_mesh": missing_mesh}


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--tool", "hammer"], "unknown tool 'hammer'; expected one of clamp, lineman-a"),
        (["--tool", "{broken}"], "broken.urdf: not valid XML"),
        (["--tool", "{missing_mesh}"], "link 'a': mesh file 'meshes/gone.obj' not found"),
        (["--tool", "{tmp}/nowhere.urdf"], "nowhere.urdf: no such URDF file"),
        (["--tool", str(ARTICULATED_URDF), "--size", "0", "24"], "argument --size: 0 is not a positive integer"),
        (["--tool", str(ARTICULATED_URDF), "--size", "32"], "argument --size: expected 2 arguments"),
        (["--tool", str(ARTICULATED_URDF), "--views", "0"], "argument --views: 0 is not a positive integer"),
        (["--tool", str(ARTICULATED_URDF), "--noise-rot-deg", "-1"], "argument --noise-rot-deg: -1 is not a finite number >= 0"),
        (["--tool", str(ARTICULATED_URDF), "--noise", "loud"], "argument --noise: invalid choice: 'loud'"),
    ],
)
def test_bad_input(capfd, tmp_path, args, fragment):
    paths = {name: str(p) for name, p in bad_urdfs(tmp_path).items()}
    argv = [a.format(tmp=tmp_path, **paths) for a in args]
    code, stdout, err = run(capfd, "synth", "--out", str(tmp_path / "out"), "--views", "1", *argv)  # later wins
    assert stdout == ""
    assert_one_error_line(code, err, fragment)


def test_unwritable_output_folder(capfd, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    code, _, err = run(capfd, "synth", "--tool", str(ARTICULATED_URDF), "--out", str(blocker / "ds"), "--views", "1")
    assert_one_error_line(code, err, "a_file")
    if os.geteuid() != 0:  # root ignores permissions
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        code, _, err = run(capfd, "synth", "--tool", str(ARTICULATED_URDF), "--out", str(locked / "ds"), "--views", "1")
        assert_one_error_line(code, err, "Permission denied")


def test_refuses_non_empty_folder_without_overwrite(capfd, tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "thesis.tex").write_text("")
    code, _, err = run(capfd, "synth", "--tool", str(ARTICULATED_URDF), "--out", str(out), "--views", "1")
    assert_one_error_line(code, err, "folder is not empty")
    code, _, err = run(capfd, "synth", "--tool", str(ARTICULATED_URDF), "--out", str(out), "--views", "1", "--overwrite")
    assert_one_error_line(code, err, "will not overwrite a folder holding ['thesis.tex']")
    assert (out / "thesis.tex").exists()


def test_console_entry_point_subprocess(tmp_path):
    """The real process: exit status 2 and a single stderr line (pybullet's import banner kept off)."""
    proc = subprocess.run(
        [sys.executable, "-m", "narf_core.cli", "synth", "--tool", "hammer", "--out", str(tmp_path / "o")],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [
        "narf synth: error: unknown tool 'hammer'; expected one of clamp, lineman-a, lineman-b, longnose, lamp, gripper, "
        "cabinet or a path to a .urdf file"
    ]
