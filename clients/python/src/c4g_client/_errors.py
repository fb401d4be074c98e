"""Every failure the client raises, as one hierarchy rooted at :class:`C4GError`.

The server answers errors as ``{"error": "<what happened and what to do>", "kind": "<kind>"}``
(REST) or as a gRPC status with the same message and the kind in the ``c4g-error-kind`` metadata
entry. The ``kind`` is what a caller switches on (``busy``: retry later; ``not_found``: the clip
is gone), so each kind of ``docs/api.md``'s error table is a class here, and every instance keeps
the HTTP status, the kind and the server's message. One table (:data:`KINDS`) maps kinds to
classes, HTTP statuses and gRPC codes, so REST and gRPC errors read the same.

Failures that never reached an answer (no connection) are :class:`TransportError`; payloads that
do not parse (a corrupt C4GS set, a C4GV stream cut short) are :class:`FormatError`.
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple, Type


class C4GError(Exception):
    """The root of every error this package raises."""


class TransportError(C4GError):
    """The request failed before the server answered (refused, reset, timed out)."""


class FormatError(C4GError, ValueError):
    """A payload from the server (or given to a decoder) is not what its format says."""


class StreamInterrupted(FormatError):
    """A stream ended before its last record: the server stopped it after the first byte.

    The compact 4D stream ends with an index record; a body without it was cut short by an error
    the server could no longer report as a status (it logs it).
    """


class ApiError(C4GError):
    """The server answered with an error: its HTTP ``status``, ``kind`` and ``message``.

    ``retry_after`` is the ``Retry-After`` the server sent (seconds), when it sent one;
    ``grpc_code`` is the gRPC status code's name when the error came over gRPC.
    """

    kind_name: str = ""

    def __init__(
        self,
        status: int,
        kind: str,
        message: str,
        *,
        retry_after: Optional[float] = None,
        grpc_code: Optional[str] = None,
    ) -> None:
        super().__init__(f"{status} {kind}: {message}")
        self.status = status
        self.kind = kind
        self.message = message
        self.retry_after = retry_after
        self.grpc_code = grpc_code


class RetryableError(ApiError):
    """Errors that say nothing about the request: the same request may succeed later."""


class InvalidInput(ApiError):
    """400: malformed JSON, NaN or out-of-span times, a bad camera, bad options."""


class Unauthorized(ApiError):
    """401: the server has an API key and the request lacks it or has another."""


class NotFound(ApiError):
    """404: an unknown clip, job, context frame or endpoint."""


class TooLarge(ApiError):
    """413: a body, frame count, resolution, duration or archive expansion over a limit."""


class UnsupportedMedia(ApiError):
    """415: neither a video FFmpeg reads nor an image archive."""


class UnreadableMedia(ApiError):
    """422: a truncated or corrupt file, frames too small, mixed frame sizes."""


class Unsupported(ApiError):
    """422: well formed, but the model package cannot do it."""


class TimedOut(ApiError):
    """408: the request body did not arrive in time."""


class Busy(RetryableError):
    """429: every encode slot is taken (``retry_after`` says when to retry)."""


class NotReady(RetryableError):
    """503: the model is still loading."""


class Draining(RetryableError):
    """503: the server is shutting down; another replica answers."""


class Overloaded(RetryableError):
    """503: the queue of decode and render work is full."""


class Unavailable(RetryableError):
    """503: a service the server depends on failed; nothing was changed."""


class InsufficientStorage(ApiError):
    """507: the store's disk is full; nothing was stored."""


class InternalError(ApiError):
    """500: the server or its model package failed (the server logged it)."""


#: kind → (class, HTTP status, gRPC code): docs/api.md's error table, in one place.
KINDS: Dict[str, Tuple[Type[ApiError], int, str]] = {
    "invalid_input": (InvalidInput, 400, "INVALID_ARGUMENT"),
    "unauthorized": (Unauthorized, 401, "UNAUTHENTICATED"),
    "not_found": (NotFound, 404, "NOT_FOUND"),
    "too_large": (TooLarge, 413, "RESOURCE_EXHAUSTED"),
    "unsupported_media": (UnsupportedMedia, 415, "INVALID_ARGUMENT"),
    "unreadable_media": (UnreadableMedia, 422, "INVALID_ARGUMENT"),
    "unsupported": (Unsupported, 422, "INVALID_ARGUMENT"),
    "timed_out": (TimedOut, 408, "DEADLINE_EXCEEDED"),
    "busy": (Busy, 429, "RESOURCE_EXHAUSTED"),
    "not_ready": (NotReady, 503, "UNAVAILABLE"),
    "draining": (Draining, 503, "UNAVAILABLE"),
    "overloaded": (Overloaded, 503, "UNAVAILABLE"),
    "unavailable": (Unavailable, 503, "UNAVAILABLE"),
    "insufficient_storage": (InsufficientStorage, 507, "RESOURCE_EXHAUSTED"),
    "internal": (InternalError, 500, "INTERNAL"),
}

for _kind, (_cls, _status, _code) in KINDS.items():
    _cls.kind_name = _kind

#: The kind of an answer whose body is not the API's JSON (a proxy's page), by status.
_STATUS_KINDS: Dict[int, str] = {
    400: "invalid_input",
    401: "unauthorized",
    404: "not_found",
    408: "timed_out",
    413: "too_large",
    415: "unsupported_media",
    429: "busy",
    500: "internal",
    503: "unavailable",
    507: "insufficient_storage",
}

#: The kind of a gRPC status that carries no ``c4g-error-kind`` (refused before the service saw
#: it: a message that does not decode is INVALID_ARGUMENT), by code.
_GRPC_KINDS: Dict[str, str] = {
    "INVALID_ARGUMENT": "invalid_input",
    "UNAUTHENTICATED": "unauthorized",
    "NOT_FOUND": "not_found",
    "UNIMPLEMENTED": "not_found",
    "RESOURCE_EXHAUSTED": "too_large",
    "DEADLINE_EXCEEDED": "timed_out",
    "UNAVAILABLE": "unavailable",
    "INTERNAL": "internal",
}


def api_error(
    status: int,
    kind: str,
    message: str,
    *,
    retry_after: Optional[float] = None,
    grpc_code: Optional[str] = None,
) -> ApiError:
    """The exception for an error answer: the kind's class, or :class:`ApiError` for a kind
    this version does not know (a newer server's), so a caller can still read ``kind``."""
    cls = KINDS[kind][0] if kind in KINDS else ApiError
    return cls(status, kind, message, retry_after=retry_after, grpc_code=grpc_code)


def kind_for_status(status: int) -> str:
    """The kind an error status stands for when the body does not say (``http_502`` for
    statuses no kind uses)."""
    return _STATUS_KINDS.get(status, f"http_{status}")


def grpc_api_error(code: str, message: str, kind: Optional[str]) -> ApiError:
    """The exception for a gRPC status ``code`` (its name, ``NOT_FOUND``), with the kind from
    the ``c4g-error-kind`` metadata when the server sent one."""
    kind = kind or _GRPC_KINDS.get(code, code.lower())
    status = KINDS[kind][1] if kind in KINDS else 500
    return api_error(status, kind, message, grpc_code=code)
