"""The ``pvs`` command line: the one place that knows every package (the composition root).

Subcommands: ``serve`` (the edge server), ``walk`` (headless client over a walkthrough),
``query`` (a cell's PVS over HTTP), ``scenes`` (list or describe scenes), ``precompute`` (a
scene's cell PVS into the on-disk cache a server starts with), ``demo`` (server + client end to
end on a built-in scene), ``warmup`` (compile the kernels into the numba cache). Packages stay
independent of each other; only this module imports both the server and the client, each lazily
inside its subcommand.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: Where the real third-party scenes live when the repository sits beside ``shared/``.
DEFAULT_SCENES_DIR = Path(__file__).resolve().parent.parent / "shared" / "scenes"


def parse_params(items: list[str] | None) -> dict:
    """``["resolution=128", "runs=2"]`` -> {"resolution": 128, "runs": 2} (JSON values)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise SystemExit(f"--param takes NAME=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def _token(args: argparse.Namespace) -> str | None:
    """The bearer token for a server with access control: ``--token``, else ``PVS_TOKEN``."""
    return getattr(args, "token", None) or os.environ.get("PVS_TOKEN") or None


def _auth_headers(args: argparse.Namespace) -> dict[str, str]:
    """The ``Authorization`` header of ``_token`` ({} without one)."""
    from protocol.auth import authorization_header

    token = _token(args)
    return authorization_header(token) if token else {}


def _add_token_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--token", help="bearer token of a server with access control (default "
                                   "PVS_TOKEN, which keeps it out of the process list)")


def serve_settings(args: argparse.Namespace, env: Mapping[str, str] | None = None):
    """The server's ``Settings`` for ``pvs serve``: flags the user gave override ``PVS_*``
    environment variables (``env``, default ``os.environ``), which override the defaults; the
    scenes folder falls back to ``../shared/scenes`` only when neither names one."""
    from server.settings import Settings

    env = os.environ if env is None else env
    flags = {"host": args.host, "port": args.port, "core": args.core,
             "cell_size": args.cell_size, "workers": args.workers,
             "scenes_dir": Path(args.scenes) if args.scenes else None,
             "cache_dir": Path(args.cache_dir) if getattr(args, "cache_dir", None) else None,
             "progressive": getattr(args, "progressive", None),
             "tokens_file": Path(args.tokens_file) if getattr(args, "tokens_file", None)
             else None, "cors_origins": getattr(args, "cors_origin", None),
             "executor": getattr(args, "executor", None),
             "cache": getattr(args, "cache", None)}
    updates = {k: v for k, v in flags.items() if v is not None}
    if "scenes_dir" not in updates and not env.get("PVS_SCENES_DIR") \
            and DEFAULT_SCENES_DIR.is_dir():
        updates["scenes_dir"] = DEFAULT_SCENES_DIR
    return Settings.from_env(env, **updates)


def cmd_serve(args: argparse.Namespace) -> int:
    from server.app import serve

    try:
        settings = serve_settings(args)
    except ValueError as exc:  # pydantic's ValidationError: a bad flag or PVS_* value
        raise SystemExit(f"pvs serve: {exc}") from None
    print(f"viewer: {served_viewer_url(settings.host, settings.port)}", flush=True)
    serve(settings)
    return 0


def served_viewer_url(host: str, port: int, scene: str | None = None,
                      core: str | None = None) -> str:
    """The browser viewer's URL on a server listening on ``host:port`` (a wildcard address is
    reached on this machine's loopback)."""
    from server.viewer_files import viewer_url

    host = "127.0.0.1" if host in ("", "0.0.0.0") else "[::1]" if host == "::" else host
    return viewer_url(f"http://{host}:{port}", scene, core)


def walk_cores(args: argparse.Namespace) -> list[str | None]:
    """The cores a walk replays: ``--cores a,b,c`` when given, else ``--core`` (which also takes
    a comma list), else ``[None]`` (the server's default core); SystemExit when a given list is
    empty."""
    text = args.cores if getattr(args, "cores", None) else args.core
    if text is None:
        return [None]
    cores = [c.strip() for c in text.split(",") if c.strip()]
    if not cores:
        raise SystemExit(f"no core named in {text!r}")
    return cores


def cmd_walk(args: argparse.Namespace) -> int:
    from client.replay import ReplayOptions, replay_cores
    from client.session import SessionError

    opts = ReplayOptions(
        server=args.server,
        scene=args.scene,
        cores=walk_cores(args),
        params=parse_params(args.param),
        walkthrough=Path(args.walkthrough) if args.walkthrough else None,
        out_dir=Path(args.out),
        scenes_dir=Path(args.scenes) if args.scenes else DEFAULT_SCENES_DIR,
        duration=args.duration,
        width=args.width,
        height=args.height,
        realtime=args.realtime,
        seed=args.seed,
        quiet=args.quiet,
        budget=args.budget,
        token=_token(args),
    )
    from websockets.exceptions import InvalidHandshake, InvalidURI

    try:
        summaries = replay_cores(opts)
    except SessionError as exc:  # refused: no token, a bad one, a scene it may not use, ...
        raise SystemExit(f"pvs walk: the server refused the session: {exc}") from None
    except (FileNotFoundError, ValueError) as exc:  # no local copy, or another one
        raise SystemExit(f"pvs walk: {exc}") from None
    except (OSError, InvalidHandshake, InvalidURI) as exc:
        raise SystemExit(_unreachable("walk", args.server, exc)) from None
    bad = [s for s in summaries if s.get("frames_rendered", 0) == 0]
    return 1 if bad else 0


def _six_floats(text: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 6:
        raise argparse.ArgumentTypeError(f"expected six comma-separated numbers, got {text!r}")
    return vals


def _unreachable(cmd: str, server: str, why: object) -> str:
    """The one line a command prints when ``server`` cannot be reached or is no PVS server."""
    why = str(why) or type(why).__name__
    return (f"pvs {cmd}: no PVS server answered at {server} ({why}); start one with "
            f"`pvs serve` or pass --server URL")


def _call(cmd: str, args: argparse.Namespace, method: str, path: str,
          timeout: float = 600.0, **kw) -> tuple[int, Any]:
    """(status, JSON body) of ``method`` ``path`` on ``args.server`` with the user's token;
    one line, not a traceback, when no PVS server answers there (``_unreachable``)."""
    import httpx

    try:
        r = httpx.request(method, args.server.rstrip("/") + path, timeout=timeout,
                          headers=_auth_headers(args), **kw)
        return r.status_code, r.json()
    except httpx.HTTPError as exc:
        raise SystemExit(_unreachable(cmd, args.server, exc)) from None
    except json.JSONDecodeError:
        raise SystemExit(_unreachable(cmd, args.server, "the answer is not JSON")) from None


def cmd_query(args: argparse.Namespace) -> int:
    params = parse_params(args.param)
    base = f"/scenes/{args.scene}"
    region = args.segment or args.box
    if region is not None:
        p, q = region[:3], region[3:]
        req: dict = {"segment" if args.segment else "box": [p, q], "params": params}
        if args.core:
            req["core"] = args.core
        status, body = _call("query", args, "POST", f"{base}/pvs", args.timeout, json=req)
    else:
        if args.core:
            params["core"] = args.core
        status, body = _call("query", args, "GET", f"{base}/cells/{args.cell}/pvs",
                             args.timeout, params=params)
    if status != 200:
        print(json.dumps(body, indent=2), file=sys.stderr)
        return 1
    if args.ids:
        print(json.dumps(body))
    else:
        ids = body.pop("triangle_ids", [])
        body["triangle_ids"] = f"[{len(ids)} ids]" if len(ids) > 10 else ids
        print(json.dumps(body, indent=2))
    return 0


def _scene_files(scenes: str | None) -> dict[str, Path]:
    """{stem: path} of the scene files in ``scenes`` (default: ../shared/scenes)."""
    from visibility.loaders import SCENE_EXTENSIONS

    folder = Path(scenes) if scenes else DEFAULT_SCENES_DIR
    if not folder.is_dir():
        if scenes:  # named by the user: a typo should not look like an empty folder
            raise SystemExit(f"pvs: --scenes {scenes}: no such folder")
        return {}
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix in SCENE_EXTENSIONS}


def _local_scene(name: str, scenes: str | None):
    """The scene file ``name`` in ``scenes``, else the generated scene of that name."""
    from visibility.generators import available_generators, make_scene
    from visibility.loaders import load_scene

    files = _scene_files(scenes)
    if name in files:
        return load_scene(files[name])
    if name not in available_generators():
        folder = scenes or DEFAULT_SCENES_DIR
        raise SystemExit(f"pvs: unknown scene {name!r}: no scene file of that name in {folder} "
                         f"(--scenes DIR) and no generator of it "
                         f"({', '.join(available_generators())})")
    return make_scene(name)


def _server_json(cmd: str, args: argparse.Namespace, path: str,
                 params: dict | None = None) -> int:
    """Print a running server's JSON answer to GET ``path``: 0 when it is 200, else 1."""
    status, body = _call(cmd, args, "GET", path, params=params or {})
    print(json.dumps(body, indent=2))
    return 0 if status == 200 else 1


def cores_help() -> str:
    """Every registered core with its promise and parameters (units, ranges, defaults), as the
    cores declare them: the help text of the commands that take ``--core`` and ``--param``."""
    from visibility.cores.base import AUTO_CORE, available_cores, get_core

    lines = [f"cores (--core NAME, or {AUTO_CORE!r}: chosen per scene; --param NAME=VALUE):"]
    for name in available_cores():
        core = get_core(name)
        lines.append(f"  {name}: {core.promise}; fits {core.fits}")
        lines += [f"    {s.name:<18} {s.describe()}" for s in core.param_specs()]
    return "\n".join(lines)


def cmd_cores(args: argparse.Namespace) -> int:
    """List the cores (the local registry, or a running server's ``GET /cores``)."""
    if args.server:
        return _server_json("cores", args, "/cores", {"scene": args.scene} if args.scene else None)
    if args.scene:
        from server.calibration import decide_auto, fit_report
        from visibility.calibration import (
            BUDGET_SECONDS,
            calibrate,
            load_calibration,
            save_calibration,
        )
        from visibility.scene import scene_fingerprint
        from visibility.viewcells import DEFAULT_CELL_SIZE

        scene = _local_scene(args.scene, args.scenes)
        # The grid's rule (sidecar, else the default) without building the grid.
        size = float(args.cell_size or scene.meta.get("cell_size") or DEFAULT_CELL_SIZE)
        budget = args.budget or BUDGET_SECONDS
        folder = Path(args.cache_dir) if args.cache_dir else None
        cal = None
        if args.calibrate:
            cal = calibrate(scene, size, budget_seconds=budget, progress=print)
            for what, why in cal.skipped.items():
                print(f"{what}: skipped: {why}")
            if folder is not None:
                save_calibration(folder, cal)
        elif folder is not None:
            cal = load_calibration(folder, scene_fingerprint(scene), size)
        # The server's own decision (``server.calibration``): what a server with this
        # calibration in its cache folder gives a session asking for auto.
        decision = decide_auto(scene, size, cal, budget)
        if args.calibrate:
            print(f"calibrated in {cal.seconds:.1f} s; auto: {decision.label()}: "
                  f"{decision.why}")
            return 0
        print(json.dumps(fit_report(scene, size, decision), indent=2))
        return 0
    print(cores_help())
    return 0


def cmd_scenes(args: argparse.Namespace) -> int:
    if args.server:
        return _server_json("scenes", args, f"/scenes/{args.name}" if args.name else "/scenes")
    from visibility.generators import DEFAULT_TRIANGLES, available_generators
    from visibility.scene_analysis import is_2_5d
    from visibility.viewcells import ViewcellGrid

    files = _scene_files(args.scenes)
    if not args.name:
        for g in available_generators():
            print(f"{g:16s} generated  {DEFAULT_TRIANGLES.get(g, 0):>10,d} triangles (default)")
        for stem, p in files.items():
            print(f"{stem:16s} file       {p}")
        return 0
    scene = _local_scene(args.name, args.scenes)
    info = scene.summary()
    flat, how = is_2_5d(scene)
    info["is_2_5d"] = {"value": flat, "source": how["source"], "why": how["reason"]}
    info["grid"] = ViewcellGrid.for_scene(scene).to_dict()
    # Where cos can fuse occluders: edges of one triangle only after welding, and how many of
    # those are T-junctions (continuous surfaces fusion cannot join).
    from visibility.cores.cos.fusion import open_edge_share, t_junction_share

    info["edges"] = {"open_share": round(open_edge_share(scene), 4),
                     "t_junction_share_of_open": round(t_junction_share(scene), 4)}
    print(json.dumps(info, indent=2))
    return 0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_healthy(url: str, proc: subprocess.Popen, timeout: float = 120.0) -> bool:
    """Poll ``url``/health until it answers 200 (True), or until ``proc`` exits or ``timeout``
    seconds pass (False): how every caller that starts a server process waits for it."""
    import httpx

    deadline = time.monotonic() + timeout
    while True:
        try:
            if httpx.get(url + "/health", timeout=2).status_code == 200:
                return True
        except httpx.HTTPError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            return False
        time.sleep(0.2)


def cmd_demo(args: argparse.Namespace) -> int:
    """Start the real server in a child process, replay a walkthrough against it, stop it."""

    port = args.port or _free_port()
    url = f"http://127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1", "--port", str(port)]
    if args.scenes:
        cmd += ["--scenes", args.scenes]
    env = dict(os.environ)
    if args.near_far:
        # The child server reads PVS_*: near-far streams (near PVS geometry + far cubemap).
        env["PVS_NEAR_FAR"] = "1"
        for flag, var in (("r1", "PVS_NEAR_FAR_R1"), ("r2", "PVS_NEAR_FAR_R2"),
                          ("cubemap_resolution", "PVS_NEAR_FAR_RESOLUTION"),
                          ("near_far_block", "PVS_NEAR_FAR_BLOCK")):
            if getattr(args, flag) is not None:
                env[var] = str(getattr(args, flag))
    if args.triangles is not None:
        from visibility.generators import available_generators

        if args.scene not in available_generators():
            raise SystemExit(f"--triangles sizes a generated scene; {args.scene!r} is not one")
        # The child server reads PVS_GENERATED; the client regenerates the same scene from the
        # welcome's source (name, size, seed) for its ground truth.
        env["PVS_GENERATED"] = f"{args.scene}={int(args.triangles)}"
    log_path = Path(args.out) / "server.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    print(f"[demo] starting server: {' '.join(cmd)} (log: {log_path})", flush=True)
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            if not wait_until_healthy(url, proc):
                print(log_path.read_text()[-3000:], file=sys.stderr)
                raise SystemExit("[demo] the server did not start")
            print(f"[demo] server up at {url}; watch it in a browser while the walk runs: "
                  f"{served_viewer_url('127.0.0.1', port, args.scene, args.core)}", flush=True)
            # Every walk option the demo parsed, pointed at the child server.
            walk = argparse.Namespace(**{**vars(args), "server": url, "quiet": False})
            return cmd_walk(walk)
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


