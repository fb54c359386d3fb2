"""Request bodies: read within their limits, parsed and validated off the event loop when large.

:class:`GuardedBodyRoute` is the route class of the API's routes. Before FastAPI reads a body it
  * answers 415 to a JSON route sent another media type, or none;
  * reads a JSON body up to ``Settings.max_json_bytes`` (413 beyond: a valid request is a few kB);
  * parses and validates a JSON body larger than :data:`INLINE_BYTES` on a thread, so that a
    hostile document (millions of keys) never stalls the event loop and the other clients with it;
  * parses a multipart form with ``max_json_bytes`` per non-file field and a few fields and files.
A valid body then reaches FastAPI already parsed (its validation of it is cheap); an invalid one is
answered from the thread's result with the usual error body.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import params
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import TypeAdapter, ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect, Request
from starlette.responses import Response

from narf_service.errors import ApiError

INLINE_BYTES = 8 * 2**10
"""JSON bodies up to this size are parsed on the event loop (it takes microseconds); larger ones on a thread."""
CLIENT_CLOSED_REQUEST = 499  # nginx's status for a client gone before its answer (which nobody reads)
MAX_FORM_FIELDS = 8
MAX_FORM_FILES = 8


class ManyValidationErrors(RequestValidationError):
    """A validation failure reported by its first errors and its ``total`` count."""

    def __init__(self, errors: list[dict[str, Any]], total: int) -> None:
        super().__init__(errors)
        self.total = total


def is_json(content_type: str | None) -> bool:
    if content_type is None:
        return False
    media_type = content_type.split(";")[0].strip().lower()
    return media_type == "application/json" or (media_type.startswith("application/") and media_type.endswith("+json"))


async def read_limited(request: Request, limit: int) -> bytes:
    """The whole body, or 413 as soon as more than ``limit`` bytes came."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise ApiError(413, f"body: a JSON body exceeds the limit of {limit} bytes", field="body")
        chunks.append(chunk)
    return b"".join(chunks)


def _json_invalid(position: int, reason: str) -> dict[str, Any]:
    """A malformed-JSON error as FastAPI reports it."""
    return {"type": "json_invalid", "loc": ("body", position), "msg": "JSON decode error", "input": {},
            "ctx": {"error": reason}}


def parse_and_validate(body: bytes, adapter: TypeAdapter) -> Any:
    """``json.loads(body)``, checked against ``adapter``; errors as FastAPI reports them (under ``body``)."""
    try:
        document = json.loads(body)
    except json.JSONDecodeError as e:
        raise RequestValidationError([_json_invalid(e.pos, e.msg)]) from None
    except (UnicodeDecodeError, RecursionError) as e:
        raise RequestValidationError([_json_invalid(0, type(e).__name__)]) from None
    try:
        adapter.validate_python(document)
    except ValidationError as e:
        first = e.errors(include_url=False, include_input=False)[:1]
        raise ManyValidationErrors([{**err, "loc": ("body", *err["loc"])} for err in first], e.error_count()) from None
    return document


class GuardedBodyRoute(APIRoute):
    """An ``APIRoute`` whose body is read within limits and, when large, parsed off the event loop."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        field = self.body_field
        if field is None:
            return handler
        if isinstance(field.field_info, params.Form):

            async def form_handler(request: Request) -> Response:
                limit = request.app.state.settings.max_json_bytes
                try:  # parsed here with our limits; FastAPI's own request.form() then returns this cached form
                    await request.form(max_files=MAX_FORM_FILES, max_fields=MAX_FORM_FIELDS, max_part_size=limit)
                except ClientDisconnect:
                    return Response(status_code=CLIENT_CLOSED_REQUEST)
                except StarletteHTTPException as e:  # Starlette answers 400 to every multipart limit
                    if "maximum size" in str(e.detail):
                        message = f"body: a form field exceeds the limit of {limit} bytes"
                        raise ApiError(413, message, field="body") from None
                    if "Too many" in str(e.detail):
                        raise ApiError(413, f"body: {e.detail}", field="body") from None
                    raise
                return await handler(request)

            return form_handler
        adapter = TypeAdapter(field.field_info.annotation)

        async def json_handler(request: Request) -> Response:
            content_type = request.headers.get("content-type")
            if not is_json(content_type):
                raise ApiError(415, f"body: expected application/json, got {content_type!r}", field="body")
            try:
                body = await read_limited(request, request.app.state.settings.max_json_bytes)
            except ClientDisconnect:
                return Response(status_code=CLIENT_CLOSED_REQUEST)
            request._body = body  # Starlette's cache of the body: FastAPI reads it from there
            if len(body) > INLINE_BYTES:
                request._json = await asyncio.to_thread(parse_and_validate, body, adapter)  # likewise cached
            return await handler(request)

        return json_handler
