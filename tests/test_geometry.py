"""Tests for narf_core.geometry: every function, float32 and float64, batch shapes [], [5], [2, 3]."""

import math

import pytest
import torch

from narf_core.geometry import (
    Pinhole,
    Rays,
    axis_angle_to_quaternion,
    invert_pose,
    look_at,
    make_pose,
    matrix_to_quaternion,
    pose_from_position_quaternion,
    pose_to_position_quaternion,
    quaternion_to_axis_angle,
    quaternion_to_matrix,
    rotate_vectors,
    se3_exp,
    se3_log,
    skew,
    so3_exp,
    so3_log,
    transform_points,
)

SHAPES = [(), (5,), (2, 3)]
PI = math.pi
# Rotation angles where the maps switch formulas or lose conditioning.
EXTREME_ANGLES = [0.0, 1e-8, 1e-3, 1.0, PI - 1e-3, PI - 1e-6, PI]


def tol(dtype: torch.dtype) -> dict:
    return {"atol": 2e-5, "rtol": 1e-5} if dtype == torch.float32 else {"atol": 1e-11, "rtol": 1e-11}


def random_axis_angle(shape, dtype, max_angle=PI - 0.1, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(*shape, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(*shape, 1, generator=g, dtype=torch.float64) * max_angle
    return (axis * angle).to(dtype)


def random_pose(shape, dtype, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed + 1)
    t = torch.randn(*shape, 3, generator=g, dtype=torch.float64).to(dtype)
    return make_pose(so3_exp(random_axis_angle(shape, dtype, seed=seed)), t)


def axis_angle(angle: float, dtype, axis=(1.0, 2.0, -2.0)) -> torch.Tensor:
    a = torch.tensor(axis, dtype=torch.float64)
    return (a / a.norm() * angle).to(dtype)


def reference_so3_exp(omega: torch.Tensor) -> torch.Tensor:
    return torch.linalg.matrix_exp(skew(omega.double()))


def reference_se3_exp(xi: torch.Tensor) -> torch.Tensor:
    xi = xi.double()
    m = torch.zeros(*xi.shape[:-1], 4, 4, dtype=torch.float64)
    m[..., :3, :3] = skew(xi[..., 3:])
    m[..., :3, 3] = xi[..., :3]
    return torch.linalg.matrix_exp(m)


def assert_rotation(R: torch.Tensor, dtype) -> None:
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, **tol(dtype))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), **tol(dtype))


# --- skew -------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_skew_is_cross_product(shape, dtype):
    v, w = torch.randn(2, *shape, 3, dtype=dtype)
    out = skew(v)
    assert out.shape == (*shape, 3, 3) and out.dtype == dtype
    torch.testing.assert_close((out @ w[..., None])[..., 0], torch.linalg.cross(v, w), **tol(dtype))
    torch.testing.assert_close(out, -out.transpose(-1, -2))


# --- so3 --------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_so3_exp_matches_matrix_exponential(shape, dtype):
    omega = random_axis_angle(shape, dtype)
    R = so3_exp(omega)
    assert R.shape == (*shape, 3, 3) and R.dtype == dtype
    assert_rotation(R, dtype)
    torch.testing.assert_close(R, reference_so3_exp(omega).to(dtype), **tol(dtype))


def test_so3_exp_quarter_turn_about_z(dtype):
    R = so3_exp(torch.tensor([0.0, 0.0, PI / 2], dtype=dtype))
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
    torch.testing.assert_close(R, expected, **tol(dtype))


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_so3_exp_at_extreme_angles(angle, dtype):
    omega = axis_angle(angle, dtype)
    R = so3_exp(omega)
    assert_rotation(R, dtype)
    torch.testing.assert_close(R, reference_so3_exp(omega).to(dtype), **tol(dtype))


@pytest.mark.parametrize("shape", SHAPES)
def test_so3_log_inverts_exp(shape, dtype):
    omega = random_axis_angle(shape, dtype)
    out = so3_log(so3_exp(omega))
    assert out.shape == (*shape, 3) and out.dtype == dtype
    torch.testing.assert_close(out, omega, **tol(dtype))


@pytest.mark.parametrize("angle", [a for a in EXTREME_ANGLES if a < PI - 1e-4])
def test_so3_log_inverts_exp_at_extreme_angles(angle, dtype):
    omega = axis_angle(angle, dtype)
    torch.testing.assert_close(so3_log(so3_exp(omega)), omega, **tol(dtype))


