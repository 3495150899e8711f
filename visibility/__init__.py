"""Visibility: scenes, view cells and the PVS cores (no networking)."""

from visibility.compile_speed import install as _shorter_compiles
from visibility.kernel_cache import key_numba_cache

# Before any kernel module is imported: numba decides where a kernel caches when it is defined.
key_numba_cache()
# Before any kernel is compiled: the same kernels, compiled sooner (``compile_speed``).
_shorter_compiles()
