"""A new core is one package and nothing else: a throwaway core written into a temporary folder,
registered only through the ``pvs.cores`` entry-point group of a distribution in that folder,
is listed by a real server's ``GET /cores``, chosen by ``auto`` where it declares the best fit,
passes ``check_core`` and shows up in ``pvs bench --quick``. No file of the repository changes."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import httpx
import pytest

from pvs_cli import wait_until_healthy

REPO = Path(__file__).resolve().parents[1]

PLUGIN = textwrap.dedent('''
    """A throwaway core: point sampling that declares itself the best fit for room scenes."""
    from visibility.cores.sampling import SamplingCore


    class ThrowawayCore(SamplingCore):
        name = "throwaway"
        description = "a test plugin: point sampling under another name"
        fits = "scenes whose generator is rooms"

        def suitability(self, scene, cell_size):
            if scene.meta.get("generator") == "rooms":
                return 50.0, "rooms scene: the throwaway plugin says it fits best"
            return 0.01, "not a rooms scene"
''')


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("plugin")
    (root / "throwaway_core").mkdir()
    (root / "throwaway_core" / "__init__.py").write_text(PLUGIN)
    dist = root / "throwaway_core-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: throwaway-core\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(
        "[pvs.cores]\nthrowaway = throwaway_core:ThrowawayCore\n")
    return root


def _env(plugin_path: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(plugin_path), str(REPO),
                                         env.get("PYTHONPATH", "")])
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_plugin_core_passes_check_core(plugin_path):
    code = ("from visibility.cores.checks import check_core\n"
            "from visibility.cores.base import available_cores\n"
            "assert 'throwaway' in available_cores(), available_cores()\n"
            "check_core('throwaway')\nprint('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], env=_env(plugin_path), cwd=REPO,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith("ok")


def test_plugin_core_is_served_and_chosen_by_auto(plugin_path, tmp_path):
    port = _free_port()
    env = _env(plugin_path) | {"PVS_GENERATED": "rooms=3000,city=3000", "PVS_SCENES_DIR": ""}
    log = open(tmp_path / "server.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1",
                             "--port", str(port), "--scenes", str(tmp_path)],
                            env=env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        assert wait_until_healthy(url, proc), (tmp_path / "server.log").read_text()[-3000:]
        listing = httpx.get(url + "/cores", timeout=60).json()
        names = [c["name"] for c in listing["cores"]]
        assert "throwaway" in names and "sampling" in names
        mine = next(c for c in listing["cores"] if c["name"] == "throwaway")
        assert mine["fits"] == "scenes whose generator is rooms"
        assert {p["name"] for p in mine["params"]} >= {"resolution", "samples"}
        fit = httpx.get(url + "/cores", params={"scene": "rooms"}, timeout=120).json()["fit"]
        assert fit["auto"]["core"] == "throwaway" and "throwaway plugin" in fit["auto"]["why"]
        city = httpx.get(url + "/cores", params={"scene": "city"}, timeout=120).json()["fit"]
        assert city["auto"]["core"] != "throwaway"
        r = httpx.get(url + "/scenes/rooms/cells/0/pvs",
                      params={"core": "auto", "samples": 2, "resolution": 16}, timeout=300)
        assert r.status_code == 200, r.text
        assert r.json()["core"] == "throwaway"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        log.close()


def test_plugin_core_shows_up_in_pvs_bench_quick(plugin_path, tmp_path):
    out = tmp_path / "BENCH.md"
    argv = ["--quick", "--scenes", "rooms:1500", "--levels", "1", "--gt-points", "8",
            "--gt-resolution", "32", "--views", "1", "--view-size", "32", "--resolution", "32",
            "--cores", "throwaway", "--reference", "none", "--no-peer", "--out", str(out),
            "--results-dir", str(tmp_path), "--cache-dir", str(tmp_path / "cache")]
    run = subprocess.run([sys.executable, "-m", "pvs_cli", "bench", *argv],
                         env=_env(plugin_path), cwd=REPO, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    rows = json.loads((tmp_path / "bench_quick.json").read_text())["rows"]
    assert {r["core"] for r in rows} == {"throwaway"}
    assert "throwaway" in out.read_text()
