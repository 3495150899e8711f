"""Server building blocks without the network: settings, catalogue, compute service."""

from __future__ import annotations

import threading
from concurrent.futures import Future

import numpy as np
import pytest
from pydantic import ValidationError

from server.cache import PVSCache, pvs_nbytes
from server.catalog import SceneCatalog, SceneLoadFailed, UnknownSceneError, check_scene_name
from server.compute import ComputeService
from server.region import UnknownCellError
from server.resolve import Resolver, UnknownCoreError, coerce_params
from server.settings import Settings
from tests.conftest import NearCore, make_tiny_scene, near_ids
from visibility.cores.base import PVS


# --------------------------------------------------------------------------- settings
def test_settings_defaults_and_validation():
    s = Settings(generated={})
    assert (s.host, s.port, s.cell_size, s.core, s.workers) == ("127.0.0.1", 8000, None,
                                                                "sampling", 2)
    assert s.cell_size_for(None) == 4.0 and s.cell_size_for(2.0) == 2.0
    assert s.cache_bytes == 256 * 1024 * 1024 and s.max_frame_bytes == 1 << 20
    for bad in ({"cell_size": 0}, {"cell_size": float("nan")}, {"workers": 0},
                {"max_frame_bytes": 50}, {"generated": {"city": 0}}, {"port": 70000},
                {"unknown": 1}):
        with pytest.raises(ValidationError):
            Settings(**bad)


def test_settings_from_env(tmp_path):
    env = {
        "PVS_HOST": "0.0.0.0", "PVS_PORT": "9001", "PVS_SCENES_DIR": str(tmp_path),
        "PVS_CELL_SIZE": "3.5", "PVS_CORE": "test_near", "PVS_CORE_PARAMS": '{"radius": 2}',
        "PVS_WORKERS": "3", "PVS_CACHE_BYTES": "1000", "PVS_MAX_FRAME_BYTES": "4096",
        "PVS_MAX_MESSAGE_BYTES": "2048", "PVS_WS_DEFLATE": "true", "PVS_WS_PING_INTERVAL": "none",
        "PVS_GENERATED": "city=20000, rooms=1e4", "PVS_HELLO_TIMEOUT": "2.5",
    }
    s = Settings.from_env(env)
    assert s.host == "0.0.0.0" and s.port == 9001 and s.scenes_dir == tmp_path
    assert s.cell_size == 3.5 and s.core == "test_near" and s.core_params == {"radius": 2}
    assert (s.workers, s.cache_bytes, s.max_frame_bytes, s.max_message_bytes) == (3, 1000, 4096,
                                                                                   2048)
    assert s.ws_deflate is True and s.ws_ping_interval is None and s.hello_timeout == 2.5
    assert s.generated == {"city": 20000, "rooms": 10000}
    assert Settings.from_env({"PVS_GENERATED": '{"village": 5000}'}).generated == {"village": 5000}
    assert Settings.from_env({"PVS_GENERATED": ""}).generated == {}
    assert Settings.from_env({}, port=1234).port == 1234
    for bad in ({"PVS_PORT": "http"}, {"PVS_CORE_PARAMS": "{nope"}, {"PVS_CORE_PARAMS": "[1]"},
                {"PVS_GENERATED": "city=abc"}, {"PVS_GENERATED": "nosuchgen"},
                {"PVS_GENERATED": "city=1.5"}):
        with pytest.raises(ValueError):
            Settings.from_env(bad)


def test_scene_file_limits_default_to_the_loaders_and_come_from_env():
    from visibility.loaders import MAX_FILE_BYTES, MAX_TRIANGLES

    s = Settings(generated={})
    assert (s.max_scene_triangles, s.max_scene_bytes) == (MAX_TRIANGLES, MAX_FILE_BYTES)
    env = Settings.from_env({"PVS_MAX_SCENE_TRIANGLES": "1000", "PVS_MAX_SCENE_BYTES": "4096",
                             "PVS_GENERATED": ""})
    assert (env.max_scene_triangles, env.max_scene_bytes) == (1000, 4096)
    # Triangle ids are int32: more than 2**31 triangles could not be named on the wire.
    for bad in ({"max_scene_triangles": 0}, {"max_scene_triangles": 2**31 + 1},
                {"max_scene_bytes": 0}):
        with pytest.raises(ValidationError):
            Settings(generated={}, **bad)


def test_prefetch_ahead_from_env_and_bounds():
    assert Settings.from_env({"PVS_PREFETCH_AHEAD": "0.5", "PVS_GENERATED": ""}
                             ).prefetch_ahead == 0.5
    for bad in ("1.5", "nan", "x"):
        with pytest.raises(ValueError):
            Settings.from_env({"PVS_PREFETCH_AHEAD": bad, "PVS_GENERATED": ""})


