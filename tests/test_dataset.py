"""The dataset format (docs/design.md §3): write -> read round trips, and every malformed input is refused
with a message naming the file or JSON field that is wrong."""

from __future__ import annotations

import json
import math
from re import escape as re_escape
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from narf_core.data.dataset import (
    Dataset,
    DatasetError,
    DatasetWriter,
    FrameImages,
    UrdfError,
    copy_urdf,
    read_urdf,
)
from narf_core.depth import depth_to_mm, mm_to_depth
from narf_core.geometry import Pinhole

ASSETS = Path(__file__).parent / "assets"
ARTICULATED_URDF = ASSETS / "synth_articulated.urdf"
W, H = 8, 6


def images(seed: int, n_links: int = 4) -> FrameImages:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.2, 3.0, size=(H, W)).astype(np.float32)
    depth[0, :3] = 0.0  # no return
    labels = rng.integers(0, n_links + 1, size=(H, W)).astype(np.uint8)
    return FrameImages(rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8), depth, labels)


def pose(angle: float, t=(0.01, -0.02, 0.6)) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def write_small(root: Path, **kwargs) -> Path:
    camera = Pinhole(torch.tensor([[9.0, 0, 4.0], [0, 8.0, 3.0], [0, 0, 1]]), W, H)
    with DatasetWriter(root, read_urdf(ARTICULATED_URDF), camera, {"tool": "test"}, **kwargs) as w:
        w.add("train", images(0), pose(0.1), {"slide": 0.0, "lever": -1.2})
        w.add("test", images(1), pose(0.2), {"slide": 0.12, "lever": 1.2})
        w.add("novel", images(2), pose(-3.1), {"slide": 0.05, "lever": 0.3})
    return root


@pytest.fixture
def small(tmp_path) -> Path:
    return write_small(tmp_path / "ds")


def test_round_trip(small):
    ds = Dataset.open(small)
    assert ds.links == ["bar", "jaw", "lever", "tip"]
    assert [j["name"] for j in ds.joints] == ["slide", "lever"]
    assert ds.camera.K.dtype == torch.float32 and (ds.camera.width, ds.camera.height) == (W, H)
    assert ds.camera.K[0, 0].item() == 9.0 and ds.generator["tool"] == "test"
    assert [f.split for f in ds.frames()] == ["train", "test", "novel"]
    assert [f.id for f in ds.frames("test")] == [1]
    for i, frame in enumerate(ds.frames()):
        expected = images(i)
        got = ds.load(frame)
        np.testing.assert_array_equal(got.rgb, expected.rgb)
        np.testing.assert_array_equal(got.labels, expected.labels)
        assert got.depth.dtype == np.float32
        assert np.abs(got.depth - expected.depth).max() <= 0.0005 + 1e-7  # rounded to millimetres
        assert (got.depth[0, :3] == 0).all()
    np.testing.assert_array_equal(ds.frames()[2].T_cam_obj, pose(-3.1))
    assert ds.frames()[1].joints == {"slide": 0.12, "lever": 1.2}
    assert not ds.noisy and Dataset.open(small, clean=True).frames()[0].rgb == ds.frames()[0].rgb


def test_depth_png_is_uint16_millimetres(small):
    with Image.open(small / "depth/000000.png") as im:
        assert im.mode == "I;16"
        mm = np.asarray(im)
    assert mm.dtype == np.uint16
    np.testing.assert_array_equal(mm, np.rint(images(0).depth.astype(np.float64) * 1000))
    assert (mm[0, :3] == 0).all() and mm[1:].min() >= 200
    # the one codec saturates: a positive depth never reads back as "no return", 65.6 m is 65535
    assert depth_to_mm(np.array([[0.0, 0.0004, 0.0015001, 65.535, 65.6]])).tolist() == [[0, 1, 2, 65535, 65535]]
    assert mm_to_depth(depth_to_mm(np.array([0.25, 0.0]))).tolist() == [0.25, 0.0]


def test_npy_depth_is_read_as_metres(small):
    scene = json.loads((small / "scene.json").read_text())
    depth = np.full((H, W), 0.75, dtype=np.float32)
    np.save(small / "depth/000000.npy", depth)
    scene["frames"][0]["depth"] = "depth/000000.npy"
    (small / "scene.json").write_text(json.dumps(scene))
    ds = Dataset.open(small)
    np.testing.assert_array_equal(ds.load(ds.frames()[0]).depth, depth)


