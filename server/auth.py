"""Optional access control: bearer tokens on HTTP and WebSocket, per-scene allow lists and
per-token quotas (``server.tokens``, ``server.quotas``), with the WebSocket ``Origin`` check
(``server.cors``).

Off unless tokens are configured (``tokens_file``, ``PVS_TOKENS``): then every route but
``OPEN_PATHS`` needs a valid token (``protocol.auth`` says how a client presents one):

- HTTP (``AccessGuard``, before any routing or body parsing): none or an invalid one answers
  401 ``unauthorized`` with ``WWW-Authenticate: Bearer``; a scene outside the token's allow list
  (``/scenes/{scene}...``, ``?scene=``) 403 ``forbidden``, whether it exists or not; a PVS
  request past the token's ``pvs_per_minute`` 429 ``over_quota`` with ``Retry-After``.
  ``GET /scenes`` lists only the token's scenes.
- WebSocket (``admit_session``, ``check_scene`` in the handshake): the session is accepted,
  then a token refusal is an ``error`` and a close before ``hello`` is read (``unauthorized``,
  4401; ``over_quota``, 4429 past ``max_sessions``), a scene refusal the same right after
  ``hello`` (``forbidden``, 4403), before the scene is looked up.

Open without a token: ``/health`` (liveness probes), the API's description
(``/openapi.json``, ``/docs``, ``/redoc``: the same for everyone, no data, and the docs page's
"Authorize" button is how a person tries the API with a token) and the browser viewer's page and
static files (``VIEWER_FILES``: no data either, and a browser opening a page sends no
``Authorization`` header; the page then sends its token on every data request). ``/metrics``
needs a token: Prometheus sends one (``authorization: {credentials_file: ...}``).
"""

from __future__ import annotations

import json
import logging
import re
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI
from starlette.datastructures import QueryParams
from starlette.types import ASGIApp, Receive, Scope, Send

from protocol.auth import SUBPROTOCOL, TOKEN_SUBPROTOCOL_PREFIX, is_token
from protocol.codes import ErrorCode
from server.cors import normalize_origins, origin_allowed
from server.errors import error_body
from server.quotas import TokenQuotas, retry_after_header
from server.settings import Settings
from server.tokens import Grant, TokenBook, env_grants, read_tokens_file

if TYPE_CHECKING:
    from server.state import Session

log = logging.getLogger(__name__)

#: Routes answered without a token.
OPEN_PATHS = frozenset({"/health", "/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc"})
#: The viewer's page and files (``server.viewer_files``), GET or HEAD: ``/viewer``, ``/viewer/``
#: and files of the served types below it. One pattern rather than a prefix, so that nothing
#: else under ``/viewer`` opens: no segment starts with a dot (no ``..``, no hidden file) and
#: none is empty.
VIEWER_FILES = re.compile(r"/viewer(/|(/[A-Za-z0-9_~-][A-Za-z0-9_.~-]*)*"
                          r"/[A-Za-z0-9_~-][A-Za-z0-9_.~-]*\.(html|js|mjs|css|png|svg|ico|map))?")
#: Where a request's ``Verdict`` travels in its ASGI scope (absent: access control off).
SCOPE_KEY = "pvs.access"
#: Counters of refusals (``ServerState.counters``, ``/health``), present when access control is.
COUNTERS = ("access_unauthorized", "access_forbidden", "access_over_quota",
            "access_origin_refused")
REALM = 'Bearer realm="pvs"'

#: Loggers of the WebSocket library under uvicorn: at DEBUG they print every handshake header.
HEADER_LOGGERS = ("uvicorn.error", "websockets.server")
#: Request headers that carry a token.
_CREDENTIAL_HEADERS = frozenset({"authorization", "sec-websocket-protocol"})

_NEED_TOKEN = ("a bearer token is required: Authorization: Bearer <token> (a browser's "
               f"WebSocket offers the subprotocols {SUBPROTOCOL!r} and "
               f"'{TOKEN_SUBPROTOCOL_PREFIX}<token>')")
