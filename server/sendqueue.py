"""A session's outgoing messages: two lanes, the current cell first, bounded in items and bytes.

Every message a session's streamer queues is an ``Outgoing``. Those of a cell stream
(``cell_begin``, geometry and cubemap frames, ``cell_end``) carry the stream's ``StreamTag``;
``drop`` and ``error`` messages carry none. The ``now`` lane holds the current cell's streams,
the ``ahead`` lane prefetch streams (with the ``drop`` messages that make room for them).

The sender (``get``) takes ``now`` items first, with one exception that keeps the client's
bracketing valid: a stream whose ``cell_begin`` has gone out is finished before anything else
(chunks arrive between one ``cell_begin`` and its ``cell_end``). ``cut_ahead`` ends such a
prefetch stream at once with a ``cell_end(partial)`` and removes every queued prefetch stream
that has not ended, so the current cell's frames wait for at most the one frame being sent.
Messages without a stream are never removed (a ``drop`` the server has accounted for must
reach the client): they move to the end of the ``now`` lane, keeping their order.

Single producer (the session's streamer) and single consumer (its sender), one event loop.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Kind = Literal["begin", "frame", "cubemap", "end", "message"]


@dataclass(eq=False)
class StreamTag:
    """One cell stream in the queue.

    ``seq`` is the pose sequence number its messages carry, ``t0`` its start (perf_counter
    seconds), ``compute_seconds``/``cached`` what its ``cell_end`` reports; ``cut`` is set once
    ``cut_ahead`` removed it (its producer must stop).
    """

    cell: int
    prefetch: bool
    seq: int = 0
    t0: float = 0.0
    compute_seconds: float = 0.0
    cached: bool = False
    cut: bool = False


@dataclass(eq=False)
class Outgoing:
    """A queued message: ``data`` as sent (text or binary), its ``kind``, its stream (None for
    ``drop``/``error``), the triangle ids a geometry frame carries, and for a ``cell_end``
    whether it is ``partial``."""

    data: str | bytes
    kind: Kind = "message"
    stream: StreamTag | None = None
    ids: np.ndarray | None = field(default=None, repr=False)
    partial: bool = False

    @property
    def nbytes(self) -> int:
        return len(self.data)


class SendQueue:
    """At most ``max_items`` messages and ``max_bytes`` bytes (one larger message fits an empty
    queue; a cut may add one partial ``cell_end``), in a ``now`` and an ``ahead`` lane."""

    def __init__(self, max_items: int, max_bytes: int) -> None:
        self.max_items = int(max_items)
        self.max_bytes = int(max_bytes)
        self._now: deque[Outgoing] = deque()
        self._ahead: deque[Outgoing] = deque()
        self._bytes = 0
        #: The stream whose ``cell_begin`` went out and whose ``cell_end`` has not.
        self._open: StreamTag | None = None
        #: Whether the open stream's messages are in the ahead lane. Not ``_open.prefetch``: a
        #: prefetch stream of the walker's new cell moves to the now lane (``cut_ahead``).
        self._open_ahead = False
        self._signal = asyncio.Event()

    # ----------------------------------------------------------------------------- state
    def __len__(self) -> int:
        return len(self._now) + len(self._ahead)

    @property
    def nbytes(self) -> int:
        """Bytes of the queued messages."""
        return self._bytes

    def lanes(self) -> tuple[int, int]:
        """(items in the now lane, items in the ahead lane)."""
        return len(self._now), len(self._ahead)

    def queued_ids(self) -> np.ndarray:
        """The triangle ids carried by queued geometry frames (int32, may repeat)."""
        parts = [i.ids for lane in (self._now, self._ahead) for i in lane if i.ids is not None]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int32)

    def has_room(self, nbytes: int) -> bool:
        """Whether a message of ``nbytes`` fits now."""
        n = len(self)
        return n == 0 or (n < self.max_items and self._bytes + nbytes <= self.max_bytes)

    def _changed(self) -> None:
        # Wake every waiter; each re-checks its own condition on a fresh event.
        self._signal.set()
        self._signal = asyncio.Event()

    async def _until(self, ready: Callable[[], bool]) -> None:
        while not ready():
            await self._signal.wait()

    # ----------------------------------------------------------------------------- producer
    async def wait_room(self, nbytes: int) -> None:
        """Wait until a message of ``nbytes`` fits."""
        await self._until(lambda: self.has_room(nbytes))

    def put_nowait(self, item: Outgoing, ahead: bool) -> None:
        """Append ``item`` to the ahead (prefetch) or the now lane, room or not."""
        (self._ahead if ahead else self._now).append(item)
        self._bytes += item.nbytes
        self._changed()

    async def put(self, item: Outgoing, ahead: bool) -> None:
        """Append ``item`` once it fits (backpressure on the producer)."""
        await self.wait_room(item.nbytes)
        self.put_nowait(item, ahead)

    def cut_ahead(
        self, keep: int | None, partial_end: Callable[[StreamTag], Outgoing]
    ) -> tuple[list[Outgoing], list[StreamTag]]:
        """Make way for the now lane: remove every queued prefetch stream except those of cell
        ``keep`` (the walker's current cell: they move to the now lane instead, in order).

        A removed stream whose ``cell_begin`` went out gets ``partial_end(tag)`` at the head of
        the ahead lane (sent next). Messages without a stream move to the now lane's end.
        Returns (the removed items, the removed streams, each once, in queue order).
        """
        head: deque[Outgoing] = deque()
        moved: list[Outgoing] = []
        removed: list[Outgoing] = []
        cut: list[StreamTag] = []
        opened = self._open if self._open is not None and self._open_ahead else None
        for item in self._ahead:
            s = item.stream
            if s is None:
                moved.append(item)
            elif s.cell == keep:
                # The open stream goes on first (its cell_begin is out); others join `now`.
                (head if s is opened else moved).append(item)
            else:
                removed.append(item)
                if s not in cut:
                    cut.append(s)
        if opened is not None and opened.cell != keep:
            if opened not in cut:
                cut.append(opened)
            head.appendleft(partial_end(opened))
        for s in cut:
            s.cut = True
        self._ahead = head
        self._now.extend(moved)
        self._bytes = sum(i.nbytes for i in self._now) + sum(i.nbytes for i in head)
        self._changed()
        return removed, cut

    # ----------------------------------------------------------------------------- consumer
    def _lane(self) -> deque[Outgoing] | None:
        if self._open is not None:
            lane = self._ahead if self._open_ahead else self._now
            return lane or None
        return self._now or self._ahead or None

    async def get(self) -> Outgoing:
        """The next message to send (waits for one): the open stream's, else the now lane's,
        else the ahead lane's."""
        await self._until(lambda: self._lane() is not None)
        lane = self._lane()
        item = lane.popleft()
        self._bytes -= item.nbytes
        if item.kind == "begin":
            self._open = item.stream
            self._open_ahead = lane is self._ahead
        elif item.kind == "end" and item.stream is self._open:
            self._open = None
        self._changed()
        return item
