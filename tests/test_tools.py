"""The procedural tools and multi-joint objects: specs, determinism, URDF structure, kinematics,
meshes, textures, collisions over the joint range, pybullet loading and rendering."""

from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import shapely
import torch
import yourdfpy
from PIL import Image
from shapely.affinity import rotate
from shapely.ops import unary_union
from trimesh.transformations import euler_matrix

from narf_core.data.synth.tools import _DESIGNS, TOOLS, ToolSpec, build_tool, tool_spec
from narf_core.kinematics import KinematicTree

ONE_JOINT = ("clamp", "lineman-a", "lineman-b", "longnose")
MULTI_JOINT = ("lamp", "gripper", "cabinet")
LINKS = {
    "clamp": ("bar", "moving_jaw"),
    "lineman-a": ("lower_half", "upper_half"),
    "lineman-b": ("lower_half", "upper_half"),
    "longnose": ("lower_half", "upper_half"),
    "lamp": ("base", "lower_arm", "upper_arm", "head"),
    "gripper": ("palm", "finger_left", "finger_right"),
    "cabinet": ("body", "drawer_lower", "drawer_upper", "door"),
}
# joint name, type, axis, lower, upper
JOINTS = {
    "clamp": ("jaw_opening", "prismatic", (1, 0, 0), 0.02, 0.20),
    "lineman-a": ("pivot", "revolute", (0, 0, 1), 0.0, 0.5),
    "lineman-b": ("pivot", "revolute", (0, 0, 1), 0.0, 0.5),
    "longnose": ("pivot", "revolute", (0, 0, 1), 0.0, 0.6),
}


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("tools")
    return {name: build_tool(name, root / name, seed=0) for name in TOOLS}


@pytest.fixture(scope="module")
def loaded(built) -> dict[str, yourdfpy.URDF]:
    return {name: yourdfpy.URDF.load(str(path)) for name, path in built.items()}


