"""``check_core(core)``: the one conformance suite every core passes (like scikit-learn's
``check_estimator``), importable so anyone can run it on their own core.

Each ``check_*`` function takes a core and asserts one property on scenes with known answers
(``visibility.cores.designed_scenes``, the ``stress`` generator, small hand-built cases).
Nothing branches on a core's name: what differs between cores is what they declare, above all
their ``promise`` (``visibility.cores.base.PROMISES``):

- every core: valid, sorted, unique ids of valid faces; no NaN in its stats; determinism for a
  seed; the known answers of the designed scenes; its stated FN and FP bounds against a dense
  sampled ground truth;
- cores not ``aggressive`` (exact at pixel samples along the cell, or conservative) also find the
  slivers in plain view that move across many pixel centres as the eye crosses the cell;
- ``conservative`` cores have no false negative at all on the designed scenes, find a lone
  1e6-aspect sliver, and report every triangle of a cell that contains the whole scene; a
  triangle seen only edge-on (zero area from every eye) may be reported by them, by no one else;
- cores made for 2.5D scenes only (``requires_2_5d``) are held, on every scene that is not 2.5D
  (``visibility.scene_analysis.scene_is_2_5d``), to the clear refusal instead: ``fit`` says no
  and names 2.5D, ``compute`` raises a ValueError that does; on the 2.5D ones (the open ring, the
  stiff one-triangle cases, ``designed_scenes.city_blocks`` in place of the two rooms) to all of
  the above.

The checks run at small resolutions (``CONFORMANCE_RESOLUTION``, ``STIFF_RESOLUTION``) on top of
the core's ``check_params`` so the whole suite stays quick for every core.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from visibility.cores import designed_scenes as ds
from visibility.cores.base import (
    PROMISES,
    PVS,
    Core,
    CoreParams,
    SegmentNotSupported,
    get_core,
)
from visibility.scene import Scene
from visibility.viewcells import Viewcell

#: Resolution of the conformance checks on the designed scenes (the FN / FP bounds are stated
#: at it), and of the stiff and extreme checks.
CONFORMANCE_RESOLUTION = 128
STIFF_RESOLUTION = 64
#: The dense sampled ground truth of the FN / FP checks: points in the cell, pixels, seed.
REFERENCE = {"n_points": 128, "resolution": 128, "seed": 11}


# --------------------------------------------------------------------------- helpers
def check_params(core: Core, resolution: int = CONFORMANCE_RESOLUTION, **extra: Any) -> CoreParams:
    """The core's ``check_params`` at ``resolution`` pixels, with ``extra`` fields changed."""
    return core.make_params(**{**core.check_params, "resolution": resolution, **extra})


def check_valid(pvs: PVS, scene: Scene) -> set[int]:
    """Assert the PVS is well formed (int32, sorted, unique, valid faces, finite stats) and
    return its ids as a set."""
    ids = pvs.triangle_ids
    assert ids.dtype == np.int32, f"triangle ids must be int32, got {ids.dtype}"
    assert np.all(np.diff(ids.astype(np.int64)) > 0), "ids must be sorted and unique"
    if len(ids):
        assert ids[0] >= 0 and ids[-1] < scene.n_triangles, "ids outside the face array"
        assert scene.valid_faces[ids].all(), "degenerate faces must never be in a PVS"
    assert np.isfinite(pvs.seconds)
    for k, v in pvs.stats.items():
        if isinstance(v, float):
            assert not np.isnan(v), f"stat {k} is NaN"
    return set(ids.tolist())


def _solve(core: Core, scene: Scene, cell: Viewcell, resolution: int, **extra: Any) -> set[int]:
    return check_valid(core.compute(scene, cell, check_params(core, resolution, **extra)), scene)


