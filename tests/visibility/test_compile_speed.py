"""numba's compiler with ``visibility.compile_speed``: the same kernels, fewer copies."""

from __future__ import annotations

import copy

import numpy as np
from numba import njit
from numba.core import inline_closurecall, ir, targetconfig
from numba.core.compiler import Flags

from visibility import compile_speed


@njit(inline="always")
def _leaf(x):
    y = 0.0
    for k in range(3):
        y += x * k if x > k else -x
    return y


@njit(inline="always")
def _middle(x):
    return _leaf(x) + _leaf(x + 1.0) * 2.0


def _caller(a):
    out = np.empty_like(a)
    for k in range(a.shape[0]):
        out[k] = _middle(a[k]) - _leaf(a[k])
    return out


class _CountingCopy:
    """``copy`` for ``inline_closurecall``: counts the blocks its deep copies make anew."""

    def __init__(self) -> None:
        self.new_blocks = 0

    def deepcopy(self, x, memo=None):
        out = copy.deepcopy(x, memo)
        if isinstance(x, ir.Block) and out is not x:
            self.new_blocks += 1
        return out


def _compile_and_count(monkeypatch) -> tuple[np.ndarray, int]:
    counting = _CountingCopy()
    monkeypatch.setattr(inline_closurecall, "copy", counting)
    a = np.linspace(-3.0, 5.0, 17)
    # A fresh dispatcher, uncached: each call compiles.
    got = njit(cache=False)(_caller)(a)
    return got, counting.new_blocks


def test_installed_where_numba_is_a_checked_version():
    installed = compile_speed._version() in compile_speed.CHECKED
    assert (inline_closurecall.InlineWorker.inline_function
            is compile_speed._inline_function) == installed
    assert (targetconfig.TargetConfig.values is compile_speed._values) == installed


def test_inlined_helpers_compile_to_the_same_kernel_without_copying_their_blocks(monkeypatch):
    if compile_speed._version() not in compile_speed.CHECKED:
        # Another numba: its compiler runs as it is (read the replacements against it before
        # adding it to CHECKED).
        assert not compile_speed.install()
        assert inline_closurecall.InlineWorker.inline_function is compile_speed._ORIGINAL[0]
        return
    try:
        compile_speed.uninstall()
        plain, plain_copies = _compile_and_count(monkeypatch)
    finally:
        assert compile_speed.install()
    fast, fast_copies = _compile_and_count(monkeypatch)
    np.testing.assert_array_equal(fast, plain)
    a = np.linspace(-3.0, 5.0, 17)
    want = [_leaf.py_func(x) + _leaf.py_func(x + 1.0) * 2.0 - _leaf.py_func(x) for x in a]
    np.testing.assert_allclose(fast, want, rtol=1e-15)
    assert plain_copies > 0 and fast_copies == 0, (plain_copies, fast_copies)


def test_flag_values_are_numbas_own():
    flags = Flags()
    flags.nrt = True
    flags.error_model = "numpy"
    flags.fastmath = False
    assert compile_speed._values(flags) == compile_speed._ORIGINAL[1](flags)
    other = Flags(flags)
    assert other == flags and hash(other) == hash(flags)
    other.nrt = False
    assert other != flags
    # A stored value equal to the default: equal to a configuration that stores none.
    plain, explicit = Flags(), Flags()
    explicit.debuginfo = plain.debuginfo
    assert explicit._values != plain._values
    assert explicit == plain and hash(explicit) == hash(plain)