def _obj_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions [n, 3] and 0-based triangle vertex indices [m, 3] of one of our OBJ files."""
    lines = path.read_text().splitlines()
    v = np.array([[float(t) for t in line.split()[1:]] for line in lines if line.startswith("v ")])
    f = np.array([[int(t.split("/")[0]) - 1 for t in line.split()[1:]] for line in lines if line.startswith("f ")])
    return v, f


# --- specs ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, n_train, n_novel",
    [("clamp", 4, 3), ("lineman-a", 1, 3), ("lineman-b", 1, 3), ("longnose", 1, 1), ("lamp", 8, 4), ("gripper", 8, 4),
     ("cabinet", 8, 4)],
)
def test_spec_counts_follow_the_paper(name, n_train, n_novel):
    spec = tool_spec(name)
    assert isinstance(spec, ToolSpec) and spec.name == name
    assert (len(spec.train_configurations), len(spec.novel_configurations)) == (n_train, n_novel)


def test_spec_values_are_fixed_and_fresh():
    assert tool_spec("clamp").train_configurations == [
        {"jaw_opening": 0.05}, {"jaw_opening": 0.09}, {"jaw_opening": 0.13}, {"jaw_opening": 0.17}
    ]
    assert tool_spec("longnose").novel_configurations == [{"pivot": 0.35}]
    spec = tool_spec("lineman-a")
    spec.train_configurations[0]["pivot"] = 9.0  # callers get their own copies
    assert tool_spec("lineman-a").train_configurations == [{"pivot": 0.02}]


@pytest.mark.parametrize("name", TOOLS)
def test_spec_configurations_lie_in_limits_and_novel_ones_are_new(name, loaded):
    urdf = loaded[name]
    limits = {j.name: (j.limit.lower, j.limit.upper) for j in urdf.robot.joints if j.type != "fixed"}
    spec = tool_spec(name)
    for configuration in spec.train_configurations + spec.novel_configurations:
        assert set(configuration) == set(limits) == set(urdf.actuated_joint_names)
        for joint, value in configuration.items():
            assert limits[joint][0] <= value <= limits[joint][1]
    assert not any(c in spec.train_configurations for c in spec.novel_configurations)


def test_unknown_tool_is_refused_with_the_known_names(tmp_path):
    known = "clamp, lineman-a, lineman-b, longnose, lamp, gripper, cabinet"
    with pytest.raises(ValueError, match=f"unknown tool 'hammer'; known tools: {known}$"):
        tool_spec("hammer")
    with pytest.raises(ValueError, match="known tools"):
        build_tool("hammer", tmp_path)


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_bad_seed_is_refused(tmp_path, seed):
    with pytest.raises(ValueError, match="seed must be a non-negative integer"):
        build_tool("clamp", tmp_path, seed=seed)


# --- files --------------------------------------------------------------------------------------


def test_same_seed_gives_identical_bytes_and_seed_changes_only_textures(tmp_path, built):
    first = built["lineman-b"].parent
    again = build_tool("lineman-b", tmp_path / "again", seed=0).parent
    other = build_tool("lineman-b", tmp_path / "other", seed=1).parent
    files = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    assert [str(p) for p in files] == [
        "meshes/lower_half.mtl", "meshes/lower_half.obj", "meshes/lower_half.png",
        "meshes/upper_half.mtl", "meshes/upper_half.obj", "meshes/upper_half.png", "object.urdf",
    ]
    for rel in files:
        assert (first / rel).read_bytes() == (again / rel).read_bytes(), rel
        same = (first / rel).read_bytes() == (other / rel).read_bytes()
        assert same == (rel.suffix != ".png"), rel


# SHA-256 (first 16 hex digits) of each tool's URDF, OBJ and MTL files (path, then bytes, in path order).
GEOMETRY_DIGESTS = {
    "clamp": "71f5a7395b5774d3",
    "lineman-a": "ceb00cdd3dfbbcff",
    "lineman-b": "adb9e8ef6d65a818",
    "longnose": "617d7599a0dc4ba5",
}


@pytest.mark.parametrize("name", ONE_JOINT)
def test_the_tools_geometry_is_unchanged(name, built):
    """Trained models (the bundled clamp among them) and published figures rest on these files: new
    objects and generator features must leave the tools' meshes and URDFs byte for byte as they were.
    (Textures are left out: PNG bytes depend on the zlib build.)"""
    root = built[name].parent
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file() and p.suffix != ".png"):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    assert digest.hexdigest()[:16] == GEOMETRY_DIGESTS[name]


@pytest.mark.parametrize("name", ONE_JOINT)
def test_urdf_structure_and_relative_mesh_paths(name, built, loaded):
    urdf = loaded[name]
    assert tuple(link.name for link in urdf.robot.links) == LINKS[name]
    assert urdf.base_link == LINKS[name][0]
    (joint,) = urdf.robot.joints
    joint_name, kind, axis, lower, upper = JOINTS[name]
    assert (joint.name, joint.type, joint.parent, joint.child) == (joint_name, kind, *LINKS[name])
    np.testing.assert_allclose(joint.axis, axis)
    assert (joint.limit.lower, joint.limit.upper) == pytest.approx((lower, upper))
    np.testing.assert_allclose(joint.origin, np.eye(4))
    text = built[name].read_text()
    for link in LINKS[name]:
        assert text.count(f'filename="meshes/{link}.obj"') == 2  # visual and collision
        inertial = urdf.link_map[link].inertial
        assert inertial.mass > 0.005 and np.allclose(inertial.origin, np.eye(4))
        assert np.all(np.linalg.eigvalsh(inertial.inertia) > 0)


@pytest.mark.parametrize("name", TOOLS)
def test_meshes_load_with_uv_textures(name, loaded):
    for geometry in loaded[name].scene.geometry.values():
        visual = geometry.visual
        assert visual.kind == "texture"
        assert visual.uv.shape == (len(geometry.vertices), 2)
        assert visual.uv.min() >= 0.0 and visual.uv.max() <= 1.0
        assert visual.material.image.size[0] >= 256


def test_trimesh_reads_the_texture_where_the_design_paints_it(loaded):
    """Vertex colours sampled through the uv map: the clamp's pads are orange, the grip yellow."""
    bar = loaded["clamp"].scene.geometry["bar.obj"]
    colours = bar.visual.to_color().vertex_colors[:, :3].astype(np.float64)
    x, y, z = bar.vertices.T
    pad_top = np.isclose(z, 0.0115) & (x > -0.0061) & (y < -0.02)
    grip_top = np.isclose(z, 0.014) & (y < -0.05)
    assert pad_top.sum() >= 4 and grip_top.sum() >= 4
    r, g, b = colours[pad_top].mean(0)
    assert r > 200 and 0.3 * r < g < 0.7 * r and b < 0.3 * r
    r, g, b = colours[grip_top].mean(0)
    assert r > 150 and g > 0.6 * r and b < 0.4 * g


