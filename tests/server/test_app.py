"""``server/app.py``: a real ``pvs serve`` process says at start when its kernels are not
compiled (each would compile at the first cells, stalling walkers), and loads its cores'
kernels before it serves."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import httpx

import pvs_cli

ROOT = Path(__file__).resolve().parents[2]
WARNING = "numba kernel cache"


def _startup_log(cache_dir: str, tmp_path: Path, **env_update: str) -> str:
    """stderr of a ``pvs serve`` started with ``NUMBA_CACHE_DIR=cache_dir`` (and
    ``env_update``) up to its first healthy answer."""
    port = pvs_cli._free_port()
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir, "PYTHONPATH": str(ROOT),
           "PVS_LOG_LEVEL": "warning", **env_update}
    log = tmp_path / f"serve-{port}.log"
    with log.open("wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1", "--port",
             str(port), "--scenes", str(tmp_path / "no-scenes")],
            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err)
        try:
            assert pvs_cli.wait_until_healthy(f"http://127.0.0.1:{port}", proc), log.read_text()
        finally:
            proc.terminate()
            proc.wait(20)
    return log.read_text()


def test_a_server_on_an_empty_kernel_cache_warns_at_start(tmp_path):
    # Not loading its kernels ahead: on an empty cache that compiles them (minutes).
    out = _startup_log(str(tmp_path / "empty-cache"), tmp_path, PVS_PRELOAD_KERNELS="0")
    assert WARNING in out and "is empty" in out and "pvs warmup" in out


def test_a_server_on_the_compiled_cache_does_not(tmp_path):
    # The test command runs `pvs warmup` into the project's cache before pytest.
    cache = os.environ.get("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    assert WARNING not in _startup_log(cache, tmp_path)


def test_a_server_loads_its_cores_kernels_before_it_serves(tmp_path):
    cache = os.environ.get("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    out = _startup_log(cache, tmp_path, PVS_LOG_LEVEL="info", PVS_CORE="dual_ray")
    loaded = out.index("kernels of dual_ray, sampling loaded in")
    # uvicorn says it is up once the lifespan's start-up is done.
    assert loaded < out.index("Application startup complete")


def test_preload_names_the_default_and_first_answer_cores():
    from server.app import preload_cores
    from server.settings import Settings
    from visibility.cores.base import available_cores

    assert preload_cores(Settings()) == ["sampling"]
    assert preload_cores(Settings(core="cos", first_core="sampling")) == ["cos", "sampling"]
    assert preload_cores(Settings(core="auto")) == available_cores()


def test_a_core_that_cannot_load_never_stops_the_server(settings, caplog):
    from tests.conftest import serving

    bad = settings.model_copy(update={"preload_kernels": True, "first_core": "no_such_core"})
    with caplog.at_level("ERROR", logger="server.app"), serving(bad) as (url, _app):
        assert httpx.get(url + "/health", timeout=10).status_code == 200
    assert "could not load the kernels of core 'no_such_core'" in caplog.text
