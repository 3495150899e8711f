"""The shared Redis cache (``server.cache.codec``, ``server.cache.shared``): values round-trip
and refuse what is not theirs; keys carry scene content hash, core, parameters and format
version; and against a REAL ``redis-server`` on loopback: two server processes share a PVS (the
second answers from Redis), a walker keeps walking while Redis is killed and restarted, a
server whose Redis is down at start still serves, near-far cubemaps are shared, and
``precompute`` fills Redis and resumes from it."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

import visibility.nearfar as nearfar
from benchmarks.common import stop_process
from benchmarks.redis_process import RedisProcess, available, free_port
from client.session import Session
from pvs_cli import build_parser, serve_settings, wait_until_healthy
from server.cache import BadEntry, PVSKey
from server.cache.codec import (
    FORMAT_VERSION,
    PVS_HEADER,
    cubemap_key,
    decode_blob,
    decode_pvs,
    encode_blob,
    encode_pvs,
)
from server.cache.key import KEY_VERSION
from server.settings import Settings
from tests.conftest import make_tiny_scene, near_ids, serving, wait_for
from visibility.cores.base import PVS

REPO = Path(__file__).resolve().parents[2]
BOX = np.array([[0.0, 0.0, 0.0], [4.0, 3.0, 4.0]])
RADIUS = 4.5


def pvs_key(fingerprint: str, core: str, params: str, region: np.ndarray = BOX,
            kind: str = "box") -> str:
    """The Redis key of a PVS (``PVSKey.shared``)."""
    return PVSKey.of(fingerprint, kind, region, core, params).shared()


# --------------------------------------------------------------------------- values and keys
def test_pvs_value_round_trips_every_array():
    key = pvs_key("0123456789abcdef", "sampling", "resolution=64")
    pvs = PVS(np.array([0, 5, 6, 90_000], np.int32), granularity="object",
              object_ids=np.array([2, 7], np.int32), sphere_ids=np.array([1, 3, 4], np.int32),
              stats={"seconds": 1.25})
    back = decode_pvs(key, encode_pvs(key, pvs, 100_000), 100_000)
    np.testing.assert_array_equal(back.triangle_ids, pvs.triangle_ids)
    np.testing.assert_array_equal(back.object_ids, pvs.object_ids)
    np.testing.assert_array_equal(back.sphere_ids, pvs.sphere_ids)
    assert back.triangle_ids.dtype == np.int32 and back.granularity == "object"
    assert back.seconds == 1.25 and back.stats["redis"] is True
    empty = decode_pvs(key, encode_pvs(key, PVS(np.zeros(0, np.int32)), 10), 10)
    assert len(empty) == 0 and empty.object_ids is None and empty.sphere_ids is None


def test_pvs_value_is_compact():
    ids = np.unique(np.random.default_rng(0).integers(0, 100_000, 5_000)).astype(np.int32)
    key = pvs_key("f" * 16, "sampling", "")
    value = encode_pvs(key, PVS(ids), 100_000)
    raw = encode_pvs(key, PVS(ids), 100_000, compress=False)
    assert len(raw) >= 4 * len(ids)
    # Gaps of a sorted set under zlib: well under the 4 bytes per id of the raw array.
    assert len(value) < 0.6 * len(raw), (len(value), len(raw))
    np.testing.assert_array_equal(decode_pvs(key, raw, 100_000).triangle_ids, ids)


def test_values_refuse_what_is_not_theirs():
    key = pvs_key("0123456789abcdef", "sampling", "resolution=64")
    value = encode_pvs(key, PVS(np.arange(0, 100, 7, dtype=np.int32)), 200)
    other = pvs_key("0123456789abcdef", "sampling", "resolution=64", BOX + 1.0)
    with pytest.raises(BadEntry, match="checksum"):
        decode_pvs(other, value, 200)  # copied under another key
    damaged = bytearray(value)
    damaged[-1] ^= 0xFF
    with pytest.raises(BadEntry):
        decode_pvs(key, bytes(damaged), 200)
    with pytest.raises(BadEntry):
        decode_pvs(key, value[:-3], 200)  # truncated
    with pytest.raises(BadEntry, match="header"):
        decode_pvs(key, value[:10], 200)
    with pytest.raises(BadEntry, match="triangles"):
        decode_pvs(key, value, 50)  # another scene's triangle count
    newer = bytearray(value)
    newer[4] = FORMAT_VERSION + 1
    assert decode_pvs(key, bytes(newer), 200) is None  # another format: a plain miss
    with pytest.raises(BadEntry):
        encode_pvs(key, PVS(np.array([5, 300], np.int32)), 200)  # never written


def test_a_value_claiming_more_ids_than_its_payload_is_refused():
    key = pvs_key("a" * 16, "c", "")
    value = bytearray(encode_pvs(key, PVS(np.arange(10, dtype=np.int32)), 1_000_000))
    fields = list(PVS_HEADER.unpack_from(value))
    fields[6] = 900_000  # n_ids: a decompression "bomb" header
    value[:PVS_HEADER.size] = PVS_HEADER.pack(*fields)
    with pytest.raises(BadEntry):
        decode_pvs(key, bytes(value), 1_000_000)


def test_blob_round_trip_and_checks():
    key = cubemap_key("0123456789abcdef", "c0ffee", 40.0, 80.0, 32, 7, BOX)
    for data in (bytes(50_000), np.random.default_rng(1).bytes(5_000)):
        value = encode_blob(key, data)
        assert decode_blob(key, value, 1 << 20) == data
    assert len(encode_blob(key, bytes(50_000))) < 5_000  # zeros compress
    with pytest.raises(BadEntry, match="checksum"):
        decode_blob(key.replace(":7:", ":8:"), encode_blob(key, b"abc"), 100)
    with pytest.raises(BadEntry, match="allowed"):
        decode_blob(key, encode_blob(key, bytes(1000)), 100)


def test_keys_carry_version_scene_core_params_and_region():
    key = pvs_key("0123456789abcdef", "dual_ray", "resolution=64")
    parts = key.split(":")
    assert parts[:4] == ["pvs", f"v{KEY_VERSION}", "0123456789abcdef", "dual_ray"]
    assert parts[5] == "box" and len(parts) == 7
    variants = {
        pvs_key("0123456789abcdef", "dual_ray", "resolution=128"),
        pvs_key("fedcba9876543210", "dual_ray", "resolution=64"),
        pvs_key("0123456789abcdef", "sampling", "resolution=64"),
        pvs_key("0123456789abcdef", "dual_ray", "resolution=64", BOX * 2),
        pvs_key("0123456789abcdef", "dual_ray", "resolution=64", kind="segment"),
        PVSKey("0123456789abcdef", "box", tuple(BOX.ravel().tolist()), "dual_ray",
               "resolution=64", KEY_VERSION + 1).shared(),
    }
    assert key not in variants and len(variants) == 6
    # A grid cell and an ad-hoc box with the same corners are one entry; the key is the same
    # in every process (floats, not a scene name or a cell id).
    assert pvs_key("0123456789abcdef", "dual_ray", "resolution=64", BOX.tolist()) == key
    # A ':' in a name cannot shift the other parts.
    assert len(pvs_key("x:y", "a:b", "").split(":")) == 7
    with pytest.raises(ValueError):
        PVSKey.of("0123456789abcdef", "sphere", BOX, "dual_ray", "")
    colour = cubemap_key("0123456789abcdef", "c0", 40.0, 80.0, 32, 1, BOX)
    assert colour != cubemap_key("0123456789abcdef", "c1", 40.0, 80.0, 32, 1, BOX)
    assert colour.split(":")[3] == "cubemap" and colour.split(":")[5] == "1"


# --------------------------------------------------------------------------- settings, CLI
def test_cache_setting_env_and_flag():
    s = Settings.from_env({"PVS_CACHE": "redis://10.0.0.5:6380/2", "PVS_REDIS_TTL": "60",
                           "PVS_REDIS_TIMEOUT": "0.1"}, generated={})
    assert (s.cache, s.redis_ttl, s.redis_timeout) == ("redis://10.0.0.5:6380/2", 60.0, 0.1)
    assert Settings(generated={}).cache == "disk"
    for bad in ("memcached://x:1", "redis://", "somewhere"):
        with pytest.raises(ValueError, match="Redis URL"):
            Settings(cache=bad, generated={})
    with pytest.raises(ValueError, match="port"):
        Settings(cache="redis://localhost:sixty/0", generated={})
    with pytest.raises(ValueError):
        Settings(redis_ttl=-1, generated={})
    args = build_parser().parse_args(["serve", "--cache", "redis://127.0.0.1:7000/0"])
    assert serve_settings(args, env={}).cache == "redis://127.0.0.1:7000/0"


def test_health_names_the_disk_backend_without_redis(settings, tmp_path):
    with serving(settings, cache_dir=tmp_path) as (url, app):
        cache = httpx.get(url + "/health", timeout=30).json()["cache"]
        assert cache == {"backend": "disk", "up": True, "disk": True}
        text = httpx.get(url + "/metrics", timeout=30).text
        assert "pvs_redis_up" not in text
        assert metric(text, "pvs_cache_tier_hits_total", tier="disk", kind="pvs") == 0
        assert metric(text, "pvs_cache_tier_misses_total", tier="memory", kind="near_far") == 0


# --------------------------------------------------------------------------- helpers
def metric(text: str, name: str, **labels: str) -> float:
    """The value of ``name`` (with exactly ``labels``) in Prometheus text; KeyError if none."""
    want = ",".join(f'{k}="{v}"' for k, v in sorted(labels.items()))
    pattern = re.compile(rf"^{re.escape(name)}(\{{([^}}]*)\}})? (\S+)$", re.M)
    for m in pattern.finditer(text):
        got = ",".join(sorted((m.group(2) or "").split(","))) if m.group(2) else ""
        if got == want:
            return float(m.group(3))
    raise KeyError(f"{name}{{{want}}}")


def redis_stats(url: str) -> dict:
    return httpx.get(url + "/health", timeout=30).json()["compute"]["redis"]


@contextlib.contextmanager
def server_process(redis_url: str) -> Iterator[str]:
    """``pvs serve`` in its own OS process on a free loopback port with the shared cache at
    ``redis_url``, serving a small generated ``rooms``; yields its base URL."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ, PVS_CACHE=redis_url, PVS_GENERATED="rooms=4000",
               PVS_LOG_LEVEL="warning", PVS_CALIBRATE="0", PVS_PROGRESSIVE="0",
               PVS_WS_PING_INTERVAL="none", PVS_CORE="sampling",
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1", "--port", str(port),
         "--scenes", str(REPO / "nonexistent-scenes-dir")],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        if not wait_until_healthy(url, proc, timeout=180):
            err = proc.stderr.read().decode()[-3000:] if proc.stderr else ""
            raise RuntimeError(f"the server process did not start: {err}")
        yield url
    finally:
        stop_process(proc)