def test_out_dir_must_be_a_directory(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="exists and is not a directory"):
        build_tool("clamp", tmp_path / "file")


@pytest.mark.parametrize("name", TOOLS)
def test_meshes_are_closed_and_modest(name, built):
    for link in LINKS[name]:
        v, f = _obj_arrays(built[name].parent / "meshes" / f"{link}.obj")
        assert len(f) < 5000
        # Weld coincident vertices; a closed, consistently oriented surface (or a union of them)
        # uses every edge a -> b exactly as often as b -> a.
        v, welded = np.unique(np.round(v, 7), axis=0, return_inverse=True)
        f = welded.reshape(-1)[f]
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        forward = {tuple(e): 0 for e in edges}
        for a, b in edges:
            forward[(a, b)] += 1
        assert all(forward.get((b, a), 0) == n for (a, b), n in forward.items())
        # Outward normals: the signed volume is positive.
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6 > 1e-7


# Per link: extent along x, along y, along z (metres), each as (min, max).
SIZES = {
    ("clamp", "bar"): ((0.30, 0.34), (0.12, 0.17), (0.02, 0.035)),
    ("clamp", "moving_jaw"): ((0.025, 0.05), (0.09, 0.13), (0.015, 0.03)),
    ("lineman-a", "lower_half"): ((0.18, 0.23), (0.03, 0.045), (0.01, 0.02)),
    ("lineman-b", "lower_half"): ((0.19, 0.24), (0.03, 0.045), (0.01, 0.02)),
    ("longnose", "lower_half"): ((0.17, 0.22), (0.025, 0.04), (0.008, 0.016)),
}


@pytest.mark.parametrize("key", SIZES)
def test_link_sizes_are_plausible(key, built):
    name, link = key
    v, _ = _obj_arrays(built[name].parent / "meshes" / f"{link}.obj")
    extent = v.max(0) - v.min(0)
    for size, (lo, hi) in zip(extent, SIZES[key]):
        assert lo <= size <= hi, (key, extent)


@pytest.mark.parametrize("name", ["lineman-a", "lineman-b", "longnose"])
def test_pliers_frame_and_halves_never_overlap_in_the_joint_range(name):
    lower, upper = _DESIGNS[name]().links
    # Pieces spanning z = 0 (all but the lap disc, where the halves sit one above the other).
    full = [unary_union([p.outline for p in half.prisms if p.z[0] < 0 < p.z[1]]) for half in (lower, upper)]
    assert full[0].bounds[2] > 0.04 and full[0].bounds[0] < -0.1  # jaws along +x, handles along -x
    for angle in np.linspace(0.0, JOINTS[name][4], 6):
        moved = rotate(full[1], angle, origin=(0.0, 0.0), use_radians=True)
        assert full[0].intersection(moved).area < 1e-10
        assert full[0].distance(moved) >= 0.0005


def test_clamp_jaw_stays_on_the_bar_in_the_joint_range(loaded):
    urdf = loaded["clamp"]
    for opening, pad_gap in ((0.02, 0.02), (0.20, 0.20)):
        urdf.update_cfg({"jaw_opening": opening})
        jaw = urdf.scene.geometry["moving_jaw.obj"].bounds
        T = urdf.get_transform("moving_jaw", "bar")
        x_min, x_max = jaw[:, 0] + T[0, 3]
        assert x_min == pytest.approx(pad_gap)  # the moving pad's face, from the fixed pad's face at x = 0
        assert x_max < 0.236  # the bar's end stop


# --- textures -----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ONE_JOINT)
def test_textures_carry_detail(name, built):
    means = []
    for link in LINKS[name]:
        image = np.asarray(Image.open(built[name].parent / "meshes" / f"{link}.png"))
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
        painted = image[image.max(-1) > 0].astype(np.int64)
        assert len(np.unique(painted @ [65536, 256, 1])) > 500
        painted = painted / 255
        assert painted.std(0).mean() > 0.1
        # Fine grain everywhere: most neighbouring texels differ, not only at pattern edges.
        inside = (image[:, 1:].max(-1) > 0) & (image[:, :-1].max(-1) > 0)
        steps = np.abs(np.diff(image.astype(np.int64), axis=1)).max(-1)[inside]
        assert np.mean(steps > 0) > 0.5
        means.append(painted.mean(0))
    # The two parts do not look alike (colours of the pliers halves differ by a few percent).
    assert np.abs(means[0] - means[1]).max() > 0.01


