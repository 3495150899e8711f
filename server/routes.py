"""HTTP routes: health, the scene catalogue, the cores, viewcells and PVS queries; JSON error
bodies.

PVS answers come in three forms, chosen by the request's ``Accept`` header (media ranges with
q-values, ``server.negotiation``; no header: JSON; only other types acceptable: 406
``not_acceptable``):

- ``application/json`` (default): ``PvsResponse``;
- ``application/octet-stream``: the sorted triangle ids as packed little-endian int32
  (4 bytes per id, nothing else; the count is the body length / 4);
- ``application/vnd.pvs.geometry``: the PVS triangles as binary geometry frames
  (``protocol.frames``) back to back, each at most ``max_frame_bytes``; a frame's length is
  ``56 + 43 n`` with ``n`` at byte offset 24 of its header (none when the PVS is empty).

Binary answers carry ``X-PVS-Count``, ``X-PVS-Core``, ``X-PVS-Core-Reason``, ``X-PVS-Seconds``
and ``X-PVS-Cached`` headers. ``core=auto`` picks a core per scene, as on the WebSocket; the
answer says why (``chosen_because``, ``X-PVS-Core-Reason``).

Every error answers ``{"error": {"code": <ErrorCode>, "message": str}}`` (validation errors add
``"details"``; codes and statuses from ``server.errors``) with its status: 400 a body that
cannot be parsed, 404 unknown scene/cell/core/route, 405 a method the route lacks (with
``Allow``), 406 no acceptable answer form, 413 a request body over ``settings.max_body_bytes``
(``too_big``), 422 bad parameters, NaN or an inverted box, a region far outside the scene
(``unsupported_region``), 500 a scene that fails to load or a computation that fails. The
OpenAPI schema documents each route's (``server.openapi``).

Answers are encoded off the event loop (a PVS of 10^5 ids takes milliseconds to render), so a
big answer never delays other sessions' frames.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Awaitable
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from protocol.codes import ErrorCode
from protocol.frames import chunk_geometry
from protocol.messages import BoxPvsRequest, CoresResponse, ErrorResponse, PvsResponse
from protocol.version import PROTOCOL_VERSION
from server.auth import visible_scenes
from server.catalog import LoadedScene, wire_origin
from server.errors import ApiError, code_for_status, error_body
from server.negotiation import choose_media_type
from server.region import PVSResult
from server.resolve import CoreChoice
from server.state import ServerState
from visibility.cancel import ComputationCancelled
from visibility.cores.base import AUTO_CORE, available_cores, describe_cores, get_core

__all__ = ["ApiError", "error_response", "install_error_handlers", "jsonable", "router"]

router = APIRouter()

#: ``Accept`` values of the binary PVS answers (see the module docstring).
IDS_MEDIA_TYPE = "application/octet-stream"
GEOMETRY_MEDIA_TYPE = "application/vnd.pvs.geometry"
JSON_MEDIA_TYPE = "application/json"
#: The answer forms of the PVS routes, in the server's order of preference (ties of q).
PVS_MEDIA_TYPES = (JSON_MEDIA_TYPE, IDS_MEDIA_TYPE, GEOMETRY_MEDIA_TYPE)
#: Headers of the binary PVS answers (JSON answers carry the same facts in the body).
_PVS_HEADERS: dict[str, str] = {
    "X-PVS-Count": "the number of triangle ids",
    "X-PVS-Core": "the core that answered",
    "X-PVS-Core-Reason": "why that core answered (\"requested\", \"server default\" or the "
                         "auto choice's reason)",
    "X-PVS-Seconds": "the computation's time in seconds (the original one when cached)",
    "X-PVS-Cached": "True when the answer came from the cache",
}
_PVS_OK: dict[int, dict] = {200: {
    "description": "The PVS, in the form the Accept header asks for.",
    "headers": {name: {"description": f"binary answers only: {doc}",
                       "schema": {"type": "string"}} for name, doc in _PVS_HEADERS.items()},
    "content": {
        JSON_MEDIA_TYPE: {},
        IDS_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"},
                         "description": "sorted triangle ids, packed little-endian int32"},
        GEOMETRY_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"},
                              "description": "geometry frames (protocol.frames) back to back"},
    },
}}


def _errors(**why: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` of the errors a route answers: ``e404="unknown scene"`` documents a
    404 with the JSON error body (``ErrorResponse``) and that description."""
    return {int(k[1:]): {"model": ErrorResponse, "description": v} for k, v in why.items()}


