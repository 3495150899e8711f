"""The FastAPI application and how to run it under uvicorn.

``create_app(settings)`` wires the catalogue, the compute service, the HTTP routes and the ``/ws``
endpoint; ``uvicorn_config`` is the one place uvicorn options are derived from settings (the test
fixture and ``serve`` share it); ``serve(settings)`` runs the server until interrupted.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from collections import Counter
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import uvicorn
from fastapi import FastAPI

from protocol.codes import ErrorCode
from protocol.version import PROTOCOL_VERSION
from server import auth, metrics, routes, ws
from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.cors import add_cors
from server.middleware import HttpGuard, RateLimit
from server.nearfar_store import NearFarStore
from server.openapi import install_openapi
from server.settings import Settings
from server.viewer_files import install_viewer

#: uvicorn's own cap on an incoming WebSocket message. Kept well above ``max_message_bytes`` so
#: that oversized messages reach the session, which answers them with a named ``too_big`` error;
#: only beyond this does the WebSocket library close with 1009 by itself.
WS_LIBRARY_MAX_FACTOR = 4
WS_LIBRARY_MAX_MIN = 1 << 20


#: Stream counters of ``ServerState.counters`` (all start at 0; /health and /metrics show them).
COUNTERS = ("sessions_total", "messages_received", "messages_sent", "text_bytes_sent",
            "errors_sent", "frames_sent", "frame_bytes_sent", "triangles_sent",
            "triangles_dropped", "cells_streamed", "cells_prefetched", "prefetch_yields",
            "stalls", "slow_clients", "cubemaps_sent", "cells_sent_whole", "http_bytes_sent",
            "http_abandoned", "http_rate_limited")

log = logging.getLogger(__name__)

#: Seconds a stopping server waits for its sessions to take their 1001 close.
CLOSE_SESSIONS_TIMEOUT_S = 2.0


@dataclass
class ServerState:
    """What the routes and sessions share: settings, catalogue, compute service, open sessions
    (by id), stream counters and the near-far store (``near_far``: per-cell splits and cubemaps
    in one LRU bounded by ``settings.near_far_cache_bytes``)."""

    settings: Settings
    catalog: SceneCatalog
    compute: ComputeService
    sessions: dict[str, Any] = field(default_factory=dict)
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
                                         shared=self.compute.redis)
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

        async def close(s: Any) -> None:
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

    def wanted(self, key: tuple) -> bool:
        """Whether any open session still needs the PVS of cache key ``key`` (asked by worker
        threads before they start prefetch work)."""
        try:
            sessions = list(self.sessions.values())
        except RuntimeError:  # the dict changed under us: assume wanted
            return True
        return any(s.wants(key) for s in sessions)

    def centroids(self, loaded: Any) -> np.ndarray:
        """(m, 3) triangle centroids of a loaded scene, metres (computed once per scene)."""
        c = self._centroids.get(loaded.name)
        if c is None or len(c) != loaded.scene.n_triangles:
            c = loaded.scene.centroids()
            self._centroids[loaded.name] = c
        return c


def create_app(settings: Settings | None = None) -> FastAPI:
    """The server application for ``settings`` (default ``Settings()``); its ``ServerState`` is
    ``app.state.server``. The worker pool stops when the application shuts down."""
    settings = settings or Settings()
    catalog = SceneCatalog(settings)
    state = ServerState(settings, catalog, ComputeService(catalog, settings))
    for key in COUNTERS:
        state.counters[key] = 0
    metrics.install(app_state=state)
    state.access = auth.Access.from_settings(settings, state.counters)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        state.compute.shutdown()

    app = FastAPI(
        title="PVS stream server",
        version=f"protocol {PROTOCOL_VERSION}",
        description="Potentially visible sets of viewcells, computed online and streamed to thin "
        "clients over WebSocket (/ws).",
        lifespan=lifespan,
    )
    app.state.server = state
    if state.access is not None:  # innermost: after the address's rate limit, inside CORS
        app.add_middleware(auth.AccessGuard, access=state.access)
    app.add_middleware(RateLimit, rate=settings.pvs_rate, burst=settings.pvs_burst,
                       counters=state.counters)
    add_cors(app, settings.cors_origins)
    # Added last, so outermost: every answer's bytes are counted, the 429s included.
    app.add_middleware(HttpGuard, max_body_bytes=settings.max_body_bytes,
                       counters=state.counters)
    app.include_router(routes.router)
    app.include_router(metrics.router)
    app.add_api_websocket_route("/ws", ws.websocket_endpoint)
    routes.install_error_handlers(app)
    install_viewer(app, settings)
    install_openapi(app)
    if state.access is not None and state.access.book is not None:
        auth.document(app)
    return app


def uvicorn_config(app: FastAPI, settings: Settings, **overrides: Any) -> uvicorn.Config:
    """uvicorn options for ``app`` from ``settings`` (``overrides`` win)."""
    options: dict[str, Any] = dict(
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        ws_max_size=max(WS_LIBRARY_MAX_MIN, WS_LIBRARY_MAX_FACTOR * settings.max_message_bytes),
        ws_per_message_deflate=settings.ws_deflate,
        ws_ping_interval=settings.ws_ping_interval,
        ws_ping_timeout=settings.ws_ping_interval,
        lifespan="on",
        timeout_graceful_shutdown=settings.shutdown_grace,
    )
    options.update(overrides)
    return uvicorn.Config(app, **options)


class PVSServer(uvicorn.Server):
    """uvicorn's server, stopping the PVS way on SIGTERM/SIGINT: computations are cancelled
    and sessions closed with 1001 first (``ServerState.stop``), then uvicorn closes what is
    left, giving open requests ``settings.shutdown_grace`` seconds."""

    def __init__(self, config: uvicorn.Config, state: ServerState) -> None:
        super().__init__(config)
        self.state = state

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        for server in self.servers:
            server.close()  # no new connections while the sessions close
        try:
            await self.state.stop()
        except Exception:  # stopping must go on whatever a session does
            log.exception("closing the sessions failed")
        await super().shutdown(sockets)


def make_server(app: FastAPI, settings: Settings, **overrides: Any) -> PVSServer:
    """The ``PVSServer`` of ``app`` (``uvicorn_config`` options)."""
    return PVSServer(uvicorn_config(app, settings, **overrides), app.state.server)


def serve(settings: Settings | None = None) -> None:
    """Run the server on ``settings.host:settings.port`` until SIGTERM or Ctrl-C."""
    settings = settings or Settings()
    make_server(create_app(settings), settings).run()
