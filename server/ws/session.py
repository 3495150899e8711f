"""One WebSocket client: the walker's state, the reader, and the session's lifecycle.

Three tasks per session: the reader (here) validates every client message; a pose updates the
walker's cell, its predicted motion and the prefetch list (``server.prefetch``), states the
walker's needs to the compute service (``ComputeService.want``: the current cell first, the
cells ahead by expected arrival time; ``docs/scheduling.md``), and counts a *stall* when the
walker stands in a cell whose stream the server has not finished. The streamer
(``server.ws.streams``) and the sender (``server.ws.outbox``) do the rest.
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np
from starlette.websockets import WebSocket

from protocol.codes import (
    BAD_MESSAGE_LIMIT,
    BAD_MESSAGE_WINDOW_S,
    CloseCode,
    ErrorCode,
    close_code_for,
    is_fatal,
)
from protocol.messages import Bye, Error, Hello, Pose, ProtocolError, parse_client_message
from server.auth import release_session
from server.cache import PVSKey
from server.catalog import LoadedScene
from server.prefetch import arrival_seconds, motion_direction, prefetch_order, walker_speed
from server.region import cell_key
from server.ws.dynamic import DynamicFrames
from server.ws.handshake import handshake
from server.ws.inventory import Inventory
from server.ws.nearfar import NearFarStreams
from server.ws.outbox import Outbox
from server.ws.streams import Streamer
from server.ws.transport import SessionOver, Transport
from visibility.cores.base import Core, CoreParams

if TYPE_CHECKING:
    from server.state import ServerState

#: Current cells rank by ``NEWEST_FIRST`` minus their entry time: the newest first, and all
#: after an HTTP request's rank (0, 0), which waits for its answer whoever enters a cell.
NEWEST_FIRST = 1e12

log = logging.getLogger(__name__)

#: Longest ``error.message`` sent (a core's message may quote a whole parameter).
MAX_ERROR_MESSAGE = 2000
#: Seconds between two re-rankings of a walker's needs while its cell and prefetch list stay
#: the same (a change of either re-ranks at once): poses come tens of times a second, and an
#: arrival time moves by about as much as the pose interval between them.
RERANK_INTERVAL_S = 0.25
#: The least priority of a cell ahead: the cell a walker stands in alone ranks 0.
MIN_AHEAD_PRIORITY = 1e-3


class StreamSession:
    """One WebSocket client: handshake, pose handling, the streamer and the sender (what other
    modules may use of it: ``server.state.Session``).

    The parts set up by the handshake (``loaded``, ``core``, ``params``, ``inventory``,
    ``nearfar``, ``dynamic``) are None before it.
    """

    def __init__(self, websocket: WebSocket, state: ServerState) -> None:
        self.state = state
        self.settings = state.settings
        self.id = uuid.uuid4().hex[:16]
        self.transport = Transport(websocket, self.settings, state.counters, self.id)
        #: Set when the walker's state changes: the streamer and waiting producers recheck.
        self.wake = asyncio.Event()
        self.streamer = Streamer(self)
        self.outbox = Outbox(self.transport, self.settings, state.counters, self.wake,
                             self.streamer.current_pending)
        self.loaded: LoadedScene | None = None
        self.core: Core | None = None
        self.params: CoreParams | None = None
        self.inventory: Inventory | None = None
        self.nearfar: NearFarStreams | None = None
        self.dynamic: DynamicFrames | None = None
        self.prefetch = False
        #: The token's grant (``server.tokens.Grant``), holding one of its ``max_sessions``
        #: places until the session ends; None without access control.
        self.grant: Any = None
        #: Cheap first answers for the walker's cell, refined in place (``server.ws.streams``).
        self.progressive = False
        self.progressive_why = ""
        #: Cells streamed with a first answer whose core computation goes on: (the compute
        #: service's future, the seq of the pose that asked for the cell).
        self.refining: dict[int, tuple[Any, int | None]] = {}
        #: Which first answer ("known" or "first") each refining cell holds.
        self.provisional: dict[int, str] = {}
        self.first_failed = False
        self.send_all = False
        self.cell: int | None = None
        self.cell_seq = 0
        self.cell_t0 = 0.0
        self.want: list[int] = []
        self.want_set: frozenset[int] = frozenset()
        self.skip: set[int] = set()
        #: The last cell that got a current-cell stream (an empty one confirms a cell the
        #: client already holds, e.g. prefetched or revisited).
        self.announced: int | None = None
        self.stalls = 0
        self._stall_cell: int | None = None
        self._last_pos: np.ndarray | None = None
        self._last_t: float | None = None
        #: Expected seconds to the walker's arrival in each cell of ``want`` (its rank).
        self.eta: dict[int, float] = {}
        self._ranked_at = -np.inf
        self._pinned: PVSKey | None = None
        #: Cache keys of the cells' PVS with the session's core and parameters (``key_of``).
        self._keys: dict[int, PVSKey] = {}
        #: The keys of the current cell and the prefetch list (``wants``), replaced whole.
        self._wanted_keys: frozenset[PVSKey] = frozenset()
        self._outside = False
        #: True once ``welcome`` is sent: bad messages are then answered, not fatal.
        self.welcomed = False
        #: Monotonic times of the recent bad messages (``protocol.codes.BAD_MESSAGE_LIMIT``).
        self._bad: deque[float] = deque()

    # ----------------------------------------------------------------------------- errors
    async def error(self, code: ErrorCode, message: str, seq: int | None = None) -> None:
        """Send an ``error``; when the code is fatal (in this phase: before ``welcome`` every
        bad message is) also close the connection and end the session (raises SessionOver)."""
        fatal = is_fatal(code, handshake=not self.welcomed)
        self.state.counters["errors_sent"] += 1
        log.info("session %s: %s%s: %s", self.id, code, " (fatal)" if fatal else "", message)
        await self.transport.send_message(Error(code=code, message=message[:MAX_ERROR_MESSAGE],
                                                fatal=fatal, seq=seq))
        if fatal:
            await self.transport.close(int(close_code_for(code)), str(code))
            raise SessionOver

    async def close(self, code: int = CloseCode.NORMAL, reason: str = "") -> None:
        """Close the WebSocket once (no-op when already closed)."""
        await self.transport.close(code, reason)

    # ----------------------------------------------------------------------------- lifecycle
    async def run(self) -> None:
        """Handshake, then read until the client leaves or a fatal error; never raises."""
        tasks: list[asyncio.Task] = []
        try:
            await handshake(self)
            self.state.counters["sessions_total"] += 1
            tasks.append(asyncio.create_task(self.outbox.run(), name=f"pvs-send-{self.id}"))
            tasks.append(asyncio.create_task(self.streamer.run(), name=f"pvs-stream-{self.id}"))
            await self._read_loop(tasks)
        except SessionOver:
            pass
        except Exception:
            log.exception("session %s failed", self.id)
            try:
                await self.transport.send_message(Error(code=ErrorCode.INTERNAL, fatal=True,
                                                        message="internal server error"))
            except SessionOver:
                pass
            await self.close(int(close_code_for(ErrorCode.INTERNAL)), "internal")
        finally:
            self.state.sessions.pop(self.id, None)
            # What only this walker wanted is cancelled; what others want goes on at theirs.
            self.state.compute.unwant(self.id)
            release_session(self)
            self._unpin()
            self.streamer.release_refinements()
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self.close(CloseCode.NORMAL, "")

    async def _read_loop(self, tasks: list[asyncio.Task]) -> None:
        while True:
            if any(t.done() for t in tasks):
                return
            try:
                msg = parse_client_message(await self.transport.receive())
            except ProtocolError as exc:
                code = exc.code
                if code == ErrorCode.INVALID_HELLO:
                    code = ErrorCode.DUPLICATE_HELLO
                await self._bad_message(code, exc.message, exc.seq)
                continue
            if isinstance(msg, Pose):
                await self._on_pose(msg)
            elif isinstance(msg, Bye):
                await self.close(CloseCode.NORMAL, "bye")
                return
            elif isinstance(msg, Hello):
                await self.error(ErrorCode.DUPLICATE_HELLO, "hello sent twice")

    async def _bad_message(self, code: ErrorCode, message: str, seq: int | None) -> None:
        """Answer a bad message after ``welcome`` (skipped, the session goes on) and close the
        session once a client passes ``BAD_MESSAGE_LIMIT`` of them in ``BAD_MESSAGE_WINDOW_S``
        seconds (``too_many_errors``)."""
        now = time.monotonic()
        self._bad.append(now)
        while self._bad and self._bad[0] < now - BAD_MESSAGE_WINDOW_S:
            self._bad.popleft()
        if len(self._bad) > BAD_MESSAGE_LIMIT:
            await self.error(ErrorCode.TOO_MANY_ERRORS,
                             f"more than {BAD_MESSAGE_LIMIT} bad messages in "
                             f"{BAD_MESSAGE_WINDOW_S:g} s", seq)
        await self.error(code, message, seq)

    # ----------------------------------------------------------------------------- poses
    async def _on_pose(self, pose: Pose) -> None:
        pos = np.asarray(pose.position, dtype=np.float64)
        grid = self.loaded.grid
        cell = grid.cell_of(pos)
        if cell is None:
            if not self._outside:
                self._outside = True
                await self.error(ErrorCode.OUTSIDE_GRID,
                                 f"position {list(pose.position)} is in no viewcell", pose.seq)
            return
        self._outside = False
        moved = cell != self.cell
        if moved:
            self.cell = cell
            self.cell_seq = pose.seq
            self.cell_t0 = time.perf_counter()
            self.skip.clear()
            self._pin(cell)
        if self.prefetch:
            vel = None if pose.velocity is None else np.asarray(pose.velocity)
            direction = motion_direction(vel, pos, self._last_pos)
            want = prefetch_order(grid, cell, pos, direction, self.settings.prefetch_ahead)
            moved = moved or frozenset(want) != self.want_set
            if moved or time.perf_counter() - self._ranked_at >= RERANK_INTERVAL_S:
                dt = None if self._last_t is None else pose.t - self._last_t
                speed = walker_speed(vel, pos, self._last_pos, dt)
                eta = arrival_seconds(grid.boxes[want], pos, direction, speed) if want else []
                self.eta = {c: max(float(t), MIN_AHEAD_PRIORITY)
                            for c, t in zip(want, eta, strict=True)}
                # The walker's own streams go soonest arrival first too (ties: heading).
                self.want = sorted(want, key=self.eta.__getitem__)
                self.want_set = frozenset(want)
                moved = True
        self._wanted_keys = frozenset(self.key_of(c) for c in (cell, *self.want))
        if moved:
            self._rank()
        self._last_pos = pos
        self._last_t = pose.t
        if cell not in self.inventory.done:
            self.stalls += 1
            self.state.counters["stalls"] += 1
            if self._stall_cell != cell:
                self._stall_cell = cell
                log.info("session %s: stall: pose %d in cell %d before its stream finished",
                         self.id, pose.seq, cell)
        self.wake.set()

    # ----------------------------------------------------------------------------- ranking
    def _rank(self) -> None:
        """State the walker's needs to the compute service: its cell (0, newest entered
        first: ``rank_of``), the cells ahead (expected arrival seconds)."""
        self._ranked_at = time.perf_counter()
        needs = {self.key_of(c): (self.eta[c], 0.0) for c in self.want if c in self.eta}
        needs[self.key_of(self.cell)] = self.rank_of(self.cell)
        self.state.compute.want(self.id, needs)

    def rank_of(self, cell: int) -> tuple[float, float]:
        """(priority, since) of the walker's job for ``cell`` (``server.demand``): (0,
        ``NEWEST_FIRST`` minus the ``time.perf_counter()`` instant it entered) for its cell,
        (expected arrival seconds, 0) for a cell ahead, (the walk to it at a slow pace, 0) for
        any other.

        Among current cells the one entered last goes first: its walker stays longest, so its
        answer serves the most frames, while the walker who entered first is about to leave
        (when the workers cannot keep up, the cells entered first would be computed for
        walkers who have gone)."""
        if cell == self.cell:
            return 0.0, NEWEST_FIRST - self.cell_t0
        eta = self.eta.get(cell)
        if eta is None:
            boxes = self.loaded.grid.boxes
            pos = self._last_pos if self._last_pos is not None else boxes[cell].mean(axis=0)
            eta = float(arrival_seconds(boxes[[cell]], pos, None,
                                        walker_speed(None, pos, None, None))[0])
        return max(eta, MIN_AHEAD_PRIORITY), 0.0

    # ----------------------------------------------------------------------------- shared state
    def key_of(self, cell: int) -> PVSKey:
        """The cache key of ``cell``'s PVS with the session's core and parameters (kept: a
        walker asks for the same few cells again and again)."""
        key = self._keys.get(cell)
        if key is None:
            key = self._keys[cell] = cell_key(self.loaded, cell, self.core, self.params)
        return key

    def _pin(self, cell: int) -> None:
        # The walker's current cell stays cached while it stands there (another walker
        # entering, or this one losing it to drops, then costs no recomputation).
        self._unpin()
        self._pinned = self.key_of(cell)
        self.state.compute.cache.pin(self._pinned)

    def _unpin(self) -> None:
        if self._pinned is not None:
            self.state.compute.cache.unpin(self._pinned)
            self._pinned = None

    def wants(self, key: PVSKey) -> bool:
        """Whether this session still needs the PVS of cache key ``key``: its current cell's or
        one on its prefetch list (called from worker threads: reads only an attribute replaced
        atomically)."""
        return key in self._wanted_keys

    def cubemap_cell(self, cell: int | None) -> int | None:
        """The anchor cell whose cubemap ``cell`` shares (itself without blocks); ``cell``
        before the handshake or without near-far."""
        return cell if self.nearfar is None else self.nearfar.anchor(cell)
