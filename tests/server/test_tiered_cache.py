"""``server.cache.TieredCache`` against a REAL ``redis-server`` and a real folder: one key for
every region, the tiers' order, copies into the faster tiers, ``peek`` (memory, then Redis,
never the disk, never a computation) and the disk kept for what ``put`` says."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from benchmarks.redis_process import free_port
from server.cache import DiskPVSCache, PVSCache, PVSKey, TieredCache
from server.cache.shared import RedisLink, SharedCache
from visibility.cores.base import PVS

N = 1000
BOX = np.array([[0.0, 0.0, 0.0], [4.0, 3.0, 4.0]])


def _key(x: float = 0.0, region: str = "box") -> PVSKey:
    return PVSKey.of("c" * 16, region, BOX + x, "sampling", "resolution=64")


def _pvs(start: int) -> PVS:
    return PVS(np.arange(start, start + 50, dtype=np.int32), stats={"seconds": 0.5})


@pytest.fixture
def tiers(redis_server, tmp_path):
    shared = SharedCache(RedisLink(redis_server.url, timeout=1.0))
    cache = TieredCache(PVSCache(1 << 20), shared, DiskPVSCache(tmp_path / "pvs"))
    yield cache
    redis_server.client().flushdb()
    cache.close()


def test_get_asks_memory_then_redis_then_disk_and_copies_up(tiers):
    key = _key(1.0)
    assert tiers.get(key, N) is None
    tiers.disk.put(key, _pvs(3), N)  # only the disk holds it (another server's precompute)
    got = tiers.get(key, N)
    assert got is not None and got.stats.get("disk") is True
    np.testing.assert_array_equal(got.triangle_ids, _pvs(3).triangle_ids)
    # Copied into Redis (the other replicas' gain) and memory.
    assert tiers.shared.stats()["pvs"]["writes"] == 1
    assert tiers.get(key, N, upto="memory") is got
    tiers.memory.clear()
    again = tiers.get(key, N)
    assert again.stats.get("redis") is True and tiers.disk.stats()["hits"] == 1
    with pytest.raises(ValueError, match="tier"):
        tiers.get(key, N, upto="tape")


def test_peek_never_reads_the_disk_and_counts_apart(tiers):
    on_disk, shared = _key(2.0), _key(3.0, "segment")
    tiers.disk.put(on_disk, _pvs(1), N)
    tiers.put(shared, _pvs(7), N, disk=False)  # memory and Redis only
    assert not tiers.disk.path(shared).exists()
    tiers.memory.clear()
    before = tiers.memory.stats()
    assert tiers.peek(on_disk, N) is None  # on disk only: not a peek's business
    got = tiers.peek(shared, N)
    np.testing.assert_array_equal(got.triangle_ids, _pvs(7).triangle_ids)
    assert shared in tiers.memory  # Redis's answer is now in memory
    assert asyncio.run(tiers.peek_async(shared, N)) is got  # memory, inline
    assert asyncio.run(tiers.peek_async(_key(9.0), N)) is None
    after = tiers.memory.stats()
    assert (after["hits"], after["misses"]) == (before["hits"], before["misses"])
    stats = tiers.stats()["cache"]
    assert (stats["peeks"], stats["peek_hits"]) == (4, 2)
    assert tiers.disk.stats()["hits"] == 0
    assert tiers.missing(shared, N) == ["disk"] and tiers.missing(on_disk, N) == ["shared"]


def test_peek_with_redis_down_answers_from_memory_at_once(tmp_path):
    dead = SharedCache(RedisLink(f"redis://127.0.0.1:{free_port()}/0", timeout=0.2,
                                 retry=60.0))
    tiers = TieredCache(PVSCache(1 << 20), dead, None)
    try:
        key = _key()
        tiers.put(key, _pvs(0), N)  # memory only: Redis refuses
        assert tiers.peek(key, N) is not None
        assert tiers.peek(_key(5.0), N) is None  # the breaker is open now, or this call opens it
        assert not tiers.shared_up
        t0 = time.perf_counter()
        assert asyncio.run(tiers.peek_async(_key(6.0), N)) is None
        # Redis down: the event loop's peek does not even try it.
        assert time.perf_counter() - t0 < 0.2
        assert tiers.state()["backend"] == "redis" and tiers.state()["up"] is False
    finally:
        tiers.close()
