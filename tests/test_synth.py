"""pybullet ground truth (render.py) and the dataset generator (generate.py).

The renderer is checked against geometry computed without pybullet: an exact ray/box intersection
for the projection (0 mislabelled pixels, depth < 1e-4 m, also with fx != fy, an off-centre
principal point and grazing faces), and a yourdfpy + trimesh (embree) ray cast of an articulated
URDF at its joint limits and of a procedural tool's textured OBJ meshes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yourdfpy

pytest.importorskip("pybullet")

from narf_core.data.dataset import Dataset, read_urdf  # noqa: E402
from narf_core.data.synth.generate import (  # noqa: E402
    NoiseOptions,
    ViewSampling,
    add_depth_noise,
    jitter_mask,
    perturb_configuration,
    perturb_pose,
    synthesize,
)
from narf_core.data.synth.render import (  # noqa: E402
    BulletScene,
    depth_buffer_to_z,
    opengl_projection,
    split_segmentation,
)
from narf_core.data.synth.tools import build_tool, tool_spec  # noqa: E402
from narf_core.geometry import Pinhole, invert_pose, look_at  # noqa: E402

ASSETS = Path(__file__).parent / "assets"
BOX_URDF = ASSETS / "synth_box.urdf"
ARTICULATED_URDF = ASSETS / "synth_articulated.urdf"


def camera_looking_at(eye, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    T_obj_cam = look_at(
        torch.tensor(eye, dtype=torch.float64),
        torch.tensor(target, dtype=torch.float64),
        torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
    )
    return invert_pose(T_obj_cam).numpy()


def pixel_rays(camera: Pinhole) -> np.ndarray:
    """Camera-frame ray directions ``[H, W, 3]`` through pixel centres, scaled to z = 1."""
    rays = camera.rays()
    d = (rays.directions / rays.z_per_t[:, None]).double().numpy()
    return d.reshape(camera.height, camera.width, 3)


def exact_box(camera: Pinhole, T_cam_box: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slab-test hit mask and z-depth ``[H, W]`` of a box (centred in its frame) per pixel centre."""
    T_box_cam = np.linalg.inv(T_cam_box)
    d = pixel_rays(camera) @ T_box_cam[:3, :3].T
    o = T_box_cam[:3, 3]
    half = size / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    t_near, t_far = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    hit = (t_far >= t_near) & (t_far > 0)
    return hit, np.where(hit, t_near, 0.0)  # t is z-depth since d has z = 1


def raycast_urdf(urdf_path, config, camera: Pinhole, T_cam_obj, sections=256):
    """Labels, z-depth and "hit a cylinder" ``[H, W]`` of a URDF of boxes, cylinders and meshes,
    ray cast with trimesh (embree) at configuration ``config``, its link poses from yourdfpy."""
    model = yourdfpy.URDF.load(str(urdf_path), build_scene_graph=True, load_meshes=False)
    model.update_cfg(config)
    links = [link.name for link in model.robot.links]
    meshes, face_labels, face_cylinder = [], [], []
    for link in model.robot.links:
        T_obj_link = model.get_transform(frame_to=link.name)
        for visual in link.visuals:
            g = visual.geometry
            if g.box is not None:
                mesh = trimesh.creation.box(extents=g.box.size)
            elif g.cylinder is not None:
                mesh = trimesh.creation.cylinder(radius=g.cylinder.radius, height=g.cylinder.length, sections=sections)
            else:
                mesh = trimesh.load(Path(urdf_path).parent / g.mesh.filename, force="mesh")
                mesh.apply_scale(1.0 if g.mesh.scale is None else g.mesh.scale)
            origin = visual.origin if visual.origin is not None else np.eye(4)
            mesh.apply_transform(T_obj_link @ origin)
            meshes.append(mesh)
            face_labels.append(np.full(len(mesh.faces), 1 + links.index(link.name)))
            face_cylinder.append(np.full(len(mesh.faces), g.cylinder is not None))
    scene = trimesh.util.concatenate(meshes)
    face_labels, face_cylinder = np.concatenate(face_labels), np.concatenate(face_cylinder)
    T_obj_cam = np.linalg.inv(T_cam_obj)
    dirs = pixel_rays(camera).reshape(-1, 3) @ T_obj_cam[:3, :3].T
    origins = np.broadcast_to(T_obj_cam[:3, 3], dirs.shape)
    locations, ray_index, face = scene.ray.intersects_location(origins, dirs, multiple_hits=False)
    n = camera.height * camera.width
    labels, depth, cylinder = np.zeros(n, dtype=np.uint8), np.zeros(n), np.zeros(n, dtype=bool)
    labels[ray_index] = face_labels[face]
    cylinder[ray_index] = face_cylinder[face]
    depth[ray_index] = ((locations - T_obj_cam[:3, 3]) @ T_obj_cam[:3, :3])[:, 2]
    shape = (camera.height, camera.width)
    return labels.reshape(shape), depth.reshape(shape), cylinder.reshape(shape)


