"""A thin client for the NARF HTTP service: numpy in, numpy out; httpx, numpy and pillow only (no torch).

    from narf_client import NarfClient
    with NarfClient("http://127.0.0.1:8000") as narf:
        view = narf.render("clamp", pose, K, 160, 120, outputs=("rgb", "depth", "opacity"))
        estimate = narf.estimate(view.rgb, view.opacity > 0.5, K, initial_pose, model="clamp")
"""

from narf_client.client import AsyncNarfClient, NarfClient
from narf_client.errors import (
    BadRequest,
    InvalidInput,
    NarfConnectionError,
    NarfError,
    NotFound,
    PayloadTooLarge,
    ServerError,
    ServiceUnavailable,
    Unauthorized,
)
from narf_client.types import Estimate, JointInfo, ModelInfo, Pose, RenderResult, TrackFrame, TrackUpdate, Uncertainty

__version__ = "0.1.0"

__all__ = [
    "AsyncNarfClient",
    "BadRequest",
    "Estimate",
    "InvalidInput",
    "JointInfo",
    "ModelInfo",
    "NarfClient",
    "NarfConnectionError",
    "NarfError",
    "NotFound",
    "PayloadTooLarge",
    "Pose",
    "RenderResult",
    "TrackFrame",
    "TrackUpdate",
    "Uncertainty",
    "ServerError",
    "ServiceUnavailable",
    "Unauthorized",
]