def test_near_far_block_from_env_and_bounds():
    assert Settings(generated={}).near_far_block == 1
    assert Settings.from_env({"PVS_NEAR_FAR_BLOCK": "4", "PVS_GENERATED": ""}).near_far_block == 4
    for bad in ("0", "65", "2.5", "x"):
        with pytest.raises(ValueError):
            Settings.from_env({"PVS_NEAR_FAR_BLOCK": bad, "PVS_GENERATED": ""})


def test_near_far_settings_share_nearfar_defaults_and_bounds():
    """One source of truth: the defaults are ``NearFarConfig``'s, and settings it would refuse
    fail at start-up instead of failing every hello (internal/1011)."""
    from visibility.nearfar import MAX_RESOLUTION, MIN_RESOLUTION, NearFarConfig

    s = Settings(generated={})
    default = NearFarConfig()
    assert (s.near_far_r1, s.near_far_r2, s.near_far_resolution) == (
        default.r1, default.r2, default.resolution)
    assert s.near_far_config() == default
    for ok in (MIN_RESOLUTION, MAX_RESOLUTION):
        assert Settings(generated={}, near_far_resolution=ok).near_far_config().resolution == ok
    for bad in ({"near_far_resolution": MAX_RESOLUTION + 1},
                {"near_far_resolution": MIN_RESOLUTION - 1},
                {"near_far_r1": 2 * default.r2}, {"near_far_r1": 10.0, "near_far_r2": 10.0},
                {"near_far_r2": float("inf")}):
        with pytest.raises(ValidationError):
            Settings(generated={}, **bad)
    with pytest.raises(ValueError):
        Settings.from_env({"PVS_NEAR_FAR": "1", "PVS_NEAR_FAR_RESOLUTION": "4096"})
    env = Settings.from_env({"PVS_NEAR_FAR_CACHE_BYTES": "1000", "PVS_MAX_BODY_BYTES": "2048"})
    assert env.near_far_cache_bytes == 1000 and env.max_body_bytes == 2048


# --------------------------------------------------------------------------- catalogue
@pytest.mark.parametrize("name", ["", ".", "..", "../x", "a/b", "a\\b", "a..b", "c:x", "a\x00",
                                  "x" * 300])
def test_bad_names_are_unknown(name):
    with pytest.raises(UnknownSceneError):
        check_scene_name(name)