def dilate(mask: np.ndarray) -> np.ndarray:
    """``mask [H, W]`` grown by one pixel (8-neighbourhood)."""
    padded = np.pad(mask, 1)
    h, w = mask.shape
    return np.any([padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)], axis=0)


# ---------------------------------------------------------------------------------------------
# projection and decoding


CAMERAS = {
    "primesense float32": Pinhole.primesense(160, 120),  # what the generator uses
    "fx!=fy, off-centre": Pinhole(torch.tensor([[171.0, 0, 71.3], [0, 139.0, 66.8], [0, 0, 1]], dtype=torch.float64), 160, 120),
    "odd size, far off-centre": Pinhole(torch.tensor([[95.0, 0, 30.1], [0, 120.0, 47.9], [0, 0, 1]], dtype=torch.float64), 97, 61),
}


@pytest.fixture(scope="module")
def box_scene():
    with BulletScene(read_urdf(BOX_URDF)) as scene:
        yield scene


def box_pose() -> tuple[np.ndarray, np.ndarray]:
    """The box visual's pose in the object frame and its size, read with yourdfpy (not pybullet)."""
    model = yourdfpy.URDF.load(str(BOX_URDF), build_scene_graph=False, load_meshes=False)
    visual = model.robot.links[0].visuals[0]
    return visual.origin, np.asarray(visual.geometry.box.size)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_supersampling_keeps_labels_and_depth_exact(box_scene, name):
    camera = CAMERAS[name]
    T_cam_obj = camera_looking_at((0.25, -0.2, 0.3), target=(0.01, -0.005, 0.0))
    T_obj_box, size = box_pose()
    hit, z = exact_box(camera, T_cam_obj @ T_obj_box, size)
    point = box_scene.render(camera, T_cam_obj)
    area = box_scene.render(camera, T_cam_obj, supersample=3)
    assert np.count_nonzero((area.labels > 0) != hit) == 0
    assert np.abs(area.depth[hit] - z[hit]).max() < 1e-4
    # colour: the mean of the samples that share the pixel's label, so it never mixes in background
    background = point.rgb[~hit].reshape(-1, 3)[0]
    assert (area.rgb[~hit] == background).all()
    assert np.abs(area.rgb[hit].astype(int) - background.astype(int)).sum(-1).min() > 0
    with pytest.raises(ValueError, match="odd"):
        box_scene.render(camera, T_cam_obj, supersample=2)


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("eye", [(0.25, -0.2, 0.3), (-0.1, 0.35, 0.15)])
def test_render_matches_exact_box(box_scene, name, eye):
    camera = CAMERAS[name]
    T_cam_obj = camera_looking_at(eye, target=(0.01, -0.005, 0.0))
    T_obj_box, size = box_pose()
    hit, z = exact_box(camera, T_cam_obj @ T_obj_box, size)
    out = box_scene.render(camera, T_cam_obj)
    assert hit.sum() > 300
    assert np.count_nonzero((out.labels > 0) != hit) == 0
    assert np.abs(out.depth[hit] - z[hit]).max() < 1e-4
    assert (out.depth[~hit] == 0).all()
    assert out.rgb.dtype == np.uint8 and out.rgb.shape == (camera.height, camera.width, 3)


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_render_matches_exact_box_face_on(box_scene, name, axis):
    """Looking straight at a face: the four side faces are grazing and the box's edges run along
    pixel rows and columns."""
    camera = CAMERAS[name]
    T_obj_box, size = box_pose()
    centre, normal, up = T_obj_box[:3, 3], T_obj_box[:3, axis], T_obj_box[:3, (axis + 1) % 3]
    T_obj_cam = look_at(*(torch.from_numpy(v) for v in (centre + 0.3 * normal, centre, up)))
    T_cam_obj = invert_pose(T_obj_cam).numpy()
    hit, z = exact_box(camera, T_cam_obj @ T_obj_box, size)
    out = box_scene.render(camera, T_cam_obj)
    assert hit.sum() > 300
    assert np.count_nonzero((out.labels > 0) != hit) == 0
    assert np.abs(out.depth[hit] - z[hit]).max() < 1e-4


