"""One error shape for every failure: ``{"error": {"code", "message", "field"?}}``.

Routes raise :class:`ApiError` (or a subclass); FastAPI's own validation errors and HTTP errors are
rewritten into the same body by the handlers installed with :func:`install_error_handlers`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

logger = logging.getLogger("narf_service")

_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    408: "request_timeout",
    413: "too_large",
    415: "unsupported_media_type",
    422: "invalid_input",
    503: "busy",
}


class ApiError(StarletteHTTPException):
    """An error answered with ``status`` and the JSON error body.

    A subclass of Starlette's ``HTTPException`` so that FastAPI lets it through body parsing
    unchanged (the body-size limit raises it from inside ``receive``).
    """

    def __init__(
        self,
        status: int,
        message: str,
        *,
        field: str | None = None,
        code: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(status_code=status, detail=message, headers=headers)
        self.code = code or _CODES.get(status, "error")
        self.message = message
        self.field = field


def invalid(field: str, message: str) -> ApiError:
    """A 422 naming ``field`` (dotted path into the request, e.g. ``"pose.matrix"``)."""
    return ApiError(422, f"{field}: {message}", field=field)


def error_body(code: str, message: str, field: str | None = None) -> dict[str, Any]:
    error: dict[str, Any] = {"code": code, "message": message}
    if field is not None:
        error["field"] = field
    return {"error": error}


def field_path(loc: Sequence[str | int]) -> str:
    """``("body", "pose", "matrix", 0)`` -> ``"pose.matrix[0]"``; the ``body`` / ``query`` root dropped."""
    parts = list(loc[1:] if loc and loc[0] in ("body", "query", "path", "header") else loc)
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "body"


def _validation_message(err: dict[str, Any]) -> str:
    msg = str(err.get("msg", "invalid value"))
    return msg.removeprefix("Value error, ")


async def _api_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    return JSONResponse(error_body(exc.code, exc.message, exc.field), exc.status_code, headers=exc.headers)


async def _http_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    code = _CODES.get(exc.status_code, "error")
    return JSONResponse(error_body(code, str(exc.detail)), exc.status_code, headers=exc.headers)


async def _validation_error(_: Request, exc: Exception) -> JSONResponse:
    """The first validation error, as ``field: message``; malformed JSON is a 400."""
    assert isinstance(exc, RequestValidationError)
    errors = list(exc.errors())
    if not errors:
        return JSONResponse(error_body("invalid_input", "invalid request"), 422)
    first = errors[0]
    if first.get("type") == "json_invalid":
        where = field_path([p for p in first.get("loc", ()) if not isinstance(p, int)])
        detail = (first.get("ctx") or {}).get("error", "")
        return JSONResponse(error_body("malformed_json", f"{where}: malformed JSON ({detail})".strip(), where), 400)
    where = field_path(first.get("loc", ()))
    total = getattr(exc, "total", len(errors))  # bodies validated off the loop report their first error and a count
    more = f" (and {total - 1} more)" if total > 1 else ""
    return JSONResponse(error_body("invalid_input", f"{where}: {_validation_message(first)}{more}", where), 422)


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    logger.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return JSONResponse(error_body("internal", "internal server error"), 500)


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(Exception, _unexpected)