def error_response(status: int, code: str, message: str, **extra: Any) -> JSONResponse:
    """The JSON error body every route uses, with ``status``."""
    return JSONResponse(error_body(code, message, **extra), status)


def jsonable(obj: Any) -> Any:
    """``obj`` with numpy scalars/arrays turned into Python values and NaN/inf into None."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def _state(request: Request) -> ServerState:
    return request.app.state.server


async def _loaded(request: Request, scene: str) -> LoadedScene:
    try:
        return await _state(request).catalog.load(scene)
    except Exception as exc:
        api = ApiError.of(exc)
        if api is None:
            raise
        raise api from None


#: Smallest margin (metres) around a scene's bounds within which ad-hoc regions are answered.
REGION_MARGIN_MIN = 1000.0


def _check_region(loaded: LoadedScene, region: np.ndarray) -> None:
    """Refuse (422 ``unsupported_region``) a box or segment (2, 3) with a corner farther from
    the scene's bounds than the larger of its diagonal and ``REGION_MARGIN_MIN`` metres: such a
    region sees the scene as a speck at best, and coordinates near the float limits overflow the
    cores' arithmetic into wrong answers."""
    bounds = np.asarray(loaded.info.get("bounds", loaded.scene.bounds()), dtype=np.float64)
    margin = max(float(np.linalg.norm(bounds[1] - bounds[0])), REGION_MARGIN_MIN)
    lo, hi = bounds[0] - margin, bounds[1] + margin
    if np.any(region < lo) or np.any(region > hi):
        raise ApiError(422, ErrorCode.UNSUPPORTED_REGION,
                       f"region {np.asarray(region).tolist()} lies too far from the scene "
                       f"(answered within {lo.tolist()} .. {hi.tolist()} metres)")


async def _resolve(request: Request, scene: str, core_name: str | None,
                   params: dict[str, Any]) -> tuple[LoadedScene, CoreChoice]:
    """The loaded scene and the request's core choice (``server.resolve``: ``auto`` decided
    for the scene). Cheap checks first: an unknown scene, core or parameter never loads a
    scene."""
    state = _state(request)
    try:
        state.catalog.require(scene)
        choice = state.resolver.resolve(core_name, params)
        loaded = await _loaded(request, scene)
        choice = choice or state.resolver.resolve(core_name, params, loaded)
    except Exception as exc:
        api = ApiError.of(exc, params=True)
        if api is None:
            raise
        raise api from None
    return loaded, choice


#: Seconds between checks, while a PVS is computed, that the HTTP client is still there.
DISCONNECT_POLL_S = 0.25


def client_of(request: Request) -> str:
    """Who an HTTP request counts against for ``max_inflight_per_client``: its peer address
    (behind a proxy, uvicorn's ``--forwarded-allow-ips`` makes it the forwarded one)."""
    return f"http:{request.client.host if request.client else '?'}"


async def _unless_gone(request: Request, work: Awaitable[Any]) -> Any:
    """Await ``work``; when the HTTP client disconnects first, cancel it (the computation is
    then cancelled unless another request or walker wants it: ``ComputeService.release``)
    and raise ``ClientGone``."""
    task = asyncio.ensure_future(work)
    try:
        while True:
            done, _ = await asyncio.wait({task}, timeout=DISCONNECT_POLL_S)
            if done:
                return task.result()
            if await request.is_disconnected():
                raise ClientGone
    finally:
        if not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task


#: The status logged for a request whose client left before the answer (nginx's 499; no
#: client receives it).
CLIENT_CLOSED_REQUEST = 499


class ClientGone(Exception):
    """The HTTP client left before its answer was ready (nobody to answer)."""


def _header_text(text: str) -> str:
    """``text`` as a header value (latin-1 only, one line)."""
    return " ".join(text.encode("ascii", "replace").decode().split())


