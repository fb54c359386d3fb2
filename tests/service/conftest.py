"""Fixtures of the service and client tests (the names they import are in ``helpers.py``).

Two fixtures decide what the service computes with:
  ``service_model``   the served model: the toy box, or the bundled ``models/clamp.narf`` in
                      tests marked ``helpers.ON_BOTH_MODELS`` (its ``clamp`` case is slow);
  ``service_engine``  how estimates are computed: the toy refiner for the toy, the real
                      library (``Engine.narf_core()``) for the bundled model.
Module-scoped servers use ``toy_model`` and ``toy_engine`` directly.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.register_assert_rewrite("helpers")

from helpers import BUNDLED, ToyModel, make_client, toy_engine  # noqa: E402
from narf_service.engine import Engine  # noqa: E402
from narf_service.settings import Settings  # noqa: E402


@pytest.fixture(scope="session")
def toy_model() -> ToyModel:
    return ToyModel("toy")


@pytest.fixture(scope="session", name="toy_engine")
def toy_engine_fixture() -> Engine:
    return toy_engine()


@pytest.fixture(scope="session")
def bundled_model():
    """``models/clamp.narf``, loaded once (shared: read it, never change it)."""
    if not BUNDLED.exists():
        pytest.skip("no bundled model")
    from narf_core.bundle import load_bundle

    return load_bundle(BUNDLED)


@pytest.fixture
def service_model(request: pytest.FixtureRequest):
    """The toy model, or the bundled one where a test parametrises this fixture with ``"clamp"``."""
    kind = getattr(request, "param", "toy")
    assert kind in ("toy", "clamp"), kind
    return request.getfixturevalue("toy_model" if kind == "toy" else "bundled_model")


@pytest.fixture
def service_engine(service_model, toy_engine: Engine) -> Engine:
    return toy_engine if isinstance(service_model, ToyModel) else Engine.narf_core()


@pytest.fixture
def service_settings(tmp_path: Path) -> Settings:
    return Settings(models_dir=tmp_path, workers=2, queue_size=4, torch_threads=1, max_body_bytes=2**20)


@pytest.fixture
def client(service_settings: Settings, service_engine: Engine, service_model) -> Iterator:
    """A TestClient on the app serving ``service_model`` under its name, lifespan run."""
    with make_client(service_settings, service_engine, service_model) as c:
        yield c
