"""The wire protocol between the PVS server and its clients: JSON messages, binary geometry
frames, error and close codes. Imports nothing of the project beyond itself (numpy, pydantic)."""

from protocol.codes import CloseCode, ErrorCode, close_code_for, is_fatal
from protocol.frames import (
    DEFAULT_MAX_FRAME_BYTES,
    FrameError,
    GeometryChunk,
    chunk_geometry,
    decode_geometry,
    encode_geometry,
)
from protocol.messages import (
    Bye,
    CellBegin,
    CellEnd,
    Drop,
    Error,
    Hello,
    Pose,
    ProtocolError,
    Welcome,
    dump_message,
    parse_client_message,
    parse_server_message,
)
from protocol.version import PROTOCOL_VERSION

__all__ = [
    "DEFAULT_MAX_FRAME_BYTES",
    "PROTOCOL_VERSION",
    "Bye",
    "CellBegin",
    "CellEnd",
    "CloseCode",
    "Drop",
    "Error",
    "ErrorCode",
    "FrameError",
    "GeometryChunk",
    "Hello",
    "Pose",
    "ProtocolError",
    "Welcome",
    "chunk_geometry",
    "close_code_for",
    "decode_geometry",
    "dump_message",
    "encode_geometry",
    "is_fatal",
    "parse_client_message",
    "parse_server_message",
]
