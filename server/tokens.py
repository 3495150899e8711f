"""Bearer tokens and what each may do: from a tokens file (JSON or TOML) and ``PVS_TOKENS``.

A tokens file maps each token to what it may do; every field is optional::

    {"tokens": {"<token>": {"name": "alice", "scenes": ["rooms", "village"],
                            "max_sessions": 2, "pvs_per_minute": 60}}}

or in TOML (``.toml``)::

    [tokens.<token>]
    name = "alice"
    scenes = ["rooms", "village"]   # omitted: every scene
    max_sessions = 2                # open WebSocket sessions at once; omitted: no quota
    pvs_per_minute = 60             # HTTP PVS requests in any 60 s; omitted: no quota

Tokens of ``PVS_TOKENS`` (comma-separated) may use every scene, without quotas. A token is
``protocol.auth.TOKEN_CHARS``. Tokens are kept as SHA-256 digests and compared with
``hmac.compare_digest`` against every known one (no early exit), so neither the comparison nor
the number tried reveals a token; no message or log line names one (entries are named by
``name`` or their place in the file).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError

from protocol.auth import TOKEN_CHARS, is_token

#: Largest quotas a file may set (the per-minute window keeps one timestamp per request).
MAX_SESSIONS_QUOTA = 1 << 16
MAX_PVS_PER_MINUTE = 100_000
#: Largest tokens file read, bytes.
MAX_FILE_BYTES = 1 << 20

_FORM = f"a token must match {TOKEN_CHARS.pattern} (e.g. secrets.token_urlsafe(32))"


@dataclass(frozen=True, eq=False)
class Grant:
    """What one token may do. Compared by identity: one object per token (quota keys).

    Attributes
    ----------
    name : how logs and messages name the token (never the token itself).
    scenes : the scenes it may use; None: every scene.
    max_sessions : WebSocket sessions it may have open at once; None: no quota.
    pvs_per_minute : HTTP PVS requests it may send in any 60 s; None: no quota.
    """

    name: str
    scenes: frozenset[str] | None = None
    max_sessions: int | None = None
    pvs_per_minute: int | None = None

    def allows(self, scene: str) -> bool:
        """Whether the token may use ``scene``."""
        return self.scenes is None or scene in self.scenes


class _Entry(BaseModel):
    """One token's entry in a tokens file."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, min_length=1, max_length=200)
    scenes: list[str] | None = None
    max_sessions: int | None = Field(None, ge=0, le=MAX_SESSIONS_QUOTA)
    pvs_per_minute: int | None = Field(None, ge=0, le=MAX_PVS_PER_MINUTE)


def _why(exc: ValidationError) -> str:
    # Never pydantic's own text: it quotes the input, and a wrong field could hold a token.
    return "; ".join(f"{'.'.join(map(str, e['loc'])) or 'entry'}: {e['msg']}"
                     for e in exc.errors(include_input=False, include_url=False))


def read_tokens_file(path: Path | str) -> list[tuple[str, Grant]]:
    """The (token, grant) pairs of a tokens file (TOML when it ends in ``.toml``, else JSON).

    Raises ValueError, naming the file and the entry but never a token, when the file cannot be
    read, does not parse, holds no token, or an entry is malformed.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ValueError(f"tokens file {path}: {exc.strerror or exc}") from None
    if len(raw) > MAX_FILE_BYTES:
        raise ValueError(f"tokens file {path}: over {MAX_FILE_BYTES} bytes")
    try:
        text = raw.decode("utf-8")
        data: Any = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except UnicodeDecodeError:
        raise ValueError(f"tokens file {path}: not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"tokens file {path}: not JSON ({exc.msg} at line {exc.lineno}); "
                         "name a TOML file *.toml") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"tokens file {path}: not TOML ({exc})") from None
    if not isinstance(data, dict) or set(data) != {"tokens"} or not isinstance(
            data["tokens"], dict):
        raise ValueError(f"tokens file {path}: expected one table, tokens, mapping each token "
                         "to its entry")
    if not data["tokens"]:
        raise ValueError(f"tokens file {path}: no tokens (a server with a tokens file and no "
                         "token would refuse everyone; leave the file out to turn access "
                         "control off)")
    out = []
    for i, (token, entry) in enumerate(data["tokens"].items(), start=1):
        where = f"tokens file {path}, entry {i}"
        if not is_token(token):
            raise ValueError(f"{where}: {_FORM}")
        try:
            e = _Entry.model_validate({} if entry is None else entry)
        except ValidationError as exc:
            raise ValueError(f"{where}: {_why(exc)}") from None
        out.append((token, Grant(
            name=e.name or f"{path.name} #{i}",
            scenes=None if e.scenes is None else frozenset(e.scenes),
            max_sessions=e.max_sessions, pvs_per_minute=e.pvs_per_minute)))
    return out


def env_grants(tokens: Iterable[SecretStr | str]) -> list[tuple[str, Grant]]:
    """(token, grant) pairs of ``PVS_TOKENS``' tokens: every scene, no quota; ValueError for a
    malformed one (named by its place)."""
    out = []
    for i, t in enumerate(tokens, start=1):
        token = t.get_secret_value() if isinstance(t, SecretStr) else str(t)
        if not is_token(token):
            raise ValueError(f"PVS_TOKENS #{i}: {_FORM}")
        out.append((token, Grant(name=f"PVS_TOKENS #{i}")))
    return out


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).digest()


class TokenBook:
    """The known tokens, by digest; ``lookup`` finds a presented token's grant."""

    def __init__(self, pairs: Iterable[tuple[str, Grant]]) -> None:
        self._entries: list[tuple[bytes, Grant]] = []
        seen: dict[bytes, Grant] = {}
        for token, grant in pairs:
            d = _digest(token)
            if d in seen:
                raise ValueError(f"{grant.name} repeats the token of {seen[d].name}")
            seen[d] = grant
            self._entries.append((d, grant))

    def __len__(self) -> int:
        return len(self._entries)

    def lookup(self, token: str | None) -> Grant | None:
        """The grant of ``token``, else None: compared with every known token in constant time
        per token (digests of equal length, ``hmac.compare_digest``, no early exit)."""
        if token is None:
            return None
        d = _digest(token)
        found = None
        for known, grant in self._entries:
            if hmac.compare_digest(known, d):
                found = grant
        return found
