"""Winding numbers beside closed surfaces' triangles (``visibility.winding``)."""

from __future__ import annotations

import numpy as np
import trimesh

from visibility.winding import UNDECIDED, front_windings


def _box(lo, hi, inward: bool = False) -> np.ndarray:
    m = trimesh.creation.box(bounds=np.array([lo, hi], dtype=float))
    t = np.asarray(m.triangles, dtype=np.float64)
    return t[:, ::-1].copy() if inward else t


def _windings(tris, part=None):
    part = np.zeros(len(tris), dtype=np.int64) if part is None else part
    return front_windings(tris, part, np.ones(len(tris), dtype=bool))


def test_outside_is_zero_in_front_of_an_outward_box_and_one_behind():
    w = _windings(_box((0, 0, 0), (1, 2, 3)))
    assert np.all(w == 0)


def test_an_inward_box_has_its_inside_in_front():
    w = _windings(_box((0, 0, 0), (1, 1, 1), inward=True))
    assert np.all(w == -1)


def test_an_inward_box_inside_an_outward_one():
    # One surface passing through itself: an outward box A and an inward box B across its
    # side. B's faces outside A have w = -1 in front, 0 behind: an eye outside sees their
    # back. Inside A, w is 0 in front and 1 behind: A hides them from any eye outside.
    a = _box((0, 0, 0), (2, 2, 2))
    b = _box((1.5, 0.5, 0.5), (3.0, 1.5, 1.5), inward=True)
    tris = np.concatenate([a, b])
    w = _windings(tris)
    c = tris[len(a):].mean(axis=1)
    outside_a = c[:, 0] > 2.0
    wb = w[len(a):]
    decided = wb != UNDECIDED
    assert decided[outside_a].all()
    assert np.all(wb[outside_a] == -1)
    inside_a = c[:, 0] < 2.0
    assert np.all(wb[inside_a & decided] == 0)
    # Parts are counted apart: the same boxes as two surfaces.
    w2 = _windings(tris, np.repeat([0, 1], [len(a), len(b)]))
    assert np.all(w2[len(a):][w2[len(a):] != UNDECIDED] == -1)
    assert np.all(w2[:len(a)] == 0)
