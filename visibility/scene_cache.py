"""Per-scene caches of what a core builds once per scene (kd-trees, fences, octrees, edge
topology): built once per scene object, kept while the scene lives (weak keys), rebuilt when
the scene's arrays change size."""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import Any, TypeVar

from visibility.scene import Scene

T = TypeVar("T")

_CACHE: weakref.WeakKeyDictionary[Scene, dict[str, tuple[tuple[int, int], Any]]] = \
    weakref.WeakKeyDictionary()
_LOCK = threading.Lock()
# One build lock per (scene, kind): concurrent first requests build once, not once each.
_BUILDING: weakref.WeakKeyDictionary[Scene, dict[str, threading.Lock]] = \
    weakref.WeakKeyDictionary()


def per_scene(scene: Scene, kind: str, build: Callable[[Scene], T]) -> tuple[T, bool]:
    """``build(scene)`` cached per scene object under ``kind``.

    Returns
    -------
    value : the cached or freshly built value.
    built : True when it was built by this call (the caller then reports the build time).
    """
    sig = (scene.n_vertices, scene.n_triangles)
    with _LOCK:
        hit = _CACHE.get(scene, {}).get(kind)
        if hit is not None and hit[0] == sig:
            return hit[1], False
        lock = _BUILDING.setdefault(scene, {}).setdefault(kind, threading.Lock())
    with lock:
        with _LOCK:
            hit = _CACHE.get(scene, {}).get(kind)
        if hit is not None and hit[0] == sig:
            return hit[1], False
        value = build(scene)
        with _LOCK:
            _CACHE.setdefault(scene, {})[kind] = (sig, value)
        return value, True
