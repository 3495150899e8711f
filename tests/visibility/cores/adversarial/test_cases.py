"""The adversarial cases (``cases``) scored for ``cos`` and ``dual_ray`` by dense random ray
casting in float64 (``visibility.ray_reference``, engine "exact"), never by our rasterizer.

For each case the reference draws random eyes in the cell (a quarter on its faces, its corners,
and, where a case names one, more in the corner that sees its trick), drops those inside
geometry, and casts random directions plus rays aimed at the case's openings and targets, seen
with near planes 0 and 5 cm. A core that promises no false negatives must hold every triangle
the rays see first: ``missed == []``, with where each missed one is and the ray that saw it in
the failure message. ``dual_ray`` takes the cases its 2.5D analysis accepts (every case built
as 2.5D must be among them) and refuses the others with the reason.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from tests.grouping import on_one_worker
from tests.visibility.cores.adversarial.cases import Case, all_cases, random_variants
from visibility.cores.base import get_core
from visibility.cores.cos.core import REFINE_MAX
from visibility.cores.dual_ray.core import NotTwoPointFiveD
from visibility.ray_reference import RaySample, describe, draw_eyes, ray_reference
from visibility.viewcells import Viewcell

#: The reference per case: random eyes (+ 8 corners; as many again in a case's eye box),
#: random directions per eye, seeds.
EYES = 256
DIRS = 512
EYE_SEED = 1
RAY_SEED = 2

CASES: dict[str, Case] = {c.name: c for c in all_cases()}


def _on_one_worker(name: str, *args: object) -> object:
    """A test of case ``name``, on the worker of the case's other tests: its reference is
    cast once."""
    return on_one_worker(f"adversarial_{name}", name, *args)


PAIRS = [_on_one_worker(name, core) for name in CASES for core in ("cos", "dual_ray")]
#: The cases built for ``cos`` (each case's tests on one worker).
COS_CASES = [_on_one_worker(n) for n in CASES if "cos" in CASES[n].cores]
#: Cases drawn with random parameters (``cases.random_variants``), seeded: fixed draws,
#: judged like the others for misses only (a draw may leave the reference too few rays
#: through a slit to judge its targets, which says nothing about a core).
VARIANT_SEED = 2026
VARIANTS: dict[str, Case] = {c.name: c for c in random_variants(VARIANT_SEED, 8)}


@cache
def reference(name: str) -> RaySample:
    """The case's float64 reference (module docstring)."""
    case = CASES[name] if name in CASES else VARIANTS[name]
    rng = np.random.default_rng(EYE_SEED)
    eyes = draw_eyes(case.box, EYES, rng)
    if case.eye_box is not None:
        lo, hi = case.eye_box
        eyes = np.concatenate([eyes, lo + rng.random((EYES, 3)) * (hi - lo)])
    return ray_reference(case.scene, case.box, n_dirs=DIRS, seed=RAY_SEED, aim=case.aim,
                         n_aim=case.n_aim, engine="exact", eyes=eyes)


@pytest.mark.parametrize("name", [_on_one_worker(n) for n in CASES])
def test_the_reference_sees_enough_to_judge(name):
    case = CASES[name]
    ref = reference(name)
    assert len(ref.ids) > 0
    assert len(ref.eyes) >= EYES // 2, f"{ref.dropped} eyes dropped as inside geometry"
    missing = np.setdiff1d(case.must_see, ref.ids)
    assert missing.size == 0, f"{name}: the rays never saw {missing.tolist()}"
    wrong = np.intersect1d(case.must_not_see, ref.ids)
    assert wrong.size == 0, f"{name}: the rays saw {wrong.tolist()}, which they cannot"
    if case.targets:
        share = np.isin(case.targets, ref.ids).mean()
        assert share >= case.targets_seen, f"{name}: saw {share:.0%} of the targets"


