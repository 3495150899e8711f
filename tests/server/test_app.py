"""``server/app.py``: a real ``pvs serve`` process says at start when its kernels are not
compiled (each would compile at the first cells, stalling walkers)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pvs_cli

ROOT = Path(__file__).resolve().parents[2]
WARNING = "numba kernel cache"


def _startup_log(cache_dir: str, tmp_path: Path) -> str:
    """stderr of a ``pvs serve`` started with ``NUMBA_CACHE_DIR=cache_dir`` up to its first
    healthy answer."""
    port = pvs_cli._free_port()
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir, "PYTHONPATH": str(ROOT),
           "PVS_LOG_LEVEL": "warning"}
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
    out = _startup_log(str(tmp_path / "empty-cache"), tmp_path)
    assert WARNING in out and "is empty" in out and "pvs warmup" in out


def test_a_server_on_the_compiled_cache_does_not(tmp_path):
    # The test command runs `pvs warmup` into the project's cache before pytest.
    cache = os.environ.get("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    assert WARNING not in _startup_log(cache, tmp_path)
