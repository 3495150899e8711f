"""Shared fixtures: fast server settings, a tiny hand-made scene, test cores, and the REAL uvicorn
server on loopback (``live_server`` yields its base URL).

Test cores (``test_near``, ``test_slow``, ``test_fail``, ``test_picky``) are registered only while
a module that uses the server runs, and removed afterwards so suites that walk every registered
core (the conformance suite) never see them.
"""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".numba_cache"))
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
# Bytecode written, also where pytest runs without scripts/env.sh: otherwise every server,
# worker and CLI process a test starts compiles its imports from source (docs/getting-started.md).
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

from visibility.cores import base as core_base  # noqa: E402
from visibility.cores.base import Core, CoreParams  # noqa: E402
from visibility.scene import Scene, WalkArea  # noqa: E402

#: Tiny scene: walk area 16 x 8 m (a 4 x 2 grid of 4 m cells) with box rows beside it.
TINY_WALK = [[0.0, 0.0, 16.0, 8.0, 0.0]]
#: Generators served by the test settings, at this small size (lazily: only loaded when used).
SMALL_GENERATED_TRIANGLES = 10_000


# --------------------------------------------------------------------------- tiny scene
def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """8 vertices and 12 outward triangles of an axis-aligned box."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [3, 6, 2], [3, 7, 6], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]])
    return v, f


def make_tiny_scene(offset: float = 0.0) -> Scene:
    """A ground quad, two rows of 9 boxes along the walk area and 3 degenerate faces (one
    zero-area, one repeated-index, one with a NaN vertex): 2 + 216 + 3 = 221 triangles."""
    verts = [np.array([[-2, 0, -2], [18, 0, -2], [18, 0, 10], [-2, 0, 10]], dtype=np.float64)]
    faces = [np.array([[0, 2, 1], [0, 3, 2]])]
    objs = [np.zeros(2, dtype=np.int32)]
    n = 4
    obj = 1
    for z in (-1.5, 9.5):
        for x in np.arange(0.0, 17.0, 2.0):
            v, f = _box((x - 0.4, 0.0, z - 0.4), (x + 0.4, 1.0 + 0.1 * x, z + 0.4))
            verts.append(v)
            faces.append(f + n)
            objs.append(np.full(12, obj, dtype=np.int32))
            n += 8
            obj += 1
    bad_v = np.array([[1, 0, 1], [1, 0, 1], [1, 0, 1], [np.nan, 0, 0], [2, 0, 2], [3, 1, 2]])
    verts.append(bad_v)
    faces.append(np.array([[n, n + 1, n + 2], [n + 4, n + 4, n + 5], [n + 3, n + 4, n + 5]]))
    objs.append(np.full(3, obj, dtype=np.int32))
    v = np.concatenate(verts)
    v[:, [0, 2]] += offset
    f = np.concatenate(faces)
    rng = np.random.default_rng(0)
    colors = rng.integers(0, 256, size=(len(f), 3), dtype=np.uint8)
    walk = WalkArea(rects=np.array(TINY_WALK) + [offset, offset, offset, offset, 0.0])
    return Scene(vertices=v, faces=f, object_ids=np.concatenate(objs), colors=colors,
                 name="tiny", walk=walk)


# --------------------------------------------------------------------------- test cores
@dataclass
class NearParams(CoreParams):
    #: XZ distance (metres) from the cell centre within which a triangle's centroid is visible.
    radius: float = 5.0
    delay: float = 0.0

    def validate(self) -> None:
        super().validate()
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"radius must be a positive number of metres, got {self.radius}")
        if not (0 <= self.delay <= 5):
            raise ValueError("delay must be in [0, 5] s")


def near_ids(scene: Scene, box: np.ndarray, radius: float) -> np.ndarray:
    """What ``test_near`` answers: valid triangles whose centroid is within ``radius`` (XZ) of
    the box centre, sorted int32."""
    c = np.asarray(box, dtype=np.float64).mean(axis=0)
    with np.errstate(invalid="ignore"):
        cent = scene.triangles().mean(axis=1)
        d = np.hypot(cent[:, 0] - c[0], cent[:, 2] - c[2])
    return np.nonzero((d < radius) & scene.valid_faces)[0].astype(np.int32)


class NearCore(Core):
    """Deterministic, instant stand-in for a real core."""

    name = "test_near"
    Params = NearParams
    calls = 0
    _lock = threading.Lock()

    def _compute(self, scene, cell, params):
        with NearCore._lock:
            type(self).calls += 1
        if params.delay:
            time.sleep(params.delay)
        ids = near_ids(scene, cell.box, params.radius)
        # A NaN and an array in the stats exercise the server's JSON sanitising.
        return ids, {"candidates": int(scene.n_triangles), "nan_stat": float("nan"),
                     "hist": np.arange(3)}


class SlowCore(NearCore):
    name = "test_slow"
    calls = 0


class FailCore(Core):
    name = "test_fail"

    def _compute(self, scene, cell, params):
        raise RuntimeError("deliberate failure")


class PickyCore(NearCore):
    name = "test_picky"

    def supports(self, scene):
        return False, "this core fits no scene"


TEST_CORES = (NearCore, SlowCore, FailCore, PickyCore)


@pytest.fixture(scope="module")
def registered_test_cores() -> Iterator[None]:
    """Register the test cores for one module, then remove them."""
    for cls in TEST_CORES:
        core_base.register(cls)
    yield
    for cls in TEST_CORES:
        core_base.unregister(cls.name)


# --------------------------------------------------------------------------- settings
def small_generated() -> dict[str, int]:
    """Every available generator at a small size ({} while the generators are absent)."""
    try:
        from visibility.generators import available_generators
    except ImportError:
        return {}
    return {name: SMALL_GENERATED_TRIANGLES for name in available_generators()}


def write_scene_files(folder: Path) -> None:
    """``box.obj`` (a loadable room with a sidecar walk area), ``broken.obj`` (unloadable), and
    ``outside.obj``, a symlink to a file outside the folder (must not be served)."""
    folder.mkdir(parents=True, exist_ok=True)
    v, f = _box((0.0, 0.0, 0.0), (8.0, 3.0, 8.0))
    lines = [f"v {a} {b} {c}" for a, b, c in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    (folder / "box.obj").write_text("\n".join(lines) + "\n")
    (folder / "box.json").write_text('{"walk": {"rects": [[1, 1, 7, 7, 0]]}, "cell_size": 3.0}')
    (folder / "broken.obj").write_text("this is not an obj file\n")
    secret = folder.parent / "secret_outside.obj"
    secret.write_text("\n".join(lines) + "\n")
    link = folder / "outside.obj"
    if not link.exists():
        link.symlink_to(secret)


@pytest.fixture(scope="session")
def scenes_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("server") / "scenes"
    write_scene_files(folder)
    return folder


@pytest.fixture(scope="session")
def settings(scenes_dir: Path):
    """Fast server settings: small generated scenes, small frames (so cells span several
    chunks), the scene files of ``write_scene_files``. The hello timeout is generous so a loaded
    machine does not turn other tests into timeouts (``test_hello_timeout`` shortens it)."""
    from server.settings import Settings

    return Settings(
        host="127.0.0.1", port=0, scenes_dir=scenes_dir, generated=small_generated(),
        workers=2, cache_bytes=8 * 1024 * 1024, max_frame_bytes=1024, max_message_bytes=4096,
        hello_timeout=30.0, ws_ping_interval=None, log_level="warning",
        # Tests of validation send hundreds of refused requests in a row; the rate limit has
        # its own tests (tests/server/test_robustness.py, at the defaults).
        pvs_rate=1e6, pvs_burst=1_000_000,
        # Streams carry the session core's answers only, as these tests expect; progressive
        # streams (the default) have their own tests (tests/server/test_progressive.py).
        progressive=False,
        # ``auto`` follows the cores' declared fits here, deterministically; calibrated choices
        # have their own tests (tests/server/test_calibration.py).
        calibrate=False,
    )


def wait_for(pred, timeout: float = 20.0, what: str = "condition") -> None:
    """Poll ``pred()`` every 10 ms until it is true; TimeoutError naming ``what`` after
    ``timeout`` seconds. Tests wait for the state they need rather than sleep a fixed time:
    a busy machine can take far longer to start a thread, a job or a server."""
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not met within {timeout:g} s")
        time.sleep(0.01)


async def wait_for_async(pred, timeout: float = 30.0, what: str = "condition") -> None:
    """``wait_for`` inside a coroutine: polls without blocking the event loop the test's own
    clients run on."""
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not met within {timeout:g} s")
        await asyncio.sleep(0.02)


# --------------------------------------------------------------------------- live server
class LiveServer:
    """uvicorn serving ``app`` on 127.0.0.1 in a daemon thread."""

    def __init__(self, app, settings) -> None:
        from server.app import make_server

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = make_server(app, settings, host="127.0.0.1", port=self.port)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]},
                                       name="live-uvicorn", daemon=True)

    def start(self, timeout: float = 120.0) -> None:
        # Starting loads the default core's kernels: seconds, more while other workers compile.
        self.thread.start()
        deadline = time.monotonic() + timeout
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.01)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=15)
        self.sock.close()


@contextmanager
def serving(settings, scenes: dict | None = None, **update) -> Iterator[tuple[str, Any]]:
    """The REAL server for ``settings`` with ``update`` applied and ``scenes`` ({name: Scene})
    registered, on a loopback port for the ``with`` block; yields (base URL, app)."""
    from server.app import create_app

    s = settings.model_copy(update=update) if update else settings
    app = create_app(s)
    for name, scene in (scenes or {}).items():
        app.state.server.catalog.register(name, scene)
    srv = LiveServer(app, s)
    srv.start()
    try:
        yield srv.url, app
    finally:
        srv.stop()


@pytest.fixture(scope="module")
def server_app(settings, registered_test_cores):
    """The FastAPI app of ``live_server`` with the tiny scene registered as "tiny" and, 100 km
    away from the origin, "tiny_far"."""
    from server.app import create_app

    app = create_app(settings)
    app.state.server.catalog.register("tiny", make_tiny_scene())
    app.state.server.catalog.register("tiny_far", make_tiny_scene(offset=1e5))
    return app


@pytest.fixture(scope="module")
def live_server(server_app, settings) -> Iterator[str]:
    """The REAL server on loopback; yields its base URL (http://127.0.0.1:PORT)."""
    srv = LiveServer(server_app, settings)
    srv.start()
    yield srv.url
    srv.stop()


@pytest.fixture(scope="module")
def ws_endpoint(live_server: str) -> str:
    """The live server's WebSocket URL (ws://127.0.0.1:PORT/ws)."""
    return live_server.replace("http://", "ws://") + "/ws"
