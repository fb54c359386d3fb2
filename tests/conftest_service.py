"""Fixtures for the service and client tests (used through ``pytest_plugins`` in those modules).

Two fixtures decide what the service computes with:
  ``service_model``   the model served under the name ``toy``;
  ``service_engine``  how estimates are computed (``narf_service.engine.Engine``).
Until a tiny trained bundle is part of the test assets they are test doubles, defined here and
only here: :class:`ToyModel` follows ``narf_core.bundle.NarfModel``'s API (it ray-casts its box, so
the images are exact and cheap) and :func:`toy_refine` follows ``narf_core.estimate.refine``'s.
The tests use only that API and read joint names and limits from the model, so pointing the two
fixtures at ``load_bundle(...)`` and ``Engine.narf_core()`` runs them on the real library.

This module also makes ``narf_service`` and ``narf_client`` importable from a plain checkout
(``scripts/install.sh`` installs both; running ``python -m pytest`` without it should work too).
"""

from __future__ import annotations

import importlib.util
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent


def import_from_checkout() -> None:
    """Register ``service/`` as ``narf_service`` and put ``clients/python`` on the path, if not installed."""
    if importlib.util.find_spec("narf_client") is None:
        sys.path.insert(0, str(ROOT / "clients" / "python"))
    if "narf_service" not in sys.modules and importlib.util.find_spec("narf_service") is None:
        spec = importlib.util.spec_from_file_location(
            "narf_service", ROOT / "service" / "__init__.py", submodule_search_locations=[str(ROOT / "service")]
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules["narf_service"] = module
        spec.loader.exec_module(module)


import_from_checkout()

from narf_core.geometry import Pinhole, invert_pose  # noqa: E402
from narf_service.app import create_app  # noqa: E402
from narf_service.engine import Engine  # noqa: E402
from narf_service.registry import ModelRegistry  # noqa: E402
from narf_service.settings import Settings  # noqa: E402


@dataclass(frozen=True)
class ToyJoint:
    name: str
    type: str
    lower: float
    upper: float


class ToyModel:
    """Test double of ``NarfModel``: an opaque box whose colour encodes θ.

    The box ``aabb`` is ray-cast exactly in the object frame: opacity is 1 on the box and 0 off
    it, depth is the camera z of the entry point, rgb is ``(0.2 + 0.6 * u, 0.5, 0.8)`` with ``u`` the
    first joint's position in its range.
    """

    def __init__(self, name: str = "toy", *, has_parts: bool = False) -> None:
        self.name = name
        self.links = ["base", "jaw"]
        self.joints = [ToyJoint("jaw_slide", "prismatic", 0.0, 0.02), ToyJoint("jaw_turn", "revolute", -0.5, 0.5)]
        self.aabb = torch.tensor([[-0.05, -0.03, -0.02], [0.05, 0.03, 0.02]])
        self.metadata = {"arch": "box", "metrics": {"psnr_test": float("inf")}, "urdf": "<robot name='toy'/>"}
        self.has_parts = has_parts

    def joint_vector(self, joints: Mapping[str, float] | None) -> torch.Tensor:
        joints = dict(joints or {})
        theta = []
        for j in self.joints:
            value = float(joints.pop(j.name, (j.lower + j.upper) / 2))
            if not np.isfinite(value) or not j.lower <= value <= j.upper:
                raise ValueError(f"joint {j.name!r}: {value} outside [{j.lower}, {j.upper}]")
            theta.append(value)
        if joints:
            raise ValueError(f"unknown joint(s) {sorted(joints)}")
        return torch.tensor(theta, dtype=torch.float32)

    def joint_dict(self, theta: torch.Tensor) -> dict[str, float]:
        return {j.name: float(v) for j, v in zip(self.joints, theta.tolist())}

    def render(
        self,
        T_cam_obj: torch.Tensor,
        theta: torch.Tensor,
        camera: Pinhole,
        *,
        outputs: tuple[str, ...] = ("rgb",),
        mode: str = "narf",
    ) -> dict[str, torch.Tensor]:
        if mode == "parts" and not self.has_parts:
            raise ValueError("render mode 'parts' is unavailable")
        rays = camera.rays().transform(invert_pose(T_cam_obj.to(camera.K.dtype)))
        d = torch.where(rays.directions.abs() < 1e-12, torch.full_like(rays.directions, 1e-12), rays.directions)
        t0, t1 = (self.aabb[0] - rays.origins) / d, (self.aabb[1] - rays.origins) / d
        near = torch.minimum(t0, t1).amax(-1).clamp_min(0)
        far = torch.maximum(t0, t1).amin(-1)
        hit = far > near
        H, W = camera.height, camera.width
        u = float((theta[0] - self.joints[0].lower) / (self.joints[0].upper - self.joints[0].lower))
        colour = torch.tensor([0.2 + 0.6 * u, 0.5, 0.8])
        images = {
            "rgb": torch.where(hit[:, None], colour, torch.zeros(3)).reshape(H, W, 3),
            "depth": torch.where(hit, near * rays.z_per_t, torch.zeros(())).reshape(H, W),
            "opacity": hit.float().reshape(H, W),
        }
        return {k: images[k] for k in outputs}


class ToyInputError(ValueError):
    """Stands for ``narf_core.estimate.EstimateInputError``."""


@dataclass
class ToyOptions:
    """Stands for ``narf_core.estimate.EstimateOptions`` (same fields and defaults where given)."""

    preset: str = "paper"
    iterations: int = 150
    lr_pose: float = 0.01
    lr_theta: float = 0.05
    lr_decay: float = 0.1
    rays_per_iteration: int = 1024
    mode: str = "narf"
    silhouette_weight: float = 0.0
    depth_weight: float = 0.0
    theta_starts: int = 1
    coarse_to_fine: int = 1
    box_margin: float = 0.15
    early_stop: bool = True
    tolerance: float = 3e-4
    loss_tolerance: float = 0.02
    patience: int = 15
    seed: int = 0


@dataclass
class ToyResult:
    T_cam_obj: np.ndarray
    joints: dict[str, float]
    loss: float | None
    iterations: int
    seconds: float
    trace: list[tuple[float, float]]
    status: str
    recovered_non_finite: bool
    metrics: dict[str, float] | None
    uncertainty: None = None  # the toy refiner has no covariance
    warnings: list[str] = field(default_factory=list)


def toy_refine(
    model: ToyModel,
    image: np.ndarray,
    mask: np.ndarray,
    camera: Pinhole,
    T_init: np.ndarray,
    *,
    joints_init: dict[str, float] | None = None,
    depth: np.ndarray | None = None,
    options: ToyOptions | None = None,
    ground_truth: tuple[np.ndarray, dict[str, float]] | None = None,
    should_stop=None,
) -> ToyResult:
    """Stands for ``refine``: checks its inputs like it, then "converges" to the ground truth if given;
    ``should_stop()`` is polled once per iteration and ends the loop with the status it returns."""
    started = time.perf_counter()
    options = options or ToyOptions()
    assert image.dtype == np.uint8 and image.shape == (camera.height, camera.width, 3)
    assert mask.dtype == bool and mask.shape == image.shape[:2]
    assert depth is None or (depth.dtype == np.float32 and depth.shape == mask.shape)
    if mask.sum() < 2:
        raise ToyInputError(f"mask: {int(mask.sum())} object pixel(s); need at least 2")
    joints = model.joint_dict(model.joint_vector(joints_init))
    T = np.asarray(T_init, dtype=np.float64)
    metrics = None
    if ground_truth is not None:
        T_true, joints_true = ground_truth
        metrics = {"add": float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]))}
        metrics |= {f"joint_error/{k}": abs(joints[k] - v) for k, v in joints_true.items()}
    trace, status = [], "max_iterations"
    for i in range(options.iterations):
        if should_stop is not None and (reason := should_stop()):
            status = reason
            break
        trace.append((1.0 / (i + 1), 0.001 * i))
    loss = trace[-1][0] if trace else None
    seconds = time.perf_counter() - started  # measured, so that it never exceeds the server's wall time
    return ToyResult(T, joints, loss, len(trace), seconds, trace, status, False, metrics)


