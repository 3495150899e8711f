"""The opening of a session: ``hello`` in, checks, the scene loaded, ``welcome`` out.

Every error before ``welcome`` is fatal: ``Session.error`` closes and ends the session.
With access control on (``server.auth``) the token is checked before ``hello`` is read and the
scene against its allow list right after. Cheap checks go first (version, scene name, core and
parameters) so a bad hello never pays for loading a scene.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

import numpy as np

from protocol.codes import ErrorCode
from protocol.messages import (
    GridInfo,
    Hello,
    Limits,
    ProtocolError,
    SceneInfo,
    Welcome,
    parse_client_message,
)
from protocol.version import SUPPORTED_VERSIONS
from server.auth import admit_session, check_scene
from server.catalog import LoadedScene
from server.errors import error_code, error_message
from server.resolve import core_fits, offered_cores
from server.ws.dynamic import DynamicFrames
from server.ws.inventory import Inventory
from server.ws.nearfar import NearFarStreams
from visibility.cores.base import CoreParams
from visibility.raster.camera import DEFAULT_NEAR

if TYPE_CHECKING:
    from server.state import Session

#: Handshake errors answered with their own code; any other bad first message is
#: ``expected_hello``.
_OWN_CODE = (ErrorCode.BAD_JSON, ErrorCode.INVALID_HELLO, ErrorCode.TOO_BIG,
             ErrorCode.BINARY_UNSUPPORTED, ErrorCode.EXPECTED_HELLO)


def grid_info(loaded: LoadedScene) -> GridInfo:
    """The welcome's ``grid``."""
    d = loaded.grid.to_dict()
    return GridInfo(cell_size=d["cell_size"], origin_xz=tuple(d["origin_xz"]), cells=d["cells"],
                    levels=d["levels"], eye_range=tuple(d["eye_range"]),
                    bounds=tuple(map(tuple, d["bounds"])))


def scene_info(loaded: LoadedScene) -> SceneInfo:
    """The welcome's ``scene``."""
    i = loaded.info
    return SceneInfo(
        name=loaded.name, kind=loaded.kind, triangles=i["triangles"],
        valid_triangles=i["valid_triangles"], vertices=i["vertices"], objects=i["objects"],
        spheres=i["spheres"], dynamic=i["dynamic"], states=i["states"],
        bounds=tuple(map(tuple, i["bounds"])), degenerate=i["degenerate"],
        source=i.get("source", {}),
    )


def jsonable_params(params: CoreParams) -> dict[str, Any]:
    """Core parameters as JSON values (tuples as lists)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in params.as_dict().items()}


def near_plane(params: CoreParams) -> float:
    """The near plane (metres, along the view axis) the session's answers assume: the core's
    own ``near`` parameter where it has one (``from_segment``), else the clients' default the
    cores are built for (``visibility.raster.camera.DEFAULT_NEAR``; the conservative cores'
    ``visibility.topology.NEAR_CLEARANCE`` derives from it)."""
    near = params.as_dict().get("near")
    return DEFAULT_NEAR if near is None else float(near)


async def read_hello(session: Session) -> Hello:
    """The client's ``hello``, within ``settings.hello_timeout``; anything else is fatal."""
    try:
        text = await session.transport.receive(timeout=session.settings.hello_timeout)
        msg = parse_client_message(text)
    except ProtocolError as exc:
        if exc.code in _OWN_CODE:
            await session.error(exc.code, exc.message)
        await session.error(ErrorCode.EXPECTED_HELLO, f"the first message must be hello ({exc})")
    if not isinstance(msg, Hello):
        await session.error(ErrorCode.EXPECTED_HELLO,
                            f"the first message must be hello, got {msg.type}")
    return msg


