"""The service must not pull in the dataset generator (narf_core.data.synth) nor pybullet (docs/design.md §1)."""

from __future__ import annotations

import json
import subprocess
import sys

from helpers import ROOT

PROBE = """
import importlib.util, json, sys
sys.path.insert(0, "tests")
from checkout import import_from_checkout
import_from_checkout()
import narf_service, narf_service.app, narf_service.main
from narf_service.engine import Engine
from narf_service.settings import Settings
app = narf_service.create_app(Settings(models_dir="models"))
engine = Engine.narf_core() if importlib.util.find_spec("narf_core.estimate") else None  # what the lifespan loads
bad = sorted(m for m in sys.modules if m.split(".")[0] == "pybullet" or m.startswith("narf_core.data.synth"))
print(json.dumps({"bad": bad, "engine": engine is not None, "service": "narf_service.app" in sys.modules}))
"""


def test_service_imports_neither_synth_nor_pybullet() -> None:
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["service"] and report["bad"] == []
