"""Named error codes (the ``code`` of an ``error`` message) and WebSocket close codes.

Every error the server reports has an ``ErrorCode``. Whether it ends the session is fixed per code
and phase (``is_fatal``); a fatal error is followed by a WebSocket close whose code is
``close_code_for(code)``: standard codes where one fits (1003 unsupported data, 1008 policy
violation, 1009 message too big, 1011 internal error) and application codes in 4000-4999
otherwise (4000 + the HTTP status a REST call would get for the same problem, so 4004 means "not
found").

The rule: the session survives where it can. Before ``welcome`` nothing is agreed yet, so every
error ends the session. After ``welcome`` a bad message (malformed JSON, an unknown type, a binary
frame, a message over ``max_message_bytes``, an invalid pose) is answered with a non-fatal
``error`` and skipped; the session goes on with its current cell. The session closes only where
going on is unsafe or pointless: a second ``hello`` (the client believes in another session
than the server streams), the server's own failures, a client that stopped reading
(``slow_client``), a client past ``BAD_MESSAGE_LIMIT`` bad messages within
``BAD_MESSAGE_WINDOW_S`` seconds (``too_many_errors``: abuse), and a message above the WebSocket
library's hard cap (the library itself closes with 1009, before the session sees it).

| code               | fatal     | close | meaning                                          |
|--------------------|-----------|-------|--------------------------------------------------|
| bad_json           | handshake | 1008  | a text frame that is not a JSON object           |
| binary_unsupported | handshake | 1003  | a binary frame from the client (clients send text) |
| too_big            | handshake | 1009  | a message over ``max_message_bytes`` (HTTP: 413) |
| expected_hello     | yes       | 1008  | the first message was not ``hello``              |
| invalid_hello      | yes       | 1008  | ``hello`` failed validation                      |
| duplicate_hello    | yes       | 1008  | a second ``hello`` in one session                |
| version_mismatch   | yes       | 4001  | ``hello.version`` is not one the server speaks   |
| unknown_scene      | yes       | 4004  | no such scene in the catalogue                   |
| unknown_core       | yes       | 4005  | no such visibility core                          |
| bad_params         | yes       | 4022  | core parameters rejected                         |
| unsupported_scene  | yes       | 4023  | the core does not fit this scene (e.g. 2.5D only) |
| scene_load_failed  | yes       | 1011  | the scene file could not be loaded               |
| internal           | yes       | 1011  | a server bug; the session cannot go on           |
| slow_client        | yes       | 4008  | the client fell behind the stream past the limit |
| too_many_errors    | yes       | 1008  | bad messages past ``BAD_MESSAGE_LIMIT`` a window |
| unknown_type       | no        | -     | a message type this server does not know (skipped) |
| invalid_message    | no        | -     | a known type that failed validation (skipped)    |
| invalid_pose       | no        | -     | a pose with NaN/inf, a bad vector, a seq past uint32 |
| outside_grid       | no        | -     | a pose in no viewcell (the session keeps its cell) |
| compute_failed     | no        | -     | the PVS of a cell could not be computed          |
| over_budget        | no        | -     | a cell's PVS alone exceeds the client's budget   |
| deadline_exceeded  | no        | -     | past its deadline, or cancelled (HTTP 503)        |
| over_limit         | no        | -     | estimated cost over a server limit (HTTP 422)    |
| busy               | no        | -     | the queue is full (HTTP 503, Retry-After)        |
| too_many_requests  | no        | -     | a client at its cap of computations (HTTP 429)   |
| shutting_down      | yes       | 1001  | the server is stopping (HTTP 503)                |
| unauthorized       | yes       | 4401  | no valid bearer token (HTTP 401)                 |
| forbidden          | yes       | 4403  | the token may not use this scene (HTTP 403)      |
| over_quota         | yes       | 4429  | the token is past its own quota (HTTP 429)       |

"handshake": fatal while the server waits for ``hello``, answered and skipped afterwards. Bad
messages after ``welcome`` (the non-fatal protocol errors above) count towards the abuse limit.
HTTP-only codes: ``bad_request`` (400, a body that cannot be parsed), ``not_found`` (404),
``method_not_allowed`` (405), ``not_acceptable`` (406), ``validation`` (422). The last three
rows of the table come only from a server with access control on (``server.auth``); its
WebSocket refusals of a token happen before ``hello`` is read, of a scene right after it.
``HTTP_STATUS`` gives the HTTP status of every code an HTTP answer carries.
"""

