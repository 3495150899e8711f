"""A session's outgoing stream: the bounded two-lane queue (``server.sendqueue``) and the sender
task that drains it into the transport, counting what reached the socket."""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from protocol.messages import CellBegin, CellEnd, dump_message
from server.sendqueue import Outgoing, SendQueue, StreamTag
from server.settings import Settings
from server.ws.transport import SessionOver, SlowClient, Transport


async def first_of(*aws: Any) -> None:
    """Wait until the first of ``aws`` finishes; cancel the others."""
    tasks = [asyncio.ensure_future(a) for a in aws]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()


def partial_end(tag: StreamTag) -> Outgoing:
    """The ``cell_end(partial)`` closing a prefetch stream cut after its ``cell_begin``."""
    end = CellEnd(cell=tag.cell, seq=tag.seq, seconds=time.perf_counter() - tag.t0,
                  compute_seconds=tag.compute_seconds, cached=tag.cached, prefetch=True,
                  partial=True)
    return Outgoing(dump_message(end), "end", tag, partial=True)


class Outbox:
    """The messages a session's streamer queued and the sender that sends them in order.

    Parameters
    ----------
    transport : where messages go.
    settings : ``send_queue_frames`` and ``max_frame_bytes`` bound the queue.
    counters : the server's stream counters.
    wake : set when the walker's state changes (a prefetch stream waiting for room rechecks).
    current_pending : ``current_pending(cell)``: whether the walker's cell, not ``cell``,
        waits for its stream (a prefetch stream of ``cell`` must then yield).
    """

    def __init__(self, transport: Transport, settings: Settings, counters: Counter,
                 wake: asyncio.Event, current_pending: Callable[[int], bool]) -> None:
        self.transport = transport
        self.counters = counters
        self.queue = SendQueue(settings.send_queue_frames,
                               settings.send_queue_frames * settings.max_frame_bytes)
        self._wake = wake
        self._current_pending = current_pending

    async def put(self, item: Any, stream: StreamTag | None = None,
                  ids: np.ndarray | None = None, cubemap: bool = False) -> bool:
        """Queue a message (model) or frame (bytes) in ``stream``'s lane (the prefetch lane for
        prefetch streams); waits while the queue is full (backpressure on the streamer).

        ``cell_begin``, ``cell_end`` and frames belong to ``stream``; ``ids`` are the triangle
        ids a geometry frame carries. Returns False, queuing nothing, when a prefetch stream's
        message waited for room while the walker's current cell became pending (the caller
        yields); ``drop``/``error`` messages are always queued.
        """
        if self.transport.closed:
            raise SessionOver
        if isinstance(item, bytes):
            out = Outgoing(item, "cubemap" if cubemap else "frame", stream, ids)
        elif isinstance(item, (CellBegin, CellEnd)):
            out = Outgoing(dump_message(item), "begin" if isinstance(item, CellBegin) else "end",
                           stream, partial=isinstance(item, CellEnd) and item.partial)
        else:
            out = Outgoing(dump_message(item))
        ahead = stream is not None and stream.prefetch
        if ahead and out.stream is not None:
            while not self.queue.has_room(out.nbytes):
                self._wake.clear()
                if stream.cut or self._current_pending(stream.cell):
                    return False
                await first_of(self.queue.wait_room(out.nbytes), self._wake.wait())
        await self.queue.put(out, ahead)
        return True

    def cut_ahead(self, cell: int | None) -> tuple[list[Outgoing], list[StreamTag]]:
        """Remove the queued prefetch streams but ``cell``'s (``SendQueue.cut_ahead``)."""
        return self.queue.cut_ahead(cell, partial_end)

    def queued_ids(self) -> np.ndarray:
        """The triangle ids of the geometry frames still queued."""
        return self.queue.queued_ids()

    async def run(self) -> None:
        """The sender task: send queued messages until the session ends."""
        try:
            while True:
                item = await self.queue.get()
                await self.transport.send_now(item.data)
                self._sent(item)
        except SlowClient:
            await self.transport.slow()
        except SessionOver:
            pass

    def _sent(self, item: Outgoing) -> None:
        """Count what reached the socket (cut prefetch frames never count)."""
        c = self.counters
        if item.ids is not None:
            c["triangles_sent"] += len(item.ids)
        elif item.kind == "cubemap":
            c["cubemaps_sent"] += 1
        elif item.kind == "end" and not item.partial:
            c["cells_streamed"] += 1
            if item.stream is not None and item.stream.prefetch:
                c["cells_prefetched"] += 1