async def _pvs(
    request: Request,
    scene: str,
    core_name: str | None,
    params: dict[str, Any],
    cell: int | None = None,
    box: np.ndarray | None = None,
    segment: np.ndarray | None = None,
    deadline: float | None = None,
) -> Response:
    compute = _state(request).compute
    # Negotiated first: a request no answer form satisfies costs no computation.
    media = choose_media_type(request.headers.get("accept"), PVS_MEDIA_TYPES)
    if media is None:
        raise ApiError.coded(ErrorCode.NOT_ACCEPTABLE, "no acceptable answer form; this route "
                             f"answers {list(PVS_MEDIA_TYPES)}")
    loaded, choice = await _resolve(request, scene, core_name, params)
    core_params, why = choice.params, choice.why
    if box is not None or segment is not None:
        _check_region(loaded, box if segment is None else segment)
    try:
        result: PVSResult = await _unless_gone(request, compute.compute(
            scene, choice.core, core_params, cell=cell, box=box, segment=segment, deadline=deadline,
            client=client_of(request)))
    except ClientGone:
        _state(request).counters["http_abandoned"] += 1
        return Response(status_code=CLIENT_CLOSED_REQUEST)
    except Exception as exc:
        if isinstance(exc, ComputationCancelled) and _state(request).stopping:
            raise ApiError.coded(ErrorCode.SHUTTING_DOWN, "the server is shutting down; "
                                 "retry on another server or later") from None
        api = ApiError.of(exc)
        if api is None:
            raise ApiError.coded(ErrorCode.COMPUTE_FAILED, "PVS computation failed: "
                                 f"{type(exc).__name__}: {exc}") from None
        raise api from None
    pvs = result.pvs
    if media != JSON_MEDIA_TYPE:
        headers = {"X-PVS-Count": str(len(pvs)), "X-PVS-Core": result.core,
                   "X-PVS-Core-Reason": _header_text(why),
                   "X-PVS-Seconds": repr(result.seconds), "X-PVS-Cached": str(result.cached)}
        ids = pvs.triangle_ids
        if media == GEOMETRY_MEDIA_TYPE:
            scene_obj = loaded.scene
            limit = _state(request).settings.max_frame_bytes

            def encode() -> bytes:
                return b"".join(chunk_geometry(
                    ids, scene_obj.triangles(ids), scene_obj.colors[ids],
                    cell=-1 if cell is None else int(cell), max_frame_bytes=limit,
                    origin=wire_origin(scene_obj)))

            body_bytes = await asyncio.to_thread(encode)
            return Response(body_bytes, media_type=GEOMETRY_MEDIA_TYPE, headers=headers)
        return Response(ids.astype("<i4").tobytes(), media_type=IDS_MEDIA_TYPE, headers=headers)

    def render() -> Response:
        answer = PvsResponse(
            scene=scene,
            core=result.core,
            cell=result.cell,
            box=result.box.tolist(),
            segment=None if segment is None else segment.tolist(),
            granularity=pvs.granularity,
            count=len(pvs),
            triangle_ids=pvs.triangle_ids.tolist(),
            object_ids=None if pvs.object_ids is None else pvs.object_ids.tolist(),
            seconds=result.seconds,
            cached=result.cached,
            params=jsonable(core_params.as_dict()),
            stats=jsonable(pvs.stats),
            chosen_because=why,
        )
        return Response(answer.model_dump_json(), media_type=JSON_MEDIA_TYPE)

    return await asyncio.to_thread(render)


# --------------------------------------------------------------------------- routes
@router.get("/health", summary="Liveness and load")
async def health(request: Request) -> dict:
    """Server status: protocol version, uptime, open sessions, cache and worker statistics;
    ``cache`` names the cache backend and whether it is up (a Redis that is down leaves the
    server serving from memory and recomputing: status stays ok)."""
    st = _state(request)
    listing = st.catalog.names()
    return {
        "status": "ok",
        "version": PROTOCOL_VERSION,
        "uptime_s": time.monotonic() - st.started,
        "sessions": len(st.sessions),
        "sessions_total": st.counters["sessions_total"],
        "scenes": len(listing),
        "compute": st.compute.stats(),
        "cache": st.compute.cache.state(),
        "stream": {k: v for k, v in st.counters.items() if k != "sessions_total"},
    }


