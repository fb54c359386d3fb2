"""Observation sanity checks: each warning on a crafted bad input, none on a clean view, and the
warnings reaching the refiner's result, ``narf estimate`` and ``/v1/estimate``."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from narf_core.geometry import Pinhole
from narf_core.observation import MaskEvidence, check_observation, mask_evidence, usable_depth

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "clamp.narf"
CAMERA = Pinhole(torch.tensor([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]]), 80, 60)


def _clean() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:60, 0:80]
    mask = (y - 30) ** 2 + (x - 40) ** 2 <= 15**2
    rng = np.random.default_rng(0)
    image = rng.integers(40, 220, (60, 80, 3)).astype(np.uint8)
    depth = np.where(mask, 0.7, 1.2).astype(np.float32)
    return image, mask, depth


def _codes(warnings: list[str]) -> list[str]:
    return [w.split(":", 1)[0] for w in warnings]


def test_a_clean_view_draws_no_warning() -> None:
    image, mask, depth = _clean()
    assert check_observation(image, mask, depth, CAMERA) == []
    assert check_observation(image, mask, depth, CAMERA, expected_depth_m=0.65) == []
    assert check_observation(image, mask, None, CAMERA) == []


def test_clipped_exposure() -> None:
    image, mask, depth = _clean()
    over = image.copy()
    over[mask] = np.minimum(over[mask].astype(int) * 3, 255).astype(np.uint8)
    assert _codes(check_observation(over, mask, depth, CAMERA)) == ["clipped"]
    under = image.copy()
    under[mask] = 0
    warnings = check_observation(under, mask, depth, CAMERA)
    assert _codes(warnings) == ["clipped"] and "underexposed" in warnings[0]
    a_few = image.copy()
    a_few[mask & (np.arange(80)[None, :] < 28)] = 255  # a highlight on a few percent of the object
    assert check_observation(a_few, mask, depth, CAMERA) == []


def test_mask_touching_the_border() -> None:
    image, mask, depth = _clean()
    shifted = np.roll(mask, -30, axis=1)  # the disc now crosses the left edge
    warnings = check_observation(image, shifted, np.where(shifted, 0.7, 1.2), CAMERA)
    assert _codes(warnings) == ["mask_border"] and "80x60" in warnings[0]


@pytest.mark.parametrize("factor, guess", [(1000.0, "millimetres read as metres"), (0.001, "metres written as millimetres")])
def test_depth_in_the_wrong_unit(factor: float, guess: str) -> None:
    image, mask, depth = _clean()
    for expected in (None, 0.7):
        warnings = check_observation(image, mask, depth * factor, CAMERA, expected_depth_m=expected)
        assert _codes(warnings) == ["depth_unit"] and guess in warnings[0]
        assert usable_depth(depth * factor, warnings) is None
    assert usable_depth(depth, check_observation(image, mask, depth, CAMERA)) is depth


def test_mask_that_does_not_overlap_the_depth() -> None:
    image, mask, depth = _clean()
    elsewhere = np.where(mask, 0.0, 1.2).astype(np.float32)  # returns only off the object
    warnings = check_observation(image, mask, elsewhere, CAMERA)
    assert _codes(warnings) == ["depth_overlap"] and "misaligned" in warnings[0]
    assert usable_depth(elsewhere, warnings) is None
    nan = np.full_like(depth, np.nan)
    assert _codes(check_observation(image, mask, nan, CAMERA)) == ["depth_overlap"]


def _grown(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` grown (``px > 0``) or shrunk by ``|px|`` pixels (chessboard distance)."""
    out = mask.copy()
    for _ in range(abs(px)):
        padded = np.pad(out, 1, constant_values=px < 0)
        shifts = [padded[1 + dy : 61 + dy, 1 + dx : 81 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        out = np.logical_or.reduce(shifts) if px > 0 else np.logical_and.reduce(shifts)
    return out


def test_an_exact_mask_agrees_with_the_depth() -> None:
    _, mask, depth = _clean()
    noisy = depth + np.random.default_rng(1).normal(0, 0.002, depth.shape).astype(np.float32)
    holes = np.where(np.random.default_rng(2).random(depth.shape) < 0.2, np.nan, noisy)
    for d in (depth, noisy, holes, np.where(mask, depth, 0.0)):  # the last: no background depth (a render)
        evidence = mask_evidence(mask, d)
        assert evidence.occluded == 0 and evidence.seam < 0.05 and not evidence.doubtful, evidence


@pytest.mark.parametrize("px", [-2, 2])
def test_an_eroded_or_grown_mask_has_its_edge_on_a_continuous_surface(px: int) -> None:
    _, mask, depth = _clean()
    evidence = mask_evidence(_grown(mask, px), depth)
    assert evidence.seam > 0.9 and evidence.doubtful, evidence


def test_an_occluder_beside_the_mask_is_seen_in_front() -> None:
    _, mask, depth = _clean()
    hand = np.zeros_like(mask)
    hand[:, 47:] = True  # over the right part of the disc, 10 cm in front of it
    evidence = mask_evidence(mask & ~hand, np.where(hand, 0.6, depth).astype(np.float32))
    assert evidence.occluded > 0.2 and evidence.doubtful, evidence
    behind = mask_evidence(mask & ~hand, np.where(hand & ~mask, 1.5, depth).astype(np.float32))
    assert behind.occluded == 0, behind  # a surface behind the object is no occluder
    assert mask_evidence(np.zeros_like(mask), depth) == MaskEvidence(0.0, 0.0)


# ------------------------------------------------------------------------------------------------
# through the refiner, the CLI and the service, on the bundled clamp


def _clamp_view():
    """A view of the bundled clamp rendered by the model itself: image, mask, depth, camera, pose."""
    from narf_core.bundle import load_bundle

    model = load_bundle(MODEL)
    camera = Pinhole.primesense(80, 60)
    T = np.eye(4)
    T[:3, :3] = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1.0]])  # looking down at the clamp
    centre = ((model.aabb[0] + model.aabb[1]) / 2).double().numpy()
    T[:3, 3] = -T[:3, :3] @ centre + [0, 0, 0.8]
    out = model.render(torch.as_tensor(T, dtype=torch.float32), model.joint_vector(None), camera,
                       outputs=("rgb", "depth", "opacity"))
    mask = out["opacity"].numpy() > 0.5
    image = (out["rgb"].numpy() * 255 + 0.5).astype(np.uint8)
    depth = np.where(mask, out["depth"].numpy(), 0.0).astype(np.float32)
    return model, image, mask, depth, camera, T


