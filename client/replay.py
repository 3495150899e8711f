"""Walkthrough replay: the headless client measuring itself against the full scene.

For each pose of a walkthrough the client sends the pose, renders a frame from the triangles it
holds (pyrender, offscreen), renders ground truth from the full scene at the same pose, and
records epsilon, PSNR and SSIM. A frame is *stalled* when, at the moment it is due, the client
has not yet received the whole PVS of the cell the eye is in; the client then waits for it (so
the metrics measure the PVS, and the stall count measures the streaming).

With a triangle ``budget`` the client declares it in its hello (the server then drops held
triangles to make room before it sends new ones) and, as a last resort, evicts by itself before
each frame when the store still holds more (``client.budget``; counted per frame in
``evicted``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from client.budget import enforce_budget
from client.metrics import epsilon_mask, frame_metrics
from client.render import OffscreenRenderer
from client.report import format_summary, save_frame_images, write_report
from client.session import SessionError, SyncSession
from client.walkthrough import Walkthrough, generate_walkthrough, load_walkthrough, save_walkthrough
from visibility.scene import Scene
from visibility.viewcells import ViewcellGrid

log = logging.getLogger(__name__)


@dataclass
class ReplayOptions:
    """What to replay, against which server, and how to measure it."""

    server: str
    scene: str
    #: Cores to replay against, one after the other; None: the server's default core.
    cores: list[str | None] = field(default_factory=lambda: [None])
    params: dict[str, Any] = field(default_factory=dict)
    walkthrough: Path | None = None
    out_dir: Path = Path("runs/walk")
    scenes_dir: Path | None = None
    duration: float = 12.0
    fps: float = 10.0
    width: int = 256
    height: int = 256
    #: Pace frames at their timestamps (as ``pvs walk`` does by default); False: as fast as
    #: possible.
    realtime: bool = True
    seed: int = 0
    quiet: bool = False
    #: Longest wait (seconds) for a cell's PVS before the frame is rendered with what is held.
    wait_timeout: float = 600.0
    #: How many of the worst frames (by epsilon) get side-by-side images.
    worst_frames: int = 3
    #: Most triangles the client holds (None: no limit); declared to the server in the hello.
    budget: int | None = None
    #: Bearer token of a server with access control (never in the report or a repr).
    token: str | None = field(default=None, repr=False)


def local_scene(info: Any, scenes_dir: Path | None) -> Scene:
    """The full scene for ground truth, rebuilt locally from what the server's welcome says.

    Generated scenes are regenerated (deterministic for name, size and seed); file scenes are
    loaded from ``scenes_dir``. The triangle count must match the server's.
    """
    from visibility.generators import DEFAULT_TRIANGLES, make_scene
    from visibility.loaders import SCENE_EXTENSIONS, load_scene

    source = getattr(info, "source", None) or {}
    if info.kind == "generated":
        scene = make_scene(
            source.get("generator", info.name),
            triangles=source.get("triangles", DEFAULT_TRIANGLES.get(info.name)),
            seed=source.get("seed", 0),
        )
    else:
        # The frame metrics need the whole scene here: the server streams only what is seen.
        need = (f"scene {info.name!r} is a file the server serves; the client renders the "
                f"full scene for its ground truth, so it needs a copy: pass --scenes DIR, a "
                f"folder holding {info.name}{{{','.join(SCENE_EXTENSIONS)}}}")
        if scenes_dir is None:
            raise FileNotFoundError(need)
        files = [scenes_dir / f"{info.name}{ext}" for ext in SCENE_EXTENSIONS]
        found = [p for p in files if p.is_file()]
        if not found:
            raise FileNotFoundError(f"{need} (none in {scenes_dir})")
        scene = load_scene(found[0])
    if scene.n_triangles != info.triangles:
        raise ValueError(
            f"local scene {info.name!r} has {scene.n_triangles} triangles, the server's "
            f"{info.triangles}: ground truth would not match"
        )
    return scene


def _walkthrough(opts: ReplayOptions, grid: ViewcellGrid, out: Path) -> Walkthrough:
    if opts.walkthrough is not None:
        return load_walkthrough(opts.walkthrough)
    w = generate_walkthrough(grid, duration=opts.duration, fps=opts.fps, seed=opts.seed)
    save_walkthrough(w, out / "walkthrough.json")
    return w


def replay(opts: ReplayOptions, core: str | None, out: Path) -> dict:
    """Replay the walkthrough against ``core`` (None: the server's default); write the report
    into ``out``; its summary (``meta.core`` names the core the server used)."""
    out.mkdir(parents=True, exist_ok=True)
    session = SyncSession.connect(opts.server, opts.scene, core, opts.params,
                                  budget=opts.budget, token=opts.token)
    try:
        welcome = session.welcome
        core = welcome.core
        scene = local_scene(welcome.scene, opts.scenes_dir)
        grid = ViewcellGrid.for_scene(scene, welcome.grid.cell_size)
        if len(grid) != welcome.grid.cells:
            raise ValueError(f"local grid has {len(grid)} cells, the server's {welcome.grid.cells}")
        walk = _walkthrough(opts, grid, out)
        # The near plane the server's answers assume: a farther one could show holes.
        renderer = OffscreenRenderer(opts.width, opts.height, znear=welcome.near_plane)
        frames: list[dict] = []
        worst: list[tuple[float, int, Any]] = []
        startup = _start_up(session, grid, walk, opts)
        t_start = time.perf_counter()
        bar = tqdm(
            total=len(walk),
            desc=f"{opts.scene}/{core}",
            unit="frame",
            disable=True if opts.quiet else None,
            leave=False,
        )
        for i in range(len(walk)):
            t = float(walk.t[i])
            pos, fwd = walk.positions[i], walk.forwards[i]
            if opts.realtime:
                delay = t - walk.t[0] - (time.perf_counter() - t_start)
                if delay > 0:
                    time.sleep(delay)
            vel = None
            if i + 1 < len(walk):
                dt = walk.t[i + 1] - t
                vel = (walk.positions[i + 1] - pos) / dt if dt > 0 else None
            if i > 0:  # pose 0 went out during start-up
                session.send_pose(i, t, pos, fwd, vel)
            cell = grid.cell_of(pos)
            stalled = False
            waited = 0.0
            if cell is not None and not session.is_complete(cell):
                # Give the stream one frame interval to arrive before calling it a stall.
                w0 = time.perf_counter()
                try:
                    session.wait_cell(cell, timeout=1.0 / opts.fps)
                except TimeoutError:
                    stalled = True
                    try:
                        session.wait_cell(cell, timeout=opts.wait_timeout)
                    except TimeoutError:
                        log.warning("cell %d did not arrive in %.0f s", cell, opts.wait_timeout)
                waited = time.perf_counter() - w0
            evicted = 0
            if cell is not None and cell in session.cells:
                evicted = enforce_budget(session.store, _stream_ids(session.cells[cell]), pos)
            elif session.store.over_budget:
                evicted = enforce_budget(session.store, np.zeros(0, np.int64), pos)
            ids = session.store.ids
            # A dynamic scene is seen at the pose's time, by the client (its keyframes) and by
            # the ground truth alike; a static one at rest.
            scene_t = scene_time(scene, t)
            r0 = time.perf_counter()
            frame = renderer.render_store(session.store, pos, fwd, t=scene_t)
            render_s = time.perf_counter() - r0
            gt = renderer.render_scene(scene, pos, fwd, t=scene_t)
            m = frame_metrics(frame, gt)
            rec = {
                "frame": i,
                "t": t,
                "cell": -1 if cell is None else int(cell),
                "epsilon": m["epsilon"],
                "psnr": m["psnr"],
                "ssim": m["ssim"],
                "stalled": stalled,
                "wait_seconds": waited,
                "triangles_held": int(len(ids)),
                "bytes_received": int(session.bytes_received),
                "render_seconds": render_s,
                "evicted": int(evicted),
            }
            stream = session.cells.get(cell) if cell is not None else None
            if stream is not None and stream.begin is not None:
                rec["pvs_triangles"] = int(stream.begin.triangles)  # the cell's, per the server
            # Which answer the frame's cell held (a first answer not yet refined, or not).
            rec["answer"] = (stream.answer if stream is not None else None) or "none"
            cube = session.cubemap_for(cell) if cell is not None else None
            if cube is not None:
                # Near-far stream: the geometry-only frame above lacks the far field; the
                # composed frame (morph + cubemap) is what the device shows.
                frame, extra = composed_metrics_at(renderer, session.store, scene_t, cube, pos,
                                                   fwd, gt)
                rec.update(extra)
                # |U - O| horizontally (metres): the seam and the morph's bend both grow with it.
                off = np.asarray(pos, float) - np.asarray(cube.center, float)
                rec["eye_offset"] = float(np.hypot(off[0], off[2]))
                m = {k: extra[f"{k}_composed"] for k in ("epsilon", "psnr", "ssim")}
            frames.append(rec)
            worst.append((m["epsilon"], i, (frame, gt)))
            worst.sort(key=lambda w: -w[0])
            del worst[opts.worst_frames :]
            if not opts.quiet:
                bar.write(
                    f"frame {i:4d} t={t:6.2f}s cell={rec['cell']:5d} eps={m['epsilon']:7.3f}% "
                    f"psnr={m['psnr']:6.2f}dB ssim={m['ssim']:.4f} tris={len(ids):7d}"
                    + (" STALL" if stalled else "")
                )
            bar.update(1)
        bar.close()
        for _eps, i, (frame, gt) in worst:
            save_frame_images(out, f"worst_{i:04d}", frame.color, gt.color, frame.depth, gt.depth)
        renderer.close()
        meta = {
            "server": opts.server,
            "scene": opts.scene,
            "core": core,
            "params": welcome.params,
            "scene_triangles": scene.n_triangles,
            "cells": len(grid),
            "walkthrough": str(opts.walkthrough or out / "walkthrough.json"),
            "frames": len(frames),
            "startup_seconds": startup,
            "realtime": bool(opts.realtime),
            "budget": opts.budget,
            "server_drops": int(session.dropped),
            "client_evictions": int(sum(f["evicted"] for f in frames)),
            "image": [opts.width, opts.height],
            "server_errors": [e.message for e in session.errors],
            "epsilon_definition": epsilon_mask.__doc__.strip().splitlines()[0]
            if epsilon_mask.__doc__
            else "",
        }
        summary = write_report(out, frames, meta)
        summary["frames_rendered"] = len(frames)
        return summary
    finally:
        try:
            session.close()
        except SessionError:
            pass


def _stream_ids(stream: Any) -> np.ndarray:
    """The ids a cell's latest stream brought (its PVS as far as the client knows it)."""
    return np.concatenate(stream.ids) if stream.ids else np.zeros(0, np.int64)


def _start_up(session: SyncSession, grid: ViewcellGrid, walk: Walkthrough,
              opts: ReplayOptions) -> float:
    """Send the first pose and wait for its cell, as a device waits behind a loading screen
    before the user starts walking; seconds waited. Stalls count from the first frame on."""
    if not len(walk):
        return 0.0
    pos, fwd = walk.positions[0], walk.forwards[0]
    vel = None
    if len(walk) > 1 and walk.t[1] > walk.t[0]:
        vel = (walk.positions[1] - pos) / (walk.t[1] - walk.t[0])
    t0 = time.perf_counter()
    session.send_pose(0, float(walk.t[0]), pos, fwd, vel)
    cell = grid.cell_of(pos)
    if cell is not None:
        try:
            session.wait_cell(cell, timeout=opts.wait_timeout)
        except TimeoutError:
            log.warning("first cell %d did not arrive in %.0f s", cell, opts.wait_timeout)
    return time.perf_counter() - t0


def scene_time(scene: Scene, t: float) -> float | None:
    """The scene time (seconds) a frame posed at walkthrough time ``t`` shows: ``t`` itself for a
    dynamic scene (keyframes clamp it to their range), None (at rest) for a static one. Client
    frames and ground truth both use it."""
    return float(t) if scene.is_dynamic else None


def composed_metrics_at(renderer, store, t, cube, eye, forward, gt) -> tuple[Any, dict]:
    """``composed_metrics`` of what ``store`` holds at scene time ``t`` (seconds; None: at
    rest): moving triangles and spheres wholly beyond r2 are passed as far dynamic objects
    (displaced by Q = U + (P - O) and depth-composited against the cubemap range), the rest as
    near geometry (``client.compose.split_far_dynamic``)."""
    from client.compose import split_far_dynamic

    (nt, nc), (ft, fc) = split_far_dynamic(store, t, cube.center, cube.r2)
    return composed_metrics(renderer, nt, nc, cube, eye, forward, gt, far_tris=ft, far_cols=fc)


def composed_metrics(renderer, tris, cols, cube, eye, forward, gt, far_tris=None,
                     far_cols=None) -> tuple[Any, dict]:
    """Compose the near-far frame (morph + cubemap) and the conventional one (no morph); their
    metrics against ground truth and their discontinuity delta. ``far_tris``/``far_cols``: far
    dynamic objects at the frame's time (``compose_frame``'s ``far_dynamic_tris``). Returns
    (composed frame as a ``Frame``, per-frame fields: ``{epsilon,psnr,ssim,delta}_composed``,
    their ``_conventional`` twins, and ``compose_seconds``, the morphed composition's time)."""
    from client.compose import compose_frame
    from client.discontinuity import discontinuity
    from client.render import Frame

    out: dict[str, float] = {}
    composed = None
    for morph, suffix in ((True, "composed"), (False, "conventional")):
        c0 = time.perf_counter()
        c = compose_frame(renderer, tris, cols, cube, eye, forward, cube.r1, cube.r2,
                          far_dynamic_tris=far_tris, far_dynamic_colors=far_cols, morph=morph)
        if morph:
            # What the device spends on its frame: morph, render, cubemap lookup, compositing.
            out["compose_seconds"] = time.perf_counter() - c0
        f = Frame(c.color, c.depth)
        mm = frame_metrics(f, gt)
        for k in ("epsilon", "psnr", "ssim"):
            out[f"{k}_{suffix}"] = mm[k]
        d = discontinuity(c.points, eye, forward, renderer.tan_x, renderer.tan_y)
        out[f"delta_{suffix}"] = d.mean_abs
        if morph:
            composed = f
    return composed, out


def replay_cores(opts: ReplayOptions) -> list[dict]:
    """Replay the same walkthrough against each core in ``opts.cores``; print each summary and,
    for several cores, a side-by-side table."""
    summaries = []
    several = len(opts.cores) > 1
    shared_walk = opts.walkthrough
    for core in opts.cores:
        out = opts.out_dir / (core or "default") if several else opts.out_dir
        run_opts = ReplayOptions(**{**opts.__dict__, "walkthrough": shared_walk})
        s = replay(run_opts, core, out)
        core = s["meta"]["core"]
        if shared_walk is None:
            shared_walk = out / "walkthrough.json"  # the next cores replay the same walk
        print(f"\n== {opts.scene} / {core}  (report: {out})")
        print(format_summary(s, per_frame=False))
        summaries.append(s)
    if several:
        print(side_by_side(summaries))
    return summaries


#: Side-by-side columns: (header, summary key, format); near-far ones only when present.
_COLUMNS = (
    ("eps %", "epsilon", "8.3f"),
    ("PSNR dB", "psnr", "8.2f"),
    ("SSIM", "ssim", "8.4f"),
    ("eps_c %", "epsilon_composed", "8.3f"),
    ("PSNR_c", "psnr_composed", "8.2f"),
    ("SSIM_c", "ssim_composed", "8.4f"),
    ("δ morph", "delta_composed", "8.4f"),
    ("δ conv", "delta_conventional", "8.4f"),
)


def side_by_side(summaries: list[dict]) -> str:
    """A table with one row per core and its means in columns: ε, PSNR, SSIM of the
    geometry-only frame; for near-far runs also of the composed frame (``_c``) and δ with and
    without the morph; then stalls and the most triangles held."""
    cols = [c for c in _COLUMNS if any(s.get(c[1]) is not None for s in summaries)]
    head = f"{'core':16s} " + " ".join(f"{h:>8s}" for h, _k, _f in cols)
    lines = [head + f" {'stalls':>7s} {'tris':>9s}"]
    for s in summaries:
        held = int(max((f.get("triangles_held", 0) for f in s.get("frames", [])), default=0))
        vals = []
        for _h, key, fmt in cols:
            v = s.get(key)
            vals.append(f"{'-':>8s}" if v is None else format(float(v), fmt))
        lines.append(f"{s['meta']['core']:16s} " + " ".join(vals)
                     + f" {int(s['stalls']):7d} {held:9d}")
    return "\n".join(lines)
