"""The edge pool of ``resolve`` (``groups.EdgePool``): each group's block holds exactly its
active edges through kills, joins, growth and compaction, checked against a model of sets."""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.cores.cos.groups import EdgePool
from visibility.cores.cos.resolve import _edge_kill, _edges_join, _edges_new


@njit(cache=True)
def _run(ops, ov, ow, grp, edges):  # pragma: no cover - numba
    """Apply ``ops`` (k, 3): (0, q, -) a new triangle q; (1, node, g) kill node of group g;
    (2, g1, g2) join g2's edges into g1 (the caller relabels grp)."""
    for k in range(ops.shape[0]):
        op, a, b = ops[k, 0], ops[k, 1], ops[k, 2]
        if op == 0:
            _edges_new(a, ov, ow, grp, edges)
        elif op == 1:
            _edge_kill(a, b, edges)
        else:
            _edges_join(a, b, grp, edges)


def _pool(n: int, room: int) -> EdgePool:
    return EdgePool(geo=np.full((room, 6), np.nan), node=np.full(room, -1, dtype=np.int64),
                    pos=np.full(3 * n, -1, dtype=np.int64), start=np.zeros(n, dtype=np.int64),
                    length=np.zeros(n, dtype=np.int64), cap=np.zeros(n, dtype=np.int64),
                    top=np.zeros(1, dtype=np.int64))


def _blocks(edges: EdgePool, groups: set[int]) -> dict[int, set[int]]:
    out = {}
    for g in groups:
        s, n = int(edges.start[g]), int(edges.length[g])
        assert n <= edges.cap[g]
        out[g] = {int(x) for x in edges.node[s:s + n]}
        assert len(out[g]) == n  # no record twice
    return out


def test_blocks_hold_exactly_the_active_edges_through_joins_and_compactions():
    n = 400
    # A pool with little room beyond the live edges (three times the most live at once, the
    # least a compaction needs: the live edges plus a block twice the largest group's): growth
    # compacts it many times.
    room = 4 * n + 64
    edges = _pool(n, room)
    rng = np.random.default_rng(7)
    ov = rng.random((n, 3, 2))
    ow = rng.random((n, 3))
    grp = np.arange(n, dtype=np.int64)
    model: dict[int, set[int]] = {}
    compactions = 0
    for q in range(n):
        top = int(edges.top[0])
        ops = [(0, q, 0)]
        model[q] = {3 * q, 3 * q + 1, 3 * q + 2}
        # Fuse with up to two random live groups along a random edge each, as insertion does:
        # both edges die, then the smaller group joins the larger.
        for _ in range(int(rng.integers(0, 3))):
            others = [g for g in model if g != grp[q] and model[g]]
            if not others or not model[int(grp[q])]:
                break
            g1 = int(rng.choice(others))
            g2 = int(grp[q])
            n1 = int(rng.choice(sorted(model[g1])))
            n2 = int(rng.choice(sorted(model[g2])))
            ops += [(1, n1, g1), (1, n2, g2)]
            model[g1].discard(n1)
            model[g2].discard(n2)
            if len(model[g1]) < len(model[g2]):
                g1, g2 = g2, g1
            ops.append((2, g1, g2))
            _run(np.array(ops, dtype=np.int64), ov, ow, grp, edges)
            ops = []
            grp[grp == g2] = g1
            model[g1] |= model.pop(g2)
        if ops:
            _run(np.array(ops, dtype=np.int64), ov, ow, grp, edges)
        compactions += int(edges.top[0]) < top + 3
        assert 3 * sum(len(v) for v in model.values()) <= room
        assert _blocks(edges, set(model)) == model
        for nodes in model.values():
            for nd in nodes:
                i = edges.pos[nd]
                assert edges.node[i] == nd
                # The record carries its edge: corner e to corner e + 1 of triangle q.
                q, e = divmod(nd, 3)
                b = (e + 1) % 3
                assert list(edges.geo[i]) == [*ov[q, e], *ov[q, b], ow[q, e], ow[q, b]]
    assert edges.top[0] <= edges.node.shape[0]
    assert compactions > 0
