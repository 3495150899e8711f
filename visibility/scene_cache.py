"""Per-scene caches of what is built once per scene (the spatial hierarchy, kd-trees, fences,
octrees, edge topology): built once per scene object, kept while the scene lives (weak keys),
rebuilt when the scene's arrays change size.

A build may also be kept on disk (``Persist``) under a folder set once per process
(``set_store``; the server's ``cache_dir``), named by the scene's content hash
(``visibility.scene.scene_fingerprint``), so a restart reads it instead of building it again.
Builds may run in the background (``build_in_background``): a caller that must not wait asks
``peek`` and goes on without the structure until it is there.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import weakref
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from visibility.scene import Scene, scene_fingerprint

T = TypeVar("T")

log = logging.getLogger(__name__)

_CACHE: weakref.WeakKeyDictionary[Scene, dict[str, tuple[tuple[int, int], Any]]] = \
    weakref.WeakKeyDictionary()
_LOCK = threading.Lock()
# One build lock per (scene, kind): concurrent first requests build once, not once each.
_BUILDING: weakref.WeakKeyDictionary[Scene, dict[str, threading.Lock]] = \
    weakref.WeakKeyDictionary()
_STORE: Path | None = None
# numpy parses each ``.npy`` header with ``ast.literal_eval``, and CPython 3.11's AST
# constructor keeps its recursion depth per interpreter, not per thread: two threads parsing at
# once (a garbage collection switching threads mid-parse) can raise SystemError ("AST
# constructor recursion depth mismatch") on a sound file (python/cpython#106905's counter).
_NPZ_LOCK = threading.Lock()


@dataclass(frozen=True)
class Persist(Generic[T]):
    """How a per-scene build is kept on disk: ``save(value, path)`` writes it, ``load(path,
    scene)`` reads it back (None when the file is missing, outdated or does not fit the scene);
    ``version`` names the format, so another format is built again, never read."""

    save: Callable[[T, Path], None]
    load: Callable[[Path, Scene], T | None]
    version: str


def save_npz(path: str | os.PathLike, **arrays: Any) -> None:
    """Write ``arrays`` to ``path`` (``.npz``) through a temporary file renamed into place, so
    a reader (a restart, another process) never meets half a file; makes the folder."""
    import numpy as np

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    tmp.replace(path)


def load_npz(path: str | os.PathLike) -> dict[str, Any]:
    """Every array of the ``.npz`` file at ``path`` (pickles refused), read in full under one
    process-wide lock so threads reading at once never meet numpy's header parsing together
    (``_NPZ_LOCK``). Raises what ``numpy.load`` raises for a missing, truncated or foreign
    file, and KeyError, ValueError or EOFError for a damaged member."""
    import numpy as np

    with _NPZ_LOCK, np.load(path, allow_pickle=False) as z:
        return {name: z[name] for name in z.files}


def set_store(folder: str | os.PathLike | None) -> None:
    """Keep persistent per-scene builds under ``folder`` (None: in memory only)."""
    global _STORE
    _STORE = None if folder is None else Path(folder)


def store_path(scene: Scene, kind: str, persist: Persist) -> Path | None:
    """Where ``kind`` of ``scene`` is kept on disk (None without a store)."""
    if _STORE is None:
        return None
    fp, _ = per_scene(scene, "fingerprint", scene_fingerprint)
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", kind)
    return _STORE / "scenes" / fp / f"{safe}.{persist.version}.npz"


def peek(scene: Scene, kind: str) -> Any | None:
    """The build of ``kind`` for ``scene`` when it is there, else None; never builds."""
    sig = (scene.n_vertices, scene.n_triangles)
    with _LOCK:
        hit = _CACHE.get(scene, {}).get(kind)
    return hit[1] if hit is not None and hit[0] == sig else None


def in_progress(scene: Scene, kind: str) -> bool:
    """Whether a build of ``kind`` for ``scene`` is running now."""
    with _LOCK:
        lock = _BUILDING.get(scene, {}).get(kind)
    return lock is not None and lock.locked()


def per_scene(scene: Scene, kind: str, build: Callable[[Scene], T],
              persist: Persist[T] | None = None) -> tuple[T, bool]:
    """``build(scene)`` cached per scene object under ``kind`` (and on disk with ``persist``
    when a store is set).

    Returns
    -------
    value : the cached, loaded or freshly built value.
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
        path = store_path(scene, kind, persist) if persist is not None else None
        value = None
        if path is not None and path.is_file():
            try:
                value = persist.load(path, scene)
            except Exception as exc:  # a bad file is rebuilt, never trusted
                log.warning("per-scene %s of %s unreadable (%s): building it", kind,
                            scene.name, type(exc).__name__)
        built = value is None
        if built:
            value = build(scene)
            if path is not None:
                try:
                    persist.save(value, path)
                except OSError as exc:  # a full disk costs a rebuild later, nothing else
                    log.warning("could not keep per-scene %s of %s: %s", kind, scene.name,
                                type(exc).__name__)
        with _LOCK:
            _CACHE.setdefault(scene, {})[kind] = (sig, value)
        return value, built


@dataclass(frozen=True)
class Build:
    """One per-scene build to run: ``per_scene(scene, kind, build, persist)``."""

    kind: str
    build: Callable[[Scene], Any]
    persist: Persist | None = None


def build_in_background(scene: Scene, builds: Iterable[Build], nice: int = 0,
                        on_done: Callable[[str, float], None] | None = None) -> threading.Thread:
    """Run ``builds`` one after another on a daemon thread (``nice`` lowers its CPU priority on
    Linux), so nothing waits for them; a failure is logged and skips that build. ``on_done``
    gets (kind, seconds) after each build that succeeds. Returns the thread (started)."""
    import time

    todo = list(builds)

    def run() -> None:
        if nice > 0 and hasattr(os, "setpriority") and hasattr(threading, "get_native_id"):
            try:
                tid = threading.get_native_id()
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)
            except OSError:
                pass
        for b in todo:
            t0 = time.perf_counter()
            try:
                per_scene(scene, b.kind, b.build, b.persist)
            except Exception:
                log.exception("background build of %s for %s failed", b.kind, scene.name)
                continue
            if on_done is not None:
                on_done(b.kind, time.perf_counter() - t0)

    th = threading.Thread(target=run, name=f"pvs-build-{scene.name}", daemon=True)
    th.start()
    return th
