"""The conservative cores' promise on the real scenes (``../shared/scenes``), scored by dense
random ray casting (``visibility.ray_reference``, Embree), never by our rasterizer.

For each real scene, each cell size (0.3 m and 1 m cubes) and ``CELLS`` cubes centred on cells
of the scene's own viewcell grid (its walk area), drawn at random with another seed than the
benchmark's and kept when most of their eyes are in open space
(``benchmarks.bench_conservative.open_cells``), Embree rays from random eyes in the cell's open
space, in random directions, seen with near planes 0 and the clients' 5 cm, find the triangles
seen first. Every one a core
leaves out is cast again in float64 from its witness rays (``ray_reference.confirm``: Embree
is float32); a confirmed one is a miss, and there must be none.

``dual_ray`` runs where its 2.5D analysis accepts the scene (denhaag, lyon_vilo3d) and must
refuse the others (lavaducts, an interior; the kitchen) with the reason. ``cos`` on the
1M-triangle kitchen keeps most of it in a cell's PVS and costs far more than this suite can
spend: those cells live in the benchmark only
(``python -m benchmarks.bench_conservative --scenes kitchen``), outside this suite's budget.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from benchmarks.bench_conservative import open_cells
from tests.grouping import on_one_worker
from tests.visibility.real_scenes import REAL, SHARED_SCENES, real_scene
from visibility.cores.base import get_core
from visibility.cores.cos.core import REFINE_MAX
from visibility.cores.dual_ray.core import NotTwoPointFiveD
from visibility.ray_reference import RaySample, confirm, describe
from visibility.viewcells import Viewcell

#: Real scenes: out of the fast lane (``-m "not slow"``), always in CI.
pytestmark = pytest.mark.slow

#: Cell sizes (cube sides, metres) and cells per scene and size.
SIZES = (0.3, 1.0)
#: One cell per scene and size here; the benchmark scores three (``bench_conservative``).
CELLS = 1
#: The reference per cell: random eyes (+ 8 corners), random directions per eye, seed.
EYES = 96
DIRS = 2048
SEED = 5
#: Scenes whose cos cells cost too much for the suite (the benchmark scores them).
BENCHMARK_ONLY = {"cos": ("kitchen",)}
#: Every real scene the issue names: the suite must find them all.
NAMED = ("denhaag", "kitchen", "lavaducts", "lyon_vilo3d")


@cache
def cells(name: str, size: float) -> list[tuple[int, np.ndarray, RaySample]]:
    """(grid cell id, (2, 3) box, reference) of ``CELLS`` cubes of side ``size`` m in open
    space of the scene (module docstring)."""
    return open_cells(real_scene(name), size, CELLS, EYES, DIRS, SEED)


def _on_one_worker(name: str, *args: object) -> object:
    """A case of scene ``name``, run by the worker that runs the scene's other cases (``bash
    scripts/test.sh`` distributes by ``xdist_group``), so its reference cells are cast once."""
    return on_one_worker(name, name, *args)


CASES = [_on_one_worker(name, size, k, core) for name in REAL for size in SIZES
         for k in range(CELLS) for core in ("cos", "dual_ray")
         if name not in BENCHMARK_ONLY.get(core, ())]
#: ``cos`` with every screen tile busy (by default only cluttered tiles are): the 0.3 m cell.
BUSY = [_on_one_worker(name, 0.3) for name in REAL if name not in BENCHMARK_ONLY["cos"]]


def test_every_named_scene_is_there():
    missing = sorted(set(NAMED) - set(REAL))
    assert not missing, f"{missing} not found in {SHARED_SCENES}"


@pytest.mark.parametrize("name,size,k,core_name", CASES)
def test_no_confirmed_misses(name, size, k, core_name):
    scene = real_scene(name)
    core = get_core(core_name)
    fit = core.fit(scene, size)
    if core.requires_2_5d and not fit.ok:
        assert "2.5D" in fit.why
        box = np.array([[0.0, 1.5, 0.0], [size, 1.5 + size, size]])
        with pytest.raises(NotTwoPointFiveD, match="2.5D"):
            core.compute(scene, Viewcell(box), core.make_params())
        return
    assert fit.ok, f"{core_name} refuses {name}: {fit.why}"
    picked = cells(name, size)
    assert len(picked) == CELLS, f"only {len(picked)} cells of {name} in open space"
    _, box, ref = picked[k]
    # Enough to judge: the rays see a fair share of the scene.
    assert len(ref.ids) >= 50, f"the rays saw only {len(ref.ids)} triangles"
    pvs = core.compute(scene, Viewcell(box), core.make_params())
    missed = np.setdiff1d(ref.ids, pvs.triangle_ids)
    sure = confirm(scene, ref, missed)
    assert sure.tolist() == [], (
        f"{core_name} misses {len(sure)} of {len(ref.ids)} triangles the rays see from "
        f"{name}'s {size:g} m cell {box.tolist()} (float64-confirmed; {len(missed)} before "
        f"confirming):\n{describe(scene, ref, sure, box)}")


@pytest.mark.parametrize("name,size", BUSY)
def test_cos_busy_tiles_no_confirmed_misses(name, size, monkeypatch):
    # Every tile is busy, however short its lists: sampled per 4 x 4 pixels (the default
    # ``busy_block``), an entry a sample sees tested again down to single pixels.
    monkeypatch.setattr("visibility.cores.cos.core.BUSY_BLOCK_MIN", 0)
    scene = real_scene(name)
    _, box, ref = cells(name, size)[0]
    core = get_core("cos")
    pvs = core.compute(scene, Viewcell(box), core.make_params(busy_items=1))
    assert pvs.stats["block_tiles"] > 0 and pvs.stats["subpixels"] > 0
    sure = confirm(scene, ref, np.setdiff1d(ref.ids, pvs.triangle_ids))
    assert sure.tolist() == [], (
        f"cos sampling busy tiles misses {len(sure)} of {len(ref.ids)} triangles the rays see "
        f"from {name}'s {size:g} m cell {box.tolist()}:\n{describe(scene, ref, sure, box)}")


@pytest.mark.parametrize("name", [_on_one_worker(n) for n in REAL
                                  if n not in BENCHMARK_ONLY["cos"]])
def test_cos_sub_cells_no_confirmed_misses(name):
    # The 1 m cell solved as 2 x 2 sub-cells, each passing what it found on as known.
    scene = real_scene(name)
    _, box, ref = cells(name, 1.0)[0]
    core = get_core("cos")
    pvs = core.compute(scene, Viewcell(box), core.make_params(subcells=2))
    assert pvs.stats["subcells"] == 2
    sure = confirm(scene, ref, np.setdiff1d(ref.ids, pvs.triangle_ids))
    assert sure.tolist() == [], (
        f"cos in 2 x 2 sub-cells misses {len(sure)} of {len(ref.ids)} triangles the rays see "
        f"from {name}'s 1 m cell {box.tolist()}:\n{describe(scene, ref, sure, box)}")


#: ``cos``'s options that change how occludees are proven hidden, each judged on every cell.
OPTIONS = {"relaxed cover": {"cover": "relaxed"}, "separate groups": {"fusion": "groups"},
           "sub-pixels": {"refine": REFINE_MAX},
           # The open scenes' lists never reach the default 2048 entries: a box test at
           # every pixel holds the leaf boxes to their promise there too.
           "leaf boxes at every pixel": {"leaf_list": 1}}


@pytest.mark.parametrize("option", list(OPTIONS))
@pytest.mark.parametrize("name,size", [_on_one_worker(n, s) for n in REAL
                                       if n not in BENCHMARK_ONLY["cos"] for s in SIZES])
def test_cos_options_no_confirmed_misses(name, size, option):
    scene = real_scene(name)
    _, box, ref = cells(name, size)[0]
    core = get_core("cos")
    pvs = core.compute(scene, Viewcell(box), core.make_params(**OPTIONS[option]))
    sure = confirm(scene, ref, np.setdiff1d(ref.ids, pvs.triangle_ids))
    assert sure.tolist() == [], (
        f"cos with the {option} misses {len(sure)} of {len(ref.ids)} triangles the rays see "
        f"from {name}'s {size:g} m cell {box.tolist()}:\n{describe(scene, ref, sure, box)}")


@pytest.mark.parametrize("name", [n for n in REAL if n in ("kitchen", "lavaducts")])
def test_dual_ray_refuses_the_interiors_with_the_reason(name):
    # The interiors are not 2.5D: dual_ray says why instead of answering.
    fit = get_core("dual_ray").fit(real_scene(name), 1.0)
    assert not fit.ok
    assert "2.5D" in fit.why and len(fit.why) > len("needs a 2.5D scene")

