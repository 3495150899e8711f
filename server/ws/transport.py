"""The socket of one session: timed and counted sends, size-checked receives, one close.

A send that waits longer than ``settings.send_timeout`` (the client stopped reading) raises
``SlowClient``; the session then closes with ``slow_client`` (4008, ``Transport.slow``). Any
transport failure, and a peer that went away, ends the session (``SessionOver``).
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from typing import Any

from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from protocol.codes import CloseCode, ErrorCode, close_code_for
from protocol.messages import ProtocolError, dump_message
from server.settings import Settings

log = logging.getLogger(__name__)

#: Seconds a close may take when a send is stuck on a client that does not read, and otherwise.
STUCK_CLOSE_TIMEOUT_S = 2.0
CLOSE_TIMEOUT_S = 5.0
#: WebSocket close reasons are at most 123 bytes (RFC 6455); ours are cut well below.
MAX_CLOSE_REASON = 120


class SessionOver(Exception):
    """The session has ended (closed by us, by the peer, or the transport failed)."""


class SlowClient(Exception):
    """A send waited past ``send_timeout``."""


class Transport:
    """Sends, receives and closes for one WebSocket session.

    Parameters
    ----------
    websocket : the accepted WebSocket.
    settings : the server's settings (``send_timeout``, ``max_message_bytes``).
    counters : the server's stream counters (messages and bytes sent and received).
    session_id : for log lines.
    """

    def __init__(self, websocket: WebSocket, settings: Settings, counters: Counter,
                 session_id: str) -> None:
        self.ws = websocket
        self.settings = settings
        self.counters = counters
        self.session_id = session_id
        self.closed = False
        self._send_lock = asyncio.Lock()

    async def send_now(self, data: str | bytes) -> None:
        """Send one message, waiting at most ``send_timeout`` for the client to take it."""
        if self.closed:
            raise SessionOver
        try:
            async with self._send_lock:
                coro = (self.ws.send_bytes(data) if isinstance(data, bytes)
                        else self.ws.send_text(data))
                await asyncio.wait_for(coro, self.settings.send_timeout)
        except TimeoutError:
            raise SlowClient from None
        except (WebSocketDisconnect, RuntimeError, OSError) as exc:
            self.closed = True
            raise SessionOver from exc
        c = self.counters
        if isinstance(data, bytes):
            c["frames_sent"] += 1
            c["frame_bytes_sent"] += len(data)
        else:
            c["messages_sent"] += 1
            c["text_bytes_sent"] += len(data)

    async def send_message(self, msg: Any) -> None:
        """Send a message model now, past the queue (handshake, the reader's answers)."""
        try:
            await self.send_now(dump_message(msg))
        except SlowClient:
            await self.slow()

    async def slow(self) -> None:
        """Close a client that fell behind (``slow_client``) and end the session."""
        self.counters["slow_clients"] += 1
        log.warning("session %s: client fell behind for %.1f s; closing", self.session_id,
                    self.settings.send_timeout)
        await self.close(int(close_code_for(ErrorCode.SLOW_CLIENT)), str(ErrorCode.SLOW_CLIENT))
        raise SessionOver

    async def close(self, code: int = CloseCode.NORMAL, reason: str = "") -> None:
        """Close the WebSocket once (no-op when already closed)."""
        if self.closed:
            return
        self.closed = True
        reason = reason[:MAX_CLOSE_REASON]
        try:
            if self._send_lock.locked() and code != CloseCode.NORMAL:
                # A send is stuck on a client that does not read: do not queue behind it.
                await asyncio.wait_for(self.ws.close(code, reason), STUCK_CLOSE_TIMEOUT_S)
                return
            async with self._send_lock:
                if self.ws.application_state != WebSocketState.DISCONNECTED:
                    await asyncio.wait_for(self.ws.close(code, reason), CLOSE_TIMEOUT_S)
        except (WebSocketDisconnect, RuntimeError, OSError, TimeoutError):
            pass

    async def receive(self, timeout: float | None = None) -> str:
        """The next text message.

        Ends the session (``SessionOver``) on disconnect. Raises ProtocolError for ``timeout``
        seconds of silence (``expected_hello``: only the handshake waits with a timeout), a
        binary message (``binary_unsupported``) or one over ``max_message_bytes``
        (``too_big``); the caller answers them.
        """
        try:
            msg = await asyncio.wait_for(self.ws.receive(), timeout)
        except TimeoutError:
            raise ProtocolError(ErrorCode.EXPECTED_HELLO,
                                f"no hello within {timeout:g} s") from None
        except (WebSocketDisconnect, RuntimeError, OSError) as exc:
            self.closed = True
            raise SessionOver from exc
        if msg["type"] == "websocket.disconnect":
            self.closed = True
            raise SessionOver
        self.counters["messages_received"] += 1
        text = msg.get("text")
        if text is None:
            raise ProtocolError(ErrorCode.BINARY_UNSUPPORTED,
                                "clients send JSON text messages, not binary frames")
        limit = self.settings.max_message_bytes
        # Characters bound bytes from below (and 4x from above): encode only when it matters.
        if len(text) > limit or (4 * len(text) > limit and len(text.encode()) > limit):
            raise ProtocolError(ErrorCode.TOO_BIG, f"message over {limit} bytes")
        return text
