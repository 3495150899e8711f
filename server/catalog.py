"""The scene catalogue: which scenes the server serves, loaded lazily and once each.

Scenes come from three places: files in ``settings.scenes_dir`` (named by file stem), generators
(``settings.generated``, named by generator) and in-memory scenes registered by code (tests,
embedding). Listing never loads anything; ``get`` loads a scene and builds its viewcell grid the
first time it is asked for, under a per-scene lock so concurrent requests load it once while other
scenes stay available. A name is looked up only in the catalogue, never turned into a path, so no
request can reach a file outside the scenes folder; and no answer shows a path either: a load
failure names the scene and what is wrong (the full path goes to the server log only).

Scene files are loaded within ``settings.max_scene_triangles`` and ``max_scene_bytes``; a file
over either is refused with a message naming the scene, the limit and the setting.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from protocol.frames import common_origin
from server.heap import release_freed_memory
from server.settings import Settings
from visibility.scene import FACE_BLOCK, Scene, scene_fingerprint
from visibility.scene_analysis import scene_is_2_5d
from visibility.scene_cache import per_scene
from visibility.viewcells import ViewcellGrid

if TYPE_CHECKING:
    from visibility.loaders import SceneTooLarge

log = logging.getLogger(__name__)

SceneKind = Literal["file", "generated", "memory"]
_FALLBACK_EXTENSIONS = (".glb", ".gltf", ".obj", ".ply")


class UnknownSceneError(LookupError):
    """No scene of this name in the catalogue (or a name that could never be one)."""


class SceneLoadFailed(RuntimeError):
    """A catalogued scene that could not be loaded (corrupt file, generator error, a file over
    the server's limits). The message names the scene, never a file-system path."""

#: Longest reason a load failure quotes from the loader (characters): an exception's text can be
#: a whole parser dump.
MAX_REASON_CHARS = 300
#: The setting and environment variable behind each ``load_scene`` limit.
_LIMIT_SETTINGS = {"max_triangles": ("max_scene_triangles", "PVS_MAX_SCENE_TRIANGLES"),
                   "max_bytes": ("max_scene_bytes", "PVS_MAX_SCENE_BYTES")}


def scene_extensions() -> tuple[str, ...]:
    """File extensions served from the scenes folder (the loader's, lower case)."""
    try:
        from visibility.loaders import SCENE_EXTENSIONS
    except ImportError:
        return _FALLBACK_EXTENSIONS
    return tuple(SCENE_EXTENSIONS)


@dataclass(frozen=True)
class LoadedScene:
    """A loaded scene with its grid and a JSON-friendly description (``info``)."""

    name: str
    kind: SceneKind
    scene: Scene
    grid: ViewcellGrid
    info: dict

    @cached_property
    def fingerprint(self) -> str:
        """``visibility.scene.scene_fingerprint`` of the scene (hashed once per scene object,
        shared with the per-scene builds' store)."""
        return per_scene(self.scene, "fingerprint", scene_fingerprint)[0]


@dataclass
class _Entry:
    name: str
    kind: SceneKind
    path: Path | None = None
    triangles: int | None = None
    loaded: LoadedScene | None = None
    pending: Scene | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)


def check_scene_name(name: str) -> str:
    """``name`` when it could name a catalogue entry; UnknownSceneError for names holding path
    separators, "..", control characters, or nothing."""
    if (
        not isinstance(name, str)
        or not name
        or len(name) > 256
        or name in (".", "..")
        or ".." in name
        or any(c in name for c in "/\\:")
        or any(ord(c) < 32 for c in name)
    ):
        raise UnknownSceneError(f"unknown scene {str(name)[:80]!r}")
    return name


