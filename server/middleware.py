"""HTTP middleware: a request-body size limit (413 with the JSON error body) and the count of HTTP
bytes sent (``/metrics``).

A pure ASGI middleware (no ``BaseHTTPMiddleware``, which buffers and breaks streaming). A request
whose ``Content-Length`` is over the limit is refused before any of its body is read; a body
without a length (chunked) is counted as it arrives and refused once it passes the limit.
WebSocket traffic passes untouched (the session enforces ``max_message_bytes`` itself).
"""

from __future__ import annotations

import json
from collections import Counter

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from protocol.codes import ErrorCode
from server.errors import error_body


class BodyTooLarge(HTTPException):
    """A request body over the limit (raised while the body is read; answered 413)."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body over {limit} bytes")


def too_large_body(limit: int) -> bytes:
    """The JSON error body of a 413 answer."""
    return json.dumps(error_body(ErrorCode.TOO_BIG, f"request body over {limit} bytes")).encode()


class HttpGuard:
    """Refuse HTTP request bodies over ``max_body_bytes`` (413) and add every HTTP response
    body byte to ``counters["http_bytes_sent"]``."""

    def __init__(self, app: ASGIApp, max_body_bytes: int, counters: Counter) -> None:
        self.app = app
        self.max_body_bytes = int(max_body_bytes)
        self.counters = counters

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_body_bytes
        counters = self.counters

        async def counted_send(message: Message) -> None:
            if message["type"] == "http.response.body":
                counters["http_bytes_sent"] += len(message.get("body", b""))
            await send(message)

        length = _content_length(scope)
        if length is not None and length > limit:
            await _refuse(limit, counted_send)
            return
        seen = 0

        async def limited_receive() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    # An HTTPException: FastAPI passes it through its body parsing to the
                    # app's handler, which answers the JSON error body with 413.
                    raise BodyTooLarge(limit)
            return message

        await self.app(scope, limited_receive, counted_send)


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", ()):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


async def _refuse(limit: int, send: Send) -> None:
    body = too_large_body(limit)
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})
