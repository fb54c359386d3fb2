"""The edge of the service, before any route runs: who may ask, and how long a client may take.

* :class:`AuthGate` checks the bearer token on every route that ``Settings.public_routes`` does not
  name, from the headers alone, so an unauthenticated body is never read, let alone parsed. Routes
  are matched by path prefix, so a route added later is private unless it is listed.
* :class:`BodyDeadline` answers 408 (and closes the connection) when a request body has not fully
  arrived within ``body_timeout_s`` of its headers: a client trickling a byte a second cannot hold a
  connection and a handler forever.
* :func:`timed_h11_protocol` closes connections that do not finish a request's headers within
  ``header_timeout_s`` (a 408 if some bytes came); uvicorn closes idle keep-alive connections itself
  after ``timeout_keep_alive``, but only once a first response was sent, and never re-arms it while
  the headers of the next request trickle in.
"""

from __future__ import annotations

import asyncio
import hmac
import json

import h11
from starlette.datastructures import Headers
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from narf_service.errors import ApiError, error_body
from narf_service.settings import Settings


def authorized(settings: Settings, authorization: str | None) -> bool:
    """Whether an ``Authorization`` header value carries the token (always, when none is set)."""
    if settings.token is None:
        return True
    scheme, _, given = (authorization or "").partition(" ")
    if scheme.lower() != "bearer":
        return False
    return hmac.compare_digest(given.strip().encode(), settings.token.get_secret_value().encode())


class AuthGate:
    """Pure ASGI middleware: 401 on a non-public route without the token, before the body is read."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or self.settings.token is None
            or self.settings.is_public(scope["path"])
            or authorized(self.settings, Headers(scope=scope).get("authorization"))
        ):
            await self.app(scope, receive, send)
            return
        body = error_body("unauthorized", "missing or wrong bearer token")
        await JSONResponse(body, 401, headers={"WWW-Authenticate": "Bearer"})(scope, receive, send)


class RequestTimeout(ApiError):
    def __init__(self, seconds: float) -> None:
        message = f"the request body did not arrive within {seconds:g} s"
        super().__init__(408, message, code="request_timeout", headers={"Connection": "close"})


class BodyDeadline:
    """Pure ASGI middleware: the whole body must arrive within ``seconds`` of the headers.

    ``receive`` raises :class:`RequestTimeout` (an ``HTTPException``, answered 408 by the error
    handlers) once the deadline passes. After the last body chunk, ``receive`` is not timed: a
    handler may wait on it for the client's disconnect.
    """

    def __init__(self, app: ASGIApp, seconds: float) -> None:
        self.app = app
        self.seconds = seconds

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        deadline = asyncio.get_running_loop().time() + self.seconds
        complete = False

        async def timed_receive() -> Message:
            nonlocal complete
            if complete:
                return await receive()
            remaining = deadline - asyncio.get_running_loop().time()
            try:
                message = await asyncio.wait_for(receive(), timeout=max(remaining, 0))
            except TimeoutError:
                raise RequestTimeout(self.seconds) from None
            if message["type"] != "http.request" or not message.get("more_body", False):
                complete = True
            return message

        await self.app(scope, timed_receive, send)


_TIMEOUT_RESPONSE = json.dumps(
    error_body("request_timeout", "the request headers did not arrive in time")
).encode()


def timed_h11_protocol(header_timeout_s: float) -> type[H11Protocol]:
    """uvicorn's h11 protocol, closing a connection whose request headers are not complete within
    ``header_timeout_s`` of connecting or of the previous response."""

    class TimedH11Protocol(H11Protocol):
        _header_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._arm_header_timer()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self.conn.their_state is not h11.IDLE:  # a request's headers are complete
                self._disarm_header_timer()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
                self._arm_header_timer()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm_header_timer()
            super().connection_lost(exc)

        def _arm_header_timer(self) -> None:
            self._disarm_header_timer()
            self._header_timer = self.loop.call_later(header_timeout_s, self._headers_timed_out)

        def _disarm_header_timer(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _headers_timed_out(self) -> None:
            self._header_timer = None
            if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
                return
            if self.conn.trailing_data[0]:  # part of a request came: say why it is dropped
                self.transport.write(
                    b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\nconnection: close\r\n"
                    + f"content-length: {len(_TIMEOUT_RESPONSE)}\r\n\r\n".encode()
                    + _TIMEOUT_RESPONSE
                )
            self.transport.close()

    return TimedH11Protocol