def refused(core: Core, scene: Scene, cell: Viewcell | None = None) -> bool:
    """True when ``core`` is made for 2.5D scenes only and ``scene`` is not 2.5D, after
    asserting the clear refusal: ``fit`` says no with a reason naming 2.5D, and ``compute``
    raises a ValueError naming it too. False (nothing asserted) otherwise: the caller checks
    the answer."""
    if not core.requires_2_5d:
        return False
    from visibility.scene_analysis import scene_is_2_5d

    if scene_is_2_5d(scene)[0]:
        return False
    fit = core.fit(scene, 4.0)
    assert not fit.ok, f"a 2.5D-only core fits the non-2.5D scene {scene.name!r}"
    assert "2.5D" in fit.why, f"the refusal does not say why (2.5D): {fit.why!r}"
    cell = cell if cell is not None else Viewcell(np.array([[0.0, 1.5, 0.0], [1.0, 1.9, 1.0]]))
    try:
        core.compute(scene, cell, check_params(core))
    except ValueError as exc:
        assert "2.5D" in str(exc), f"compute refused without naming 2.5D: {exc}"
        return True
    raise AssertionError(f"a 2.5D-only core computed the non-2.5D scene {scene.name!r}")


def main_case(core: Core) -> tuple[Scene, Viewcell, dict[str, list[int]], Viewcell]:
    """The designed scene the general checks (determinism, granularity, segments, tiny and huge
    cells, translation) run on, its cell, its known answers and a 1 mm cell inside the cell:
    the two rooms, or for a 2.5D-only core the 2.5D ``city_blocks`` (the two rooms have a
    ceiling)."""
    if core.requires_2_5d:
        scene, cell, known = ds.city_blocks()
    else:
        scene, cell, known = ds.two_rooms_and_a_door()
    if scene.name == "two_rooms":
        tiny = Viewcell(np.array([[2.5, 1.7, 3.0], [2.501, 1.701, 3.001]]))
    else:
        c = cell.center
        tiny = Viewcell(np.stack([c, c + 0.001]))
    return scene, cell, known, tiny


@functools.cache
def designed_reference(scene_name: str) -> np.ndarray:
    """The ``REFERENCE`` ground truth of a designed scene's cell (ids), computed once."""
    from visibility.ground_truth import sample_pvs

    scene, cell, _ = getattr(ds, scene_name)()
    return sample_pvs(scene, cell, **REFERENCE).triangle_ids


def _tri_scene(tris: Any, name: str = "tris") -> Scene:
    t = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
    return Scene(t.reshape(-1, 3), np.arange(len(t) * 3).reshape(-1, 3), name=name)


def _assert_known(found: set[int], known: dict[str, list[int]], what: str) -> None:
    missing = set(known["visible"]) - found
    assert not missing, f"{what}: visible triangles missing: {sorted(missing)}"
    leaked = set(known["hidden"]) & found
    assert not leaked, f"{what}: hidden triangles reported: {sorted(leaked)}"


# --------------------------------------------------------------------------- declarations
def check_declarations(core: Core) -> None:
    """Name, description, promise, bounds, parameter specs, knob and its levels are coherent,
    and bad parameters are refused."""
    assert core.name and core.description, "a core needs a name and a description"
    assert core.promise in PROMISES, f"promise {core.promise!r} is not one of {list(PROMISES)}"
    assert 0.0 <= core.fn_bound <= 1.0 and 0.0 <= core.fp_bound <= 1.0
    if core.promise == "conservative":
        assert core.fn_bound == 0.0, "a conservative core claims no false negatives: fn_bound 0"
    specs = core.param_specs()
    names = [s.name for s in specs]
    assert {"resolution", "granularity", "seed"} <= set(names)
    for s in specs:
        assert s.help, f"parameter {s.name} has no help"
    if core.knob is not None:
        assert core.knob in names, f"knob {core.knob!r} is not a parameter"
        assert len(core.knob_levels) >= 2, "a knob needs at least two levels"
        for level in core.knob_levels:
            core.make_params(**{core.knob: level})
    core.make_params(**core.check_params)
    for bad in ({"no_such_parameter": 1}, {"resolution": 10**6}, {"seed": -1},
                {"granularity": "pixel"}):
        try:
            core.make_params(**bad)
        except ValueError:
            continue
        raise AssertionError(f"make_params accepted {bad}")
    fit = core.fit(ds.empty()[0], 4.0)
    assert isinstance(fit.ok, bool) and np.isfinite(fit.score) and isinstance(fit.why, str)
    d = core.describe()
    assert d["name"] == core.name and [p["name"] for p in d["params"]] == names


