"""NARF's HTTP service (API v1): FastAPI app, settings, model registry, bounded work queue.

``narf_service.create_app()`` builds the app; ``narf_service.main.serve()`` runs it with uvicorn.
The service imports the core library but never the dataset generator (``narf_core.data.synth``)
nor pybullet.
"""

from narf_core.threads import prefer_passive_wait

prefer_passive_wait()  # before torch is first imported: idle OpenMP threads sleep, not spin

from narf_service.app import create_app  # noqa: E402
from narf_service.settings import Settings  # noqa: E402

__all__ = ["Settings", "create_app"]
