"""A joint whose part another part of the object hides (a drawer behind an open door; issue #11): the share of
its surface points the mask shows counts only the points no other link hides (``band.hidden_points``), so the
view's σ of it is its prior's and the estimate says it is unobserved; on the bundled clamp, looked at along its
bar from the fixed jaw's side, where the fixed jaw covers the moving one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from narf_core.band import hidden_points, point_spacing, surface_points
from narf_core.estimate import (
    HIDDEN_SHARE,
    UNOBSERVED_CODE,
    EstimateOptions,
    _observation,
    joint_mask_shares,
    refine,
)
from narf_core.geometry import Pinhole

CLAMP = Path(__file__).resolve().parents[1] / "models" / "clamp.narf"
CAMERA = Pinhole.primesense(160, 120)
THETA = {"jaw_opening": 0.1}


@pytest.fixture(scope="module")
def clamp():
    from narf_core.bundle import load_bundle

    return load_bundle(CLAMP)


def looking(centre, direction, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """``T_cam_obj [4,4]`` of a camera at ``centre`` (object frame) looking along ``direction``."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ np.asarray(centre, float)
    return T


# Along the bar (+x) from beyond the fixed jaw, which is taller and thicker than the moving jaw: the moving jaw is
# wholly behind it. From the side both jaws show.
ALONG_BAR = looking((-0.6, -0.05, 0.0), (1.0, 0.0, 0.0))
SIDE = looking((0.08, -0.05, 0.6), (0.0, 0.0, -1.0))


def rendered(model, T: np.ndarray) -> dict[str, np.ndarray]:
    """The model's own rgb (uint8), depth (0 = none) and mask (opacity over 0.5) at ``T`` and :data:`THETA`."""
    out = model.render(torch.as_tensor(T, dtype=torch.float32), model.joint_vector(THETA), CAMERA,
                       outputs=("rgb", "depth", "opacity"))
    mask = out["opacity"].cpu().numpy() > 0.5
    depth = np.where(mask, out["depth"].cpu().numpy(), 0.0).astype(np.float32)
    rgb = (out["rgb"].cpu().numpy().clip(0, 1) * 255).astype(np.uint8)
    return {"rgb": rgb, "depth": depth, "mask": mask}


def grid(z: float, half: float, n: int = 21) -> torch.Tensor:
    """``[n*n, 3]`` points of a square of side ``2 half`` at camera depth ``z``, centred on the optical axis."""
    s = torch.linspace(-half, half, n, dtype=torch.float64)
    u, v = torch.meshgrid(s, s, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1), torch.full((n * n,), z, dtype=torch.float64)], -1)


def test_hidden_points_are_those_with_an_occluder_nearer_in_their_cell():
    """A small square 10 cm in front of a larger one hides the larger one's points behind it, not those around
    it; the small square's own points are hidden by nothing of their own set; points beside the occluder at its
    depth (closer than the spacing) are not hidden; nothing hides where the occluders are none."""
    near, far = grid(0.5, 0.02, 11), grid(0.6, 0.06, 31)  # 4 mm spacing on both
    points = torch.cat([near, far])
    occluders = torch.stack([torch.arange(len(points)) < len(near), torch.zeros(len(points), dtype=torch.bool)])
    hidden = hidden_points(points, CAMERA, 0.004, occluders)
    behind = far[:, :2].abs().max(1).values * 0.5 / 0.6 < 0.02 - 0.004  # well inside the near square's shadow
    beside = far[:, :2].abs().max(1).values * 0.5 / 0.6 > 0.02 + 0.008  # well outside it
    assert hidden[0, len(near):][behind].all() and behind.sum() > 50
    assert not hidden[0, len(near):][beside].any() and beside.sum() > 300
    assert not hidden[0, : len(near)].any()
    assert not hidden[1].any()
    flat = torch.cat([grid(0.5, 0.02, 11), grid(0.5 + 0.002, 0.02, 11) + torch.tensor([0.001, 0.0, 0.0])])
    same = hidden_points(flat, CAMERA, 0.004, torch.stack([torch.arange(len(flat)) < 121]))
    assert not same.any()  # 2 mm behind: the same surface, not an occluder


def test_hidden_points_skip_points_behind_the_camera():
    points = torch.cat([grid(0.5, 0.02, 5), grid(-0.5, 0.02, 5)])
    occluders = torch.ones(1, len(points), dtype=torch.bool)
    assert not hidden_points(points, CAMERA, 0.004, occluders).any()


def test_a_joint_whose_part_another_part_hides_shows_nothing_of_it_to_the_mask(clamp):
    """Along the bar the moving jaw's surface points all project inside the mask (the fixed jaw's outline), which
    the share counted before; the fixed jaw hides them, so the share is 0. From the side it is nearly one."""
    theta = clamp.joint_vector(THETA)
    shares = {}
    for name, T in (("along", ALONG_BAR), ("side", SIDE)):
        view = rendered(clamp, T)
        obs = _observation(view["rgb"], view["mask"], None, (0, 0, 160, 120), 1, "cpu")
        shares[name] = float(joint_mask_shares(clamp, CAMERA, torch.as_tensor(T, dtype=torch.float32), theta, obs)[0])
        if name == "along":
            xyz = surface_points(clamp, torch.as_tensor(T)[None], theta[None])[0]
            moved = clamp.kinematics.moved_points(clamp.sample_points, theta)[0]
            uv, _ = CAMERA.project(xyz[moved].float())
            col, row = uv[:, 0].long().clamp(0, 159), uv[:, 1].long().clamp(0, 119)
            assert view["mask"][row.numpy(), col.numpy()].mean() > 0.9  # inside the outline: no help there
            hidden = hidden_points(xyz, CAMERA, point_spacing(clamp), ~moved[None])[0]
            assert hidden[moved].all()
    assert shares["along"] == 0.0
    assert shares["side"] > 0.8


def test_the_estimate_says_the_hidden_joint_is_unobserved(clamp):
    """Refined at the view along the bar (the model's own render: rgb, depth, mask), the jaw's σ is at least its
    half range and the warning says another part may hide it; from the side neither."""
    half = float(clamp.kinematics.upper[0] - clamp.kinematics.lower[0]) / 2
    options = EstimateOptions.preset("gauss-newton", iterations=2, rays_per_iteration=128, uncertainty_rays=256)
    for T, hidden in ((ALONG_BAR, True), (SIDE, False)):
        view = rendered(clamp, T)
        result = refine(clamp, view["rgb"], view["mask"], CAMERA, T, joints_init=THETA, depth=view["depth"],
                        options=options)
        sigma = result.uncertainty.joint_sigma["jaw_opening"]
        warned = [w for w in result.warnings if w.startswith(f"{UNOBSERVED_CODE}: jaw_opening")]
        assert (sigma >= half) == hidden, sigma
        assert (result.uncertainty.unseen_variance[6] == pytest.approx(half**2)) == hidden
        if hidden:
            assert len(warned) == 1 and "another part hides it" in warned[0], warned
            assert f"under {HIDDEN_SHARE:.0%}" in warned[0]
        else:
            assert warned == []
