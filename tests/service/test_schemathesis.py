"""Property-based fuzzing of the API from its own OpenAPI document: no input may cause a 5xx.

Bounded for CI: a few dozen deterministic examples per operation; the server's image and iteration
limits are set small (160x120, 3 iterations) so that valid requests stay cheap even on a real model.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from narf_service.app import create_app
from narf_service.registry import ModelRegistry
from narf_service.settings import Settings


@pytest.fixture(scope="module")
def api_schema(toy_engine, toy_model, tmp_path_factory):
    limits = Settings(
        models_dir=Path(tmp_path_factory.mktemp("models")),
        workers=2,
        queue_size=8,
        torch_threads=1,
        max_image_pixels=160 * 120,
        max_iterations=3,
        max_body_bytes=256 * 1024,
    )
    app = create_app(limits, engine=toy_engine, registry=ModelRegistry(models={"toy": toy_model}))
    return schemathesis.openapi.from_asgi("/openapi.json", app)


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=30, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck), database=None)
def test_no_input_causes_a_server_error(case) -> None:
    if isinstance(case.body, dict) and "model" in case.body:
        case.body["model"] = "toy"  # the served model, so that generated renders reach it
    response = case.call_and_validate(checks=[not_a_server_error])
    assert response.status_code < 500