def test_textbook_projection_is_half_pixel_off(box_scene, monkeypatch):
    """Without the half-pixel terms (principal point used as is) silhouettes shift: the test above
    would catch it."""
    import narf_core.data.synth.render as render

    camera = CAMERAS["primesense float32"]
    T_cam_obj = camera_looking_at((0.25, -0.2, 0.3))
    hit, _ = exact_box(camera, T_cam_obj @ box_pose()[0], box_pose()[1])

    def textbook(K, width, height, near, far):
        shifted = K.copy()
        shifted[0, 2] += 0.5
        shifted[1, 2] -= 0.5  # cancels the correction inside opengl_projection
        return opengl_projection(shifted, width, height, near, far)

    monkeypatch.setattr(render, "opengl_projection", textbook)
    out = box_scene.render(camera, T_cam_obj)
    assert np.count_nonzero((out.labels > 0) != hit) > 20


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_buffer_to_z(dtype):
    near, far = 0.1, 10.0
    buffer = np.array([0.0, 1.0, 0.5], dtype=dtype)
    z = depth_buffer_to_z(buffer, near, far)
    assert z[0] == pytest.approx(near) and z[1] == pytest.approx(far)
    assert z[2] == pytest.approx(2 * far * near / (far + near))  # NDC depth 0 <-> harmonic mean
    P = opengl_projection(np.diag([100.0, 100.0, 1.0]), 64, 64, near, far)
    clip = P @ np.array([0.0, 0.0, -0.7, 1.0])  # a point 0.7 m in front of the GL camera
    assert depth_buffer_to_z(0.5 * clip[2] / clip[3] + 0.5, near, far) == pytest.approx(0.7)


def test_projection_rejects_bad_clip_range():
    with pytest.raises(ValueError, match="near"):
        opengl_projection(np.eye(3), 4, 4, 0.0, 1.0)


def test_split_segmentation():
    seg = np.array([-1, 3, (2 + 1) << 24 | 5, (0 + 1) << 24 | 7])
    body, link = split_segmentation(seg)
    assert body.tolist() == [-1, 3, 5, 7]
    assert link.tolist() == [-1, -1, 2, 0]


# ---------------------------------------------------------------------------------------------
# the articulated object against an independent ray cast


@pytest.fixture(scope="module")
def articulated_scene():
    with BulletScene(read_urdf(ARTICULATED_URDF)) as scene:
        yield scene