@pytest.mark.parametrize("angle", [PI - 1e-6, PI])
def test_so3_log_near_pi_gives_the_same_rotation(angle, dtype):
    # Near pi the rotation determines the axis only up to sign once the angle is rounded to pi.
    R = so3_exp(axis_angle(angle, dtype))
    out = so3_log(R)
    assert out.norm() <= PI + 1e-6
    torch.testing.assert_close(out.norm(), torch.tensor(angle, dtype=dtype), atol=1e-5, rtol=0)
    torch.testing.assert_close(so3_exp(out), R, atol=1e-5, rtol=0)


def test_so3_log_of_exact_half_turns():
    for axis in torch.eye(3, dtype=torch.float64):
        R = torch.diag(2 * axis * axis - 1).requires_grad_()  # exactly pi about a coordinate axis
        out = so3_log(R)
        torch.testing.assert_close(out.detach().abs(), PI * axis)
        (g,) = torch.autograd.grad(out.sum(), R)
        assert torch.isfinite(g).all()


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_so3_gradients_finite(angle, dtype):
    omega = axis_angle(angle, dtype).requires_grad_()
    R = so3_exp(omega)
    (g_exp,) = torch.autograd.grad((R * torch.arange(9, dtype=dtype).reshape(3, 3)).sum(), omega)
    assert torch.isfinite(g_exp).all()
    R_leaf = R.detach().requires_grad_()
    out = so3_log(R_leaf)
    (g_log,) = torch.autograd.grad(out.sum(), R_leaf)
    assert torch.isfinite(out).all() and torch.isfinite(g_log).all()


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-3, 1.0, 2.5, PI - 1e-3])
def test_jacobian_of_log_exp_is_identity(angle):
    # d log(exp(w)) / dw = I for |w| < pi: checks the series branches' derivatives too.
    omega = axis_angle(angle, torch.float64)
    J = torch.autograd.functional.jacobian(lambda w: so3_log(so3_exp(w)), omega)
    torch.testing.assert_close(J, torch.eye(3, dtype=torch.float64), atol=1e-7, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-2, 1.0, PI - 1e-3])
def test_so3_exp_gradcheck(angle):
    omega = axis_angle(angle, torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(so3_exp, (omega,))


# --- quaternions ------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_quaternion_matrix_round_trip_and_sign(shape, dtype):
    R = so3_exp(random_axis_angle(shape, dtype, max_angle=PI))
    q = matrix_to_quaternion(R)
    assert q.shape == (*shape, 4) and q.dtype == dtype
    assert (q[..., 3] >= 0).all()
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(shape, dtype=dtype), **tol(dtype))
    torch.testing.assert_close(quaternion_to_matrix(q), R, **tol(dtype))


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_matrix_to_quaternion_at_extreme_angles(angle, dtype):
    omega = axis_angle(angle, dtype)
    q = matrix_to_quaternion(so3_exp(omega))
    assert q[3] >= 0
    expected = axis_angle_to_quaternion(omega.double()).to(dtype)
    if angle == PI:  # w = 0: q and -q are both valid
        expected = expected * torch.sign(expected[:3] @ q[:3])
    torch.testing.assert_close(q, expected, atol=1e-6 if dtype == torch.float32 else 1e-12, rtol=0)