@router.get("/scenes", summary="The scene catalogue")
async def list_scenes(request: Request) -> dict:
    """Every scene (with access control, every scene the token may use): name, kind (file,
    generated, memory), whether it is loaded, triangles."""
    return {"scenes": visible_scenes(request.scope, _state(request).catalog.listing())}


_SCENE_ERRORS = _errors(e404="unknown scene (unknown_scene)",
                        e500="the scene failed to load (scene_load_failed)")


@router.get("/scenes/{scene}", summary="One scene: summary and viewcell grid",
            responses=_SCENE_ERRORS)
async def scene_info(request: Request, scene: str) -> dict:
    """Counts, bounds, motion, degenerate-face report and the viewcell grid summary (loads the
    scene on first use)."""
    loaded = await _loaded(request, scene)
    return jsonable({**loaded.info, "grid": loaded.grid.to_dict()})


@router.get("/scenes/{scene}/cells", summary="The viewcells of a scene",
            responses=_SCENE_ERRORS)
async def scene_cells(request: Request, scene: str) -> dict:
    """Every viewcell: id, grid column ``ij``, box [[x0, y0, z0], [x1, y1, z1]], floor height
    and ``walk``, a point of the cell where one may walk (metres)."""
    loaded = await _loaded(request, scene)
    grid = loaded.grid.to_dict(include_cells=True)
    cells = grid.pop("cell_list")
    return jsonable({"scene": scene, "grid": grid, "cells": cells})


@router.get("/cores", summary="The visibility cores", response_model=CoresResponse,
            responses=_SCENE_ERRORS)
async def list_cores(
    request: Request,
    scene: Annotated[str | None,
                     Query(description="also report how each core fits this scene")] = None,
) -> Any:
    """Every core with its parameters (name, type, default, unit, bounds) and what it fits;
    ``default`` is the core a request without one gets. With ``scene``, ``fit`` says how each
    core fits that scene and what ``auto`` picks there, the very choice a session or PVS
    request with ``core=auto`` gets now (``server.calibration``; 404 ``unknown_scene``)."""
    answer: dict[str, Any] = {"default": _state(request).settings.core,
                              "cores": await asyncio.to_thread(describe_cores)}
    if scene is not None:
        loaded = await _loaded(request, scene)
        answer["fit"] = await asyncio.to_thread(_state(request).resolver.calibration.report,
                                                loaded)
    return Response(CoresResponse.model_validate(jsonable(answer)).model_dump_json(),
                    media_type=JSON_MEDIA_TYPE)


DEADLINE_HELP = ("seconds the computation may take, queueing included (capped by the "
                 "server's compute_deadline); past it: 503 deadline_exceeded")

_PVS_ERRORS = dict(
    e404="unknown scene, cell or core (unknown_scene, unknown_cell, unknown_core)",
    e406="no answer form the Accept header allows (not_acceptable)",
    e422="bad parameters (validation, bad_params), a core that does not fit the scene "
         "(unsupported_scene), a computation estimated over a server limit (over_limit: the "
         "body names the limit, its value and the estimate)",
    e429="this client already has max_inflight_per_client computations in flight "
         "(too_many_requests; Retry-After)",
    e500="the scene failed to load or the computation failed (scene_load_failed, "
         "compute_failed)",
    e503="the queue is full (busy; Retry-After), the deadline passed (deadline_exceeded) or "
         "the server is stopping (shutting_down)",
)


def core_query_parameters() -> list[dict[str, Any]]:
    """OpenAPI query parameters for every core parameter, from the cores' own declarations
    (``Core.param_specs``): one entry per name, its help per core, range and unit. The core
    converts and checks the values (422 ``bad_params``); they are read from the query string."""
    by_name: dict[str, dict[str, Any]] = {}
    for name in available_cores():
        for spec in get_core(name).param_specs():
            entry = by_name.setdefault(spec.name, {"types": set(), "lines": []})
            entry["types"].add(spec.type)
            entry["lines"].append(f"{name}: {spec.describe()}")
    out = []
    for pname, entry in by_name.items():
        # Strings are accepted too: the core converts "32" to 32 and says why it refuses.
        types = sorted(entry["types"] | {"string"})
        out.append({"name": pname, "in": "query", "required": False,
                    "description": ". ".join(entry["lines"]),
                    "schema": {"anyOf": [{"type": t} for t in types]}})
    return out


