"""The procedural tools: specs, determinism, URDF structure, meshes, textures, pybullet loading."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yourdfpy
from PIL import Image
from shapely.affinity import rotate
from shapely.ops import unary_union

from narf_core.data.synth.tools import _DESIGNS, TOOLS, ToolSpec, build_tool, tool_spec

LINKS = {
    "clamp": ("bar", "moving_jaw"),
    "lineman-a": ("lower_half", "upper_half"),
    "lineman-b": ("lower_half", "upper_half"),
    "longnose": ("lower_half", "upper_half"),
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
    "name, n_train, n_novel", [("clamp", 4, 3), ("lineman-a", 1, 3), ("lineman-b", 1, 3), ("longnose", 1, 1)]
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
    with pytest.raises(ValueError, match="unknown tool 'hammer'; known tools: clamp, lineman-a, lineman-b, longnose"):
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


@pytest.mark.parametrize("name", TOOLS)
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


@pytest.mark.parametrize("name", TOOLS)
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
