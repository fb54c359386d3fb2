"""Make ``narf_service`` and ``narf_client`` importable from a plain checkout.

``scripts/install.sh`` installs both; running ``python -m pytest`` without it should work too, so
``tests/conftest.py`` calls :func:`import_from_checkout` before any test module is imported. A
plain module (no pytest) so that a test's subprocess can call it as well.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

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