_BAD_TOKEN = "the bearer token is not valid"


@dataclass(frozen=True)
class Verdict:
    """What the token of one request or handshake is worth: its ``grant``, or None and
    ``why`` not (``presented``: a credential was sent, but not a valid one)."""

    grant: Grant | None
    presented: bool = False
    why: str = ""


def is_open(scope: Scope) -> bool:
    """Whether an HTTP request is answered without a token: ``OPEN_PATHS``, or a GET or HEAD
    of the viewer's files (``VIEWER_FILES``; the path as the router reads it, decoded)."""
    path = scope["path"]
    if path in OPEN_PATHS:
        return True
    return (scope.get("method") in ("GET", "HEAD")
            and VIEWER_FILES.fullmatch(path) is not None)


def presented_token(scope: Scope) -> tuple[bool, str | None]:
    """(whether a credential was sent, the token when it has a token's form). One
    ``Authorization: Bearer`` header, else (WebSocket) one ``pvs.bearer.`` subprotocol;
    several of either, another scheme or a malformed token: sent, but no token."""
    values = [v for k, v in scope.get("headers", ()) if k == b"authorization"]
    if not values and scope["type"] == "websocket":
        offered = [p for p in scope.get("subprotocols") or ()
                   if isinstance(p, str) and p.startswith(TOKEN_SUBPROTOCOL_PREFIX)]
        if not offered:
            return False, None
        token = offered[0][len(TOKEN_SUBPROTOCOL_PREFIX):]
        return True, token if len(offered) == 1 and is_token(token) else None
    if not values:
        return False, None
    if len(values) > 1:
        return True, None
    scheme, _, token = values[0].decode("latin-1").strip().partition(" ")
    token = token.strip()
    return True, token if scheme.lower() == "bearer" and is_token(token) else None


def requested_scenes(scope: Scope) -> list[str]:
    """The scenes an HTTP request names: ``/scenes/{scene}...`` (as the router reads it) and
    every ``scene`` query parameter."""
    parts = scope["path"].split("/")
    named = [parts[2]] if len(parts) > 2 and parts[1] == "scenes" and parts[2] else []
    query = scope.get("query_string", b"")
    if query:  # parsed as the router parses it: "sc%65ne" is a scene too
        named += QueryParams(query).getlist("scene")
    return named


class Access:
    """The application's access control: its tokens (None: no token needed), their quotas,
    the WebSocket origins allowed (empty: any) and the refusal counters."""

    def __init__(self, book: TokenBook | None, origins: frozenset[str],
                 counters: Counter) -> None:
        self.book = book
        self.origins = origins
        self.quotas = TokenQuotas()
        self.counters = counters

    @classmethod
    def from_settings(cls, settings: Settings, counters: Counter) -> Access | None:
        """The access control of ``settings``; None when neither tokens nor origins are set
        (then nothing differs from a server without this module). ValueError for a bad
        tokens file, token or origin (never quoting a token)."""
        pairs = env_grants(settings.tokens)
        if settings.tokens_file is not None:
            pairs += read_tokens_file(settings.tokens_file)
        origins = frozenset(normalize_origins(settings.cors_origins))
        if not pairs and not origins:
            return None
        for key in COUNTERS:
            counters[key] += 0
        if pairs:
            redact_header_logs()
        return cls(TokenBook(pairs) if pairs else None, origins, counters)

    def verdict(self, scope: Scope) -> Verdict:
        """The ``Verdict`` of a request's or handshake's credentials."""
        presented, token = presented_token(scope)
        grant = self.book.lookup(token) if self.book is not None else None
        if grant is not None:
            return Verdict(grant, True)
        return Verdict(None, presented, _BAD_TOKEN if presented else _NEED_TOKEN)

    def count(self, what: str) -> None:
        """Count one refusal (``COUNTERS`` without the prefix)."""
        self.counters[f"access_{what}"] += 1


