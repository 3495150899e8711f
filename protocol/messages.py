"""JSON message schemas of the streaming protocol (WebSocket text frames) and the HTTP PVS API.

Every message is a JSON object with a ``type`` field that picks its schema. Schemas are strict:
unknown fields, unknown types, NaN/inf numbers, strings where numbers belong and vice versa are
validation errors. Vectors are ``[x, y, z]`` in metres (Y-up, right-handed, see
``visibility/raster/camera.py``). Integers are bounded by the width the wire gives them
(``protocol.ints``): ``seq`` is uint32, cell and triangle ids int32, so a number past them is a
validation error of its message, not a failure of the frame encoder later.

Client to server: ``hello`` (once, first), then any number of ``pose``, optionally ``bye``.
Server to client: ``welcome`` (answer to hello), per cell change ``cell_begin``, binary geometry
frames (``protocol.frames``), ``cell_end``; ``error`` at any time (``fatal`` ones are followed by a
close, see ``protocol.codes``).

``parse_client_message`` / ``parse_server_message`` turn a frame into a model or raise
``ProtocolError`` carrying the ``ErrorCode`` the server reports for it; ``dump_message`` is the
inverse.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    StrictStr,
    TypeAdapter,
    ValidationError,
    model_validator,
)

from protocol.codes import ErrorCode
from protocol.ints import (
    INT64_MAX,
    INT64_MIN,
    Count32,
    Id32,
    Int64,
    PositiveUInt32,
    UInt16,
    UInt32,
    fits_uint32,
)
from protocol.version import PROTOCOL_VERSION

#: A finite float (ints accepted, strings, NaN and inf rejected).
FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
#: A 3-vector of finite floats, metres (or a unit direction).
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
Vec2 = tuple[FiniteFloat, FiniteFloat]
#: A finite float > 0 (a distance that cannot be zero: the welcome's near plane, metres).
PositiveFloat = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0.0)]
#: A non-negative integer with no wire width (sizes in bytes, vertex counts: server to client).
NonNegInt = Annotated[int, Field(strict=True, ge=0)]

#: A core parameter value (JSON scalar or list of scalars); integers are int64, as cores hold
#: them (each core checks its own narrower ranges, e.g. a seed in uint32).
ParamScalar = StrictBool | Int64 | FiniteFloat | StrictStr | None
ParamValue = ParamScalar | list[ParamScalar]


def _int64_params(params: Any) -> Any:
    """``params``, unless a value (or a list item) is a JSON integer outside int64. Checked
    before the union of types, whose float branch would take such an integer as a float."""
    if not isinstance(params, dict):
        return params
    for name, value in params.items():
        for v in value if isinstance(value, list) else (value,):
            if isinstance(v, int) and not isinstance(v, bool) and not (
                    INT64_MIN <= v <= INT64_MAX):
                raise ValueError(f"parameter {str(name)[:64]!r}: an integer of "
                                 f"{len(str(abs(v)))} digits does not fit in int64")
    return params


Params = Annotated[dict[StrictStr, ParamValue], BeforeValidator(_int64_params)]
#: Bound on names (scene, core, session) so a hostile hello cannot carry megabytes of name.
Name = Annotated[str, Field(strict=True, min_length=1, max_length=256)]


class ProtocolError(ValueError):
    """A frame that is not a valid message; ``code`` is what the server reports for it."""

    def __init__(self, code: ErrorCode, message: str, seq: int | None = None) -> None:
        super().__init__(message)
        self.code = ErrorCode(code)
        self.message = message
        self.seq = seq


#: What a cell's stream holds (``cell_begin.answer``): the session core's whole PVS, a cheap
#: first answer, or what refines a first answer into the core's PVS.
ANSWERS = ("full", "known", "first", "refined")
Answer = Literal["full", "known", "first", "refined"]


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# --------------------------------------------------------------------------- client -> server
class Hello(_Message):
    """Opens a session: which scene, which core with which parameters, how much the client holds.

    ``budget`` is the most triangles the client can hold (None: no limit).
    """

    type: Literal["hello"] = "hello"
    version: UInt16 = PROTOCOL_VERSION
    scene: Name
    #: None: the server's default core (the welcome names it); "auto": chosen per scene.
    core: Name | None = None
    params: Params = Field(default_factory=dict)
    budget: PositiveUInt32 | None = None
    #: Whether the server should send the cells ahead before the client reaches them (None:
    #: the server's setting).
    prefetch: StrictBool | None = None
    #: Whether a cell the walker needs now may come first as a cheap answer, refined in place
    #: (``cell_begin.answer``; None: the server's setting).
    progressive: StrictBool | None = None


class Pose(_Message):
    """Where the client's eye is at time ``t`` (seconds, client clock), metres; ``seq`` increases
    per pose and is echoed in the answers it triggers."""

    type: Literal["pose"] = "pose"
    #: uint32: the binary frames a pose triggers carry it in a uint32 header field.
    seq: UInt32
    t: FiniteFloat
    position: Vec3
    forward: Vec3
    velocity: Vec3 | None = None


class Bye(_Message):
    """Ends the session cleanly (the server closes with 1000)."""

    type: Literal["bye"] = "bye"
    reason: Annotated[str, Field(strict=True, max_length=1024)] | None = None


# --------------------------------------------------------------------------- server -> client
class SceneInfo(_Message):
    """What a client needs to know about the scene (``Scene.summary()`` plus its kind)."""

    name: str
    kind: Literal["file", "generated", "memory"]
    triangles: Count32
    valid_triangles: Count32
    vertices: NonNegInt
    objects: Count32
    spheres: Count32 = 0
    dynamic: bool = False
    states: NonNegInt = 1
    bounds: tuple[Vec3, Vec3]
    degenerate: dict[str, NonNegInt] = Field(default_factory=dict)
    #: How to rebuild the scene locally (ground truth): ``{"generator", "triangles", "seed"}``
    #: for a generated scene, ``{"file"}`` (the file's name) for a file scene.
    source: dict[str, str | int | float] = Field(default_factory=dict)


class GridInfo(_Message):
    """The viewcell grid (``ViewcellGrid.to_dict()``): metres; ``cells`` is the cell count."""

    cell_size: FiniteFloat
    origin_xz: Vec2
    cells: Count32
    levels: NonNegInt
    eye_range: Vec2
    bounds: tuple[Vec3, Vec3]


class Limits(_Message):
    """Sizes the server enforces: binary frames it sends, text messages it accepts (bytes)."""

    max_frame_bytes: NonNegInt
    max_message_bytes: NonNegInt


class Welcome(_Message):
    """Answer to ``hello``: the session id, the scene and grid, the core's full parameters, and
    the near plane its answers assume."""

    type: Literal["welcome"] = "welcome"
    version: UInt16 = PROTOCOL_VERSION
    session: str
    scene: SceneInfo
    grid: GridInfo
    core: str
    params: Params
    budget: PositiveUInt32 | None = None
    limits: Limits
    #: Whether cells ahead are streamed before the client reaches them (``cell_begin.prefetch``).
    prefetch: bool = False
    #: What the server leaves out for this scene and why, e.g. ``{"pvs": {"on": false, "why":
    #: ...}, "cubemap": {...}, "dynamic_updates": {...}, "cores": [...], "core_choice": {...}}``.
    features: dict[str, Any] = Field(default_factory=dict)
    #: The near plane (metres, along the view axis) the answers assume the client draws with:
    #: a conservative core keeps what such a client sees through a wall nearer than it, and a
    #: client drawing with a farther near plane may see holes. Clients use it as their camera's.
    near_plane: PositiveFloat


class CellBegin(_Message):
    """Start of a cell's stream: the PVS holds ``triangles`` ids, ``new`` of them not sent to this
    session before; they follow in ``chunks`` binary geometry frames, then ``cell_end``."""

    type: Literal["cell_begin"] = "cell_begin"
    cell: Id32
    seq: UInt32
    triangles: Count32
    new: Count32
    chunks: UInt32
    #: True for a cell ahead of the walker, sent before it gets there (lower priority).
    prefetch: bool = False
    #: Near-far partition of this cell's stream: ``{"r1", "r2", "center", "cubemap",
    #: "cubemap_cell"}`` (metres; ``center`` is the cubemap centre O, ``cubemap_cell`` the cell
    #: whose cubemap frame this cell composes with: cells of a block share one).
    near_far: dict[str, Any] | None = None
    #: Which answer the stream brings (``ANSWERS``): "full", the session core's PVS; "known",
    #: a first answer that cost nothing: the union of the core's PVS already known for the
    #: neighbouring cells; "first", a cheap computed one (the welcome's
    #: ``features.progressive``), both sent while that core computes; "refined", the rest of
    #: the core's PVS for a cell that got a first answer.
    answer: Answer = "full"


class CellEnd(_Message):
    """End of a cell's stream. ``seconds``: server wall time from the pose to this message;
    ``compute_seconds``: the PVS computation time (of the original computation when ``cached``)."""

    type: Literal["cell_end"] = "cell_end"
    cell: Id32
    seq: UInt32
    seconds: FiniteFloat
    compute_seconds: FiniteFloat = 0.0
    cached: bool = False
    prefetch: bool = False
    #: True when the stream was cut short (a prefetch stream yielding to the current cell's):
    #: the chunks that arrived are valid, but the cell is not complete.
    partial: bool = False
    #: The answer the stream brought (``cell_begin.answer``).
    answer: Answer = "full"


class Drop(_Message):
    """The client may (and, to stay within its budget, must) drop these triangle ids. ``cells``
    are the cells whose streams are no longer complete on the client because of it; the server
    will send their triangles again when needed."""

    type: Literal["drop"] = "drop"
    ids: list[Id32]
    cells: list[Id32] = Field(default_factory=list)
    reason: str = "budget"


class Error(_Message):
    """A problem. ``code`` is an ``ErrorCode`` value (kept as a string so a client tolerates codes
    newer than itself); ``seq`` names the pose it concerns, if any."""

    type: Literal["error"] = "error"
    code: StrictStr
    message: str
    fatal: bool = False
    seq: UInt32 | None = None


ClientMessage = Annotated[Hello | Pose | Bye, Field(discriminator="type")]
ServerMessage = Annotated[
    Welcome | CellBegin | CellEnd | Drop | Error, Field(discriminator="type")
]

CLIENT_TYPES = {"hello": Hello, "pose": Pose, "bye": Bye}
SERVER_TYPES = {"welcome": Welcome, "cell_begin": CellBegin, "cell_end": CellEnd, "drop": Drop,
                "error": Error}

_CLIENT_ADAPTER: TypeAdapter = TypeAdapter(ClientMessage)
_SERVER_ADAPTER: TypeAdapter = TypeAdapter(ServerMessage)


# --------------------------------------------------------------------------- HTTP API
def _exactly_one(*names: str) -> dict[str, Any]:
    """JSON schema: exactly one of the nullable properties ``names`` is given, not null."""
    return {"oneOf": [
        {"required": [name], "properties": {
            other: ({"not": {"type": "null"}} if other == name else {"type": "null"})
            for other in names}}
        for name in names
    ]}


class BoxPvsRequest(_Message):
    """Body of ``POST /scenes/{scene}/pvs``: an ad-hoc region, exactly one of a ``box``
    [min, max] and a ``segment`` [p, q] (metres; the triangles visible from some point of the
    segment)."""

    model_config = ConfigDict(extra="forbid", frozen=True,
                              json_schema_extra=_exactly_one("box", "segment"))

    box: tuple[Vec3, Vec3] | None = None
    segment: tuple[Vec3, Vec3] | None = None
    core: Name | None = None
    params: Params = Field(default_factory=dict)

    @model_validator(mode="after")
    def _box_ordered(self) -> BoxPvsRequest:
        if (self.box is None) == (self.segment is None):
            raise ValueError("give exactly one of 'box' and 'segment'")
        if self.box is not None:
            lo, hi = self.box
            if any(h < lo_ for lo_, h in zip(lo, hi, strict=True)):
                raise ValueError(f"box max < min: {list(lo)} > {list(hi)}")
        return self

    def region(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """The viewcell box [min, max] (metres) this request asks about."""
        if self.box is not None:
            return self.box
        p, q = self.segment
        return (tuple(map(min, p, q)), tuple(map(max, p, q)))


class PvsResponse(BaseModel):
    """Answer of the PVS routes: sorted triangle ids (and object ids with object granularity)."""

    model_config = ConfigDict(extra="forbid")

    scene: str
    core: str
    cell: int | None
    box: tuple[Vec3, Vec3]
    segment: tuple[Vec3, Vec3] | None = None
    granularity: str
    count: int
    triangle_ids: list[int]
    object_ids: list[int] | None = None
    seconds: float
    cached: bool
    params: dict[str, Any]
    stats: dict[str, Any]
    #: Why this core answered: "requested", "server default", or the ``auto`` choice's reason.
    chosen_because: str | None = None


class ErrorInfo(BaseModel):
    """An HTTP error: its ``ErrorCode`` (a string, so clients tolerate newer codes) and a
    message; request validation errors add ``details`` (one per problem)."""

    code: str
    message: str
    details: list[dict[str, Any]] | None = None


class ErrorResponse(BaseModel):
    """The body of every HTTP error answer."""

    error: ErrorInfo


class CoreParamInfo(BaseModel):
    """One parameter of a core: its name, type, default and, where known, unit, help, bounds
    and choices."""

    model_config = ConfigDict(extra="allow")

    name: str
    type: str | None = None
    default: Any = None
    unit: str | None = None
    help: str | None = None
    minimum: float | None = None
    maximum: float | None = None
    choices: list[Any] | None = None


class CoreInfo(BaseModel):
    """A visibility core: what it is, what it promises, its parameters, its quality knob and
    what it fits."""

    model_config = ConfigDict(extra="allow")

    name: str
    description: str = ""
    promise: str | None = None
    params: list[CoreParamInfo] = Field(default_factory=list)
    knob: str | None = None
    knob_levels: list[Any] | None = None
    native_segments: bool | None = None
    fits: Any = None


class CoreFit(BaseModel):
    """Whether a core fits a scene (``ok``), how well (``score``, higher is better) and why."""

    model_config = ConfigDict(extra="allow")

    core: str
    ok: bool
    score: float | None = None
    why: str = ""


class AutoChoice(BaseModel):
    """The core ``auto`` picks for a scene (None when no core fits) and why; ``params``: the
    parameters the choice comes with (a calibrated trial's knob level), ``calibrated``: whether
    a calibration decided (else the cores' declared fits did)."""

    model_config = ConfigDict(extra="allow")

    core: str | None = None
    why: str = ""
    params: dict[str, Any] = Field(default_factory=dict)
    calibrated: bool = False


class CoreFitReport(BaseModel):
    """Every core's fit for one scene, and the ``auto`` choice."""

    model_config = ConfigDict(extra="allow")

    cores: list[CoreFit]
    auto: AutoChoice


class CoresResponse(BaseModel):
    """Answer of ``GET /cores``: the server's default core, every core, and with ``?scene=``
    how each fits that scene."""

    default: str
    cores: list[CoreInfo]
    fit: CoreFitReport | None = None


# --------------------------------------------------------------------------- parse / dump
def _summarize(exc: ValidationError, limit: int = 5) -> str:
    parts = []
    for err in exc.errors(include_url=False)[:limit]:
        # The first loc element is the union tag; the rest is the field path.
        loc = ".".join(str(x) for x in err["loc"][1:]) or "message"
        parts.append(f"{loc}: {err['msg']}")
    more = exc.error_count() - limit
    if more > 0:
        parts.append(f"... and {more} more")
    return "; ".join(parts)


def _parse(data: str | bytes, adapter: TypeAdapter, types: dict, what: str) -> Any:
    try:
        obj = json.loads(data)
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, over-long integers
        raise ProtocolError(ErrorCode.BAD_JSON, f"not valid JSON: {exc}") from None
    except RecursionError:
        raise ProtocolError(ErrorCode.BAD_JSON, "JSON nested too deeply") from None
    if not isinstance(obj, dict):
        raise ProtocolError(
            ErrorCode.BAD_JSON, f"a message is a JSON object, got {type(obj).__name__}"
        )
    kind = obj.get("type")
    if not isinstance(kind, str):
        raise ProtocolError(ErrorCode.INVALID_MESSAGE, "a message needs a string 'type' field")
    if kind not in types:
        raise ProtocolError(
            ErrorCode.UNKNOWN_TYPE,
            f"unknown {what} message type {kind[:64]!r}; known: {sorted(types)}",
        )
    # The error names the pose only by a seq the wire can carry (an out-of-range seq is the
    # very thing being refused).
    seq = obj.get("seq") if fits_uint32(obj.get("seq")) else None
    try:
        return adapter.validate_python(obj)
    except ValidationError as exc:
        code = {"pose": ErrorCode.INVALID_POSE, "hello": ErrorCode.INVALID_HELLO}.get(
            kind, ErrorCode.INVALID_MESSAGE
        )
        raise ProtocolError(code, f"invalid {kind}: {_summarize(exc)}", seq) from None


def parse_client_message(data: str | bytes) -> Hello | Pose | Bye:
    """The client message in a text frame; ``ProtocolError`` (with its ``ErrorCode``) otherwise."""
    return _parse(data, _CLIENT_ADAPTER, CLIENT_TYPES, "client")


def parse_server_message(data: str | bytes) -> Welcome | CellBegin | CellEnd | Drop | Error:
    """The server message in a text frame; ``ProtocolError`` otherwise."""
    return _parse(data, _SERVER_ADAPTER, SERVER_TYPES, "server")


def dump_message(msg: BaseModel) -> str:
    """The JSON text of a message (compact; floats round-trip exactly)."""
    return msg.model_dump_json()
