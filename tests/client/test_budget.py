"""The client's last-resort budget enforcement (client.budget) on a real GeometryStore."""

from __future__ import annotations

import numpy as np

from client.budget import choose_evictions, enforce_budget
from client.store import GeometryStore


def _store(n: int, budget: int | None) -> GeometryStore:
    """``n`` small triangles, triangle i centred at x = i metres."""
    s = GeometryStore(budget)
    base = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]])
    tris = base[None] + np.stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)],
                                 axis=1)[:, None, :]
    s.add(np.arange(n), tris, np.full((n, 3), 128, np.uint8))
    return s


def test_unprotected_farthest_go_first():
    ids = np.arange(10)
    cent = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], axis=1)
    # Eye at x = 0; ids 8, 9 are the farthest but protected (the current cell's).
    out = choose_evictions(ids, cent, np.array([8, 9]), np.zeros(3), budget=7)
    assert sorted(out.tolist()) == [5, 6, 7]
    # Not enough unprotected ones: the farthest protected go last.
    out = choose_evictions(ids, cent, np.arange(3, 10), np.zeros(3), budget=2)
    assert sorted(out.tolist()) == [0, 1, 2, 5, 6, 7, 8, 9]
    assert len(choose_evictions(ids, cent, ids, np.zeros(3), budget=10)) == 0


def test_enforce_budget_on_a_store():
    s = _store(20, budget=12)
    assert s.over_budget
    evicted = enforce_budget(s, np.arange(15, 20), eye=np.array([19.0, 0, 0]))
    assert evicted == 8 and len(s) == 12 and not s.over_budget
    held = set(s.ids.tolist())
    assert set(range(15, 20)) <= held  # protected survive
    assert held == set(range(8, 20))  # the farthest from the eye (x = 0..7) went
    assert enforce_budget(s, np.zeros(0), np.zeros(3)) == 0  # within budget: nothing
    free = _store(20, budget=None)
    assert enforce_budget(free, np.zeros(0), np.zeros(3)) == 0 and len(free) == 20
