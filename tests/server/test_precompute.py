"""``server.precompute``: a scene's cells computed ahead into the on-disk cache, read back by a
fresh service and by a real server started on the same folder."""

from __future__ import annotations

import hashlib

import httpx
import numpy as np
import pytest

from server.catalog import SceneCatalog, UnknownSceneError
from server.compute import ComputeService
from server.precompute import parse_cells, precompute
from server.region import UnknownCellError, cell_key
from server.resolve import CoreChoice, Resolver, UnknownCoreError
from tests.conftest import serving

FAST = {"samples": 4, "resolution": 32}


@pytest.fixture
def disk_settings(settings, tmp_path):
    return settings.model_copy(update={"cache_dir": tmp_path / "pvs-cache",
                                       "generated": {"rooms": 3000}, "core": "sampling",
                                       "core_params": FAST})


def _service(s) -> ComputeService:
    return ComputeService(SceneCatalog(s), s)


def _default(service: ComputeService) -> CoreChoice:
    """The server default core and parameters of ``service``'s settings."""
    return Resolver(service.settings).named()


def test_precompute_fills_the_disk_cache_a_restart_reads(disk_settings):
    first = _service(disk_settings)
    try:
        report = precompute(first, "rooms", cells=[0, 1, 2, 3], progress=False)
        default = _default(first)
        ids = {c: first.submit("rooms", default.core, default.params,
                               cell=c).result().pvs.triangle_ids for c in range(4)}
    finally:
        first.shutdown()
    assert (report.computed, report.cached, report.failed) == (4, 0, {})
    assert report.core == "sampling" and report.params["samples"] == 4
    assert report.compute_seconds > 0 and "4 computed" in report.summary()
    assert "auto" not in report.summary()
    # A fresh service (a restarted server) finds every cell on disk, computing nothing.
    second = _service(disk_settings)
    try:
        again = precompute(second, "rooms", cells=range(4), progress=False)
    finally:
        second.shutdown()
    assert (again.computed, again.cached) == (0, 4) and second.computed == 0
    # And so does the real server on that folder, over HTTP, with the same ids.
    with serving(disk_settings) as (url, app):
        for c in range(4):
            r = httpx.get(f"{url}/scenes/rooms/cells/{c}/pvs", timeout=60)
            assert r.status_code == 200 and r.json()["cached"] is True
            assert np.array_equal(r.json()["triangle_ids"], ids[c])
        assert app.state.server.compute.computed == 0


def test_precompute_auto_says_which_core_and_why(disk_settings):
    service = _service(disk_settings.model_copy(update={"core_params": {}}))
    try:
        report = precompute(service, "rooms", core="auto", params={"resolution": 32},
                            cells=[0], progress=False)
    finally:
        service.shutdown()
    assert report.core == "from_segment" and report.computed == 1
    assert "(auto: static triangle scene" in report.summary()


def test_precompute_refuses_bad_requests_before_computing(disk_settings):
    service = _service(disk_settings)
    try:
        n = len(service.catalog.get("rooms").grid)
        with pytest.raises(UnknownCellError):
            precompute(service, "rooms", cells=[0, n], progress=False)
        with pytest.raises(UnknownSceneError):
            precompute(service, "../etc", progress=False)
        with pytest.raises(UnknownCoreError):
            precompute(service, "rooms", core="nope", progress=False)
        with pytest.raises(ValueError):
            precompute(service, "rooms", params={"samples": -1}, progress=False)
        assert service.computed == 0
    finally:
        service.shutdown()


def test_parse_cells_ranges_and_errors():
    assert parse_cells("3,0-2, 2,7-7", 10) == [0, 1, 2, 3, 7]
    for bad in ("", "a", "5-2", "0-10", "-1", "1-x"):
        with pytest.raises(ValueError):
            parse_cells(bad, 10)


def test_precompute_counts_unwritable_entries_and_failed_cells_as_failures(disk_settings,
                                                                           monkeypatch):
    from server.cache import DiskPVSCache

    service = _service(disk_settings)
    real_put = DiskPVSCache.put

    def unlucky(key) -> bool:
        return hashlib.sha256(repr(key).encode()).digest()[0] % 2 == 1

    def flaky_put(self, key, pvs, n_triangles=None):
        # Some keys fail to write (a full disk, say); which is fixed by the key.
        if unlucky(key):
            return False
        return real_put(self, key, pvs, n_triangles)

    monkeypatch.setattr(DiskPVSCache, "put", flaky_put)
    try:
        report = precompute(service, "rooms", cells=range(6), progress=False)
        default = _default(service)
        loaded = service.catalog.get("rooms")
        unwritten = {c for c in range(6)
                     if unlucky(cell_key(loaded, c, default.core, default.params))}
    finally:
        service.shutdown()
    assert unwritten and len(unwritten) < 6
    assert set(report.failed) == unwritten
    assert all("could not be written" in why for why in report.failed.values())
    assert report.computed == 6 - len(unwritten)
    assert f"{len(unwritten)} failed" in report.summary()


def test_precompute_reports_a_cell_whose_computation_fails(disk_settings, monkeypatch):
    service = _service(disk_settings)
    default = _default(service)
    core = default.core

    def boom(scene, cell, params, token=None):
        if cell.id == 1:
            raise RuntimeError("kernel blew up")
        return real(scene, cell, params, token=token)

    real = type(core).compute.__get__(core)
    monkeypatch.setattr(core, "compute", boom)
    resolver = Resolver(service.settings)
    monkeypatch.setattr(resolver, "resolve", lambda *a, **k: default)
    try:
        report = precompute(service, "rooms", cells=[0, 1, 2], progress=False,
                            resolver=resolver)
    finally:
        service.shutdown()
    assert set(report.failed) == {1} and "kernel blew up" in report.failed[1]
    assert report.computed == 2 and "1 failed" in report.summary()