@router.get(
    "/scenes/{scene}/cells/{cell}/pvs",
    summary="PVS of a viewcell",
    response_model=PvsResponse,
    responses={**_PVS_OK, **_errors(**_PVS_ERRORS)},
    openapi_extra={"parameters": core_query_parameters()},
)
async def cell_pvs(
    request: Request,
    scene: str,
    cell: int,
    core: Annotated[str | None, Query(description=f"a core of GET /cores, or {AUTO_CORE!r}: "
                                      "chosen for the scene")] = None,
    deadline: Annotated[float | None, Query(gt=0, le=86400, description=DEADLINE_HELP)] = None,
) -> Any:
    """The PVS of grid cell ``cell`` (404 ``unknown_cell`` outside the grid). ``core=auto``
    picks a core for the scene (``chosen_because`` says why). ``granularity``: ``triangle`` or
    ``object`` (every triangle of each visible object; 422 ``bad_params`` otherwise, like every
    core parameter). Other query parameters are core parameters (e.g.
    ``resolution=64&samples=8``), converted to the core's types. ``Accept:
    application/octet-stream`` answers packed int32 ids, ``application/vnd.pvs.geometry``
    geometry frames."""
    params = {k: v for k, v in request.query_params.items() if k not in ("core", "deadline")}
    return await _pvs(request, scene, core, params, cell=cell, deadline=deadline)


@router.post("/scenes/{scene}/pvs", summary="PVS of an ad-hoc box or segment",
             response_model=PvsResponse,
             responses={**_PVS_OK, **_errors(
                 e400="the body cannot be parsed (bad_request)",
                 e413="the body is over the server's limit (too_big)",
                 **{**_PVS_ERRORS, "e422": "an invalid body (validation: not exactly one of "
                    "box and segment, an inverted box, NaN), bad parameters (bad_params), a "
                    "core that does not fit the scene (unsupported_scene), a region far "
                    "outside the scene or a diagonal segment for a box-only core "
                    "(unsupported_region)"})})
async def box_pvs(
    request: Request, scene: str, body: BoxPvsRequest,
    deadline: Annotated[float | None, Query(gt=0, le=86400, description=DEADLINE_HELP)] = None,
) -> Any:
    """The PVS of an arbitrary region: exactly one of ``{"box": [min, max]}`` and
    ``{"segment": [p, q]}`` (metres; ``cell`` is null in the answer, ``box`` is the region's
    bounding box). Cores with ``native_segments`` (``GET /cores``) answer
    the segment itself; others answer an axis-aligned segment as its degenerate box and refuse
    a diagonal one (422 ``unsupported_region``). ``core`` as for the cell route (``auto``
    included). Binary answers as for the cell route."""
    if body.segment is not None:
        seg = np.asarray(body.segment, dtype=np.float64)
        return await _pvs(request, scene, body.core, dict(body.params), segment=seg,
                          deadline=deadline)
    box = np.asarray(body.box, dtype=np.float64)
    return await _pvs(request, scene, body.core, dict(body.params), box=box, deadline=deadline)


# --------------------------------------------------------------------------- error handlers
def install_error_handlers(app: FastAPI) -> None:
    """Make every HTTP error answer the JSON error body."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        response = error_response(exc.status, exc.code, exc.message, **jsonable(exc.extra))
        response.headers.update(exc.headers)
        return response

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        details = [
            {"loc": [str(x) for x in e.get("loc", ())], "msg": str(e.get("msg", "")),
             "type": str(e.get("type", ""))}
            for e in exc.errors()
        ]
        summary = "; ".join(f"{'.'.join(d['loc'])}: {d['msg']}" for d in details[:5])
        return error_response(422, ErrorCode.VALIDATION, summary or "invalid request",
                              details=details)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        # The framework's own errors (no route, a method the route lacks, an unparsable body,
        # a body over the limit); their headers (405's Allow) go along.
        response = error_response(exc.status_code, code_for_status(exc.status_code),
                                  str(exc.detail))
        response.headers.update(exc.headers or {})
        return response
