"""Block moves inside a numba array: one ``memmove`` instead of a loop over its elements.

Sorted per-pixel lists that take an insertion in the middle (``from_segment``'s envelopes)
shift every row after it. An element loop over a 3D array moves a few bytes per iteration
with its index arithmetic; the C library's ``memmove`` moves the same bytes in wide blocks and
handles the overlap of source and destination.
"""

from __future__ import annotations

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numba.np.arrayobj import make_array


@intrinsic
def move_items(typingctx, arr, dst, src, count):
    """Move ``count`` items of C-contiguous ``arr``'s flat storage from flat index ``src`` to
    ``dst`` (overlap allowed, as ``memmove``). Indices are not checked: the caller keeps
    ``[src, src + count)`` and ``[dst, dst + count)`` inside ``arr.size``."""
    if not (isinstance(arr, types.Array) and arr.layout == "C"):
        return None
    if not all(isinstance(t, types.Integer) for t in (dst, src, count)):
        return None

    def codegen(context, builder, signature, args):
        a = make_array(signature.args[0])(context, builder, args[0])
        d, s, n = (context.cast(builder, v, t, types.intp)
                   for v, t in zip(args[1:], signature.args[1:], strict=True))
        itemsize = context.get_abi_sizeof(context.get_data_type(signature.args[0].dtype))
        pd = builder.gep(a.data, [d])
        ps = builder.gep(a.data, [s])
        cgutils.raw_memmove(builder, pd, ps, n, itemsize)
        return context.get_dummy_value()

    return types.none(arr, dst, src, count), codegen
