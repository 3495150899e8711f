"""The cos core stops inside a view when its computation is cancelled: the resolution kernel
polls the stop flag (``visibility.cancel.stop_flag``) between pixels and within long lists."""

from __future__ import annotations

import time

import numpy as np
import pytest

import visibility.cores.cos.core as cos_core
from tests.visibility.cores.cos.reference import cell_around
from visibility.cancel import CancelToken, ComputationCancelled
from visibility.cores.base import get_core
from visibility.generators import make_scene
from visibility.viewcells import Viewcell


@pytest.fixture(scope="module")
def rooms():
    return make_scene("rooms", triangles=20_000)


def test_the_kernel_returns_at_once_when_the_flag_is_set(rooms, monkeypatch):
    box = cell_around(rooms, 1.0, 0)
    ids, stats = cos_core.cos_pvs(rooms, box, 32)
    assert stats["tested"] > 0 and len(ids) > 0
    # The flag set from the start, and no checkpoint to raise: the kernel must test nothing.
    monkeypatch.setattr(cos_core, "stop_flag", lambda: np.ones(1, dtype=np.uint8))
    monkeypatch.setattr(cos_core, "checkpoint", lambda: None)
    ids, stats = cos_core.cos_pvs(rooms, box, 32)
    assert stats["tested"] == 0
    assert stats["list_entries"] > 0  # the lists were built: the stop was in the resolution


def test_a_deadline_stops_a_long_cell_inside_its_views(rooms):
    # A 4 m cell of 20k rooms takes about 20 s at the default resolution on 2 cores
    # (benchmarks/results/cos.md), most of it inside the resolution of single views.
    core = get_core("cos")
    cell = Viewcell(cell_around(rooms, 4.0, 0))
    core.compute(rooms, cell, core.make_params(resolution=16))  # compile outside the deadline
    t0 = time.monotonic()
    with pytest.raises(ComputationCancelled, match="deadline"):
        core.compute(rooms, cell, core.make_params(), token=CancelToken.after(0.3))
    assert time.monotonic() - t0 < 5.0
