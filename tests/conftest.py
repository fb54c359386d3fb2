"""Shared test fixtures: the hand-written assets, the bundled clamp and the two float dtypes every numeric test runs in.

The service and client tests live in ``tests/service/`` with their own ``conftest.py``.
"""

import os
from pathlib import Path

import pytest
import torch
from checkout import import_from_checkout

ASSETS = Path(__file__).parent / "assets"


def pytest_configure(config: pytest.Config) -> None:
    torch.set_num_threads(1)  # 2 shared CPU cores: threads only add contention for tiny tensors
    os.environ.setdefault("NARF_THREADS", "1")  # the same for `narf` commands run in-process or as children
    import_from_checkout()  # narf_service and narf_client, installed or not, before any test module imports them


@pytest.fixture(scope="session")
def assets() -> Path:
    """The folder of hand-written test assets (URDFs and their meshes)."""
    return ASSETS


@pytest.fixture(scope="session")
def bundled_clamp():
    """The bundled model ``models/clamp.narf``, loaded once (tests must not change it)."""
    from narf_core.bundle import load_bundle

    return load_bundle(Path(__file__).resolve().parent.parent / "models" / "clamp.narf")


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    return request.param