# --------------------------------------------------------------------------- live, shared
def test_shared_cache_bounds_values_and_deletes_bad_ones(redis_server):
    """A value over ``redis_max_value_bytes`` stays local; a value that fails its checks is a
    miss and is deleted; the TTL is set on every write."""
    from server.cache.shared import RedisLink, SharedCache

    shared = SharedCache(RedisLink(redis_server.url, timeout=1.0), ttl=30,
                         max_value_bytes=2048)
    client = redis_server.client()
    try:
        key = pvs_key("b" * 16, "sampling", "")
        ids = np.unique(np.random.default_rng(2).integers(0, 200_000, 20_000))
        big = PVS(ids.astype(np.int32))  # random gaps: over 2 KiB even compressed
        assert not shared.put_pvs(key, big, 200_000)
        assert client.get(key) is None and shared.stats()["pvs"]["too_large"] == 1
        small = PVS(np.array([1, 2, 3], np.int32))
        assert shared.put_pvs(key, small, 10)
        assert 0 < client.pttl(key) <= 30_000
        np.testing.assert_array_equal(shared.get_pvs(key, 10).triangle_ids, [1, 2, 3])
        client.set(key, b"PVSr this is not a value")
        assert shared.get_pvs(key, 10) is None
        assert client.get(key) is None  # deleted, so the next writer replaces it
        assert shared.stats()["pvs"]["rejected"] == 1
        bkey = cubemap_key("b" * 16, "c", 40.0, 80.0, 32, 1, BOX)
        assert shared.put_blob(bkey, b"frame" * 10) and shared.get_blob(bkey) == b"frame" * 10
    finally:
        shared.close()
        client.close()


