"""What the service and client tests import by name: the toy model and refiner, request builders and scenes.

The fixtures built from these live in ``tests/service/conftest.py``. :class:`ToyModel` follows
``narf_core.bundle.NarfModel``'s API (it ray-casts its box, so its images are exact and cheap) and
:func:`toy_refine` follows ``narf_core.estimate.refine``'s; options, input errors and the result
type are the core's own. The tests read joint names and limits from the model they are given, so
the ones marked :data:`ON_BOTH_MODELS` run unchanged on the bundled ``models/clamp.narf``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch

from narf_core.estimate import EstimateInputError, EstimateResult
from narf_core.geometry import Pinhole, invert_pose, pose_to_position_quaternion
from narf_core.modes import choose_mode
from narf_service.app import create_app
from narf_service.engine import Engine
from narf_service.registry import ModelRegistry
from narf_service.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
BUNDLED = ROOT / "models" / "clamp.narf"

ON_BOTH_MODELS = pytest.mark.parametrize(
    "service_model", ["toy", pytest.param("clamp", marks=pytest.mark.slow)], indirect=True
)
"""Run a test on the toy model and (slow) on the bundled clamp, each with its engine (see conftest)."""


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

    def describe(self) -> dict:
        """Like ``NarfModel.describe`` (the service's /v1/models answers are built from it)."""
        return {"name": self.name, "links": list(self.links), "joints": [vars(j) for j in self.joints],
                "bounds": self.aabb.tolist(), "modes": ["narf", "parts"] if self.has_parts else ["narf"],
                "auto_mode": dict(zip(("mode", "reason"), choose_mode(self, "auto"))),
                "metrics": self.metadata["metrics"]}

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


def toy_refine(
    model: ToyModel,
    image: np.ndarray,
    mask: np.ndarray,
    camera: Pinhole,
    T_init: np.ndarray,
    *,
    joints_init: dict[str, float] | None = None,
    depth: np.ndarray | None = None,
    options=None,
    ground_truth: tuple[np.ndarray, dict[str, float]] | None = None,
    should_stop=None,
) -> EstimateResult:
    """Stands for ``refine``: checks its inputs like it, then stays at the start (so its ADD is the
    start's translation error, known exactly); ``should_stop()`` is polled once per iteration and
    ends the loop with the status it returns."""
    started = time.perf_counter()
    assert image.dtype == np.uint8 and image.shape == (camera.height, camera.width, 3)
    assert mask.dtype == bool and mask.shape == image.shape[:2]
    assert depth is None or (depth.dtype == np.float32 and depth.shape == mask.shape)
    if mask.sum() < 2:
        raise EstimateInputError(f"mask: {int(mask.sum())} object pixel(s); need at least 2")
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
    position, quaternion = pose_to_position_quaternion(torch.from_numpy(T))
    return EstimateResult(
        T_cam_obj=T,
        position=position.numpy(),
        quaternion=quaternion.numpy(),
        joints=joints,
        loss=trace[-1][0] if trace else None,
        iterations=len(trace),
        seconds=time.perf_counter() - started,  # measured, so that it never exceeds the server's wall time
        trace=trace,
        status=status,
        recovered_non_finite=False,
        metrics=metrics,
    )


def toy_load_bundle(path: Path, device: str = "cpu") -> ToyModel:
    """Stands for ``load_bundle``: a file holding ``toy`` is a model, anything else is refused."""
    if path.read_bytes() != b"toy":
        raise ValueError(f"{path}: not a NARF model bundle")
    return ToyModel(path.stem)


def toy_engine(load_bundle=toy_load_bundle, refine=toy_refine) -> Engine:
    """The real engine's options and input error, with the toy's loader and refiner (or the given ones)."""
    real = Engine.narf_core()
    return Engine(load_bundle, refine, real.options, real.input_error)


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


def make_client(settings: Settings, engine: Engine, model, **registry_models):
    """A TestClient (lifespan not yet run) on the app serving ``model`` under its name, and ``registry_models``."""
    from fastapi.testclient import TestClient

    registry = ModelRegistry(models={model.name: model, **registry_models})
    return TestClient(create_app(settings, engine=engine, registry=registry))


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


@dataclass(frozen=True)
class Scene:
    """A view of a model with its truth: ``T_cam_obj`` and ``joints``, through ``K`` at ``width x height``."""

    model: str
    K: np.ndarray  # [3, 3]
    width: int
    height: int
    T_cam_obj: np.ndarray  # [4, 4]
    joints: dict[str, float]
    aabb: np.ndarray  # [2, 3] the model's box, object frame

    def camera_json(self) -> dict:
        return {"K": self.K.tolist(), "width": self.width, "height": self.height}

    def pose_json(self, T: np.ndarray | None = None) -> dict:
        return {"matrix": (self.T_cam_obj if T is None else T).tolist()}

    def pinhole(self) -> Pinhole:
        return Pinhole(torch.tensor(self.K, dtype=torch.float32), self.width, self.height)

    def moved(self, metres: tuple[float, float, float]) -> np.ndarray:
        """The true pose moved by ``metres`` along the camera's axes: an estimate's start."""
        T = self.T_cam_obj.copy()
        T[:3, 3] += metres
        return T

    def depth_range(self) -> tuple[float, float]:
        """The camera z range (metres) of the model's box at the true pose: where its depth must lie."""
        corners = np.array([[self.aabb[i, 0], self.aabb[j, 1], self.aabb[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        z = corners @ self.T_cam_obj[2, :3] + self.T_cam_obj[2, 3]
        return float(z.min()), float(z.max())


def scene_for(model, width: int = 128, height: int = 96) -> Scene:
    """``model`` seen from above at about 30 degrees, its box's diagonal over 80% of the image
    width, centred; the joints at 40% of their ranges (so that mid-range starts off the truth)."""
    f = float(width)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    aabb = model.aabb.double().cpu().numpy()
    centre, diameter = aabb.mean(0), float(np.linalg.norm(aabb[1] - aabb[0]))
    c, s = math.cos(-0.5), math.sin(-0.5)
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    T[:3, 3] = np.array([0, 0, f * diameter / (0.8 * width)]) - T[:3, :3] @ centre
    joints = {j.name: j.lower + 0.4 * (j.upper - j.lower) for j in model.joints}
    return Scene(model.name, K, width, height, T, joints, aabb)