@pytest.mark.parametrize(
    "config", [{"slide": 0.0, "lever": -1.2}, {"slide": 0.12, "lever": 1.2}, {"slide": 0.05, "lever": 0.3}]
)
def test_render_matches_raycast(articulated_scene, config):
    camera = Pinhole(torch.tensor([[150.0, 0, 62.0], [0, 140.0, 50.5], [0, 0, 1]], dtype=torch.float64), 128, 96)
    T_cam_obj = camera_looking_at((0.12, -0.22, 0.25), target=(0.05, 0.0, 0.02))
    articulated_scene.set_configuration(config)
    out = articulated_scene.render(camera, T_cam_obj)
    labels, depth, cylinder = raycast_urdf(ARTICULATED_URDF, config, camera, T_cam_obj)
    assert set(np.unique(labels)) == {0, 1, 2, 3}
    # pybullet draws a cylinder as a coarse prism (seen end-on, its outline swings between about
    # 0.99 and 1.02 of the radius): allow disagreement only within a pixel of a cylinder.
    wrong = out.labels != labels
    assert np.count_nonzero(wrong & ~dilate(dilate(cylinder))) == 0
    assert np.count_nonzero(wrong) < 0.25 * np.count_nonzero(cylinder)
    boxes = (labels > 0) & ~dilate(cylinder | wrong)
    assert np.count_nonzero(boxes) > 1000
    assert np.abs(out.depth[boxes] - depth[boxes]).max() < 1e-4
    inside_cylinder = cylinder & ~dilate(~cylinder | wrong)  # away from its grazing silhouette
    # facets vs the true surface, seen obliquely: a quarter of the 12 mm radius, i.e. placed right
    assert np.abs(out.depth[inside_cylinder] - depth[inside_cylinder]).max() < 3e-3


@pytest.fixture(scope="module")
def longnose(tmp_path_factory) -> Path:
    return build_tool("longnose", tmp_path_factory.mktemp("longnose"))


@pytest.mark.parametrize("pivot", [0.0, 0.6])
def test_textured_tool_matches_raycast(longnose, pivot):
    """The procedural tools' OBJ meshes: pybullet and trimesh see the same triangles."""
    camera = Pinhole.primesense(128, 96, dtype=torch.float64)
    config = {"pivot": pivot}
    with BulletScene(read_urdf(longnose)) as scene:
        scene.set_configuration(config)
        centre = scene.bounds().mean(0)
        T_cam_obj = camera_looking_at(centre + [0.1, -0.15, 0.2], target=centre)
        out = scene.render(camera, T_cam_obj)
    labels, depth, _ = raycast_urdf(longnose, config, camera, T_cam_obj)
    assert np.count_nonzero(labels == 1) > 100 and np.count_nonzero(labels == 2) > 100
    assert np.count_nonzero(out.labels != labels) <= 2  # at most a grazing pixel or two
    hit = (labels > 0) & (out.labels == labels)
    assert np.abs(out.depth[hit] - depth[hit]).max() < 1e-4
    assert len(np.unique(out.rgb[labels > 0].reshape(-1, 3), axis=0)) > 50  # textured, not flat


def test_bounds_follow_configuration(articulated_scene):
    articulated_scene.set_configuration({"slide": 0.0, "lever": 0.0})
    closed = articulated_scene.bounds()
    articulated_scene.set_configuration({"slide": 0.12, "lever": 0.0})
    opened = articulated_scene.bounds()
    assert opened[1, 0] > closed[1, 0] + 0.03  # the jaw and lever slid along +x
    assert opened[0].tolist() == pytest.approx(closed[0].tolist())


@pytest.mark.parametrize(
    "config, message",
    [
        ({"slide": 0.13, "lever": 0.0}, "outside its limits"),
        ({"slide": float("nan"), "lever": 0.0}, "joint 'slide': value must be finite"),
        ({"slide": 0.0}, "missing value\\(s\\) for joint\\(s\\) \\['lever'\\]"),
        ({"slide": 0.0, "lever": 0.0, "jaw": 1.0}, "unknown joint\\(s\\) \\['jaw'\\]"),
    ],
)
def test_set_configuration_rejects(articulated_scene, config, message):
    with pytest.raises(ValueError, match=message):
        articulated_scene.set_configuration(config)


