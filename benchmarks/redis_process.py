"""A real ``redis-server`` on a loopback port, for tests and benchmarks: started, killed and
restarted on demand, never persisting anything (``--save ''``, ``--appendonly no``).

``scripts/setup.sh`` installs the Debian package ``redis-server``; ``available()`` says whether
the binary is here (tests fail with that reason when it is not: a broken set-up).
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import time

from benchmarks.common import free_port, stop_process

REDIS_SERVER = "redis-server"


def available() -> bool:
    """Whether ``redis-server`` is on PATH."""
    return shutil.which(REDIS_SERVER) is not None


class RedisProcess:
    """``redis-server`` on 127.0.0.1:``port`` (default a free one), bounded by ``maxmemory``
    with LRU eviction, as the README advises for the shared cache."""

    def __init__(self, port: int | None = None, maxmemory: str = "64mb") -> None:
        self.port = port or free_port()
        self.maxmemory = maxmemory
        self.proc: subprocess.Popen | None = None
        self._dir = tempfile.TemporaryDirectory(prefix="pvs-redis-")

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 15.0) -> RedisProcess:
        """Start it and wait until it answers PING; RuntimeError when it does not."""
        import redis

        cmd = [REDIS_SERVER, "--port", str(self.port), "--bind", "127.0.0.1",
               "--save", "", "--appendonly", "no", "--dir", self._dir.name,
               "--maxmemory", self.maxmemory, "--maxmemory-policy", "allkeys-lru"]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        client = redis.Redis(host="127.0.0.1", port=self.port, socket_timeout=0.5,
                             socket_connect_timeout=0.5)
        deadline = time.monotonic() + timeout
        try:
            while True:
                try:
                    if client.ping():
                        return self
                except redis.RedisError:
                    pass
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    err = self.proc.stderr.read().decode()[-2000:] if self.proc.stderr else ""
                    self.stop()
                    raise RuntimeError(f"redis-server on port {self.port} did not start: {err}")
                time.sleep(0.05)
        finally:
            client.close()

    def stop(self, kill: bool = False) -> None:
        """Stop it: SIGKILL when ``kill`` (a crash), else SIGTERM."""
        proc, self.proc = self.proc, None
        if proc is not None:
            stop_process(proc, kill=kill, timeout=10)

    def client(self):
        """A redis-py client on it (for assertions)."""
        import redis

        return redis.Redis(host="127.0.0.1", port=self.port, socket_timeout=2)

    def close(self) -> None:
        """Stop it and remove its folder."""
        self.stop()
        self._dir.cleanup()
