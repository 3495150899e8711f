"""The ``pvs`` command line: ``scenes`` locally, ``query`` (cell, segment, box, bad input) against
the real server on loopback."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import pvs_cli


def test_scenes_lists_generators_locally(capsys):
    assert pvs_cli.main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in ("city", "rooms", "village", "stress"):
        assert name in out


def test_scenes_describes_one_with_its_edges(tmp_path, capsys):
    from tests.conftest import write_scene_files

    write_scene_files(tmp_path / "scenes")
    assert pvs_cli.main(["scenes", "box", "--scenes", str(tmp_path / "scenes")]) == 0
    info = json.loads(capsys.readouterr().out)
    edges = info["edges"]
    assert 0.0 <= edges["open_share"] <= 1.0
    assert 0.0 <= edges["t_junction_share_of_open"] <= 1.0
    assert info["grid"]["cells"] > 0


def test_query_cell_segment_and_box(live_server, capsys):
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--cell", "1",
                         "--core", "sampling", "--param", "samples=4", "--param",
                         "resolution=32", "--ids"]) == 0
    cell = json.loads(capsys.readouterr().out)
    assert cell["cell"] == 1 and cell["core"] == "sampling" and cell["count"] > 0
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--segment",
                         "1,1.7,1,3,1.9,2.5", "--core", "from_segment", "--param",
                         "resolution=32", "--ids"]) == 0
    seg = json.loads(capsys.readouterr().out)
    assert seg["segment"] == [[1, 1.7, 1], [3, 1.9, 2.5]] and seg["count"] > 0
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--box",
                         "1,1.7,1,3,1.9,2.5", "--core", "sampling", "--param", "samples=4",
                         "--param", "resolution=32"]) == 0
    box = json.loads(capsys.readouterr().out)
    assert box["segment"] is None and box["box"] == [[1, 1.7, 1], [3, 1.9, 2.5]]


def test_query_errors_are_reported_not_raised(live_server, capsys):
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "nope", "--cell",
                         "0"]) == 1
    assert "unknown_scene" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--segment", "1,2"])
    with pytest.raises(SystemExit):  # exactly one of --cell, --segment, --box
        pvs_cli.main(["query", "--server", live_server, "--scene", "tiny"])


def _serve_settings(argv, env):
    return pvs_cli.serve_settings(pvs_cli.build_parser().parse_args(["serve", *argv]), env)


def test_serve_settings_defaults_without_flags_or_env():
    s = _serve_settings([], {})
    assert (s.host, s.port) == ("127.0.0.1", 8000)
    expected = pvs_cli.DEFAULT_SCENES_DIR if pvs_cli.DEFAULT_SCENES_DIR.is_dir() else None
    assert s.scenes_dir == expected


def test_serve_settings_env_overrides_defaults(tmp_path):
    env = {"PVS_HOST": "0.0.0.0", "PVS_PORT": "9123", "PVS_SCENES_DIR": str(tmp_path),
           "PVS_WORKERS": "3", "PVS_CORE": "from_segment"}
    s = _serve_settings([], env)
    assert (s.host, s.port, s.scenes_dir) == ("0.0.0.0", 9123, tmp_path)
    assert (s.workers, s.core) == (3, "from_segment")


def test_serve_settings_flags_override_env(tmp_path):
    env = {"PVS_HOST": "0.0.0.0", "PVS_PORT": "9123", "PVS_SCENES_DIR": "/nowhere",
           "PVS_CELL_SIZE": "8", "PVS_WORKERS": "3"}
    s = _serve_settings(["--host", "127.0.0.2", "--port", "9200", "--scenes", str(tmp_path),
                         "--workers", "1"], env)
    assert (s.host, s.port, s.scenes_dir, s.workers) == ("127.0.0.2", 9200, tmp_path, 1)
    assert s.cell_size == 8.0  # not given as a flag: the environment's value stays


def test_serve_progressive_flag_overrides_env():
    assert _serve_settings([], {}).progressive is True
    assert _serve_settings(["--no-progressive"], {}).progressive is False
    assert _serve_settings(["--progressive"], {"PVS_PROGRESSIVE": "0"}).progressive is True


def test_cores_calibrate_prints_the_trials_and_autos_pick(tmp_path, capsys):
    from tests.conftest import write_scene_files

    write_scene_files(tmp_path / "scenes")
    assert pvs_cli.main(["cores", "--scene", "box", "--scenes", str(tmp_path / "scenes"),
                         "--calibrate", "--budget", "0.5"]) == 0
    out = capsys.readouterr().out
    # Measured, or stopped at the trial's deadline where another job slows the machine: the
    # trial ran and is reported either way.
    assert re.search(r"sampling \(samples=8\) +([0-9.]+ s/cell +FN|stopped at the [0-9.]+ s "
                     r"deadline)", out), out
    assert "auto: " in out and "calibrated on" in out


def test_serve_rejects_bad_values_with_a_message():
    with pytest.raises(SystemExit, match="pvs serve"):
        pvs_cli.main(["serve", "--workers", "0"])
    with pytest.raises(ValueError):
        _serve_settings([], {"PVS_PORT": "not-a-port"})


def test_demo_end_to_end_through_the_pvs_entry_point(tmp_path):
    """The README's first command's job, through the installed ``pvs`` script: the real server
    in a child process, the headless client over a short walk of a small ``rooms``; it prints
    per-frame and mean epsilon/PSNR/SSIM and writes summary.json with the documented fields."""
    exe = shutil.which("pvs", path=str(Path(sys.executable).parent))
    assert exe, "the `pvs` entry point is not installed beside this Python (run scripts/setup.sh)"
    out = tmp_path / "demo"
    env = {**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "osmesa")}
    run = subprocess.run(
        [exe, "demo", "--scene", "rooms", "--triangles", "5000", "--duration", "2",
         "--width", "64", "--height", "64", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, timeout=300,
    )
    assert run.returncode == 0, run.stdout[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    frames = summary["frames"]
    assert len(frames) >= 10  # 2 s at the client's 10 frames per second
    for rec in frames:
        assert {"t", "epsilon", "psnr", "ssim", "stalled"} <= set(rec)
        assert 0.0 <= rec["epsilon"] <= 100.0 and -1.0 <= rec["ssim"] <= 1.0
    for key in ("epsilon", "psnr", "ssim"):
        assert isinstance(summary[key], float)
    assert isinstance(summary["stalls"], int) and summary["stalls"] >= 0
    # The sampling stream of a small indoor scene matches the full scene on nearly every pixel.
    assert summary["epsilon"] < 5.0 and summary["ssim"] > 0.8
    printed = re.findall(r"frame +\d+ .*eps= *([\d.]+)% psnr= *\S+dB ssim=([\d.]+)", run.stdout)
    assert len(printed) == len(frames)
    assert float(printed[0][0]) == pytest.approx(frames[0]["epsilon"], abs=1e-3)
    means = dict(re.findall(r"^(epsilon|psnr|ssim)\b\S*(?: \(cap [^)]*\))? +(\S+)", run.stdout,
                            re.M))
    assert set(means) == {"epsilon", "psnr", "ssim"}, run.stdout[-2000:]
    assert float(means["ssim"]) == pytest.approx(summary["ssim"], rel=1e-3)
    assert f"stalls: {summary['stalls']}" in run.stdout


def test_precompute_fills_a_cache_folder_and_resumes(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PVS_GENERATED", "rooms=3000")
    monkeypatch.setenv("PVS_CORE_PARAMS", '{"samples": 4, "resolution": 32}')
    empty = tmp_path / "no-scenes"
    empty.mkdir()
    argv = ["precompute", "--scene", "rooms", "--scenes", str(empty), "--cache-dir",
            str(tmp_path / "cache"), "--cells", "0-2", "--quiet"]
    assert pvs_cli.main(argv) == 0
    assert "3 computed" in capsys.readouterr().out
    assert pvs_cli.main(argv) == 0  # a second run reads the folder instead of computing
    assert "0 computed" in (out := capsys.readouterr().out) and "3 already cached" in out
    assert len(list((tmp_path / "cache").rglob("*.npz"))) == 3


def test_precompute_errors_are_messages(tmp_path, monkeypatch):
    monkeypatch.setenv("PVS_GENERATED", "rooms=3000")
    monkeypatch.delenv("PVS_CACHE_DIR", raising=False)
    base = ["precompute", "--scenes", str(tmp_path)]
    for argv, said in (
        ([*base, "--scene", "rooms"], "cache-dir"),
        ([*base, "--scene", "nope", "--cache-dir", str(tmp_path / "c")], "nope"),
        ([*base, "--scene", "rooms", "--cache-dir", str(tmp_path / "c"), "--cells", "0-99999"],
         "outside"),
        ([*base, "--scene", "rooms", "--cache-dir", str(tmp_path / "c"), "--core", "nope"],
         "nope"),
    ):
        with pytest.raises(SystemExit) as exc:
            pvs_cli.main(argv)
        assert said in str(exc.value.code)


def test_serve_cache_dir_flag_overrides_env(tmp_path):
    s = _serve_settings(["--cache-dir", str(tmp_path / "a")], {"PVS_CACHE_DIR": str(tmp_path)})
    assert s.cache_dir == tmp_path / "a"
    assert _serve_settings([], {"PVS_CACHE_DIR": str(tmp_path)}).cache_dir == tmp_path


def test_serve_prints_the_viewer_url():
    port = pvs_cli._free_port()
    proc = subprocess.Popen([sys.executable, "-m", "pvs_cli", "serve", "--host", "0.0.0.0",
                             "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True,
                            cwd=Path(__file__).resolve().parents[1])
    try:
        line = proc.stdout.readline()
    finally:
        proc.terminate()
        proc.wait(20)
    assert line.strip() == f"viewer: http://127.0.0.1:{port}/viewer/"


def test_walk_on_a_file_scene_without_a_local_copy_says_what_to_pass(live_server, tmp_path,
                                                                      capsys):
    """The server serves ``box.obj``; the client has no copy: one line naming --scenes, no
    traceback, nothing replayed."""
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SystemExit) as exc:
        pvs_cli.main(["walk", "--server", live_server, "--scene", "box", "--scenes", str(empty),
                      "--out", str(tmp_path / "out"), "--duration", "1", "--quiet"])
    msg = str(exc.value.code)
    assert msg.startswith("pvs walk: scene 'box' is a file the server serves")
    assert "--scenes DIR" in msg and str(empty) in msg and "\n" not in msg


@pytest.fixture
def closed_port() -> str:
    """A loopback URL nothing listens on (a port bound and released)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"http://127.0.0.1:{port}"


