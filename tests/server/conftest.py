"""Fixtures of the HTTP tests against the live server (``tests.conftest.live_server``)."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest


@pytest.fixture(scope="module")
def http(live_server: str) -> Iterator[httpx.Client]:
    """An HTTP client on the live server (generous timeout: real cores run on 2 cores)."""
    with httpx.Client(base_url=live_server, timeout=120) as client:
        yield client


@pytest.fixture
def still_healthy(http: httpx.Client) -> Iterator[None]:
    """After the test the server is up and answers /health with ok (a module opts in with
    ``pytestmark = pytest.mark.usefixtures("still_healthy")``)."""
    yield
    r = http.get("/health")
    assert r.status_code == 200 and r.json()["status"] == "ok"


@pytest.fixture(scope="module")
def redis_server() -> Iterator:
    """A REAL ``redis-server`` on a free loopback port for the module (``tests.redis_process``);
    a missing binary fails (``scripts/setup.sh`` installs the Debian package redis-server)."""
    from benchmarks.redis_process import RedisProcess, available

    assert available(), "redis-server is missing: scripts/setup.sh installs it"
    proc = RedisProcess().start()
    try:
        yield proc
    finally:
        proc.close()