def test_table_is_background_with_depth():
    camera = Pinhole.primesense(80, 60)
    T_cam_obj = camera_looking_at((0.3, -0.3, 0.25), target=(0.05, 0.0, 0.02))
    config = {"slide": 0.06, "lever": 0.5}
    with BulletScene(read_urdf(ARTICULATED_URDF)) as plain, BulletScene(read_urdf(ARTICULATED_URDF), background=True) as table:
        plain.set_configuration(config)
        table.set_configuration(config)
        a, b = plain.render(camera, T_cam_obj), table.render(camera, T_cam_obj)
    assert np.array_equal(a.labels, b.labels)
    np.testing.assert_allclose(a.depth[a.labels > 0], b.depth[b.labels > 0], atol=1e-5)  # other far plane
    floor = (b.labels == 0) & (b.depth > 0)
    assert floor.mean() > 0.5 and (a.depth[a.labels == 0] == 0).all()
    assert b.rgb[floor].std() > 3  # textured, not flat
    # the table lies just under the object's lowest point
    lowest = table.bounds()[0, 2]
    assert b.depth[floor].min() > 0.1 and lowest == pytest.approx(-0.01)


# ---------------------------------------------------------------------------------------------
# views and noise


def test_view_sampling_ranges():
    rng = np.random.default_rng(0)
    sampling = ViewSampling(target_jitter=0.0)
    centre = np.array([0.05, -0.02, 0.03])
    for _ in range(200):
        T = sampling.sample(rng, centre, 0.1)
        eye = -T[:3, :3].T @ T[:3, 3]
        offset = eye - centre
        distance = np.linalg.norm(offset)
        elevation = math.degrees(math.asin(offset[2] / distance))
        assert 0.4 <= distance <= 1.0 and 15.0 <= elevation <= 75.0
        centre_cam = T[:3, :3] @ centre + T[:3, 3]
        assert centre_cam[:2] == pytest.approx([0.0, 0.0], abs=1e-9)  # looks at the centre
        assert np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() < 1e-12


def test_view_sampling_keeps_to_its_azimuths_and_draws_the_whole_turn_as_before():
    centre = np.zeros(3)
    front = ViewSampling(target_jitter=0.0, azimuth_deg=(-75.0, 75.0), elevation_deg=(10.0, 50.0))
    rng = np.random.default_rng(3)
    azimuths = []
    for _ in range(300):
        T = front.sample(rng, centre, 0.1)
        eye = -T[:3, :3].T @ T[:3, 3]
        azimuths.append(math.degrees(math.atan2(eye[1], eye[0])))
        assert 10.0 <= math.degrees(math.asin(eye[2] / np.linalg.norm(eye))) <= 50.0
    assert -75.0 <= min(azimuths) < -65.0 and 65.0 < max(azimuths) <= 75.0  # the front, all of it, never the back
    # the rig's whole turn: the same draws as a uniform azimuth over 2 pi (datasets made before stay the same)
    first, second = np.random.default_rng(4), np.random.default_rng(4)
    T = ViewSampling(target_jitter=0.0).sample(first, centre, 0.1)
    second.uniform(0.4, 1.0)
    elevation, azimuth = math.radians(second.uniform(15.0, 75.0)), second.uniform(0.0, 2 * math.pi)
    eye = -T[:3, :3].T @ T[:3, 3]
    assert math.atan2(eye[1], eye[0]) % (2 * math.pi) == pytest.approx(azimuth, abs=1e-12)
    assert math.asin(eye[2] / np.linalg.norm(eye)) == pytest.approx(elevation, abs=1e-12)


