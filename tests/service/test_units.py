"""The service's parts on their own: codecs, pose and camera schemas, Accept negotiation, the work
queue, the model registry, settings and metrics helpers."""

from __future__ import annotations

import asyncio
import io
import json
import math
import os
import threading

import numpy as np
import pytest
from PIL import Image
from pydantic import ValidationError

from helpers import toy_load_bundle
from narf_service.app import prefers_png
from narf_service.errors import ApiError, field_path
from narf_core.depth import depth_to_mm
from narf_service.images import decode_depth, decode_mask, decode_rgb, rgb_to_uint8
from narf_service.main import serve
from narf_service.monitoring import peak_rss_bytes
from narf_service.registry import ModelRegistry, valid_model_name
from narf_service.schemas import Camera, Pose, PoseOut
from narf_service.settings import Settings
from narf_service.workers import QueueFull, WorkQueue


def png(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


# --- codecs ---------------------------------------------------------------------------------------


def test_depth_to_millimetres_edges() -> None:
    metres = np.array([0, 1e-5, 0.38, 0.3804, 65.535, 100, np.nan, -1, np.inf, -np.inf])
    assert depth_to_mm(metres).tolist() == [0, 1, 380, 380, 65535, 65535, 0, 0, 0, 0]
    assert depth_to_mm(metres.astype(np.float32)).dtype == np.uint16


def test_depth_decodes_from_png_millimetres_and_npy_metres() -> None:
    mm = np.array([[0, 380], [1000, 65535]], dtype=np.uint16)
    assert np.allclose(decode_depth(png(mm), "depth", 100), [[0, 0.38], [1, 65.535]])
    metres = np.array([[np.nan, 0.5], [np.inf, -np.inf]], dtype=np.float32)
    depth = decode_depth(npy(metres), "depth", 100)
    assert depth.dtype == np.float32 and depth.tolist() == [[0, 0.5], [0, 0]]
    assert decode_depth(npy(np.ones((2, 2))), "depth", 100).dtype == np.float32  # float64 accepted


@pytest.mark.parametrize(
    ("data", "status", "word"),
    [
        (npy(np.array([[-0.1, 1.0]], dtype=np.float32)), 422, "negative"),
        (npy(np.ones((2, 2, 2), dtype=np.float32)), 422, "2-D"),
        (npy(np.ones((2, 2), dtype=np.int32)), 422, "float"),
        (npy(np.ones((20, 20), dtype=np.float32)), 413, "pixels"),
        (b"\x93NUMPY garbage", 422, "npy"),
        (png(np.zeros((2, 2), np.uint8)), 422, "16-bit"),
        (b"GIF89a", 422, ".npy"),
    ],
)
def test_bad_depth(data: bytes, status: int, word: str) -> None:
    with pytest.raises(ApiError) as info:
        decode_depth(data, "depth", 100)
    assert info.value.status_code == status and word in info.value.message and info.value.field == "depth"


def test_rgb_and_mask_decoding() -> None:
    rgba = np.zeros((3, 4, 4), np.uint8)
    rgba[..., 0] = 200
    assert decode_rgb(png(rgba), "image", 100)[..., 0].tolist() == [[200] * 4] * 3
    mask = decode_mask(png(np.array([[0, 255], [1, 0]], np.uint8)), "mask", 100)
    assert mask.dtype == bool and mask.tolist() == [[False, True], [True, False]]
    one_bit = io.BytesIO()
    Image.fromarray(np.array([[True, False]])).save(one_bit, format="PNG")
    assert decode_mask(one_bit.getvalue(), "mask", 100).tolist() == [[True, False]]
    with pytest.raises(ApiError, match="pixels exceeds"):
        decode_rgb(png(np.zeros((11, 10, 3), np.uint8)), "image", 100)
    jpeg = io.BytesIO()
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(jpeg, format="JPEG")
    with pytest.raises(ApiError, match="readable PNG"):
        decode_mask(jpeg.getvalue(), "mask", 100)  # a lossy mask is refused


def test_rgb_to_uint8_clamps_and_zeroes_non_finite() -> None:
    assert rgb_to_uint8(np.array([-1, 0, 0.5, 1, 2, np.nan, np.inf])).tolist() == [0, 0, 128, 255, 255, 0, 255]


# --- schemas --------------------------------------------------------------------------------------


def test_pose_near_unit_inputs_are_projected_exactly() -> None:
    q = Pose(position=[0, 0, 1], orientation=[0, 0, 0, 1.0009]).orientation
    assert math.isclose(sum(x * x for x in q), 1.0, rel_tol=1e-15)
    c, s = math.cos(0.3), math.sin(0.3)
    m = [[c, -s, 0, 0.1], [s, c + 5e-4, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]
    R = np.asarray(Pose(matrix=m).matrix)[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12 and np.linalg.det(R) == pytest.approx(1)


@pytest.mark.parametrize(
    "q", [[0, 0, 0, 1], [1, 0, 0, 0], [0, 0.70710678, 0, 0.70710678], [0.5, -0.5, 0.5, 0.5], [0, 0, 1, 1e-8]]
)
def test_pose_forms_round_trip_including_half_turns(q: list[float]) -> None:
    q = list(np.asarray(q) / np.linalg.norm(q))
    T = Pose(position=[0.1, 0.2, 0.3], orientation=q).as_matrix()
    out = PoseOut.from_matrix(T)
    back = Pose(position=out.position, orientation=out.orientation).as_matrix()
    assert np.allclose(back, T, atol=1e-9) and out.orientation[3] >= 0
    assert np.allclose(Pose(matrix=out.matrix).as_matrix(), T, atol=1e-9)


def test_camera_accepts_skew_and_off_centre_principal_point() -> None:
    cam = Camera(K=[[500, 1.5, 10], [0, 480, -20], [0, 0, 1]], width=640, height=480)
    assert cam.K[0][1] == 1.5
    with pytest.raises(ValidationError, match="focal"):
        Camera(K=[[1e-9, 0, 10], [0, 480, 20], [0, 0, 1]], width=640, height=480)


@pytest.mark.parametrize(
    ("loc", "path"),
    [(("body", "pose", "matrix", 2, 3), "pose.matrix[2][3]"), (("body",), "body"), (("path", "name"), "name")],
)
def test_field_paths(loc: tuple, path: str) -> None:
    assert field_path(loc) == path


@pytest.mark.parametrize("name", ["clamp", "lineman-a", "v1.2_b", "x" * 64])
def test_model_name_pattern_accepts(name: str) -> None:
    assert valid_model_name(name)


@pytest.mark.parametrize("name", ["..", "a..b", ".hidden", "a/b", "/abs", "", "x" * 65, "a b", "a\\b"])
def test_model_name_pattern_refuses(name: str) -> None:
    assert not valid_model_name(name)


# --- Accept negotiation ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("accept", "png"),
    [
        (None, False),
        ("", False),
        ("*/*", False),
        ("application/json", False),
        ("image/png", True),
        ("image/*", True),
        ("image/png, application/json", False),
        ("image/png, application/json;q=0.5", True),
        ("application/json;q=0.9, image/png", True),
        ("image/png;q=0", False),
        ("image/png;q=bad", False),
        ("image/*;q=0.2, image/png;q=0.8, */*;q=0.5", True),
    ],
)
def test_prefers_png(accept: str | None, png: bool) -> None:
    assert prefers_png(accept) is png


# --- work queue -----------------------------------------------------------------------------------


def test_work_queue_admits_workers_plus_queue_then_refuses() -> None:
    gate = threading.Event()

    async def main() -> None:
        queue = WorkQueue(workers=1, queue_size=1, retry_after_max_s=7)
        first = asyncio.ensure_future(queue.run(lambda: gate.wait(5)))
        second = asyncio.ensure_future(queue.run(lambda: "second"))
        await asyncio.sleep(0.05)
        assert (queue.running, queue.waiting) == (1, 1)
        with pytest.raises(QueueFull) as info:
            await queue.run(lambda: "third")
        assert 1 <= info.value.retry_after_s <= 7
        second.cancel()  # a waiting job given up by its client frees its slot at once
        await asyncio.sleep(0.05)
        assert queue.waiting == 0
        third = asyncio.ensure_future(queue.run(lambda: "third"))
        gate.set()
        assert await first is True and await third == "third"
        assert (queue.running, queue.waiting) == (0, 0)
        queue.shutdown()

    asyncio.run(main())


def test_work_queue_propagates_exceptions_and_frees_the_slot() -> None:
    async def main() -> None:
        queue = WorkQueue(workers=1, queue_size=0)

        def boom() -> None:
            raise KeyError("x")

        with pytest.raises(KeyError):
            await queue.run(boom)
        assert await queue.run(lambda: 3) == 3
        queue.shutdown()

    asyncio.run(main())
    with pytest.raises(ValueError, match="workers"):
        WorkQueue(workers=0, queue_size=1)


# --- registry -------------------------------------------------------------------------------------


def test_registry_loads_good_bundles_and_reports_bad_ones(tmp_path) -> None:
    (tmp_path / "toy.narf").write_bytes(b"toy")
    (tmp_path / "broken.narf").write_bytes(b"garbage")
    (tmp_path / "bad name.narf").write_bytes(b"toy")
    (tmp_path / "notes.txt").write_text("not a bundle")
    outside = tmp_path.parent / f"{tmp_path.name}-outside.narf"
    outside.write_bytes(b"toy")
    (tmp_path / "escape.narf").symlink_to(outside)
    registry = ModelRegistry.load_folder(tmp_path, toy_load_bundle)
    assert list(registry) == ["toy"] and registry.get("toy").name == "toy"
    assert set(registry.failed) == {"broken", "bad name", "escape"}
    assert "not a NARF model bundle" in registry.failed["broken"] and "outside" in registry.failed["escape"]
    with pytest.raises(ApiError) as info:
        registry.get("broken")
    assert info.value.status_code == 404 and "served: toy" in info.value.message


def test_registry_of_a_missing_folder_is_empty(tmp_path) -> None:
    registry = ModelRegistry.load_folder(tmp_path / "absent", toy_load_bundle)
    assert len(registry) == 0 and registry.failed == {}


# --- settings, serve, metrics ---------------------------------------------------------------------


def test_blank_token_means_no_auth(monkeypatch) -> None:
    monkeypatch.setenv("NARF_TOKEN", "  ")
    assert Settings().token is None


def test_settings_from_environment_and_sized_to_the_machine(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("NARF_MODELS_DIR", str(tmp_path))
    monkeypatch.setenv("NARF_TOKEN", "s3cret")
    monkeypatch.setenv("NARF_WORKERS", "3")
    s = Settings()
    assert s.models_dir == tmp_path and s.token.get_secret_value() == "s3cret" and "s3cret" not in repr(s)
    assert (s.workers, s.queue_size, s.torch_threads) == (3, 12, 0)  # 0: free cores / workers at start
    monkeypatch.delenv("NARF_WORKERS")
    cores = len(os.sched_getaffinity(0))
    assert Settings().workers == cores and Settings().torch_threads == 0
    monkeypatch.setenv("NARF_MAX_BODY_BYTES", "-5")
    with pytest.raises(ValidationError, match="max_body_bytes"):
        Settings()


def test_serve_refuses_a_missing_models_folder_and_bad_settings(tmp_path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        serve(tmp_path / "absent")
    with pytest.raises(ValueError, match="workers"):
        serve(tmp_path, workers=-1)
    with pytest.raises(ValueError, match="device 'gpu0': not a torch device"):
        serve(tmp_path, device="gpu0")


def test_settings_refuse_a_device_the_machine_lacks(monkeypatch) -> None:
    import torch

    assert Settings(device="cpu").device == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setenv("NARF_DEVICE", "cuda:0")
    with pytest.raises(ValidationError, match="device 'cuda:0': this torch .* sees no CUDA device"):
        Settings()


def test_peak_rss_is_read_from_proc_status(tmp_path) -> None:
    status = tmp_path / "status"
    status.write_text("Name:\tpython\nVmPeak:\t  999 kB\nVmHWM:\t  2048 kB\nVmRSS:\t 1024 kB\n")
    assert peak_rss_bytes(status) == 2048 * 1024
    assert math.isnan(peak_rss_bytes(tmp_path / "absent"))
    assert peak_rss_bytes() > 0


def test_the_real_engine_builds_options_from_a_preset_and_overrides() -> None:
    from narf_core.estimate import EstimateInputError, EstimateOptions
    from narf_service.engine import Engine

    options = Engine.narf_core().options
    assert options("paper") == EstimateOptions()
    assert options(preset="robust", iterations=20) == EstimateOptions.robust(iterations=20)
    with pytest.raises(EstimateInputError, match="preset"):
        options(preset="fast")


def test_serve_process_reports_a_server_that_does_not_start(tmp_path) -> None:
    from narf_service.main import serve_process

    with pytest.raises(RuntimeError, match=r"narf serve exited with 2 .*models folder .*absent does not exist"):
        with serve_process(["--models", str(tmp_path / "absent")], startup_timeout_s=30):
            pass


def test_track_options_come_from_the_core_tracker() -> None:
    from narf_core.track import TrackInputError, TrackOptions
    from narf_service.schemas import TrackOptionsIn

    props = TrackOptionsIn.model_json_schema()["properties"]
    core = TrackOptions()
    for name in ("iterations", "rays_per_iteration", "solver"):
        assert props[name]["description"].endswith(f"the tracker's value ({json.dumps(getattr(core, name))})"), name
    assert TrackOptionsIn(solver="gauss-newton").solver == "gauss-newton"
    with pytest.raises(ValueError, match="solver"):
        TrackOptionsIn(solver="newton")
    with pytest.raises(TrackInputError) as info:
        TrackOptions(iterations=-1)
    assert info.value.field == "options.iterations" and info.value.reason == "must be >= 0 (0 = the solver's own), got -1"


def test_track_request_rays_keep_their_floor() -> None:
    """A track request's ``rays_per_iteration`` is at least 16 when given (left out: the solver's own)."""
    from narf_service.schemas import TrackOptionsIn

    with pytest.raises(ValueError, match="rays_per_iteration"):
        TrackOptionsIn(rays_per_iteration=8)
    assert TrackOptionsIn().rays_per_iteration is None and TrackOptionsIn(rays_per_iteration=16).rays_per_iteration == 16