def _add_walk_options(p: argparse.ArgumentParser, default_out: str) -> None:
    p.add_argument("--scene", default="rooms", help="scene name (generated or a file stem)")
    p.add_argument("--core", default=None,
                   help="core name, or several separated by commas (default: the server's; "
                        "'pvs cores' lists them)")
    p.add_argument("--cores", metavar="A,B,C",
                   help="replay the same walkthrough against each of these cores and print their "
                        "means side by side (overrides --core)")
    p.add_argument("--budget", type=int,
                   help="most triangles the client holds (declared to the server, which drops "
                        "held ones to make room; the client evicts itself as a last resort)")
    p.add_argument("--param", action="append", help="core parameter NAME=VALUE (repeatable)")
    p.add_argument("--walkthrough", help="walkthrough JSON file (default: generate one)")
    p.add_argument("--out", default=default_out, help="output folder for the report")
    p.add_argument("--scenes", help="folder of scene files (for file scenes' ground truth)")
    p.add_argument("--duration", type=float, default=12.0, help="generated walk length, seconds")
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=256)
    p.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=True,
                   help="pace frames at their timestamps, so stalls measure prefetch at the "
                        "walk's speed (default); --no-realtime replays as fast as possible")
    p.add_argument("--seed", type=int, default=0)


def cmd_precompute(args: argparse.Namespace) -> int:
    from server.catalog import SceneCatalog, SceneLoadFailed, UnknownSceneError
    from server.compute import ComputeService
    from server.precompute import parse_cells, precompute
    from server.region import UnknownCellError
    from server.resolve import UnknownCoreError

    try:
        settings = serve_settings(args)
    except ValueError as exc:
        raise SystemExit(f"pvs precompute: {exc}") from None
    if settings.cache_dir is None and settings.cache == "disk":
        raise SystemExit("pvs precompute: name the on-disk cache or the Redis the server will "
                         "read (--cache-dir or PVS_CACHE_DIR, --cache redis://... or PVS_CACHE); "
                         "without one the work is lost on exit")
    catalog = SceneCatalog(settings)
    service = ComputeService(catalog, settings)
    try:
        cells = None
        if args.cells:
            cells = parse_cells(args.cells, len(catalog.get(args.scene).grid))
        report = precompute(service, args.scene, args.core, parse_params(args.param), cells,
                            progress=not args.quiet)
    except (UnknownSceneError, UnknownCoreError, UnknownCellError, SceneLoadFailed,
            ValueError) as exc:
        raise SystemExit(f"pvs precompute: {exc.args[0] if exc.args else exc}") from None
    finally:
        service.shutdown()
    print(report.summary())
    for cell, why in sorted(report.failed.items())[:10]:
        print(f"  cell {cell} failed: {why}", file=sys.stderr)
    return 1 if report.failed else 0