def test_jitter_mask_by_hand():
    labels = np.zeros((7, 7), dtype=np.uint8)
    labels[2:5, 2:5] = 1
    labels[3, 3] = 2
    dilated = jitter_mask(labels, 1)
    assert dilated[1, 3] == 1 and dilated[1, 1] == 0  # disk of radius 1: no diagonal growth
    assert dilated[3, 3] == 2 and np.count_nonzero(dilated) == 9 + 4 * 3
    eroded = jitter_mask(labels, -1)
    assert eroded.tolist() == (labels * (labels == 2)).tolist()  # only the centre survives
    assert np.array_equal(jitter_mask(labels, 0), labels)


def test_perturbations_are_valid_and_sized():
    rng = np.random.default_rng(1)
    T = camera_looking_at((0.3, 0.2, 0.4))
    angles, shifts = [], []
    for _ in range(300):
        T2 = perturb_pose(T, rng, rot_deg=2.0, trans_mm=5.0)
        R = T2[:3, :3]
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12 and np.linalg.det(R) > 0
        delta = R @ T[:3, :3].T
        angles.append(math.degrees(math.acos(np.clip((np.trace(delta) - 1) / 2, -1, 1))))
        shifts.append(np.linalg.norm(T2[:3, 3] - T[:3, 3]) * 1000)
    # |N(0, s^2 I_3)| has mean 2 sqrt(2/pi) s = 1.596 s
    assert np.mean(angles) == pytest.approx(1.596 * 2.0, rel=0.1)
    assert np.mean(shifts) == pytest.approx(1.596 * 5.0, rel=0.1)
    joints = [{"name": "a", "type": "revolute", "lower": -0.1, "upper": 0.1}]
    values = [perturb_configuration({"a": 0.1}, joints, rng, 0.05)["a"] for _ in range(100)]
    assert max(values) == 0.1 and min(values) < 0.05  # clipped at the limit, never beyond
    depth = np.array([[0.0, 0.5], [0.0005, 2.0]], dtype=np.float32)
    noisy = add_depth_noise(depth, rng, 0.01)
    assert noisy[0, 0] == 0 and noisy[1, 0] >= 1e-3 and noisy.dtype == np.float32


@pytest.mark.parametrize("kwargs", [{"rot_deg": -1.0}, {"trans_mm": float("nan")}, {"mask_px": 1.5}])
def test_noise_options_reject(kwargs):
    with pytest.raises(ValueError, match="noise"):
        NoiseOptions(**kwargs)


# ---------------------------------------------------------------------------------------------
# the generator end to end (tiny)


def test_synthesize_splits_and_determinism(tmp_path):
    a = synthesize(ARTICULATED_URDF, tmp_path / "a", size=(40, 30), views=6, seed=3)
    b = synthesize(ARTICULATED_URDF, tmp_path / "b", size=(40, 30), views=6, seed=3)
    ds = Dataset.open(a)
    assert [len(ds.frames(s)) for s in ("train", "test", "novel")] == [6, 17, 17]
    train_configs = {tuple(f.joints.values()) for f in ds.frames("train")}
    assert len(train_configs) == 3
    assert {tuple(f.joints.values()) for f in ds.frames("test")} == train_configs
    novel_configs = {tuple(f.joints.values()) for f in ds.frames("novel")}
    assert len(novel_configs) == 3 and not novel_configs & train_configs
    mid = (0.06, 0.0)
    assert mid in train_configs
    for frame in ds.frames():
        images = ds.load(frame)
        assert np.count_nonzero(images.labels) >= 1
    scene_a = json.loads((a / "scene.json").read_text())
    scene_b = json.loads((b / "scene.json").read_text())
    assert scene_a == scene_b
    assert (a / "rgb/000005.png").read_bytes() == (b / "rgb/000005.png").read_bytes()
    c = synthesize(ARTICULATED_URDF, tmp_path / "c", size=(40, 30), views=8, seed=3)
    scene_c = json.loads((c / "scene.json").read_text())
    # more views: same configurations (independent random streams)
    assert scene_c["generator"]["configurations"] == scene_a["generator"]["configurations"]