def test_catalog_files_lazy_and_once(scenes_dir, tmp_path):
    cat = SceneCatalog(Settings(scenes_dir=scenes_dir, generated={}))
    assert {"box", "broken"} <= set(cat.names()) and "outside" not in cat.names()
    assert not cat.is_loaded("box")
    with pytest.raises(UnknownSceneError):
        cat.get("outside")
    results = []
    threads = [threading.Thread(target=lambda: results.append(cat.get("box"))) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len({id(r) for r in results}) == 1  # loaded once, shared
    assert cat.is_loaded("box") and results[0].grid.cell_size == 3.0
    with pytest.raises(SceneLoadFailed):
        cat.get("broken")
    assert not cat.is_loaded("broken")


def test_a_cell_size_setting_wins_over_the_scenes_own(scenes_dir):
    # The sidecar says 3 m; a server told 0.5 m (small cells for cos) uses 0.5 m everywhere.
    small = SceneCatalog(Settings(scenes_dir=scenes_dir, generated={}, cell_size=0.5))
    assert small.get("box").grid.cell_size == 0.5
    assert SceneCatalog(Settings(scenes_dir=scenes_dir, generated={})).get(
        "box").grid.cell_size == 3.0


def test_catalog_picks_up_new_files_and_prefers_formats(tmp_path, scenes_dir):
    folder = tmp_path / "s"
    folder.mkdir()
    cat = SceneCatalog(Settings(scenes_dir=folder, generated={}))
    assert cat.names() == []
    obj = (scenes_dir / "box.obj").read_text()
    (folder / "late.obj").write_text(obj)
    (folder / "late.json").write_text('{"walk": {"rects": [[1, 1, 7, 7, 0]]}}')
    (folder / "notes.txt").write_text("not a scene")
    assert cat.get("late").kind == "file"  # an unknown name triggers a rescan
    assert "notes" not in cat.names()
    (folder / "twin.ply").write_text("garbage")
    (folder / "twin.obj").write_text(obj)
    cat.refresh()
    # Same stem twice: the loader's extension order (.obj before .ply) picks the file.
    assert cat._entry("twin").path.suffix == ".obj"


def test_catalog_memory_scene_and_generated_listing():
    cat = SceneCatalog(Settings(generated={"city": 12345}))
    listing = {e["name"]: e for e in cat.listing()}
    assert listing["city"] == {"name": "city", "kind": "generated", "loaded": False,
                               "triangles": 12345}
    cat.register("tiny", make_tiny_scene())
    loaded = cat.get("tiny")
    assert loaded.kind == "memory" and len(loaded.grid) == 8
    assert loaded.info["triangles"] == 221 and loaded.info["kind"] == "memory"
    with pytest.raises(UnknownSceneError):
        cat.register("../evil", make_tiny_scene())


# --------------------------------------------------------------------------- compute
def test_coerce_params():
    core = NearCore()
    p = coerce_params(core, {"radius": "2.5", "resolution": "64", "granularity": "object"})
    assert p.radius == 2.5 and p.resolution == 64 and p.granularity == "object"
    assert coerce_params(core, {"resolution": 32.0}).resolution == 32
    for bad in ({"radius": "nan"}, {"resolution": "32.5"}, {"resolution": 3}, {"zzz": 1},
                {"granularity": "pixel"}, {"radius": [1, 2]}):
        with pytest.raises(ValueError):
            coerce_params(core, bad)


def test_cache_lru_bounded_in_bytes():
    pvs = [PVS(np.arange(1000 * (i + 1))) for i in range(4)]
    sizes = [pvs_nbytes(p) for p in pvs]
    cache = PVSCache(sizes[2] + sizes[3])
    for i, p in enumerate(pvs):
        cache.put(i, p)
        assert cache.nbytes <= cache.max_bytes
    assert cache.get(0) is None and cache.get(1) is None
    assert cache.get(3) is pvs[3]
    cache.put(4, PVS(np.arange(10)))  # evicts 2, the least recently used
    assert cache.get(2) is None and cache.get(3) is pvs[3]
    cache.put(9, PVS(np.arange(20_000)))  # larger than the whole bound: not stored
    assert cache.get(9) is None
    st = cache.stats()
    assert st["evictions"] >= 3 and st["bytes"] == cache.nbytes and st["hits"] == 2


@pytest.fixture
def service(registered_test_cores):
    settings = Settings(generated={}, core="test_near", core_params={"radius": 3.0}, workers=2)
    cat = SceneCatalog(settings)
    cat.register("tiny", make_tiny_scene())
    svc = ComputeService(cat, settings)
    yield svc
    svc.shutdown()


def test_service_defaults_cache_and_errors(service):
    resolver = Resolver(service.settings)
    choice = resolver.named()
    core, params = choice.core, choice.params
    assert core.name == "test_near" and params.radius == 3.0  # settings' default params
    assert choice.why == "server default"
    other = resolver.named(None, {"radius": 4.0})
    assert other.params.radius == 4.0 and other.why == "server default"
    assert resolver.named("test_near").why == "requested"
    with pytest.raises(UnknownCoreError):
        resolver.named("nope")
    with pytest.raises(UnknownCoreError):
        resolver.named("auto")  # chosen per scene: ``resolve`` with the loaded scene
    assert resolver.resolve("auto", {}) is None
    with pytest.raises(ValueError):
        resolver.named(None, {"radius": -1})
    r1 = service.submit("tiny", core, params, cell=2).result(10)
    r2 = service.submit("tiny", core, params, cell=2).result(10)
    assert not r1.cached and r2.cached and r2.pvs is r1.pvs
    box = service.catalog.get("tiny").grid.boxes[2]
    np.testing.assert_array_equal(r1.pvs.triangle_ids, near_ids(make_tiny_scene(), box, 3.0))
    np.testing.assert_array_equal(r2.box, box)
    with pytest.raises(UnknownCellError):
        service.submit("tiny", core, params, cell=99).result(10)
    with pytest.raises(UnknownSceneError):
        service.submit("nope", core, params, cell=0)
    with pytest.raises(ValueError):
        service.submit("tiny", core, params)  # neither cell nor box
    with pytest.raises(ValueError):
        service.submit("tiny", core, params, box=np.array([[1, 1, 1], [0, 0, 0]]))
    assert service.stats()["computed"] == 1 and service.stats()["inflight"] == 0


def test_service_shares_inflight_work(service):
    choice = Resolver(service.settings).named("test_slow", {"delay": 0.3})
    core, params = choice.core, choice.params
    before = type(core).calls
    futs = [service.submit("tiny", core, params, cell=1) for _ in range(5)]
    assert len({id(f) for f in futs}) == 1
    assert futs[0].result(10).pvs is not None and type(core).calls - before == 1


def test_service_with_an_inline_pool(registered_test_cores):
    """A pool that runs work at submit time (as a process-pool stand-in might) must not
    deadlock or leave stale in-flight entries."""

    class InlinePool:
        workers = 1

        def submit(self, fn, *args):
            fut = Future()
            try:
                fut.set_result(fn(*args))
            except Exception as exc:
                fut.set_exception(exc)
            return fut

        def shutdown(self, wait=True, *, cancel_futures=False):
            pass

    settings = Settings(generated={}, core="test_near")
    cat = SceneCatalog(settings)
    cat.register("tiny", make_tiny_scene())
    svc = ComputeService(cat, settings, pool=InlinePool())
    choice = Resolver(settings).named()
    core, params = choice.core, choice.params
    r = svc.submit("tiny", core, params, cell=0).result()
    assert not r.cached and svc.stats()["inflight"] == 0
    assert svc.submit("tiny", core, params, cell=0).result().cached