# --- pybullet -----------------------------------------------------------------------------------


def _top_view(p, client: int, centre: tuple[float, float], height: float, size: tuple[int, int], fov_deg: float):
    """Render from ``height`` above ``centre`` looking down (image right = +x, image up = +y)."""
    w, h = size
    eye, target = [centre[0], centre[1], height], [centre[0], centre[1], 0.0]
    view = p.computeViewMatrix(eye, target, [0, 1, 0], physicsClientId=client)
    proj = p.computeProjectionMatrixFOV(fov_deg, w / h, 0.01, 2.0, physicsClientId=client)
    _, _, rgb, _, seg = p.getCameraImage(
        w, h, view, proj,
        renderer=p.ER_TINY_RENDERER,
        flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
        physicsClientId=client,
    )
    return np.reshape(rgb, (h, w, 4))[..., :3].astype(np.uint8), np.reshape(seg, (h, w))


def test_pybullet_loads_the_tools_and_renders_their_textures(built):
    p = pytest.importorskip("pybullet")
    client = p.connect(p.DIRECT)
    try:
        mean_colour = {}
        for name in ("clamp", "lineman-a", "lineman-b"):  # two pliers with the same file names
            body = p.loadURDF(str(built[name]), useFixedBase=True, physicsClientId=client)
            n_joints = p.getNumJoints(body, physicsClientId=client)
            joint = {p.getJointInfo(body, j, physicsClientId=client)[1].decode(): j for j in range(n_joints)}
            assert list(joint) == [JOINTS[name][0]]
            p.resetJointState(body, joint[JOINTS[name][0]], 0.1, physicsClientId=client)
            centre, height = ((0.08, -0.05), 0.5) if name == "clamp" else ((-0.05, 0.0), 0.3)
            rgb, seg = _top_view(p, client, centre, height, (320, 240), 45.0)
            on_object = seg >= 0
            # Both links show up (segmentation: (link index + 1) << 24 | body, -1 for the root).
            links = set(np.unique((seg[on_object] >> 24) - 1).tolist())
            assert links == {-1, 0}
            colours = rgb[on_object]
            assert on_object.sum() > 3000
            assert len(np.unique(colours, axis=0)) > 400
            assert colours.astype(np.float64).std(0).mean() > 20
            mean_colour[name] = colours.mean(0)
            p.removeBody(body, physicsClientId=client)
        a, b = mean_colour["lineman-a"], mean_colour["lineman-b"]
        assert a[2] > a[0] and b[0] > b[2]  # blue grips vs red grips: no texture mix-up by file name
    finally:
        p.disconnect(client)


def test_pybullet_texture_lands_where_the_mesh_says(built):
    """Seen from above, the clamp's pad is orange, its grip yellow and its bar grey steel."""
    p = pytest.importorskip("pybullet")
    client = p.connect(p.DIRECT)
    try:
        p.loadURDF(str(built["clamp"]), useFixedBase=True, physicsClientId=client)
        size, fov, height, centre = (320, 240), 45.0, 0.4, (0.08, -0.05)
        rgb, _ = _top_view(p, client, centre, height, size, fov)
        f = size[1] / 2 / math.tan(math.radians(fov) / 2)

        def colour_at(x: float, y: float, z: float) -> np.ndarray:
            u = size[0] / 2 + f * (x - centre[0]) / (height - z)
            v = size[1] / 2 - f * (y - centre[1]) / (height - z)
            return rgb[int(v) - 1 : int(v) + 2, int(u) - 1 : int(u) + 2].reshape(-1, 3).mean(0)

        pad = colour_at(-0.003, -0.06, 0.0115)
        grip = colour_at(-0.062, -0.11, 0.014)
        bar = colour_at(0.15, -0.006, 0.003)
        assert pad[0] > 150 and pad[0] > 1.6 * pad[1] > 1.6 * pad[2]  # orange
        assert grip[0] > 100 and grip[1] > 0.6 * grip[0] and grip[2] < 0.5 * grip[1]  # yellow (with dark ribs)
        assert bar.min() > 100 and bar.max() - bar.min() < 25  # light grey
    finally:
        p.disconnect(client)