def check_cost_estimate(core: Core) -> None:
    """``estimate_cost`` (what admission control prices a request by) answers quickly with
    finite, non-negative seconds and bytes that do not shrink as the resolution grows, and
    grow in one of them from 64 to 1024 px."""
    scene, cell, _ = ds.two_rooms_and_a_door()
    costs = []
    for r in (64, 256, 1024):
        t0 = time.perf_counter()
        cost = core.estimate_cost(scene, cell, check_params(core, resolution=r))
        assert time.perf_counter() - t0 < 0.5, "an estimate must be cheap (no computing)"
        assert np.isfinite(cost.seconds) and cost.seconds >= 0, cost
        assert int(cost.peak_bytes) >= 0, cost
        costs.append(cost)
    for lo, hi in itertools.pairwise(costs):
        assert hi.seconds >= lo.seconds and hi.peak_bytes >= lo.peak_bytes, (lo, hi)
    assert costs[-1].seconds > costs[0].seconds or costs[-1].peak_bytes > costs[0].peak_bytes, \
        "the estimate ignores the resolution"


# --------------------------------------------------------------------------- designed scenes
def check_empty_scene(core: Core) -> None:
    """A scene with no triangles: an empty PVS."""
    scene, cell, _ = ds.empty()
    if refused(core, scene, cell):
        return
    assert _solve(core, scene, cell, CONFORMANCE_RESOLUTION) == set()


def check_all_degenerate(core: Core) -> None:
    """A scene whose faces are all degenerate: an empty PVS."""
    scene, cell, _ = ds.only_degenerate()
    if refused(core, scene, cell):
        return
    assert _solve(core, scene, cell, CONFORMANCE_RESOLUTION) == set()


def check_everything_visible(core: Core) -> None:
    """A ring of quads in plain view around the cell: every one is found."""
    scene, cell, known = ds.open_ring()
    if refused(core, scene, cell):
        return
    assert set(known["visible"]) <= _solve(core, scene, cell, CONFORMANCE_RESOLUTION)


def check_deterministic(core: Core) -> None:
    """Two runs with the same seed give the same ids."""
    scene, cell, _, _ = main_case(core)
    a = core.compute(scene, cell, check_params(core, seed=3))
    b = core.compute(scene, cell, check_params(core, seed=3))
    np.testing.assert_array_equal(a.triangle_ids, b.triangle_ids)


def check_two_rooms_and_a_door(core: Core) -> None:
    """The far wall through the door and a box in the room are found; a box behind the wall
    is not."""
    scene, cell, known = ds.two_rooms_and_a_door()
    if refused(core, scene, cell):
        return
    _assert_known(_solve(core, scene, cell, CONFORMANCE_RESOLUTION), known, "two rooms")


def check_object_granularity(core: Core) -> None:
    """Object granularity reports every valid triangle of each visible object."""
    scene, cell, _, _ = main_case(core)
    pvs = core.compute(scene, cell, check_params(core, granularity="object"))
    check_valid(pvs, scene)
    assert pvs.granularity == "object"
    objs = np.unique(scene.object_ids[pvs.triangle_ids])
    np.testing.assert_array_equal(objs, pvs.object_ids)
    whole = np.isin(scene.object_ids, objs) & scene.valid_faces
    np.testing.assert_array_equal(np.nonzero(whole)[0], pvs.triangle_ids)


def check_stiff_cases(core: Core) -> None:
    """Coplanar, intersecting, huge, through-the-cell and degenerate triangles and a closed room,
    at offsets 0, 1e5 and 1e7 m: the known answers hold."""
    for offset in (0.0, 1e5, 1e7):
        scene, cell, known = ds.stiff_cases(offset=(offset, 0.0, -offset))
        if refused(core, scene, cell):
            return
        found = _solve(core, scene, cell, CONFORMANCE_RESOLUTION)
        _assert_known(found, known, f"stiff cases at {offset:g} m")
        assert not set(known["degenerate"]) & found
        if core.promise == "conservative":
            assert set(known["sliver"]) <= found, f"the 1e6 sliver is missing at {offset:g} m"


