"""Keeping tests that share costly work on one pytest-xdist worker.

``bash scripts/test.sh`` runs pytest with ``--dist loadgroup``: tests carrying one
``xdist_group`` run on one worker, ungrouped tests are spread one by one. A group is worth it
where its tests share work a process caches (a real scene, a case's ray reference) or
kernels only they compile (inline helpers called directly, test-local kernels, their own array
types): done once per run instead of once per worker that meets it.
"""

from __future__ import annotations

import pytest


def on_one_worker(group: str, *values: object) -> object:
    """A parametrize value ``values`` whose test runs on the worker of ``group``."""
    return pytest.param(*values, marks=pytest.mark.xdist_group(group))


def module_on_one_worker(group: str) -> pytest.MarkDecorator:
    """The ``pytestmark`` of a module whose tests compile kernels of their own (module
    docstring)."""
    return pytest.mark.xdist_group(group)
