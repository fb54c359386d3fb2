"""End to end: a real uvicorn server on a free loopback port, driven through narf_client and the benchmark."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator

import numpy as np
import pytest

pytest.register_assert_rewrite("conftest_service")
pytest_plugins = ("conftest_service",)

from conftest_service import ROOT, ToyModel  # noqa: E402
from narf_client import AsyncNarfClient, InvalidInput, NarfClient, NotFound, PayloadTooLarge, Pose  # noqa: E402
from narf_service.app import create_app  # noqa: E402
from narf_service.main import serve_in_thread  # noqa: E402
from narf_service.registry import ModelRegistry  # noqa: E402
from narf_service.settings import Settings  # noqa: E402

pytestmark = pytest.mark.slow

K = np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]])
W, H = 64, 48


@pytest.fixture(scope="module")
def server(service_engine, service_model, tmp_path_factory) -> Iterator[str]:
    settings = Settings(
        models_dir=tmp_path_factory.mktemp("models"), workers=2, queue_size=4, torch_threads=1, max_body_bytes=256 * 1024
    )
    app = create_app(settings, engine=service_engine, registry=ModelRegistry(models={"toy": service_model}))
    with serve_in_thread(app) as url:
        yield url


def test_render_then_estimate_through_the_client(server: str, service_model) -> None:
    pose = Pose.from_position_orientation([0, 0, 0.4], [0, 0, 0, 1])
    with NarfClient(server) as narf:
        assert narf.health() and narf.ready()
        assert [m.name for m in narf.models()] == ["toy"]
        info = narf.model("toy")
        assert info.bounds.shape == (2, 3) and [j.name for j in info.joints] == [j.name for j in service_model.joints]
        view = narf.render("toy", pose, K, W, H, joints=info.mid_joints, outputs=("rgb", "depth", "opacity"))
        assert view.rgb.shape == (H, W, 3) and view.depth.shape == view.opacity.shape == (H, W)
        mask = view.opacity > 0.5
        assert mask.any() and (view.depth[mask] > 0).all() and (view.depth[~mask] == 0).all()
        if isinstance(service_model, ToyModel):
            assert view.depth[H // 2, W // 2] == pytest.approx(0.38, abs=1e-3)
        start = Pose.from_position_orientation([0.01, 0, 0.41], [0, 0, 0, 1])
        est = narf.estimate(
            view.rgb,
            mask,
            K,
            start,
            model="toy",
            initial_joints=info.mid_joints,
            depth=view.depth,
            iterations=5,
            ground_truth=(pose, info.mid_joints),
        )
    assert est.pose.matrix.shape == (4, 4) and set(est.joints) == set(info.mid_joints)
    assert est.iterations <= 5 and est.metrics is not None
    assert est.metrics["add"] == pytest.approx(np.hypot(0.01, 0.01))  # the toy refiner scores its unmoved start


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
    import asyncio

    async def main() -> list:
        async with AsyncNarfClient(server) as narf:
            pose = Pose.from_position_orientation([0, 0, 0.4], [0, 0, 0, 1])
            return await asyncio.gather(*(narf.render("toy", pose, K, W, H) for _ in range(4)))

    views = asyncio.run(main())
    assert all(v.rgb.shape == (H, W, 3) for v in views)


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
    assert "ADD" in out and "status" in out and "round trip" in out