def check_fn_fp_against_sampled_ground_truth(core: Core) -> None:
    """FN and FP rates against a dense sampled reference (``REFERENCE``) within the core's
    stated bounds on two rooms, the open ring and the stiff cases. FP counts what the core
    reports that the reference did not see. The stiff cases' sub-pixel sliver is held only
    against conservative cores' FN (which must be 0 everywhere)."""
    from visibility.ground_truth import fn_fp_rates

    cases = [("two_rooms_and_a_door", True), ("open_ring", True),
             ("stiff_cases", core.promise == "conservative")]
    if core.requires_2_5d:
        cases.append(("city_blocks", True))
    for name, fn_applies in cases:
        scene, cell, _ = getattr(ds, name)()
        if refused(core, scene, cell):
            continue
        pvs = core.compute(scene, cell, check_params(core))
        fn, fp = fn_fp_rates(pvs.triangle_ids, designed_reference(name))
        if fn_applies:
            assert fn <= core.fn_bound, f"{name}: FN rate {fn:.3f} > its bound {core.fn_bound}"
        assert fp <= core.fp_bound, f"{name}: FP rate {fp:.3f} > its bound {core.fp_bound}"


def check_fp_bound_can_fail(core: Core) -> None:
    """The FP bound is not vacuous: reporting every valid triangle of the two rooms (the box
    hidden behind the wall included; for a 2.5D-only core, of the city blocks) exceeds it."""
    from visibility.ground_truth import fn_fp_rates

    name = "city_blocks" if core.requires_2_5d else "two_rooms_and_a_door"
    scene, _, _ = getattr(ds, name)()
    _, fp = fn_fp_rates(np.nonzero(scene.valid_faces)[0], designed_reference(name))
    assert fp > core.fp_bound, f"fp_bound {core.fp_bound} lets every triangle through ({fp:.3f})"


def check_tiny_and_huge_cells(core: Core) -> None:
    """A 1 mm cell keeps the two rooms' known answers; a 1 km cell around the whole scene is
    valid and, for a conservative core, reports every valid triangle (an eye can stand next to
    each)."""
    scene, _, known, tiny = main_case(core)
    _assert_known(_solve(core, scene, tiny, CONFORMANCE_RESOLUTION), known, "1 mm cell")
    huge = Viewcell(np.array([[-500.0, -500.0, -500.0], [500.0, 500.0, 500.0]]))
    found = _solve(core, scene, huge, CONFORMANCE_RESOLUTION)
    if core.promise == "conservative":
        assert found == set(np.flatnonzero(scene.valid_faces).tolist())


def check_segment_queries(core: Core) -> None:
    """Every core answers an axis-aligned segment (a degenerate box); a diagonal one when it
    declares ``native_segments``, else ``SegmentNotSupported``; infinite end points raise."""
    scene, cell, known, _ = main_case(core)
    # A segment along x through the cell's middle, and a diagonal one from its start.
    c = cell.center
    p, q = c - [0.5, 0.0, 0.2], c + [0.5, 0.0, -0.2]
    params = check_params(core)
    found = check_valid(core.compute_segment(scene, p, q, params), scene)
    _assert_known(found, known, "axis-aligned segment")
    diagonal = c + np.array([0.5, 0.2, 0.4])
    if core.native_segments:
        found = check_valid(core.compute_segment(scene, p, diagonal, params), scene)
        assert not set(known["hidden"]) & found
    else:
        try:
            core.compute_segment(scene, p, diagonal, params)
        except SegmentNotSupported:
            pass
        else:
            raise AssertionError("a box-only core answered a diagonal segment")
    try:
        core.compute_segment(scene, p, np.array([np.inf, 0.0, 0.0]), params)
    except ValueError:
        return
    raise AssertionError("an infinite segment end point was accepted")


