"""Handing freed heap memory back to the operating system after a big, one-off job.

numpy's arrays of up to 32 MB come from the C heap once glibc has raised its mmap threshold,
and glibc keeps freed heap pages resident for reuse. After a scene load (a generator's or a
parser's temporaries, freed) that is memory the process holds but no array uses; it counts in
the resident set like any other. ``release_freed_memory`` returns it (glibc ``malloc_trim``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging

log = logging.getLogger(__name__)


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None on a C library without it (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        fn = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


def release_freed_memory() -> bool:
    """Return the C heap's free pages to the operating system; True when the C library can
    (glibc), False where it has no ``malloc_trim`` (nothing is done then)."""
    fn = _malloc_trim()
    if fn is None:
        return False
    fn(0)
    return True
