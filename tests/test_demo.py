"""The README's main job, end to end: ``narf serve`` on the bundled demo model, driven by the example client.

Runs the real command in a subprocess on a free loopback port, as ``scripts/demo.sh`` does, so the
console script, the lifespan model loading, the HTTP layer, the client and the trained bundle are
all exercised together.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from narf_service.main import serve_process

ROOT = Path(__file__).resolve().parent.parent
MODEL = ROOT / "models" / "clamp.narf"

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not MODEL.exists(), reason="no bundled demo model")]


@pytest.fixture(scope="module")
def server():
    with serve_process(["--models", str(MODEL.parent)], {**os.environ, "NARF_TORCH_THREADS": "1"}, startup_timeout_s=60) as url:
        yield url


def test_models_lists_the_demo_clamp(server):
    models = httpx.get(f"{server}/v1/models").json()
    assert [m["name"] for m in models["models"]] == ["clamp"]
    info = httpx.get(f"{server}/v1/models/clamp").json()
    assert [j["name"] for j in info["joints"]] == ["jaw_opening"]


def test_example_client_recovers_pose_and_jaw(server):
    out = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "robot_client.py"), "--url", server, "--model", "clamp", "--json"],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["status"] in ("converged", "max_iterations")
    assert result["preset"] == "gauss-newton"  # the default, auto, on a view with a depth image
    # The paper's protocol start (10 deg / 2 cm off, jaw at mid-range) has an ADD of about 3 cm;
    # the refined pose must at least halve it (measured: 0.6 cm and 1.2 cm on this scene with two
    # revisions of the refiner). The benchmark, not this test, reports the accuracy.
    assert result["metrics"]["add"] < 0.015
    assert result["model"] == "clamp" and set(result["joints"]) == {"jaw_opening"}