def test_axis_angle_to_quaternion_closed_form(dtype):
    q = axis_angle_to_quaternion(torch.tensor([0.0, 0.0, PI / 2], dtype=dtype))
    s = math.sqrt(0.5)
    torch.testing.assert_close(q, torch.tensor([0.0, 0.0, s, s], dtype=dtype), **tol(dtype))
    assert axis_angle_to_quaternion(torch.zeros(3, dtype=dtype)).tolist() == [0.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize("shape", SHAPES)
def test_axis_angle_quaternion_round_trip(shape, dtype):
    omega = random_axis_angle(shape, dtype)
    q = axis_angle_to_quaternion(omega)
    assert q.shape == (*shape, 4) and q.dtype == dtype
    torch.testing.assert_close(quaternion_to_axis_angle(q), omega, **tol(dtype))
    torch.testing.assert_close(quaternion_to_matrix(q), so3_exp(omega), **tol(dtype))


def test_quaternion_to_axis_angle_picks_the_short_way(dtype):
    omega = axis_angle(1.0, dtype)
    q = axis_angle_to_quaternion(omega)
    torch.testing.assert_close(quaternion_to_axis_angle(-q), omega, **tol(dtype))


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_quaternion_axis_angle_gradients_finite(angle, dtype):
    omega = axis_angle(angle, dtype).requires_grad_()
    q = axis_angle_to_quaternion(omega)
    (g,) = torch.autograd.grad((q * torch.arange(1.0, 5.0, dtype=dtype)).sum(), omega)
    assert torch.isfinite(g).all()
    q_leaf = q.detach().requires_grad_()
    (g,) = torch.autograd.grad(quaternion_to_axis_angle(q_leaf).sum(), q_leaf)
    assert torch.isfinite(g).all()


def test_quaternion_to_matrix_normalises_and_ignores_sign(dtype):
    q = torch.tensor([0.1, -0.2, 0.3, 0.9], dtype=dtype)
    R = quaternion_to_matrix(q)
    assert_rotation(R, dtype)
    torch.testing.assert_close(quaternion_to_matrix(-3 * q), R, **tol(dtype))


# --- poses ------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_make_pose_layout(shape, dtype):
    R = so3_exp(random_axis_angle(shape, dtype))
    t = torch.randn(*shape, 3, dtype=dtype)
    T = make_pose(R, t)
    assert T.shape == (*shape, 4, 4) and T.dtype == dtype
    assert torch.equal(T[..., :3, :3], R) and torch.equal(T[..., :3, 3], t)
    assert T[..., 3, :].tolist() == torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(*shape, 4).tolist()


@pytest.mark.parametrize("shape", SHAPES)
def test_pose_position_quaternion_round_trip(shape, dtype):
    T = random_pose(shape, dtype)
    p, q = pose_to_position_quaternion(T)
    assert p.shape == (*shape, 3) and q.shape == (*shape, 4)
    assert (q[..., 3] >= 0).all()
    torch.testing.assert_close(pose_from_position_quaternion(p, q), T, **tol(dtype))


@pytest.mark.parametrize("shape", SHAPES)
def test_invert_pose(shape, dtype):
    T = random_pose(shape, dtype)
    eye = torch.eye(4, dtype=dtype).expand(*shape, 4, 4)
    torch.testing.assert_close(T @ invert_pose(T), eye, **tol(dtype))
    torch.testing.assert_close(invert_pose(T) @ T, eye, **tol(dtype))
    torch.testing.assert_close(invert_pose(T), torch.linalg.inv(T), **tol(dtype))


@pytest.mark.parametrize("shape", SHAPES)
def test_transform_points_and_rotate_vectors(shape, dtype):
    T = random_pose(shape, dtype)
    x = torch.randn(*shape, 3, dtype=dtype)
    homog = (T @ torch.cat([x, torch.ones(*shape, 1, dtype=dtype)], -1)[..., None])[..., :3, 0]
    torch.testing.assert_close(transform_points(T, x), homog, **tol(dtype))
    torch.testing.assert_close(rotate_vectors(T, x), (T[..., :3, :3] @ x[..., None])[..., 0])
    torch.testing.assert_close(rotate_vectors(T[..., :3, :3], x), rotate_vectors(T, x))


def test_transform_points_broadcasts_one_pose_over_points(dtype):
    T = random_pose((), dtype)
    x = torch.randn(7, 3, dtype=dtype)
    out = transform_points(T, x)
    assert out.shape == (7, 3)
    torch.testing.assert_close(out[4], transform_points(T, x[4]))


def test_pure_translation(dtype):
    T = make_pose(torch.eye(3, dtype=dtype), torch.tensor([0.01, 0.0, 0.0], dtype=dtype))
    out = transform_points(T, torch.zeros(3, dtype=dtype))
    assert out.tolist() == pytest.approx([0.01, 0.0, 0.0])
    assert rotate_vectors(T, torch.tensor([1.0, 2.0, 3.0], dtype=dtype)).tolist() == [1.0, 2.0, 3.0]


# --- se3 --------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_se3_exp_matches_matrix_exponential(shape, dtype):
    xi = torch.cat([torch.randn(*shape, 3, dtype=dtype), random_axis_angle(shape, dtype)], -1)
    T = se3_exp(xi)
    assert T.shape == (*shape, 4, 4) and T.dtype == dtype
    torch.testing.assert_close(T, reference_se3_exp(xi).to(dtype), **tol(dtype))


@pytest.mark.parametrize("shape", SHAPES)
def test_se3_log_inverts_exp(shape, dtype):
    xi = torch.cat([torch.randn(*shape, 3, dtype=dtype), random_axis_angle(shape, dtype)], -1)
    out = se3_log(se3_exp(xi))
    assert out.shape == (*shape, 6) and out.dtype == dtype
    torch.testing.assert_close(out, xi, **tol(dtype))


def test_se3_exp_of_pure_translation(dtype):
    xi = torch.tensor([0.1, -0.2, 0.3, 0.0, 0.0, 0.0], dtype=dtype)
    expected = make_pose(torch.eye(3, dtype=dtype), xi[:3])
    torch.testing.assert_close(se3_exp(xi), expected)


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_se3_at_extreme_angles(angle, dtype):
    xi = torch.cat([torch.tensor([0.3, -0.1, 0.2], dtype=dtype), axis_angle(angle, dtype)]).requires_grad_()
    T = se3_exp(xi)
    torch.testing.assert_close(T, reference_se3_exp(xi.detach()).to(dtype), **tol(dtype))
    (g,) = torch.autograd.grad(T.sum(), xi)
    assert torch.isfinite(g).all()
    T_leaf = T.detach().requires_grad_()
    out = se3_log(T_leaf)
    (g,) = torch.autograd.grad(out.sum(), T_leaf)
    assert torch.isfinite(out).all() and torch.isfinite(g).all()
    torch.testing.assert_close(se3_exp(out), T.detach(), atol=1e-5 if dtype == torch.float32 else 1e-9, rtol=0)
    if angle < PI - 1e-4:
        torch.testing.assert_close(out, xi.detach(), atol=1e-5 if dtype == torch.float32 else 1e-9, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-2, 1.0, PI - 1e-3])