def test_synthesize_noise_keeps_clean_truth(tmp_path):
    noise = NoiseOptions(rot_deg=2.0, trans_mm=5.0, theta=0.02, mask_px=1, depth_m=0.002)
    out = synthesize(ARTICULATED_URDF, tmp_path / "n", size=(48, 36), views=4, seed=0, noise=noise)
    noisy, clean = Dataset.open(out), Dataset.open(out, clean=True)
    assert noisy.noisy and len(noisy) == len(clean) == 4 + 17 + 17
    reference = synthesize(ARTICULATED_URDF, tmp_path / "r", size=(48, 36), views=4, seed=0)
    plain = Dataset.open(reference)
    changed_masks = 0
    for f_noisy, f_clean, f_plain in zip(noisy.frames(), clean.frames(), plain.frames(), strict=True):
        # the clean truth is exactly what a run without noise writes
        np.testing.assert_array_equal(f_clean.T_cam_obj, f_plain.T_cam_obj)
        assert f_clean.joints == f_plain.joints
        i_noisy, i_clean, i_plain = noisy.load(f_noisy), clean.load(f_clean), plain.load(f_plain)
        np.testing.assert_array_equal(i_clean.labels, i_plain.labels)
        np.testing.assert_array_equal(i_clean.depth, i_plain.depth)
        np.testing.assert_array_equal(i_noisy.rgb, i_plain.rgb)  # images stay clean
        assert f_noisy.rgb == f_clean.rgb
        assert not np.array_equal(f_noisy.T_cam_obj, f_clean.T_cam_obj)
        assert np.abs(f_noisy.T_cam_obj[:3, 3] - f_clean.T_cam_obj[:3, 3]).max() < 0.03
        changed_masks += not np.array_equal(i_noisy.labels, i_clean.labels)
    assert changed_masks > 10


def test_synthesize_tool_copies_textured_meshes(tmp_path):
    out = synthesize("longnose", tmp_path / "ln", size=(32, 24), views=2, seed=0, background=True)
    ds = Dataset.open(out)
    spec = tool_spec("longnose")
    assert ds.generator["configurations"] == {"train": spec.train_configurations, "novel": spec.novel_configurations}
    assert [f.joints for f in ds.frames("train")] == spec.train_configurations * 2
    assert {f.joints["pivot"] for f in ds.frames("novel")} == {spec.novel_configurations[0]["pivot"]}
    copied = sorted(p.name for p in (out / "meshes").iterdir())
    assert copied == sorted(f"{link}.{ext}" for link in ds.links for ext in ("obj", "mtl", "png"))
    assert set(read_urdf(ds.urdf_path).meshes) == {f"meshes/{link}.obj" for link in ds.links}
    images = ds.load(ds.frames()[0])
    assert (images.depth[images.labels == 0] > 0).mean() > 0.3  # the table returns depth


def test_synthesize_rigid_urdf(tmp_path):
    ds = Dataset.open(synthesize(BOX_URDF, tmp_path / "box", size=(24, 18), views=1))
    assert ds.joints == [] and len(ds) == 1 + 17 + 17
    assert all(f.joints == {} for f in ds.frames())


@pytest.mark.parametrize("bad", [np.eye(3), np.full((4, 4), np.nan)])
def test_render_rejects_bad_pose(box_scene, bad):
    with pytest.raises(ValueError, match="T_cam_obj must be a finite 4x4 matrix"):
        box_scene.render(CAMERAS["primesense float32"], bad)


def test_noise_presets():
    assert NoiseOptions.preset("paper") == NoiseOptions(rot_deg=2.0, trans_mm=5.0, theta=0.02, mask_px=1, depth_m=0.002)
    assert not NoiseOptions.preset("none").active
    with pytest.raises(ValueError, match="unknown noise preset 'loud'; expected one of none, paper"):
        NoiseOptions.preset("loud")