@pytest.fixture
def not_pvs() -> str:
    """A real HTTP server on loopback that is no PVS server: every path answers 404 in HTML."""
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    class NotFound(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - the stdlib's name
            self.send_response(404)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(b"<html>not here</html>")

        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), NotFound)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


@pytest.mark.parametrize("server", ["closed_port", "not_pvs"])
@pytest.mark.parametrize("cmd", [["walk", "--duration", "1", "--quiet"], ["query", "--cell", "0"]])
def test_no_server_there_is_one_line_not_a_traceback(cmd, server, request, tmp_path):
    """Nothing listening, or an HTTP server that is not ours: the command stops with one line
    naming the URL and what to do."""
    url = request.getfixturevalue(server)
    argv = [cmd[0], "--server", url, "--scene", "village", *cmd[1:]]
    if cmd[0] == "walk":
        argv += ["--out", str(tmp_path / "out")]
    with pytest.raises(SystemExit) as exc:
        pvs_cli.main(argv)
    msg = str(exc.value.code)
    assert msg.startswith(f"pvs {cmd[0]}: no PVS server answered at {url} (")
    assert msg.endswith("start one with `pvs serve` or pass --server URL")
    assert "\n" not in msg


@pytest.mark.parametrize("cmd", ["cores", "scenes"])
def test_server_listings_without_a_server_are_one_line(cmd, closed_port):
    with pytest.raises(SystemExit) as exc:
        pvs_cli.main([cmd, "--server", closed_port])
    msg = str(exc.value.code)
    assert msg.startswith(f"pvs {cmd}: no PVS server answered at {closed_port} (")
    assert "\n" not in msg


@pytest.mark.parametrize("argv", [["scenes", "nosuch"], ["cores", "--scene", "nosuch"]])
def test_an_unknown_local_scene_names_where_it_looked(argv, tmp_path):
    with pytest.raises(SystemExit) as exc:
        pvs_cli.main([*argv, "--scenes", str(tmp_path)])
    msg = str(exc.value.code)
    assert msg.startswith("pvs: unknown scene 'nosuch': no scene file of that name in "
                          f"{tmp_path} (--scenes DIR) and no generator of it (")
    assert "village" in msg


def test_a_scenes_folder_that_is_not_there_is_said(tmp_path):
    with pytest.raises(SystemExit, match=r"^pvs: --scenes .*/missing: no such folder$"):
        pvs_cli.main(["scenes", "--scenes", str(tmp_path / "missing")])