def test_se3_gradcheck(angle):
    xi = torch.cat([torch.tensor([0.3, -0.1, 0.2], dtype=torch.float64), axis_angle(angle, torch.float64)])
    assert torch.autograd.gradcheck(se3_exp, (xi.requires_grad_(),))
    J = torch.autograd.functional.jacobian(lambda x: se3_log(se3_exp(x)), xi.detach())
    torch.testing.assert_close(J, torch.eye(6, dtype=torch.float64), atol=1e-7, rtol=0)


# --- look_at ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "eye", [(2.0, 0.0, 0.0), (0.3, -1.0, 0.5), (-1.0, -1.0, -1.0), (0.0, 0.05, 3.0)]
)
def test_look_at_sees_target_upright(eye, dtype):
    eye_t = torch.tensor(eye, dtype=dtype)
    target = torch.tensor([0.1, 0.2, -0.1], dtype=dtype)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    T_world_cam = look_at(eye_t, target, up)
    assert T_world_cam.dtype == dtype
    assert_rotation(T_world_cam[:3, :3], dtype)
    T_cam_world = invert_pose(T_world_cam)
    p = transform_points(T_cam_world, target)
    distance = (target - eye_t).norm()
    torch.testing.assert_close(p, torch.stack([p.new_zeros(()), p.new_zeros(()), distance]), **tol(dtype))
    cam = Pinhole.primesense(64, 48, dtype=dtype)
    centre, _ = cam.project(p)
    above, _ = cam.project(transform_points(T_cam_world, target + 0.1 * up))
    right, _ = cam.project(transform_points(T_cam_world, target + 0.1 * torch.linalg.cross(target - eye_t, up)))
    assert above[1] < centre[1]  # world up is image up (smaller v)
    assert right[0] > centre[0]  # looking along d with z up, d x up points to the image's right
    torch.testing.assert_close(above[0], centre[0], **tol(dtype))


@pytest.mark.parametrize("shape", SHAPES)
def test_look_at_batches(shape, dtype):
    eye = torch.randn(*shape, 3, dtype=dtype) + torch.tensor([0.0, 0.0, 3.0], dtype=dtype)
    target = torch.zeros(*shape, 3, dtype=dtype)
    T = look_at(eye, target, torch.tensor([0.0, 1.0, 0.0], dtype=dtype))
    assert T.shape == (*shape, 4, 4)
    z = T[..., :3, 2]
    torch.testing.assert_close(z, (target - eye) / (target - eye).norm(dim=-1, keepdim=True), **tol(dtype))
    torch.testing.assert_close(T[..., :3, 3], eye)


# --- Pinhole and Rays -------------------------------------------------------------------------


def make_camera(dtype, skew_term=0.0) -> Pinhole:
    K = torch.tensor([[50.0, skew_term, 13.0], [0.0, 80.0, 7.5], [0.0, 0.0, 1.0]], dtype=dtype)
    return Pinhole(K, width=20, height=12)