def test_clean_frames(tmp_path):
    camera = Pinhole(torch.tensor([[9.0, 0, 4.0], [0, 8.0, 3.0], [0, 0, 1]]), W, H)
    clean_images = images(0)
    noisy_images = FrameImages(clean_images.rgb, clean_images.depth + 0.01, clean_images.labels // 2)
    with DatasetWriter(tmp_path / "n", read_urdf(ARTICULATED_URDF), camera) as w:
        w.add("train", noisy_images, pose(0.11), {"slide": 0.01, "lever": 0.0},
              clean=(clean_images, pose(0.1), {"slide": 0.0, "lever": 0.0}))
    noisy, clean = Dataset.open(tmp_path / "n"), Dataset.open(tmp_path / "n", clean=True)
    assert noisy.noisy and clean.clean
    assert clean.frames()[0].joints["slide"] == 0.0 and noisy.frames()[0].joints["slide"] == 0.01
    assert clean.frames()[0].labels == "clean/labels/000000.png" and clean.frames()[0].rgb == "rgb/000000.png"
    np.testing.assert_array_equal(clean.load(clean.frames()[0]).labels, clean_images.labels)
    np.testing.assert_array_equal(noisy.load(noisy.frames()[0]).labels, clean_images.labels // 2)


def test_copy_urdf_with_obj_mtl_texture(tmp_path):
    pkg = tmp_path / "my_pkg"
    (pkg / "meshes" / "textures").mkdir(parents=True)
    (pkg / "urdf").mkdir()
    (pkg / "meshes/part.obj").write_text("mtllib part.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n")
    (pkg / "meshes/part.mtl").write_text("newmtl m\nmap_Kd -s 1 1 1 textures/part.png\n")
    Image.fromarray(np.zeros((2, 2, 3), np.uint8)).save(pkg / "meshes/textures/part.png")
    urdf = pkg / "urdf/robot.urdf"
    urdf.write_text(
        '<robot name="r"><link name="a"><visual><geometry><mesh filename="package://my_pkg/meshes/part.obj"/>'
        '</geometry></visual><collision><geometry><mesh filename="../meshes/part.obj"/></geometry></collision>'
        "</link></robot>"
    )
    info = read_urdf(urdf)
    assert info.links == ["a"] and info.joints == [] and len(info.meshes) == 2
    out = tmp_path / "copy"
    out.mkdir()
    copied = copy_urdf(info, out)
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()) == [
        "meshes/part.mtl", "meshes/part.obj", "meshes/textures/part.png", "object.urdf",
    ]
    again = read_urdf(copied)
    assert set(again.meshes) == {"meshes/part.obj"} and again.meshes["meshes/part.obj"] == out / "meshes/part.obj"


@pytest.mark.parametrize(
    "text, message",
    [  # the URDF rules are KinematicTree's (tests/test_kinematics.py); these are what the dataset adds or relies on
        ("<robot><link", "not valid XML"),
        ('<robot name="r"><link name="a"><visual><geometry><mesh filename="meshes/none.obj"/></geometry></visual></link></robot>',
         "link 'a': mesh file 'meshes/none.obj' not found"),
        ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="prismatic"><parent link="a"/><child link="b"/><limit lower="0.1" upper="0.1"/></joint></robot>',
         "joint 'j' has limits [0.1, 0.1]; they must be finite with lower < upper"),
        ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute"><parent link="a"/><child link="b"/><limit lower="0" upper="1"/><mimic joint="k"/></joint></robot>',
         "joint 'j' mimics 'k', which is no joint"),
    ],
)
def test_read_urdf_rejects(tmp_path, text, message):
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    with pytest.raises(UrdfError, match=f"bad.urdf: .*{re_escape(message)}"):
        read_urdf(path)


