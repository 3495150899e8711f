"""What a server's routes and sessions share (``ServerState``) and what they may ask of a session
(``Session``, the protocol ``server.ws.session.StreamSession`` implements).

Everything above the compute layer (``app``, ``routes``, ``metrics``, ``auth``, ``ws``) imports
these types from here, and nothing here imports any of them, so ``server`` has no import cycle
(``tests/server/test_import_cycles.py``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from protocol.codes import ErrorCode
from server.cache import PVSKey
from server.catalog import LoadedScene, SceneCatalog
from server.compute import ComputeService
from server.nearfar_store import NearFarStore
from server.resolve import Resolver
from server.settings import Settings
from visibility.cores.base import Core, CoreParams

if TYPE_CHECKING:
    from server.ws.dynamic import DynamicFrames
    from server.ws.inventory import Inventory
    from server.ws.nearfar import NearFarStreams
    from server.ws.outbox import Outbox
    from server.ws.transport import Transport

log = logging.getLogger(__name__)

#: Seconds a stopping server waits for its sessions to take their 1001 close.
CLOSE_SESSIONS_TIMEOUT_S = 2.0


class Session(Protocol):
    """One WebSocket client as the handshake, the streamer, access control and ``ServerState``
    see it. The parts set up by the handshake (``loaded``, ``core``, ``params``, ``inventory``,
    ``nearfar``, ``dynamic``) are None before it."""

    id: str
    state: ServerState
    settings: Settings
    transport: Transport
    outbox: Outbox
    #: Set when the walker's state changes: the streamer and waiting producers recheck.
    wake: asyncio.Event
    loaded: LoadedScene | None
    core: Core | None
    params: CoreParams | None
    inventory: Inventory | None
    nearfar: NearFarStreams | None
    dynamic: DynamicFrames | None
    prefetch: bool
    #: The token's grant (``server.tokens.Grant``); None without access control.
    grant: Any
    progressive: bool
    progressive_why: str
    #: Cells streamed with a first answer whose core computation goes on: (the compute
    #: service's future, the seq of the pose that asked for the cell).
    refining: dict[int, tuple[Any, int | None]]
    #: Which first answer ("known" or "first") each refining cell holds.
    provisional: dict[int, str]
    first_failed: bool
    send_all: bool
    cell: int | None
    cell_seq: int
    cell_t0: float
    want: list[int]
    want_set: frozenset[int]
    skip: set[int]
    announced: int | None
    welcomed: bool

    async def error(self, code: ErrorCode, message: str, seq: int | None = None) -> None:
        """Send an ``error``; a fatal one also closes the session (raises SessionOver)."""

    def key_of(self, cell: int) -> PVSKey:
        """The cache key of ``cell``'s PVS with the session's core and parameters."""

    def wants(self, key: PVSKey) -> bool:
        """Whether the session still needs the PVS of ``key`` (from any thread)."""

    def cubemap_cell(self, cell: int | None) -> int | None:
        """The anchor cell whose cubemap ``cell`` shares."""

    def rank_of(self, cell: int) -> tuple[float, float]:
        """(priority, since) of ``cell``'s work for this walker: 0 and the time it entered
        for its current cell, else the expected seconds until it arrives."""


@dataclass
class ServerState:
    """What the routes and sessions share: settings, catalogue, compute service, the resolver
    of requests' cores (``auto``'s calibrations inside), open sessions (by id), stream
    counters and the near-far store (``near_far``: per-cell splits and cubemaps in one LRU
    bounded by ``settings.near_far_cache_bytes``)."""

    settings: Settings
    catalog: SceneCatalog
    compute: ComputeService
    resolver: Resolver
    sessions: dict[str, Session] = field(default_factory=dict)
    counters: Counter = field(default_factory=Counter)
    started: float = field(default_factory=time.monotonic)
    registry: Any = None
    near_far: NearFarStore | None = None
    #: Tokens, quotas and origins (``server.auth.Access``); None: access control off.
    access: Any = None
    #: True once the server is stopping: computations cancelled then answer shutting_down.
    stopping: bool = False
    _centroids: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.near_far is None:
            self.near_far = NearFarStore(self.settings.near_far_cache_bytes, self.walker_in,
                                         shared=self.compute.cache.shared)
        # A computation its last HTTP caller abandoned goes on while a walker wants the cell.
        self.compute.still_wanted = self.wanted

    async def stop(self) -> None:
        """Begin stopping: cancel every computation (each stops at its core's next checkpoint)
        and close every WebSocket session with a ``shutting_down`` error and 1001 (going
        away), waiting at most ``CLOSE_SESSIONS_TIMEOUT_S``."""
        if self.stopping:
            return
        self.stopping = True
        n = self.compute.cancel_all("server shutting down")
        sessions = list(self.sessions.values())
        log.info("stopping: %d computations cancelled, closing %d sessions", n, len(sessions))

        async def close(s: Session) -> None:
            with contextlib.suppress(Exception):
                await s.error(ErrorCode.SHUTTING_DOWN, "the server is shutting down")

        if sessions:
            await asyncio.wait([asyncio.ensure_future(close(s)) for s in sessions],
                               timeout=CLOSE_SESSIONS_TIMEOUT_S)

    def walker_in(self, scene: str, cell: int) -> bool:
        """Whether a connected walker stands in ``cell`` of ``scene`` now, or in a cell whose
        cubemap ``cell`` anchors (asked by caches before they evict that cell's data, from any
        thread)."""
        try:
            sessions = list(self.sessions.values())
        except RuntimeError:  # the dict changed under us: assume someone is there
            return True
        # A walker also holds the cubemap its block shares (near-far anchors).
        return any(s.loaded is not None and s.loaded.name == scene
                   and cell in (s.cell, s.cubemap_cell(s.cell)) for s in sessions)

    def wanted(self, key: PVSKey) -> bool:
        """Whether any open session still needs the PVS of cache key ``key`` (asked by worker
        threads before they start prefetch work)."""
        try:
            sessions = list(self.sessions.values())
        except RuntimeError:  # the dict changed under us: assume wanted
            return True
        return any(s.wants(key) for s in sessions)

    def centroids(self, loaded: LoadedScene) -> np.ndarray:
        """(m, 3) triangle centroids of a loaded scene, metres (computed once per scene)."""
        c = self._centroids.get(loaded.name)
        if c is None or len(c) != loaded.scene.n_triangles:
            c = loaded.scene.centroids()
            self._centroids[loaded.name] = c
        return c