class RedactCredentials(logging.Filter):
    """Blank the value of credential headers in the WebSocket library's DEBUG lines of a
    handshake (``"< %s: %s"``, name and value), so ``--log-level debug`` logs no token."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if (isinstance(args, tuple) and len(args) == 2 and isinstance(args[0], str)
                and args[0].lower() in _CREDENTIAL_HEADERS):
            record.args = (args[0], "[redacted]")
        return True


def redact_header_logs() -> None:
    """Install ``RedactCredentials`` on ``HEADER_LOGGERS`` (once)."""
    for name in HEADER_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactCredentials) for f in logger.filters):
            logger.addFilter(RedactCredentials())


class AccessGuard:
    """ASGI middleware: the HTTP checks and the WebSocket ``Origin`` check of ``Access``; a
    handshake's ``Verdict`` goes into its scope (``SCOPE_KEY``) for the session to act on.

    Installed inside ``CORSMiddleware`` (so preflights and refusals carry CORS headers) and
    the per-address ``RateLimit`` (so floods of bad tokens are throttled like any other).
    """

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        access = self.access
        if scope["type"] == "websocket":
            if not origin_allowed(scope, access.origins):
                access.count("origin_refused")
                await _deny_handshake(scope, receive, send)
                return
            if access.book is not None:
                scope[SCOPE_KEY] = access.verdict(scope)
        elif scope["type"] == "http" and access.book is not None and not is_open(scope):
            refused = await self._refused(scope, send)
            if refused:
                return
        await self.app(scope, receive, send)

    async def _refused(self, scope: Scope, send: Send) -> bool:
        """Answer an HTTP request its token does not allow (True), else put its verdict in its
        scope (False)."""
        access = self.access
        verdict = access.verdict(scope)
        grant = verdict.grant
        if grant is None:
            access.count("unauthorized")
            challenge = REALM + (', error="invalid_token"' if verdict.presented else "")
            await _answer(send, 401, ErrorCode.UNAUTHORIZED, verdict.why,
                          [(b"www-authenticate", challenge.encode())])
            return True
        denied = [s for s in requested_scenes(scope) if not grant.allows(s)]
        if denied:
            access.count("forbidden")
            await _answer(send, 403, ErrorCode.FORBIDDEN,
                          f"token {grant.name!r} may not use scene {denied[0]!r}",
                          [(b"www-authenticate", f'{REALM}, error="insufficient_scope"'.encode())])
            return True
        if scope["path"].endswith("/pvs"):
            wait = access.quotas.take_pvs(grant)
            if wait is not None:
                access.count("over_quota")
                await _answer(send, 429, ErrorCode.OVER_QUOTA,
                              f"token {grant.name!r} has sent its {grant.pvs_per_minute} PVS "
                              "requests of the last minute (pvs_per_minute)",
                              [(b"retry-after", retry_after_header(wait).encode())],
                              limit="pvs_per_minute", value=grant.pvs_per_minute)
                return True
        scope[SCOPE_KEY] = verdict
        return False


async def _answer(send: Send, status: int, code: ErrorCode, message: str,
                  headers: list[tuple[bytes, bytes]], **extra: Any) -> None:
    """An HTTP error answer with the project's JSON error body."""
    body = json.dumps(error_body(code, message, **extra)).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()), *headers]})
    await send({"type": "http.response.body", "body": body})


async def _deny_handshake(scope: Scope, receive: Receive, send: Send) -> None:
    """Refuse a WebSocket handshake with 403 and the JSON error body (a plain close, which
    the server answers 403, where it cannot send a body)."""
    if (await receive())["type"] != "websocket.connect":
        return
    if "websocket.http.response" not in scope.get("extensions", {}):
        await send({"type": "websocket.close", "code": 1008})
        return
    body = json.dumps(error_body(ErrorCode.FORBIDDEN, "this Origin may not open a WebSocket "
                                 "here (cors_origins)")).encode()
    await send({"type": "websocket.http.response.start", "status": 403,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "websocket.http.response.body", "body": body})