# --- objects with several joints ------------------------------------------------------------------

# joint name, type, parent, child, axis (joint frame), lower, upper, origin xyz, origin rpy
MULTI_JOINTS = {
    "lamp": [
        ("shoulder", "revolute", "base", "lower_arm", (0, 0, 1), -0.5, 0.5, (0, 0, 0.05), (math.pi / 2, 0, 0)),
        ("elbow", "revolute", "lower_arm", "upper_arm", (0, 0, 1), -0.2, 0.8, (0, 0.18, 0), (0, 0, -math.pi / 2)),
        ("head_tilt", "revolute", "upper_arm", "head", (0, 0, 1), -0.5, 0.9, (0, 0.15, 0), (0, 0, -math.pi / 2)),
    ],
    "gripper": [
        ("finger_left", "prismatic", "palm", "finger_left", (0, 1, 0), 0.0, 0.04, (0.008, 0.002, 0), (0, 0, 0)),
        ("finger_right", "prismatic", "palm", "finger_right", (0, -1, 0), 0.0, 0.04, (0.008, -0.002, 0), (0, 0, 0)),
    ],
    "cabinet": [
        ("drawer_lower", "prismatic", "body", "drawer_lower", (1, 0, 0), 0.0, 0.16, (0.11, -0.0805, 0.0775), (0, 0, 0)),
        ("drawer_upper", "prismatic", "body", "drawer_upper", (1, 0, 0), 0.0, 0.16, (0.11, -0.0805, 0.1925), (0, 0, 0)),
        ("door", "revolute", "body", "door", (0, 0, 1), 0.0, 1.75, (0.11, 0.16, 0.135), (0, 0, 0)),
    ],
}


@pytest.mark.parametrize("name", MULTI_JOINT)
def test_multi_joint_splits_cover_the_joint_box(name):
    """Train: each joint takes 8 distinct values over most of its range and the joints vary together
    (no two move in lockstep); novel: values no train configuration has, away from every train one."""
    limits = {j[0]: (j[5], j[6]) for j in MULTI_JOINTS[name]}
    spec = tool_spec(name)
    span = np.array([hi - lo for lo, hi in limits.values()])
    low = np.array([lo for lo, _ in limits.values()])

    def unit(configurations):  # [n, k] in [0, 1] per joint
        return (np.array([[c[j] for j in limits] for c in configurations]) - low) / span

    train, novel = unit(spec.train_configurations), unit(spec.novel_configurations)
    for k in range(len(limits)):
        assert len(np.unique(train[:, k])) == 8 and np.ptp(train[:, k]) >= 0.85
        assert not set(novel[:, k].round(6)) & set(train[:, k].round(6))
    correlation = np.corrcoef(train.T)
    assert np.abs(correlation[~np.eye(len(limits), dtype=bool)]).max() < 0.5
    distance = np.linalg.norm(novel[:, None] - train[None], axis=-1).min(1)
    assert distance.min() >= 0.2 and np.all((novel > 0.1) & (novel < 0.9))


def test_only_the_cabinet_is_seen_otherwise_than_the_rig_sees_the_tools():
    assert {name: tool_spec(name).views for name in TOOLS} == {
        **{name: {} for name in TOOLS},
        "cabinet": {"distance": (0.6, 1.3), "azimuth_deg": (-75.0, 75.0), "elevation_deg": (10.0, 50.0)},
    }


@pytest.mark.parametrize("name", MULTI_JOINT)
def test_multi_joint_objects_are_deterministic_from_the_seed(name, built, tmp_path):
    first = built[name].parent
    again = build_tool(name, tmp_path / "again", seed=0).parent
    other = build_tool(name, tmp_path / "other", seed=1).parent
    files = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    expected = [f"meshes/{link}.{ext}" for link in sorted(LINKS[name]) for ext in ("mtl", "obj", "png")]
    assert [str(p) for p in files] == [*expected, "object.urdf"]
    for rel in files:
        assert (first / rel).read_bytes() == (again / rel).read_bytes(), rel
        assert ((first / rel).read_bytes() == (other / rel).read_bytes()) == (rel.suffix != ".png"), rel


