"""Server failures mapped to protocol error codes, in one place for HTTP and WebSocket.

``error_code`` names the ``ErrorCode`` of a known failure (an unknown scene, core or cell, a
core that does not fit, a scene that fails to load, ...); the HTTP routes answer it with
``protocol.codes.HTTP_STATUS`` (``ApiError.of``), the WebSocket session sends it in an
``error`` message (fatal or not per ``protocol.codes.is_fatal``). Every HTTP error body is
``error_body``'s.
"""

from __future__ import annotations

from typing import Any

from protocol.codes import HTTP_STATUS, ErrorCode
from server.admission import Busy, OverLimit, Refused, TooManyInFlight
from server.catalog import SceneLoadFailed, UnknownSceneError
from server.region import UnknownCellError, UnsupportedSceneError
from server.resolve import UnknownCoreError
from visibility.cancel import ComputationCancelled
from visibility.cores.base import SegmentNotSupported

#: Known failures and their codes, most specific class first (the first match wins).
_CODES: tuple[tuple[type[BaseException], ErrorCode], ...] = (
    (UnknownSceneError, ErrorCode.UNKNOWN_SCENE),
    (UnknownCellError, ErrorCode.UNKNOWN_CELL),
    (UnknownCoreError, ErrorCode.UNKNOWN_CORE),
    (UnsupportedSceneError, ErrorCode.UNSUPPORTED_SCENE),
    (SegmentNotSupported, ErrorCode.UNSUPPORTED_REGION),
    (SceneLoadFailed, ErrorCode.SCENE_LOAD_FAILED),
    (ComputationCancelled, ErrorCode.DEADLINE_EXCEEDED),
    (OverLimit, ErrorCode.OVER_LIMIT),
    (TooManyInFlight, ErrorCode.TOO_MANY_REQUESTS),
    (Busy, ErrorCode.BUSY),
)


def error_code(exc: BaseException, *, params: bool = False) -> ErrorCode | None:
    """The code of a known failure, else None.

    Parameters
    ----------
    exc : the failure.
    params : the failure came from checking a request's core and parameters: any other
        ValueError there is ``bad_params``.
    """
    for cls, code in _CODES:
        if isinstance(exc, cls):
            return code
    if params and isinstance(exc, ValueError):
        return ErrorCode.BAD_PARAMS
    return None


def error_message(exc: BaseException) -> str:
    """The message of ``exc`` for an error answer (a LookupError's own text, not the quoted
    repr ``str(KeyError)`` gives)."""
    if isinstance(exc, LookupError) and exc.args:
        return str(exc.args[0])
    return str(exc)


def error_body(code: ErrorCode | str, message: str, **extra: Any) -> dict[str, Any]:
    """The JSON body of every HTTP error: ``{"error": {"code", "message", ...extra}}``."""
    return {"error": {"code": str(code), "message": message, **extra}}


def code_for_status(status: int) -> ErrorCode | str:
    """The code of an HTTP error the framework raised with ``status`` (routing, body parsing):
    the named one for the status, else ``http_<status>``."""
    for code, s in HTTP_STATUS.items():
        if s == status and code in _FRAMEWORK_CODES:
            return code
    return f"http_{status}"


#: The codes of errors the framework (not a route) raises: one per status.
_FRAMEWORK_CODES = frozenset({ErrorCode.BAD_REQUEST, ErrorCode.NOT_FOUND,
                              ErrorCode.METHOD_NOT_ALLOWED, ErrorCode.NOT_ACCEPTABLE,
                              ErrorCode.TOO_BIG})


class ApiError(Exception):
    """An error answered as ``error_body(code, message, **extra)`` with HTTP ``status`` and
    ``headers`` (``Retry-After`` of a refusal)."""

    def __init__(self, status: int, code: ErrorCode, message: str,
                 headers: dict[str, str] | None = None, **extra: Any) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers or {}
        self.extra = extra

    @classmethod
    def coded(cls, code: ErrorCode, message: str, headers: dict[str, str] | None = None,
              **extra: Any) -> ApiError:
        """The error for ``code``, with its ``HTTP_STATUS``."""
        return cls(HTTP_STATUS[code], code, message, headers, **extra)

    @classmethod
    def of(cls, exc: BaseException, *, params: bool = False) -> ApiError | None:
        """The error for a known failure (``error_code``), else None. An admission refusal
        carries its limit in the body and ``Retry-After`` when retrying can help."""
        if isinstance(exc, ApiError):
            return exc
        code = error_code(exc, params=params)
        if code is None:
            return None
        if isinstance(exc, Refused):
            headers = ({} if exc.retry_after is None
                       else {"Retry-After": str(int(exc.retry_after))})
            return cls.coded(code, error_message(exc), headers, **exc.detail)
        return cls.coded(code, error_message(exc))