needs_model = pytest.mark.skipif(not MODEL.exists(), reason="no bundled demo model")


@needs_model
def test_refine_reports_warnings_and_drops_a_depth_in_millimetres() -> None:
    from narf_core.estimate import EstimateOptions, refine

    model, image, mask, depth, camera, T = _clamp_view()
    options = EstimateOptions.preset("robust", iterations=3)
    clean = refine(model, image, mask, camera, T, depth=depth, options=options)
    assert clean.warnings == [] and clean.to_dict()["warnings"] == []
    bad = refine(model, image, mask, camera, T, depth=depth * 1000, options=options)
    assert _codes(bad.warnings) == ["depth_unit"]
    # the bad depth was not used; a depth given but dropped keeps one refinement and no polish (the work bound was
    # the depth's)
    rgb_only = refine(model, image, mask, camera, T, options=EstimateOptions.preset("robust", iterations=3, rgb_polish=0))
    assert np.allclose(bad.T_cam_obj, rgb_only.T_cam_obj) and bad.iterations == rgb_only.iterations


@needs_model
def test_a_view_without_depth_finer_than_the_training_views_is_warned() -> None:
    """``coarse_model``: without depth the distance follows the model's outline, which a field trained on coarser
    views draws less exactly at the camera's pixels. Over ``COARSE_MODEL_RATIO`` (the bundled clamp records no
    training camera: the reference 160x120 one's focal length) a view without depth is warned, by the refiner and
    by the tracker's warm-started frame; with depth, at the ratio or for a model trained at the camera's size not."""
    from narf_core.estimate import COARSE_MODEL_RATIO, REFERENCE_TRAINING_FX, EstimateOptions, coarse_model, refine
    from narf_core.track import refine_frame

    model, image, mask, depth, camera, T = _clamp_view()  # 80x60: fx 67 px, half the training views'
    assert coarse_model(model, camera, None) == []
    fine = Pinhole.primesense(640, 480)  # 4x the training views' focal length
    (warning,) = coarse_model(model, fine, None)
    assert _codes([warning]) == ["coarse_model"] and "4.0x coarser than this 640x480" in warning
    assert "narf synth --size 640 480" in warning
    assert coarse_model(model, fine, depth) == []  # with the depth the refiner uses
    assert coarse_model(model, Pinhole.primesense(320, 240), None) == []  # 2.0x: not over the ratio
    assert COARSE_MODEL_RATIO == 2.0 and float(Pinhole.primesense(320, 240).K[0, 0]) == 2 * REFERENCE_TRAINING_FX
    own = model.metadata.get("training_camera")
    model.metadata["training_camera"] = {"fx": float(fine.K[0, 0])}
    try:
        assert coarse_model(model, fine, None) == []  # trained on views of this camera's size
    finally:
        if own is None:
            model.metadata.pop("training_camera")
        else:
            model.metadata["training_camera"] = own
    # the same view through a camera 2.5x finer than the training views, the clamp 5x further away
    K = camera.K.clone()
    K[0, 0], K[1, 1] = 2.5 * REFERENCE_TRAINING_FX, 2.5 * REFERENCE_TRAINING_FX
    far, T_far = Pinhole(K, camera.width, camera.height), T.copy()
    T_far[2, 3] += 4 * 0.8
    options = EstimateOptions.preset("robust", iterations=2, rgb_polish=0)
    without = refine(model, image, mask, far, T_far, options=options)
    assert _codes(without.warnings) == ["coarse_model"] and "2.5x coarser" in without.warnings[0]
    assert refine(model, image, mask, far, T_far, depth=depth + 4 * 0.8 * (depth > 0), options=options).warnings == []
    frame = refine_frame(model, far, image, mask, None, T_far, {}, EstimateOptions.gauss_newton(iterations=1))
    assert _codes(frame.warnings) == ["coarse_model"]


