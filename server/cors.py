"""Browser origins: CORS on HTTP (Starlette's ``CORSMiddleware``) and the ``Origin`` check of
WebSocket handshakes, both from ``settings.cors_origins``.

Without origins nothing changes: no CORS headers (a preflight answers 405, as before) and a
WebSocket from any ``Origin`` is accepted (tokens, not cookies, authorise a session, so a page
elsewhere gains nothing a script could not do directly). With origins, those pages (``*``: any)
may call the HTTP API from a browser, and a WebSocket handshake whose ``Origin`` is another is
refused with 403 before it is upgraded; a handshake without ``Origin`` (not a browser) passes.
"""

from __future__ import annotations

from collections.abc import Iterable
from urllib.parse import urlsplit

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware
from starlette.types import Scope

#: Any origin.
ANY = "*"
#: Headers a page may send (the token, a JSON body, answer negotiation) and read.
ALLOW_HEADERS = ("Authorization", "Content-Type", "Accept")
EXPOSE_HEADERS = ("Retry-After", "WWW-Authenticate", "X-PVS-Count", "X-PVS-Core",
                  "X-PVS-Core-Reason", "X-PVS-Seconds", "X-PVS-Cached")
#: Seconds a browser may cache a preflight answer.
PREFLIGHT_MAX_AGE = 600
_DEFAULT_PORTS = {"http": 80, "https": 443}


def normalize_origin(text: str) -> str:
    """``text`` as browsers send it in ``Origin`` (``scheme://host[:port]``, lower case, no
    default port, no slash); ``*`` stays. ValueError for anything else (a path, a query,
    another scheme)."""
    t = text.strip()
    if t == ANY:
        return t
    try:
        parts = urlsplit(t)
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"CORS origin {text!r}: {exc}") from None
    if (parts.scheme.lower() not in _DEFAULT_PORTS or not parts.hostname
            or parts.path not in ("", "/") or parts.query or parts.fragment
            or parts.username is not None or t.endswith("?") or t.endswith("#")):
        raise ValueError(f"CORS origin {text!r}: expected scheme://host[:port] with scheme "
                         "http or https, or *")
    scheme = parts.scheme.lower()
    host = parts.hostname if ":" not in parts.hostname else f"[{parts.hostname}]"
    if port is not None and port != _DEFAULT_PORTS[scheme]:
        host = f"{host}:{port}"
    return f"{scheme}://{host}"


def normalize_origins(origins: Iterable[str]) -> list[str]:
    """Every origin normalized (``normalize_origin``), duplicates dropped, order kept."""
    return list(dict.fromkeys(normalize_origin(o) for o in origins))


def add_cors(app: FastAPI, origins: Iterable[str]) -> None:
    """Answer CORS for ``origins`` (nothing when there are none)."""
    allowed = normalize_origins(origins)
    if allowed:
        app.add_middleware(CORSMiddleware, allow_origins=allowed, allow_methods=["GET", "POST"],
                           allow_headers=list(ALLOW_HEADERS),
                           expose_headers=list(EXPOSE_HEADERS), max_age=PREFLIGHT_MAX_AGE)


def origin_allowed(scope: Scope, origins: frozenset[str]) -> bool:
    """Whether a WebSocket handshake may proceed: no origins configured, ``*``, no ``Origin``
    header, or an ``Origin`` among ``origins`` (compared as sent, as ``CORSMiddleware`` does;
    several ``Origin`` headers: refused)."""
    if not origins or ANY in origins:
        return True
    sent = [v for k, v in scope.get("headers", ()) if k == b"origin"]
    if not sent:
        return True
    return len(sent) == 1 and sent[0].decode("latin-1") in origins
