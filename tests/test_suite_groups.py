"""The suite's own machinery: ``--dist loadgroup`` (scripts/test.sh) keeps an ``xdist_group``
on one worker, which the suite's costly shared fixtures (the kitchen, servers, module
fixtures) rely on to be built once per run. pytest 9.2 silently broke it
(pytest-dev/pytest-xdist#1386); a worker then marks no test with its group."""

from __future__ import annotations

import os

import pytest

pytestmark = pytest.mark.xdist_group("suite_groups")


def test_a_grouped_test_carries_its_group_under_loadgroup(request):
    # A worker of a ``--dist loadgroup`` run has ``option.loadgroup`` set (its own ``dist``
    # reads "no"); run alone, nothing is grouped and nothing can be checked.
    if os.environ.get("PYTEST_XDIST_WORKER") is None or not getattr(
            request.config.option, "loadgroup", False):
        return
    assert request.node.nodeid.endswith("@suite_groups"), (
        f"{request.node.nodeid}: xdist_group is ignored, so grouped tests are spread over "
        "the workers and their shared fixtures built once per worker (pin pytest, "
        "pyproject.toml)")
