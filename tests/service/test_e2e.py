"""End to end: a real uvicorn server on a free loopback port, driven through narf_client and the benchmark."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator

import numpy as np
import pytest

from helpers import ROOT, ToyModel, scene_for
from narf_client import AsyncNarfClient, InvalidInput, NarfClient, NotFound, PayloadTooLarge, Pose
from narf_service.app import create_app
from narf_service.main import serve_in_thread
from narf_service.registry import ModelRegistry
from narf_service.settings import Settings

pytestmark = pytest.mark.slow

K = np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]])
W, H = 64, 48


@pytest.fixture(scope="module")
def server(request: pytest.FixtureRequest, toy_engine, toy_model, tmp_path_factory) -> Iterator[str]:
    """The toy model with the toy engine; or, where a test parametrises this fixture with ``"clamp"``,
    the bundled model with the real library."""
    from narf_service.engine import Engine

    if getattr(request, "param", "toy") == "clamp":
        engine, model = Engine.narf_core(), request.getfixturevalue("bundled_model")
    else:
        engine, model = toy_engine, toy_model
    settings = Settings(
        models_dir=tmp_path_factory.mktemp("models"), workers=2, queue_size=4, torch_threads=1, max_body_bytes=256 * 1024
    )
    app = create_app(settings, engine=engine, registry=ModelRegistry(models={model.name: model}))
    with serve_in_thread(app) as url:
        yield url


@pytest.mark.parametrize("server", ["toy", "clamp"], indirect=True)
def test_render_then_estimate_through_the_client(server: str, request: pytest.FixtureRequest) -> None:
    """The client's round trip on the served model: the listing, a render whose depth lies within the
    model's box, and an estimate from 1 cm off scored against the truth (see test_api.py for the bounds)."""
    model = request.getfixturevalue({"toy": "toy_model", "clamp": "bundled_model"}[request.node.callspec.params["server"]])
    scene = scene_for(model)
    with NarfClient(server) as narf:
        assert narf.health() and narf.ready()
        assert [m.name for m in narf.models()] == [model.name]
        info = narf.model(model.name)
        assert np.allclose(info.bounds, model.aabb.tolist()) and [j.name for j in info.joints] == [j.name for j in model.joints]
        view = narf.render(model.name, scene.T_cam_obj, scene.K, scene.width, scene.height, joints=scene.joints,
                           outputs=("rgb", "depth", "opacity"))
        assert view.rgb.shape == (scene.height, scene.width, 3) and view.depth.shape == view.opacity.shape
        solid = view.opacity == 1
        near, far = scene.depth_range()
        assert solid.sum() > 0.05 * solid.size and (view.depth[solid] >= near - 1e-3).all()
        assert (view.depth[solid] <= far + 1e-3).all() and (view.depth[view.opacity == 0] <= 1e-3).all()
        start = scene.moved((0.01, 0.0, 0.01))
        toy = isinstance(model, ToyModel)
        est = narf.estimate(
            view.rgb,
            view.opacity > 0.5,
            scene.K,
            start,
            model=model.name,
            initial_joints=info.mid_joints,
            depth=view.depth,
            iterations=5 if toy else 30,
            options={"depth_weight": 1.0},
            ground_truth=(scene.T_cam_obj, scene.joints),
        )
    assert set(est.joints) == set(scene.joints) and all(j.lower <= est.joints[j.name] <= j.upper for j in model.joints)
    assert 1 <= est.iterations <= (5 if toy else 30) and est.metrics is not None
    if toy:  # the toy refiner scores its unmoved start
        assert est.metrics["add"] == pytest.approx(np.hypot(0.01, 0.01)) and est.uncertainty is None
    else:  # from about 2.2 cm (1.41 cm of pose, 1.8 cm of jaw)
        assert est.metrics["add"] < 0.011 and est.uncertainty is not None
        assert np.isfinite(est.uncertainty.covariance).all()


def test_errors_reach_the_client_with_the_servers_message(server: str, service_model) -> None:
    j = service_model.joints[0]
    with NarfClient(server) as narf:
        with pytest.raises(NotFound, match="unknown model"):
            narf.render("nope", np.eye(4), K, W, H)
        with pytest.raises(InvalidInput) as info:
            narf.render("toy", np.eye(4), K, W, H, joints={j.name: j.upper + 1})
        assert info.value.field == f"joints.{j.name}" and "limits" in info.value.message
        noise = np.random.default_rng(0).integers(0, 256, (400, 400, 3), dtype=np.uint8)  # ~480 kB as PNG
        with pytest.raises(PayloadTooLarge, match="exceeds"):
            narf.estimate(noise, np.ones((400, 400)), K, np.eye(4), model="toy")


def test_async_client_against_the_server(server: str) -> None:
    """Four renders at once, each answered with its own view: the toy box's near face at z - 2 cm."""
    import asyncio

    distances = [0.3, 0.35, 0.4, 0.45]

    async def main() -> list:
        async with AsyncNarfClient(server) as narf:
            poses = [Pose.from_position_orientation([0, 0, z], [0, 0, 0, 1]) for z in distances]
            return await asyncio.gather(*(narf.render("toy", p, K, W, H, outputs=("rgb", "depth")) for p in poses))

    views = asyncio.run(main())
    assert all(v.rgb.shape == (H, W, 3) for v in views)
    assert [float(v.depth[H // 2, W // 2]) for v in views] == pytest.approx([z - 0.02 for z in distances], abs=1e-3)


def test_benchmark_answers_every_request(server: str) -> None:
    spec = importlib.util.spec_from_file_location("bench_service", ROOT / "benchmarks" / "service.py")
    bench = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = bench
    spec.loader.exec_module(bench)
    result = bench.run(server, clients=4, requests=24, duration_s=30, estimate_clients=16, estimate_iterations=3, size=(W, H))
    render, estimate = result["routes"]
    assert render["ok"] == 24 and render["errors"] == {} and render["lost"] == {}
    assert estimate["ok"] + estimate["busy_503"] == 16 and estimate["errors"] == {} and estimate["lost"] == {}
    assert render["p99_ms"] >= render["p50_ms"] > 0 and result["server_peak_rss_mib"] > 0
    assert "| /v1/render | 4 | 24 | 24 |" in bench.markdown(result)
    with pytest.raises(ValueError, match="loopback"):
        bench.run("http://192.0.2.1:8000")


def test_robot_client_example(server: str, capsys) -> None:
    spec = importlib.util.spec_from_file_location("robot_client_example", ROOT / "examples" / "robot_client.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    assert example.main(["--url", server, "--size", str(W), str(H), "--iterations", "3"]) == 0
    out = capsys.readouterr().out
    assert "status max_iterations after 3 iterations" in out and "round trip" in out
    assert "ADD 2.00 cm (started 10 deg and 2 cm off)" in out  # the toy refiner's unmoved start: the 2 cm shift
    assert "joint jaw_slide: error " in out and "joint jaw_turn: error " in out
