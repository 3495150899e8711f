"""HTTP middleware: a request-body size limit (413 with the JSON error body), the count of HTTP
bytes sent (``/metrics``), and a per-address rate limit on the PVS routes (429, ``RateLimit``).

A pure ASGI middleware (no ``BaseHTTPMiddleware``, which buffers and breaks streaming). A request
whose ``Content-Length`` is over the limit is refused before any of its body is read; a body
without a length (chunked) is counted as it arrives and refused once it passes the limit.
WebSocket traffic passes untouched (the session enforces ``max_message_bytes`` itself).
"""

from __future__ import annotations

import asyncio
import json
import time
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


class RateLimit:
    """Requests per second per client address on the PVS routes (paths ending in ``/pvs``): a
    token bucket of ``burst`` requests refilled at ``rate`` per second. Past it the request is
    answered 429 ``too_many_requests`` with ``Retry-After`` before it is parsed or routed.

    Refusing an over-limit PVS request costs the event loop about 3 ms (body parsing, the cost
    estimate, the JSON error); a client that sends hundreds a second without waiting for a
    limit to pass would take the loop from every walker. This answer costs a tenth of that,
    and it comes after ``TARPIT_S`` seconds (a sleeping coroutine costs nothing), so a client
    that waits for its answers sends at most one request per connection that often.
    A request answered with a refusal (422, 429, 503) costs ``REFUSED_COST`` tokens, not one:
    a client whose requests succeed keeps the whole rate, one that keeps asking for what the
    server refuses gets a fifth of it.
    Buckets of addresses idle for ``IDLE_S`` seconds are dropped once there are
    ``MAX_CLIENTS``, so the table stays bounded whatever the number of addresses.
    """

    IDLE_S = 60.0
    MAX_CLIENTS = 10_000
    TARPIT_S = 0.5
    REFUSED_COST = 5.0
    REFUSED = frozenset({422, 429, 503})

    def __init__(self, app: ASGIApp, rate: float, burst: int, counters: Counter) -> None:
        self.app = app
        self.rate = float(rate)
        self.burst = float(burst)
        self.counters = counters
        self._buckets: dict[str, tuple[float, float]] = {}

    def allow(self, client: str, now: float, cost: float = 1.0) -> bool:
        """Take ``cost`` tokens of ``client``'s bucket at monotonic time ``now`` (a bucket may
        go into debt, repaid at ``rate``); False, taking nothing, when it holds less than one."""
        tokens, last = self._buckets.get(client, (self.burst, now))
        tokens = min(self.burst, tokens + (now - last) * self.rate)
        ok = tokens >= 1.0
        self._buckets[client] = (tokens - cost if ok else tokens, now)
        if len(self._buckets) > self.MAX_CLIENTS:
            self._buckets = {k: v for k, v in self._buckets.items()
                             if now - v[1] < self.IDLE_S}
        return ok

    def charge(self, client: str, cost: float) -> None:
        """Take ``cost`` more tokens from ``client``'s bucket (its request was refused)."""
        tokens, last = self._buckets.get(client, (self.burst, time.monotonic()))
        self._buckets[client] = (tokens - cost, last)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope.get("path", "").endswith("/pvs"):
            await self.app(scope, receive, send)
            return
        host = (scope.get("client") or ("?", 0))[0]
        if self.allow(host, time.monotonic()):
            async def charged_send(message: Message) -> None:
                if (message["type"] == "http.response.start"
                        and message.get("status") in self.REFUSED):
                    self.charge(host, self.REFUSED_COST - 1.0)
                await send(message)

            await self.app(scope, receive, charged_send)
            return
        self.counters["http_rate_limited"] += 1
        await asyncio.sleep(self.TARPIT_S)
        body = json.dumps(error_body(
            ErrorCode.TOO_MANY_REQUESTS, f"over {self.rate:g} PVS requests per second from "
            "this address (pvs_rate)", limit="pvs_rate", value=self.rate)).encode()
        await send({"type": "http.response.start", "status": 429,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode()),
                                (b"retry-after", b"1")]})
        await send({"type": "http.response.body", "body": body})
