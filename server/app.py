"""The FastAPI application and how to run it under uvicorn.

``create_app(settings)`` wires the catalogue, the compute service, the resolver of requests'
cores, the HTTP routes and the ``/ws`` endpoint (what they share: ``server.state.ServerState``);
``uvicorn_config`` is the one place uvicorn options are derived from settings (the test fixture
and ``serve`` share it); ``serve(settings)`` runs the server until interrupted.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import uvicorn
from fastapi import FastAPI

from protocol.version import PROTOCOL_VERSION
from server import auth, metrics, routes, ws
from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.cors import add_cors
from server.middleware import HttpGuard, RateLimit
from server.openapi import install_openapi
from server.resolve import Resolver
from server.scene_builds import prepare_scene
from server.settings import Settings
from server.state import ServerState
from server.viewer_files import install_viewer
from visibility.cores.base import AUTO_CORE, available_cores
from visibility.kernel_cache import cached_kernels, key_numba_cache
from visibility.scene_cache import set_store
from visibility.warmup import load_kernels

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


def create_app(settings: Settings | None = None) -> FastAPI:
    """The server application for ``settings`` (default ``Settings()``); its ``ServerState`` is
    ``app.state.server``. The worker pool stops when the application shuts down."""
    settings = settings or Settings()
    catalog = SceneCatalog(settings)
    # Per-scene builds (the hierarchy, a core's kd-tree) start when a scene loads and are kept
    # under the cache folder by the scene's content hash.
    set_store(settings.cache_dir)
    catalog.on_load = lambda loaded: prepare_scene(loaded, settings)
    state = ServerState(settings, catalog, ComputeService(catalog, settings), Resolver(settings))
    for key in COUNTERS:
        state.counters[key] = 0
    metrics.install(app_state=state)
    state.access = auth.Access.from_settings(settings, state.counters)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        warn_cold_kernels()
        if settings.preload_kernels:
            await asyncio.to_thread(preload_kernels, settings)
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


def warn_cold_kernels() -> bool:
    """Log a warning when the numba kernel cache holds no kernel (a fresh install, or the
    kernels' sources edited since ``pvs warmup``): each kernel then compiles at its first use,
    on the thread serving cells and holding the GIL, which stalls every walker for seconds at a
    time over the first minutes. True when it warned."""
    n = cached_kernels()
    if n != 0:
        return False
    log.warning("the numba kernel cache %s is empty: the kernels compile at the first cells "
                "(minutes on 2 cores, walkers stall meanwhile); run `pvs warmup` before "
                "serving", key_numba_cache())
    return True


def preload_cores(settings: Settings) -> list[str]:
    """The cores whose kernels a server loads before it serves (``preload_kernels``): the
    default core (``auto``: every registered core, any of which it may pick) and the first
    answers' core."""
    if settings.core == AUTO_CORE:
        names = available_cores()
    else:
        names = [settings.core]
    return list(dict.fromkeys([*names, settings.first_core]))


def preload_kernels(settings: Settings) -> float:
    """Load the kernels of ``preload_cores`` into this process (``visibility.warmup``): a
    kernel loads at its first call, a second or two per core with the GIL taken in long
    slices, and a server that did it at its first cells stalled every walker meanwhile.
    Seconds taken; a core that fails to load is logged, never fatal."""
    names = preload_cores(settings)
    log.info("loading the kernels of %s before serving", ", ".join(names))
    t0 = time.perf_counter()
    for name, exc in load_kernels(names).items():
        log.error("could not load the kernels of core %r ahead of use: %s", name, exc)
    seconds = time.perf_counter() - t0
    log.info("kernels of %s loaded in %.1f s", ", ".join(names), seconds)
    return seconds


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
