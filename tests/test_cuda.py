"""The CUDA path: the bundled clamp loaded on a GPU renders, refines and tracks as on the CPU.

Every test but the first needs a CUDA device and is skipped without one (CI has none; the
GPU check is in docs/benchmarks.md). The views are the model's own renders (no data generator,
so that the check runs wherever torch does), the same on both devices.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from narf_core.bundle import load_bundle, resolve_device
from narf_core.cli import main
from narf_core.estimate import EstimateOptions, refine
from narf_core.geometry import Pinhole, so3_exp
from narf_core.metrics import add
from narf_core.track import TrackFrame, TrackOptions, track

CLAMP = Path(__file__).resolve().parent.parent / "models" / "clamp.narf"
CAMERA = Pinhole.primesense(160, 120)
JAW = "jaw_opening"
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def test_device_names_are_checked(monkeypatch) -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="not a torch device"):
        resolve_device("gpu0")
    with pytest.raises(ValueError, match="only 'cpu' and 'cuda'"):
        resolve_device("meta")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="sees no CUDA device"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match="has 1 CUDA device"):
        resolve_device("cuda:3")


def test_benchmarks_name_the_device_they_timed(monkeypatch) -> None:
    from types import SimpleNamespace

    from narf_benchmarks.load import describe_machine, device_of, machine

    on = lambda device: SimpleNamespace(aabb=torch.zeros(2, 3, device=device))  # noqa: E731
    assert device_of([on("cpu"), on("cpu")]) == "cpu" and device_of([]) == "none"
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device: "Some GPU")
    fake = SimpleNamespace(aabb=SimpleNamespace(device=torch.device("cuda", 1)))
    assert device_of([on("cpu"), fake]) == "cpu, cuda:1 (Some GPU)"
    record = machine([on("cpu")])
    assert record["device"] == "cpu" and record["cores"] >= 1
    assert describe_machine(record).startswith(" Measured on cpu, load ") and describe_machine(None) == ""


def test_cli_refuses_a_device_it_cannot_use_in_one_line(monkeypatch, tmp_path: Path, capsys) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code = main(["--device", "cuda", "render", str(CLAMP), "--pose", json.dumps(np.eye(4).tolist()),
                 "--out", str(tmp_path / "x.png")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("narf render: error: device 'cuda'"), err
    assert not (tmp_path / "x.png").exists()


def pose(turn, centre=(0.03, -0.02, 0.55), box=None) -> np.ndarray:
    """``T_cam_obj`` turning the object by ``turn`` (rotation vector) with its box centre at ``centre``."""
    R = so3_exp(torch.tensor(turn, dtype=torch.float64)).numpy()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(centre) - R @ box
    return T


def observe(model, T: np.ndarray, jaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(image, mask, depth)``: the model's render at ``T`` and the jaw opening ``jaw``."""
    out = model.render(torch.from_numpy(T), model.joint_vector({JAW: jaw}), CAMERA,
                       outputs=("rgb", "depth", "opacity"))
    mask = out["opacity"].cpu().numpy() > 0.5
    image = (out["rgb"].cpu().numpy() * 255).round().astype(np.uint8)
    return image, mask, np.where(mask, out["depth"].cpu().numpy(), 0.0).astype(np.float32)


def add_of(model, T_true, jaw_true, T, joints) -> float:
    kin = model.kinematics
    return float(add(model.sample_points, kin.link_poses(kin.joint_vector({JAW: jaw_true})).numpy(), T_true,
                     kin.link_poses(kin.joint_vector(joints)).numpy(), T, model.links))


@pytest.fixture(scope="module")
def models():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    return load_bundle(CLAMP), load_bundle(CLAMP, "cuda")


@pytest.fixture(scope="module")
def scene(models):
    """A view of the clamp (drawn on the CPU), its truth and a start 10 deg / 2 cm off."""
    cpu, _ = models
    centre = ((cpu.aabb[0] + cpu.aabb[1]) / 2).double().numpy()
    T = pose((1.9, -0.7, 0.4), box=centre)
    jaw = float((cpu.lower[0] + cpu.upper[0]) / 2) * 0.6
    turn = so3_exp(torch.tensor(np.radians(10) * np.array([0.6, 0.0, 0.8]))).numpy()
    off = T.copy()  # turned by 10 deg about the box centre and moved 2 cm
    off[:3, :3] = turn @ T[:3, :3]
    off[:3, 3] = (0.05, -0.02, 0.55) - off[:3, :3] @ centre
    return T, jaw, off, observe(cpu, T, jaw)