def check_city_blocks(core: Core) -> None:
    """The 2.5D designed cases (``designed_scenes.city_blocks``): a box behind a wall and one
    behind three blocks side by side (occluder fusion) are hidden, a box seen through a gap
    between two buildings and a tower behind a low block are found. Held by the cores made for
    2.5D scenes; the general cores meet 2.5D scenes in the sampled checks and their own tests
    (a 10 m cell is far beyond what some of them are made for)."""
    if not core.requires_2_5d:
        return
    scene, cell, known = ds.city_blocks()
    from visibility.scene_analysis import scene_is_2_5d

    assert scene_is_2_5d(scene)[0], "city_blocks must read as 2.5D"
    found = _solve(core, scene, cell, CONFORMANCE_RESOLUTION)
    for case in ("gap_visible", "tall_visible"):
        assert set(known[case]) <= found, f"city blocks: {case} missing"
    for case in ("wall_hidden", "fusion_hidden", "low_hidden"):
        assert not set(known[case]) & found, f"city blocks: {case} reported"


def check_refuses_scenes_that_are_not_2_5d(core: Core) -> None:
    """A core made for 2.5D scenes refuses, clearly, a scene under a ceiling (the two rooms);
    ``fit`` says why with the share of the footprint measured. Other cores fit it."""
    scene, cell, _ = ds.two_rooms_and_a_door()
    if core.requires_2_5d:
        assert refused(core, scene, cell)
        why = core.fit(scene, 4.0).why
        assert "%" in why and "ceiling" in why, why
    else:
        assert core.fit(scene, 4.0).ok


# --------------------------------------------------------------------------- stiff and extreme
def check_stress_scene(core: Core) -> None:
    """The ``stress`` generator's cases at 1e5 and 1e7 m: plain view, a 12 km triangle, a box
    behind a closed wall, degenerate faces, intersecting and coplanar pairs, edge-on and
    eye-plane triangles; slivers for cores that are not aggressive."""
    from visibility.generators import make_scene

    for offset in (1e5, 1e7):
        stress = make_scene("stress", triangles=1500, offset=offset)
        if refused(core, stress):
            return
        cases = stress.meta["cases"]
        for cell_index in (0, 1):
            cell = Viewcell(np.array(stress.meta["cells"][cell_index]))
            found = _solve(core, stress, cell, STIFF_RESOLUTION)
            where = f"stress at {offset:g} m, cell {cell_index}"
            assert set(cases["visible"]) <= found, f"{where}: the triangle in plain view"
            assert set(cases["huge"]) <= found, f"{where}: the 12 km triangle"
            assert not set(cases["hidden"]) & found, f"{where}: the box behind the wall leaked"
            for bad in ("zero_area", "repeated_index", "non_finite"):
                assert not set(cases[bad]) & found
            assert set(cases["intersecting"]) <= found, f"{where}: an intersecting triangle"
            assert set(cases["coplanar"]) & found, f"{where}: no coplanar triangle"
            # Edge-on for the eyes on their planes, seen from one side by every other eye.
            assert set(cases["edge_on"]) <= found, f"{where}: an edge-on triangle"
            assert set(cases["eye_plane"]) <= found, f"{where}: an eye-plane triangle"
            if core.promise != "aggressive":
                # Seven slivers in plain view cross many pixel centres as the eye travels the
                # cell (the eighth, horizontal at eye height, registers only by rounding).
                assert set(cases["slivers"][:-1]) <= found, f"{where}: a sliver in plain view"


def check_lone_sliver(core: Core) -> None:
    """A 4 m by 4 micrometre sliver (aspect 1e6) 8 m in front of the cell, in plain view: a
    conservative core reports it; the others answer validly (point samples and pixel centres
    see it only where one happens to cross it)."""
    scene = _tri_scene([[(-2, 1.7, -8), (2, 1.7, -8), (0, 1.7 + 4e-6, -8)]], "sliver")
    cell = Viewcell(np.array([[-1.0, 1.5, -1.0], [1.0, 1.9, 1.0]]))
    if refused(core, scene, cell):
        return
    found = _solve(core, scene, cell, STIFF_RESOLUTION)
    assert found <= {0}
    if core.promise == "conservative":
        assert found == {0}, "a conservative core missed a sliver in plain view"


