"""Arrays numba counts no references for, inside a kernel's hot loops.

Every njit function that receives an array, and every variable numba may rebind, counts a
reference to the array's memory on entry and releases it on exit: an atomic add each, on a
cache line that two threads taking the same shared array fight over. In a kernel that calls a
helper per pixel or per primitive these counts become a large share of the run time. ``borrow``
returns the same array (same data, shape and strides) without an owner, so numba counts
nothing for it or for anything sliced from it; ``keep_alive`` holds the owner until the
kernel's end, since numba frees an array after its variable's last use.

Rules: borrow only arrays whose owner outlives every use of the borrowed one (a kernel's
arguments, or a local owner passed to ``keep_alive`` after the last use); never return a
borrowed array to Python or store it in one that outlives the owner; and never write, inside
a ``prange`` loop, to an array borrowed outside it. numba's parfor pass does not know that a
borrowed array aliases its owner, so when the borrowed name is not used after the loop it
takes the loop's stores into it for dead and drops them: a 1D argument borrowed before a
``prange`` loop that fills it comes back untouched (numba 0.68; with a read after the loop,
or a 2D array, the stores stayed in a trial, but that is not a rule to lean on). Arrays
borrowed inside the loop's body, or written by a function the loop calls, are not affected.
"""

from __future__ import annotations

from numba import types
from numba.extending import intrinsic
from numba.np.arrayobj import make_array, populate_array


@intrinsic
def borrow(typingctx, arr):
    """The array ``arr`` (numba array) without its owner: no reference counting."""
    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, signature, args):
        src = make_array(signature.args[0])(context, builder, args[0])
        out = make_array(signature.return_type)(context, builder)
        populate_array(out, data=src.data, shape=src.shape, strides=src.strides,
                       itemsize=src.itemsize, meminfo=None)
        return out._getvalue()

    return arr(arr), codegen


@intrinsic
def keep_alive(typingctx, arr):
    """A use of ``arr`` that does nothing: numba keeps its reference until here."""
    def codegen(context, builder, signature, args):
        return context.get_dummy_value()

    return types.none(arr), codegen