def test_read_urdf_joint_kinds(tmp_path):
    path = tmp_path / "kinds.urdf"
    path.write_text(
        '<robot name="r"><link name="a"/><link name="b"/><link name="c"/>'
        '<joint name="spin" type="continuous"><parent link="a"/><child link="b"/></joint>'
        '<joint name="follow" type="revolute"><parent link="b"/><child link="c"/><limit lower="-1" upper="1"/>'
        '<mimic joint="spin" multiplier="-0.5" offset="0.1"/></joint></robot>'
    )
    info = read_urdf(path)
    assert info.joints == [{"name": "spin", "type": "continuous", "lower": -math.pi, "upper": math.pi}]
    assert info.mimics == {"follow": ("spin", -0.5, 0.1)}
    assert read_urdf(ARTICULATED_URDF).links == ["bar", "jaw", "lever", "tip"]
    with pytest.raises(UrdfError, match=r"missing.urdf: no such URDF file$"):
        read_urdf(tmp_path / "missing.urdf")


def _edit(root: Path, change) -> None:
    scene = json.loads((root / "scene.json").read_text())
    change(scene)
    (root / "scene.json").write_text(json.dumps(scene))


def _set(path: str, value):
    """A change that sets ``scene[path]`` (dotted keys, integer indices)."""

    def change(scene):
        *parents, last = [int(k) if k.isdigit() else k for k in path.split(".")]
        node = scene
        for key in parents:
            node = node[key]
        node[last] = value

    return change


BAD_SCENES = [
    (_set("camera.K", [[1, 0, 0], [0, 1, 0]]), "camera.K: expected a 3x3 array"),
    (_set("camera.K", [[0, 0, 4], [0, 8, 3], [0, 0, 1]]), "camera.K: focal lengths"),
    (_set("camera.K", [[9, 0, 4], [0, 8, 3], [0, 0, 2]]), "camera.K: must be upper triangular"),
    (_set("camera.width", 0), "camera.width: expected an integer >= 1, got 0"),
    (_set("camera.height", 6.5), "camera.height: expected an integer >= 1, got 6.5"),
    (_set("links", ["bar", "bar"]), "links: link names must be unique"),
    (_set("links", ["bar", "handle"]), "links ['handle'] are not in object.urdf"),
    (_set("joints.0.type", "ball"), "joints[0].type: expected one of revolute, prismatic, continuous"),
    (_set("joints.0.lower", 1.0), "joints[0]: lower 1.0 must be < upper 0.12"),
    (_set("joints.1.upper", 2.0), "joints[1]: 'lever' does not match object.urdf"),
    (_set("joints.0.name", "slider"), "joints[0]: 'slider' is not an actuated joint"),
    (_set("frames.1.id", 0), "frames[1].id: duplicate id 0"),
    (_set("frames.0.rgb", "rgb/999999.png"), "frames[0].rgb: file 'rgb/999999.png' not found"),
    (_set("frames.0.labels", "../ds/labels/000000.png"), "frames[0].labels: '../ds/labels/000000.png' must be relative"),
    (_set("frames.2.T_cam_obj.0.0", 1.1), "frames[2].T_cam_obj has a rotation block that is not orthonormal"),
    (_set("frames.2.T_cam_obj.3", [0, 0, 1, 1]), "frames[2].T_cam_obj must have the last row [0, 0, 0, 1]"),
    (_set("frames.0.T_cam_obj", np.diag([1.0, 1, -1, 1]).tolist()), "frames[0].T_cam_obj has a rotation block that is a reflection"),
    (_set("frames.0.T_cam_obj.0.3", float("nan")), "frames[0].T_cam_obj[0][3]: expected a finite number, got nan"),
    (_set("frames.0.joints", {"slide": 0.0}), "frames[0].joints: missing value(s) for joint(s) ['lever']"),
    (_set("frames.0.joints.jaw", 0.0), "frames[0].joints: unknown joint(s) ['jaw']"),
    (_set("frames.1.joints.slide", 0.1201), "frames[1].joints: joint 'slide': 0.1201 is outside its limits [0.0, 0.12] (m)"),
    (_set("frames.1.joints.lever", "1"), "frames[1].joints: joint 'lever': value must be a number, got str '1'"),
    (_set("frames.2.split", "val"), "frames[2].split: expected one of train, test, novel, got 'val'"),
    (_set("frames", {}), "frames: expected a list of frames"),
    (_set("generator.clean_frames", [{"id": -1}]), "generator.clean_frames[0].id: expected an integer >= 0"),
]


@pytest.mark.parametrize("change, message", BAD_SCENES, ids=[m.split(":")[0] for _, m in BAD_SCENES])
def test_open_rejects(small, change, message):
    _edit(small, change)
    with pytest.raises(DatasetError, match=re_escape(message)):
        Dataset.open(small, clean=True)


