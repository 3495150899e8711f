"""Visibility: scenes, view cells and the PVS cores (no networking)."""

from visibility.kernel_cache import key_numba_cache

# Before any kernel module is imported: numba decides where a kernel caches when it is defined.
key_numba_cache()
