"""Tests for narf_core.metrics on hand-computed cases."""

import math
import sys

import numpy as np
import pytest
import torch

from narf_core.diameter import object_diameter
from narf_core.metrics import (
    _nearest_distances,
    add,
    add_s,
    joint_errors,
    mse,
    psnr_from_mse,
    success_rates,
)

EYE = np.eye(4)


def translation(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def rotation_z(angle: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    return T


# --- images -------------------------------------------------------------------------------------


def test_mse_by_hand():
    pred = np.zeros((2, 2, 3))
    target = np.zeros((2, 2, 3))
    target[0, 0] = [0.5, 0.5, 0.5]  # one pixel off by 0.5 in every channel
    assert mse(pred, target) == pytest.approx(0.25 / 4)
    mask = np.array([[True, False], [False, False]])
    assert mse(pred, target, mask) == pytest.approx(0.25)
    assert mse(pred, target, ~mask) == 0.0
    assert mse(pred, target, np.array([[255, 0], [0, 0]], dtype=np.uint8)) == pytest.approx(0.25)  # non-zero selects


def test_mse_takes_torch_and_a_channel_mask(dtype):
    pred = torch.zeros(4, 3, dtype=dtype, requires_grad=True)
    target = torch.ones(4, 3, dtype=dtype)
    mask = torch.zeros(4, 3, dtype=torch.bool)
    mask[0, 0] = True
    assert mse(pred, target, mask) == 1.0
    assert mse(pred, target) == 1.0 and isinstance(mse(pred, target), float)


def test_mse_rejects():
    with pytest.raises(ValueError, match=r"same shape, got \[2, 3\] and \[3, 3\]"):
        mse(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"mask must have shape \[2\] or \[2, 3\], got \[3\]"):
        mse(np.zeros((2, 3)), np.zeros((2, 3)), np.ones(3))
    with pytest.raises(ValueError, match="mask selects no pixels"):
        mse(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2))


def test_psnr_from_mse():
    assert psnr_from_mse(0.01) == pytest.approx(20.0)
    assert psnr_from_mse(1.0) == 0.0
    assert psnr_from_mse(0.0) == math.inf
    np.testing.assert_allclose(psnr_from_mse(np.array([1e-3, 1e-4])), [30.0, 40.0])
    assert psnr_from_mse(torch.tensor(0.1)) == pytest.approx(10.0)
    with pytest.raises(ValueError, match="mse must be >= 0 and not NaN"):
        psnr_from_mse(-1e-3)
    with pytest.raises(ValueError, match="mse must be >= 0 and not NaN"):
        psnr_from_mse(float("nan"))


# --- ADD / ADD-S --------------------------------------------------------------------------------

LINKS = ["base", "finger"]
POINTS = {"base": np.array([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]), "finger": np.array([[0.0, 0.05, 0.0]])}


def test_add_of_a_pure_translation():
    poses = np.stack([EYE, translation(0.0, 0.1)])
    assert add(POINTS, poses, EYE, poses, translation(0.0, 0.0, 0.01), LINKS) == pytest.approx(0.01, abs=1e-15)
    assert add(POINTS, poses, EYE, poses, EYE, LINKS) == 0.0


def test_add_of_a_half_turn():
    # 180 deg about z through the origin: (0.1, 0, 0) <-> (-0.1, 0, 0) swap (0.2 each), and the
    # finger point at (0, 0.15, 0) in the object frame goes to (0, -0.15, 0) (0.3).
    poses = np.stack([EYE, translation(0.0, 0.1)])
    value = add(POINTS, poses, EYE, poses, rotation_z(math.pi), LINKS)
    assert value == pytest.approx((0.2 + 0.2 + 0.3) / 3)
    # ADD-S: the base points map onto each other; the finger point's nearest is a base point.
    assert add_s(POINTS, poses, EYE, poses, rotation_z(math.pi), LINKS) == pytest.approx(
        (0.0 + 0.0 + math.hypot(0.1, 0.15)) / 3
    )


def test_add_moves_points_by_fk():
    # Only the finger's FK pose differs (1 cm along x): 1 of 3 points is off by 1 cm.
    true = np.stack([EYE, translation(0.0, 0.1)])
    est = np.stack([EYE, translation(0.01, 0.1)])
    assert add(POINTS, true, EYE, est, EYE, LINKS) == pytest.approx(0.01 / 3)
    assert add({"finger": POINTS["finger"]}, true, EYE, est, EYE, LINKS) == pytest.approx(0.01)


def test_add_s_of_a_symmetric_set_under_its_symmetry_is_zero():
    square = {"base": np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]])}
    poses = EYE[None]
    T = translation(0.2, 0.0, 1.0)
    assert add_s(square, poses, T, poses, T @ rotation_z(math.pi / 2), ["base"]) == pytest.approx(0.0, abs=1e-15)
    assert add(square, poses, T, poses, T @ rotation_z(math.pi / 2), ["base"]) == pytest.approx(math.sqrt(2))


def test_add_takes_torch():
    poses = torch.stack([torch.eye(4, dtype=torch.float64), torch.tensor(translation(0.0, 0.1))])
    value = add({k: torch.tensor(v) for k, v in POINTS.items()}, poses, torch.eye(4), poses, torch.tensor(translation(0, 0, 0.01)), LINKS)
    assert value == pytest.approx(0.01)


