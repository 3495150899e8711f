"""Shorter numba compiles of the cores' kernels: two of numba's compile-time costs removed.

The cores' kernels are built from small ``inline="always"`` helpers nested a few levels deep,
and compiling them is most of a fresh machine's warm-up (``visibility.warmup``). Two costs in
numba's front end grow with that nesting, and neither changes what is compiled:

* **Copies of IR made for one call site.** numba inlines a helper at each call site by
  compiling the helper's untyped IR afresh (``InlineWorker.run_untyped_passes``) and splicing
  it in (``InlineWorker.inline_ir``). ``inline_ir`` first deep-copies that IR twice (one copy
  to mutate, one kept unmutated to return), block by block, and each block's copy copies the
  function's whole scope again, so a copy costs blocks x variables. The IR was made for this
  call site alone, and the only caller of ``inline_function`` in numba (the
  ``InlineInlinables`` pass) drops the unmutated copy: both copies are waste (numba issue
  #8989). ``_inline_function`` hands ``inline_ir`` the fresh blocks, each answering
  ``copy.deepcopy`` with itself for the duration of the call.
* **Flag comparisons.** Each call typed against an ``@overload`` looks its implementation up
  in a cache keyed by the compile flags (``templates._OverloadFunctionTemplate._get_impl``),
  hashing and comparing them through ``TargetConfig.values``, which reads some forty options
  through a property each. ``_values`` builds the same dict from the stored values directly,
  and ``_eq`` finds two configurations of one class equal at once when their stored values
  are (every option then is), comparing every option's value only otherwise.

``install`` applies both to numba versions this was checked on (``CHECKED``); with another
numba it does nothing and says so in the log. Same kernels: the suite runs on them.
"""

from __future__ import annotations

import logging

import numba
from numba.core import inline_closurecall, targetconfig

log = logging.getLogger(__name__)

#: numba versions (major, minor) whose ``InlineWorker.inline_function`` and
#: ``TargetConfig.values`` these replacements were read against.
CHECKED = ((0, 68),)

_ORIGINAL = (inline_closurecall.InlineWorker.inline_function, targetconfig.TargetConfig.values,
             targetconfig.TargetConfig.__eq__)


def _inline_function(self, caller_ir, block, i, function, arg_typs=None):
    """``InlineWorker.inline_function`` without ``inline_ir``'s copies of the helper's fresh
    IR; returns what ``inline_ir`` returns (its first item is the spliced IR itself, not an
    unmutated copy: numba's caller drops it)."""
    callee_ir = self.run_untyped_passes(function)
    freevars = function.__code__.co_freevars
    blocks = list(callee_ir.blocks.values())
    for b in blocks:
        # An instance attribute: ``copy.deepcopy`` looks ``__deepcopy__`` up on the object.
        b.__deepcopy__ = _itself(b)
    try:
        return self.inline_ir(caller_ir, block, i, callee_ir, freevars, arg_typs=arg_typs)
    finally:
        for b in blocks:
            del b.__deepcopy__


def _itself(block):
    """A ``__deepcopy__`` that returns ``block``."""
    def deepcopy(memo):
        return block
    return deepcopy


def _values(self) -> dict:
    """``TargetConfig.values``: every option's value, read from the stored ones."""
    stored = self._values
    return {k: stored.get(k, opt.default) for k, opt in self.options.items()}


def _eq(self, other) -> bool:
    """``TargetConfig.__eq__``: equal stored values of one class first (then every option is
    equal), every option's value otherwise."""
    if not isinstance(other, targetconfig.TargetConfig):
        return NotImplemented
    if type(self) is type(other) and self._values == other._values:
        return True
    return self.values() == other.values()


def _version() -> tuple[int, int]:
    major, minor = numba.__version__.split(".")[:2]
    return int(major), int(minor)


def install() -> bool:
    """Apply both replacements in this process when numba's version is in ``CHECKED``
    (idempotent); whether they are applied."""
    if _version() not in CHECKED:
        log.info("numba %s: its compiler is used as it is (compile_speed checked %s)",
                 numba.__version__, CHECKED)
        return False
    inline_closurecall.InlineWorker.inline_function = _inline_function
    targetconfig.TargetConfig.values = _values
    targetconfig.TargetConfig.__eq__ = _eq
    return True


def uninstall() -> None:
    """numba's own functions again."""
    inline_closurecall.InlineWorker.inline_function = _ORIGINAL[0]
    targetconfig.TargetConfig.values = _ORIGINAL[1]
    targetconfig.TargetConfig.__eq__ = _ORIGINAL[2]
