"""NARF's HTTP service (API v1): FastAPI app, settings, model registry, bounded work queue.

``narf_service.create_app()`` builds the app; ``narf_service.main.serve()`` runs it with uvicorn.
The service imports the core library but never the dataset generator (``narf_core.data.synth``)
nor pybullet.
"""

from narf_service.app import create_app
from narf_service.settings import Settings

__all__ = ["Settings", "create_app"]