def test_add_rejects():
    poses = np.stack([EYE, EYE])
    with pytest.raises(ValueError, match=r"points_per_link has link 'thumb', which is not in links \['base', 'finger'\]"):
        add({"thumb": np.zeros((1, 3))}, poses, EYE, poses, EYE, LINKS)
    with pytest.raises(ValueError, match=r"link_poses_est must have shape \[2, 4, 4\] \(one per link\), got \[1, 4, 4\]"):
        add(POINTS, poses, EYE, poses[:1], EYE, LINKS)
    with pytest.raises(ValueError, match=r"T_cam_obj_true must be a 4x4 pose matrix, got shape \(3, 4\)"):
        add_s(POINTS, poses, EYE[:3], poses, EYE, LINKS)
    with pytest.raises(ValueError, match=r"points_per_link\['base'\] must have shape \[n, 3\], got \[3\]"):
        add({"base": np.zeros(3)}, poses, EYE, poses, EYE, LINKS)
    with pytest.raises(ValueError, match="T_cam_obj_est has a rotation block that is not orthonormal"):
        add(POINTS, poses, EYE, poses, np.diag([2.0, 1.0, 1.0, 1.0]), LINKS)
    with pytest.raises(ValueError, match="points_per_link holds no points"):
        add({}, poses, EYE, poses, EYE, LINKS)


def test_nearest_distances_without_scipy(monkeypatch):
    rng = np.random.default_rng(0)
    queries, points = rng.normal(size=(300, 3)), rng.normal(size=(200, 3))
    expected = np.sqrt(((queries[:, None] - points[None]) ** 2).sum(-1)).min(1)
    np.testing.assert_allclose(_nearest_distances(queries, points), expected, atol=1e-12)
    monkeypatch.setitem(sys.modules, "scipy.spatial", None)  # import fails: the brute-force path
    monkeypatch.setattr("narf_core.metrics.PAIRWISE_BLOCK", 1000)  # and several blocks of queries
    np.testing.assert_allclose(_nearest_distances(queries, points), expected, atol=1e-12)
    assert _nearest_distances(points, points).max() == 0.0


# --- configuration and summary ------------------------------------------------------------------


def test_joint_errors():
    types = ["revolute", "prismatic", "continuous", "continuous", "continuous"]
    true = np.array([0.5, 0.01, 3.1, -math.pi, 0.2])
    est = np.array([-0.5, 0.03, -3.1, math.pi, 0.2 + 4 * math.pi + 0.1])
    errors = joint_errors(true, est, types)
    np.testing.assert_allclose(errors, [1.0, 0.02, 2 * math.pi - 6.2, 0.0, 0.1], atol=1e-12)
    batch = joint_errors(np.zeros((4, 2)), np.full((4, 2), 2 * math.pi - 0.1), ["revolute", "continuous"])
    np.testing.assert_allclose(batch, np.tile([2 * math.pi - 0.1, 0.1], (4, 1)), atol=1e-12)
    assert joint_errors(np.zeros(1), np.array([math.pi]), ["continuous"])[0] == pytest.approx(math.pi)


def test_joint_errors_rejects():
    with pytest.raises(ValueError, match=r"shape \[\.\.\., 2\] .* got \[3\] and \[3\]"):
        joint_errors(np.zeros(3), np.zeros(3), ["revolute", "prismatic"])
    with pytest.raises(ValueError, match=r"joint_types must be revolute, continuous or prismatic, got \['fixed'\]"):
        joint_errors(np.zeros(1), np.zeros(1), ["fixed"])


def test_success_rates():
    rates = success_rates([0.001, 0.009, 0.01, 0.02], diameter=0.15)  # 0.1 d = 1.5 cm
    assert rates == {"add<1cm": 0.5, "add<0.1d": 0.75}
    with pytest.raises(ValueError, match="add_values is empty"):
        success_rates([], 0.1)
    with pytest.raises(ValueError, match="diameter must be a positive number of metres, got 0"):
        success_rates([0.1], 0)
    with pytest.raises(ValueError, match="add_values must be finite"):
        success_rates([float("nan")], 0.1)


def test_object_diameter_exact():
    assert object_diameter(np.array([[0.0, 0, 0]])) == 0.0
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 2) for z in (0, 3)], dtype=float)
    assert object_diameter(cube) == pytest.approx(math.sqrt(14), rel=1e-15)
    far = cube * 0.01 + 1000.0  # a small object far from the origin keeps its precision
    assert object_diameter(far) == pytest.approx(0.01 * math.sqrt(14), rel=1e-9)
    assert object_diameter(torch.tensor(cube)) == pytest.approx(math.sqrt(14))
    with pytest.raises(ValueError, match="points is empty"):
        object_diameter(np.zeros((0, 3)))


@pytest.mark.parametrize("with_scipy", [True, False])
def test_object_diameter_large_sets(monkeypatch, with_scipy):
    if not with_scipy:
        monkeypatch.setitem(sys.modules, "scipy.spatial", None)
    rng = np.random.default_rng(0)
    ball = rng.normal(size=(6000, 3)) * [0.1, 0.05, 0.02]
    ball[17], ball[4242] = [0.6, 0.0, 0.0], [-0.6, 0.0, 0.0]  # a known diameter of 1.2 dominates
    assert object_diameter(ball) == pytest.approx(1.2, rel=1e-12)
    sphere = rng.normal(size=(6000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)  # every point on the hull
    assert 2 * math.cos(0.078) <= object_diameter(sphere) <= 2.0
