"""Shared test fixtures: the hand-written assets and the two float dtypes every numeric test runs in."""

import os
from pathlib import Path

import pytest
import torch

ASSETS = Path(__file__).parent / "assets"


def pytest_configure(config: pytest.Config) -> None:
    torch.set_num_threads(1)  # 2 shared CPU cores: threads only add contention for tiny tensors
    os.environ.setdefault("NARF_THREADS", "1")  # the same for `narf` commands run in-process or as children


@pytest.fixture(scope="session")
def assets() -> Path:
    """The folder of hand-written test assets (URDFs and their meshes)."""
    return ASSETS


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    return request.param