@pytest.mark.parametrize(
    "setup, message",
    [
        (lambda root: (root / "scene.json").write_text("{\"camera\": "), "scene.json: not valid JSON"),
        (lambda root: (root / "scene.json").unlink(), "scene.json: file not found"),
        (lambda root: (root / "object.urdf").unlink(), "object.urdf: file not found"),
        (lambda root: (root / "scene.json").write_text("[1]"), "scene.json: must be a JSON object"),
    ],
)
def test_open_rejects_files(small, setup, message):
    setup(small)
    with pytest.raises(DatasetError, match=re_escape(message)):
        Dataset.open(small)


def test_open_rejects_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match="not a dataset folder"):
        Dataset.open(tmp_path / "nothing")


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda root: Image.new("RGB", (W + 1, H)).save(root / "rgb/000001.png"), "rgb/000001.png: image is 9x6 but the camera in scene.json is 8x6"),
        (lambda root: Image.new("L", (W, H)).save(root / "rgb/000001.png"), "rgb/000001.png: expected an 8-bit RGB image, got mode L"),
        (lambda root: Image.new("L", (W, H), 5).save(root / "labels/000001.png"), "labels/000001.png: label 5 but scene.json lists only 4 links"),
        (lambda root: Image.new("L", (W, H)).save(root / "depth/000001.png"), "depth/000001.png: depth PNG must be 16-bit millimetres, got mode L"),
        (lambda root: (root / "labels/000001.png").write_bytes(b"not a png"), "labels/000001.png: not a readable image"),
    ],
)
def test_load_names_the_wrong_file(small, corrupt, message):
    corrupt(small)
    ds = Dataset.open(small)
    ds.load(ds.frames()[0])  # other frames are fine
    with pytest.raises(DatasetError, match=re_escape(message)):
        ds.load(ds.frames()[1])


def test_frames_rejects_unknown_split(small):
    with pytest.raises(ValueError, match="unknown split 'val'"):
        Dataset.open(small).frames("val")


def test_writer_folder_rules(tmp_path):
    root = write_small(tmp_path / "ds")
    with pytest.raises(FileExistsError, match="not empty"):
        write_small(root)
    write_small(root, overwrite=True)  # replaces a dataset
    assert len(Dataset.open(root)) == 3
    (root / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="notes.txt"):
        write_small(root, overwrite=True)  # never deletes what a dataset does not hold
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError):
        write_small(tmp_path / "file" / "ds")


def test_writer_leaves_no_scene_when_interrupted(tmp_path):
    camera = Pinhole(torch.tensor([[9.0, 0, 4.0], [0, 8.0, 3.0], [0, 0, 1]]), W, H)
    with pytest.raises(RuntimeError):
        with DatasetWriter(tmp_path / "x", read_urdf(ARTICULATED_URDF), camera) as w:
            w.add("train", images(0), pose(0.1), {"slide": 0.0, "lever": 0.0})
            raise RuntimeError("interrupted")
    assert not (tmp_path / "x/scene.json").exists()
    with pytest.raises(DatasetError, match="scene.json: file not found"):
        Dataset.open(tmp_path / "x")


@pytest.mark.parametrize(
    "bad, message",
    [
        (FrameImages(np.zeros((H, W, 3), np.uint8), None, np.zeros((H, W + 1), np.uint8)), "labels must be uint8 [6, 8]"),
        (FrameImages(np.zeros((H, W, 3), np.float32), None, np.zeros((H, W), np.uint8)), "rgb must be uint8 [6, 8, 3]"),
        (FrameImages(np.zeros((H, W, 3), np.uint8), None, np.full((H, W), 9, np.uint8)), "label 9 but the object has 4 links"),
    ],
)
def test_writer_rejects_bad_images(tmp_path, bad, message):
    camera = Pinhole(torch.tensor([[9.0, 0, 4.0], [0, 8.0, 3.0], [0, 0, 1]]), W, H)
    w = DatasetWriter(tmp_path / "w", read_urdf(ARTICULATED_URDF), camera)
    with pytest.raises(ValueError, match=re_escape(message)):
        w.add("train", bad, pose(0.0), {"slide": 0.0, "lever": 0.0})
    with pytest.raises(ValueError, match="unknown split"):
        w.add("val", images(0), pose(0.0), {"slide": 0.0, "lever": 0.0})
