"""HTTP routes: health, the scene catalogue, viewcells and PVS queries; JSON error bodies.

PVS answers come in three forms, chosen by the request's ``Accept`` header (media ranges with
q-values, ``server.negotiation``; no header: JSON; only other types acceptable: 406
``not_acceptable``):

- ``application/json`` (default): ``PvsResponse``;
- ``application/octet-stream``: the sorted triangle ids as packed little-endian int32
  (4 bytes per id, nothing else; the count is the body length / 4);
- ``application/vnd.pvs.geometry``: the PVS triangles as binary geometry frames
  (``protocol.frames``) back to back, each at most ``max_frame_bytes``; a frame's length is
  ``56 + 43 n`` with ``n`` at byte offset 24 of its header (none when the PVS is empty).

Binary answers carry ``X-PVS-Count``, ``X-PVS-Core``, ``X-PVS-Seconds`` and ``X-PVS-Cached``
headers.

Every error answers ``{"error": {"code": <ErrorCode>, "message": str}}`` (validation errors add
``"details"``) with its status: 404 unknown scene/cell/core/route, 406 no acceptable answer form,
413 a request body over ``settings.max_body_bytes`` (``too_big``), 422 bad parameters, NaN or an
inverted box, a region far outside the scene (``unsupported_region``), 500 a scene that fails
to load or a computation that fails.

Answers are encoded off the event loop (a PVS of 10^5 ids takes milliseconds to render), so a
big answer never delays other sessions' frames.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from protocol.codes import ErrorCode
from protocol.frames import chunk_geometry
from protocol.messages import BoxPvsRequest, PvsResponse
from protocol.version import PROTOCOL_VERSION
from server.catalog import LoadedScene, SceneLoadFailed, UnknownSceneError
from server.compute import (
    PVSResult,
    UnknownCellError,
    UnknownCoreError,
    UnsupportedSceneError,
)
from server.negotiation import choose_media_type
from visibility.cores.base import SegmentNotSupported

if TYPE_CHECKING:
    from server.app import ServerState

router = APIRouter()

#: ``Accept`` values of the binary PVS answers (see the module docstring).
IDS_MEDIA_TYPE = "application/octet-stream"
GEOMETRY_MEDIA_TYPE = "application/vnd.pvs.geometry"
JSON_MEDIA_TYPE = "application/json"
#: The answer forms of the PVS routes, in the server's order of preference (ties of q).
PVS_MEDIA_TYPES = (JSON_MEDIA_TYPE, IDS_MEDIA_TYPE, GEOMETRY_MEDIA_TYPE)
_PVS_RESPONSES: dict = {200: {"content": {
    "application/json": {},
    IDS_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"},
                     "description": "sorted triangle ids, packed little-endian int32"},
    GEOMETRY_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"},
                          "description": "geometry frames (protocol.frames) back to back"},
}}}


class ApiError(Exception):
    """An error answered as ``{"error": {"code", "message"}}`` with HTTP ``status``."""

    def __init__(self, status: int, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message


def error_response(status: int, code: str, message: str, **extra: Any) -> JSONResponse:
    """The JSON error body every route uses."""
    return JSONResponse({"error": {"code": str(code), "message": message, **extra}}, status)


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


def map_exception(exc: BaseException) -> ApiError | None:
    """The ApiError for a known failure of a scene/core/cell lookup or computation."""
    if isinstance(exc, ApiError):
        return exc
    if isinstance(exc, UnknownSceneError):
        return ApiError(404, ErrorCode.UNKNOWN_SCENE, str(exc.args[0] if exc.args else exc))
    if isinstance(exc, UnknownCellError):
        return ApiError(404, ErrorCode.UNKNOWN_CELL, str(exc))
    if isinstance(exc, UnknownCoreError):
        return ApiError(404, ErrorCode.UNKNOWN_CORE, str(exc.args[0] if exc.args else exc))
    if isinstance(exc, UnsupportedSceneError):
        return ApiError(422, ErrorCode.UNSUPPORTED_SCENE, str(exc))
    if isinstance(exc, SegmentNotSupported):
        return ApiError(422, ErrorCode.UNSUPPORTED_REGION, str(exc))
    if isinstance(exc, SceneLoadFailed):
        return ApiError(500, ErrorCode.SCENE_LOAD_FAILED, str(exc))
    return None


async def _loaded(request: Request, scene: str) -> LoadedScene:
    catalog = _state(request).catalog
    try:
        catalog.require(scene)
        # Loading can take seconds (file parse, walk-area detection): keep it off the loop.
        return await asyncio.to_thread(catalog.get, scene)
    except Exception as exc:
        api = map_exception(exc)
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


async def _pvs(
    request: Request,
    scene: str,
    core_name: str | None,
    params: dict[str, Any],
    cell: int | None = None,
    box: np.ndarray | None = None,
    segment: np.ndarray | None = None,
) -> Response:
    compute = _state(request).compute
    # Negotiated first: a request no answer form satisfies costs no computation.
    media = choose_media_type(request.headers.get("accept"), PVS_MEDIA_TYPES)
    if media is None:
        raise ApiError(406, ErrorCode.NOT_ACCEPTABLE,
                       f"no acceptable answer form; this route answers {list(PVS_MEDIA_TYPES)}")
    try:
        compute.catalog.require(scene)
        core, core_params = compute.resolve(core_name, params)
    except (UnknownSceneError, UnknownCoreError) as exc:
        raise map_exception(exc) from None
    except ValueError as exc:
        raise ApiError(422, ErrorCode.BAD_PARAMS, str(exc)) from None
    if box is not None or segment is not None:
        _check_region(await _loaded(request, scene), box if segment is None else segment)
    try:
        result: PVSResult = await compute.compute(scene, core, core_params, cell=cell, box=box,
                                                  segment=segment)
    except Exception as exc:
        api = map_exception(exc)
        if api is None:
            raise ApiError(500, ErrorCode.COMPUTE_FAILED,
                           f"PVS computation failed: {type(exc).__name__}: {exc}") from None
        raise api from None
    pvs = result.pvs
    if media != JSON_MEDIA_TYPE:
        headers = {"X-PVS-Count": str(len(pvs)), "X-PVS-Core": result.core,
                   "X-PVS-Seconds": repr(result.seconds), "X-PVS-Cached": str(result.cached)}
        ids = pvs.triangle_ids
        if media == GEOMETRY_MEDIA_TYPE:
            scene_obj = (await _loaded(request, scene)).scene
            limit = _state(request).settings.max_frame_bytes

            def encode() -> bytes:
                return b"".join(chunk_geometry(
                    ids, scene_obj.triangles(ids), scene_obj.colors[ids],
                    cell=-1 if cell is None else int(cell), max_frame_bytes=limit))

            body_bytes = await asyncio.to_thread(encode)
            return Response(body_bytes, media_type=GEOMETRY_MEDIA_TYPE, headers=headers)
        return Response(ids.astype("<i4").tobytes(), media_type=IDS_MEDIA_TYPE, headers=headers)

    def render() -> JSONResponse:
        return JSONResponse({
            "scene": scene,
            "core": result.core,
            "cell": result.cell,
            "box": result.box.tolist(),
            "segment": None if segment is None else segment.tolist(),
            "granularity": pvs.granularity,
            "count": len(pvs),
            "triangle_ids": pvs.triangle_ids.tolist(),
            "object_ids": None if pvs.object_ids is None else pvs.object_ids.tolist(),
            "seconds": result.seconds,
            "cached": result.cached,
            "params": jsonable(core_params.as_dict()),
            "stats": jsonable(pvs.stats),
        })

    return await asyncio.to_thread(render)


# --------------------------------------------------------------------------- routes
@router.get("/health", summary="Liveness and load")
async def health(request: Request) -> dict:
    """Server status: protocol version, uptime, open sessions, cache and worker statistics."""
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
        "stream": {k: v for k, v in st.counters.items() if k != "sessions_total"},
    }


@router.get("/scenes", summary="The scene catalogue")
async def list_scenes(request: Request) -> dict:
    """Every scene: name, kind (file, generated, memory), whether it is loaded, triangles."""
    return {"scenes": _state(request).catalog.listing()}


@router.get("/scenes/{scene}", summary="One scene: summary and viewcell grid")
async def scene_info(request: Request, scene: str) -> dict:
    """Counts, bounds, motion, degenerate-face report and the viewcell grid summary (loads the
    scene on first use)."""
    loaded = await _loaded(request, scene)
    return jsonable({**loaded.info, "grid": loaded.grid.to_dict()})


@router.get("/scenes/{scene}/cells", summary="The viewcells of a scene")
async def scene_cells(request: Request, scene: str) -> dict:
    """Every viewcell: id, grid column ``ij`` and box [[x0, y0, z0], [x1, y1, z1]] metres."""
    loaded = await _loaded(request, scene)
    grid = loaded.grid.to_dict(include_cells=True)
    cells = grid.pop("cell_list")
    return jsonable({"scene": scene, "grid": grid, "cells": cells})


@router.get(
    "/scenes/{scene}/cells/{cell}/pvs",
    summary="PVS of a viewcell",
    response_model=PvsResponse,
    responses=_PVS_RESPONSES,
)
async def cell_pvs(
    request: Request,
    scene: str,
    cell: int,
    core: str | None = None,
    granularity: Annotated[str | None, Query(description="triangle or object")] = None,
    # Declared (integers, strings accepted) so the spec documents them and fuzzers try them; the
    # core converts and checks them (422 ``bad_params``), from ``request.query_params``.
    resolution: Annotated[int | str | None, Query(description="resolution, pixels")] = None,
    samples: Annotated[int | str | None, Query(description="sampling: viewpoints")] = None,
    runs: Annotated[int | str | None, Query(description="from_segment: runs")] = None,
    seed: Annotated[int | str | None, Query(description="random seed")] = None,
) -> Any:
    """The PVS of grid cell ``cell`` (404 ``unknown_cell`` outside the grid). ``granularity``:
    ``triangle`` or ``object`` (every triangle of each visible object; 422 ``bad_params``
    otherwise, like every core parameter). Other query parameters are core parameters (e.g.
    ``resolution=64&samples=8``), converted to the core's types. ``Accept:
    application/octet-stream`` answers packed int32 ids, ``application/vnd.pvs.geometry``
    geometry frames."""
    params = {k: v for k, v in request.query_params.items() if k != "core"}
    return await _pvs(request, scene, core, params, cell=cell)


@router.post("/scenes/{scene}/pvs", summary="PVS of an ad-hoc box or segment",
             response_model=PvsResponse, responses=_PVS_RESPONSES)
async def box_pvs(request: Request, scene: str, body: BoxPvsRequest) -> Any:
    """The PVS of an arbitrary region: ``{"box": [min, max]}`` or ``{"segment": [p, q]}``
    (metres; ``cell`` is null in the answer, ``box`` is the region's bounding box). Cores that
    solve segments natively (``from_segment``, ``sampling``) answer the segment itself; others
    answer an axis-aligned segment as its degenerate box and refuse a diagonal one (422
    ``unsupported_region``). Binary answers as for the cell route."""
    if body.segment is not None:
        seg = np.asarray(body.segment, dtype=np.float64)
        return await _pvs(request, scene, body.core, dict(body.params), segment=seg)
    box = np.asarray(body.box, dtype=np.float64)
    return await _pvs(request, scene, body.core, dict(body.params), box=box)


# --------------------------------------------------------------------------- error handlers
def install_error_handlers(app: FastAPI) -> None:
    """Make every HTTP error answer the JSON error body."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return error_response(exc.status, exc.code, exc.message)

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
        named = {404: ErrorCode.NOT_FOUND, 406: ErrorCode.NOT_ACCEPTABLE,
                 413: ErrorCode.TOO_BIG}
        code = named.get(exc.status_code, f"http_{exc.status_code}")
        return error_response(exc.status_code, code, str(exc.detail))