def cmd_bench(args: argparse.Namespace) -> int:
    # benchmarks/ lives in the repository, not in the installed packages: import it from there.
    repo = str(Path(__file__).resolve().parent)
    if repo not in sys.path:
        sys.path.insert(0, repo)
    from benchmarks.bench_matrix import main as bench_main

    return bench_main(list(args.rest))


def cmd_warmup(args: argparse.Namespace) -> int:
    """``pvs warmup``: compile the kernels into the numba cache and print seconds per group."""
    from visibility.warmup import warm_up

    t0 = time.perf_counter()
    for group, seconds in warm_up(args.processes).items():
        print(f"{group:<40} {seconds:6.1f} s")
    print(f"{'total (wall)':<40} {time.perf_counter() - t0:6.1f} s")
    return 0


EXECUTOR_HELP = ("where computations run: local (default) or dask://HOST:PORT, a Dask "
                 "scheduler; add ?scenes=load for workers that load the scenes themselves "
                 "(PVS_EXECUTOR)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="pvs", description=__doc__.splitlines()[0])
    ap.add_argument("-v", "--verbose", action="store_true")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("serve", help="run the edge server (uvicorn)")
    # No argparse defaults: a flag the user did not give leaves PVS_* or the Settings default.
    p.add_argument("--host", help="address to listen on (PVS_HOST; default 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (PVS_PORT; default 8000)")
    p.add_argument("--scenes", help="folder of GLB/glTF/OBJ/PLY scenes to serve "
                                    "(PVS_SCENES_DIR; default ../shared/scenes when present)")
    p.add_argument("--core", help="default core (PVS_CORE)")
    p.add_argument("--cell-size", type=float, help="viewcell size in metres (PVS_CELL_SIZE)")
    p.add_argument("--workers", type=int, help="PVS worker threads (PVS_WORKERS)")
    p.add_argument("--cache-dir", help="on-disk PVS cache folder, kept across restarts "
                                       "(PVS_CACHE_DIR; `pvs precompute` fills it)")
    p.add_argument("--cache", help="'disk' (default) or a Redis URL redis://host:port/db that "
                                   "replicas share (PVS_CACHE; PVS_REDIS_* tune it)")
    p.add_argument("--progressive", action=argparse.BooleanOptionalAction, default=None,
                   help="a walker's cell gets a cheap first answer at once, refined in place "
                        "when the core's answer is ready (PVS_PROGRESSIVE; default on)")
    p.add_argument("--tokens-file", help="JSON or TOML file of bearer tokens, each with its "
                                         "scenes and quotas: access control on "
                                         "(PVS_TOKENS_FILE; PVS_TOKENS adds tokens for all)")
    p.add_argument("--cors-origin", action="append", metavar="ORIGIN",
                   help="origin whose pages may use the API and WebSockets from a browser, "
                        "e.g. https://viewer.example.org, or * (repeatable; PVS_CORS_ORIGINS)")
    p.add_argument("--executor", help=EXECUTOR_HELP)
    p.set_defaults(fn=cmd_serve)

    p = sub.add_parser("walk", help="replay a walkthrough with the headless client",
                       epilog=cores_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--server", default="http://127.0.0.1:8000")
    p.add_argument("--quiet", action="store_true")
    _add_token_option(p)
    _add_walk_options(p, "runs/walk")
    p.set_defaults(fn=cmd_walk)

    p = sub.add_parser("query", help="a cell's (or a segment's, a box's) PVS over HTTP",
                       epilog=cores_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--server", default="http://127.0.0.1:8000")
    p.add_argument("--scene", required=True)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--cell", type=int, help="grid cell id")
    where.add_argument("--segment", type=_six_floats, metavar="X0,Y0,Z0,X1,Y1,Z1",
                       help="the PVS of the segment between two points (metres)")
    where.add_argument("--box", type=_six_floats, metavar="X0,Y0,Z0,X1,Y1,Z1",
                       help="the PVS of an axis-aligned box [min, max] (metres)")
    p.add_argument("--core", default=None, help="core name (default: the server's)")
    p.add_argument("--param", action="append", help="core parameter NAME=VALUE (repeatable)")
    p.add_argument("--ids", action="store_true", help="print every id")
    _add_token_option(p)
    p.add_argument("--timeout", type=float, default=600)
    p.set_defaults(fn=cmd_query)

    p = sub.add_parser("cores", help="list the cores, their promises and parameters; with "
                                     "--scene, how well each fits it and what auto picks")
    p.add_argument("--server", help="ask a running server (GET /cores) instead of this install")
    _add_token_option(p)
    p.add_argument("--scene", help="a scene name: every core's fit and the auto choice")
    p.add_argument("--scenes", help="folder of scene files")
    p.add_argument("--cell-size", type=float, help="viewcell size in metres for the fit")
    p.add_argument("--calibrate", action="store_true",
                   help="with --scene: measure every fitting core on a few cells against a "
                        "dense sample, as the server's auto does, and print its pick")
    p.add_argument("--budget", type=float, help="seconds per cell auto may spend, for "
                                                "--calibrate and the pick (default 1, as "
                                                "the server's PVS_AUTO_BUDGET)")
    p.add_argument("--cache-dir", help="with --scene: the server's cache folder, where "
                                       "--calibrate keeps its calibration and the auto pick "
                                       "reads it, as a server on that folder does")
    p.set_defaults(fn=cmd_cores)

    p = sub.add_parser("scenes", help="list scenes, or describe one")
    p.add_argument("name", nargs="?")
    p.add_argument("--server", help="ask a running server instead of loading locally")
    _add_token_option(p)
    p.add_argument("--scenes", help="folder of scene files")
    p.set_defaults(fn=cmd_scenes)

    p = sub.add_parser("demo", help="server + headless client over a walkthrough, end to end")
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--triangles", type=int,
                   help="size of the generated scene the server builds (default: its default "
                        "size); serves only that scene")
    p.add_argument("--near-far", action="store_true",
                   help="the server streams near-far (near PVS geometry + a far cubemap per "
                        "cell); the report adds the composed frame's metrics and δ")
    p.add_argument("--r1", type=float, help="near-far inner radius, metres (PVS_NEAR_FAR_R1)")
    p.add_argument("--r2", type=float, help="near-far outer radius, metres (PVS_NEAR_FAR_R2)")
    p.add_argument("--cubemap-resolution", type=int,
                   help="near-far cubemap face size, pixels (PVS_NEAR_FAR_RESOLUTION)")
    p.add_argument("--near-far-block", type=int,
                   help="cells per side of a block sharing one cubemap (PVS_NEAR_FAR_BLOCK; "
                        "default 1: a cubemap per cell)")
    _add_walk_options(p, "runs/demo")
    p.set_defaults(fn=cmd_demo)

    p = sub.add_parser("precompute", help="compute a scene's cell PVS into the on-disk cache "
                                          "(or Redis) a server then starts with",
                       epilog=cores_help(),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", required=True)
    p.add_argument("--cache-dir", help="on-disk PVS cache folder (PVS_CACHE_DIR); start the "
                                       "server with the same one")
    p.add_argument("--cache", help="a Redis URL to fill instead of (or with) the folder "
                                   "(PVS_CACHE)")
    p.add_argument("--cells", help="cell ids and ranges, e.g. 0-99,120 (default: every cell)")
    p.add_argument("--core", help="core name (PVS_CORE; 'auto' as the server picks)")
    p.add_argument("--param", action="append", help="core parameter NAME=VALUE (repeatable)")
    p.add_argument("--scenes", help="folder of scene files (PVS_SCENES_DIR)")
    p.add_argument("--cell-size", type=float, help="viewcell size in metres (PVS_CELL_SIZE)")
    p.add_argument("--workers", type=int, help="computations at once (PVS_WORKERS)")
    p.add_argument("--executor", help=EXECUTOR_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(fn=cmd_precompute, host=None, port=None)

    p = sub.add_parser("warmup", help="compile every core's numba kernels into the cache "
                                      "(NUMBA_CACHE_DIR) once, so first cells do not pay it")
    p.add_argument("--processes", type=int, default=2, help="compiling processes (default 2)")
    p.set_defaults(fn=cmd_warmup)

    # Every argument after "bench" goes to benchmarks.bench_matrix (its own parser and --help).
    p = sub.add_parser("bench", help="error against run time for every core (pvs bench --help)",
                       add_help=False, prefix_chars="\x00")
    p.add_argument("rest", nargs="*")
    p.set_defaults(fn=cmd_bench)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return int(args.fn(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
