"""The layers show in the imports (docs/design.md §1): checked in fresh interpreters, on ``sys.modules``.

The core never imports the service or the benchmarks (the CLI imports them inside the commands that
need them); the renderer never imports a concrete field; the part composition sits below the
renderer; the model bundle does not depend on the evaluation metrics.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PROBE = """
import importlib, json, pkgutil, sys

def fresh(name):
    # the narf_core modules that importing `name` loads, from none loaded (torch and the rest stay)
    for m in [m for m in sys.modules if m.split(".")[0] == "narf_core"]:
        del sys.modules[m]
    importlib.import_module(name)
    return sorted(m for m in sys.modules if m.split(".")[0] == "narf_core")

report = {
    "render": fresh("narf_core.render"),
    "composed": fresh("narf_core.fields.composed"),
    "bundle": fresh("narf_core.bundle"),
}
import narf_core
names = sorted(m.name for m in pkgutil.walk_packages(narf_core.__path__, "narf_core."))
skipped = {}
for name in names:
    try:
        importlib.import_module(name)
    except ImportError as e:  # an optional extra (pybullet, mitsuba) that is not installed
        if (e.name or "").split(".")[0] in ("narf_core", "narf_service", "narf_benchmarks"):
            raise
        skipped[name] = e.name
report["modules"], report["skipped"] = names, skipped
report["outer"] = sorted(m for m in sys.modules if m.split(".")[0] in ("narf_service", "narf_benchmarks"))
print(json.dumps(report))
"""


def test_the_layers_show_in_the_imports():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    # no core module (the CLI included) imports the service or the benchmarks
    assert {"narf_core.cli", "narf_core.render", "narf_core.bundle", "narf_core.estimate"} <= set(report["modules"])
    assert "narf_core.cli" not in report["skipped"]
    assert report["outer"] == []
    # the renderer is occupancy + sampling + compositing, and imports no field
    assert {"narf_core.occupancy", "narf_core.sampling", "narf_core.compositing"} <= set(report["render"])
    assert not any(m.startswith("narf_core.fields") for m in report["render"])
    # the part composition sits below the renderer; the bundle does not need the metrics
    assert "narf_core.render" not in report["composed"]
    assert "narf_core.bundle" in report["bundle"] and "narf_core.metrics" not in report["bundle"]