def check_non_finite_vertices_at_load(core: Core) -> None:
    """NaN and inf vertices are rejected at load with a report; the good triangle is found."""
    import trimesh

    from visibility.loaders import load_scene

    v = np.array([[-1, 0, -5], [1, 0, -5], [0, 3, -5],
                  [np.nan, 0, -5], [np.inf, 1, -5], [0, -np.inf, -5]], float)
    f = np.array([[0, 1, 2], [0, 1, 3], [4, 1, 2], [0, 5, 2], [3, 4, 5]])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "nonfinite.ply"
        trimesh.Trimesh(v, f, process=False, validate=False).export(path)
        scene = load_scene(path)
    assert scene.valid_faces.tolist() == [True, False, False, False, False]
    assert scene.degenerate_report.non_finite == 4
    cell = Viewcell(np.array([[-0.5, 0.5, -0.5], [0.5, 1.5, 0.5]]))
    if refused(core, scene, cell):
        return
    assert _solve(core, scene, cell, STIFF_RESOLUTION) == {0}


def check_kilometre_cell(core: Core) -> None:
    """A 1 km cell inside a ring of eight 1 km walls 1.5 km away sees every wall."""
    b = ds.Builder()
    ids: list[int] = []
    for k in range(8):
        a = 2 * np.pi * k / 8
        c, s = np.cos(a), np.sin(a)
        t = np.array([-s, 0.0, c])
        p = np.array([c, 0.0, s]) * 1500.0
        w = 500.0
        ids += b.quad(p - w * t, p - w * t + [0, 400, 0], p + w * t + [0, 400, 0], p + w * t, k)
    scene = b.scene("km_ring")
    cell = Viewcell(np.array([[-500.0, 0.0, -500.0], [500.0, 1000.0, 500.0]]))
    if refused(core, scene, cell):
        return
    assert set(ids) <= _solve(core, scene, cell, STIFF_RESOLUTION)


def check_eye_on_a_triangles_plane(core: Core) -> None:
    """A flat cell in the plane of two horizontal triangles (one through the cell): they have
    zero area from every eye, so only the upright triangle is seen; a conservative core may
    also report the zero-area ones."""
    scene = _tri_scene([
        [(-5, 1.7, -5), (5, 1.7, -5), (0, 1.7, 5)],
        [(10, 1.7, -2), (14, 1.7, -2), (12, 1.7, 2)],
        [(-2, 0.0, -10), (2, 0.0, -10), (0, 3.0, -10)],
    ], "eye_plane")
    cell = Viewcell(np.array([[-1.0, 1.7, -1.0], [1.0, 1.7, 1.0]]))
    if refused(core, scene, cell):
        return
    found = _solve(core, scene, cell, STIFF_RESOLUTION)
    assert 2 in found
    if core.promise != "conservative":
        assert found == {2}, found
    else:
        assert found <= {0, 1, 2}


def check_triangle_crossing_the_near_plane(core: Core) -> None:
    """A triangle from 1 cm to 10 m in front of a point cell is found."""
    scene = _tri_scene([[(-0.5, 1.0, -0.01), (0.5, 1.0, -0.01), (0.0, 2.5, -10.0)]], "near")
    cell = Viewcell(np.array([[0.0, 1.7, 0.0], [0.0, 1.7, 0.0]]))
    if refused(core, scene, cell):
        return
    assert _solve(core, scene, cell, STIFF_RESOLUTION) == {0}


def check_scene_of_one_triangle(core: Core) -> None:
    """One small triangle in view, and one 20 km triangle under the eyes: each is found."""
    cell = Viewcell(np.array([[-0.5, 1.5, -0.5], [0.5, 1.9, 0.5]]))
    for tri in ([(-1, 0, -6), (1, 0, -6), (0, 2, -6)],
                [(-1e4, 0, -1e4), (1e4, 0, -1e4), (0, 0, 1e4)]):
        scene = _tri_scene([tri], "one")
        if refused(core, scene, cell):
            continue
        assert _solve(core, scene, cell, STIFF_RESOLUTION) == {0}


