"""The ``/ws`` streaming endpoint: hello, then poses in, PVS geometry out.

One ``StreamSession`` per connection, three tasks:

- the reader validates every client message; a pose updates the walker's cell, its predicted
  motion and the prefetch list (``server.prefetch``), and counts a *stall* when the walker stands
  in a cell whose stream the server has not finished;
- the streamer picks the next job (the current cell first, then the neighbours ahead in order),
  gets its PVS from the shared compute service (cache, in-flight sharing, priority pool; prefetch
  work no walker wants any more is skipped), and streams ``cell_begin``, the triangles the client
  lacks as geometry frames, ``cell_end``. A prefetch stream yields to the current cell's between
  chunks, and when the walker needs another cell its queued frames are cut
  (``server.sendqueue``: ``cell_end.partial``). When a client's triangle ``budget`` would be
  exceeded, a ``drop`` message first names the held triangles it must drop (outside the current
  and prefetched cells' PVS first, farthest first);
- the sender drains a bounded two-lane queue of outgoing messages (``server.sendqueue``: the
  current cell's stream before prefetch streams); a send that waits longer than
  ``settings.send_timeout`` (the client stopped reading) closes the session with ``slow_client``
  (4008).

Every problem is an ``error`` message with an ``ErrorCode``; fatal ones are followed by a close
with the code from ``protocol.codes``. Nothing a client sends can take the server down:
unexpected exceptions end that session only (1011). Memory per session is bounded: a bit per
scene triangle (held), the PVS of at most ``MAX_KNOWN_PVS`` cells, and the send queue
(``send_queue_frames`` messages of at most ``max_frame_bytes``).

Outside-grid poses report ``outside_grid`` once per stay outside the grid (not once per pose).
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np
from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from protocol.codes import (
    BAD_MESSAGE_LIMIT,
    BAD_MESSAGE_WINDOW_S,
    ErrorCode,
    close_code_for,
    is_fatal,
)
from protocol.frames import chunk_count, encode_geometry, triangles_per_frame
from protocol.messages import (
    Bye,
    CellBegin,
    CellEnd,
    Drop,
    Error,
    GridInfo,
    Hello,
    Limits,
    Pose,
    ProtocolError,
    SceneInfo,
    Welcome,
    dump_message,
    parse_client_message,
)
from protocol.version import SUPPORTED_VERSIONS
from server.catalog import LoadedScene, SceneLoadFailed, UnknownSceneError
from server.compute import (
    AUTO_CORE,
    PVSResult,
    UnknownCoreError,
    UnsupportedSceneError,
    core_fits,
    offered_cores,
)
from server.dynamic import DynamicStream
from server.prefetch import choose_drops, motion_direction, prefetch_order
from server.sendqueue import Outgoing, SendQueue, StreamTag
from visibility.cores.base import PVS, Core, CoreParams

if TYPE_CHECKING:
    from server.app import ServerState

log = logging.getLogger(__name__)

#: Cells whose PVS a session remembers (current, prefetch, complete ones); beyond it, the oldest
#: complete cells are forgotten (and count as incomplete: a revisit re-sends what is missing).
MAX_KNOWN_PVS = 32


def encode_cubemap(*args: Any) -> bytes:
    """``protocol.cubemap.encode_cubemap`` (the near-far helper's encoder)."""
    from protocol.cubemap import encode_cubemap as enc

    return enc(*args)


def _near_far_module() -> Any:
    """``visibility.nearfar`` when it is installed (the near-far helper's module), else None.

    INTEGRATION POINT (near-far): with the module present and ``settings.near_far`` on, each
    cell stream carries PVS ∩ near ids ∪ far dynamic ids as geometry and a cubemap frame."""
    try:
        from visibility import nearfar
    except ImportError:
        return None
    return nearfar


class _SessionOver(Exception):
    """The session has ended (closed by us, by the peer, or the transport failed)."""


def _grid_info(loaded: LoadedScene) -> GridInfo:
    d = loaded.grid.to_dict()
    return GridInfo(cell_size=d["cell_size"], origin_xz=tuple(d["origin_xz"]), cells=d["cells"],
                    levels=d["levels"], eye_range=tuple(d["eye_range"]),
                    bounds=tuple(map(tuple, d["bounds"])))


def _scene_info(loaded: LoadedScene) -> SceneInfo:
    i = loaded.info
    return SceneInfo(
        name=loaded.name, kind=loaded.kind, triangles=i["triangles"],
        valid_triangles=i["valid_triangles"], vertices=i["vertices"], objects=i["objects"],
        spheres=i["spheres"], dynamic=i["dynamic"], states=i["states"],
        bounds=tuple(map(tuple, i["bounds"])), degenerate=i["degenerate"],
        source=i.get("source", {}),
    )


def _jsonable_params(params: CoreParams) -> dict[str, Any]:
    out = {}
    for k, v in params.as_dict().items():
        out[k] = list(v) if isinstance(v, tuple) else v
    return out


class _SlowClient(Exception):
    """A send waited past ``send_timeout``."""


_CLOSE = object()


class StreamSession:
    """One WebSocket client: handshake, pose handling, prefetch, the delta stream."""

    def __init__(self, websocket: WebSocket, state: ServerState) -> None:
        self.ws = websocket
        self.state = state
        self.settings = state.settings
        self.id = uuid.uuid4().hex[:16]
        self._send_lock = asyncio.Lock()
        self._out = SendQueue(self.settings.send_queue_frames,
                              self.settings.send_queue_frames * self.settings.max_frame_bytes)
        self._wake = asyncio.Event()
        self.loaded: LoadedScene | None = None
        self.core: Core | None = None
        self.params: CoreParams | None = None
        self.budget: int | None = None
        self.prefetch = False
        self.send_all = False
        #: held[i]: triangle i was sent and not dropped since.
        self.held: np.ndarray | None = None
        self.n_held = 0
        self.cell: int | None = None
        self.cell_seq = 0
        self.cell_t0 = 0.0
        self.want: list[int] = []
        self.want_set: frozenset[int] = frozenset()
        self.done: set[int] = set()
        self.skip: set[int] = set()
        self.pvs_of: dict[int, np.ndarray] = {}
        #: The last cell that got a current-cell stream (an empty one confirms a cell the
        #: client already holds, e.g. prefetched or revisited).
        self.announced: int | None = None
        #: Anchor cells whose cubemap this session was sent (a block shares its anchor's).
        self.cubemaps_sent: set[int] = set()
        #: Keyframes and spheres of a dynamic scene (``server.dynamic``), made on first stream.
        self.dynamic: DynamicStream | None = None
        self.stalls = 0
        self._stall_cell: int | None = None
        self._last_pos: np.ndarray | None = None
        self._pinned: tuple | None = None
        self._outside = False
        self._closed = False
        #: True once ``welcome`` is sent: bad messages are then answered, not fatal.
        self._welcomed = False
        #: Monotonic times of the recent bad messages (``protocol.codes.BAD_MESSAGE_LIMIT``).
        self._bad: deque[float] = deque()

    # ----------------------------------------------------------------------------- sending
    async def _send_now(self, data: str | bytes) -> None:
        """Send one message, waiting at most ``send_timeout`` for the client to take it."""
        if self._closed:
            raise _SessionOver
        try:
            async with self._send_lock:
                coro = (self.ws.send_bytes(data) if isinstance(data, bytes)
                        else self.ws.send_text(data))
                await asyncio.wait_for(coro, self.settings.send_timeout)
        except TimeoutError:
            raise _SlowClient from None
        except (WebSocketDisconnect, RuntimeError, OSError) as exc:
            self._closed = True
            raise _SessionOver from exc
        c = self.state.counters
        if isinstance(data, bytes):
            c["frames_sent"] += 1
            c["frame_bytes_sent"] += len(data)
        else:
            c["messages_sent"] += 1
            c["text_bytes_sent"] += len(data)

    async def _send_text(self, msg: Any) -> None:
        """Send a message now (handshake, the reader's answers)."""
        try:
            await self._send_now(dump_message(msg))
        except _SlowClient:
            await self._slow()

    async def _enqueue(self, item: Any, stream: StreamTag | None = None,
                       ids: np.ndarray | None = None, cubemap: bool = False) -> bool:
        """Queue a message (model) or frame (bytes) for the sender, in ``stream``'s lane (the
        prefetch lane for prefetch streams); waits while the queue is full (backpressure on
        the streamer).

        ``cell_begin``, ``cell_end`` and frames belong to ``stream``; ``ids`` are the triangle
        ids a geometry frame carries. Returns False, queuing nothing, when a prefetch stream's
        message waited for room while the walker's current cell became pending (the caller
        yields: ``_yield_prefetch``); ``drop``/``error`` messages are always queued.
        """
        if self._closed:
            raise _SessionOver
        if isinstance(item, bytes):
            out = Outgoing(item, "cubemap" if cubemap else "frame", stream, ids)
        elif isinstance(item, (CellBegin, CellEnd)):
            out = Outgoing(dump_message(item), "begin" if isinstance(item, CellBegin) else "end",
                           stream, partial=isinstance(item, CellEnd) and item.partial)
        else:
            out = Outgoing(dump_message(item))
        ahead = stream is not None and stream.prefetch
        if ahead and out.stream is not None:
            while not self._out.has_room(out.nbytes):
                self._wake.clear()
                if stream.cut or self._current_pending(stream.cell):
                    return False
                await self._first_of(self._out.wait_room(out.nbytes), self._wake.wait())
        await self._out.put(out, ahead)
        return True

    @staticmethod
    async def _first_of(*aws: Any) -> None:
        """Wait until the first of ``aws`` finishes; cancel the others."""
        tasks = [asyncio.ensure_future(a) for a in aws]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()

    async def _sender(self) -> None:
        try:
            while True:
                item = await self._out.get()
                await self._send_now(item.data)
                self._sent(item)
        except _SlowClient:
            await self._slow()
        except _SessionOver:
            pass

    def _sent(self, item: Outgoing) -> None:
        """Count what reached the socket (cut prefetch frames never count)."""
        c = self.state.counters
        if item.ids is not None:
            c["triangles_sent"] += len(item.ids)
        elif item.kind == "cubemap":
            c["cubemaps_sent"] += 1
        elif item.kind == "end" and not item.partial:
            c["cells_streamed"] += 1
            if item.stream is not None and item.stream.prefetch:
                c["cells_prefetched"] += 1

    def _partial_end(self, tag: StreamTag) -> Outgoing:
        """The ``cell_end(partial)`` closing a prefetch stream cut after its ``cell_begin``."""
        end = CellEnd(cell=tag.cell, seq=tag.seq, seconds=time.perf_counter() - tag.t0,
                      compute_seconds=tag.compute_seconds, cached=tag.cached, prefetch=True,
                      partial=True)
        return Outgoing(dump_message(end), "end", tag, partial=True)

    def _yield_prefetch(self) -> None:
        """Cut the queued prefetch streams (but the current cell's) so the current cell's
        messages go next: their unsent triangles count as not held, their cells as not done
        (a later stream sends what is missing)."""
        removed, cut = self._out.cut_ahead(self.cell, self._partial_end)
        unsent = [item.ids for item in removed if item.ids is not None]
        if unsent:
            # A triangle a queued frame still carries stays held (it was dropped and re-sent).
            ids = np.setdiff1d(np.concatenate(unsent), self._out.queued_ids())
            ids = ids[self.held[ids]]
            self.held[ids] = False
            self.n_held -= len(ids)
        for item in removed:
            if item.kind == "cubemap":
                self.cubemaps_sent.discard(self.cubemap_cell(item.stream.cell))
        for tag in cut:
            self.done.discard(tag.cell)
        c = self.state.counters
        c["prefetch_yields"] += len(cut)
        c["prefetch_frames_cut"] += len(unsent)

    async def _slow(self) -> None:
        self.state.counters["slow_clients"] += 1
        log.warning("session %s: client fell behind for %.1f s; closing", self.id,
                    self.settings.send_timeout)
        await self.close(int(close_code_for(ErrorCode.SLOW_CLIENT)), str(ErrorCode.SLOW_CLIENT))
        raise _SessionOver

    async def error(self, code: ErrorCode, message: str, seq: int | None = None) -> None:
        """Send an ``error``; when the code is fatal (in this phase: before ``welcome`` every
        bad message is) also close the connection and end the session (raises _SessionOver)."""
        fatal = is_fatal(code, handshake=not self._welcomed)
        self.state.counters["errors_sent"] += 1
        log.info("session %s: %s%s: %s", self.id, code, " (fatal)" if fatal else "", message)
        await self._send_text(Error(code=code, message=message[:2000], fatal=fatal, seq=seq))
        if fatal:
            await self.close(int(close_code_for(code)), str(code))
            raise _SessionOver

    async def close(self, code: int = 1000, reason: str = "") -> None:
        """Close the WebSocket once (no-op when already closed)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._send_lock.locked() and code != 1000:
                # A send is stuck on a client that does not read: do not queue behind it.
                await asyncio.wait_for(self.ws.close(code, reason[:120]), 2.0)
                return
            async with self._send_lock:
                if self.ws.application_state != WebSocketState.DISCONNECTED:
                    await asyncio.wait_for(self.ws.close(code, reason[:120]), 5.0)
        except (WebSocketDisconnect, RuntimeError, OSError, TimeoutError):
            pass

    # ----------------------------------------------------------------------------- receiving
    async def _receive(self, timeout: float | None = None) -> str:
        """The next text message. Ends the session on disconnect (and on ``timeout`` seconds of
        silence); raises ProtocolError (``binary_unsupported``, ``too_big``) for a binary or
        oversized message, which the caller answers."""
        try:
            msg = await asyncio.wait_for(self.ws.receive(), timeout)
        except TimeoutError:
            await self.error(ErrorCode.EXPECTED_HELLO, f"no hello within {timeout:g} s")
        except (WebSocketDisconnect, RuntimeError, OSError) as exc:
            self._closed = True
            raise _SessionOver from exc
        if msg["type"] == "websocket.disconnect":
            self._closed = True
            raise _SessionOver
        self.state.counters["messages_received"] += 1
        text = msg.get("text")
        if text is None:
            raise ProtocolError(ErrorCode.BINARY_UNSUPPORTED,
                                "clients send JSON text messages, not binary frames")
        limit = self.settings.max_message_bytes
        if len(text) > limit or (4 * len(text) > limit and len(text.encode()) > limit):
            raise ProtocolError(ErrorCode.TOO_BIG, f"message over {limit} bytes")
        return text

    # ----------------------------------------------------------------------------- lifecycle
    async def run(self) -> None:
        """Handshake, then read until the client leaves or a fatal error; never raises."""
        tasks: list[asyncio.Task] = []
        try:
            await self._handshake()
            self.state.counters["sessions_total"] += 1
            tasks.append(asyncio.create_task(self._sender(), name=f"pvs-send-{self.id}"))
            tasks.append(asyncio.create_task(self._stream(), name=f"pvs-stream-{self.id}"))
            await self._read_loop(tasks)
        except _SessionOver:
            pass
        except Exception:
            log.exception("session %s failed", self.id)
            try:
                await self._send_text(Error(code=ErrorCode.INTERNAL, fatal=True,
                                            message="internal server error"))
            except _SessionOver:
                pass
            await self.close(int(close_code_for(ErrorCode.INTERNAL)), "internal")
        finally:
            self.state.sessions.pop(self.id, None)
            self._unpin()
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self.close(1000, "")

    async def _handshake(self) -> None:
        # Every error below is fatal: ``self.error`` closes and raises _SessionOver.
        try:
            msg = parse_client_message(await self._receive(timeout=self.settings.hello_timeout))
        except ProtocolError as exc:
            if exc.code in (ErrorCode.BAD_JSON, ErrorCode.INVALID_HELLO, ErrorCode.TOO_BIG,
                            ErrorCode.BINARY_UNSUPPORTED):
                await self.error(exc.code, exc.message)
            await self.error(ErrorCode.EXPECTED_HELLO, f"the first message must be hello ({exc})")
        if not isinstance(msg, Hello):
            await self.error(ErrorCode.EXPECTED_HELLO,
                             f"the first message must be hello, got {msg.type}")
        if msg.version not in SUPPORTED_VERSIONS:
            await self.error(ErrorCode.VERSION_MISMATCH,
                             f"protocol version {msg.version} not supported; server speaks "
                             f"{list(SUPPORTED_VERSIONS)}")
        catalog, compute = self.state.catalog, self.state.compute
        try:
            catalog.require(msg.scene)
        except UnknownSceneError as exc:
            await self.error(ErrorCode.UNKNOWN_SCENE, str(exc.args[0] if exc.args else exc))
        if msg.core != AUTO_CORE:
            # Check the core and its parameters before paying for loading the scene.
            try:
                compute.resolve(msg.core, msg.params)
            except UnknownCoreError as exc:
                await self.error(ErrorCode.UNKNOWN_CORE, str(exc.args[0] if exc.args else exc))
            except ValueError as exc:
                await self.error(ErrorCode.BAD_PARAMS, str(exc))
        try:
            self.loaded = await asyncio.to_thread(catalog.get, msg.scene)
        except UnknownSceneError as exc:
            await self.error(ErrorCode.UNKNOWN_SCENE, str(exc.args[0] if exc.args else exc))
        except SceneLoadFailed as exc:
            await self.error(ErrorCode.SCENE_LOAD_FAILED, str(exc))
        scene = self.loaded.scene
        try:
            self.core, self.params, why = compute.resolve_for(scene, msg.core, msg.params)
        except UnknownCoreError as exc:
            await self.error(ErrorCode.UNKNOWN_CORE, str(exc.args[0] if exc.args else exc))
        except ValueError as exc:
            await self.error(ErrorCode.BAD_PARAMS, str(exc))
        ok, reason = core_fits(self.core, scene)
        if not ok:
            await self.error(ErrorCode.UNSUPPORTED_SCENE,
                             f"core {self.core.name!r} does not fit {msg.scene!r}: {reason}")
        self.budget = msg.budget
        self.prefetch = self.settings.prefetch if msg.prefetch is None else bool(msg.prefetch)
        self.held = np.zeros(scene.n_triangles, dtype=bool)
        valid = int(np.count_nonzero(scene.valid_faces))
        self.send_all = self.budget is not None and valid <= self.budget
        features = await asyncio.to_thread(self._features, why, valid)
        # Registered before the welcome leaves: a client that has its welcome finds its session
        # (pins, /sessions, metrics) already there. ``run`` removes it on every way out.
        self.state.sessions[self.id] = self
        await self._send_text(Welcome(
            session=self.id,
            scene=_scene_info(self.loaded),
            grid=_grid_info(self.loaded),
            core=self.core.name,
            params=_jsonable_params(self.params),
            budget=self.budget,
            limits=Limits(max_frame_bytes=self.settings.max_frame_bytes,
                          max_message_bytes=self.settings.max_message_bytes),
            prefetch=self.prefetch,
            features=features,
        ))
        self._welcomed = True

    def _features(self, why: str, valid: int) -> dict[str, Any]:
        """What this session's streams include and leave out, and why (the welcome's
        ``features``)."""
        scene = self.loaded.scene
        if self.send_all:
            pvs = {"on": False, "why": f"the whole scene ({valid} valid triangles) fits the "
                   f"client's budget of {self.budget}: it is sent whole, no PVS is computed"}
        else:
            pvs = {"on": True, "why": "no budget declared" if self.budget is None else
                   f"the scene ({valid} triangles) exceeds the budget of {self.budget}"
                   + ("; a cell whose near region (within r2) fits it is sent whole, "
                      "without a PVS" if self.settings.near_far else "")}
        dynamic = scene.is_dynamic
        nf = _near_far_module()
        if nf is None:
            cubemap = {"on": False, "why": "near-far module (visibility.nearfar) not installed"}
        elif not self.settings.near_far:
            cubemap = {"on": False, "why": "the server's near_far setting is off"}
        else:
            cfg = self._near_far_cfg(nf)
            # Every cell at once, computed once per scene and r2 (shared by all sessions); a
            # cell needs a cubemap when its anchor (its block's centre cell) does.
            anchors = self._anchors()
            need = self.state.near_far.cubemap_cells(self.loaded, cfg)[anchors]
            n = int(np.count_nonzero(need))
            maps = int(len(np.unique(anchors[need])))
            block = self.settings.near_far_block
            cubemap = {"on": n > 0, "cells": n, "cubemaps": maps, "block": block,
                       "r1": cfg.r1, "r2": cfg.r2,
                       "why": f"{n} of {len(need)} cells have static geometry beyond r2"
                       + (f", sharing {maps} cubemaps (blocks of {block} x {block} cells)"
                          if block > 1 else "")
                       if n else "nothing static lies beyond r2 of any cell"}
        return {
            "pvs": pvs,
            "prefetch": {"on": self.prefetch},
            "delta": {"on": True, "why": "each triangle is sent once unless dropped"},
            "dynamic_updates": {"on": dynamic, "why": "the scene has moving triangles or "
                                "spheres: their keyframes follow their geometry" if dynamic
                                else "static scene: no dynamic updates"},
            "cubemap": cubemap,
            "cores": offered_cores(scene),
            "core_choice": {"core": self.core.name, "why": why},
        }

    def _anchors(self) -> np.ndarray:
        """(cells,) the cell whose centre is each cell's cubemap centre (``near_far_block``)."""
        return self.state.near_far.anchors(self.loaded, self.settings.near_far_block)

    def cubemap_cell(self, cell: int | None) -> int | None:
        """The anchor cell whose cubemap ``cell`` shares (itself without blocks); None for
        None or without near-far."""
        if cell is None or self.loaded is None or not self.settings.near_far:
            return cell
        return int(self._anchors()[int(cell)])

    def _near_far_cfg(self, nf: Any) -> Any:
        s = self.settings
        return nf.NearFarConfig(r1=s.near_far_r1, r2=s.near_far_r2,
                                resolution=s.near_far_resolution)

    async def _read_loop(self, tasks: list[asyncio.Task]) -> None:
        while True:
            if any(t.done() for t in tasks):
                return
            try:
                msg = parse_client_message(await self._receive())
            except ProtocolError as exc:
                code = exc.code
                if code == ErrorCode.INVALID_HELLO:
                    code = ErrorCode.DUPLICATE_HELLO
                await self._bad_message(code, exc.message, exc.seq)
                continue
            if isinstance(msg, Pose):
                await self._on_pose(msg)
            elif isinstance(msg, Bye):
                await self.close(1000, "bye")
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
        if cell != self.cell:
            self.cell = cell
            self.cell_seq = pose.seq
            self.cell_t0 = time.perf_counter()
            self.skip.clear()
            self._pin(cell)
        if self.prefetch:
            vel = None if pose.velocity is None else np.asarray(pose.velocity)
            direction = motion_direction(vel, pos, self._last_pos)
            self.want = prefetch_order(grid, cell, pos, direction, self.settings.prefetch_ahead)
            self.want_set = frozenset(self.want)
        self._last_pos = pos
        if cell not in self.done:
            self.stalls += 1
            self.state.counters["stalls"] += 1
            if self._stall_cell != cell:
                self._stall_cell = cell
                log.info("session %s: stall: pose %d in cell %d before its stream finished",
                         self.id, pose.seq, cell)
        self._wake.set()

    # ----------------------------------------------------------------------------- cache pins
    def _pin(self, cell: int) -> None:
        # The walker's current cell stays cached while it stands there (another walker
        # entering, or this one losing it to drops, then costs no recomputation).
        self._unpin()
        self._pinned = self.state.compute.key(self.loaded.name, self.core, self.params, cell)
        self.state.compute.cache.pin(self._pinned)

    def _unpin(self) -> None:
        if self._pinned is not None:
            self.state.compute.cache.unpin(self._pinned)
            self._pinned = None

    def wants(self, key: tuple) -> bool:
        """Whether this session still needs the PVS of cache key ``key`` (called from worker
        threads: reads only attributes replaced atomically)."""
        return (self.loaded is not None and key[0] == self.loaded.name
                and key[2] == self.core.name and key[3] == self.params.cache_key()
                and (key[1] == self.cell or key[1] in self.want_set))

    # ----------------------------------------------------------------------------- streaming
    def _next_job(self) -> tuple[int, bool, int] | None:
        """(cell, prefetch?, rank) of the next stream: the current cell, then prefetch order."""
        c = self.cell
        if c is not None and (c not in self.done or c != self.announced) and c not in self.skip:
            return c, False, 0
        for rank, n in enumerate(self.want):
            if n not in self.done and n not in self.skip and n != c:
                return n, True, rank
        return None

    def _current_pending(self, streaming: int) -> bool:
        c = self.cell
        return c is not None and c != streaming and c not in self.done and c not in self.skip

    async def _stream(self) -> None:
        try:
            while True:
                job = self._next_job()
                if job is None:
                    self._wake.clear()
                    await self._wake.wait()
                    continue
                cell, prefetch, rank = job
                result = await self._get_pvs(cell, prefetch, rank)
                if result is not None:
                    await self._stream_cell(cell, result, prefetch)
        except _SessionOver:
            pass
        except Exception:
            log.exception("session %s: streaming failed", self.id)
            try:
                await self.error(ErrorCode.INTERNAL, "internal server error while streaming")
            except _SessionOver:
                pass

    async def _get_pvs(self, cell: int, prefetch: bool, rank: int) -> PVSResult | None:
        """The PVS of ``cell``, or None when the job was superseded (the walker moved on: the
        computation goes on in the pool and lands in the cache) or failed (error sent)."""
        name = self.loaded.name
        known = self.pvs_of.get(cell)
        if known is not None and cell in self.done:
            box = self.loaded.grid.boxes[cell].copy()
            return PVSResult(name, cell, box, self.core.name, self.params, PVS(known), True)
        if self.send_all:
            scene = self.loaded.scene
            ids = np.flatnonzero(scene.valid_faces).astype(np.int32)
            box = self.loaded.grid.boxes[cell].copy()
            return PVSResult(name, cell, box, self.core.name, self.params, PVS(ids), True)
        near = await self._near_region_if_it_fits(cell)
        if near is not None:
            self.state.counters["cells_sent_whole"] += 1
            box = self.loaded.grid.boxes[cell].copy()
            stats = {"skipped": "the near region fits the client's budget: sent whole"}
            return PVSResult(name, cell, box, self.core.name, self.params,
                             PVS(near, stats=stats), True)
        compute = self.state.compute
        key = compute.key(name, self.core, self.params, cell)
        seq = self.cell_seq if not prefetch else None
        try:
            cf = compute.submit(name, self.core, self.params, cell=cell,
                                priority=(1.0 + rank) if prefetch else 0.0,
                                wanted=(lambda: self.state.wanted(key)) if prefetch else None)
        except LookupError as exc:
            await self._job_failed(cell, prefetch, str(exc), seq)
            return None
        fut = asyncio.wrap_future(cf)
        fut.add_done_callback(lambda f: f.cancelled() or f.exception())
        job = (cell, prefetch)
        while not fut.done():
            self._wake.clear()
            waker = asyncio.ensure_future(self._wake.wait())
            await asyncio.wait({fut, waker}, return_when=asyncio.FIRST_COMPLETED)
            waker.cancel()
            nxt = self._next_job()
            if not fut.done() and (nxt is None or nxt[:2] != job):
                return None
        if fut.cancelled():
            return None
        exc = fut.exception()
        if exc is None:
            return fut.result()
        if isinstance(exc, (UnsupportedSceneError, LookupError, SceneLoadFailed)):
            msg = str(exc)
        else:
            log.error("session %s: PVS of %s cell %d failed: %r", self.id, name, cell, exc)
            msg = f"PVS of cell {cell} failed: {type(exc).__name__}: {exc}"
        await self._job_failed(cell, prefetch, msg, seq)
        return None

    async def _job_failed(self, cell: int, prefetch: bool, msg: str, seq: int | None) -> None:
        self.skip.add(cell)
        if not prefetch:
            await self.error(ErrorCode.COMPUTE_FAILED, msg, seq)

    def _remember(self, cell: int, ids: np.ndarray) -> None:
        self.pvs_of[cell] = ids
        if len(self.pvs_of) <= MAX_KNOWN_PVS:
            return
        keep = {self.cell, cell, *self.want}
        for c in list(self.pvs_of):
            if len(self.pvs_of) <= MAX_KNOWN_PVS:
                break
            if c not in keep:
                del self.pvs_of[c]
                self.done.discard(c)

    async def _make_room(self, cell: int, ids: np.ndarray, new: np.ndarray,
                         prefetch: bool, seq: int, stream: StreamTag | None = None) -> bool:
        """Drop held triangles so ``new`` fits the budget; False when a prefetch cannot fit
        without touching the current cell's PVS (the prefetch is then skipped)."""
        need = self.n_held + len(new) - (self.budget or 0)
        if self.budget is None or need <= 0:
            return True
        n = len(self.held)
        protect = np.zeros(n, dtype=bool)
        protect[ids] = True
        cur = self.pvs_of.get(self.cell)
        if cur is not None:
            protect[cur] = True
        spare = np.zeros(n, dtype=bool)
        for c in self.want:
            p = self.pvs_of.get(c)
            if p is not None:
                spare[p] = True
        if prefetch:
            # A prefetch may only push out what no nearby cell needs.
            protect |= spare
            spare[:] = False
        box = self.loaded.grid.boxes[self.cell if self.cell is not None else cell]
        drops = choose_drops(self.held, need, protect, spare, self.state.centroids(self.loaded),
                             box.mean(axis=0))
        if len(drops) < need:
            if prefetch:
                self.skip.add(cell)
                return False
            await self._enqueue(Error(
                code=ErrorCode.OVER_BUDGET, seq=seq,
                message=f"PVS of cell {cell} holds {len(ids)} triangles; with the current "
                f"cell's it exceeds the budget of {self.budget}"), stream)
            self.state.counters["errors_sent"] += 1
        if len(drops):
            dmask = np.zeros(n, dtype=bool)
            dmask[drops] = True
            self.held[drops] = False
            self.n_held -= len(drops)
            gone = sorted(c for c in self.done if dmask[self.pvs_of[c]].any())
            self.done.difference_update(gone)
            self.state.counters["triangles_dropped"] += len(drops)
            await self._enqueue(Drop(ids=np.sort(drops).tolist(), cells=gone), stream)
        return True

    async def _split(self, nf: Any, cell: int) -> Any:
        """The near-far split of ``cell`` (``visibility.nearfar.NearFarSplit``), or False when
        nothing static lies beyond r2 of its centre; shared by every session of the server
        (``ServerState.near_far``, bounded)."""
        store, cfg = self.state.near_far, self._near_far_cfg(nf)
        split = store.cached_split(self.loaded, cell, cfg)
        if split is None:
            split = await asyncio.to_thread(store.split, self.loaded, cell, cfg)
        return split

    async def _near_region_if_it_fits(self, cell: int) -> np.ndarray | None:
        """The ids of the cell's near region (near + intermediate + far dynamic: everything the
        cell sends as geometry before culling) when they fit the client's budget, else None:
        such a cell needs no PVS computation, it is sent whole."""
        nf = _near_far_module() if self.settings.near_far else None
        if self.budget is None or nf is None:
            return None
        split = await self._split(nf, self.cubemap_cell(cell))
        if split is False:
            return None  # no far part: the near region is the whole scene (send_all decides)
        near = np.union1d(split.near_ids, split.far_dynamic_ids).astype(np.int32)
        return near if len(near) <= self.budget else None

    async def _near_far(self, nf: Any, cell: int, ids: np.ndarray
                        ) -> tuple[np.ndarray, dict | None, bytes | None]:
        """INTEGRATION POINT (near-far): the cell's geometry ids, its ``cell_begin.near_far``
        and the cubemap frame to send (None when already sent or not needed).

        With static geometry beyond r2 of the cell centre O: geometry = PVS ∩ near ids ∪ far
        dynamic ids; the far static part goes as a cubemap baked from O (cached per scene, cell
        and configuration)."""
        scene = self.loaded.scene
        cfg = self._near_far_cfg(nf)
        # The block's anchor cell: its centre is O, its split and cubemap are the block's.
        anchor = self.cubemap_cell(cell)
        centre = self.loaded.grid.boxes[anchor].mean(axis=0)
        split = await self._split(nf, anchor)
        info = {"r1": cfg.r1, "r2": cfg.r2, "center": centre.tolist(),
                "cubemap": split is not False, "cubemap_cell": anchor}
        if split is False:
            return ids, info, None
        near = np.union1d(np.intersect1d(ids, split.near_ids),
                          split.far_dynamic_ids).astype(np.int32)
        if anchor in self.cubemaps_sent:
            return near, info, None
        def bake() -> bytes:
            cube = nf.bake_cubemap(scene, centre, cfg)
            return encode_cubemap(anchor, cube.center, cube.colors, cube.ranges, cfg.r1,
                                  cfg.r2)

        frame = await asyncio.to_thread(self.state.near_far.cubemap, self.loaded, anchor, cfg,
                                        bake)
        return near, info, frame

    async def _queue_dynamic(self, make: Any, tag: StreamTag) -> bool:
        """Queue the keyframe or sphere frames ``make(self.dynamic)`` encodes (off the event
        loop) in stream ``tag``; nothing for a static scene. False when a prefetch stream had to
        yield meanwhile (it is cut: the caller stops)."""
        if self.dynamic is None:
            self.dynamic = await asyncio.to_thread(DynamicStream, self.loaded.scene,
                                                   self.settings.max_frame_bytes)
            if self.dynamic.why_not:
                log.warning("session %s: no keyframe frames: %s", self.id, self.dynamic.why_not)
        if not self.dynamic.active:
            return True
        frames = await asyncio.to_thread(make, self.dynamic)
        for frame in frames:
            if not await self._enqueue(frame, tag):
                self._yield_prefetch()
                return False
            self.state.counters["dynamic_frames_sent"] += 1
        return True

    async def _stream_cell(self, cell: int, result: PVSResult, prefetch: bool) -> None:
        """Queue ``cell``'s stream: ``cell_begin``, the triangles the client lacks as geometry
        frames, the cubemap (near-far), ``cell_end``. A current cell's stream first cuts the
        queued prefetch streams; a prefetch stream stops (cut) when the walker needs another
        cell."""
        seq = self.cell_seq
        t0 = self.cell_t0 if not prefetch else time.perf_counter()
        if not prefetch:
            self.announced = cell
            self._yield_prefetch()
        tag = StreamTag(cell, prefetch, seq, t0, result.seconds, result.cached)
        ids = result.pvs.triangle_ids
        near_far, cube = None, None
        nf = _near_far_module() if self.settings.near_far else None
        if nf is not None:
            ids, near_far, cube = await self._near_far(nf, cell, ids)
        self._remember(cell, ids)
        new = ids[~self.held[ids]]
        if not prefetch and self.budget is not None and len(ids) > self.budget:
            await self._enqueue(Error(
                code=ErrorCode.OVER_BUDGET, seq=seq,
                message=f"PVS of cell {cell} holds {len(ids)} triangles, over the budget "
                f"of {self.budget}"), tag)
            self.state.counters["errors_sent"] += 1
        if not await self._make_room(cell, ids, new, prefetch, seq, tag):
            return
        max_bytes = self.settings.max_frame_bytes
        count = chunk_count(len(new), max_bytes)
        begin = CellBegin(cell=cell, seq=seq, triangles=len(ids), new=len(new), chunks=count,
                          prefetch=prefetch, near_far=near_far)
        if not await self._enqueue(begin, tag):
            self._yield_prefetch()  # a prefetch stream waited for room: the walker moved on
            return
        spheres = result.pvs.sphere_ids
        if not await self._queue_dynamic(lambda d: d.spheres_for(spheres, cell, seq, tag), tag):
            return
        per = triangles_per_frame(max_bytes)
        scene = self.loaded.scene
        for i in range(count):
            if prefetch and self._current_pending(cell):
                self._yield_prefetch()  # the walker needs another cell now
                return
            part = new[i * per:(i + 1) * per]
            # A moving triangle's keyframes go just before its geometry (``server.dynamic``).
            if not await self._queue_dynamic(lambda d, p=part: d.keyframes_for(p, cell, seq),
                                             tag):
                return
            # Encoding a full frame takes milliseconds: do it off the loop.
            frame = await asyncio.to_thread(
                lambda p=part, k=i: encode_geometry(
                    p, scene.triangles(p), scene.colors[p], cell=cell, seq=seq, index=k,
                    count=count,
                )
            )
            if not await self._enqueue(frame, tag, ids=part):
                self._yield_prefetch()
                return
            self.held[part] = True
            self.n_held += len(part)
        if cube is not None:
            if not await self._enqueue(cube, tag, cubemap=True):
                self._yield_prefetch()
                return
            self.cubemaps_sent.add(self.cubemap_cell(cell))
        end = CellEnd(cell=cell, seq=seq, seconds=time.perf_counter() - t0,
                      compute_seconds=result.seconds, cached=result.cached, prefetch=prefetch,
                      partial=False)
        if not await self._enqueue(end, tag):
            self._yield_prefetch()
            return
        self.done.add(cell)


async def websocket_endpoint(websocket: WebSocket) -> None:
    """The ``/ws`` route: accept, run one ``StreamSession``."""
    await websocket.accept()
    await StreamSession(websocket, websocket.app.state.server).run()
