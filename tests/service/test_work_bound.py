"""The service's work bound (``jobs.check_work``) knows whether the request carries a depth image: the
robust preset polishes an RGB-only view's estimate (``EstimateOptions.rgb_polish``) and not one with a
depth, so the same options may be refused without a depth image and admitted with one."""

from __future__ import annotations

import io
from collections.abc import Iterator

import numpy as np
import pytest

from helpers import ToyModel
from narf_core.estimate import EstimateOptions
from narf_service import jobs
from narf_service.app import create_app
from narf_service.errors import ApiError
from narf_service.main import serve_in_thread
from narf_service.registry import ModelRegistry
from narf_service.settings import Settings
from test_adversarial import H, W, SlowEngine, estimate_parts, post_estimate, settings_for


def test_the_default_limit_admits_robust_and_gauss_newton_with_and_without_a_depth_image() -> None:
    """The presets as they are, and gauss-newton asked for 30 iterations (the preset's 25 and a fifth more, as
    the service's end-to-end tests ask: with three estimates its bound is 8.4 M rays)."""
    limit = Settings.model_fields["max_work_rays"].default
    robust = EstimateOptions.robust()
    for options in (robust, EstimateOptions.gauss_newton(), EstimateOptions.gauss_newton(iterations=30)):
        for depth in (True, False):
            jobs.check_work(options, limit, "request.options", depth=depth)  # no 422
    assert robust.max_rays(depth=False) > robust.max_rays(depth=True) * 1.4  # 4 starts and the polish vs 8 starts


def test_the_bound_without_a_depth_image_counts_its_polish() -> None:
    options = EstimateOptions.robust(iterations=5)
    between = (options.max_rays(depth=True) + options.max_rays(depth=False)) // 2
    jobs.check_work(options, between, "request.options", depth=True)
    with pytest.raises(ApiError) as caught:
        jobs.check_work(options, between, "request.options", depth=False)
    assert caught.value.status_code == 422 and caught.value.field == "request.options"
    assert f"would trace up to {options.max_rays(depth=False)} rays" in str(caught.value.detail)


@pytest.fixture(scope="module")
def bounded(tmp_path_factory) -> Iterator[tuple[str, SlowEngine]]:
    """A server whose work limit lies between robust's bound for 5 iterations with and without a depth."""
    options = EstimateOptions.robust(iterations=5)
    limit = (options.max_rays(depth=True) + options.max_rays(depth=False)) // 2
    engine = SlowEngine(step_s=0.0)
    app = create_app(settings_for(tmp_path_factory.mktemp("models"), max_work_rays=limit), engine=engine.engine(),
                     registry=ModelRegistry(models={"toy": ToyModel("toy")}))
    with serve_in_thread(app) as url:
        yield url, engine


def test_an_rgb_only_request_over_the_bound_is_refused_and_the_same_with_a_depth_runs(bounded) -> None:
    url, engine = bounded
    request = {"iterations": 5, "options": {"preset": "robust"}}
    reply = post_estimate(url, estimate_parts(request=request))
    assert reply.status == 422 and reply.error()["field"] == "request.options", reply
    assert "refinements" in reply.error()["message"] and engine.started == []
    buffer = io.BytesIO()
    np.save(buffer, np.full((H, W), 0.41, np.float32))
    reply = post_estimate(url, estimate_parts(request=request, depth=("d.npy", buffer.getvalue(), "application/octet-stream")))
    assert reply.status == 200 and len(engine.started) == 1, reply