@needs_cuda
@pytest.mark.parametrize("mode", ["narf", "parts"])
def test_cuda_renders_what_the_cpu_renders(models, scene, mode: str) -> None:
    cpu, gpu = models
    T, jaw, _, _ = scene
    outputs = ("rgb", "depth", "opacity")
    a = cpu.render(torch.from_numpy(T), cpu.joint_vector({JAW: jaw}), CAMERA, outputs=outputs, mode=mode)
    b = gpu.render(torch.from_numpy(T), gpu.joint_vector({JAW: jaw}), CAMERA, outputs=outputs, mode=mode)
    assert b["rgb"].device.type == "cuda"
    assert float(a["opacity"].sum()) > 200  # the clamp is in view
    for name in outputs:
        err = (a[name] - b[name].cpu()).abs()
        assert float(err.mean()) < 1e-3 and float(err.max()) < 0.05, (name, float(err.mean()), float(err.max()))


@needs_cuda
@pytest.mark.parametrize("preset, depth", [("gauss-newton", True), ("robust", True), ("robust", False)])
def test_cuda_refines_as_the_cpu(models, scene, preset: str, depth: bool) -> None:
    T, jaw, off, (image, mask, z) = scene
    found = {}
    for name, model in zip(("cpu", "cuda"), models):
        options = EstimateOptions.preset(preset, depth=depth)
        result = refine(model, image, mask, CAMERA, off, depth=z if depth else None, options=options,
                        ground_truth=(T, {JAW: jaw}))
        found[name] = add_of(model, T, jaw, result.T_cam_obj, result.joints)
        assert result.status in ("converged", "max_iterations"), (name, result.status)
        assert np.isfinite(result.T_cam_obj).all()
    start = add_of(models[0], T, jaw, off, {JAW: float((models[0].lower[0] + models[0].upper[0]) / 2)})
    assert start > 0.015
    assert max(found.values()) < (0.003 if preset == "gauss-newton" else 0.01), found  # Adam's path varies


@needs_cuda
def test_cuda_gauss_newton_gives_the_cpus_covariance(models, scene) -> None:
    T, jaw, off, (image, mask, z) = scene
    sigmas = []
    for model in models:
        result = refine(model, image, mask, CAMERA, off, depth=z, options=EstimateOptions.preset("gauss-newton", depth=True))
        assert result.uncertainty is not None
        sigmas.append(np.asarray(result.uncertainty.position_sigma_m))
    assert np.isfinite(sigmas[1]).all() and (sigmas[1] > 0).all()
    np.testing.assert_allclose(sigmas[1], sigmas[0], rtol=0.5)


@needs_cuda
@pytest.mark.parametrize("rgb_only", [False, True], ids=["rgbd", "rgb"])
def test_cuda_tracks_a_moving_clamp(models, scene, rgb_only: bool) -> None:
    cpu, gpu = models
    T0, jaw0, _, _ = scene
    centre = ((cpu.aabb[0] + cpu.aabb[1]) / 2).double().numpy()
    truths, frames = [], []
    for i in range(8):  # 1 cm/s sideways, 20 deg/s about the view axis, the jaw closing, at 30 fps
        t = i / 30
        T = T0.copy()
        T[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, np.radians(20) * t])).numpy() @ T0[:3, :3]
        T[:3, 3] = T0[:3, 3] + (T0[:3, :3] - T[:3, :3]) @ centre + (0.01 * t, 0.0, 0.0)  # about the box centre
        truths.append((T, jaw0 * (1 - 0.5 * t)))
        image, mask, z = observe(cpu, *truths[-1])
        frames.append(TrackFrame(image, mask, t, None if rgb_only else z))
    rows = list(track(gpu, frames, CAMERA, T0, {JAW: jaw0}, TrackOptions(first_frame="warm")))
    errors = [add_of(cpu, T, jaw, r.T_cam_obj, r.joints) for (T, jaw), r in zip(truths, rows)]
    assert [r.status for r in rows].count("lost") == 0, [r.status for r in rows]
    assert max(errors) < (0.01 if rgb_only else 0.005), errors


@needs_cuda
def test_cli_estimates_on_cuda(models, scene, tmp_path: Path, capsys) -> None:
    T, jaw, off, (image, mask, z) = scene
    Image.fromarray(image).save(tmp_path / "rgb.png")
    Image.fromarray(mask.astype(np.uint8) * 255).save(tmp_path / "mask.png")
    Image.fromarray(np.round(z * 1000).astype(np.uint16)).save(tmp_path / "depth.png")
    K = CAMERA.K.double().numpy()
    code = main(["--device", "cuda", "estimate", str(CLAMP), "--image", str(tmp_path / "rgb.png"),
                 "--mask", str(tmp_path / "mask.png"), "--depth", str(tmp_path / "depth.png"),
                 "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}", "--init-pose", json.dumps(off.tolist()),
                 "--gt", json.dumps({"pose": T.tolist(), "joints": {JAW: jaw}}), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["preset"] == "gauss-newton"
    assert out["metrics"]["add"] < 0.003, out["metrics"]
