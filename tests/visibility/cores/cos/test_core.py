"""The order ``cos_pvs`` solves its 30 views in (``core.view_order``)."""

from __future__ import annotations

import numpy as np

import visibility.cores.cos.core as cos_core
from visibility.cores.cos.core import cos_pvs, view_order
from visibility.generators import make_scene
from visibility.ground_truth import cell_around


def test_views_with_fewer_listed_positions_come_first_ties_in_place():
    assert view_order([5, 1, 5, 0, 1]) == [3, 1, 4, 0, 2]
    assert view_order([]) == []


def test_the_cell_solves_its_views_cheapest_first_and_each_once(monkeypatch):
    scene = make_scene("rooms", triangles=3000)
    box = cell_around(scene, 1.0, 0)
    seen: list[tuple[tuple[int, int], str, int]] = []
    solve = cos_core._solve_view

    def logged(prims, solid, order, listed, gap, view, *args, **kwargs):
        seen.append((view.face, view.kind, len(listed)))
        return solve(prims, solid, order, listed, gap, view, *args, **kwargs)

    monkeypatch.setattr(cos_core, "_solve_view", logged)
    ids, stats = cos_pvs(scene, box, 32)
    counts = [n for _, _, n in seen]
    assert len(seen) == stats["views"] == 30
    assert counts == sorted(counts)
    # Every side plane's front frustum and four half frusta.
    faces = [face for face, _, _ in seen]
    assert sorted(set(faces)) == [(a, s) for a in range(3) for s in (-1, 1)]
    assert all(faces.count(f) == 5 for f in set(faces))
    assert sorted(face for face, kind, _ in seen if kind == "front") == sorted(set(faces))
    assert len(ids) > 0 and np.all(np.diff(np.sort(ids)) > 0)
