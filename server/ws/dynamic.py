"""Dynamic streaming of one session: the keyframe and sphere frames (``server.dynamic``) that go
with a cell stream's geometry (a moving triangle's keyframes just before its geometry)."""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Callable

from server.dynamic import DynamicStream
from server.sendqueue import StreamTag
from server.ws.outbox import Outbox
from visibility.scene import Scene

log = logging.getLogger(__name__)


class DynamicFrames:
    """Queues a session's keyframe and sphere frames; nothing for a static scene.

    The ``DynamicStream`` (keyframes and spheres of the scene, encoded per request) is made on
    the first stream, off the event loop.
    """

    def __init__(self, scene: Scene, max_frame_bytes: int, outbox: Outbox, counters: Counter,
                 session_id: str) -> None:
        self.scene = scene
        self.max_frame_bytes = max_frame_bytes
        self.outbox = outbox
        self.counters = counters
        self.session_id = session_id
        self.stream: DynamicStream | None = None

    async def queue(self, make: Callable[[DynamicStream], list[bytes]], tag: StreamTag) -> bool:
        """Queue the frames ``make(stream)`` encodes (off the event loop) in stream ``tag``.
        False when a prefetch stream had to yield meanwhile (the caller cuts it and stops)."""
        if self.stream is None:
            self.stream = await asyncio.to_thread(DynamicStream, self.scene,
                                                  self.max_frame_bytes)
            if self.stream.why_not:
                log.warning("session %s: no keyframe frames: %s", self.session_id,
                            self.stream.why_not)
        if not self.stream.active:
            return True
        frames = await asyncio.to_thread(make, self.stream)
        for frame in frames:
            if not await self.outbox.put(frame, tag):
                return False
            self.counters["dynamic_frames_sent"] += 1
        return True
