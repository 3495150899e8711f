"""Near-far streaming of one session: with static geometry beyond r2 of a cell's centre O, the
cell's geometry is PVS ∩ near ids ∪ far dynamic ids and the far static part goes as a cubemap
baked from O.

Cells of a block (``settings.near_far_block``) share their anchor cell's centre, split and
cubemap; splits and cubemaps are computed once per server (``store``: ``ServerState.near_far``,
bounded).
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np

from protocol.cubemap import encode_cubemap
from server.catalog import LoadedScene
from server.nearfar_store import NearFarStore
from server.settings import Settings
from visibility import nearfar


class NearFarStreams:
    """The near-far part of a session's cell streams (inactive when ``settings.near_far`` is
    off: every method then leaves the stream as it is).

    Attributes
    ----------
    cubemaps_sent : set of anchor cells whose cubemap this session was sent.
    """

    def __init__(self, settings: Settings, store: NearFarStore, loaded: LoadedScene) -> None:
        self.store = store
        self.loaded = loaded
        self.on = bool(settings.near_far)
        self.block = settings.near_far_block
        self.cfg = settings.near_far_config()
        self.cubemaps_sent: set[int] = set()

    def anchors(self) -> np.ndarray:
        """(cells,) the cell whose centre is each cell's cubemap centre (``near_far_block``)."""
        return self.store.anchors(self.loaded, self.block)

    def anchor(self, cell: int | None) -> int | None:
        """The anchor cell whose cubemap ``cell`` shares (itself without blocks or near-far)."""
        if cell is None or not self.on:
            return cell
        return int(self.anchors()[int(cell)])

    async def split(self, anchor: int) -> Any:
        """The near-far split of ``anchor`` (``visibility.nearfar.NearFarSplit``), or False when
        nothing static lies beyond r2 of its centre."""
        store = self.store
        split = store.cached_split(self.loaded, anchor, self.cfg)
        if split is None:
            split = await asyncio.to_thread(store.split, self.loaded, anchor, self.cfg)
        return split

    async def near_region_if_it_fits(self, cell: int, budget: int | None) -> np.ndarray | None:
        """The ids of the cell's near region (near + intermediate + far dynamic: everything the
        cell sends as geometry before culling) when they fit ``budget``, else None: such a cell
        needs no PVS computation, it is sent whole."""
        if budget is None or not self.on:
            return None
        split = await self.split(self.anchor(cell))
        if split is False:
            return None  # no far part: the near region is the whole scene (send_all decides)
        near = np.union1d(split.near_ids, split.far_dynamic_ids).astype(np.int32)
        return near if len(near) <= budget else None

    async def geometry(self, cell: int, ids: np.ndarray
                       ) -> tuple[np.ndarray, dict | None, bytes | None]:
        """The cell's geometry ids, its ``cell_begin.near_far`` and the cubemap frame to send
        (None when already sent or not needed); ``ids`` and None, None when inactive."""
        if not self.on:
            return ids, None, None
        anchor = self.anchor(cell)
        centre = self.loaded.grid.boxes[anchor].mean(axis=0)
        split = await self.split(anchor)
        cfg = self.cfg
        info = {"r1": cfg.r1, "r2": cfg.r2, "center": centre.tolist(),
                "cubemap": split is not False, "cubemap_cell": anchor}
        if split is False:
            return ids, info, None
        near = np.union1d(np.intersect1d(ids, split.near_ids),
                          split.far_dynamic_ids).astype(np.int32)
        if anchor in self.cubemaps_sent:
            return near, info, None
        scene = self.loaded.scene

        def bake() -> bytes:
            cube = nearfar.bake_cubemap(scene, centre, cfg)
            return encode_cubemap(anchor, cube.center, cube.colors, cube.ranges, cfg.r1, cfg.r2)

        frame = await asyncio.to_thread(self.store.cubemap, self.loaded, anchor, cfg,
                                        bake)
        return near, info, frame

    def feature(self) -> dict[str, Any]:
        """The welcome's ``features.cubemap``: which cells get cubemaps, and why."""
        if not self.on:
            return {"on": False, "why": "the server's near_far setting is off"}
        cfg = self.cfg
        # Every cell at once, computed once per scene and r2 (shared by all sessions); a cell
        # needs a cubemap when its anchor (its block's centre cell) does.
        anchors = self.anchors()
        need = self.store.cubemap_cells(self.loaded, cfg)[anchors]
        n = int(np.count_nonzero(need))
        maps = int(len(np.unique(anchors[need])))
        block = self.block
        return {"on": n > 0, "cells": n, "cubemaps": maps, "block": block,
                "r1": cfg.r1, "r2": cfg.r2,
                "why": f"{n} of {len(need)} cells have static geometry beyond r2"
                + (f", sharing {maps} cubemaps (blocks of {block} x {block} cells)"
                   if block > 1 else "")
                if n else "nothing static lies beyond r2 of any cell"}