@pytest.mark.parametrize("name,core_name", PAIRS)
def test_no_misses(name, core_name):
    case = CASES[name]
    core = get_core(core_name)
    fit = core.fit(case.scene, float(np.max(case.box[1] - case.box[0])))
    if core.requires_2_5d and not fit.ok:
        # Not 2.5D: the core refuses the scene, with the reason, and never answers for it.
        assert core_name not in case.cores, f"{core_name} refuses {name}: {fit.why}"
        assert "2.5D" in fit.why
        with pytest.raises(NotTwoPointFiveD, match="2.5D"):
            core.compute(case.scene, Viewcell(case.box), core.make_params())
        return
    assert fit.ok, f"{core_name} refuses {name}: {fit.why}"
    pvs = core.compute(case.scene, Viewcell(case.box), core.make_params())
    ref = reference(name)
    missed = np.setdiff1d(ref.ids, pvs.triangle_ids)
    assert missed.tolist() == [], (
        f"{core_name} misses {len(missed)} of {len(ref.ids)} triangles the rays see in "
        f"{name}:\n{describe(case.scene, ref, missed, case.box)}")


@pytest.mark.parametrize("name", COS_CASES)
def test_cos_leaf_boxes_miss_nothing(name):
    # Every pixel tests leaf boxes (by default only lists of LEAF_LIST entries or more do,
    # which these small scenes never reach): once an entry is hidden, its hierarchy leaf's
    # box against the group that hid it, and the leaf's other entries skip the pixel.
    case = CASES[name]
    core = get_core("cos")
    pvs = core.compute(case.scene, Viewcell(case.box), core.make_params(leaf_list=1))
    st = pvs.stats
    assert st["leaf_hidden"] <= st["leaf_tests"]
    missed = np.setdiff1d(reference(name).ids, pvs.triangle_ids)
    assert missed.tolist() == [], (
        f"cos testing leaf boxes at every pixel misses {len(missed)} triangles in "
        f"{name}:\n{describe(case.scene, reference(name), missed, case.box)}")


@pytest.mark.parametrize("name", COS_CASES)
@pytest.mark.parametrize("busy_block,coarse", [
    # ``long``: sampled at another size, or the coarse pass alone (``(4, True)`` takes both).
    pytest.param(2, False, marks=pytest.mark.long), (8, False),
    pytest.param(1, True, marks=pytest.mark.long), (4, True)])
def test_cos_busy_tiles_miss_nothing(name, busy_block, coarse, monkeypatch):
    # Every screen tile is busy (on these small scenes none would be by default) and sampled
    # once per busy_block x busy_block pixels (the default 4 without the coarse pass runs in
    # the relaxed cover's test below), an entry a sample sees tested again at its sub-samples
    # down to single pixels. With the coarse pass (an option, off by default) first, what it
    # leaves out of the per-pixel lists must be hidden for the whole tile.
    monkeypatch.setattr("visibility.cores.cos.core.BUSY_BLOCK_MIN", 0)  # short lists too
    case = CASES[name]
    core = get_core("cos")
    pvs = core.compute(case.scene, Viewcell(case.box),
                       core.make_params(busy_items=1, coarse_items=int(coarse),
                                        busy_block=busy_block))
    st = pvs.stats
    assert (st["block_tiles"] > 0) == (busy_block > 1)
    # Every tile busy: the sampled tiles' share of the work is all of it, or none unsampled.
    assert st["block_tested"] == (st["tested"] if busy_block > 1 else 0)
    assert (st["block_cycles"] > 0) == (busy_block > 1)
    assert st["block_cycles"] <= st["cycles_resolve"]
    assert (st["coarse_tiles"] > 0) == coarse
    # The coarse pass's work counted apart from the pixels' (what it tests is among what it
    # lists).
    assert st["coarse_tested"] <= st["coarse_entries"]
    assert (st["coarse_cycles_resolve"] > 0) == coarse
    missed = np.setdiff1d(reference(name).ids, pvs.triangle_ids)
    assert missed.tolist() == [], (
        f"cos sampling busy tiles per {busy_block} px (coarse pass: {coarse}) misses "
        f"{len(missed)} triangles in "
        f"{name}:\n{describe(case.scene, reference(name), missed, case.box)}")


@pytest.mark.parametrize("name", COS_CASES)
@pytest.mark.parametrize("coarse_items", [
    None,
    # ``long``: the sub-pixel test "with the others" runs the relaxed cover with the coarse pass.
    pytest.param(1, marks=pytest.mark.long)])
