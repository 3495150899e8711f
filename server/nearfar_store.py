"""Near-far data shared by every session of a server, computed once and bounded in memory.

- per (scene, r2): which cells have static geometry beyond r2 (``cubemap_cells``, all cells in
  one vectorised pass, ``visibility.nearfar.cells``), small (a bool per cell) and kept;
- per (scene, cell, r2): the cell's ``NearFarSplit`` (``split``), None-free: ``False`` when the
  cell needs no cubemap, which the per-scene mask answers without touching the scene;
- per (scene, cell, r1, r2, resolution): the encoded cubemap frame (``cubemap``);
- per (scene, block): the cell whose centre each cell's cubemap is baked from (``anchors``,
  ``visibility.nearfar.cells.cubemap_anchors``): splits and cubemaps are asked for that anchor
  cell, so cells of one block share them.

Splits and cubemaps share one ``ByteLRU`` bounded by ``settings.near_far_cache_bytes``; an entry
of a cell where a connected walker stands (``in_use(scene, cell)``) is never evicted. Keys carry
the scene's geometry fingerprint, so a scene replaced under the same name never meets old data.

With a shared cache (``shared``: Redis, ``server.cache.shared``), encoded cubemaps missing
from memory are looked up there before they are baked, and what is baked is written there, so
replicas bake each cubemap once between them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np

from server.cache.codec import colours_digest, cubemap_key
from server.cache.memory import ByteLRU
from server.catalog import LoadedScene
from visibility import nearfar
from visibility.nearfar.cells import cells_needing_cubemap, cubemap_anchors


class NearFarStore:
    """Cubemap masks, splits and encoded cubemaps of loaded scenes. Thread-safe."""

    def __init__(self, max_bytes: int, in_use: Callable[[str, int], bool] | None = None,
                 shared: Any = None) -> None:
        self._in_use = in_use
        #: A ``server.cache.shared.SharedCache`` replicas share cubemaps through, or None.
        self.shared = shared
        self._colours: dict[tuple, str] = {}
        self.cache = ByteLRU(max_bytes, keep=self._keep)
        self._masks: dict[tuple, np.ndarray] = {}
        self._anchors: dict[tuple, np.ndarray] = {}
        self._lock = threading.Lock()

    def _keep(self, key: Hashable) -> bool:
        # key: (kind, scene name, fingerprint, cell, ...)
        return self._in_use is not None and self._in_use(key[1], key[3])

    # ----------------------------------------------------------------------------- per scene
    def cubemap_cells(self, loaded: LoadedScene, cfg: nearfar.NearFarConfig) -> np.ndarray:
        """(cells,) bool: the cells of ``loaded``'s grid with static geometry beyond ``cfg.r2``
        of their centre (computed once per scene and r2)."""
        key = (loaded.name, loaded.fingerprint, len(loaded.grid), cfg.r2)
        mask = self._masks.get(key)
        if mask is None:
            centers = loaded.grid.boxes.mean(axis=1)
            mask = cells_needing_cubemap(loaded.scene, centers, cfg.r2)
            mask.setflags(write=False)
            with self._lock:
                self._masks[key] = mask
        return mask

    def anchors(self, loaded: LoadedScene, block: int) -> np.ndarray:
        """(cells,) int64: the cell whose centre is each cell's cubemap centre O, for blocks of
        ``block`` x ``block`` grid columns (computed once per scene and block)."""
        key = (loaded.name, loaded.fingerprint, len(loaded.grid), int(block))
        a = self._anchors.get(key)
        if a is None:
            a = cubemap_anchors(loaded.grid, block)
            a.setflags(write=False)
            with self._lock:
                self._anchors[key] = a
        return a

    # ----------------------------------------------------------------------------- per cell
    def _split_key(self, loaded: LoadedScene, cell: int, cfg: nearfar.NearFarConfig) -> tuple:
        return ("split", loaded.name, loaded.fingerprint, int(cell), cfg.r2)

    def cached_split(self, loaded: LoadedScene, cell: int,
                     cfg: nearfar.NearFarConfig) -> nearfar.NearFarSplit | bool | None:
        """What ``split`` would answer when that costs no scene pass (False: no cubemap for this
        cell; a cached split), else None."""
        mask = self._masks.get((loaded.name, loaded.fingerprint, len(loaded.grid), cfg.r2))
        if mask is not None and not mask[cell]:
            return False
        return self.cache.get(self._split_key(loaded, cell, cfg))

    def split(self, loaded: LoadedScene, cell: int,
              cfg: nearfar.NearFarConfig) -> nearfar.NearFarSplit | bool:
        """The near-far split of ``cell`` around its centre, or False when nothing static lies
        beyond r2 (no cubemap; the cell streams its PVS as usual). Blocking: call it off the
        event loop."""
        if not self.cubemap_cells(loaded, cfg)[cell]:
            return False
        key = self._split_key(loaded, cell, cfg)
        split = self.cache.get(key)
        if split is None:
            centre = loaded.grid.boxes[cell].mean(axis=0)
            split = nearfar.split_ids(loaded.scene, centre, cfg)
            self.cache.put(key, split)
        return split

    def cubemap(self, loaded: LoadedScene, cell: int, cfg: nearfar.NearFarConfig,
                bake: Callable[[], bytes]) -> bytes:
        """The encoded cubemap frame of ``cell``: cached, else ``bake()`` (blocking: call it off
        the event loop)."""
        key = ("cubemap", loaded.name, loaded.fingerprint, int(cell), cfg.r1, cfg.r2,
               cfg.resolution)
        frame = self.cache.get(key)
        if frame is None:
            skey = self._shared_key(loaded, cell, cfg) if self.shared is not None else None
            frame = self.shared.get_blob(skey) if skey is not None else None
            if frame is None:
                frame = bake()
                if skey is not None:
                    self.shared.put_blob(skey, frame)
            self.cache.put(key, frame)
        return frame

    def _shared_key(self, loaded: LoadedScene, cell: int, cfg: nearfar.NearFarConfig) -> str:
        # A cubemap shows colours, which the fingerprint leaves out: they join the key.
        ck = (loaded.name, loaded.fingerprint)
        colours = self._colours.get(ck)
        if colours is None:
            colours = colours_digest(loaded.scene.colors)
            with self._lock:
                self._colours[ck] = colours
        return cubemap_key(loaded.fingerprint, colours, cfg.r1, cfg.r2, cfg.resolution,
                           int(cell), loaded.grid.boxes[int(cell)])

    def stats(self) -> dict[str, Any]:
        """The LRU's statistics plus the number of per-scene masks."""
        return {**self.cache.stats(), "masks": len(self._masks), "anchors": len(self._anchors)}