def toy_load_bundle(path: Path, device: str = "cpu") -> ToyModel:
    """Stands for ``load_bundle``: a file holding ``toy`` is a model, anything else is refused."""
    if path.read_bytes() != b"toy":
        raise ToyInputError(f"{path}: not a NARF model bundle")
    return ToyModel(path.stem)


@dataclass
class GatedEngine:
    """An engine whose ``refine`` waits at ``gate`` (to hold workers busy) and counts its calls."""

    inner: Engine
    gate: threading.Event = field(default_factory=threading.Event)
    calls: int = 0

    def engine(self) -> Engine:
        def refine(*args, **kwargs):
            self.calls += 1
            if not self.gate.wait(timeout=10):
                raise TimeoutError("gate never opened")
            return self.inner.refine(*args, **kwargs)

        return Engine(self.inner.load_bundle, refine, self.inner.options, self.inner.input_error)


@pytest.fixture(scope="session")
def service_model() -> ToyModel:
    return ToyModel("toy")


@pytest.fixture(scope="session")
def service_engine() -> Engine:
    return Engine(load_bundle=toy_load_bundle, refine=toy_refine, options=ToyOptions, input_error=ToyInputError)


@pytest.fixture
def service_settings(tmp_path: Path) -> Settings:
    return Settings(models_dir=tmp_path, workers=2, queue_size=4, torch_threads=1, max_body_bytes=2**20)


def make_client(settings: Settings, engine: Engine, model, **registry_models):
    from fastapi.testclient import TestClient

    registry = ModelRegistry(models={"toy": model, **registry_models})
    return TestClient(create_app(settings, engine=engine, registry=registry))


@pytest.fixture
def client(service_settings: Settings, service_engine: Engine, service_model) -> Iterator:
    """A TestClient on the app serving ``toy``, lifespan run."""
    with make_client(service_settings, service_engine, service_model) as c:
        yield c


def camera_json(width: int = 32, height: int = 24, f: float = 30.0) -> dict:
    return {"K": [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], "width": width, "height": height}


def pose_json(z: float = 0.4) -> dict:
    """The object ``z`` metres in front of the camera, axes aligned with the camera's."""
    return {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, z], [0, 0, 0, 1]]}


def wait_until(predicate, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met in time")
        time.sleep(0.005)
