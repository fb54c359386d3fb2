"""Tests for narf_core.kinematics: URDF parsing, FK against pybullet and by hand, parts, limits, meshes."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from narf_core.geometry import invert_pose, pose_from_position_quaternion
from narf_core.checks import InputError
from narf_core.checks import LIMIT_TOLERANCE
from narf_core.kinematics import MAX_JOINTS, KinematicTree, UrdfError

pybullet = pytest.importorskip("pybullet")

# Two joints whose poses are easy to work out by hand: a hinge about z one metre out along x,
# then a slide along the hinged link's x.
TWO_JOINTS = """<robot name="two">
  <link name="root"/>
  <link name="a"><visual><geometry><box size="1 2 4"/></geometry></visual></link>
  <link name="b"/>
  <joint name="hinge" type="revolute">
    <parent link="root"/><child link="a"/><origin xyz="1 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="slide" type="prismatic">
    <parent link="a"/><child link="b"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.5" effort="1" velocity="1"/>
  </joint>
</robot>"""


def urdf_with(joint_xml: str, links: str = '<link name="root"/><link name="a"/>') -> str:
    return f'<robot name="bad">{links}{joint_xml}</robot>'


@pytest.fixture(scope="module")
def tree(assets) -> KinematicTree:
    return KinematicTree.from_urdf(assets / "articulated.urdf")


def random_theta(tree: KinematicTree, n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return tree.lower + (tree.upper - tree.lower) * torch.rand(n, tree.n_joints, generator=g, dtype=torch.float64)


def rot_x(a):
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def rot_y(a):
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def rot_z(a):
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


# --- structure ----------------------------------------------------------------------------------


def test_tree_structure(tree):
    assert tree.root == "base"
    assert tree.links == ["base", "wheel", "arm", "slider", "tip", "cap", "plate"]
    assert [j.child for j in tree.joints] == tree.links[1:]
    assert {j.name for j in tree.joints} == {"spin", "slide", "tip_cap", "hinge", "tip_mount", "base_plate"}
    assert tree.joint_names == ["spin", "slide", "hinge"]  # file order, not tree order
    assert [j.name for j in tree.movable] == tree.joint_names
    assert tree.lower.tolist() == [-math.pi, -0.02, -1.2] and tree.upper.tolist() == [math.pi, 0.05, 0.9]
    assert tree.lower.dtype == torch.float64
    assert tree.parts == [["base", "plate"], ["wheel"], ["arm"], ["slider", "tip", "cap"]]
    assert tree.part_names == ["base", "wheel", "arm", "slider"]
    assert tree.part_of_link == [0, 1, 2, 3, 3, 3, 0]


def test_joint_fields(tree):
    hinge = next(j for j in tree.joints if j.name == "hinge")
    assert (hinge.type, hinge.parent, hinge.child, hinge.lower, hinge.upper) == ("revolute", "base", "arm", -1.2, 0.9)
    np.testing.assert_allclose(hinge.axis, [0.6, 0.0, 0.8])
    fixed = next(j for j in tree.joints if j.name == "tip_cap")
    assert (fixed.lower, fixed.upper) == (0.0, 0.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        hinge.lower = 0.0
    with pytest.raises(ValueError, match="read-only"):
        hinge.origin[0, 3] = 1.0


def test_joint_origin_is_fixed_axis_rpy(tree):
    hinge = next(j for j in tree.joints if j.name == "hinge")  # xyz="0.05 0 0.03" rpy="0.3 -0.2 0.5"
    np.testing.assert_allclose(hinge.origin[:3, :3], rot_z(0.5) @ rot_y(-0.2) @ rot_x(0.3), atol=1e-15)
    np.testing.assert_allclose(hinge.origin[:3, 3], [0.05, 0.0, 0.03])
    np.testing.assert_allclose(hinge.origin[3], [0, 0, 0, 1])


# --- forward kinematics -------------------------------------------------------------------------


def test_fk_by_hand():
    tree = KinematicTree.from_urdf_string(TWO_JOINTS)
    poses = tree.link_poses(torch.tensor([math.pi / 2, 0.5], dtype=torch.float64))
    expected_a = np.array([[0, -1, 0, 1], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
    np.testing.assert_allclose(poses[0].numpy(), np.eye(4))
    np.testing.assert_allclose(poses[1].numpy(), expected_a, atol=1e-15)
    expected_b = expected_a.copy()
    expected_b[:3, 3] = [1.0, 0.5, 0.0]  # slid 0.5 along a's x, which points along the root's y
    np.testing.assert_allclose(poses[2].numpy(), expected_b, atol=1e-15)


@pytest.fixture(scope="module")
def bullet():
    client = pybullet.connect(pybullet.DIRECT)
    yield client
    pybullet.disconnect(client)


def pybullet_link_poses(client: int, path, tree: KinematicTree, theta: torch.Tensor) -> torch.Tensor:
    """``T_base_link [n_links, 4, 4]`` from pybullet, with the base placed off the origin on purpose."""
    orientation = pybullet.getQuaternionFromEuler([0.3, 0.2, -1.0])
    body = pybullet.loadURDF(str(path), [0.3, -0.2, 0.5], orientation, useFixedBase=True, physicsClientId=client)
    try:
        infos = [pybullet.getJointInfo(body, i, physicsClientId=client) for i in range(pybullet.getNumJoints(body, physicsClientId=client))]
        joint_index = {info[1].decode(): info[0] for info in infos}  # by name: indices count fixed joints too
        link_index = {info[12].decode(): info[0] for info in infos}
        for name, value in zip(tree.joint_names, theta.tolist()):
            pybullet.resetJointState(body, joint_index[name], value, physicsClientId=client)

        def pose(position, quaternion):
            return pose_from_position_quaternion(torch.tensor(position, dtype=torch.float64), torch.tensor(quaternion, dtype=torch.float64))

        # the base pose pybullet reports is its inertial frame: undo the URDF's <inertial><origin>
        position, quaternion = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)
        local_inertial = pybullet.getDynamicsInfo(body, -1, physicsClientId=client)[3:5]
        T_world_base = pose(position, quaternion) @ invert_pose(pose(*local_inertial))
        T_base_world = invert_pose(T_world_base)
        out = []
        for name in tree.links:
            if name == tree.root:
                out.append(torch.eye(4, dtype=torch.float64))
                continue
            state = pybullet.getLinkState(body, link_index[name], computeForwardKinematics=True, physicsClientId=client)
            out.append(T_base_world @ pose(state[4], state[5]))  # link frame, not the inertial frame
        return torch.stack(out)
    finally:
        pybullet.removeBody(body, physicsClientId=client)


def test_fk_matches_pybullet(tree, assets, bullet):
    corners = torch.tensor(list(zip(tree.lower.tolist(), tree.upper.tolist())), dtype=torch.float64)
    thetas = torch.cat([random_theta(tree, 12), corners.T, tree.mid_configuration()[None]])
    ours = tree.link_poses(thetas)
    worst = 0.0
    for theta, poses in zip(thetas, ours):
        reference = pybullet_link_poses(bullet, assets / "articulated.urdf", tree, theta)
        worst = max(worst, (reference - poses).abs().max().item())
    assert worst < 1e-6, f"FK differs from pybullet by {worst:.3g}"


@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_link_poses_batch_and_dtype(tree, dtype, shape):
    theta64 = random_theta(tree, math.prod(shape), seed=1).reshape(*shape, tree.n_joints)
    poses = tree.link_poses(theta64.to(dtype))
    assert poses.shape == (*shape, len(tree.links), 4, 4) and poses.dtype == dtype
    reference = tree.link_poses(theta64)
    torch.testing.assert_close(poses, reference.to(dtype), atol=1e-6 if dtype == torch.float32 else 1e-14, rtol=0)
    R = poses[..., :3, :3]
    eye = torch.eye(3, dtype=dtype).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=1e-6 if dtype == torch.float32 else 1e-14, rtol=0)
    if shape:
        torch.testing.assert_close(poses.reshape(-1, len(tree.links), 4, 4)[-1], tree.link_poses(theta64.reshape(-1, tree.n_joints)[-1]).to(dtype))


def test_link_poses_gradcheck(tree):
    for theta in [random_theta(tree, 1, seed=2)[0], tree.lower.clone(), tree.upper.clone()]:
        assert torch.autograd.gradcheck(tree.link_poses, (theta.requires_grad_(),))


def test_gradient_of_hinge_by_hand():
    tree = KinematicTree.from_urdf_string(TWO_JOINTS)
    theta = torch.tensor([0.3, 0.2], dtype=torch.float64, requires_grad=True)
    b_position = tree.link_poses(theta)[2, :3, 3]  # (1 + s cos q, s sin q, 0)
    (grad,) = torch.autograd.grad(b_position[1], theta)
    torch.testing.assert_close(grad, torch.tensor([0.2 * math.cos(0.3), math.sin(0.3)], dtype=torch.float64))


def test_parts_are_rigid(tree):
    thetas = random_theta(tree, 2, seed=3)
    links, parts = tree.link_poses(thetas), tree.part_poses(thetas)
    assert parts.shape == (2, len(tree.parts), 4, 4)
    for i, name in enumerate(tree.links):
        part = tree.part_of_link[i]
        assert name in tree.parts[part]
        T_part_link = invert_pose(parts[:, part]) @ links[:, i]
        torch.testing.assert_close(T_part_link[0], T_part_link[1], atol=1e-14, rtol=0)
    torch.testing.assert_close(parts[:, 0], torch.eye(4, dtype=torch.float64).expand(2, 4, 4))


def test_link_poses_rejects_bad_theta(tree):
    with pytest.raises(ValueError, match=r"shape \[\.\.\., 3\].*got \[2\]"):
        tree.link_poses(torch.zeros(2))
    with pytest.raises(ValueError, match="floating-point tensor, got Tensor"):
        tree.link_poses(torch.zeros(3, dtype=torch.int64))


def test_tree_without_joints():
    tree = KinematicTree.from_urdf_string('<robot name="one"><link name="solo"/></robot>')
    assert tree.links == ["solo"] and tree.n_joints == 0 and tree.parts == [["solo"]]
    assert torch.equal(tree.link_poses(torch.zeros(0)), torch.eye(4)[None])
    assert tree.visual_meshes() == {}


def test_a_chain_of_fixed_joints_is_one_part_that_takes_no_configuration(assets, tree):
    rigid = KinematicTree.from_urdf(assets / "fixed_chain.urdf")
    assert rigid.n_joints == 0 and rigid.parts == [["a", "b", "c"]]
    poses = rigid.link_poses(None)  # the empty configuration, as a composed field passes it
    assert poses.dtype == torch.float64 and torch.equal(poses, rigid.link_poses(torch.zeros(0, dtype=torch.float64)))
    np.testing.assert_allclose(poses[2, :3, 3].numpy(), [-0.04, 0.0, 0.0], atol=1e-12)
    assert torch.equal(rigid.part_poses(None), torch.eye(4, dtype=torch.float64)[None])
    with pytest.raises(ValueError, match="theta must be a floating-point tensor, got NoneType"):
        tree.link_poses(None)  # an object with joints needs them


# --- configurations -----------------------------------------------------------------------------


def test_mid_configuration(tree):
    torch.testing.assert_close(tree.mid_configuration(), torch.tensor([0.0, 0.015, -0.15], dtype=torch.float64))


def test_joint_vector_and_dict(tree):
    theta = tree.joint_vector({"hinge": 0.9, "spin": -1.0, "slide": -0.02})
    assert theta.dtype == torch.float64 and theta.tolist() == [-1.0, -0.02, 0.9]
    assert tree.joint_dict(theta) == {"spin": -1.0, "slide": -0.02, "hinge": 0.9}
    assert tree.joint_vector(None).tolist() == tree.mid_configuration().tolist()
    assert tree.joint_vector({"slide": 0.0}).tolist() == pytest.approx([0.0, 0.0, -0.15], abs=1e-15)
    assert tree.joint_vector({"hinge": np.float32(0.9)})[2] == pytest.approx(0.9, abs=1e-7)  # float32 round-off
    assert tree.joint_vector({"hinge": 0.9 + LIMIT_TOLERANCE / 2})[2] == 0.9 + LIMIT_TOLERANCE / 2


@pytest.mark.parametrize(
    "joints, message",
    [
        ({"elbow": 0.1}, r"unknown joint\(s\) \['elbow'\]; this object's joints are \['spin', 'slide', 'hinge'\]"),
        ({"hinge": float("nan")}, "joint 'hinge': value must be finite, got nan"),
        ({"slide": float("inf")}, "joint 'slide': value must be finite, got inf"),
        ({"hinge": 1.0}, r"joint 'hinge': 1.0 is outside its limits \[-1.2, 0.9\] \(rad\)"),
        ({"slide": -0.03}, r"joint 'slide': -0.03 is outside its limits \[-0.02, 0.05\] \(m\)"),
        ({"spin": 3.2}, r"joint 'spin': 3.2 is outside its limits"),
        ({"hinge": "0.1"}, "joint 'hinge': value must be a number, got str '0.1'"),
        ({"hinge": True}, "joint 'hinge': value must be a number, got bool"),
        ([("hinge", 0.1)], "joints must be a mapping"),
    ],
)
def test_joint_vector_rejects(tree, joints, message):
    with pytest.raises(ValueError, match=message):
        tree.joint_vector(joints)


def test_joint_errors_name_the_field_and_the_joint(tree):
    with pytest.raises(InputError, match="^joints_init: joint 'hinge': 1.0 is outside") as info:
        tree.joint_vector({"hinge": 1.0}, field="joints_init")
    assert info.value.field == "joints_init.hinge"
    with pytest.raises(InputError) as info:
        tree.joint_vector({"elbow": 1.0}, field="request.joints")
    assert info.value.field == "request.joints.elbow"


def test_mimic_joint_follows_its_source():
    """A mimic joint is not in theta; it moves by multiplier * source + offset, its range mapped from the source's."""
    text = urdf_with(
        f'<joint name="drive" type="revolute"><parent link="root"/><child link="a"/><axis xyz="0 0 1"/>{LIMIT}</joint>'
        '<joint name="follow" type="prismatic"><parent link="a"/><child link="b"/><axis xyz="1 0 0"/>'
        '<mimic joint="drive" multiplier="-0.5" offset="0.1"/></joint>',
        '<link name="root"/><link name="a"/><link name="b"/>',
    )
    tree = KinematicTree.from_urdf_string(text)
    assert tree.joint_names == ["drive"] and [j.name for j in tree.mimics] == ["follow"]
    assert (tree.mimics[0].lower, tree.mimics[0].upper) == pytest.approx((-0.4, 0.6))
    poses = tree.link_poses(torch.tensor([[0.0], [0.6]], dtype=torch.float64))
    # b sits at x = -0.5 * q + 0.1 along a's x axis, which turns by q about z
    q = 0.6
    expected = np.array([math.cos(q), math.sin(q), 0.0]) * (-0.5 * q + 0.1)
    np.testing.assert_allclose(poses[0, 2, :3, 3].numpy(), [0.1, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(poses[1, 2, :3, 3].numpy(), expected, atol=1e-12)
    with pytest.raises(UrdfError, match="joint 'twice' mimics 'follow', which is a mimic joint"):
        KinematicTree.from_urdf_string(text.replace(
            "</robot>", '<link name="c"/><joint name="twice" type="continuous"><parent link="b"/><child link="c"/>'
            '<mimic joint="follow"/></joint></robot>'))


def test_joint_vector_without_fill(tree):
    with pytest.raises(ValueError, match=r"missing value\(s\) for joint\(s\) \['spin', 'hinge'\]"):
        tree.joint_vector({"slide": 0.0}, fill_mid=False)
    assert tree.joint_vector({"slide": 0.0, "spin": 0.0, "hinge": 0.0}, fill_mid=False).tolist() == [0.0] * 3


def test_joint_dict_rejects_wrong_shape(tree):
    with pytest.raises(ValueError, match=r"theta must have shape \[3\]"):
        tree.joint_dict(torch.zeros(2, 3))


# --- geometry -----------------------------------------------------------------------------------


def test_visual_meshes_merge_every_visual(tree):
    meshes = tree.visual_meshes()
    assert set(meshes) == {"base", "wheel", "arm", "slider", "tip", "plate"}  # cap has no visual
    base = meshes["base"]  # box 0.1 x 0.06 x 0.02 lifted 0.01, plus a 32-gon cylinder along y at x = 0.05
    cylinder = 0.5 * 32 * math.sin(2 * math.pi / 32) * 0.01**2 * 0.06
    assert base.volume == pytest.approx(0.1 * 0.06 * 0.02 + cylinder, rel=1e-9)
    np.testing.assert_allclose(base.bounds, [[-0.05, -0.03, 0.0], [0.06, 0.03, 0.03]], atol=1e-12)
    arm = meshes["arm"]  # tetrahedron scaled (0.04, 0.02, 0.03), yawed 0.5, at (0.01, 0.02, 0); sphere r = 0.01 at x = 0.06
    corner = rot_z(0.5) @ [0.04, 0.0, 0.0] + [0.01, 0.02, 0.0]
    assert np.abs(arm.vertices - corner).sum(1).min() < 1e-12
    sphere = arm.volume - 0.04 * 0.02 * 0.03 / 6
    assert 0.97 * (4 / 3 * math.pi * 0.01**3) < sphere < 4 / 3 * math.pi * 0.01**3
    np.testing.assert_allclose(arm.bounds[:, 0], [0.01 - 0.02 * math.sin(0.5), 0.07], atol=1e-12)
    meshes["slider"].apply_translation([1.0, 0.0, 0.0])
    np.testing.assert_allclose(tree.visual_meshes()["slider"].bounds[1], [0.015, 0.005, 0.005])  # a copy was changed


def test_sample_points(tree):
    points = tree.sample_points(n_per_link=200, seed=1)
    assert set(points) == set(tree.visual_meshes())
    assert all(p.shape == (200, 3) and p.dtype == np.float64 for p in points.values())
    on_box = np.abs(points["slider"]) / [0.015, 0.005, 0.005]  # every point on a face of the box
    np.testing.assert_allclose(on_box.max(1), 1.0, atol=1e-9)
    again, other = tree.sample_points(200, seed=1), tree.sample_points(200, seed=2)
    assert np.array_equal(again["arm"], points["arm"]) and not np.array_equal(other["arm"], points["arm"])
    with pytest.raises(ValueError, match="n_per_link must be positive, got 0"):
        tree.sample_points(0)


def test_dense_points_follow_each_links_area(tree):
    """A link gets its area over the spacing squared of points, at least 500 and at most the cap, on its surface."""
    meshes = tree.visual_meshes()
    points = tree.dense_points(spacing_m=0.002, most_per_link=600)
    for name, mesh in meshes.items():
        assert len(points[name]) == int(np.clip(mesh.area / 0.002**2, 500, 600))
    on_box = np.abs(points["slider"]) / [0.015, 0.005, 0.005]
    np.testing.assert_allclose(on_box.max(1), 1.0, atol=1e-9)
    fine = tree.dense_points(spacing_m=0.0005, most_per_link=100_000)
    slider = meshes["slider"].area
    assert len(fine["slider"]) == int(slider / 0.0005**2) > 500  # 2 * (0.03*0.01 + 0.03*0.01 + 0.01*0.01) m² / 0.25 mm²
    with pytest.raises(ValueError, match="spacing_m must be > 0"):
        tree.dense_points(spacing_m=0.0)
    with pytest.raises(ValueError, match="most_per_link >= 500"):
        tree.dense_points(most_per_link=10)


def test_bounds_hold_every_configuration(tree):
    box = tree.bounds()
    assert box.shape == (2, 3) and (box[0] < box[1]).all()
    points = tree.sample_points(100)
    thetas = random_theta(tree, 300, seed=4)
    poses = tree.link_poses(thetas).numpy()
    moved = np.concatenate([poses[:, tree.links.index(name), None, :3, :3] @ p[:, :, None] for name, p in points.items()], axis=1)
    moved = moved[..., 0] + np.concatenate([np.repeat(poses[:, tree.links.index(n), None, :3, 3], len(p), 1) for n, p in points.items()], axis=1)
    moved = moved.reshape(-1, 3)
    assert (moved >= box[0]).all() and (moved <= box[1]).all()
    tight = np.ptp(moved, axis=0)
    assert (box[1] - box[0] < 1.2 * tight).all()  # not loose either


def test_from_string_matches_from_file(tree, assets):
    text = (assets / "articulated.urdf").read_text()
    other = KinematicTree.from_urdf_string(text, mesh_dir=assets)
    assert other.urdf_text == text == tree.urdf_text
    theta = random_theta(tree, 3, seed=5)
    assert torch.equal(other.link_poses(theta), tree.link_poses(theta))
    assert other.visual_meshes()["arm"].volume == pytest.approx(tree.visual_meshes()["arm"].volume)


def test_from_string_needs_no_meshes_for_kinematics(assets):
    tree = KinematicTree.from_urdf_string((assets / "articulated.urdf").read_text())
    assert tree.link_poses(tree.mid_configuration()).shape == (7, 4, 4)
    with pytest.raises(UrdfError, match="link 'arm' uses mesh 'meshes/tetra.obj' but no mesh folder was given"):
        tree.visual_meshes()


# --- bad URDFs ----------------------------------------------------------------------------------


def test_not_xml(tmp_path):
    path = tmp_path / "broken.urdf"
    path.write_text("<robot name='x'>\n<link name='a'>\n</robot>")
    with pytest.raises(UrdfError) as info:
        KinematicTree.from_urdf(path)
    message = str(info.value)
    assert message.startswith(f"{path}: not valid XML: mismatched tag") and "\n" not in message


def test_missing_mesh(tmp_path):
    path = tmp_path / "object.urdf"
    path.write_text('<robot name="x"><link name="a"><visual><geometry><mesh filename="meshes/gone.stl"/></geometry></visual></link></robot>')
    with pytest.raises(UrdfError, match=f"^{path}: link 'a': mesh file 'meshes/gone.stl' not found \\(looked in {tmp_path}\\)$"):
        KinematicTree.from_urdf(path)
    assert KinematicTree.from_urdf(path, load_meshes=False).links == ["a"]


def test_unreadable_file(tmp_path):
    with pytest.raises(UrdfError, match=r"nope.urdf: no such URDF file$"):
        KinematicTree.from_urdf(tmp_path / "nope.urdf")
    (tmp_path / "folder.urdf").mkdir()
    with pytest.raises(UrdfError, match=r"folder.urdf: cannot read the file \(IsADirectoryError\)$"):
        KinematicTree.from_urdf(tmp_path / "folder.urdf")
    (tmp_path / "binary.urdf").write_bytes(b"\xff\xfe\x00<robot")
    with pytest.raises(UrdfError, match=r"binary.urdf: cannot read the file \(UnicodeDecodeError\)$"):
        KinematicTree.from_urdf(tmp_path / "binary.urdf")


def test_corrupt_mesh(tmp_path):
    (tmp_path / "bad.obj").write_text("this is not a mesh\n")
    path = tmp_path / "object.urdf"
    path.write_text('<robot name="x"><link name="a"><visual><geometry><mesh filename="bad.obj"/></geometry></visual></link></robot>')
    with pytest.raises(UrdfError, match="link 'a': mesh .*bad.obj' has no triangles"):
        KinematicTree.from_urdf(path)


LIMIT = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'


@pytest.mark.parametrize(
    "text, message",
    [
        ("<robt/>", "the root element is <robt>, expected <robot>"),
        ('<robot name="x"/>', "the robot has no <link>"),
        ('<robot name="x"><link/></robot>', r"malformed URDF \(missing attribute 'name'\)"),
        ('<robot name="x"><link name="a"/><link name="a"/></robot>', r"duplicate link names \['a'\]"),
        (urdf_with('<joint name="j" type="floating"><parent link="root"/><child link="a"/></joint>'), "joint 'j' has type 'floating'; supported: revolute, continuous, prismatic, fixed"),
        (urdf_with('<joint name="j" type="revolute"><parent link="root"/><child link="a"/></joint>'), r"joint 'j' \(revolute\) needs <limit lower=... upper=...>"),
        (urdf_with('<joint name="j" type="prismatic"><parent link="root"/><child link="a"/><limit lower="1" upper="0" effort="1" velocity="1"/></joint>'), r"joint 'j' has limits \[1.0, 0.0\]; they must be finite with lower < upper"),
        (urdf_with('<joint name="j" type="revolute"><parent link="root"/><child link="a"/><limit lower="0.1" upper="0.1" effort="1" velocity="1"/></joint>'), r"joint 'j' has limits \[0.1, 0.1\]; they must be finite with lower < upper \(a joint that cannot move is a fixed joint\)"),
        (urdf_with(f'<joint name="j" type="revolute"><parent link="root"/><child link="b"/>{LIMIT}</joint>'), "joint 'j' names child link 'b', which is not a <link>"),
        (urdf_with(f'<joint name="j" type="revolute"><parent link="root"/><child link="a"/><axis xyz="0 0 0"/>{LIMIT}</joint>'), r"joint 'j' has axis \[0.0, 0.0, 0.0\] of length 0; it must be a unit vector"),
        (urdf_with(f'<joint name="j" type="prismatic"><parent link="root"/><child link="a"/><axis xyz="0 3 4"/>{LIMIT}</joint>'), "joint 'j' has axis .* of length 5; it must be a unit vector"),
        (urdf_with('<joint name="j" type="continuous"><parent link="root"/><child link="a"/><mimic joint="k"/></joint>'), "joint 'j' mimics 'k', which is no joint; the source must be a revolute, continuous or prismatic joint"),
        (urdf_with(f'<joint name="k" type="revolute"><parent link="root"/><child link="a"/>{LIMIT}</joint><joint name="j" type="revolute"><parent link="a"/><child link="b"/><mimic joint="k" multiplier="0" offset="0.2"/></joint>', '<link name="root"/><link name="a"/><link name="b"/>'), "joint 'j' mimics 'k' with multiplier 0, so it cannot move; make it a fixed joint"),
        (urdf_with('<joint name="j" type="fixed"><parent link="a"/><child link="root"/></joint><joint name="k" type="fixed"><parent link="root"/><child link="a"/></joint>'), r"expected exactly one root link .*, found \[\]"),
        (urdf_with("", '<link name="a"/><link name="b"/>'), r"expected exactly one root link .*, found \['a', 'b'\]"),
        (urdf_with('<joint name="j" type="fixed"><parent link="a"/><child link="b"/></joint><joint name="k" type="fixed"><parent link="b"/><child link="a"/></joint>', '<link name="root"/><link name="a"/><link name="b"/>'), r"links \['a', 'b'\] are not connected to the root 'root'"),
        (urdf_with('<joint name="j" type="fixed"><parent link="root"/><child link="a"/></joint><joint name="j" type="fixed"><parent link="a"/><child link="root"/></joint>'), r"duplicate joint names \['j'\]"),
        (urdf_with('<joint name="j" type="fixed"><parent link="root"/><child link="a"/></joint><joint name="k" type="fixed"><parent link="root"/><child link="a"/></joint>'), "link 'a' is the child of two joints: 'j' and 'k'"),
    ],
)
def test_bad_urdf_strings(text, message):
    with pytest.raises(UrdfError, match=f"^<urdf string>: {message}"):
        KinematicTree.from_urdf_string(text)


def test_near_unit_axis_is_normalised():
    text = urdf_with(f'<joint name="j" type="revolute"><parent link="root"/><child link="a"/><axis xyz="0.7071 0 0.7071"/>{LIMIT}</joint>')
    (joint,) = KinematicTree.from_urdf_string(text).movable
    np.testing.assert_allclose(joint.axis, [math.sqrt(0.5), 0.0, math.sqrt(0.5)], atol=1e-15)


# --- URDFs users bring: many joints, continuous joints, fixed chains, mimic joints ------------------


def chain_urdf(n_joints: int, mimics: int = 0) -> str:
    """A chain of ``n_joints`` revolute joints, then ``mimics`` joints that mimic the first one."""
    n = n_joints + mimics
    links = "".join(f'<link name="l{i}"><visual><geometry><box size="0.04 0.02 0.02"/></geometry></visual></link>' for i in range(n + 1))
    mimic = '<mimic joint="j0"/>'
    joints = "".join(
        f'<joint name="j{i}" type="revolute"><parent link="l{i}"/><child link="l{i + 1}"/><origin xyz="0.05 0 0"/>'
        f'<axis xyz="0 0 1"/>{LIMIT}{mimic if i >= n_joints else ""}</joint>'
        for i in range(n)
    )
    return f'<robot name="chain">{links}{joints}</robot>'


def test_at_most_eight_movable_joints():
    assert MAX_JOINTS == 8
    tree = KinematicTree.from_urdf_string(chain_urdf(8, mimics=3))  # mimic joints are not in theta
    assert tree.n_joints == 8 and len(tree.mimics) == 3 and len(tree.parts) == 12
    with pytest.raises(UrdfError) as info:
        KinematicTree.from_urdf_string(chain_urdf(9))
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("<urdf string>: joint 'j8' is movable joint number 9; NARF handles at most 8 (this URDF has 9: 'j0',")
    assert message.endswith("make the joints you do not need fixed (fixed and mimic joints do not count)")


def test_continuous_joint_spans_one_turn(tree):
    """A continuous joint is a revolute joint over [-pi, pi]: both ends give the same pose."""
    spin = tree.movable[tree.joint_names.index("spin")]
    assert (spin.type, spin.lower, spin.upper) == ("continuous", -math.pi, math.pi)
    ends = tree.link_poses(torch.tensor([[-math.pi, 0.0, 0.0], [math.pi, 0.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(ends[0], ends[1], atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match=r"joint 'spin': 3.3 is outside its limits \[-3.14159"):
        tree.joint_vector({"spin": 3.3})


def test_mimic_gripper_asset_parts_and_theta(assets):
    """Mimic, continuous and a chain of fixed joints in one URDF (the end-to-end test below trains it)."""
    tree = KinematicTree.from_urdf(assets / "mimic_gripper.urdf")
    assert tree.joint_names == ["finger_a", "dial"] and [j.name for j in tree.mimics] == ["finger_b"]
    assert tree.parts == [["palm", "bracket", "camera"], ["finger_a"], ["finger_b"], ["dial"]]
    poses = tree.link_poses(torch.tensor([[0.0, 0.0], [0.04, 1.0]], dtype=torch.float64))
    a, b = tree.links.index("finger_a"), tree.links.index("finger_b")
    np.testing.assert_allclose((poses[1, a, :3, 3] - poses[0, a, :3, 3]).numpy(), [0, 0.04, 0], atol=1e-12)
    np.testing.assert_allclose((poses[1, b, :3, 3] - poses[0, b, :3, 3]).numpy(), [0, -0.04, 0], atol=1e-12)


def _cli(capsys, *argv) -> tuple[int, str, str]:
    from narf_core.cli import main

    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(capsys, command: str, *argv) -> str:
    code, out, err = _cli(capsys, command, *argv)
    lines = [line for line in err.splitlines() if line.strip() and "it/s" not in line and "view" not in line]
    assert code == 2 and out == "" and "Traceback" not in err, err
    assert len(lines) == 1 and lines[0].startswith(f"narf {command}: error: "), err
    return lines[0]


@pytest.mark.parametrize(
    "text, words",
    [
        (chain_urdf(9), ["joint 'j8' is movable joint number 9", "at most 8"]),
        (urdf_with('<joint name="j" type="revolute"><parent link="root"/><child link="a"/><limit lower="0.1" upper="0.1" effort="1" velocity="1"/></joint>'), ["joint 'j'", "lower < upper", "a joint that cannot move is a fixed joint"]),
        (urdf_with('<joint name="j" type="floating"><parent link="root"/><child link="a"/></joint>'), ["joint 'j' has type 'floating'"]),
    ],
    ids=["nine-joints", "zero-range", "floating"],
)
def test_narf_synth_refuses_a_bad_urdf_in_one_line(capsys, tmp_path, text, words):
    (tmp_path / "bad.urdf").write_text(text)
    line = _one_error_line(capsys, "synth", "--tool", tmp_path / "bad.urdf", "--out", tmp_path / "data", "--views", 1)
    assert str(tmp_path / "bad.urdf") in line and all(w in line for w in words), line
    assert not (tmp_path / "data").exists()


def test_narf_train_refuses_a_dataset_whose_urdf_is_bad(capsys, tmp_path, assets):
    from narf_core.data.synth.generate import synthesize

    data = synthesize(assets / "mimic_gripper.urdf", tmp_path / "data", size=(32, 24), views=1, supersample=1)
    urdf = data / "object.urdf"
    urdf.write_text(urdf.read_text().replace('multiplier="1"', 'multiplier="0"'))
    line = _one_error_line(capsys, "train", data, "--out", tmp_path / "m.narf")
    assert "joint 'finger_b' mimics 'finger_a' with multiplier 0, so it cannot move" in line, line
    assert not (tmp_path / "m.narf").exists()


@pytest.mark.slow
def test_a_rigid_chain_of_fixed_joints_trains_end_to_end(tmp_path, assets):
    """A URDF with fixed joints only trains (one part, empty theta) and renders on its labels."""
    from narf_core.bundle import load_bundle
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.generate import synthesize
    from narf_core.train.pipeline import TrainConfig, train

    data = synthesize(assets / "fixed_chain.urdf", tmp_path / "data", size=(48, 36), views=8, seed=0)
    config = TrainConfig(part_steps=20, distill_steps=20, batch_rays=256, grid_resolution=24, track_sequences=0)
    model = load_bundle(train(data, tmp_path / "m.narf", config, progress=False))
    assert model.kinematics.n_joints == 0 and model.kinematics.part_names == ["a"]
    dataset = Dataset.open(data)
    for mode in ("narf", "parts"):
        ious = []
        for frame in dataset.frames("test"):
            T = torch.as_tensor(frame.T_cam_obj, dtype=torch.float32)
            out = model.render(T, model.joint_vector(frame.joints), dataset.camera, outputs=("rgb", "opacity"), mode=mode)
            assert torch.isfinite(out["rgb"]).all()
            seen, labels = out["opacity"].numpy() > 0.5, dataset.load(frame).labels > 0
            ious.append((seen & labels).sum() / max((seen | labels).sum(), 1))
        assert np.mean(ious) > 0.5, (mode, np.mean(ious))


@pytest.mark.slow
def test_mimic_continuous_and_fixed_chain_train_end_to_end(tmp_path, assets):
    """Synthesize and train the gripper with a mimic finger, a continuous dial and a fixed chain at a
    tiny size: the model has theta [finger_a, dial], its renders (both modes) are finite and land on
    the labelled pixels at unseen views and configurations, and the dial's two ends (-pi, pi) render
    the same in parts mode (measured IoU 0.74-0.87 at 20 steps per stage)."""
    from narf_core.bundle import load_bundle
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.generate import synthesize
    from narf_core.train.pipeline import TrainConfig, train

    data = synthesize(assets / "mimic_gripper.urdf", tmp_path / "data", size=(48, 36), views=8, seed=0)
    config = TrainConfig(part_steps=20, distill_steps=20, batch_rays=256, grid_resolution=24, track_sequences=0)
    model = load_bundle(train(data, tmp_path / "m.narf", config, progress=False))
    assert model.kinematics.joint_names == ["finger_a", "dial"]
    torch.testing.assert_close(model.kinematics.upper, torch.tensor([0.05, math.pi], dtype=torch.float64))
    dataset = Dataset.open(data)
    for split in ("test", "novel"):
        for mode in ("narf", "parts"):
            ious = []
            for frame in dataset.frames(split):
                T = torch.as_tensor(frame.T_cam_obj, dtype=torch.float32)
                out = model.render(T, model.joint_vector(frame.joints), dataset.camera, outputs=("rgb", "opacity"), mode=mode)
                assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["opacity"]).all()
                seen, labels = out["opacity"].numpy() > 0.5, dataset.load(frame).labels > 0
                ious.append((seen & labels).sum() / max((seen | labels).sum(), 1))
            assert np.mean(ious) > 0.5, (split, mode, np.mean(ious))
    frame = dataset.frames("test")[0]
    T = torch.as_tensor(frame.T_cam_obj, dtype=torch.float32)
    ends = [model.render(T, model.joint_vector({"finger_a": 0.02, "dial": d}), dataset.camera, outputs=("rgb",), mode="parts")["rgb"]
            for d in (-math.pi, math.pi)]
    torch.testing.assert_close(ends[0], ends[1], atol=1e-4, rtol=0)


SPEED_URDF = """<?xml version="1.0"?>
<robot name="speeds">
  <link name="base"/><link name="arm"/><link name="tip"/><link name="slide"/><link name="bare"/>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="arm"/>
    <origin xyz="0 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1"/></joint>
  <joint name="wrist" type="revolute"><parent link="arm"/><child link="tip"/>
    <origin xyz="0.2 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1"/></joint>
  <joint name="rail" type="prismatic"><parent link="base"/><child link="slide"/>
    <origin xyz="0 0.3 0"/><axis xyz="1 0 0"/><limit lower="0" upper="0.1"/></joint>
  <joint name="spin" type="revolute"><parent link="base"/><child link="bare"/>
    <origin xyz="0 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1"/></joint>
</robot>
"""


def test_surface_speeds_are_the_moved_points_distance_from_the_axis_or_one_for_a_slide():
    """A revolute joint moves its points at their distance from its axis (a shoulder moves the arm's
    and the tip's points: the RMS of both), a distal joint only its own small part's, a prismatic joint
    at 1 m/m, a joint that moves no points at 0; the static base does not count."""
    kin = KinematicTree.from_urdf_string(SPEED_URDF)
    points = {
        "base": np.array([[0.5, 0.5, 0.0]]),
        "arm": np.array([[0.1, 0.0, 0.0], [0.2, 0.0, 0.0]]),  # 0.1 and 0.2 m from the shoulder's axis
        "tip": np.array([[0.05, 0.0, 0.0], [0.0, 0.05, 0.01]]),  # 0.25 / 0.2062 m from the shoulder, 0.05 from the wrist
        "slide": np.array([[0.0, 0.0, 0.0], [0.3, 0.1, 0.2]]),
    }
    speeds = kin.surface_speeds(points)
    shoulder = math.sqrt((0.1**2 + 0.2**2 + 0.25**2 + (0.2**2 + 0.05**2)) / 4)
    torch.testing.assert_close(speeds, torch.tensor([shoulder, 0.05, 1.0, 0.0], dtype=torch.float64), atol=1e-6, rtol=0)
    bent = kin.surface_speeds(points, torch.tensor([0.5, -0.7, 0.05, 0.3], dtype=torch.float64))
    torch.testing.assert_close(bent[1:], speeds[1:], atol=1e-6, rtol=0)  # distances from an axis do not change with it
    c, s = math.cos(-0.7), math.sin(-0.7)  # the bent wrist moves the tip's points about the shoulder's axis
    tip = [math.hypot(0.2 + c * x - s * y, s * x + c * y) for x, y in ((0.05, 0.0), (0.0, 0.05))]
    expected = math.sqrt((0.1**2 + 0.2**2 + tip[0] ** 2 + tip[1] ** 2) / 4)
    assert abs(float(bent[0]) - expected) < 1e-6 and abs(expected - shoulder) > 1e-3


def test_moved_points_are_those_of_the_links_each_joint_carries():
    """``moved_points [k, N]``, the points in link order: the shoulder carries the arm's and the tip's, the wrist
    the tip's, the slide its own, the fourth joint none, and none of them the base's."""
    kin = KinematicTree.from_urdf_string(SPEED_URDF)
    points = {"base": np.zeros((1, 3)), "arm": np.ones((2, 3)), "tip": np.ones((2, 3)), "slide": np.ones((2, 3))}
    counts = [len(points.get(link, ())) for link in kin.links]
    owner = np.repeat(np.array(kin.links), counts)
    moved = kin.moved_points(points).numpy()
    assert moved.shape == (4, 7)
    assert set(owner[moved[0]]) == {"arm", "tip"} and set(owner[moved[1]]) == {"tip"}
    assert set(owner[moved[2]]) == {"slide"} and not moved[3].any()