# --------------------------------------------------------------------------- routes, sessions
def visible_scenes(scope: Scope, listing: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The entries of a scene listing the request's token may use (all without access
    control, or for a token with every scene)."""
    verdict = scope.get(SCOPE_KEY)
    grant = verdict.grant if verdict is not None else None
    if grant is None or grant.scenes is None:
        return listing
    return [entry for entry in listing if entry.get("name") in grant.scenes]


def subprotocol(scope: Scope) -> str | None:
    """The subprotocol to accept a WebSocket with: ``protocol.auth.SUBPROTOCOL`` when offered
    (a browser that offered its token that way needs one selected), else none."""
    return SUBPROTOCOL if SUBPROTOCOL in (scope.get("subprotocols") or ()) else None


async def admit_session(session: Session) -> None:
    """Before ``hello``: refuse a session without a valid token (``unauthorized``, 4401) or
    past its token's ``max_sessions`` (``over_quota``, 4429), else hold one of its places
    until ``release_session``. Nothing without access control."""
    verdict = session.transport.ws.scope.get(SCOPE_KEY)
    if verdict is None:
        return
    access: Access = session.state.access
    grant = verdict.grant
    if grant is None:
        access.count("unauthorized")
        await session.error(ErrorCode.UNAUTHORIZED, verdict.why)
    if not access.quotas.open_session(grant):
        access.count("over_quota")
        await session.error(ErrorCode.OVER_QUOTA,
                            f"token {grant.name!r} already has {grant.max_sessions} sessions "
                            "open (max_sessions)")
    session.grant = grant


async def check_scene(session: Session, scene: str) -> None:
    """Right after ``hello``: refuse a scene outside the session's token's allow list
    (``forbidden``, 4403), whether it exists or not."""
    grant = session.grant
    if grant is not None and not grant.allows(scene):
        session.state.access.count("forbidden")
        await session.error(ErrorCode.FORBIDDEN,
                            f"token {grant.name!r} may not use scene {scene!r}")


def release_session(session: Session) -> None:
    """Give back the session's place in its token's ``max_sessions`` (once)."""
    grant, session.grant = session.grant, None
    if grant is not None:
        session.state.access.quotas.close_session(grant)


# --------------------------------------------------------------------------- OpenAPI
def document(app: FastAPI) -> None:
    """Make the OpenAPI schema say which operations need a token (a ``bearer`` security
    scheme, their 401, the 403 of those that name a scene, the token's quota in the PVS
    routes' 429). Call after ``server.openapi.install_openapi``, only with tokens on."""
    generate = app.openapi
    error_ref = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}}

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = generate()
        schema.setdefault("components", {}).setdefault("securitySchemes", {})["bearer"] = {
            "type": "http", "scheme": "bearer",
            "description": "a token of the server's tokens file or PVS_TOKENS"}
        for path, operations in schema.get("paths", {}).items():
            if path in OPEN_PATHS:
                continue
            for op in operations.values():
                op["security"] = [{"bearer": []}]
                responses = op.setdefault("responses", {})
                responses["401"] = {
                    "description": "no valid bearer token (unauthorized)", "content": error_ref,
                    "headers": {"WWW-Authenticate": {"schema": {"type": "string"}}}}
                names_scene = "{scene}" in path or any(
                    p.get("name") == "scene" for p in op.get("parameters", []))
                if names_scene:
                    responses["403"] = {"description": "the token may not use this scene "
                                        "(forbidden)", "content": error_ref}
                if path.endswith("/pvs") and "429" in responses:
                    responses["429"]["description"] += (
                        "; or the token sent its pvs_per_minute requests in the last minute "
                        "(over_quota; Retry-After)")
        return schema

    app.openapi = openapi