class SceneCatalog:
    """Scenes by name, loaded on first use. Thread-safe."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        #: Called with each scene once it has loaded (outside the loading lock): the server
        #: starts the scene's per-scene builds there (``ServerState.prepare_scene``).
        self.on_load: Callable[[LoadedScene], None] | None = None
        self._lock = threading.Lock()
        self._entries: dict[str, _Entry] = {}
        for name, n in settings.generated.items():
            self._entries[name] = _Entry(name, "generated", triangles=int(n))
        self.refresh()

    # ----------------------------------------------------------------------------- listing
    def refresh(self) -> None:
        """Pick up scene files added to the scenes folder since the last scan."""
        folder = self.settings.scenes_dir
        if folder is None:
            return
        folder = Path(folder)
        if not folder.is_dir():
            log.warning("scenes folder %s does not exist", folder)
            return
        root = folder.resolve()
        exts = scene_extensions()
        found: dict[str, Path] = {}
        for p in sorted(folder.iterdir()):
            ext = p.suffix.lower()
            if ext not in exts or not p.is_file():
                continue
            if not p.resolve().is_relative_to(root):
                log.warning("skipping %s: it points outside %s", p, root)
                continue
            prev = found.get(p.stem)
            # Same stem in two formats: the loader's preferred order decides.
            if prev is None or exts.index(ext) < exts.index(prev.suffix.lower()):
                found[p.stem] = p
        with self._lock:
            for stem, path in found.items():
                if check_name_ok(stem):
                    e = self._entries.get(stem)
                    if e is None or (e.kind == "generated" and e.loaded is None):
                        if e is not None:
                            log.warning("scene file %s hides the generator %r", path, stem)
                        self._entries[stem] = _Entry(stem, "file", path=path)

    def names(self) -> list[str]:
        """Every scene name, sorted (nothing is loaded)."""
        with self._lock:
            return sorted(self._entries)

    def listing(self) -> list[dict]:
        """[{name, kind, loaded, triangles}] for every scene; triangles is the loaded count, the
        requested count for an unloaded generated scene, else None."""
        self.refresh()
        with self._lock:
            entries = sorted(self._entries.values(), key=lambda e: e.name)
        out = []
        for e in entries:
            tris = e.loaded.scene.n_triangles if e.loaded else e.triangles
            out.append({"name": e.name, "kind": e.kind, "loaded": e.loaded is not None,
                        "triangles": tris})
        return out

    def is_loaded(self, name: str) -> bool:
        with self._lock:
            e = self._entries.get(name)
        return e is not None and e.loaded is not None

    def __contains__(self, name: object) -> bool:
        with self._lock:
            return name in self._entries

    # ----------------------------------------------------------------------------- loading
    def register(self, name: str, scene: Scene, grid: ViewcellGrid | None = None) -> None:
        """Serve an in-memory scene under ``name`` (replacing any entry of that name). The grid
        defaults to ``ViewcellGrid.for_scene(scene, cell_size)``, built on first use."""
        check_scene_name(name)
        entry = _Entry(name, "memory", pending=scene)
        if grid is not None:
            entry.loaded = self._describe(name, "memory", scene, grid)
        with self._lock:
            self._entries[name] = entry

    def _entry(self, name: str) -> _Entry:
        check_scene_name(name)
        with self._lock:
            e = self._entries.get(name)
        if e is None and self.settings.scenes_dir is not None:
            self.refresh()
            with self._lock:
                e = self._entries.get(name)
        if e is None:
            raise UnknownSceneError(f"unknown scene {name!r}")
        return e

    def require(self, name: str) -> None:
        """Return quietly when ``name`` is in the catalogue (loaded or not); UnknownSceneError
        otherwise. Never loads."""
        self._entry(name)

    def get(self, name: str) -> LoadedScene:
        """The loaded scene ``name``: loads it (and builds its grid) on first use.

        Raises UnknownSceneError for names not in the catalogue, SceneLoadFailed when loading
        fails (a later call tries again).
        """
        e = self._entry(name)
        if e.loaded is not None:
            return e.loaded
        fresh = None
        with e.lock:
            if e.loaded is None:
                try:
                    e.loaded = fresh = self._load(e)
                    e.pending = None
                finally:
                    # A load frees its temporaries (as much as the scene again, or more): give
                    # those pages back instead of keeping them resident in the heap.
                    release_freed_memory()
            loaded = e.loaded
        if fresh is not None and self.on_load is not None:
            try:
                self.on_load(fresh)
            except Exception:  # the scene is served whatever its preparation does
                log.exception("preparing scene %r failed", e.name)
        return loaded

    async def load(self, name: str) -> LoadedScene:
        """``get`` from the event loop: the one way the routes and sessions look a scene up by
        name. An unknown name fails at once (UnknownSceneError); loading, which can take
        seconds (file parse, grid, walk-area detection), runs in a thread (SceneLoadFailed)."""
        self.require(name)
        return await asyncio.to_thread(self.get, name)

    def _load(self, e: _Entry) -> LoadedScene:
        from visibility.loaders import SceneTooLarge

        try:
            if e.kind == "file":
                from visibility.loaders import load_scene

                scene = load_scene(e.path, max_triangles=self.settings.max_scene_triangles,
                                   max_bytes=self.settings.max_scene_bytes)
            elif e.kind == "generated":
                from visibility.generators import make_scene

                scene = make_scene(e.name, triangles=e.triangles, seed=0)
            else:
                scene = e.pending
            size = self.settings.cell_size_for(scene.meta.get("cell_size"))
            grid = ViewcellGrid.for_scene(scene, float(size))
        except SceneTooLarge as exc:
            log.warning("scene %r (%s) refused: %s", e.name, e.path, exc)
            raise SceneLoadFailed(over_limit_message(e.name, exc)) from exc
        except Exception as exc:  # loaders and generators raise many types
            log.exception("loading scene %r (%s) failed", e.name, e.path or e.kind)
            raise SceneLoadFailed(f"scene {e.name!r} could not be loaded: "
                                  f"{self._public_reason(exc, e)}") from exc
        scene.name = e.name
        loaded = self._describe(e.name, e.kind, scene, grid)
        if e.kind == "generated":
            loaded.info["source"] = {"generator": e.name, "triangles": int(e.triangles),
                                     "seed": 0}
        elif e.kind == "file":
            loaded.info["source"] = {"file": e.path.name}
        log.info("loaded scene %r (%s): %d triangles, %d cells", e.name, e.kind,
                 scene.n_triangles, len(grid))
        return loaded

    def _public_reason(self, exc: BaseException, e: _Entry) -> str:
        """What ``exc`` says, fit for a client: no folders (the scene's, the scenes folder, any
        absolute path), at most ``MAX_REASON_CHARS`` characters."""
        from visibility.loaders import strip_paths

        folder = e.path.parent if e.path is not None else None
        text = strip_paths(str(exc), folder, self.settings.scenes_dir) or type(exc).__name__
        return text if len(text) <= MAX_REASON_CHARS else text[:MAX_REASON_CHARS - 3] + "..."

    @staticmethod
    def _describe(name: str, kind: SceneKind, scene: Scene, grid: ViewcellGrid) -> LoadedScene:
        info = scene.summary()
        info["name"] = name
        info["kind"] = kind
        # Decided here, off the event loop, once per loaded scene (scene_is_2_5d caches it).
        flat, how = scene_is_2_5d(scene)
        info["is_2_5d"] = {"value": flat, "source": how["source"], "why": how["reason"]}
        return LoadedScene(name, kind, scene, grid, info)


def over_limit_message(name: str, exc: SceneTooLarge) -> str:
    """The message of a scene file over a size limit (``visibility.loaders.SceneTooLarge``):
    the scene, what its file is, the limit and the setting that raises it."""
    setting = _LIMIT_SETTINGS.get(exc.param)
    how = f" (setting {setting[0]}, env {setting[1]})" if setting else ""
    return (f"scene {name!r} is too large to load: its file {exc.detail}, over this server's "
            f"limit of {exc.limit}{how}")


def check_name_ok(name: str) -> bool:
    """Whether ``check_scene_name`` accepts ``name``."""
    try:
        check_scene_name(name)
    except UnknownSceneError:
        return False
    return True


_ORIGINS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def wire_origin(scene: Scene) -> np.ndarray:
    """(3,) float64 origin of every geometry frame sent of ``scene`` (``common_origin`` of its
    vertices), computed once per scene: frames of different cells hold shared vertices too."""
    hit = _ORIGINS.get(scene)
    if hit is None:
        hit = _ORIGINS[scene] = _blockwise_origin(scene.vertices)
    return hit


def _blockwise_origin(vertices: np.ndarray, block: int = FACE_BLOCK) -> np.ndarray:
    """``common_origin(vertices)``, equal to it, from the bounds of its finite rows taken by
    blocks: no copy of the finite vertices is made."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for s in range(0, len(vertices), block):
        v = vertices[s:s + block]
        v = v[np.isfinite(v).all(axis=1)]
        if len(v):
            lo = np.minimum(lo, v.min(axis=0))
            hi = np.maximum(hi, v.max(axis=0))
    if not np.all(lo <= hi):
        return common_origin(np.zeros((0, 3)))
    return common_origin(np.stack([lo, hi]))
