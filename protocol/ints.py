"""Integer ranges the wire carries, as constants and as pydantic field types.

Every integer a message carries ends up somewhere with a fixed width: ``seq`` in the uint32 field
of every binary frame header, cell ids in their int32 field, triangle ids in int32 arrays, seeds
in numpy's uint32 generators. A JSON number has no width, so the message schemas bound each one
here, at the edge: an integer the wire cannot carry is a validation error of the message it came
in (answered, and skipped where the session survives that), never an overflow deep in an encoder
that would end the session as a server failure.

Imports nothing of the project (the frame modules and the message schemas both use it).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

#: Largest uint16 (protocol versions: the frame header's version field).
UINT16_MAX = 2**16 - 1
#: Largest uint32 (``seq``, chunk indices and counts, triangle counts in frame headers; seeds).
UINT32_MAX = 2**32 - 1
#: Smallest and largest int32 (cell ids, -1 for none; triangle and object ids, >= 0).
INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1
#: Smallest and largest int64 (core parameter integers: cores hold them in numpy int64).
INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1

#: An unsigned 16-bit integer (JSON integers only: no bools, floats or strings).
UInt16 = Annotated[int, Field(strict=True, ge=0, le=UINT16_MAX)]
#: An unsigned 32-bit integer: a pose ``seq`` and everything echoing it, counts in frame headers.
UInt32 = Annotated[int, Field(strict=True, ge=0, le=UINT32_MAX)]
#: A positive unsigned 32-bit integer (a triangle budget: at least one triangle).
PositiveUInt32 = Annotated[int, Field(strict=True, gt=0, le=UINT32_MAX)]
#: A non-negative int32: a cell, triangle or object id as the frames carry it.
Id32 = Annotated[int, Field(strict=True, ge=0, le=INT32_MAX)]
#: A count of int32 ids: [0, 2**31] (ids run from 0 to INT32_MAX, so a scene holds at most
#: 2**31 triangles).
Count32 = Annotated[int, Field(strict=True, ge=0, le=INT32_MAX + 1)]
#: A signed 64-bit integer (core parameter values).
Int64 = Annotated[int, Field(strict=True, ge=INT64_MIN, le=INT64_MAX)]


def fits_uint32(value: object) -> bool:
    """Whether ``value`` is a Python int (not a bool) in [0, UINT32_MAX]."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= UINT32_MAX
