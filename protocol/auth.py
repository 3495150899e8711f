"""How a client presents a bearer token to a server with access control on.

HTTP: ``Authorization: Bearer <token>``. WebSocket: the same header where the client can set
one (the headless client does); a browser cannot set headers on a WebSocket, so it offers the
token as a subprotocol instead, beside ``SUBPROTOCOL`` which the server then selects::

    new WebSocket(url, ["pvs", "pvs.bearer." + token])

Subprotocols travel in the ``Sec-WebSocket-Protocol`` header, which servers and proxies do not
log as they log URLs (a ``?token=`` would land in every access log). A token is
``TOKEN_CHARS`` (16 to 512 characters of ``A-Z a-z 0-9 - . _ ~ +``: valid in a header, a
subprotocol name and a URL; ``secrets.token_urlsafe(32)`` makes one).
"""

from __future__ import annotations

import re

#: The subprotocol the server selects when a client offers it (a browser requires the server to
#: select one of those it offered).
SUBPROTOCOL = "pvs"
#: Prefix of the subprotocol that carries the token.
TOKEN_SUBPROTOCOL_PREFIX = "pvs.bearer."
#: What a token is made of.
TOKEN_CHARS = re.compile(r"[A-Za-z0-9._~+-]{16,512}")


def is_token(text: str) -> bool:
    """Whether ``text`` has the form of a token (``TOKEN_CHARS``)."""
    return TOKEN_CHARS.fullmatch(text) is not None


def authorization_header(token: str) -> dict[str, str]:
    """The HTTP header that presents ``token``."""
    return {"Authorization": f"Bearer {token}"}


def token_subprotocols(token: str) -> list[str]:
    """The WebSocket subprotocols a client offers to present ``token`` (browsers)."""
    return [SUBPROTOCOL, TOKEN_SUBPROTOCOL_PREFIX + token]
