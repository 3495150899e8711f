"""The ``/ws`` streaming endpoint: hello, then poses in, PVS geometry out.

One ``StreamSession`` per connection, split along its seams:

- ``transport``: timed, counted sends; size-checked receives; one close;
- ``handshake``: ``hello`` in, checks, the scene loaded, ``welcome`` out;
- ``session``: the slim ``StreamSession``: the walker's state, the reader task (poses, stalls,
  the prefetch list), errors and the lifecycle;
- ``streams``: the streamer task: the next cell, its PVS, its ``cell_begin``/frames/``cell_end``;
- ``inventory``: what the client holds, its budget, the drops that keep it within;
- ``nearfar``: near geometry plus a far cubemap per cell (``settings.near_far``);
- ``dynamic``: keyframe and sphere frames of moving geometry;
- ``outbox``: the bounded two-lane send queue and the sender task (a send that waits longer
  than ``settings.send_timeout`` closes the session with ``slow_client``, 4008).

Every problem is an ``error`` message with an ``ErrorCode``; fatal ones are followed by a close
with the code from ``protocol.codes``. Nothing a client sends can take the server down:
unexpected exceptions end that session only (1011). Memory per session is bounded: a bit per
scene triangle (held), the PVS of at most ``MAX_KNOWN_PVS`` cells, and the send queue
(``send_queue_frames`` messages of at most ``max_frame_bytes``).

Outside-grid poses report ``outside_grid`` once per stay outside the grid (not once per pose).
"""

from __future__ import annotations

from starlette.websockets import WebSocket

from server.auth import subprotocol
from server.ws.inventory import MAX_KNOWN_PVS
from server.ws.session import StreamSession

__all__ = ["MAX_KNOWN_PVS", "StreamSession", "websocket_endpoint"]


async def websocket_endpoint(websocket: WebSocket) -> None:
    """The ``/ws`` route: accept (selecting ``protocol.auth.SUBPROTOCOL`` when offered), run
    one ``StreamSession``."""
    await websocket.accept(subprotocol=subprotocol(websocket.scope))
    await StreamSession(websocket, websocket.app.state.server).run()