@pytest.mark.parametrize("name", MULTI_JOINT)
def test_multi_joint_kinematics(name, built):
    """The one URDF reader sees the designed joints, one rigid part per link, and a size the camera rig frames."""
    tree = KinematicTree.from_urdf(built[name])
    assert tree.links_in_file == list(LINKS[name]) and tree.root == LINKS[name][0]
    assert tree.parts == [[link] for link in tree.links]
    assert tree.joint_names == [j[0] for j in MULTI_JOINTS[name]]
    for joint, (_, kind, parent, child, axis, lower, upper, xyz, rpy) in zip(tree.movable, MULTI_JOINTS[name]):
        assert (joint.type, joint.parent, joint.child) == (kind, parent, child)
        assert (joint.lower, joint.upper) == pytest.approx((lower, upper))
        np.testing.assert_allclose(joint.axis, axis, atol=1e-12)
        np.testing.assert_allclose(joint.origin[:3, 3], xyz, atol=1e-12)
        np.testing.assert_allclose(joint.origin[:3, :3], euler_matrix(*rpy, "sxyz")[:3, :3], atol=1e-6)  # Rz Ry Rx
    extent = np.ptp(tree.bounds(), axis=0)
    assert 0.15 <= extent.max() <= 0.5 and extent.min() >= 0.05, extent


def test_lamp_is_a_chain_whose_head_moves_with_every_joint(built):
    tree = KinematicTree.from_urdf(built["lamp"])
    theta = tree.mid_configuration()
    head = tree.links.index("head")
    shade = torch.tensor([0.0, 0.05, 0.0, 1.0], dtype=torch.float64)  # the shade's middle, head frame
    for k in range(3):
        moved = theta.clone()
        moved[k] += 0.1
        shift = (tree.link_poses(moved)[head] - tree.link_poses(theta)[head]) @ shade
        assert float(shift.norm()) > 0.004, tree.joint_names[k]
        assert abs(float(shift[1])) < 1e-12  # the arm swings in the xz plane
    rest = tree.link_poses(torch.zeros(3, dtype=torch.float64))
    np.testing.assert_allclose(rest[head, :3, 3].numpy(), [0.15, -0.0, 0.05 + 0.18], atol=1e-12)  # up, then forward
    np.testing.assert_allclose(rest[head, :3, 1].numpy(), [0.0, 0.0, -1.0], atol=1e-12)  # the shade hangs down


def test_gripper_fingers_open_in_opposite_directions(built):
    tree = KinematicTree.from_urdf(built["gripper"])
    poses = tree.link_poses(torch.tensor([[0.0, 0.0], [0.03, 0.01]], dtype=torch.float64))
    left, right = tree.links.index("finger_left"), tree.links.index("finger_right")
    np.testing.assert_allclose((poses[1, left, :3, 3] - poses[0, left, :3, 3]).numpy(), [0, 0.03, 0], atol=1e-12)
    np.testing.assert_allclose((poses[1, right, :3, 3] - poses[0, right, :3, 3]).numpy(), [0, -0.01, 0], atol=1e-12)


def test_cabinet_drawers_slide_out_and_the_door_swings_open(built):
    tree = KinematicTree.from_urdf(built["cabinet"])
    poses = tree.link_poses(torch.tensor([[0.1, 0.05, math.pi / 2]], dtype=torch.float64))[0]
    rest = tree.link_poses(torch.zeros(3, dtype=torch.float64))
    for link, out in (("drawer_lower", 0.1), ("drawer_upper", 0.05)):
        i = tree.links.index(link)
        np.testing.assert_allclose((poses[i, :3, 3] - rest[i, :3, 3]).numpy(), [out, 0, 0], atol=1e-12)
    door = tree.links.index("door")
    np.testing.assert_allclose(poses[door, :3, 3].numpy(), rest[door, :3, 3].numpy(), atol=1e-12)  # on its hinge
    np.testing.assert_allclose(poses[door, :3, 1].numpy(), [-1.0, 0.0, 0.0], atol=1e-12)  # +y (along the door) now points back


def _inside_points(link, n: int, rng: np.random.Generator) -> np.ndarray:
    """``[m, 3]`` points inside the link's prisms, about ``n`` in all, spread by volume."""
    points = []
    volumes = np.array([p.outline.area * (p.z[1] - p.z[0]) for p in link.prisms])
    for prism, count in zip(link.prisms, np.maximum(20, (n * volumes / volumes.sum()).astype(int))):
        x0, y0, x1, y1 = prism.outline.bounds
        candidates = rng.uniform([x0, y0, prism.z[0]], [x1, y1, prism.z[1]], size=(count * 4, 3))
        keep = shapely.contains_xy(prism.outline, candidates[:, 0], candidates[:, 1])
        points.append(candidates[keep][:count])
    return np.concatenate(points)


