"""Per-token quotas, on top of the server's own limits (``server.admission``, the per-address
``RateLimit``): open WebSocket sessions at once (``Grant.max_sessions``) and HTTP PVS requests
in any ``WINDOW_S`` seconds (``Grant.pvs_per_minute``).

State lives in the application and is touched only from its event loop, each check and its
count in one step with no ``await`` between, so concurrent requests cannot both take the last
place. The window keeps one timestamp per admitted request (at most ``pvs_per_minute`` per
token), so ``retry_after`` is exact: when the oldest request leaves the window.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque

from server.tokens import Grant

#: Seconds of the PVS request window (``pvs_per_minute``).
WINDOW_S = 60.0


class TokenQuotas:
    """Sessions open and recent PVS requests per token."""

    def __init__(self) -> None:
        self._sessions: Counter[Grant] = Counter()
        self._recent: dict[Grant, deque[float]] = {}

    def open_session(self, grant: Grant) -> bool:
        """Count one more open session of ``grant``; False (nothing counted) at its
        ``max_sessions``."""
        cap = grant.max_sessions
        if cap is not None and self._sessions[grant] >= cap:
            return False
        self._sessions[grant] += 1
        return True

    def close_session(self, grant: Grant) -> None:
        """One session of ``grant`` has ended."""
        self._sessions[grant] -= 1
        if self._sessions[grant] <= 0:
            del self._sessions[grant]

    def sessions(self, grant: Grant) -> int:
        """Open sessions of ``grant``."""
        return self._sessions[grant]

    def take_pvs(self, grant: Grant, now: float | None = None) -> float | None:
        """Count one PVS request of ``grant`` at monotonic time ``now``; None when admitted,
        else the seconds until the window has room (nothing counted)."""
        cap = grant.pvs_per_minute
        if cap is None:
            return None
        now = time.monotonic() if now is None else now
        recent = self._recent.setdefault(grant, deque())
        while recent and recent[0] <= now - WINDOW_S:
            recent.popleft()
        if len(recent) >= cap:
            return WINDOW_S if not recent else recent[0] + WINDOW_S - now
        recent.append(now)
        return None


def retry_after_header(seconds: float) -> str:
    """``Retry-After`` for a wait of ``seconds``: whole seconds, at least 1."""
    return str(max(1, math.ceil(seconds)))
