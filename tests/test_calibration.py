"""The model-error fit of ``narf_benchmarks.calibration``: on rows whose needed factor is known, and
end to end on a trained model's own labelled dataset."""

import json
import shutil

import numpy as np
import pytest

from narf_benchmarks.calibration import COVERAGE, PIXELS_GRID, coverage, fit, main
from narf_core.bundle import load_bundle
from narf_core.estimate import MODEL_ERROR, chi2_quantile

pytest_plugins = ("conftest_model",)


def rows(errors_m, kind="shape", axis=0, variance=0.02):
    """One 6 + 1 parameter row per position error along ``axis`` (camera frame; the object 0.5 m down
    z, its radius 0.1 m): no statistical σ, a pixel of 1 mm, the same colour residual everywhere (so the fitted
    reference is it and the residual factor 1; ``variance``: that residual)."""
    return [{"preset": "robust", "class": kind, "sigma": np.zeros((7, 7)), "colour_variance": variance,
             "pixel_m": 0.001, "radius": 0.1, "joint_speeds": np.array([0.05]),
             "line_of_sight": np.array([0.0, 0.0, 1.0]), "stretch": 5.0,
             "e": np.eye(7)[axis] * e} for e in errors_m]


def test_fit_finds_the_smallest_factor_that_holds_the_share_also_past_five_pixels(capsys):
    group = rows(np.arange(1, 21) * 0.001)  # 19 of 20 inside needs σ >= 19 mm / sqrt(χ²₇(0.95)): 5.07 pixels
    needed = 0.019 / 0.001 / np.sqrt(chi2_quantile(COVERAGE, 7))
    calibration = fit(group)
    pixels = calibration["pixels"]["shape"]
    assert calibration["reference_variance"] == 0.02
    assert needed <= pixels and pixels == PIXELS_GRID[np.searchsorted(PIXELS_GRID, needed)]
    assert coverage(group, calibration) == {"robust": 0.95}
    assert capsys.readouterr().err == ""


def test_fit_without_depth_counts_the_line_of_sight_as_distance_over_radius_footprints(capsys):
    """The same errors along the line of sight need a fifth of the factor without depth (the object 0.5 m
    away, radius 0.1 m: 5 footprints along it per footprint across); only the classes asked are fitted."""
    needed = 0.019 / 0.001 / np.sqrt(chi2_quantile(COVERAGE, 7))
    usual = MODEL_ERROR["reference_variance"]  # the reference kept: rows at it have the residual factor 1
    calibration = fit(rows(np.arange(1, 21) * 0.001, "silhouette", axis=2, variance=usual), kinds=("silhouette",))
    pixels = calibration["pixels"]["silhouette"]
    assert needed / 5 <= pixels and pixels == PIXELS_GRID[np.searchsorted(PIXELS_GRID, needed / 5)]
    assert {k: v for k, v in calibration["pixels"].items() if k != "silhouette"} == {
        k: v for k, v in MODEL_ERROR["pixels"].items() if k != "silhouette"}
    assert calibration["reference_variance"] == MODEL_ERROR["reference_variance"]
    across = fit(rows(np.arange(1, 21) * 0.001, "silhouette", axis=0, variance=usual), kinds=("silhouette",))
    assert across["pixels"]["silhouette"] == PIXELS_GRID[np.searchsorted(PIXELS_GRID, needed)]  # across: as with depth
    assert capsys.readouterr().err == ""


def test_fit_says_when_no_factor_holds_the_share(capsys):
    calibration = fit(rows([1.0] * 10))  # a metre off: 267 pixels needed
    assert calibration["pixels"]["shape"] == PIXELS_GRID[-1]
    assert "no factor up to 50 pixels holds 95% of the 'shape' errors" in capsys.readouterr().err
    assert coverage(rows([1.0] * 10), calibration) == {"robust": 0.0}


def test_calibration_fits_a_bundle_on_a_labelled_dataset_of_its_own(tiny_bundle, tiny_dataset, tmp_path, capsys):
    """``--data``: every preset on the dataset's test and novel frames, the fitted constants printed and
    stored in the bundle; a missing dataset is one error line."""
    bundle = tmp_path / "own.narf"
    shutil.copy(tiny_bundle, bundle)
    assert main(["--model", str(bundle), "--data", str(tiny_dataset), "--scenes", "1", "--write-bundle", str(bundle)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["rows"] == 2 * 5  # one test and one novel frame; two presets with depth, three without
    own = load_bundle(bundle).metadata["uncertainty"]
    assert own == printed["calibration"]
    assert set(own["pixels"]) == {"colour", "silhouette", "shape", "shape-gauss-newton"}
    assert set(printed["coverage_95_on_fit_data"]) == {"robust", "gauss-newton", "paper (rgb)", "robust (rgb)",
                                                       "gauss-newton (rgb)"}
    assert all(value == 1.0 for value in printed["coverage_95_on_fit_data"].values())  # one row per class: inside
    with pytest.raises(SystemExit):
        main(["--model", str(bundle), "--data", str(tmp_path / "missing")])
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.endswith(f"error: --data {tmp_path / 'missing'}: {tmp_path / 'missing'}: not a dataset folder "
                          "(no such directory)")


def test_calibration_on_synthesised_data_pools_the_tracker_only_when_asked(tiny_bundle, tiny_dataset, tmp_path, capsys):
    """The synthesised seed-1 data: the single images alone by default (the tracker's frames have their own
    factor, fitted after with ``--tracker``); ``--pool-track`` adds a tracked sequence's frames. No single
    images here (``--scenes 0``; the test above fits them), so what is fitted is the tracker's frames or nothing."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "longnose-160x120-seed1").symlink_to(tiny_dataset)  # present: not synthesised again
    argv = ["--work", str(work), "--model", str(tiny_bundle), "--tool", "longnose", "--inputs", "rgbd", "--scenes", "0"]
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["rows"] == 0 and printed["coverage_95_on_fit_data"] == {}
    assert printed["calibration"]["pixels"] == MODEL_ERROR["pixels"]  # nothing to fit: the defaults
    assert not (work / "sequences").exists()
    assert main(argv + ["--pool-track", "--frames", "3"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert 1 <= printed["rows"] <= 3  # the frames the tracker did not lose
    assert set(printed["coverage_95_on_fit_data"]) == {"track"}
    assert printed["calibration"]["pixels"]["shape-gauss-newton"] != MODEL_ERROR["pixels"]["shape-gauss-newton"]
    for clash, extra in (("--data", ["--data", str(tiny_dataset)]), ("--inputs rgb", ["--inputs", "rgb"])):
        with pytest.raises(SystemExit):
            main(argv + ["--pool-track"] + extra)
        assert capsys.readouterr().err.strip().splitlines()[-1].endswith(
            f"error: --pool-track: not with {clash} (it pools a synthesised track's RGB-D frames with the single images)")
