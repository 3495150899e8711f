"""Which walkers want which PVS, and how soon: the ranks the compute pool orders work by.

Every session states its needs whole on each update: {cache key: (priority, since)}, priority
the walker's expected seconds to arrival in the cell (0 for the cell it stands in:
``server.prefetch.arrival_seconds``), ``since`` a tie-break among equal priorities (the
``time.perf_counter()`` instant the walker entered its current cell; 0 for prefetch). A key's
rank is the smallest (priority, since) over every walker that wants it; ``update`` and
``remove`` say which keys' ranks changed, so the compute service re-ranks (or cancels) only
those jobs (``server.compute.ComputeService.want``). See ``docs/scheduling.md``.
"""

from __future__ import annotations

import threading
from collections.abc import Hashable, Mapping

#: (priority, since): lower runs first.
Rank = tuple[float, float]


class Demand:
    """The needs of every walker, by walker and by key; thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_walker: dict[Hashable, dict[Hashable, Rank]] = {}
        self._by_key: dict[Hashable, dict[Hashable, Rank]] = {}

    def _rank(self, key: Hashable) -> Rank | None:
        ranks = self._by_key.get(key)
        return min(ranks.values()) if ranks else None

    def update(self, walker: Hashable, needs: Mapping[Hashable, Rank]) -> dict[Hashable,
                                                                              Rank | None]:
        """Replace ``walker``'s needs with ``needs``; the keys whose rank changed, with their
        new rank (None: no walker wants the key any more)."""
        new = {k: (float(p), float(s)) for k, (p, s) in needs.items()}
        with self._lock:
            old = self._by_walker.get(walker, {})
            touched = [k for k in old if new.get(k) != old[k]]
            touched += [k for k in new if k not in old]
            before = {k: self._rank(k) for k in touched}
            for k in touched:
                if k in old:
                    ranks = self._by_key[k]
                    del ranks[walker]
                    if not ranks:
                        del self._by_key[k]
                if k in new:
                    self._by_key.setdefault(k, {})[walker] = new[k]
            if new:
                self._by_walker[walker] = new
            else:
                self._by_walker.pop(walker, None)
            after = {k: self._rank(k) for k in touched}
        return {k: after[k] for k in touched if after[k] != before[k]}

    def remove(self, walker: Hashable) -> dict[Hashable, Rank | None]:
        """Forget ``walker`` (it left); the keys whose rank changed (``update``)."""
        return self.update(walker, {})

    def rank(self, key: Hashable) -> Rank | None:
        """The smallest (priority, since) over the walkers that want ``key``; None: none does."""
        with self._lock:
            return self._rank(key)

    def wanted(self, key: Hashable) -> bool:
        """Whether any walker wants ``key``."""
        with self._lock:
            return key in self._by_key

    def stats(self) -> dict[str, int]:
        """Walkers with needs and keys wanted."""
        with self._lock:
            return {"walkers": len(self._by_walker), "keys": len(self._by_key)}