def _rooms_keys(regions: list[tuple[str, object]]) -> list[str]:
    """The Redis keys of the regions [("cell", id) | ("box", box) | ("segment", seg)] of the
    ``rooms`` scene ``server_process`` serves, with the sampling core of ``ROOMS_QUERY``."""
    from server.catalog import SceneCatalog
    from server.region import region_of
    from server.resolve import Resolver

    s = Settings(generated={"rooms": 4000}, core="sampling")
    loaded = SceneCatalog(s).get("rooms")
    choice = Resolver(s).named("sampling", ROOMS_PARAMS)
    return [region_of(loaded, **{kind: where}).key(loaded.fingerprint, choice.core,
                                                   choice.params).shared()
            for kind, where in regions]


ROOMS_PARAMS = {"samples": 4, "resolution": 64}


def test_two_server_processes_share_a_pvs_through_redis(redis_server):
    """The first process computes cell 3, an ad-hoc box, a segment and a box with another
    cell's corners; the second answers each from Redis (the cell as that box's entry: one key
    for cells and boxes alike): cached, marked as Redis's, its Redis hits counted and no
    computation run."""
    query = {"core": "sampling", **ROOMS_PARAMS}
    body = {"core": "sampling", "params": ROOMS_PARAMS}
    with server_process(redis_server.url) as first, server_process(redis_server.url) as second:
        for url in (first, second):  # scene loaded first, so the timings are the answers'
            assert httpx.get(url + "/scenes/rooms", timeout=120).status_code == 200
        cells = httpx.get(first + "/scenes/rooms/cells", timeout=60).json()["cells"]
        box3 = np.asarray(cells[3]["box"])
        inner = box3 + [[0.25, 0.0, 0.25], [-0.25, 0.0, -0.25]]
        centre = box3.mean(axis=0)
        segment = np.stack([centre - [0.5, 0.0, 0.0], centre + [0.5, 0.0, 0.0]])
        other = len(cells) - 1
        asks = [  # (what the first server is asked, what the second is asked)
            (("get", "/scenes/rooms/cells/3/pvs", None),) * 2,
            (("post", "/scenes/rooms/pvs", {"box": inner.tolist()}),) * 2,
            (("post", "/scenes/rooms/pvs", {"segment": segment.tolist()}),) * 2,
            (("post", "/scenes/rooms/pvs", {"box": cells[other]["box"]}),
             ("get", f"/scenes/rooms/cells/{other}/pvs", None)),
        ]

        def ask(url: str, how: tuple) -> tuple[dict, float]:
            method, path, region = how
            t0 = time.perf_counter()
            if method == "get":
                r = httpx.get(url + path, params=query, timeout=300)
            else:
                r = httpx.post(url + path, json={**body, **region}, timeout=300)
            assert r.status_code == 200, r.text
            return r.json(), time.perf_counter() - t0

        firsts = [ask(first, a) for a, _ in asks]
        assert not any(a["cached"] for a, _ in firsts)
        assert redis_stats(first)["pvs"]["writes"] == len(asks)
        seconds = [ask(second, b) for _, b in asks]
        for (a, _), (b, _) in zip(firsts, seconds, strict=True):
            assert b["cached"] and b["stats"]["redis"] is True
            assert b["triangle_ids"] == a["triangle_ids"] and a["triangle_ids"]
            assert b["seconds"] == a["seconds"]  # the original computation's time
        assert seconds[1][0]["cell"] is None and seconds[3][0]["cell"] == other
        t0 = time.perf_counter()
        assert httpx.get(second + "/scenes/rooms/cells/3/pvs", params=query,
                         timeout=300).json()["cached"]
        t_memory = time.perf_counter() - t0
        text = httpx.get(second + "/metrics", timeout=30).text
        assert metric(text, "pvs_cache_tier_hits_total", tier="redis", kind="pvs") == len(asks)
        assert metric(text, "pvs_computations_total") == 0
        assert metric(text, "pvs_redis_up") == 1
        health = httpx.get(second + "/health", timeout=30).json()
        assert health["cache"]["backend"] == "redis" and health["cache"]["up"] is True
        print(f"\nHTTP answer of cell 3: first process (computed) {1e3 * firsts[0][1]:.1f} ms, "
              f"second (from Redis) {1e3 * seconds[0][1]:.1f} ms, second again (memory) "
              f"{1e3 * t_memory:.1f} ms; the computation took "
              f"{1e3 * firsts[0][0]['seconds']:.1f} ms; the box from Redis "
              f"{1e3 * seconds[1][1]:.1f} ms")
    keys = {k.decode() for k in redis_server.client().keys(f"pvs:v{KEY_VERSION}:*:sampling:*")}
    want = _rooms_keys([("cell", 3), ("box", inner), ("segment", segment), ("cell", other)])
    assert set(want) <= keys and len(set(want)) == len(asks)


