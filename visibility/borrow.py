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


def _borrowed(context, builder, typ, value):
    """LLVM value of array ``value`` (numba type ``typ``) with its owner left out."""
    src = make_array(typ)(context, builder, value)
    out = make_array(typ)(context, builder)
    populate_array(out, data=src.data, shape=src.shape, strides=src.strides,
                   itemsize=src.itemsize, meminfo=None)
    return out._getvalue()


def _borrowable(typ) -> bool:
    """An array, or a (named) tuple of borrowable members."""
    if isinstance(typ, types.Array):
        return True
    return isinstance(typ, types.BaseTuple) and all(_borrowable(t) for t in typ.types)


def _borrowed_value(context, builder, typ, value):
    """``_borrowed`` for an array, member by member for a tuple."""
    if isinstance(typ, types.Array):
        return _borrowed(context, builder, typ, value)
    vals = [_borrowed_value(context, builder, t, builder.extract_value(value, i))
            for i, t in enumerate(typ.types)]
    return context.make_tuple(builder, typ, vals)


@intrinsic
def borrow(typingctx, arr):
    """The array ``arr`` (numba array) without its owner: no reference counting. Given a
    tuple or named tuple of arrays, nested ones included (a kernel's scratch), the same tuple
    of borrowed arrays: unpack it into the names the kernel uses, and ``keep_alive`` the owning
    tuple."""
    if not _borrowable(arr):
        return None

    def codegen(context, builder, signature, args):
        return _borrowed_value(context, builder, signature.args[0], args[0])

    return arr(arr), codegen


#: njit option for helpers that allocate nothing: compiled without numba's runtime, so they
#: hold no reference counts at all, not even the calls that find a borrowed array's owner
#: missing, which a helper called per primitive and tile still pays at every entry and exit.
#: An allocation in such a function fails to compile (a TypingError), so nothing leaks.
#: ``_nrt`` is numba's own flag (not in its public options; numba 0.60-0.68 take it).
NO_REFCOUNT = {"_nrt": False}


@intrinsic
def keep_alive(typingctx, arr):
    """A use of ``arr`` that does nothing: numba keeps its reference until here."""
    def codegen(context, builder, signature, args):
        return context.get_dummy_value()

    return types.none(arr), codegen
