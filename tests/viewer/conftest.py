"""Fixtures of the browser tests: the scene and the fixed walk (``fixed_walk``), one per module."""

from __future__ import annotations

import pytest

from tests.viewer.fixed_walk import fixed_walk, walk_scene


@pytest.fixture(scope="module")
def rooms():
    return walk_scene()


@pytest.fixture(scope="module")
def walk(rooms):
    return fixed_walk(rooms)