@needs_model
def test_cli_estimate_prints_the_warnings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from narf_core.cli import main
    from narf_core.data.dataset import write_png_depth

    _, image, mask, depth, camera, T = _clamp_view()
    Image.fromarray(image).save(tmp_path / "rgb.png")
    Image.fromarray((mask * 255).astype(np.uint8)).save(tmp_path / "mask.png")
    write_png_depth(tmp_path / "depth.png", depth / 1000)  # metres written as millimetres: ~1 mm everywhere
    K = camera.K.double().numpy()
    argv = ["estimate", str(MODEL), "--image", str(tmp_path / "rgb.png"), "--mask", str(tmp_path / "mask.png"),
            "--depth", str(tmp_path / "depth.png"), "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
            "--init-pose", json.dumps({"matrix": T.tolist()}), "--iterations", "2", "--preset", "robust"]
    assert main([*argv, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert _codes(out["warnings"]) == ["depth_unit"] and "metres written as millimetres" in out["warnings"][0]
    assert main(argv) == 0
    assert "warning: depth_unit: " in capsys.readouterr().out


@needs_model
@pytest.mark.slow
def test_service_answers_with_the_warnings() -> None:
    import httpx
    from narf_client import NarfClient
    from narf_core.bundle import load_bundle
    from narf_service.app import create_app
    from narf_service.engine import Engine
    from narf_service.main import serve_in_thread
    from narf_service.registry import ModelRegistry
    from narf_service.settings import Settings

    _, image, mask, depth, camera, T = _clamp_view()
    settings = Settings(models_dir=MODEL.parent, workers=1, queue_size=2, torch_threads=1)
    app = create_app(settings, engine=Engine.narf_core(), registry=ModelRegistry(models={"clamp": load_bundle(MODEL)}))
    K = camera.K.double().numpy()
    border = np.zeros_like(mask)
    border[:, :12] = True  # a mask along the image's edge, over depth that is not there
    with serve_in_thread(app) as url:
        est = NarfClient(url).estimate(image, mask, K, T, model="clamp", depth=depth * 1000, iterations=2)
        assert [w.split(":")[0] for w in est.warnings] == ["depth_unit"]
        png = io.BytesIO()
        Image.fromarray(np.where(mask[..., None], image, 128).astype(np.uint8)).save(png, format="PNG")
        m = io.BytesIO()
        Image.fromarray((border * 255).astype(np.uint8)).save(m, format="PNG")
        d = io.BytesIO()
        np.save(d, depth)
        request = {"model": "clamp", "camera": {"K": K.tolist(), "width": 80, "height": 60},
                   "initial_pose": {"matrix": T.tolist()}, "iterations": 0}
        r = httpx.post(f"{url}/v1/estimate", data={"request": json.dumps(request)},
                       files={"image": ("i.png", png.getvalue(), "image/png"), "mask": ("m.png", m.getvalue(), "image/png"),
                              "depth": ("d.npy", d.getvalue(), "application/octet-stream")}, timeout=60)
        assert r.status_code == 200, r.text
        assert sorted(w.split(":")[0] for w in r.json()["warnings"]) == ["depth_overlap", "mask_border"]
