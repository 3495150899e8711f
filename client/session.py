"""The client's network session: one WebSocket to the server's ``/ws``, poses out, geometry in.

``Session.connect`` sends ``hello`` and waits for ``welcome``; a receive task then decodes every
binary frame into the ``GeometryStore`` (geometry, and for dynamic scenes the keyframes of moving
triangles and the spheres, ``protocol.keyframes``; cubemaps are kept by cell) and tracks each
cell's stream (``cell_begin``, geometry chunks, ``cell_end``); ``wait_cell`` waits for a cell to
be complete. Errors from the server are kept in ``errors``; a fatal one (or a close) ends the
session and wakes every waiter.

A server is not trusted with the client's memory: ids are checked against the scene the welcome
describes (triangle ids in [0, ``scene.triangles``), sphere ids in [0, ``scene.spheres``), cells
in [0, ``grid.cells``)), and a cell stream takes no more triangles than its ``cell_begin``
announced (at most the scene's). Anything else is refused, reported in ``local_errors`` and not
kept; the store holds one copy per triangle (``client.store``).

``SyncSession`` runs a ``Session`` on a background event-loop thread for synchronous code (the
replay loop): same methods, blocking.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np
import websockets
from websockets.asyncio.client import ClientConnection, connect

from client.store import GeometryStore
from protocol.auth import authorization_header, is_token
from protocol.frames import FrameError, FrameKind, decode_geometry
from protocol.keyframes import KeyframeAssembler, decode_keyframes, decode_spheres
from protocol.messages import (
    Bye,
    CellBegin,
    CellEnd,
    Drop,
    Error,
    Hello,
    Pose,
    ProtocolError,
    Welcome,
    dump_message,
    parse_server_message,
)

log = logging.getLogger(__name__)

#: Kind byte (offset 6) of a cubemap frame (``protocol.frames.FrameKind.CUBEMAP``).
CUBEMAP_KIND = 2


class SessionError(RuntimeError):
    """The server refused or ended the session. ``code`` is the error code (or ``"closed"``),
    ``close_code`` the WebSocket close code when known."""

    def __init__(self, code: str, message: str, close_code: int | None = None) -> None:
        super().__init__(f"{code}: {message}" + (f" (close {close_code})" if close_code else ""))
        self.code = code
        self.message = message
        self.close_code = close_code


@dataclass
class CellStream:
    """What the client knows of one cell's stream (the latest one for that cell).

    ``begin``/``end`` are the messages, ``chunks`` and ``triangles`` what arrived in between,
    ``received_at`` the client clock (perf_counter seconds) at ``cell_end``. ``answer``: the
    answer the cell holds as far as complete streams go (``protocol.messages.ANSWERS``;
    None before the first ``cell_end``): a "refined" stream under way leaves it "first" until
    its end, and keeps the ids of the first answer's stream.
    """

    cell: int
    begin: CellBegin | None = None
    end: CellEnd | None = None
    chunks: int = 0
    triangles: int = 0
    received_at: float | None = None
    ids: list[np.ndarray] = field(default_factory=list, repr=False)
    answer: str | None = None

    @property
    def complete(self) -> bool:
        return self.end is not None


def ws_url(url: str) -> str:
    """The ``/ws`` WebSocket URL for a server URL (``http://host:port`` or a ``ws://`` URL)."""
    parts = urlsplit(url)
    scheme = {"http": "ws", "https": "wss"}.get(parts.scheme, parts.scheme)
    if scheme not in ("ws", "wss"):
        raise ValueError(f"not a server URL: {url!r}")
    path = parts.path if parts.path.rstrip("/").endswith("/ws") else parts.path.rstrip("/") + "/ws"
    return urlunsplit((scheme, parts.netloc, path, parts.query, ""))


def _vec3(v: Sequence[float] | np.ndarray, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got {a.shape}")
    return (float(a[0]), float(a[1]), float(a[2]))


class Session:
    """An open streaming session. Use ``await Session.connect(...)``, not the constructor."""

    def __init__(self, ws: ClientConnection, welcome: Welcome, store: GeometryStore) -> None:
        self.ws = ws
        self.welcome = welcome
        self.store = store
        self.errors: list[Error] = []
        #: Problems found on the client side (undecodable frames, inconsistent streams).
        self.local_errors: list[str] = []
        self.cells: dict[int, CellStream] = {}
        self.complete: set[int] = set()
        self.current: CellStream | None = None
        self.bytes_received = 0
        self.frames_received = 0
        self.close_code: int | None = None
        self.close_reason: str | None = None
        n = welcome.scene.triangles
        #: Delta accounting: which ids the client holds, ids received while already held (a
        #: server bug), drops obeyed.
        self._held = np.zeros(n, dtype=bool)
        self.duplicates = 0
        self.dropped = 0
        self.drops: list[Drop] = []
        self.triangles_received = 0
        #: Triangles received by the answer of the stream that brought them
        #: (``cell_begin.answer``).
        self.triangles_by_answer: dict[str, int] = {}
        #: Far-field cubemaps by the cell they were baked for (``protocol.cubemap.CubemapFrame``;
        #: the anchor cell of a block that shares one), near-far streams.
        self.cubemaps: dict[int, Any] = {}
        #: Dynamic scenes: keyframe and sphere frames received, triangle ids whose keyframes
        #: arrived (and those that arrived while already held: a server bug), spheres received.
        self.keyframe_frames = 0
        self.keyframes_received = 0
        self.keyframe_duplicates = 0
        self.sphere_frames = 0
        self.spheres_received = 0
        self._kf_held = np.zeros(n, dtype=bool)
        self._assemble = {FrameKind.KEYFRAMES: KeyframeAssembler(),
                          FrameKind.SPHERES: KeyframeAssembler()}
        self._changed = asyncio.Condition()
        self._closed = asyncio.Event()
        self._task = asyncio.create_task(self._receive_loop(), name="pvs-session-recv")

    # ----------------------------------------------------------------------------- opening
    @classmethod
    async def connect(
        cls,
        url: str,
        scene: str,
        core: str | None = None,
        params: dict[str, Any] | None = None,
        budget: int | None = None,
        *,
        prefetch: bool | None = None,
        progressive: bool | None = None,
        store: GeometryStore | None = None,
        timeout: float = 30.0,
        max_size: int | None = 64 * 1024 * 1024,
        token: str | None = None,
    ) -> Session:
        """Open a session on the server at ``url`` (http(s):// or ws(s)://) for ``scene``.

        Waits (at most ``timeout`` seconds) for the ``welcome``; raises SessionError when the
        server answers with an error or closes, TimeoutError when it does not answer.
        ``prefetch``: ask for (True) or against (False) cells streamed ahead; None: the
        server's default. ``progressive``: False asks for the core's answers only, never a
        cheap first answer refined later (``cell_begin.answer``); None: the server's default.
        ``token``: the bearer token of a server with access control (``protocol.auth``), sent
        in the ``Authorization`` header; refused, SessionError ``unauthorized`` (4401).
        """
        if token is not None and not is_token(token):
            raise ValueError("not a bearer token (protocol.auth.TOKEN_CHARS)")
        headers = authorization_header(token) if token is not None else None
        ws = await connect(ws_url(url), max_size=max_size, open_timeout=timeout, compression=None,
                           additional_headers=headers)
        try:
            hello = Hello(scene=scene, core=core, params=params or {}, budget=budget,
                          prefetch=prefetch, progressive=progressive)
            try:
                await ws.send(dump_message(hello))
            except websockets.ConnectionClosed:
                pass  # refused before its hello (the token): the error waits for recv below
            raw = await asyncio.wait_for(ws.recv(), timeout)
            if isinstance(raw, bytes):
                raise SessionError("protocol", "binary frame before welcome")
            msg = parse_server_message(raw)
            if isinstance(msg, Error):
                try:
                    await asyncio.wait_for(ws.wait_closed(), 2.0)
                except TimeoutError:
                    pass
                raise SessionError(msg.code, msg.message, ws.close_code)
            if not isinstance(msg, Welcome):
                raise SessionError("protocol", f"expected welcome, got {msg.type}")
        except websockets.ConnectionClosed as exc:
            raise SessionError("closed", "server closed the connection before welcome",
                               exc.rcvd.code if exc.rcvd else None) from None
        except BaseException:
            await ws.close()
            raise
        if store is None:
            store = GeometryStore(budget, scene_triangles=msg.scene.triangles,
                                  scene_spheres=msg.scene.spheres)
        return cls(ws, msg, store)

    # ----------------------------------------------------------------------------- sending
    async def send_pose(
        self,
        seq: int,
        t: float,
        position: Sequence[float] | np.ndarray,
        forward: Sequence[float] | np.ndarray,
        velocity: Sequence[float] | np.ndarray | None = None,
    ) -> None:
        """Send a pose (metres, seconds). ValueError for NaN/inf or malformed vectors (checked
        here, before sending); SessionError once the session has ended."""
        if self.closed:
            raise SessionError("closed", "the session has ended", self.close_code)
        try:
            pose = Pose(seq=int(seq), t=float(t), position=_vec3(position, "position"),
                        forward=_vec3(forward, "forward"),
                        velocity=None if velocity is None else _vec3(velocity, "velocity"))
        except ValueError as exc:
            raise ValueError(f"invalid pose: {exc}") from None
        await self.send_raw(dump_message(pose))

    async def send_raw(self, data: str | bytes) -> None:
        """Send a frame as is (tests use it to send what a correct client never would)."""
        try:
            await self.ws.send(data)
        except websockets.ConnectionClosed:
            raise SessionError("closed", "the session has ended", self.close_code) from None

    # ----------------------------------------------------------------------------- waiting
    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def is_complete(self, cell: int) -> bool:
        """Whether ``cell_end`` for ``cell`` has arrived in this session."""
        return int(cell) in self.complete

    def cubemap_for(self, cell: int) -> Any:
        """The far cubemap ``cell`` composes with (``protocol.cubemap.CubemapFrame``), or None:
        the one its ``cell_begin.near_far`` names (``cubemap_cell``: cells of a block share
        their anchor cell's), else the cell's own."""
        stream = self.cells.get(int(cell))
        nf = stream.begin.near_far if stream is not None and stream.begin is not None else None
        key = nf.get("cubemap_cell", cell) if isinstance(nf, dict) else cell
        return self.cubemaps.get(int(key)) if key is not None else None

    async def wait_cell(self, cell: int, timeout: float | None = None) -> CellStream:
        """Wait until ``cell`` is complete; its ``CellStream``. TimeoutError after ``timeout``
        seconds, SessionError when the session ends first."""
        cell = int(cell)

        async def _wait() -> CellStream:
            async with self._changed:
                while cell not in self.complete:
                    if self.closed:
                        raise SessionError(self._end_code(), f"session ended before cell {cell}",
                                           self.close_code)
                    await self._changed.wait()
                return self.cells[cell]

        return await asyncio.wait_for(_wait(), timeout)

    async def wait_closed(self, timeout: float | None = None) -> None:
        """Wait until the connection is closed (by either side)."""
        await asyncio.wait_for(self._closed.wait(), timeout)

    async def close(self) -> None:
        """Say bye and close; waits for the receive task to finish."""
        if not self.closed:
            try:
                await self.ws.send(dump_message(Bye()))
            except websockets.ConnectionClosed:
                pass
        await self.ws.close()
        await asyncio.gather(self._task, return_exceptions=True)

    def _end_code(self) -> str:
        fatal = [e for e in self.errors if e.fatal]
        return fatal[-1].code if fatal else "closed"

    # ----------------------------------------------------------------------------- receiving
    async def _receive_loop(self) -> None:
        try:
            async for raw in self.ws:
                if isinstance(raw, bytes):
                    self._on_frame(raw)
                else:
                    self._on_text(raw)
                async with self._changed:
                    self._changed.notify_all()
        except websockets.ConnectionClosed:
            pass
        except Exception as exc:  # a bug here must not hang waiters
            log.exception("session receive loop failed")
            self.local_errors.append(f"receive loop failed: {exc!r}")
        finally:
            self.close_code = self.ws.close_code
            self.close_reason = self.ws.close_reason
            self._closed.set()
            async with self._changed:
                self._changed.notify_all()

    def _on_frame(self, raw: bytes) -> None:
        self.bytes_received += len(raw)
        self.frames_received += 1
        kind = raw[6] if len(raw) > 6 else None
        if kind == CUBEMAP_KIND:
            try:
                from protocol.cubemap import decode_cubemap

                cube = decode_cubemap(raw)
            except (FrameError, ImportError) as exc:
                self.local_errors.append(f"undecodable cubemap frame: {exc}")
                return
            if not 0 <= cube.cell < self.welcome.grid.cells:
                self.local_errors.append(f"cubemap of cell {cube.cell}, not a cell of the grid "
                                         f"({self.welcome.grid.cells} cells): refused")
                return
            self.cubemaps[cube.cell] = cube
            return
        if kind in (FrameKind.KEYFRAMES, FrameKind.SPHERES):
            self._on_keyframes(raw, FrameKind(kind))
            return
        try:
            chunk = decode_geometry(raw)
        except FrameError as exc:
            self.local_errors.append(f"undecodable frame: {exc}")
            return
        cs = self.current
        in_stream = cs is not None and cs.cell == chunk.cell
        if not self._ids_in_scene(chunk.ids, len(self._held), "triangle", "geometry frame"):
            return
        if in_stream and cs.begin is not None and cs.triangles + len(chunk) > cs.begin.new:
            self.local_errors.append(
                f"cell {cs.cell}: a geometry frame past the {cs.begin.new} triangles its "
                f"cell_begin announced: refused")
            return
        try:
            self.store.add_chunk(chunk)
        except ValueError as exc:  # a store of the caller's with its own bounds
            self.local_errors.append(f"geometry frame refused by the store: {exc}")
            return
        self.duplicates += int(np.count_nonzero(self._held[chunk.ids]))
        self._held[chunk.ids] = True
        self.triangles_received += len(chunk)
        if cs is not None and cs.begin is not None:
            a = cs.begin.answer
            self.triangles_by_answer[a] = self.triangles_by_answer.get(a, 0) + len(chunk)
        if not in_stream:
            self.local_errors.append(f"chunk of cell {chunk.cell} outside its cell stream")
            return
        cs.chunks += 1
        cs.triangles += len(chunk)
        cs.ids.append(chunk.ids)

    def _on_keyframes(self, raw: bytes, kind: FrameKind) -> None:
        """A keyframe or sphere frame: joined with its windows, then into the store."""
        try:
            if kind == FrameKind.KEYFRAMES:
                self.keyframe_frames += 1
                chunk = self._assemble[kind].add(decode_keyframes(raw))
            else:
                self.sphere_frames += 1
                chunk = self._assemble[kind].add(decode_spheres(raw))
        except FrameError as exc:
            self.local_errors.append(f"undecodable {kind.name.lower()} frame: {exc}")
            return
        if chunk is None:
            return
        what = "triangle" if kind == FrameKind.KEYFRAMES else "sphere"
        count = len(self._kf_held) if what == "triangle" else self.welcome.scene.spheres
        if not self._ids_in_scene(chunk.ids, count, what, f"{kind.name.lower()} frame"):
            return
        try:
            if kind == FrameKind.KEYFRAMES:
                self.store.add_keyframe_chunk(chunk)
                self.keyframe_duplicates += int(np.count_nonzero(self._kf_held[chunk.ids]))
                self._kf_held[chunk.ids] = True
                self.keyframes_received += len(chunk)
            else:
                self.store.add_sphere_chunk(chunk)
                self.spheres_received += len(chunk)
        except ValueError as exc:  # e.g. keyframe times that contradict the held ones
            self.local_errors.append(f"{kind.name.lower()} frame refused by the store: {exc}")

    def _ids_in_scene(self, ids: np.ndarray, count: int, what: str, frame: str) -> bool:
        """Whether every id of a frame is in [0, ``count``) (the welcome's count of ``what``);
        if not, the frame is refused and reported in ``local_errors``."""
        if len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= count):
            self.local_errors.append(
                f"{frame} with {what} ids up to {int(ids.max())}, outside [0, {count}) (the "
                f"scene's {what}s per the welcome): refused")
            return False
        return True

    def _begin_fits(self, msg: CellBegin) -> bool:
        """Whether a ``cell_begin`` names a cell of the grid and at most the scene's
        triangles; if not it is reported in ``local_errors`` and opens no stream."""
        cells, n = self.welcome.grid.cells, len(self._held)
        if msg.cell >= cells or msg.triangles > n or msg.new > msg.triangles:
            self.local_errors.append(
                f"cell_begin for cell {msg.cell} with {msg.new} new of {msg.triangles} triangles "
                f"does not fit the welcome ({cells} cells, {n} triangles): refused")
            return False
        return True

    def _on_text(self, raw: str) -> None:
        self.bytes_received += len(raw)
        try:
            msg = parse_server_message(raw)
        except ProtocolError as exc:
            self.local_errors.append(f"unreadable server message: {exc}")
            return
        if isinstance(msg, CellBegin):
            if not self._begin_fits(msg):
                self.current = None
                return
            before = self.cells.get(msg.cell)
            if msg.answer == "refined" and before is not None:
                # A refinement adds to the cell's first answer: the cell stays complete, with
                # the first answer, until this stream ends.
                self.current = CellStream(msg.cell, begin=msg, ids=list(before.ids),
                                          answer=before.answer)
            else:
                self.current = CellStream(msg.cell, begin=msg)
            self.cells[msg.cell] = self.current
        elif isinstance(msg, Drop):
            self._on_drop(msg)
        elif isinstance(msg, CellEnd):
            cs = self.current
            if cs is None or cs.cell != msg.cell:
                self.local_errors.append(f"cell_end for {msg.cell} without its cell_begin")
                if msg.cell >= self.welcome.grid.cells:
                    return
                cs = self.cells.setdefault(msg.cell, CellStream(msg.cell))
            elif cs.begin is not None and not msg.partial and (cs.chunks != cs.begin.chunks
                                           or cs.triangles != cs.begin.new):
                self.local_errors.append(
                    f"cell {msg.cell}: got {cs.chunks} chunks / {cs.triangles} triangles, "
                    f"announced {cs.begin.chunks} / {cs.begin.new}"
                )
            cs.end = msg
            cs.received_at = time.perf_counter()
            if not msg.partial:
                cs.answer = msg.answer
                self.complete.add(msg.cell)
            self.current = None
        elif isinstance(msg, Error):
            self.errors.append(msg)
        elif isinstance(msg, Welcome):
            self.local_errors.append("second welcome")


    def _on_drop(self, msg: Drop) -> None:
        """Obey a ``drop``: remove the ids from the store; the named cells are incomplete."""
        ids = np.asarray(msg.ids, dtype=np.int64)
        self.dropped += self.store.drop(ids)
        self._held[ids[ids < len(self._held)]] = False
        self._kf_held[ids[ids < len(self._kf_held)]] = False
        self.complete.difference_update(msg.cells)
        self.drops.append(Drop(ids=[], cells=msg.cells, reason=msg.reason))

    @property
    def held(self) -> int:
        """Triangles the client holds by the protocol's accounting (received minus dropped)."""
        return int(np.count_nonzero(self._held))


class SyncSession:
    """A ``Session`` driven from synchronous code through a private event-loop thread.

    ``SyncSession.connect(url, scene, ...)`` takes ``Session.connect``'s arguments; every method
    blocks until done. Attributes of the session (``store``, ``welcome``, ``errors``, ``cells``)
    are reachable directly; the store is thread-safe, the rest is read-mostly.
    """

    def __init__(self) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="pvs-session-loop",
                                        daemon=True)
        self._thread.start()
        self.session: Session | None = None

    def _run(self, coro: Any, timeout: float | None = None) -> Any:
        fut: Future = asyncio.run_coroutine_threadsafe(coro, self._loop)
        return fut.result(timeout)

    @classmethod
    def connect(cls, url: str, scene: str, core: str | None = None, params: dict | None = None,
                budget: int | None = None, **kw: Any) -> SyncSession:
        """Open a session (see ``Session.connect``)."""
        self = cls()
        try:
            self.session = self._run(Session.connect(url, scene, core, params, budget, **kw))
        except BaseException:
            self._stop()
            raise
        return self

    def __getattr__(self, name: str) -> Any:
        # Only reached for names SyncSession lacks: expose the session's attributes.
        if name in ("session", "_loop", "_thread"):
            raise AttributeError(name)
        return getattr(self.session, name)

    def send_pose(self, seq: int, t: float, position: Any, forward: Any,
                  velocity: Any = None) -> None:
        """Send a pose (blocks until written)."""
        self._run(self.session.send_pose(seq, t, position, forward, velocity))

    def wait_cell(self, cell: int, timeout: float | None = None) -> CellStream:
        """Block until ``cell`` is complete (TimeoutError / SessionError as the async one)."""
        return self._run(self.session.wait_cell(cell, timeout))

    def is_complete(self, cell: int) -> bool:
        return self.session.is_complete(cell)

    def close(self) -> None:
        """Close the session and stop the loop thread."""
        try:
            if self.session is not None:
                self._run(self.session.close(), timeout=10)
        finally:
            self._stop()

    def _stop(self) -> None:
        if self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5)
        if not self._loop.is_running():
            self._loop.close()

    def __enter__(self) -> SyncSession:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
