"""Every discovered core passes every conformance check (``visibility.cores.checks``), and the
checks can fail: cores that break one promise each are caught."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from visibility.cores import checks
from visibility.cores.base import Core, CoreParams, available_cores, get_core
from visibility.cores.sampling import SamplingCore

CASES = [(name, check.__name__) for name in available_cores() for check in checks.CHECKS]


def test_the_builtin_cores_are_discovered():
    assert {"sampling", "from_segment"} <= set(available_cores())


@pytest.mark.parametrize(("core_name", "check_name"), CASES)
def test_core_passes_check(core_name, check_name):
    getattr(checks, check_name)(get_core(core_name))


# --------------------------------------------------------------------------- teeth
class _Everything(Core):
    """Reports every valid triangle: over-inclusive, never misses."""

    name: ClassVar[str] = "everything"
    description: ClassVar[str] = "every valid triangle"
    promise = "conservative"
    fn_bound = 0.0

    def _compute(self, scene, cell, params: CoreParams) -> tuple[np.ndarray, dict[str, Any]]:
        return np.flatnonzero(scene.valid_faces), {}


class _Nothing(Core):
    """Reports nothing."""

    name: ClassVar[str] = "nothing"
    description: ClassVar[str] = "no triangle"

    def _compute(self, scene, cell, params: CoreParams) -> tuple[np.ndarray, dict[str, Any]]:
        return np.zeros(0, np.int64), {}


class _ClaimsConservative(SamplingCore):
    """Point sampling that claims no false negatives."""

    name: ClassVar[str] = "sampling_claiming_conservative"
    promise = "conservative"
    fn_bound = 0.0


class _Unseeded(Core):
    """Drops one valid triangle, a different one on each call, whatever the seed (a random
    pick could repeat itself and make this test flaky: one in the scene's triangle count)."""

    name: ClassVar[str] = "unseeded"
    description: ClassVar[str] = "valid triangles but one, chosen without the seed"
    calls: ClassVar[list[int]] = [0]

    def _compute(self, scene, cell, params: CoreParams) -> tuple[np.ndarray, dict[str, Any]]:
        ids = np.flatnonzero(scene.valid_faces)
        self.calls[0] += 1
        return np.delete(ids, self.calls[0] % len(ids)), {}


class _Priceless(_Nothing):
    """Estimates every request at the same cost, whatever its resolution."""

    name: ClassVar[str] = "priceless"

    def estimate_cost(self, scene, cell, params):
        from visibility.cores.base import Cost

        return Cost(1.0, 1 << 20)


@pytest.mark.parametrize(("core", "check_name"), [
    (_Priceless(), "check_cost_estimate"),
    (_Everything(), "check_two_rooms_and_a_door"),
    (_Everything(), "check_fn_fp_against_sampled_ground_truth"),
    (_Nothing(), "check_everything_visible"),
    (_Nothing(), "check_scene_of_one_triangle"),
    (_ClaimsConservative(), "check_lone_sliver"),
    (_Unseeded(), "check_deterministic"),
])
def test_a_core_breaking_a_promise_fails_its_check(core, check_name):
    with pytest.raises(AssertionError):
        getattr(checks, check_name)(core)


def test_check_core_lists_every_failure():
    with pytest.raises(AssertionError) as info:
        checks.check_core(_Nothing())
    text = str(info.value)
    assert "check_everything_visible" in text and "check_two_rooms_and_a_door" in text
    assert "check_empty_scene" not in text  # an empty answer is right for an empty scene
