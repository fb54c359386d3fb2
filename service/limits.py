"""Request body size limit (413), checked on the declared ``Content-Length`` *and* on the bytes
actually streamed, so neither a lying header nor chunked transfer gets past it."""

from __future__ import annotations

from starlette.datastructures import Headers
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from narf_service.errors import ApiError, error_body


class BodyTooLarge(ApiError):
    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body exceeds the limit of {limit} bytes")


class BodySizeLimit:
    """Pure ASGI middleware: a body longer than ``max_bytes`` is answered with 413.

    A too-large ``Content-Length`` is refused before any byte is read. Otherwise the bytes are
    counted as the app reads them and :class:`BodyTooLarge` is raised from ``receive`` past the
    limit; it is an ``HTTPException``, so FastAPI's body parsing lets it through to the error
    handlers, which answer 413 with the usual JSON error body.
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            error = BodyTooLarge(self.max_bytes)
            await JSONResponse(error_body(error.code, error.message), 413)(scope, receive, send)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes)
            return message

        await self.app(scope, limited_receive, send)