def check_translation_invariance(core: Core) -> None:
    """Moving the two rooms and the cell by 1e7 m changes at most a pixel-edge triangle or two
    and never lets the hidden box in."""
    build = ds.city_blocks if core.requires_2_5d else ds.two_rooms_and_a_door
    base, cell0, known = build()
    far, cell1, _ = build(offset=(1e7, 0.0, -1e7))
    a = _solve(core, base, cell0, STIFF_RESOLUTION)
    b = _solve(core, far, cell1, STIFF_RESOLUTION)
    assert not set(known["hidden"]) & b
    assert len(a ^ b) <= max(2, 0.05 * len(a | b)), sorted(a ^ b)


def check_float64_depth_order_at_1e7(core: Core) -> None:
    """A wall 3 m ahead with a triangle 0.4 m behind it (hidden) and one 0.4 m in front (seen),
    1e7 m from the origin, where float32 coordinates have a 1 m spacing: the right answer, and
    the same as at the origin."""
    def depth_scene(off: np.ndarray) -> tuple[Scene, Viewcell]:
        tris = np.array([
            [(-10, -2, -3), (10, 8, -3), (-10, 8, -3)],
            [(-10, -2, -3), (10, -2, -3), (10, 8, -3)],
            [(-1, 1, -3.4), (1, 1, -3.4), (0, 2.5, -3.4)],
            [(2.3, 1, -2.6), (4, 1, -2.6), (3, 2.5, -2.6)],
        ], dtype=np.float64) + off
        cell = Viewcell(np.array([[-0.5, 1.5, -0.5], [0.5, 1.9, 0.5]]) + off)
        return _tri_scene(tris, "depth"), cell

    scene, cell = depth_scene(np.array([1e7, 0.0, -1e7]))
    if refused(core, scene, cell):
        return
    found = _solve(core, scene, cell, STIFF_RESOLUTION)
    assert {0, 1, 3} <= found and 2 not in found, found
    base, cell0 = depth_scene(np.zeros(3))
    assert _solve(core, base, cell0, STIFF_RESOLUTION) == found


# --------------------------------------------------------------------------- the suite
#: Every check, in the order ``check_core`` runs them.
CHECKS: tuple[Callable[[Core], None], ...] = (
    check_declarations, check_cost_estimate, check_empty_scene, check_all_degenerate,
    check_everything_visible,
    check_deterministic, check_two_rooms_and_a_door, check_city_blocks,
    check_refuses_scenes_that_are_not_2_5d, check_object_granularity,
    check_stiff_cases, check_fn_fp_against_sampled_ground_truth, check_fp_bound_can_fail,
    check_tiny_and_huge_cells, check_segment_queries, check_stress_scene, check_lone_sliver,
    check_non_finite_vertices_at_load, check_kilometre_cell, check_eye_on_a_triangles_plane,
    check_triangle_crossing_the_near_plane, check_scene_of_one_triangle,
    check_translation_invariance, check_float64_depth_order_at_1e7,
)


def core_checks(core: Core | str) -> Iterator[tuple[str, Callable[[], None]]]:
    """(check name, zero-argument callable) for every check of ``core`` (an instance or a
    registered name): what a test suite parametrizes over."""
    obj = get_core(core) if isinstance(core, str) else core
    for check in CHECKS:
        yield check.__name__, (lambda c=check: c(obj))


@dataclasses.dataclass
class CheckFailure:
    """One failed check: its name and the error it raised."""

    check: str
    error: BaseException


def check_core(core: Core | str, stop_at_first: bool = False) -> None:
    """Run every conformance check on ``core``; raise AssertionError listing the failures.

    Parameters
    ----------
    core : a ``Core`` instance (registered or not) or a registered core's name.
    stop_at_first : re-raise the first failure as it is instead of collecting them all.
    """
    failures: list[CheckFailure] = []
    for name, run in core_checks(core):
        try:
            run()
        except Exception as exc:
            if stop_at_first:
                raise
            failures.append(CheckFailure(name, exc))
    if failures:
        label = core if isinstance(core, str) else core.name
        lines = "\n".join(f"  {f.check}: {type(f.error).__name__}: {f.error}" for f in failures)
        raise AssertionError(f"core {label!r} failed {len(failures)} of {len(CHECKS)} "
                             f"checks:\n{lines}")