def test_cos_relaxed_cover_misses_nothing(name, coarse_items, monkeypatch):
    # The relaxed cover test lets silhouette edges that meet an occludee's offset region pass
    # when they never cross the offsets whose rays meet it; alone, and with every tile busy
    # and taking the coarse pass (where it runs at the tile's width).
    monkeypatch.setattr("visibility.cores.cos.core.BUSY_BLOCK_MIN", 0)  # 4 x 4 samples too
    case = CASES[name]
    core = get_core("cos")
    extra = {} if coarse_items is None else {"coarse_items": coarse_items, "busy_items": 1}
    pvs = core.compute(case.scene, Viewcell(case.box), core.make_params(cover="relaxed", **extra))
    missed = np.setdiff1d(reference(name).ids, pvs.triangle_ids)
    assert missed.tolist() == [], (
        f"cos with the relaxed cover test (coarse_items={coarse_items}) misses {len(missed)} "
        f"triangles in {name}:\n{describe(case.scene, reference(name), missed, case.box)}")


@pytest.mark.parametrize("name", COS_CASES)
@pytest.mark.parametrize("cover", [
    "strict",
    # ``long``: the sub-pixel test "with the others" fuses groups under the relaxed cover.
    pytest.param("relaxed", marks=pytest.mark.long)])
def test_cos_fused_groups_miss_nothing(name, cover):
    # Separate occluder groups hiding together (``fusion="groups"``) on every case: each part
    # of an occludee's offset region covered by some group in front of it.
    case = CASES[name]
    core = get_core("cos")
    pvs = core.compute(case.scene, Viewcell(case.box),
                       core.make_params(fusion="groups", cover=cover))
    missed = np.setdiff1d(reference(name).ids, pvs.triangle_ids)
    assert missed.tolist() == [], (
        f"cos fusing separate groups ({cover} cover) misses {len(missed)} triangles in "
        f"{name}:\n{describe(case.scene, reference(name), missed, case.box)}")


@pytest.mark.parametrize("name", COS_CASES)
@pytest.mark.parametrize("options", ["alone", "with the others"])
def test_cos_sub_pixels_miss_nothing(name, options, monkeypatch):
    # Occludees no group hides over a whole pixel, tested again at its sub-pixels down to the
    # most levels (``refine``): alone, and with the relaxed cover, separate groups and every
    # tile busy (the coarse pass, 4 x 4 samples).
    monkeypatch.setattr("visibility.cores.cos.core.BUSY_BLOCK_MIN", 0)
    case = CASES[name]
    core = get_core("cos")
    extra = {} if options == "alone" else {"cover": "relaxed", "fusion": "groups",
                                           "coarse_items": 1, "busy_items": 1}
    pvs = core.compute(case.scene, Viewcell(case.box),
                       core.make_params(refine=REFINE_MAX, **extra))
    missed = np.setdiff1d(reference(name).ids, pvs.triangle_ids)
    assert missed.tolist() == [], (
        f"cos with sub-pixels ({options}) misses {len(missed)} triangles in "
        f"{name}:\n{describe(case.scene, reference(name), missed, case.box)}")


@pytest.mark.parametrize("name", list(VARIANTS))
def test_no_misses_on_random_variants(name):
    # Both cores where they take the scene (dual_ray refuses what is not 2.5D).
    case = VARIANTS[name]
    ref = reference(name)
    assert len(ref.ids) > 0
    for core_name in ("cos", "dual_ray"):
        core = get_core(core_name)
        if not core.fit(case.scene, float(np.max(case.box[1] - case.box[0]))).ok:
            assert core_name == "dual_ray"
            continue
        pvs = core.compute(case.scene, Viewcell(case.box), core.make_params())
        missed = np.setdiff1d(ref.ids, pvs.triangle_ids)
        assert missed.tolist() == [], (
            f"{core_name} misses {len(missed)} of {len(ref.ids)} triangles the rays see in "
            f"{name}:\n{describe(case.scene, ref, missed, case.box)}")