def _walk(url: str, positions: list[tuple[int, np.ndarray]], between: dict) -> Session:
    """One WebSocket session walking ``positions`` [(cell, point)], waiting for each cell;
    ``between[i]`` (a blocking callable) runs in a thread before the i-th position."""

    async def main() -> Session:
        s = await Session.connect(url, "tiny", "test_near", {"radius": RADIUS}, prefetch=False)
        try:
            for i, (cell, point) in enumerate(positions):
                if i in between:
                    await asyncio.to_thread(between[i])
                await s.send_pose(i, 0.1 * i, point, (0.0, 0.0, -1.0))
                await s.wait_cell(cell, timeout=60)
        finally:
            await s.close()
        return s

    return asyncio.run(asyncio.wait_for(main(), 180))


def test_redis_restart_mid_walkthrough_costs_the_walker_nothing(settings, registered_test_cores):
    """A walker walks cells while Redis is killed (SIGKILL) and started again: every cell
    arrives complete, no error reaches the walker, /health says down, then up, and values land
    in the new Redis once it is back."""
    assert available(), "redis-server is missing: scripts/setup.sh installs it"
    redis = RedisProcess().start()
    tiny = make_tiny_scene()
    try:
        with serving(settings, {"tiny": tiny}, cache=redis.url, redis_retry=0.2,
                     redis_timeout=0.5) as (url, app):
            boxes = app.state.server.catalog.get("tiny").grid.boxes
            walk = [(c, boxes[c].mean(axis=0)) for c in range(len(boxes))]
            http = httpx.Client(base_url=url, timeout=30)
            seen: dict[str, object] = {}

            def kill() -> None:
                seen["before"] = len(redis.client().keys(f"pvs:v{KEY_VERSION}:*"))
                redis.stop(kill=True)
                wait_for(lambda: http.get("/health").json()["cache"]["up"] is False, 10)
                seen["down"] = True

            def restart() -> None:
                seen["while_down"] = redis_stats(url)["pvs"]
                redis.start()
                wait_for(lambda: http.get("/health").json()["cache"]["up"] is True, 10)

            s = _walk(url, walk, {2: kill, 5: restart})
            assert not s.errors and not s.local_errors
            for cell, _ in walk:
                # Streams carry what the walker does not hold yet; the PVS size is announced.
                assert s.cells[cell].complete
                assert s.cells[cell].begin.triangles == len(near_ids(tiny, boxes[cell], RADIUS))
            held = np.unique(s.store.ids)
            want = np.unique(np.concatenate([near_ids(tiny, boxes[c], RADIUS) for c, _ in walk]))
            np.testing.assert_array_equal(held, want)
            assert seen["before"] == 2 and seen["down"]
            assert seen["while_down"]["writes"] == 2  # nothing written while it was down
            after = redis_stats(url)
            assert after["downs"] >= 1 and after["up"] is True
            # Cells 5..7 were computed after the restart and are in the new Redis.
            assert len(redis.client().keys(f"pvs:v{KEY_VERSION}:*")) == len(walk) - 5
            text = http.get("/metrics").text
            assert metric(text, "pvs_redis_up") == 1 and metric(text, "pvs_redis_downs_total") >= 1
            http.close()
    finally:
        redis.close()


