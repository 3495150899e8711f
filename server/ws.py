"""The ``/ws`` streaming endpoint: hello, then poses in, PVS geometry out.

One ``StreamSession`` per connection. A reader loop validates every client message; when a pose
enters a new cell, the cell goes on a queue that a streamer task drains in order: compute the PVS
off the event loop, send ``cell_begin``, the PVS triangles this session has not received yet as
binary geometry frames, then ``cell_end``. Every problem is an ``error`` message with an
``ErrorCode``; fatal ones are followed by a close with the code from ``protocol.codes``. Nothing a
client sends can take the server down: unexpected exceptions end that session only (1011).

Outside-grid poses report ``outside_grid`` once per stay outside the grid (not once per pose).
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from typing import TYPE_CHECKING, Any

import numpy as np
from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from protocol.codes import ErrorCode, close_code_for, is_fatal
from protocol.frames import chunk_count, encode_geometry, triangles_per_frame
from protocol.messages import (
    Bye,
    CellBegin,
    CellEnd,
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
from server.compute import UnknownCoreError, UnsupportedSceneError
from visibility.cores.base import Core, CoreParams

if TYPE_CHECKING:
    from server.app import ServerState

log = logging.getLogger(__name__)


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


class StreamSession:
    """One WebSocket client: handshake, pose handling and the PVS stream."""

    def __init__(self, websocket: WebSocket, state: ServerState) -> None:
        self.ws = websocket
        self.state = state
        self.settings = state.settings
        self.id = uuid.uuid4().hex[:16]
        self._send_lock = asyncio.Lock()
        self._queue: asyncio.Queue[tuple[int, int, float]] = asyncio.Queue()
        self.loaded: LoadedScene | None = None
        self.core: Core | None = None
        self.params: CoreParams | None = None
        self.budget: int | None = None
        self.sent: np.ndarray | None = None
        self.cell: int | None = None
        self._outside = False
        self._closed = False

    # ----------------------------------------------------------------------------- sending
    async def _send_text(self, msg: Any) -> None:
        if self._closed:
            raise _SessionOver
        text = dump_message(msg)
        try:
            async with self._send_lock:
                await self.ws.send_text(text)
        except (WebSocketDisconnect, RuntimeError, OSError) as exc:
            self._closed = True
            raise _SessionOver from exc
        self.state.counters["messages_sent"] += 1

    async def _send_frame(self, frame: bytes) -> None:
        if self._closed:
            raise _SessionOver
        try:
            async with self._send_lock:
                await self.ws.send_bytes(frame)
        except (WebSocketDisconnect, RuntimeError, OSError) as exc:
            self._closed = True
            raise _SessionOver from exc
        self.state.counters["frames_sent"] += 1
        self.state.counters["frame_bytes_sent"] += len(frame)

    async def error(self, code: ErrorCode, message: str, seq: int | None = None) -> None:
        """Send an ``error``; when the code is fatal also close the connection and end the
        session (raises _SessionOver)."""
        fatal = is_fatal(code)
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
            async with self._send_lock:
                if self.ws.application_state != WebSocketState.DISCONNECTED:
                    await self.ws.close(code, reason[:120])
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass

    # ----------------------------------------------------------------------------- receiving
    async def _receive(self, timeout: float | None = None) -> str:
        """The next text message; ends the session on disconnect, binary or oversized frames."""
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
            await self.error(ErrorCode.BINARY_UNSUPPORTED,
                             "clients send JSON text messages, not binary frames")
        limit = self.settings.max_message_bytes
        if len(text) > limit or (4 * len(text) > limit and len(text.encode()) > limit):
            await self.error(ErrorCode.TOO_BIG, f"message over {limit} bytes")
        return text

    # ----------------------------------------------------------------------------- lifecycle
    async def run(self) -> None:
        """Handshake, then read until the client leaves or a fatal error; never raises."""
        streamer: asyncio.Task | None = None
        try:
            await self._handshake()
            self.state.sessions[self.id] = self
            self.state.counters["sessions_total"] += 1
            streamer = asyncio.create_task(self._stream(), name=f"pvs-stream-{self.id}")
            await self._read_loop(streamer)
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
            if streamer is not None:
                streamer.cancel()
                await asyncio.gather(streamer, return_exceptions=True)
            await self.close(1000, "")

    async def _handshake(self) -> None:
        # Every error below is fatal: ``self.error`` closes and raises _SessionOver.
        text = await self._receive(timeout=self.settings.hello_timeout)
        try:
            msg = parse_client_message(text)
        except ProtocolError as exc:
            if exc.code in (ErrorCode.BAD_JSON, ErrorCode.INVALID_HELLO):
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
        try:
            self.core, self.params = compute.resolve(msg.core, msg.params)
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
        ok, why = self.core.supports(self.loaded.scene)
        if not ok:
            await self.error(ErrorCode.UNSUPPORTED_SCENE,
                             f"core {self.core.name!r} does not fit {msg.scene!r}: {why}")
        self.budget = msg.budget
        self.sent = np.zeros(self.loaded.scene.n_triangles, dtype=bool)
        await self._send_text(Welcome(
            session=self.id,
            scene=_scene_info(self.loaded),
            grid=_grid_info(self.loaded),
            core=self.core.name,
            params=_jsonable_params(self.params),
            budget=self.budget,
            limits=Limits(max_frame_bytes=self.settings.max_frame_bytes,
                          max_message_bytes=self.settings.max_message_bytes),
        ))

    async def _read_loop(self, streamer: asyncio.Task) -> None:
        while True:
            if streamer.done():
                return
            text = await self._receive()
            try:
                msg = parse_client_message(text)
            except ProtocolError as exc:
                code = exc.code
                if code == ErrorCode.INVALID_HELLO:
                    code = ErrorCode.DUPLICATE_HELLO
                await self.error(code, exc.message, exc.seq)
                continue
            if isinstance(msg, Pose):
                await self._on_pose(msg)
            elif isinstance(msg, Bye):
                await self.close(1000, "bye")
                return
            elif isinstance(msg, Hello):
                await self.error(ErrorCode.DUPLICATE_HELLO, "hello sent twice")

    async def _on_pose(self, pose: Pose) -> None:
        cell = self.loaded.grid.cell_of(np.asarray(pose.position, dtype=np.float64))
        if cell is None:
            if not self._outside:
                self._outside = True
                await self.error(ErrorCode.OUTSIDE_GRID,
                                 f"position {list(pose.position)} is in no viewcell", pose.seq)
            return
        self._outside = False
        if cell != self.cell:
            self.cell = cell
            self._queue.put_nowait((cell, pose.seq, time.perf_counter()))

    # ----------------------------------------------------------------------------- streaming
    async def _stream(self) -> None:
        try:
            while True:
                cell, seq, t0 = await self._queue.get()
                await self._stream_cell(cell, seq, t0)
        except _SessionOver:
            pass
        except Exception:
            log.exception("session %s: streaming failed", self.id)
            try:
                await self.error(ErrorCode.INTERNAL, "internal server error while streaming")
            except _SessionOver:
                pass

    async def _stream_cell(self, cell: int, seq: int, t0: float) -> None:
        scene_name = self.loaded.name
        try:
            result = await self.state.compute.compute(scene_name, self.core, self.params, cell=cell)
        except (UnsupportedSceneError, LookupError, SceneLoadFailed) as exc:
            await self.error(ErrorCode.COMPUTE_FAILED, str(exc), seq)
            return
        except Exception as exc:
            log.exception("session %s: PVS of %s cell %d failed", self.id, scene_name, cell)
            await self.error(ErrorCode.COMPUTE_FAILED,
                             f"PVS of cell {cell} failed: {type(exc).__name__}: {exc}", seq)
            return
        ids = result.pvs.triangle_ids
        new = ids[~self.sent[ids]]
        if self.budget is not None and len(ids) > self.budget:
            await self.error(ErrorCode.OVER_BUDGET,
                             f"PVS of cell {cell} holds {len(ids)} triangles, over the budget "
                             f"of {self.budget}", seq)
        self.sent[new] = True
        max_bytes = self.settings.max_frame_bytes
        count = chunk_count(len(new), max_bytes)
        await self._send_text(CellBegin(cell=cell, seq=seq, triangles=len(ids), new=len(new),
                                        chunks=count))
        per = triangles_per_frame(max_bytes)
        scene = self.loaded.scene
        for i in range(count):
            part = new[i * per:(i + 1) * per]
            # Encoding a full frame takes milliseconds: do it off the loop.
            frame = await asyncio.to_thread(
                lambda p=part, k=i: encode_geometry(
                    p, scene.triangles(p), scene.colors[p], cell=cell, seq=seq, index=k,
                    count=count,
                )
            )
            await self._send_frame(frame)
        self.state.counters["triangles_sent"] += len(new)
        self.state.counters["cells_streamed"] += 1
        await self._send_text(CellEnd(cell=cell, seq=seq, seconds=time.perf_counter() - t0,
                                      compute_seconds=result.seconds, cached=result.cached))


async def websocket_endpoint(websocket: WebSocket) -> None:
    """The ``/ws`` route: accept, run one ``StreamSession``."""
    await websocket.accept()
    await StreamSession(websocket, websocket.app.state.server).run()
