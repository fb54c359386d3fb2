"""The core's input rules (narf_core/checks.py, narf_core/depth.py) and the floors that map them:
one rule each, the same answer from the library, the dataset reader and the service."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from narf_core.checks import ROTATION_TOLERANCE, InputError, JointSpec, check_joints, check_number, check_pose
from narf_core.depth import DEPTH_MM_MAX, depth_to_mm, mm_to_depth
from narf_core.estimate import EstimateInputError, EstimateOptions

SPECS = [JointSpec("slide", "prismatic", 0.0, 0.1), JointSpec("turn", "revolute", -1.0, 1.0)]


def rotation_z(angle: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    return T


def test_a_rigid_pose_passes_as_a_float64_copy():
    T = rotation_z(0.3).astype(np.float32)
    out = check_pose(T, "T")
    assert out.dtype == np.float64 and out is not T and np.allclose(out, T)
    assert np.allclose(check_pose(torch.tensor(rotation_z(0.3)), "T"), rotation_z(0.3))
    nearly = rotation_z(0.3)
    nearly[0, 0] += ROTATION_TOLERANCE / 2  # within the tolerance: printed with few digits
    check_pose(nearly, "T")


@pytest.mark.parametrize(
    "change, reason",
    [
        (lambda T: T[:3], "must be a 4x4 pose matrix, got shape (3, 4)"),
        (lambda T: np.where(np.eye(4) > 0, np.nan, T), "must be finite numbers"),
        (lambda T: T.astype(str), "must be a 4x4 matrix of real numbers"),
        (lambda T: T + np.diag([0, 0, 0, 0.1]), "must have the last row [0, 0, 0, 1]"),
        (lambda T: T @ np.diag([1, 1.01, 1, 1]), "has a rotation block that is not orthonormal"),
        (lambda T: T @ np.diag([1, 1, -1, 1]), "has a rotation block that is a reflection"),
    ],
)
def test_a_pose_that_is_not_rigid_is_refused_naming_the_field(change, reason):
    with pytest.raises(EstimateInputError) as info:
        check_pose(change(rotation_z(0.3)), "T_init", error=EstimateInputError)
    assert str(info.value).startswith(f"T_init {reason}")
    assert info.value.field == "T_init" and info.value.reason.startswith(reason)


def test_joints_are_checked_against_their_specs():
    assert check_joints(SPECS, {"turn": np.float32(0.5)}, "joints") == {"turn": 0.5}
    assert check_joints(SPECS, None, "joints") == {}
    assert check_joints(SPECS, {"slide": 0.1 + 5e-7}, "joints") == {"slide": 0.1 + 5e-7}  # float32 round-off
    cases = [
        ({"bend": 0.0}, "joints.bend", "unknown joint(s) ['bend']; this object's joints are ['slide', 'turn']"),
        ({"slide": 0.2}, "joints.slide", "0.2 is outside its limits [0.0, 0.1] (m)"),
        ({"turn": -1.5}, "joints.turn", "-1.5 is outside its limits [-1.0, 1.0] (rad)"),
        ({"turn": math.inf}, "joints.turn", "value must be finite, got inf"),
        ({"turn": True}, "joints.turn", "value must be a number, got bool True"),
    ]
    for joints, field, reason in cases:
        with pytest.raises(InputError) as info:
            check_joints(SPECS, joints, "joints")
        assert (info.value.field, info.value.reason) == (field, reason)
        assert str(info.value).startswith("joints: ")
    with pytest.raises(InputError, match=r"^gt: missing value\(s\) for joint\(s\) \['turn'\]$"):
        check_joints(SPECS, {"slide": 0.0}, "gt", complete=True)
    with pytest.raises(InputError, match=r"^joints must be a mapping \{joint name: value\}, got list"):
        check_joints(SPECS, [("slide", 0.0)], "joints")


def test_numbers():
    assert check_number(np.int64(3), "t") == 3.0
    for bad in (math.nan, "1", True, None):
        with pytest.raises(InputError, match="^t must be a finite number"):
            check_number(bad, "t")


def test_the_depth_codec_saturates_and_round_trips():
    metres = np.array([0.0, 1e-5, 0.38, 0.3804, 65.535, 80.0, -1.0, np.nan, np.inf, -np.inf])
    assert depth_to_mm(metres).tolist() == [0, 1, 380, 380, DEPTH_MM_MAX, DEPTH_MM_MAX, 0, 0, 0, 0]
    mm = np.array([[0, 1, 380, DEPTH_MM_MAX]], np.uint16)
    assert np.array_equal(depth_to_mm(mm_to_depth(mm)), mm) and mm_to_depth(mm).dtype == np.float32


def test_the_service_request_options_are_the_core_options():
    """RefineOptions is built from EstimateOptions: the same types and choices, the core's defaults
    in the schema, and a value the core refuses is a 422 naming the option."""
    from narf_service import jobs
    from narf_service.engine import Engine
    from narf_service.errors import ApiError
    from narf_service.schemas import EstimateRequest, RefineOptions

    core = {f.name: f for f in dataclasses.fields(EstimateOptions)}
    schema = RefineOptions.model_json_schema()["properties"]
    assert set(schema) - {"preset"} <= set(core)
    assert {"lr_pose", "solver", "theta_starts", "uncertainty", "sigma_floor_joint"} <= set(schema)
    for name, spec in schema.items():
        assert spec["description"] and spec["default"] is None
        if name != "preset":
            assert "(paper: " in spec["description"] and str(core[name].default).lower() in spec["description"].lower()
    assert schema["solver"]["anyOf"][0]["enum"] == ["adam", "gauss-newton"]

    request = EstimateRequest.model_validate({
        "model": "toy", "camera": {"K": [[50, 0, 16], [0, 50, 12], [0, 0, 1]], "width": 32, "height": 24},
        "initial_pose": {"position": [0, 0, 0.5], "orientation": [0, 0, 0, 1]}, "options": {"lr_decay": 2.0},
    })
    with pytest.raises(ApiError) as info:
        jobs.refine_options(Engine.narf_core(), request, "request.options", depth=False)
    assert info.value.status_code == 422 and info.value.field == "request.options.lr_decay"
    assert info.value.message == "request.options.lr_decay: must be in (0, 1], got 2.0"
    ok = request.model_copy(update={"options": RefineOptions(preset="robust", lr_pose=0.05)})
    assert jobs.refine_options(Engine.narf_core(), ok, "request.options", depth=True) == (
        EstimateOptions.robust(lr_pose=0.05), "robust", "requested")
    auto = request.model_copy(update={"options": RefineOptions(lr_pose=0.05)})
    options, preset, _ = jobs.refine_options(Engine.narf_core(), auto, "request.options", depth=True)
    assert (options, preset) == (EstimateOptions.gauss_newton(lr_pose=0.05), "gauss-newton")


def test_option_types_are_checked_one_way_for_every_options_class():
    from narf_core.estimate import EstimateInputError, EstimateOptions
    from narf_core.track import TrackInputError, TrackOptions

    for options, error in ((EstimateOptions, EstimateInputError), (TrackOptions, TrackInputError)):
        with pytest.raises(error) as info:
            options(iterations=2.5)
        assert info.value.field == "options.iterations" and info.value.reason == "must be an integer, got 2.5"
        with pytest.raises(error) as info:
            options(lr_pose=math.nan)
        assert info.value.field == "options.lr_pose" and info.value.reason == "must be finite, got nan"
        with pytest.raises(error) as info:
            options(lr_theta=True)
        assert info.value.reason == "must be a number, got True"