def test_progressive_walker_gets_redis_answers_without_first_answers(
        settings, registered_test_cores, redis_server):
    """Progressive streams on two servers sharing Redis: the second server's walker gets each
    cell the first computed as the full answer from Redis, and no first answer is computed
    for it (the session waits ``SHARED_CACHE_GRACE_S`` for Redis before starting one)."""
    tiny = make_tiny_scene()
    opts = dict(progressive=True, cache=redis_server.url)
    with serving(settings, {"tiny": tiny}, **opts) as (url_a, app_a), \
            serving(settings, {"tiny": tiny}, **opts) as (url_b, app_b):
        boxes = app_a.state.server.catalog.get("tiny").grid.boxes
        walk = [(c, boxes[c].mean(axis=0)) for c in (4, 5, 6)]
        _walk(url_a, walk, {})
        b = _walk(url_b, walk, {})
        assert not b.errors and not b.local_errors
        assert [b.cells[c].answer for c, _ in walk] == ["full"] * 3
        compute = app_b.state.server.compute
        first_core = app_b.state.server.resolver.first().core.name
        assert compute.computed == 0
        assert not [k for k in list(compute.cache.memory._data) if k.core == first_core]
        # Every cell came out of Redis: through a counted lookup, or through the uncounted
        # peek the session makes while it waits (which of the two depends on timing, so a
        # busy machine moves hits from one count to the other).
        assert redis_stats(url_b)["pvs"]["hits"] + compute.cache.peek_hits >= 3


