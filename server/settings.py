"""Server settings: one validated pydantic model, built in code or from ``PVS_*`` environment
variables (``Settings.from_env``)."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator

from protocol.frames import DEFAULT_MAX_FRAME_BYTES, frame_bytes
from protocol.ints import INT32_MAX
from visibility.loaders import MAX_FILE_BYTES, MAX_TRIANGLES
from visibility.nearfar import MAX_RESOLUTION as NEAR_FAR_MAX_RESOLUTION
from visibility.nearfar import MIN_RESOLUTION as NEAR_FAR_MIN_RESOLUTION
from visibility.nearfar import NearFarConfig
from visibility.viewcells import DEFAULT_CELL_SIZE

#: Near-far defaults come from ``visibility.nearfar.NearFarConfig`` (one source of truth; its
#: module docstring says why they suit 4 m cells).
_NEAR_FAR_DEFAULT = NearFarConfig()


def default_generated() -> dict[str, int]:
    """Every available generator at its default size ({} while the generators are absent)."""
    try:
        from visibility.generators import DEFAULT_TRIANGLES, available_generators
    except ImportError:
        return {}
    return {name: int(DEFAULT_TRIANGLES[name]) for name in available_generators()}


class Settings(BaseModel):
    """What the server serves and how.

    Attributes
    ----------
    host, port : where uvicorn listens (port 0: any free port).
    scenes_dir : folder of scene files (``visibility.loaders.SCENE_EXTENSIONS``); None: none.
    generated : generated scenes to serve, {generator name: triangles}; default every available
        generator at its ``DEFAULT_TRIANGLES``.
    cell_size : viewcell size in metres for every scene; None (the default): each scene's own
        (a sidecar's or hint's ``cell_size``), else ``DEFAULT_CELL_SIZE`` (4 m). Set, it wins
        over the scenes' own, as ``pvs precompute --cell-size`` does (small cells for ``cos``).
    core, core_params : the core and parameters used when a request names none.
    workers : PVS computations running at once (threads; numba kernels release the GIL).
    cache_bytes : bound of the in-memory PVS cache, bytes.
    cache_dir : folder of the on-disk PVS cache (npz files, survives restarts); None: no disk
        cache.
    prefetch : compute and send the PVS of the cells ahead of each walker (clients may opt out
        in their hello).
    prefetch_ahead : cosine threshold: a neighbour is ahead of a walker when the cosine between
        its predicted motion and the direction to the neighbour's centre exceeds this.
    progressive : a walker's cell whose PVS is not ready gets a cheap first answer at once
        (``first_core``) while the session's core computes, then only what that core adds
        (``cell_begin.answer``); clients may opt out in their hello. False: the walker waits
        for the session core's answer.
    known_answers : with ``progressive``, a first answer that costs nothing where the core's
        PVS of neighbouring cells is known (in memory or the shared cache): their union
        (``cell_begin.answer`` "known"); a first answer is computed only where none is.
    first_core, first_params : the core and parameters of the first answer (default
        ``sampling``, 4 viewpoints at 128 px: tens of milliseconds on the 100k scenes). First
        answers run on a worker of their own, so computations of the session cores never
        hold them up.
    preload_kernels : load the kernels of the default core (``auto``: of every core) and of
        ``first_core`` before serving (``server.app.preload_kernels``): a kernel loads at its
        first call in a process, a second or two per core during which every walker stalls.
        Kernels of moving scenes and of cores clients name load at their first use.
    calibrate : ``auto`` picks by a calibration (``visibility.calibration``): each fitting
        core's time and misses on a few cells of the scene, measured once per scene and cell
        size in the background (kept in ``cache_dir`` across restarts); until it is done, the
        cores' declared fits decide. False: the declared fits always decide.
    auto_budget : seconds per cell ``auto`` may spend (the calibration's time budget).
    calibration_seconds : most seconds one calibration may take.
    send_queue_frames : frames (binary and text) queued per session before the streamer waits.
    send_timeout : seconds one send may wait for a slow client before the session is closed
        (``slow_client``).
    near_far, near_far_r1, near_far_r2, near_far_resolution : near-far partition of each cell's
        stream (``visibility.nearfar``): radii in metres, cubemap face size in pixels; defaults
        and bounds are ``NearFarConfig``'s, checked when the settings are made.
    near_far_block : cubemap sharing: cells are grouped by blocks of this many grid columns on a
        side (per level), and a block shares one cubemap centre O, the centre of its most
        central cell (``visibility.nearfar.cells.cubemap_anchors``); 1: a cubemap per cell.
        Larger blocks bake and send fewer cubemaps and let the eye walk farther from O, where
        the morph hides the near/far seam that conventional compositing shows.
    near_far_cache_bytes : bound of the near-far caches (splits and encoded cubemaps shared by
        every session), bytes; a connected walker's current cell is never evicted.
    max_frame_bytes : largest binary geometry frame the server sends, bytes.
    max_message_bytes : largest text message the server accepts from a client, bytes.
    max_body_bytes : largest HTTP request body the server reads, bytes (larger: 413).
    hello_timeout : seconds a new WebSocket may wait before sending hello.
    ws_deflate : negotiate permessage-deflate (costs CPU; float geometry compresses poorly).
    ws_ping_interval : seconds between keep-alive pings (None: no pings).
    compute_deadline : seconds any one PVS computation may take, queueing included; a request
        may ask for less, never more. Past it the computation stops at the core's next
        checkpoint and its requests fail with ``deadline_exceeded``.
    max_compute_bytes : the most scratch memory one computation may be estimated to need
        (``Core.estimate_cost``), bytes; above it the request is refused (``over_limit``, 422).
    refuse_over_deadline : a request estimated to take more than this many times its deadline
        is refused the same way (the estimates are good to a factor of 2 to 3, so the default
        of 3 refuses what would almost surely be cancelled anyway).
    max_queued : computations that may wait for a worker; past it new requests are refused
        (``busy``, 503 with Retry-After). A walker's current cell is never refused for it.
    max_inflight_per_client : computations one HTTP client (by address) may have running or
        waiting at once (``too_many_requests``, 429 with Retry-After).
    heavy_seconds : computations estimated above this many seconds run in the heavy lane, as
        every HTTP request's computation does (its estimate is advice a client can skew).
    heavy_workers : workers the heavy lane may occupy at once (None: all but one, so a walker's
        current cell or a cheap prefetch always finds a worker; with one worker, that one).
    worker_nice : how much nicer (lower CPU priority, Linux) the session cores' worker threads
        run than the event loop and the first answers' worker: when computations fill the cores,
        streaming and first answers still get the CPU first (0: the same priority).
    pvs_rate, pvs_burst : PVS requests (HTTP) per second one client address may send, and the
        burst it may send at once; past them 429 ``too_many_requests`` before any parsing.
    shutdown_grace : seconds a stopping server gives open requests after it has cancelled their
        computations and closed the WebSocket sessions (1001), before it cancels them.
    log_level : uvicorn's log level.
    max_scene_triangles : most triangles a scene file may hold (at most 2**31: ids are int32);
        a file declaring or holding more is refused (``scene_load_failed`` naming the limit)
        before it is parsed where its format says its count. Default
        ``visibility.loaders.MAX_TRIANGLES``.
    max_scene_bytes : largest scene file loaded, bytes (a file is read whole, so its size is
        memory); a larger one is refused without reading it. Default
        ``visibility.loaders.MAX_FILE_BYTES``.
    tokens_file, tokens : access control (``server.auth``): a tokens file (JSON or TOML: each
        token's name, scenes and quotas, ``server.tokens``) and tokens with access to
        everything; with neither (the default) no route needs a token.
    cors_origins : origins whose pages may call the API from a browser (CORS) and open
        WebSockets (``*``: any; ``server.cors``); none (the default): no CORS headers and
        WebSockets from any origin.
    executor : where the session cores' computations run: ``local`` (this process's worker
        pool, the default) or ``dask://HOST:PORT`` (a ``distributed`` scheduler,
        ``server.dask_executor``; ``workers`` then bounds the local stand-in while the
        scheduler is away, and the pool gets a thread per cluster worker thread);
        ``dask://HOST:PORT?scenes=load``: the workers load each scene themselves (same file
        path, or the generator), checked by content hash, instead of receiving it scattered.
    cache : the PVS cache behind memory: ``"disk"`` (the default: ``cache_dir`` when set) or a
        Redis URL (``redis://host:port/db``, ``rediss://``, ``unix://``) that several replicas
        share for PVS and near-far cubemaps (``server.cache.shared``), before ``cache_dir``.
    redis_ttl : seconds a value lives in Redis (0: until Redis evicts it; bound the total with
        Redis's ``maxmemory`` and an LRU policy).
    redis_max_value_bytes : largest value written to Redis, bytes (larger ones stay local).
    redis_timeout : seconds one Redis call may take; past it Redis counts as down.
    redis_retry : seconds between pings of a Redis that is down (and of one that is up, so
        ``/health`` tells).
    viewer_three_dir : three.js's build folder the viewer's page imports (``/viewer/vendor/``);
        None: the repository's ``node_modules/three/build`` (``npm ci``).
    """

    model_config = ConfigDict(extra="forbid")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    scenes_dir: Path | None = None
    generated: dict[str, int] = Field(default_factory=default_generated)
    cell_size: float | None = Field(None, gt=0, allow_inf_nan=False)
    core: str = "sampling"
    core_params: dict[str, Any] = Field(default_factory=dict)
    workers: int = Field(2, ge=1, le=256)
    cache_bytes: int = Field(256 * 1024 * 1024, ge=0)
    cache_dir: Path | None = None
    prefetch: bool = True
    prefetch_ahead: float = Field(-0.2, ge=-1.0, le=1.0, allow_inf_nan=False)
    progressive: bool = True
    known_answers: bool = True
    calibrate: bool = True
    auto_budget: float = Field(1.0, gt=0, le=3600, allow_inf_nan=False)
    calibration_seconds: float = Field(120.0, gt=0, le=86400, allow_inf_nan=False)
    first_core: str = "sampling"
    preload_kernels: bool = True
    first_params: dict[str, Any] = Field(
        default_factory=lambda: {"samples": 4, "batch": 4, "resolution": 128})
    send_queue_frames: int = Field(16, ge=1, le=4096)
    send_timeout: float = Field(10.0, gt=0, allow_inf_nan=False)
    near_far: bool = False
    near_far_r1: float = Field(_NEAR_FAR_DEFAULT.r1, gt=0, allow_inf_nan=False)
    near_far_r2: float = Field(_NEAR_FAR_DEFAULT.r2, gt=0, allow_inf_nan=False)
    near_far_resolution: int = Field(_NEAR_FAR_DEFAULT.resolution, ge=NEAR_FAR_MIN_RESOLUTION,
                                     le=NEAR_FAR_MAX_RESOLUTION)
    near_far_block: int = Field(1, ge=1, le=64)
    near_far_cache_bytes: int = Field(256 * 1024 * 1024, ge=0)
    max_frame_bytes: int = Field(DEFAULT_MAX_FRAME_BYTES, ge=frame_bytes(1), le=64 * 1024 * 1024)
    max_message_bytes: int = Field(64 * 1024, ge=1024, le=16 * 1024 * 1024)
    max_body_bytes: int = Field(1024 * 1024, ge=1024, le=256 * 1024 * 1024)
    hello_timeout: float = Field(10.0, gt=0, allow_inf_nan=False)
    ws_deflate: bool = False
    ws_ping_interval: float | None = Field(20.0, gt=0)
    compute_deadline: float = Field(300.0, gt=0, le=86400, allow_inf_nan=False)
    max_compute_bytes: int = Field(4 << 30, ge=1 << 20)
    refuse_over_deadline: float = Field(3.0, ge=1.0, allow_inf_nan=False)
    max_queued: int = Field(64, ge=1, le=1 << 20)
    max_inflight_per_client: int = Field(4, ge=1, le=1 << 16)
    heavy_seconds: float = Field(2.0, gt=0, allow_inf_nan=False)
    heavy_workers: int | None = Field(None, ge=1, le=256)
    worker_nice: int = Field(5, ge=0, le=19)
    pvs_rate: float = Field(50.0, gt=0, allow_inf_nan=False)
    pvs_burst: int = Field(100, ge=1)
    shutdown_grace: float = Field(3.0, gt=0, le=600, allow_inf_nan=False)
    log_level: str = "info"
    # scene files
    max_scene_triangles: int = Field(MAX_TRIANGLES, ge=1, le=INT32_MAX + 1)
    max_scene_bytes: int = Field(MAX_FILE_BYTES, ge=1)
    # access control (server/auth.py); tokens are checked where no error message quotes them
    tokens_file: Path | None = None
    tokens: list[SecretStr] = Field(default_factory=list)
    cors_origins: list[str] = Field(default_factory=list)
    # where computations run
    executor: str = "local"

    @field_validator("executor")
    @classmethod
    def _executor(cls, v: str) -> str:
        from server.executor_address import scheduler_address

        scheduler_address(v)  # ValueError naming the two forms
        return v.strip()

    # shared cache (Redis)
    cache: str = "disk"
    redis_ttl: float = Field(7 * 86400.0, ge=0, allow_inf_nan=False)
    redis_max_value_bytes: int = Field(8 << 20, ge=1024, le=512 << 20)
    redis_timeout: float = Field(0.25, gt=0, le=30, allow_inf_nan=False)
    redis_retry: float = Field(2.0, gt=0, le=3600, allow_inf_nan=False)

    @field_validator("cache")
    @classmethod
    def _cache_url(cls, v: str) -> str:
        v = v.strip()
        if v == "disk":
            return v
        u = urlsplit(v)
        try:
            u.port  # noqa: B018 - raises ValueError for a port that is not a number
        except ValueError:
            raise ValueError(f"cache: bad port in Redis URL {v!r}") from None
        if u.scheme in ("redis", "rediss") and u.hostname or u.scheme == "unix" and u.path:
            return v
        raise ValueError(f"cache must be 'disk' or a Redis URL (redis://host:port/db, "
                         f"rediss://..., unix:///path), got {v!r}")
    viewer_three_dir: Path | None = None

    @field_validator("generated")
    @classmethod
    def _positive_sizes(cls, v: dict[str, int]) -> dict[str, int]:
        for name, n in v.items():
            if n <= 0:
                raise ValueError(f"generated scene {name!r} needs a positive triangle count")
        return v

    @field_validator("tokens_file")
    @classmethod
    def _tokens_file_reads(cls, v: Path | None) -> Path | None:
        if v is not None:
            from server.tokens import read_tokens_file

            read_tokens_file(v)
        return v

    @field_validator("cors_origins")
    @classmethod
    def _origins(cls, v: list[str]) -> list[str]:
        from server.cors import normalize_origins

        return normalize_origins(v)

    @model_validator(mode="after")
    def _near_far_config(self) -> Settings:
        # NearFarConfig is the one judge of radii and resolution: settings it would refuse
        # fail at start-up, not at every hello.
        self.near_far_config()
        return self

    def cell_size_for(self, scene_cell_size: float | None) -> float:
        """Viewcell size (metres) of a scene whose own (sidecar, hint) is ``scene_cell_size``:
        the server's setting when given, else the scene's, else ``DEFAULT_CELL_SIZE``."""
        return float(self.cell_size or scene_cell_size or DEFAULT_CELL_SIZE)

    def heavy_lane_workers(self) -> int:
        """Workers the heavy lane may occupy at once (``heavy_workers``, default all but one)."""
        if self.heavy_workers is not None:
            return min(self.heavy_workers, self.workers)
        return max(1, self.workers - 1)

    def near_far_config(self) -> NearFarConfig:
        """The ``NearFarConfig`` of these settings (ValueError when it is not a valid one)."""
        return NearFarConfig(r1=self.near_far_r1, r2=self.near_far_r2,
                             resolution=self.near_far_resolution)

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None, **overrides: Any) -> Settings:
        """Settings from ``PVS_*`` variables (``os.environ`` by default), then ``overrides``.

        PVS_HOST, PVS_PORT, PVS_SCENES_DIR, PVS_CELL_SIZE, PVS_CORE, PVS_CORE_PARAMS (a JSON
        object), PVS_WORKERS, PVS_CACHE_BYTES, PVS_MAX_FRAME_BYTES, PVS_MAX_MESSAGE_BYTES,
        PVS_HELLO_TIMEOUT, PVS_CACHE_DIR, PVS_PREFETCH, PVS_PREFETCH_AHEAD,
        PVS_PROGRESSIVE, PVS_KNOWN_ANSWERS, PVS_FIRST_CORE, PVS_FIRST_PARAMS (a JSON object),
        PVS_PRELOAD_KERNELS,
        PVS_CALIBRATE, PVS_AUTO_BUDGET, PVS_CALIBRATION_SECONDS,
        PVS_SEND_QUEUE_FRAMES, PVS_SEND_TIMEOUT,
        PVS_NEAR_FAR, PVS_NEAR_FAR_R1, PVS_NEAR_FAR_R2, PVS_NEAR_FAR_RESOLUTION,
        PVS_NEAR_FAR_CACHE_BYTES, PVS_NEAR_FAR_BLOCK, PVS_MAX_BODY_BYTES,
        PVS_WS_DEFLATE (1/0/true/false), PVS_WS_PING_INTERVAL ("none"
        disables), PVS_LOG_LEVEL, PVS_COMPUTE_DEADLINE, PVS_MAX_COMPUTE_BYTES, PVS_MAX_QUEUED,
        PVS_REFUSE_OVER_DEADLINE,
        PVS_MAX_INFLIGHT_PER_CLIENT, PVS_HEAVY_SECONDS, PVS_HEAVY_WORKERS, PVS_WORKER_NICE,
        PVS_SHUTDOWN_GRACE,
        PVS_PVS_RATE, PVS_PVS_BURST,
        PVS_MAX_SCENE_TRIANGLES, PVS_MAX_SCENE_BYTES,
        PVS_TOKENS_FILE, PVS_TOKENS and PVS_CORS_ORIGINS (comma lists),
        PVS_EXECUTOR (local or dask://HOST:PORT),
        PVS_CACHE, PVS_REDIS_TTL, PVS_REDIS_MAX_VALUE_BYTES, PVS_REDIS_TIMEOUT, PVS_REDIS_RETRY,
        PVS_VIEWER_THREE_DIR,
        PVS_GENERATED: a JSON object {name: triangles} or a comma list ``name[=triangles]``
        (a bare name takes the generator's default size; an empty value serves none).
        Raises ValueError (pydantic's ValidationError) on malformed values.
        """
        env = os.environ if env is None else env
        values: dict[str, Any] = {}
        # Every field is read from PVS_<FIELD> as it stands, but those parsed below.
        for field in cls.model_fields.keys() - _PARSED_ENV_FIELDS:
            var = "PVS_" + field.upper()
            if env.get(var, "") != "":
                values[field] = env[var]
        if "PVS_WS_PING_INTERVAL" in env:
            raw = env["PVS_WS_PING_INTERVAL"].strip().lower()
            values["ws_ping_interval"] = None if raw in ("", "none", "0") else raw
        for field, var in (("core_params", "PVS_CORE_PARAMS"),
                           ("first_params", "PVS_FIRST_PARAMS")):
            if env.get(var, "").strip():
                try:
                    params = json.loads(env[var])
                except json.JSONDecodeError as exc:
                    raise ValueError(f"{var} is not JSON: {exc}") from None
                if not isinstance(params, dict):
                    raise ValueError(f"{var} must be a JSON object")
                values[field] = params
        if "PVS_GENERATED" in env:
            values["generated"] = _parse_generated(env["PVS_GENERATED"])
        for field, var in (("tokens", "PVS_TOKENS"), ("cors_origins", "PVS_CORS_ORIGINS")):
            if env.get(var, "").strip():
                values[field] = [t.strip() for t in env[var].split(",") if t.strip()]
        if "tokens" in values:
            from server.tokens import env_grants

            env_grants(values["tokens"])  # a malformed token named by its place, not quoted
        values.update(overrides)
        return cls.model_validate(values)


#: Settings fields whose PVS_ variable ``Settings.from_env`` parses itself (JSON, lists, "none").
_PARSED_ENV_FIELDS = frozenset({"core_params", "first_params", "generated", "tokens",
                                "cors_origins", "ws_ping_interval"})


def _parse_generated(raw: str) -> dict[str, int]:
    raw = raw.strip()
    if not raw:
        return {}
    if raw.startswith("{"):
        try:
            data = json.loads(raw)
        except json.JSONDecodeError as exc:
            raise ValueError(f"PVS_GENERATED is not JSON: {exc}") from None
        if not isinstance(data, dict):
            raise ValueError("PVS_GENERATED must be a JSON object")
        return data
    defaults = default_generated()
    out: dict[str, int] = {}
    for item in filter(None, (s.strip() for s in raw.split(","))):
        name, _, size = item.partition("=")
        name = name.strip()
        if size.strip():
            n = float(size)
            if not math.isfinite(n) or n != int(n):
                raise ValueError(f"PVS_GENERATED: bad triangle count {size!r} for {name!r}")
            out[name] = int(n)
        elif name in defaults:
            out[name] = defaults[name]
        else:
            raise ValueError(f"PVS_GENERATED: no default size for {name!r}; give name=triangles")
    return out
