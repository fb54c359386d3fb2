"""Exceptions carrying the server's error (``{"error": {"code", "message", "field"}}``) and status code."""

from __future__ import annotations


class NarfError(Exception):
    """A request the server refused or could not answer.

    ``status_code`` is the HTTP status (``None`` when no answer came: connection refused, timeout);
    ``code``, ``message`` and ``field`` come from the server's error body.
    """

    def __init__(
        self,
        message: str,
        *,
        status_code: int | None = None,
        code: str | None = None,
        field: str | None = None,
        retry_after: float | None = None,
    ) -> None:
        super().__init__(message if status_code is None else f"HTTP {status_code}: {message}")
        self.message = message
        self.status_code = status_code
        self.code = code
        self.field = field
        self.retry_after = retry_after


class NarfConnectionError(NarfError):
    """No answer: the server is unreachable or did not reply in time."""


class BadRequest(NarfError):
    """400: malformed request (e.g. invalid JSON)."""


class Unauthorized(NarfError):
    """401: missing or wrong bearer token."""


class NotFound(NarfError):
    """404: unknown model (or route)."""


class PayloadTooLarge(NarfError):
    """413: body or image over the server's limits."""


class InvalidInput(NarfError):
    """422: a field the server refused; ``field`` names it."""


class ServiceUnavailable(NarfError):
    """503: the server's work queue stayed full through every retry; ``retry_after`` is its last hint."""


class ServerError(NarfError):
    """5xx other than 503: a fault in the server."""


_BY_STATUS: dict[int, type[NarfError]] = {
    400: BadRequest,
    401: Unauthorized,
    404: NotFound,
    413: PayloadTooLarge,
    422: InvalidInput,
    503: ServiceUnavailable,
}


def error_for_status(status_code: int) -> type[NarfError]:
    if status_code in _BY_STATUS:
        return _BY_STATUS[status_code]
    return ServerError if status_code >= 500 else NarfError