from __future__ import annotations

from enum import IntEnum, StrEnum


class ErrorCode(StrEnum):
    """The ``code`` field of an ``error`` message (and of HTTP error bodies)."""

    BAD_JSON = "bad_json"
    BINARY_UNSUPPORTED = "binary_unsupported"
    TOO_BIG = "too_big"
    EXPECTED_HELLO = "expected_hello"
    INVALID_HELLO = "invalid_hello"
    DUPLICATE_HELLO = "duplicate_hello"
    VERSION_MISMATCH = "version_mismatch"
    UNKNOWN_SCENE = "unknown_scene"
    UNKNOWN_CORE = "unknown_core"
    UNKNOWN_CELL = "unknown_cell"
    BAD_PARAMS = "bad_params"
    UNSUPPORTED_SCENE = "unsupported_scene"
    UNSUPPORTED_REGION = "unsupported_region"
    SCENE_LOAD_FAILED = "scene_load_failed"
    INTERNAL = "internal"
    UNKNOWN_TYPE = "unknown_type"
    INVALID_MESSAGE = "invalid_message"
    INVALID_POSE = "invalid_pose"
    OUTSIDE_GRID = "outside_grid"
    COMPUTE_FAILED = "compute_failed"
    OVER_BUDGET = "over_budget"
    DEADLINE_EXCEEDED = "deadline_exceeded"
    OVER_LIMIT = "over_limit"
    BUSY = "busy"
    TOO_MANY_REQUESTS = "too_many_requests"
    SHUTTING_DOWN = "shutting_down"
    SLOW_CLIENT = "slow_client"
    TOO_MANY_ERRORS = "too_many_errors"
    # Access control (server.auth).
    UNAUTHORIZED = "unauthorized"
    FORBIDDEN = "forbidden"
    OVER_QUOTA = "over_quota"
    # HTTP only.
    BAD_REQUEST = "bad_request"
    NOT_FOUND = "not_found"
    METHOD_NOT_ALLOWED = "method_not_allowed"
    NOT_ACCEPTABLE = "not_acceptable"
    VALIDATION = "validation"


class CloseCode(IntEnum):
    """WebSocket close codes the server uses (RFC 6455 section 7.4 plus application codes)."""

    NORMAL = 1000
    GOING_AWAY = 1001
    UNSUPPORTED_DATA = 1003
    POLICY_VIOLATION = 1008
    MESSAGE_TOO_BIG = 1009
    INTERNAL_ERROR = 1011
    VERSION_MISMATCH = 4001
    SLOW_CLIENT = 4008
    UNKNOWN_SCENE = 4004
    UNKNOWN_CORE = 4005
    BAD_PARAMS = 4022
    UNSUPPORTED_SCENE = 4023
    #: Access control: 4000 + the HTTP status, as above.
    UNAUTHORIZED = 4401
    FORBIDDEN = 4403
    OVER_QUOTA = 4429


#: Bad messages a session answers and skips within ``BAD_MESSAGE_WINDOW_S`` seconds; one more
#: closes it with ``too_many_errors`` (a client that sends nothing but garbage is abusing it).
BAD_MESSAGE_LIMIT = 100
BAD_MESSAGE_WINDOW_S = 10.0

