"""One tiny synthetic dataset and one tiny trained model, shared by the bundle, training, evaluation
and CLI tests (used through ``pytest_plugins = ("conftest_model",)`` in those modules).

The dataset is the procedural long-nose pliers (two links, one revolute joint ``pivot``) at 48x36
pixels; the model is trained on it for a few dozen steps per stage (about 10 s on one CPU core),
enough that its opacity lands on the labelled pixels, far too little for good colour.
"""

from __future__ import annotations

from pathlib import Path

import pytest

TINY_SIZE = (48, 36)
TINY_VIEWS = 8


def tiny_config(**overrides):
    """The :class:`~narf_core.train.pipeline.TrainConfig` of the shared model (fields as ``overrides``);
    its configuration field is the distilled one (tests/test_fields.py builds the articulated one from
    its part fields)."""
    from narf_core.train.pipeline import TrainConfig

    settings = {"part_steps": 30, "distill_steps": 30, "batch_rays": 256, "grid_resolution": 32, "field": "distilled",
                "track_sequences": 0, **overrides}
    return TrainConfig(**settings)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The dataset folder: 8 train frames, 17 test and 17 novel (read it, never write to it)."""
    pytest.importorskip("pybullet")
    from narf_core.data.synth.generate import synthesize

    return synthesize("longnose", tmp_path_factory.mktemp("data") / "longnose", size=TINY_SIZE, views=TINY_VIEWS, seed=0)


@pytest.fixture(scope="session")
def tiny_bundle(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The trained model's ``.narf`` file, with its part fields (read it, never write to it)."""
    from narf_core.train.pipeline import train

    return train(tiny_dataset, tmp_path_factory.mktemp("model") / "longnose.narf", tiny_config(), progress=False)


@pytest.fixture(scope="session")
def tiny_model(tiny_bundle: Path):
    """The trained model, loaded (shared: a test that changes it must restore it)."""
    from narf_core.bundle import load_bundle

    return load_bundle(tiny_bundle)