def test_server_serves_with_redis_down_at_start(settings, registered_test_cores):
    assert available(), "redis-server is missing: scripts/setup.sh installs it"
    port = free_port()
    with serving(settings, {"tiny": make_tiny_scene()}, cache=f"redis://127.0.0.1:{port}/0",
                 redis_retry=0.2, redis_timeout=0.3) as (url, app):
        with httpx.Client(base_url=url, timeout=60) as http:
            params = {"core": "test_near", "radius": RADIUS}
            r = http.get("/scenes/tiny/cells/1/pvs", params=params)
            assert r.status_code == 200 and not r.json()["cached"]
            health = http.get("/health").json()
            assert health["status"] == "ok" and health["cache"]["up"] is False
            assert metric(http.get("/metrics").text, "pvs_redis_up") == 0
            stats = redis_stats(url)["pvs"]
            assert stats["writes"] == 0 and stats["skipped"] + stats["errors"] >= 1
            # Served from memory again, still without Redis.
            assert http.get("/scenes/tiny/cells/1/pvs", params=params).json()["cached"]
            redis = RedisProcess(port=port).start()
            try:
                wait_for(lambda: http.get("/health").json()["cache"]["up"] is True, 10)
                r = http.get("/scenes/tiny/cells/2/pvs", params=params)
                assert r.status_code == 200
                assert redis_stats(url)["pvs"]["writes"] == 1
                choice = app.state.server.resolver.named("test_near", {"radius": RADIUS})
                key = app.state.server.compute.key("tiny", choice.core, choice.params, cell=2)
                assert redis.client().keys(f"pvs:v{KEY_VERSION}:*") == [key.shared().encode()]
            finally:
                redis.close()


def _stream_cell(url: str, scene: str, point: np.ndarray) -> Session:
    async def main() -> Session:
        s = await Session.connect(url, scene, "test_near", {"radius": 30.0}, prefetch=False)
        try:
            await s.send_pose(0, 0.0, point, (0, 0, -1))
            for _ in range(600):
                if s.complete:
                    break
                await asyncio.sleep(0.1)
        finally:
            await s.close()
        return s

    return asyncio.run(asyncio.wait_for(main(), 120))


