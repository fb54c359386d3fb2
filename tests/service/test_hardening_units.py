"""Units of the service's hardening (issue #12): the job stop signal, cancellation in the work queue,
public routes, and the one-line reasons for refused bundles and refiner input errors."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import pytest

from helpers import ToyModel
from narf_service.errors import ApiError
from narf_service.jobs import _refine_input_error
from narf_service.registry import one_line_reason
from narf_service.settings import Settings
from narf_service.workers import Stop, WorkQueue


def test_stop_says_cancelled_or_budget_exceeded() -> None:
    stop = Stop(max_seconds=0.05)
    assert stop() is None  # not started: no clock yet
    stop.start()
    assert stop() is None
    time.sleep(0.08)
    assert stop() == "budget_exceeded"
    stop.cancel()
    assert stop() == "cancelled" and stop.cancelled
    unlimited = Stop()
    unlimited.start()
    assert unlimited() is None


def test_cancelling_a_waiting_job_frees_its_slot_and_it_never_runs() -> None:
    queue = WorkQueue(workers=1, queue_size=1)
    gate, ran = threading.Event(), []

    async def main() -> None:
        first = asyncio.ensure_future(queue.run(lambda: gate.wait(5)))
        await asyncio.sleep(0.05)
        stop = Stop()
        second = asyncio.ensure_future(queue.run(lambda: ran.append("second"), stop))
        await asyncio.sleep(0.05)
        assert queue.running == 1 and queue.waiting == 1
        second.cancel()
        await asyncio.sleep(0.05)
        assert queue.waiting == 0 and stop.cancelled  # free at once, the running job untouched
        gate.set()
        assert await first is True

    asyncio.run(main())
    queue.shutdown()
    assert ran == []


def test_a_running_job_sees_the_cancellation() -> None:
    queue = WorkQueue(workers=1, queue_size=0)
    seen = []

    def job(stop: Stop) -> None:
        while stop() is None:
            time.sleep(0.01)
        seen.append(stop())

    async def main() -> None:
        stop = Stop(max_seconds=30)
        task = asyncio.ensure_future(queue.run(lambda: job(stop), stop))
        await asyncio.sleep(0.05)
        task.cancel()
        await asyncio.sleep(0.1)

    asyncio.run(main())
    queue.shutdown()
    assert seen == ["cancelled"]


@pytest.mark.parametrize(
    ("path", "public"),
    [
        ("/healthz", True),
        ("/readyz", True),
        ("/readyz/anything", True),
        ("/readyzx", False),
        ("/healthz/../v1/models", False),
        ("/healthz/./x", False),
        ("/v1/render", False),
        ("/metrics", False),
        ("/viewer/", False),
        ("/", False),
    ],
)
def test_public_routes_are_path_prefixes(tmp_path: Path, path: str, public: bool) -> None:
    assert Settings(models_dir=tmp_path).is_public(path) is public


def test_public_routes_refuse_relative_entries(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="path prefix"):
        Settings(models_dir=tmp_path, public_routes=["healthz"])


def test_a_refused_bundle_reason_is_one_line_without_its_path(tmp_path: Path) -> None:
    path = tmp_path / "deep" / "folder" / "clamp.narf"
    reason = one_line_reason(ValueError(f"{path}: corrupt model bundle (SafetensorError:\n  bad\n header)"), path)
    assert reason == "corrupt model bundle (SafetensorError: bad header)"
    assert one_line_reason(OSError(f"[Errno 13] Permission denied: '{path}'"), path) == (
        "[Errno 13] Permission denied: 'clamp.narf'"
    )
    assert len(one_line_reason(ValueError("x" * 1000), path)) == 300


@pytest.mark.parametrize(
    ("message", "field"),
    [
        ("mask has only 1 object pixel(s); at least 2 are needed", "mask"),
        ("mask: 1 object pixel(s); need at least 2", "mask"),
        ("depth must be float metres, got dtype int16", "depth"),
        ("options.theta_starts must be in [1, 64], got 99", "request.options.theta_starts"),
        ("T_init has a rotation block that is not orthonormal (max |R^T R - I| = 0.2 > 0.001)", "request.initial_pose"),
        ("joints_init: unknown joint 'x'", "request.initial_joints"),
        ("something else entirely", None),
    ],
)
def test_refiner_input_errors_name_the_request_field(message: str, field: str | None) -> None:
    error = _refine_input_error(message)
    assert isinstance(error, ApiError) and error.status_code == 422 and error.field == field
    if field is not None:
        assert error.message.startswith(field) and message in error.message


def test_a_render_in_bands_is_the_render_of_the_whole_image(bundled_model) -> None:
    """The bundled clamp at 600x500 (two bands) through the service's renderer and in one piece."""
    import numpy as np
    import torch

    from narf_service import jobs
    from narf_service.schemas import RenderRequest

    model = bundled_model
    camera = {"K": [[900.0, 0, 310], [0, 900, 240], [0, 0, 1]], "width": 600, "height": 500}
    request = RenderRequest(model="clamp", pose={"position": [0, 0, 0.45], "orientation": [0, 0, 0, 1]},
                            camera=camera, outputs=["rgb", "depth", "opacity"])
    assert len(jobs._bands(jobs.pinhole(request.camera, torch.device("cpu")))) == 2
    images, theta, _ = jobs.render_images(model, request)
    whole = model.render(torch.tensor(request.pose.as_matrix(), dtype=torch.float32), theta,
                         jobs.pinhole(request.camera, torch.device("cpu")), outputs=("rgb", "depth", "opacity"))
    assert images["opacity"].astype(bool).sum() > 1000  # the clamp is in view, across the band edge
    np.testing.assert_allclose(images["rgb"], jobs.rgb_to_uint8(whole["rgb"].numpy()), atol=1)
    np.testing.assert_allclose(images["depth"], jobs.depth_to_mm(whole["depth"].numpy()), atol=1)


def test_a_render_past_the_budget_stops_between_bands() -> None:
    from narf_service import jobs
    from narf_service.schemas import RenderRequest

    camera = {"K": [[900.0, 0, 500], [0, 900, 500], [0, 0, 1]], "width": 1000, "height": 1000}  # 4 bands
    request = RenderRequest(model="toy", pose={"position": [0, 0, 0.45], "orientation": [0, 0, 0, 1]}, camera=camera)
    calls = []

    def stop_after_two() -> str | None:
        calls.append(1)
        return "budget_exceeded" if len(calls) > 2 else None

    with pytest.raises(ApiError) as info:
        jobs.render_images(ToyModel(), request, stop_after_two)
    assert info.value.status_code == 422 and info.value.code == "budget_exceeded" and info.value.field == "camera"
    assert len(calls) == 3