def test_pinhole_rejects_bad_input():
    with pytest.raises(ValueError, match="image size must be positive, got 0x4"):
        Pinhole(torch.eye(3), 0, 4)
    with pytest.raises(ValueError, match=r"K must be 3x3, got shape \(3, 4\)"):
        Pinhole(torch.zeros(3, 4), 4, 4)


def test_primesense_and_scaled():
    cam = Pinhole.primesense(640, 480)
    assert cam.K.tolist() == [[536.5, 0.0, 320.0], [0.0, 536.5, 240.0], [0.0, 0.0, 1.0]]
    small = cam.scaled(64, 48)
    assert (small.width, small.height) == (64, 48)
    torch.testing.assert_close(small.K, torch.tensor([[53.65, 0.0, 32.0], [0.0, 53.65, 24.0], [0.0, 0.0, 1.0]]))
    assert cam.K[0, 0] == 536.5  # scaled() does not touch the original


def test_pixel_grid_is_row_major():
    grid = Pinhole.primesense(3, 2).pixel_grid()
    assert grid.tolist() == [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]]


def test_ray_through_pixel_centre(dtype):
    cam = make_camera(dtype)
    rays = cam.rays(torch.tensor([[0, 0], [12, 7]]))
    # pixel (0, 0) has its centre at (0.5, 0.5): x = (0.5 - 13) / 50, y = (0.5 - 7.5) / 80
    d0 = torch.tensor([(0.5 - 13.0) / 50.0, (0.5 - 7.5) / 80.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(rays.directions[0], (d0 / d0.norm()).to(dtype), **tol(dtype))
    # pixel (12, 7) has its centre at (12.5, 7.5): half a pixel left of the principal point, y = 0
    expected = torch.tensor([-0.5 / 50.0, 0.0, 1.0], dtype=dtype) / math.hypot(0.01, 1)
    torch.testing.assert_close(rays.directions[1], expected, **tol(dtype))
    assert rays.origins.abs().max() == 0
    assert rays.directions.dtype == dtype and rays.z_per_t.dtype == dtype


@pytest.mark.parametrize("skew_term", [0.0, 3.0])
def test_project_returns_pixel_centres(dtype, skew_term):
    cam = make_camera(dtype, skew_term)
    rays = cam.rays()
    assert len(rays) == 20 * 12
    torch.testing.assert_close(rays.directions.norm(dim=-1), torch.ones(240, dtype=dtype), **tol(dtype))
    t = torch.linspace(0.1, 5.0, 240, dtype=dtype)
    points = rays.origins + t[:, None] * rays.directions
    uv, z = cam.project(points)
    torch.testing.assert_close(uv, cam.pixel_grid().to(dtype) + 0.5, atol=1e-4 if dtype == torch.float32 else 1e-10, rtol=0)
    torch.testing.assert_close(z, t * rays.z_per_t, **tol(dtype))  # z-depth = t * z_per_t


def test_z_per_t_is_cosine_to_optical_axis(dtype):
    rays = make_camera(dtype).rays()
    torch.testing.assert_close(rays.z_per_t, rays.directions[:, 2])
    assert (rays.z_per_t > 0).all() and (rays.z_per_t <= 1).all()


def test_project_batches(dtype):
    cam = make_camera(dtype)
    points = torch.tensor([0.0, 0.0, 2.0], dtype=dtype).expand(2, 3, 3)
    uv, z = cam.project(points)
    assert uv.shape == (2, 3, 2) and z.shape == (2, 3)
    torch.testing.assert_close(uv[1, 2], torch.tensor([13.0, 7.5], dtype=dtype))


def test_rays_indexing_and_transform(dtype):
    cam = make_camera(dtype)
    rays = cam.rays()
    sub = rays[torch.tensor([3, 5])]
    assert isinstance(sub, Rays) and len(sub) == 2
    torch.testing.assert_close(sub.directions[1], rays.directions[5])
    T_world_cam = random_pose((), dtype)
    moved = sub.transform(T_world_cam)
    point_cam = sub.origins + 2.0 * sub.directions
    torch.testing.assert_close(moved.origins + 2.0 * moved.directions, transform_points(T_world_cam, point_cam), **tol(dtype))
    assert torch.equal(moved.z_per_t, sub.z_per_t)
    per_ray = sub.transform(torch.stack([T_world_cam, torch.eye(4, dtype=dtype)]))
    torch.testing.assert_close(per_ray.directions[0], moved.directions[0])
    torch.testing.assert_close(per_ray.directions[1], sub.directions[1])