def test_near_far_cubemaps_are_shared(settings, registered_test_cores, redis_server):
    """Two servers on one Redis: the first bakes a city cell's cubemap, the second streams the
    same cubemap read from Redis (and the cell's PVS too)."""
    nf = dict(near_far=True, near_far_r1=40.0, near_far_r2=80.0, near_far_resolution=32,
              cache=redis_server.url)
    cfg = nearfar.NearFarConfig(r1=40.0, r2=80.0, resolution=32)
    with serving(settings, **nf) as (url_a, app_a), serving(settings, **nf) as (url_b, app_b):
        loaded = app_a.state.server.catalog.get("city")
        cid = next(c for c in range(len(loaded.grid)) if nearfar.needs_cubemap(
            loaded.scene, loaded.grid.boxes[c].mean(axis=0), cfg))
        centre = loaded.grid.boxes[cid].mean(axis=0)
        a = _stream_cell(url_a, "city", centre)
        b = _stream_cell(url_b, "city", centre)
        assert not a.local_errors and not b.local_errors and not a.errors and not b.errors
        assert cid in a.cubemaps and cid in b.cubemaps
        np.testing.assert_array_equal(a.cubemaps[cid].colors, b.cubemaps[cid].colors)
        np.testing.assert_array_equal(a.cubemaps[cid].ranges, b.cubemaps[cid].ranges)
        sa, sb = redis_stats(url_a), redis_stats(url_b)
        assert sa["cubemap"]["writes"] == 1 and sa["cubemap"]["hits"] == 0
        assert sb["cubemap"]["hits"] == 1 and sb["cubemap"]["writes"] == 0
        assert sb["pvs"]["hits"] == 1 and app_b.state.server.compute.computed == 0
        text = httpx.get(url_b + "/metrics", timeout=30).text
        assert metric(text, "pvs_cache_tier_hits_total", tier="redis", kind="cubemap") == 1


def test_precompute_fills_redis_and_resumes_from_it(settings, registered_test_cores,
                                                    redis_server):
    from server.catalog import SceneCatalog
    from server.compute import ComputeService
    from server.precompute import precompute

    s = settings.model_copy(update={"cache": redis_server.url, "generated": {}})

    def service() -> ComputeService:
        svc = ComputeService(SceneCatalog(s), s)
        svc.catalog.register("tiny_pre", make_tiny_scene())
        return svc

    first = service()
    try:
        report = precompute(first, "tiny_pre", "test_near", {"radius": 3.0}, [0, 1, 2],
                            progress=False)
    finally:
        first.shutdown()
    assert (report.computed, report.cached, report.failed) == (3, 0, {})
    again = service()
    try:
        report = precompute(again, "tiny_pre", "test_near", {"radius": 3.0}, [0, 1, 2, 3],
                            progress=False)
        assert (report.computed, report.cached, report.failed) == (1, 3, {})
        assert again.cache.shared.stats()["pvs"]["hits"] == 3
    finally:
        again.shutdown()
    # A Redis that is down: the cells are computed, but they are not where servers read them.
    down = s.model_copy(update={"cache": f"redis://127.0.0.1:{free_port()}/0",
                                "redis_timeout": 0.2})
    dead = ComputeService(SceneCatalog(down), down)
    dead.catalog.register("tiny_pre", make_tiny_scene())
    try:
        report = precompute(dead, "tiny_pre", "test_near", {"radius": 3.0}, [4], progress=False)
    finally:
        dead.shutdown()
    assert report.failed and "Redis" in report.failed[4]


def test_pvs_precompute_command_fills_redis(redis_server, monkeypatch, capsys):
    """``pvs precompute --cache redis://…`` needs no folder; a second run finds every cell."""
    from pvs_cli import main

    monkeypatch.setenv("PVS_GENERATED", "rooms=2000")
    monkeypatch.setenv("PVS_CALIBRATE", "0")
    monkeypatch.delenv("PVS_CACHE_DIR", raising=False)
    argv = ["precompute", "--scene", "rooms", "--cache", redis_server.url, "--cells", "0-1",
            "--core", "sampling", "--param", "samples=2", "--param", "resolution=32",
            "--scenes", str(REPO / "nonexistent-scenes-dir"), "--quiet"]
    assert main(argv) == 0
    assert "2 computed" in capsys.readouterr().out
    assert main(argv) == 0
    assert "0 computed" in capsys.readouterr().out
    from server.catalog import SceneCatalog
    from server.region import cell_key
    from server.resolve import Resolver

    s = Settings(generated={"rooms": 2000})
    loaded = SceneCatalog(s).get("rooms")
    choice = Resolver(s).named("sampling", {"samples": 2, "resolution": 32})
    client = redis_server.client()
    assert all(client.exists(cell_key(loaded, c, choice.core, choice.params).shared())
               for c in (0, 1))
