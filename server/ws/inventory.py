"""What a session's client holds and may hold: the triangles sent and not dropped since, the
client's triangle budget, the PVS of recently streamed cells and which cells are complete.

Memory is bounded: a bit per scene triangle (held) and the PVS of at most ``MAX_KNOWN_PVS``
cells.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from server.prefetch import choose_drops

#: Cells whose PVS a session remembers (current, prefetch, complete ones); beyond it, the oldest
#: complete cells are forgotten (and count as incomplete: a revisit re-sends what is missing).
MAX_KNOWN_PVS = 32


class Inventory:
    """The client's triangles and budget, as the server accounts for them.

    Parameters
    ----------
    n_triangles : the scene's triangle count (``held`` has a bit per triangle).
    budget : the most triangles the client holds at once (None: no limit).

    Attributes
    ----------
    held : (n,) bool, triangle i was sent and not dropped since.
    n_held : int, the count of ``held``.
    pvs_of : {cell: sorted int32 ids}, the PVS of the cells streamed lately.
    done : set of cells whose stream the client has complete.
    """

    def __init__(self, n_triangles: int, budget: int | None) -> None:
        self.budget = budget
        self.held = np.zeros(n_triangles, dtype=bool)
        self.n_held = 0
        self.pvs_of: dict[int, np.ndarray] = {}
        self.done: set[int] = set()

    def remember(self, cell: int, ids: np.ndarray, keep: Iterable[int | None]) -> None:
        """Record ``cell``'s PVS; past ``MAX_KNOWN_PVS`` cells forget the oldest but ``keep``
        (and ``cell``); a forgotten cell is no longer complete."""
        self.pvs_of[cell] = ids
        if len(self.pvs_of) <= MAX_KNOWN_PVS:
            return
        keep = {cell, *keep}
        for c in list(self.pvs_of):
            if len(self.pvs_of) <= MAX_KNOWN_PVS:
                break
            if c not in keep:
                del self.pvs_of[c]
                self.done.discard(c)

    def missing(self, ids: np.ndarray) -> np.ndarray:
        """The ids among ``ids`` the client does not hold."""
        return ids[~self.held[ids]]

    def over_budget(self, new: np.ndarray) -> int:
        """How many held triangles must go before ``new`` fits the budget (0: it fits)."""
        if self.budget is None:
            return 0
        return max(0, self.n_held + len(new) - self.budget)

    def choose_drops(self, need: int, ids: np.ndarray, current: int | None,
                     ahead: Iterable[int], prefetch: bool, centroids: np.ndarray,
                     centre: np.ndarray) -> np.ndarray:
        """Up to ``need`` held triangles to drop so a stream of ``ids`` fits.

        Never ``ids`` nor the ``current`` cell's PVS; the cells ``ahead`` (prefetch order) are
        spared while others remain, and protected outright when the stream is a ``prefetch``
        (it may only push out what no nearby cell needs). Farthest from ``centre`` first
        (``server.prefetch.choose_drops``). Fewer than ``need`` when no more may go.
        """
        n = len(self.held)
        protect = np.zeros(n, dtype=bool)
        protect[ids] = True
        cur = self.pvs_of.get(current)
        if cur is not None:
            protect[cur] = True
        spare = np.zeros(n, dtype=bool)
        for c in ahead:
            p = self.pvs_of.get(c)
            if p is not None:
                spare[p] = True
        if prefetch:
            protect |= spare
            spare[:] = False
        return choose_drops(self.held, need, protect, spare, centroids, centre)

    def drop(self, drops: np.ndarray) -> list[int]:
        """Forget ``drops`` (the client drops them); returns the complete cells that no longer
        are, sorted."""
        dmask = np.zeros(len(self.held), dtype=bool)
        dmask[drops] = True
        self.held[drops] = False
        self.n_held -= len(drops)
        gone = sorted(c for c in self.done if dmask[self.pvs_of[c]].any())
        self.done.difference_update(gone)
        return gone

    def add(self, ids: np.ndarray) -> None:
        """``ids`` (none held) are queued for the client: count them as held."""
        self.held[ids] = True
        self.n_held += len(ids)

    def release(self, ids: np.ndarray) -> None:
        """``ids`` were cut from the queue unsent: those held are no longer."""
        ids = ids[self.held[ids]]
        self.held[ids] = False
        self.n_held -= len(ids)
