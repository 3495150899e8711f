"""The server's PVS cache: one tiered cache (``TieredCache``: memory, then Redis, then disk) under
one key (``PVSKey``), for grid cells, ad-hoc boxes and segments alike.

Modules: ``key`` (the key), ``tiered`` (the tiers behind one ``get``/``put``/``peek``),
``memory`` (the byte-bounded LRU with pins, also the near-far store's), ``shared`` (Redis behind
a circuit breaker), ``codec`` (Redis keys and values), ``disk`` (checked ``.npz`` files),
``checks`` (what every entry read back must pass).
"""

from server.cache.checks import BadEntry, check_ids
from server.cache.disk import DiskPVSCache
from server.cache.key import PVSKey
from server.cache.memory import ByteLRU, PVSCache, nbytes_of, pvs_nbytes
from server.cache.tiered import TieredCache

__all__ = ["BadEntry", "ByteLRU", "DiskPVSCache", "PVSCache", "PVSKey", "TieredCache",
           "check_ids", "nbytes_of", "pvs_nbytes"]
