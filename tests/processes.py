"""Stopping the real processes tests start (servers, Redis, Dask, nginx)."""

from __future__ import annotations

import subprocess


def stop_process(proc: subprocess.Popen, kill: bool = False, timeout: float = 20.0) -> None:
    """Stop ``proc``: SIGTERM (SIGKILL when ``kill``, a crash), then SIGKILL if it has not
    exited within ``timeout`` seconds; closes its stderr pipe."""
    if proc.poll() is None:
        proc.kill() if kill else proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    if proc.stderr is not None:
        proc.stderr.close()