#: Codes that end the session in any phase, with the close code that follows the error message.
FATAL: dict[ErrorCode, CloseCode] = {
    ErrorCode.EXPECTED_HELLO: CloseCode.POLICY_VIOLATION,
    ErrorCode.INVALID_HELLO: CloseCode.POLICY_VIOLATION,
    ErrorCode.DUPLICATE_HELLO: CloseCode.POLICY_VIOLATION,
    ErrorCode.VERSION_MISMATCH: CloseCode.VERSION_MISMATCH,
    ErrorCode.UNKNOWN_SCENE: CloseCode.UNKNOWN_SCENE,
    ErrorCode.UNKNOWN_CORE: CloseCode.UNKNOWN_CORE,
    ErrorCode.BAD_PARAMS: CloseCode.BAD_PARAMS,
    ErrorCode.UNSUPPORTED_SCENE: CloseCode.UNSUPPORTED_SCENE,
    ErrorCode.SCENE_LOAD_FAILED: CloseCode.INTERNAL_ERROR,
    ErrorCode.INTERNAL: CloseCode.INTERNAL_ERROR,
    ErrorCode.SLOW_CLIENT: CloseCode.SLOW_CLIENT,
    ErrorCode.TOO_MANY_ERRORS: CloseCode.POLICY_VIOLATION,
    ErrorCode.SHUTTING_DOWN: CloseCode.GOING_AWAY,
    ErrorCode.UNAUTHORIZED: CloseCode.UNAUTHORIZED,
    ErrorCode.FORBIDDEN: CloseCode.FORBIDDEN,
    ErrorCode.OVER_QUOTA: CloseCode.OVER_QUOTA,
}

#: Codes that end the session only during the handshake (before ``welcome``); afterwards the
#: server answers them with a non-fatal error and skips the message.
HANDSHAKE_FATAL: dict[ErrorCode, CloseCode] = {
    ErrorCode.BAD_JSON: CloseCode.POLICY_VIOLATION,
    ErrorCode.BINARY_UNSUPPORTED: CloseCode.UNSUPPORTED_DATA,
    ErrorCode.TOO_BIG: CloseCode.MESSAGE_TOO_BIG,
}


#: The HTTP status of an answer carrying each code (the codes HTTP routes answer).
HTTP_STATUS: dict[ErrorCode, int] = {
    ErrorCode.BAD_REQUEST: 400,
    ErrorCode.UNAUTHORIZED: 401,
    ErrorCode.FORBIDDEN: 403,
    ErrorCode.UNKNOWN_SCENE: 404,
    ErrorCode.UNKNOWN_CELL: 404,
    ErrorCode.UNKNOWN_CORE: 404,
    ErrorCode.NOT_FOUND: 404,
    ErrorCode.METHOD_NOT_ALLOWED: 405,
    ErrorCode.NOT_ACCEPTABLE: 406,
    ErrorCode.TOO_BIG: 413,
    ErrorCode.VALIDATION: 422,
    ErrorCode.BAD_PARAMS: 422,
    ErrorCode.UNSUPPORTED_SCENE: 422,
    ErrorCode.UNSUPPORTED_REGION: 422,
    ErrorCode.OVER_LIMIT: 422,
    ErrorCode.TOO_MANY_REQUESTS: 429,
    ErrorCode.OVER_QUOTA: 429,
    ErrorCode.DEADLINE_EXCEEDED: 503,
    ErrorCode.BUSY: 503,
    ErrorCode.SHUTTING_DOWN: 503,
    ErrorCode.SCENE_LOAD_FAILED: 500,
    ErrorCode.COMPUTE_FAILED: 500,
    ErrorCode.INTERNAL: 500,
}


def is_fatal(code: ErrorCode | str, *, handshake: bool = False) -> bool:
    """Whether an error with this code ends the WebSocket session; ``handshake``: the session
    is still waiting for ``hello`` (where every bad message is fatal)."""
    c = ErrorCode(code)
    return c in FATAL or (handshake and c in HANDSHAKE_FATAL)


def close_code_for(code: ErrorCode | str) -> CloseCode:
    """The WebSocket close code sent after a fatal error with this code; NORMAL for codes that
    are never fatal."""
    c = ErrorCode(code)
    return FATAL.get(c) or HANDSHAKE_FATAL.get(c, CloseCode.NORMAL)