def _inside_link(link, points: np.ndarray, margin: float) -> np.ndarray:
    """``[m]`` whether each link-frame point lies deeper than ``margin`` inside one of the link's prisms."""
    inside = np.zeros(len(points), dtype=bool)
    for prism in link.prisms:
        core = prism.outline.buffer(-margin)
        in_z = (points[:, 2] > prism.z[0] + margin) & (points[:, 2] < prism.z[1] - margin)
        inside |= in_z & shapely.contains_xy(core, points[:, 0], points[:, 1])
    return inside


@pytest.mark.parametrize("name", MULTI_JOINT)
def test_links_never_overlap_in_the_joint_box(name, built):
    """Solid points of each link never lie inside another link, at the corners of the joint box, the
    spec's configurations and random ones (surfaces may touch: a finger's carriage rides on the rail)."""
    design = _DESIGNS[name]()
    tree = KinematicTree.from_urdf(built[name], load_meshes=False)
    rng = np.random.default_rng(0)
    spec = tool_spec(name)
    corners = np.array(list(itertools.product(*zip(tree.lower.tolist(), tree.upper.tolist()))))
    random = tree.lower.numpy() + (tree.upper - tree.lower).numpy() * rng.random((24, tree.n_joints))
    named = [[c[j] for j in tree.joint_names] for c in spec.train_configurations + spec.novel_configurations]
    theta = torch.as_tensor(np.concatenate([corners, random, np.array(named)]))
    poses = tree.link_poses(theta).numpy()  # [n, links, 4, 4]
    links = {link.name: link for link in design.links}
    points = {name_: _inside_points(link, 1500, rng) for name_, link in links.items()}
    for a, b in itertools.permutations(tree.links, 2):
        i, j = tree.links.index(a), tree.links.index(b)
        T_b_a = np.linalg.inv(poses[:, j]) @ poses[:, i]  # [n, 4, 4]
        moved = points[a] @ T_b_a[:, :3, :3].transpose(0, 2, 1) + T_b_a[:, None, :3, 3]  # [n, m, 3]
        hits = _inside_link(links[b], moved.reshape(-1, 3), margin=3e-4).reshape(len(theta), -1)
        assert not hits.any(), (a, b, theta[hits.any(1)][:3].tolist())


@pytest.mark.parametrize("name", MULTI_JOINT)
def test_multi_joint_textures_vary_on_every_link(name, built):
    for link in LINKS[name]:
        image = np.asarray(Image.open(built[name].parent / "meshes" / f"{link}.png"))
        painted = image[image.max(-1) > 0].astype(np.int64)
        assert len(np.unique(painted @ [65536, 256, 1])) > 250, link
        assert (painted / 255).std(0).mean() > 0.04, link


@pytest.mark.parametrize("name", MULTI_JOINT)
def test_small_synth_of_a_multi_joint_object_labels_every_link(name, tmp_path):
    pytest.importorskip("pybullet")
    from narf_core.data.dataset import Dataset
    from narf_core.data.synth.generate import ViewSampling, synthesize

    spec = tool_spec(name)
    ds = Dataset.open(synthesize(name, tmp_path / name, size=(64, 48), views=8, seed=0, supersample=1))
    assert ds.links == list(LINKS[name]) and [j["name"] for j in ds.joints] == [j[0] for j in MULTI_JOINTS[name]]
    assert [f.joints for f in ds.frames("train")] == spec.train_configurations
    sampling = {**asdict(ViewSampling()), **spec.views}  # the cabinet from farther away and from its front
    assert ds.generator["sampling"] == {key: list(v) if isinstance(v, tuple) else v for key, v in sampling.items()}
    assert {tuple(f.joints.values()) for f in ds.frames("novel")} == {tuple(c.values()) for c in spec.novel_configurations}
    for split in ("train", "test", "novel"):
        seen = set()
        for frame in ds.frames(split):
            seen |= set(np.unique(ds.load(frame).labels).tolist())
        assert seen == set(range(len(LINKS[name]) + 1)), (split, seen)  # the background and every link
