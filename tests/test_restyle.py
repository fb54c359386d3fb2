"""The Mitsuba restyler: camera and depth conventions, agreement with pybullet's ground truth, the
written datasets, and ``narf restyle``'s errors. Renders a few frames at a tiny size (seconds)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba")
pytest.importorskip("pybullet")

from narf_core.cli import main  # noqa: E402
from narf_core.data.dataset import Dataset  # noqa: E402
from narf_core.data.synth import restyle as rs  # noqa: E402
from narf_core.geometry import Pinhole  # noqa: E402


@pytest.fixture(scope="module")
def clamp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from narf_core.data.synth.generate import synthesize

    return synthesize("clamp", tmp_path_factory.mktemp("src") / "clamp", size=(96, 72), views=4, seed=0)


def _look_from(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``T_cam_obj`` of an OpenCV camera at ``eye`` looking at ``target`` (object z up)."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ eye
    return T


def _aov(camera: Pinhole, T_cam_obj: np.ndarray, shapes: dict) -> tuple[np.ndarray, list[str]]:
    mi = rs.mitsuba()
    scene = mi.load_dict({"type": "scene", **shapes, "sensor": rs.sensor(camera, T_cam_obj, spp=1, centres=True),
                          "integrator": {"type": "aov", "aovs": "pp:position,si:shape_index"}})
    return np.array(mi.render(scene), dtype=np.float64), [s.id() for s in scene.shapes()]


def test_opencv_camera_samples_every_pixel_centre() -> None:
    """The hit point seen at pixel (u, v) projects through K to (u + 0.5, v + 0.5), also with an
    off-centre principal point: Mitsuba's camera is the OpenCV camera of docs/design.md §2."""
    mi = rs.mitsuba()
    camera = Pinhole(torch.tensor([[70.0, 0, 41.3], [0, 70.0, 22.8], [0, 0, 1]]), 80, 50)
    T = _look_from(np.array([0.3, -0.8, 0.5]), np.array([0.0, 0.0, 0.0]))
    T_obj_cam = np.linalg.inv(T)
    # a plane facing the camera at z = 1.3 in the camera frame (tilted in the object frame)
    plane = T_obj_cam @ np.array([[4, 0, 0, 0], [0, 4, 0, 0], [0, 0, 1, 1.3], [0, 0, 0, 1.0]])
    aov, ids = _aov(camera, T, {"plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f(plane.tolist())}})
    depth, labels = rs.depth_and_labels(aov, T, ids, {"plane": 1})
    assert (labels == 1).all()
    assert np.abs(depth - 1.3).max() < 1e-4  # z along the optical axis, not the ray's length (up to 1.9% more here)
    p = aov[..., :3] @ T[:3, :3].T + T[:3, 3]
    uv = p @ camera.K.double().numpy().T
    uv = uv[..., :2] / uv[..., 2:]
    v, u = np.mgrid[0:50, 0:80]
    assert np.abs(uv[..., 0] - (u + 0.5)).max() < 1e-3 and np.abs(uv[..., 1] - (v + 0.5)).max() < 1e-3
    with pytest.raises(rs.RestyleError, match="square pixels"):
        rs.sensor(Pinhole(torch.tensor([[70.0, 0, 40], [0, 60.0, 25], [0, 0, 1]]), 80, 50), T, spp=1, centres=True)


def test_restyled_mask_and_depth_agree_with_pybullet(clamp: Path) -> None:
    dataset = Dataset.open(clamp)
    with rs.Restyler(dataset.urdf_path, dataset.links, spp=2) as restyler:
        for frame in dataset.frames("test")[:2]:
            truth = dataset.load(frame)
            render = restyler.render(dataset.camera, frame.T_cam_obj, frame.joints, (0, frame.id))
            tool = (truth.labels > 0) | (render.labels > 0)
            assert tool.sum() > 50
            assert (render.labels == truth.labels)[tool].mean() > 0.97
            both = (truth.labels > 0) & (render.labels == truth.labels)
            assert np.median(np.abs(render.depth[both] - truth.depth[both])) < 1e-3
            assert np.abs(render.depth[both] - truth.depth[both]).max() < 4e-3
            # the table and clutter have depth too, behind the tool where they meet it
            assert (render.depth[truth.labels == 0] > 0).mean() > 0.5
            assert render.linear.shape == (72, 96, 3) and np.isfinite(render.linear).all() and render.linear.max() > 0


def test_restyle_writes_each_condition_deterministically(clamp: Path, tmp_path: Path) -> None:
    source = Dataset.open(clamp)
    ids = [source.frames("test")[0].id, source.frames("novel")[0].id]
    out = rs.restyle(clamp, tmp_path / "a", conditions=("lighting", "all"), size=(64, 48), spp=2, seed=3, frame_ids=ids)
    assert set(out) == {"lighting", "all"}
    for name, root in out.items():
        d = Dataset.open(root)
        assert (d.camera.width, d.camera.height) == (64, 48)
        assert d.generator["condition"] == name and d.generator["restyle"]["source_frames"] == ids
        assert [f["source_id"] for f in d.generator["frames"]] == ids and d.generator["frames"][0]["scene"]["lights"]
        assert [f.split for f in d.frames()] == ["test", "novel"]
        for f, src in zip(d.frames(), [source.frames()[i] for i in ids]):
            assert np.allclose(f.T_cam_obj, src.T_cam_obj) and f.joints == src.joints
    lighting, faulty = Dataset.open(out["lighting"]), Dataset.open(out["all"])
    a, b = lighting.load(lighting.frames()[0]), faulty.load(faulty.frames()[0])
    assert 0 < (b.labels > 0).sum() < (a.labels > 0).sum()  # 20% occluded (and mask errors)
    assert faulty.generator["frames"][0]["faults"]["occluded"] == pytest.approx(0.2, abs=0.02)
    clean_set = Dataset.open(out["all"], clean=True)
    clean = clean_set.load(clean_set.frames()[0])
    assert (clean.labels == a.labels).all()  # the fault-free ground truth is kept
    again = rs.restyle(clamp, tmp_path / "b", conditions=("all",), size=(64, 48), spp=2, seed=3, frame_ids=ids)
    c = Dataset.open(again["all"]).load(Dataset.open(again["all"]).frames()[0])
    assert np.abs(c.rgb.astype(int) - b.rgb).max() <= 1 and (c.labels == b.labels).all()
    assert np.allclose(c.depth, b.depth)
    with pytest.raises(FileExistsError, match="already holds a dataset"):
        rs.restyle(clamp, tmp_path / "a", conditions=("all",), size=(64, 48), spp=2, seed=3, frame_ids=ids)


def test_a_restyled_sequence_keeps_its_times_and_one_scene(clamp: Path, tmp_path: Path, monkeypatch) -> None:
    """A sequence (frames with times) restyled: the times kept, one scene and one exposure / white balance
    error for all its frames (a camera moving through one room), the samples and the other faults per
    frame; a set of single views keeps a scene per frame."""
    from narf_core.data.synth.sequence import synthesize_sequence

    seq = synthesize_sequence("clamp", tmp_path / "seq", 3, size=(48, 36), events=False, supersample=1)
    out = rs.restyle(seq, tmp_path / "r", conditions=("noise", "occlusion-20"), spp=2, seed=5)
    source, restyled = Dataset.open(seq), Dataset.open(out["noise"])
    turns = np.diff([r["faults"]["occluder_direction_deg"] for r in Dataset.open(out["occlusion-20"]).generator["frames"]])
    assert turns[0] == pytest.approx(turns[1]) and 10 / 30 <= abs(turns[0]) <= 40 / 30  # one occluder, turning
    assert [f.time for f in restyled.frames()] == [f.time for f in source.frames()] != [None] * 3
    assert restyled.generator["restyle"]["scene_per"] == "sequence"
    records = restyled.generator["frames"]
    assert all(r["scene"] == records[0]["scene"] for r in records) and records[0]["scene"]["lights"]
    assert len({r["faults"]["exposure_ev"] for r in records}) == 1
    assert len({r["faults"]["white_balance"][0] for r in records}) == 1
    assert len({r["faults"]["blur_px"] for r in records}) == 3
    shared = []  # a part of the sequence is drawn in the whole sequence's scene (so its cached renders fit it)
    monkeypatch.setattr(rs, "Shared", lambda *a, real=rs.Shared: shared.append(real(*a)) or shared[-1])
    one = Dataset.open(rs.restyle(seq, tmp_path / "one", conditions=("noise",), spp=2, seed=5, frame_ids=[1])["noise"])
    assert len(shared) == 1 and len(shared[0].eyes) == 3
    assert one.generator["frames"][0]["scene"] == records[0]["scene"]  # the sequence's scene, not the frame's own
    assert (one.load(one.frames()[0]).rgb == restyled.load(restyled.frames()[1]).rgb).all()
    single = Dataset.open(rs.restyle(clamp, tmp_path / "s", conditions=("noise",), size=(48, 36), spp=2, seed=5,
                                     frame_ids=[0, 1])["noise"])
    assert single.generator["restyle"]["scene_per"] == "frame" and single.frames()[0].time is None
    first, second = (f["scene"] for f in single.generator["frames"])
    assert first != second
    assert len({f["faults"]["exposure_ev"] for f in single.generator["frames"]}) == 2


def test_a_restyled_sequence_keeps_its_occluding_bar(tmp_path: Path) -> None:
    """A sequence synthesised with events: its restyled frames hide the tool behind the same bar as pybullet's
    (background in the labels, the bar's depth) before any fault; a sequence with events that does not record
    its bar is refused with an error naming what to do."""
    from narf_core.data.synth.bar import bar_columns
    from narf_core.data.synth.sequence import synthesize_sequence

    seq = synthesize_sequence("clamp", tmp_path / "seq", 4, size=(48, 36), events=True, supersample=1)
    source = Dataset.open(seq)
    per_frame = source.generator["sequence"]["per_frame"]
    assert all(p["occluder"] is not None for p in per_frame) and max(p["occluded"] for p in per_frame) > 0
    restyled = Dataset.open(rs.restyle(seq, tmp_path / "r", conditions=("lighting",), spp=2, seed=5)["lighting"])
    hidden = 0  # the tool's pixels the path tracer drew in the bar's columns (its cached render, before the bar)
    for ours, theirs, p in zip(source.frames(), restyled.frames(), per_frame):
        cols = bar_columns(48, p["occluder"]["x"])
        a, b = source.load(ours), restyled.load(theirs)
        assert (a.labels[:, cols] == 0).all() and (b.labels[:, cols] == 0).all()
        assert np.allclose(b.depth[:, cols], p["occluder"]["z"], atol=2e-3)
        with np.load(tmp_path / "r" / "renders" / f"{ours.id:06d}.npz") as render:
            hidden += int(np.count_nonzero(render["labels"][:, cols]))
    assert hidden > 0
    scene = json.loads((seq / "scene.json").read_text())
    for p in scene["generator"]["sequence"]["per_frame"]:
        del p["occluder"]
    (seq / "scene.json").write_text(json.dumps(scene))
    with pytest.raises(rs.RestyleError, match="does not record its occluder"):
        rs.restyle(seq, tmp_path / "r2", conditions=("lighting",), spp=2, seed=5)


def test_cli_restyle_and_its_errors(clamp: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["restyle", str(clamp), "--out", str(tmp_path / "o"), "--size", "32", "24", "--spp", "1",
                 "--splits", "test", "--limit", "1", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["frames"] == 1 and result["size"] == [32, 24] and set(result["datasets"]) == {"lighting"}

    def error(argv: list[str]) -> str:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("narf restyle: error: ")
        return err

    assert "not a dataset folder" in error(["restyle", str(tmp_path / "missing"), "--out", str(tmp_path / "x")])
    assert "already holds a dataset" in error(["restyle", str(clamp), "--out", str(tmp_path / "o"), "--size", "32",
                                                "24", "--splits", "test", "--limit", "1"])
    with pytest.raises(SystemExit):
        main(["restyle", str(clamp), "--out", str(tmp_path / "y"), "--conditions", "fog"])
    assert "invalid choice: 'fog'" in capsys.readouterr().err


def test_missing_extra_is_one_clear_error(clamp: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # import mitsuba now raises ImportError
    assert main(["restyle", str(clamp), "--out", str(tmp_path / "z")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "narf restyle: error: the mitsuba renderer is not installed; install the extra: pip install 'narf[realism]'"
