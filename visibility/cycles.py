"""The CPU's cycle counter inside numba kernels: coarse timers for a core's phases.

``cycles()`` reads LLVM's ``readcyclecounter`` (the TSC on x86: a few ns, no system call), so
a kernel can split its own time between its steps where a profiler sees only one JIT-compiled
function. Cycles are not seconds (the clock varies); cores report shares of them.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def cycles(typingctx):
    """The CPU's cycle counter (int64), for differences taken inside one kernel."""
    def codegen(context, builder, signature, args):
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.IntType(64), []),
                                            "llvm.readcyclecounter")
        return builder.call(fn, [])
    return types.int64(), codegen
