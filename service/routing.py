"""What every route of the API shares: the token dependency, the model registry, running a job on
the work queue (cancelled when its client disconnects), the size check of a camera, and the error
responses for the OpenAPI document. Route modules (:mod:`narf_service.app`,
:mod:`narf_service.tracking`) import these; they import no route module.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Request
from fastapi.responses import Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from narf_service.bodies import CLIENT_CLOSED_REQUEST
from narf_service.errors import ApiError
from narf_service.guards import authorized
from narf_service.registry import ModelRegistry
from narf_service.schemas import Camera, ErrorResponse
from narf_service.settings import Settings
from narf_service.workers import QueueFull, Stop

T = TypeVar("T")


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    return {status: {"model": ErrorResponse} for status in statuses}


_bearer = HTTPBearer(auto_error=False, description="Required when the server runs with NARF_TOKEN set.")


async def require_token(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> None:
    """The token check as a dependency, for the OpenAPI document; :class:`AuthGate` has already
    refused a request without it, before its body was read."""
    given = None if credentials is None else f"Bearer {credentials.credentials}"
    if not authorized(request.app.state.settings, given):
        raise ApiError(401, "missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"})


def registry_of(request: Request) -> ModelRegistry:
    return request.app.state.registry


async def run_job(request: Request, fn: Callable[[Stop], T]) -> T | Response:
    """Run ``fn(stop)`` on the work queue; 503 with ``Retry-After`` when the queue is full.

    If the client disconnects first, the job is cancelled (a waiting one never starts, a running one
    sees ``stop()`` say ``"cancelled"``) and the answer, which nobody reads, is a bare 499.
    """
    stop = Stop(request.app.state.settings.max_seconds)
    try:
        future = request.app.state.queue.submit(lambda: fn(stop), stop)
    except QueueFull as e:
        request.app.state.metrics.rejected.inc()
        raise ApiError(503, str(e), headers={"Retry-After": str(e.retry_after_s)}) from None
    work = asyncio.wrap_future(future)
    gone = asyncio.ensure_future(_disconnected(request))
    try:
        await asyncio.wait({work, gone}, return_when=asyncio.FIRST_COMPLETED)
    finally:  # on a disconnect, and also when this coroutine is cancelled (server shutdown)
        gone.cancel()
        if not work.done():
            future.cancel()
            stop.cancel()
            work.cancel()
    if work.done() and not work.cancelled():
        return work.result()
    request.app.state.metrics.cancelled.inc()
    return Response(status_code=CLIENT_CLOSED_REQUEST)


async def _disconnected(request: Request) -> None:
    """Returns when the client has gone (called once the body is read: nothing else can arrive)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


def check_pixels(camera: Camera, settings: Settings, field: str) -> None:
    pixels = camera.width * camera.height
    if pixels > settings.max_image_pixels:
        limit = settings.max_image_pixels
        message = f"{field}: {camera.width}x{camera.height} = {pixels} pixels exceeds the limit of {limit}"
        raise ApiError(413, message, field=field)