async def handshake(session: Session) -> None:
    """Check the token (access control on), read and check ``hello``, load the scene, set up
    the session's parts, send ``welcome``. Registers the session in ``ServerState.sessions``
    just before the welcome leaves."""
    s = session
    await admit_session(s)
    msg = await read_hello(s)
    await check_scene(s, msg.scene)
    if msg.version not in SUPPORTED_VERSIONS:
        await s.error(ErrorCode.VERSION_MISMATCH,
                      f"protocol version {msg.version} not supported; server speaks "
                      f"{list(SUPPORTED_VERSIONS)}")
    catalog, resolver = s.state.catalog, s.state.resolver
    try:
        catalog.require(msg.scene)
        # A named core and its parameters are checked before paying for loading the scene.
        choice = resolver.resolve(msg.core, msg.params)
        s.loaded = await catalog.load(msg.scene)
        choice = choice or resolver.resolve(msg.core, msg.params, s.loaded)
        s.core, s.params, why = choice.core, choice.params, choice.why
    except Exception as exc:
        code = error_code(exc, params=True)
        if code is None:
            raise
        await s.error(code, error_message(exc))
    scene = s.loaded.scene
    ok, reason = core_fits(s.core, scene)
    if not ok:
        await s.error(ErrorCode.UNSUPPORTED_SCENE,
                      f"core {s.core.name!r} does not fit {msg.scene!r}: {reason}")
    settings = s.settings
    s.prefetch = settings.prefetch if msg.prefetch is None else bool(msg.prefetch)
    s.inventory = Inventory(scene.n_triangles, msg.budget)
    s.nearfar = NearFarStreams(settings, s.state.near_far, s.loaded)
    s.dynamic = DynamicFrames(scene, settings.max_frame_bytes, s.outbox, s.state.counters, s.id)
    valid = int(np.count_nonzero(scene.valid_faces))
    s.send_all = msg.budget is not None and valid <= msg.budget
    s.progressive, s.progressive_why = progressive_on(s, msg.progressive)
    features = await asyncio.to_thread(session_features, s, why, valid)
    # Registered before the welcome leaves: a client that has its welcome finds its session
    # (pins, /sessions, metrics) already there. ``run`` removes it on every way out.
    s.state.sessions[s.id] = s
    await s.transport.send_message(Welcome(
        session=s.id,
        scene=scene_info(s.loaded),
        grid=grid_info(s.loaded),
        core=s.core.name,
        params=jsonable_params(s.params),
        budget=msg.budget,
        limits=Limits(max_frame_bytes=settings.max_frame_bytes,
                      max_message_bytes=settings.max_message_bytes),
        prefetch=s.prefetch,
        features=features,
        near_plane=near_plane(s.params),
    ))
    s.welcomed = True


def progressive_on(s: Session, asked: bool | None) -> tuple[bool, str]:
    """Whether the session gets first answers refined in place (``settings.progressive``,
    the hello's ``progressive``), and why."""
    settings = s.settings
    if not settings.progressive:
        return False, "off on this server (PVS_PROGRESSIVE=0): the walker waits for the core"
    if asked is False:
        return False, "the client asked for the core's answers only"
    if s.send_all:
        return False, "the whole scene is sent: no PVS to refine"
    try:
        first = s.state.resolver.first()
    except (LookupError, ValueError) as exc:
        return False, f"the first answers' core is misconfigured: {exc}"
    if first.core.name == s.core.name and first.params.cache_key() == s.params.cache_key():
        return False, "the session's core is the first answers' core: nothing to refine"
    return True, (f"a cell not yet computed comes first as {first.core.name}'s cheap answer, then "
                  f"what {s.core.name} adds")


def session_features(s: Session, why: str, valid: int) -> dict[str, Any]:
    """What the session's streams include and leave out, and why (the welcome's
    ``features``); ``why``: why its core was chosen, ``valid``: the scene's valid triangles."""
    budget = s.inventory.budget
    if s.send_all:
        pvs = {"on": False, "why": f"the whole scene ({valid} valid triangles) fits the "
               f"client's budget of {budget}: it is sent whole, no PVS is computed"}
    else:
        pvs = {"on": True, "why": "no budget declared" if budget is None else
               f"the scene ({valid} triangles) exceeds the budget of {budget}"
               + ("; a cell whose near region (within r2) fits it is sent whole, "
                  "without a PVS" if s.settings.near_far else "")}
    scene = s.loaded.scene
    dynamic = scene.is_dynamic
    return {
        "pvs": pvs,
        "prefetch": {"on": s.prefetch},
        "progressive": progressive_feature(s),
        "delta": {"on": True, "why": "each triangle is sent once unless dropped"},
        "dynamic_updates": {"on": dynamic, "why": "the scene has moving triangles or "
                            "spheres: their keyframes follow their geometry" if dynamic
                            else "static scene: no dynamic updates"},
        "cubemap": s.nearfar.feature(),
        "cores": offered_cores(scene),
        "core_choice": {"core": s.core.name, "why": why},
    }


def progressive_feature(s: Session) -> dict[str, Any]:
    """The welcome's ``features.progressive``: on or off and why; the first answers' core and
    parameters when on."""
    out: dict[str, Any] = {"on": s.progressive, "why": s.progressive_why}
    if s.progressive:
        first = s.state.resolver.first()
        out["first"] = {"core": first.core.name, "params": jsonable_params(first.params)}
    return out
