"""Stopping a computation: checkpoints in the cores against a worker process killed and replaced.

Kernels cannot be interrupted, so a computation that must stop (its deadline passed, the service
shuts down, nobody wants the answer any more) either runs where it can be killed, a worker
process that the pool replaces, or in chunks with a check between them (``visibility.cancel``:
cores call ``checkpoint()`` between views, segments and groups of tiles, and long kernels poll
the token's stop flag inside). This benchmark
measures both on real cores and scenes and says which costs less.

Checkpoints (``--parts checkpoints``), per case (scene, core, parameters):

- overhead: the same computation with ``token=None`` and with a live ``CancelToken`` that never
  fires (a deadline an hour away, as the server sets one), interleaved, ``--repeats`` each,
  medians; next to it the estimate checkpoints x cost of one check (a micro-benchmark), since
  the difference of two timings on a shared machine is mostly noise;
- the checkpoint timeline of one uncancelled run (a token that stamps every check): the gaps
  between checks bound the stop latency (its worst case is the largest gap);
- stop latency: the computation runs in a thread; after t seconds (fractions of its run time,
  or fixed times for the long "hostile" requests that never finish in time) the main thread
  calls ``cancel()``; latency = the thread's ``ComputationCancelled`` minus the ``cancel()``.

Kill and replace (``--parts process``), per core, with ``multiprocessing``'s ``spawn`` context
and its ``forkserver`` context with numpy, numba and the cores preloaded (never ``fork``: the
parent runs numba's thread pool, and forking a threaded process is unsafe):

- per job: the pickled scene's size and the time to pickle it and to ship it to a worker
  (a process per job, or a job that brings its scene), and the round trip of a job to a
  persistent worker that holds the scene, less its compute time;
- stop latency: ``Process.kill()`` of a worker busy computing, until ``join()`` returns;
- replacement: a fresh worker, from ``Process.start()`` until it can compute again: interpreter
  start, imports (numpy, numba, the cores), the scene received, a warm-up computation (numba
  loads its cached kernels, the core builds its per-scene caches); with an empty numba cache
  once per core (the first start after a deploy); the worker's memory (RSS, PSS).

Writes ``OUT/NAME.md`` (command and machine on top, a table per option, the conclusion),
``OUT/NAME.json`` (every number) and ``OUT/NAME.png``. Usage (6 to 8 minutes on 2 cores)::

    python -m benchmarks.bench_cancel
    python -m benchmarks.bench_cancel --parts process      # one part, merged into the report
    python -m benchmarks.bench_cancel --quick --out /tmp    # smoke: a 5k scene, seconds

Only the standard library is imported at module level: a ``spawn`` worker re-imports the main
module (this one, under ``-m``) before it starts, and its import phase should be the worker's
own (``benchmarks.cancel_worker``), not this file's.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import pickle
import platform
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
#: Deadline of the live token of the overhead runs: far enough never to fire.
NEVER = 3600.0
#: Longest wait for a cancelled thread or a worker message before the run is called stuck.
STUCK = 600.0
#: Small parameters of a worker's warm-up computation, per core: enough to load the kernels.
WARM = {"sampling": {"samples": 1, "resolution": 16},
        "from_segment": {"resolution": 16, "eye_levels": 1},
        "cos": {"resolution": 16}}
#: The flood's request (``bench_load --hostile``): a job that runs until it is stopped.
HOSTILE_SAMPLING = {"resolution": 2048, "samples": 100_000}
#: The long job each core's worker is killed in the middle of.
KILL_JOBS = {"sampling": HOSTILE_SAMPLING, "from_segment": {"resolution": 1024},
             "cos": {"resolution": 1024}}


# --------------------------------------------------------------------------- cases
@dataclass(frozen=True)
class Case:
    """One computation to stop: a scene (label), a core, its parameters, and when to cancel.

    ``kind`` "request": a computation that finishes (overhead, timeline and cancels at
    ``cancel_at`` fractions of its run time); "hostile": one that would run for minutes
    (cancels at ``cancel_at`` seconds only).
    """

    scene: str
    core: str
    params: dict[str, Any]
    kind: str
    cancel_at: tuple[float, ...]

    @property
    def label(self) -> str:
        return f"{self.scene} {self.core} {json.dumps(self.params)}"


def presets(quick: bool) -> dict[str, Any]:
    """The scenes, cases and repeats of a full or a ``--quick`` run."""
    if quick:
        scenes = {"village 5k": ("village", 5_000)}
        fr = (0.5,)
        cases = [Case("village 5k", "sampling", {"samples": 16, "resolution": 64}, "request", fr),
                 Case("village 5k", "from_segment", {"resolution": 64}, "request", fr),
                 Case("village 5k", "cos", {"resolution": 32}, "request", fr),
                 Case("village 5k", "sampling", {"resolution": 512, "samples": 100_000},
                      "hostile", (0.3,))]
        return {"scenes": scenes, "cases": cases, "repeats": 1, "process_cores": ["sampling"],
                "process_methods": ["spawn"], "process_repeats": 1, "cold_jit": False,
                "process_scene": "village 5k",
                "job": {"sampling": {"samples": 16, "resolution": 64}}}
    scenes = {"village 20k": ("village", 20_000), "city 100k": ("city", 100_000),
              "denhaag": ("file", "denhaag.glb")}
    fr = (0.2, 0.4, 0.6, 0.8)
    cases = []
    for s in scenes:
        cases += [Case(s, "sampling", {"samples": 128}, "request", fr),
                  Case(s, "from_segment", {}, "request", fr),
                  Case(s, "cos", {}, "request", fr)]
    cases += [Case("village 20k", "sampling", dict(HOSTILE_SAMPLING), "hostile", (0.5, 1.0, 2.0)),
              Case("village 20k", "from_segment", {"resolution": 1024}, "hostile",
                   (0.5, 1.0, 2.0)),
              Case("village 20k", "cos", {"resolution": 512}, "hostile", (1.0, 3.0)),
              # Its first view takes seconds, a later one far longer: a cancel in each.
              Case("village 20k", "cos", {"resolution": 1024}, "hostile", (2.0, 6.0))]
    return {"scenes": scenes, "cases": cases, "repeats": 3,
            "process_cores": ["sampling", "from_segment", "cos"],
            "process_methods": ["spawn", "forkserver"], "process_repeats": 3, "cold_jit": True,
            "process_scene": "village 20k",
            "job": {"sampling": {"samples": 128}, "from_segment": {}, "cos": {}}}


def load(spec: tuple[str, Any]) -> Any:
    """The scene of a preset entry: ("village", 20000) generated, ("file", name) from
    ``../shared/scenes``."""
    kind, arg = spec
    if kind == "file":
        from benchmarks.bench_matrix import SHARED_SCENES
        from visibility.loaders import load_scene

        return load_scene(SHARED_SCENES / arg)
    from visibility.generators import make_scene

    return make_scene(kind, triangles=arg, seed=0)


def middle_cell(scene: Any) -> Any:
    """The middle cell of the scene's viewcell grid (the scene's cell size, else 4 m)."""
    from visibility.viewcells import ViewcellGrid

    grid = ViewcellGrid.for_scene(scene, scene.meta.get("cell_size") or 4.0)
    return grid.cell(len(grid) // 2)


# --------------------------------------------------------------------------- checkpoints
def _token_class() -> type:
    from visibility.cancel import CancelToken

    class StampingToken(CancelToken):
        """A ``CancelToken`` that stamps every check (``time.monotonic()``)."""

        def __init__(self, deadline: float | None = None) -> None:
            super().__init__(deadline)
            self.stamps: list[float] = []

        def check(self) -> None:
            self.stamps.append(time.monotonic())
            super().check()

    return StampingToken


def check_cost(n: int = 200_000) -> dict[str, float]:
    """Nanoseconds per ``checkpoint()`` with a live token (deadline set) and with none."""
    from visibility.cancel import CancelToken, checkpoint, running_under

    out = {}
    for label, tok in (("live_ns", CancelToken.after(NEVER)), ("none_ns", None)):
        best = float("inf")
        for _ in range(3):
            with running_under(tok):
                t0 = time.perf_counter()
                for _ in range(n):
                    checkpoint()
                best = min(best, time.perf_counter() - t0)
        out[label] = best / n * 1e9
    return out


def gap_stats(begin: float, stamps: list[float], end: float) -> dict[str, Any]:
    """Gaps between consecutive checks of one run (its start and end count as checks): what
    bounds the stop latency. ``expected_s`` is the mean latency of a cancel at a uniformly
    random instant of the run (sum of squared gaps over twice the run time)."""
    ts = [begin, *stamps, end]
    gaps = [b - a for a, b in zip(ts, ts[1:], strict=False)]
    i = max(range(len(gaps)), key=gaps.__getitem__)
    total = sum(gaps)
    return {"checks": len(stamps), "gap_median_s": statistics.median(gaps),
            "gap_max_s": gaps[i], "gap_max_at_s": ts[i] - begin,
            "expected_s": sum(g * g for g in gaps) / (2 * total) if total > 0 else 0.0,
            "run_s": end - begin}


def timed(core: Any, scene: Any, cell: Any, params: Any, token: Any) -> float:
    t0 = time.perf_counter()
    core.compute(scene, cell, params, token=token)
    return time.perf_counter() - t0


def cancel_once(core: Any, scene: Any, cell: Any, params: Any, after: float) -> dict[str, Any]:
    """Run the computation in a thread and cancel it ``after`` seconds in; what happened.

    ``outcome``: "cancelled" (stopped at a checkpoint), "completed after cancel" (no checkpoint
    came after the cancel: the computation ran to its end), "finished first" (it ended before
    the cancel) or "stuck" (still running ``STUCK`` s after the cancel). ``latency_s`` is from
    the ``cancel()`` call to the thread's end; ``late_s`` how much later than asked the main
    thread got to call it (a kernel holding the GIL would show here)."""
    from visibility.cancel import ComputationCancelled

    tok = _token_class()()
    rec: dict[str, Any] = {}
    started = threading.Event()

    def run() -> None:
        rec["begin"] = time.monotonic()
        started.set()
        try:
            core.compute(scene, cell, params, token=tok)
            rec["outcome"] = "finished"
        except ComputationCancelled:
            rec["outcome"] = "cancelled"
        rec["end"] = time.monotonic()

    th = threading.Thread(target=run, name="bench-cancel", daemon=True)
    th.start()
    started.wait()
    target = rec["begin"] + after
    th.join(timeout=max(0.0, target - time.monotonic()))
    if not th.is_alive():
        return {"after_s": after, "outcome": "finished first", "latency_s": None,
                "late_s": None, "run_s": rec["end"] - rec["begin"]}
    t_cancel = time.monotonic()
    tok.cancel("bench_cancel")
    th.join(timeout=STUCK)
    if th.is_alive():
        return {"after_s": after, "outcome": "stuck", "latency_s": None,
                "late_s": t_cancel - target, "run_s": None}
    outcome = "cancelled" if rec["outcome"] == "cancelled" else "completed after cancel"
    out = {"after_s": after, "outcome": outcome, "latency_s": rec["end"] - t_cancel,
           "late_s": t_cancel - target, "run_s": rec["end"] - rec["begin"]}
    # The gaps seen up to the stop (a hostile run has no uncancelled timeline).
    out.update({f"seen_{k}": v for k, v in gap_stats(rec["begin"], tok.stamps,
                                                     rec["end"]).items()})
    return out


def part_checkpoints(cfg: dict[str, Any], scenes: dict[str, Any], say: Callable[[str], None],
                     bar: Any) -> dict[str, Any]:
    """Overhead, timeline and stop latency of every case; the cost of one check."""
    from visibility.cancel import CancelToken
    from visibility.cores.base import get_core

    cost = check_cost()
    say(f"checkpoint(): {cost['live_ns']:.0f} ns with a live token, {cost['none_ns']:.0f} ns "
        "without")
    rows = []
    for case in cfg["cases"]:
        scene = scenes[case.scene]
        cell = middle_cell(scene)
        core = get_core(case.core)
        params = core.make_params(**case.params)
        row: dict[str, Any] = {**asdict(case), "label": case.label,
                               "triangles": int(scene.n_triangles)}
        if case.kind == "request":
            timed(core, scene, cell, params, None)  # warm-up: kernels loaded, caches built
            tok = _token_class()()
            t0 = time.monotonic()
            core.compute(scene, cell, params, token=tok)
            row["timeline"] = gap_stats(t0, tok.stamps, time.monotonic())
            none, live = [], []
            for r in range(cfg["repeats"]):
                # Interleaved, alternating which goes first, so a drift in the machine's load
                # falls on both.
                order = ("none", "live") if r % 2 == 0 else ("live", "none")
                for mode in order:
                    tk = None if mode == "none" else CancelToken.after(NEVER)
                    (none if mode == "none" else live).append(
                        timed(core, scene, cell, params, tk))
            row["none_s"], row["live_s"] = none, live
            med_none, med_live = statistics.median(none), statistics.median(live)
            row["overhead_measured"] = (med_live - med_none) / med_none
            row["overhead_estimated"] = (row["timeline"]["checks"] * cost["live_ns"] * 1e-9
                                         / med_none)
            cancel_after = [f * med_none for f in case.cancel_at]
        else:
            cancel_after = list(case.cancel_at)
        row["cancels"] = [cancel_once(core, scene, cell, params, a) for a in cancel_after]
        lat = [c["latency_s"] for c in row["cancels"] if c["latency_s"] is not None]
        row["latency_median_s"] = statistics.median(lat) if lat else None
        row["latency_max_s"] = max(lat) if lat else None
        say(_checkpoint_line(row))
        rows.append(row)
        bar.update(1)
    return {"check_cost": cost, "rows": rows}


def _checkpoint_line(r: dict[str, Any]) -> str:
    bits = [f"{r['label']:58s}"]
    if "timeline" in r:
        tl = r["timeline"]
        bits.append(f"run {statistics.median(r['none_s']):6.2f} s  overhead "
                    f"{100 * r['overhead_measured']:+5.1f} % measured, "
                    f"{100 * r['overhead_estimated']:.4f} % est.  {tl['checks']} checks, "
                    f"max gap {1e3 * tl['gap_max_s']:.0f} ms")
    lat = ", ".join(f"{c['outcome']} {1e3 * c['latency_s']:.0f} ms" if c["latency_s"]
                    is not None else c["outcome"] for c in r["cancels"])
    return " ".join(bits) + f"  stops: {lat}"


# --------------------------------------------------------------------------- process
def cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` so far (``/proc/PID/stat``)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def proc_memory(pid: int) -> dict[str, float | None]:
    """RSS and PSS of process ``pid`` in MiB (None when unreadable); PSS shares pages that a
    forkserver child holds in common with its siblings."""
    out: dict[str, float | None] = {"rss_mib": None, "pss_mib": None}
    for path, key, name in ((f"/proc/{pid}/status", "VmRSS:", "rss_mib"),
                            (f"/proc/{pid}/smaps_rollup", "Pss:", "pss_mib")):
        try:
            for line in Path(path).read_text().splitlines():
                if line.startswith(key):
                    out[name] = int(line.split()[1]) / 1024
                    break
        except (OSError, ValueError):
            pass
    return out


class Worker:
    """A ``cancel_worker.serve`` process started in context ``ctx``, timed until ready."""

    def __init__(self, ctx: Any, core: str, box: list[list[float]], blob: bytes,
                 env: dict[str, str] | None = None) -> None:
        from benchmarks.cancel_worker import serve

        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=serve, args=(child, core, box, WARM[core]), daemon=True)
        saved = dict(os.environ)
        if env:
            os.environ.update(env)  # a spawned child takes the environment at start()
        try:
            self.t_start = time.monotonic()
            self.proc.start()
        finally:
            if env:
                os.environ.clear()
                os.environ.update(saved)
        child.close()
        kind, marks = self._recv("imported")
        self.conn.send_bytes(blob)
        kind, marks = self._recv("ready")
        self.t_ready = time.monotonic()
        self.marks = dict(marks)
        # What the start cost the machine, not just the wait: the CPU the worker used.
        self.memory = {**proc_memory(self.proc.pid), "cpu_s": cpu_seconds(self.proc.pid)}

    def _recv(self, want: str) -> tuple:
        if not self.conn.poll(STUCK):
            raise RuntimeError(f"worker sent no {want!r} in {STUCK:g} s")
        msg = self.conn.recv()
        if msg[0] == "error":
            raise RuntimeError(f"worker failed: {msg[1]}")
        if msg[0] != want:
            raise RuntimeError(f"worker sent {msg[0]!r}, expected {want!r}")
        return msg

    def phases(self) -> dict[str, float]:
        """Seconds per phase of the start, in order; they add up to ``ready_s``."""
        m, out, prev = self.marks, {}, self.t_start
        for key, name in (("boot", "interpreter"), ("numpy", "numpy"), ("numba", "numba"),
                          ("cores", "cores"), ("scene", "scene"), ("warm", "warm-up")):
            out[name] = m[key] - prev
            prev = m[key]
        out["ready_s"] = self.t_ready - self.t_start
        return out

    def job(self, box: list[list[float]], params: dict[str, Any]) -> dict[str, float]:
        """One job's round trip (sent to answer received) and the worker's compute seconds."""
        t0 = time.monotonic()
        self.conn.send(("job", box, params))
        self._recv("started")
        _, ids, seconds = self._recv("done")
        rt = time.monotonic() - t0
        return {"round_trip_s": rt, "compute_s": seconds, "overhead_s": rt - seconds,
                "ids_bytes": len(ids)}

    def ship(self, blob: bytes) -> dict[str, float]:
        """A scene shipped as a job would bring it: send to unpickled-and-answered."""
        t0 = time.monotonic()
        self.conn.send(("ship", None, None))
        self.conn.send_bytes(blob)
        _, loads_s, n = self._recv("shipped")
        return {"round_trip_s": time.monotonic() - t0, "loads_s": loads_s, "bytes": n}

    def kill_busy(self, box: list[list[float]], params: dict[str, Any],
                  busy_for: float) -> float:
        """Start a long job, let it compute ``busy_for`` s, kill the worker: seconds from
        ``kill()`` until ``join()`` returned."""
        self.conn.send(("job", box, params))
        self._recv("started")
        time.sleep(busy_for)
        t0 = time.monotonic()
        self.proc.kill()
        self.proc.join()
        dt = time.monotonic() - t0
        self.conn.close()
        return dt

    def stop(self) -> None:
        try:
            self.conn.send(("stop", None, None))
        except OSError:
            pass
        self.proc.join(10)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()
        self.conn.close()


def _arrays_nbytes(scene: Any) -> int:
    """Bytes of the scene's arrays pickled alone (what a worker needs, without the rest)."""
    keep = {k: v for k, v in vars(scene).items() if hasattr(v, "nbytes")}
    return len(pickle.dumps(keep, protocol=5))


def part_process(cfg: dict[str, Any], scenes: dict[str, Any], say: Callable[[str], None],
                 bar: Any) -> dict[str, Any]:
    """Shipping, kill and replacement costs of a worker process per core and start method."""
    home = scenes[cfg["process_scene"]]
    box = middle_cell(home).box.tolist()
    blobs = {label: pickle.dumps(sc, protocol=5) for label, sc in scenes.items()}
    ship_rows = []
    for label, sc in scenes.items():
        dumps = []
        for _ in range(5):
            t0 = time.perf_counter()
            pickle.dumps(sc, protocol=5)
            dumps.append(time.perf_counter() - t0)
        ship_rows.append({"scene": label, "triangles": int(sc.n_triangles),
                          "pickle_bytes": len(blobs[label]),
                          "arrays_bytes": _arrays_nbytes(sc),
                          "dumps_s": statistics.median(dumps)})
    rows: list[dict[str, Any]] = []
    blob = blobs[cfg["process_scene"]]
    for method in cfg["process_methods"]:
        ctx = multiprocessing.get_context(method)
        prime_s = None
        if method == "forkserver":
            # Preloaded once in the fork server (its start is paid once per server, not per
            # kill); its children fork with these modules already imported.
            ctx.set_forkserver_preload(["numpy", "numba", "visibility.cores.base",
                                        "visibility.cores.sampling",
                                        "visibility.cores.from_segment",
                                        "visibility.cores.cos", "benchmarks.cancel_worker"])
            t0 = time.monotonic()
            p = ctx.Process(target=time.sleep, args=(0,))
            p.start()
            p.join()
            prime_s = time.monotonic() - t0
            say(f"forkserver started with preloads in {prime_s:.2f} s (once per server)")
        for core in cfg["process_cores"]:
            starts, kills, jobs = [], [], []
            w = Worker(ctx, core, box, blob)
            for r in range(cfg["process_repeats"]):
                starts.append({**w.phases(), **w.memory})
                first = w.job(box, cfg["job"][core])
                second = w.job(box, cfg["job"][core])
                jobs.append({"first": first, "second": second})
                if method == cfg["process_methods"][0] and core == cfg["process_cores"][0] \
                        and r == 0:
                    for srow in ship_rows:
                        trips = [w.ship(blobs[srow["scene"]]) for _ in range(3)]
                        srow["ship_s"] = statistics.median(t["round_trip_s"] for t in trips)
                        srow["loads_s"] = statistics.median(t["loads_s"] for t in trips)
                kills.append(w.kill_busy(box, KILL_JOBS[core], 0.3))
                # The replacement: what the next request waits for after every kill.
                w = Worker(ctx, core, box, blob)
            w.stop()
            row = {"method": method, "core": core, "starts": starts, "jobs": jobs,
                   "kill_s": kills, "forkserver_start_s": prime_s,
                   "ready_median_s": statistics.median(s["ready_s"] for s in starts),
                   "kill_median_s": statistics.median(kills),
                   "job_overhead_median_s": statistics.median(
                       j[k]["overhead_s"] for j in jobs for k in ("first", "second")),
                   "first_job_extra_s": statistics.median(
                       j["first"]["compute_s"] - j["second"]["compute_s"] for j in jobs)}
            say(f"{method:10s} {core:12s} kill {1e3 * row['kill_median_s']:.1f} ms, start -> "
                f"ready {row['ready_median_s']:.2f} s ({_phase_text(starts[0])}), "
                f"RSS {starts[0]['rss_mib']:.0f} MiB, job overhead "
                f"{1e3 * row['job_overhead_median_s']:.1f} ms")
            rows.append(row)
            bar.update(1)
    cold = []
    if cfg["cold_jit"]:
        ctx = multiprocessing.get_context("spawn")
        for core in cfg["process_cores"]:
            with tempfile.TemporaryDirectory(prefix="numba-cold-") as tmp:
                w = Worker(ctx, core, box, blob, env={"NUMBA_CACHE_DIR": tmp})
                j = w.job(box, cfg["job"][core])
                w.stop()
            cold.append({"method": "spawn", "core": core, **w.phases(), **w.memory,
                         "first_job_compute_s": j["compute_s"]})
            say(f"empty numba cache, spawn {core:12s} start -> ready {w.phases()['ready_s']:.1f}"
                f" s ({_phase_text(w.phases())})")
            bar.update(1)
    return {"scene": cfg["process_scene"], "ship": ship_rows, "rows": rows, "cold": cold}


def _phase_text(p: dict[str, float]) -> str:
    return ", ".join(f"{k} {p[k]:.2f}" for k in PHASES)


PHASES = ("interpreter", "numpy", "numba", "cores", "scene", "warm-up")


# --------------------------------------------------------------------------- report
def machine() -> dict[str, Any]:
    """CPU model, logical cores, memory, OS, versions, load averages (1, 5, 15 min)."""
    import numba
    import numpy as np

    model = platform.processor() or "unknown CPU"
    mem = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
        mem = next(int(x.split()[1]) / 2**20 for x in Path("/proc/meminfo").read_text()
                   .splitlines() if x.startswith("MemTotal:"))
    except (OSError, StopIteration, ValueError):
        pass
    return {"cpu": model, "cores": os.cpu_count(), "mem_gib": mem,
            "os": platform.platform(), "python": platform.python_version(),
            "numpy": np.__version__, "numba": numba.__version__,
            "threads": numba.config.NUMBA_NUM_THREADS, "load": list(os.getloadavg())}


def _ms(x: float | None, digits: int = 0) -> str:
    return "–" if x is None else f"{1e3 * x:.{digits}f}"


def _cpu(starts: list[dict[str, Any]]) -> str:
    cpu = [s["cpu_s"] for s in starts if s.get("cpu_s") is not None]
    return f"{statistics.median(cpu):.2f}" if cpu else "–"


def _med_range(xs: list[float]) -> str:
    return f"{statistics.median(xs):.2f} ({min(xs):.2f}–{max(xs):.2f})"


def per_core(res: dict[str, Any]) -> list[dict[str, Any]]:
    """Per core, the checkpoints' stops next to a kill and replacement of its worker: what
    the conclusion compares."""
    ck, pr = res["checkpoints"], res["process"]
    out = []
    for core in dict.fromkeys(r["core"] for r in pr["rows"]):
        rows = [r for r in ck["rows"] if r["core"] == core]
        req = [c["latency_s"] for r in rows if r["kind"] == "request" for c in r["cancels"]
               if c["latency_s"] is not None]
        hos = [c["latency_s"] for r in rows if r["kind"] == "hostile" for c in r["cancels"]
               if c["latency_s"] is not None]
        gaps = [r["timeline"]["gap_max_s"] for r in rows if "timeline" in r]
        gaps += [c["seen_gap_max_s"] for r in rows for c in r["cancels"]
                 if "seen_gap_max_s" in c]
        kill = {}
        for r in pr["rows"]:
            if r["core"] == core:
                cpu = [s["cpu_s"] for s in r["starts"] if s.get("cpu_s") is not None]
                kill[r["method"]] = {"seconds": r["kill_median_s"] + r["ready_median_s"],
                                     "cpu_s": statistics.median(cpu) if cpu else None}
        out.append({"core": core, "stop_median_s": statistics.median(req) if req else None,
                    "stop_max_s": max(req) if req else None,
                    "hostile_stop_max_s": max(hos) if hos else None,
                    "gap_max_s": max(gaps) if gaps else None, "kill": kill})
    return out


def conclusion(res: dict[str, Any]) -> list[str]:
    """The conclusion: paragraphs and a per-core table, every figure taken from ``res`` and
    every comparison made on them (nothing here is written before the numbers are known)."""
    ck, pr = res.get("checkpoints"), res.get("process")
    if not ck or not pr or not pr["rows"]:
        return ["Only one part was run: no comparison (run both parts for the conclusion)."]
    req = [r for r in ck["rows"] if r["kind"] == "request"]
    lat_req = [c["latency_s"] for r in req for c in r["cancels"] if c["latency_s"] is not None]
    lat_all = [(c["latency_s"], r) for r in ck["rows"] for c in r["cancels"]
               if c["latency_s"] is not None]
    # (gap, row, seconds into the run, run seconds or None for a run stopped by its cancel)
    gaps = [(r["timeline"]["gap_max_s"], r, r["timeline"]["gap_max_at_s"],
             r["timeline"]["run_s"]) for r in req]
    gaps += [(c["seen_gap_max_s"], r, c["seen_gap_max_at_s"], None) for r in ck["rows"]
             for c in r["cancels"] if "seen_gap_max_s" in c]
    by_method = {}
    for m in dict.fromkeys(r["method"] for r in pr["rows"]):
        rs = [r for r in pr["rows"] if r["method"] == m]
        starts = [s for r in rs for s in r["starts"]]
        by_method[m] = {
            "ready": statistics.median(s["ready_s"] for s in starts),
            "kill": statistics.median(k for r in rs for k in r["kill_s"]),
            "job": statistics.median(r["job_overhead_median_s"] for r in rs),
            "cpu": statistics.median(s["cpu_s"] for s in starts if s.get("cpu_s") is not None),
            "rss": statistics.median(s["rss_mib"] for s in starts if s["rss_mib"] is not None),
            "pss": statistics.median(s["pss_mib"] for s in starts if s["pss_mib"] is not None)}
    cheapest = min(by_method, key=lambda m: by_method[m]["ready"])
    c = by_method[cheapest]
    per_kill = c["kill"] + c["ready"]
    cores = per_core(res)
    lines = []
    if lat_req:
        med = statistics.median(lat_req)
        verdict = "Checkpoints cost less" if med < per_kill else "Kill and replace costs less"
        ratios = [min(v["seconds"] for v in k["kill"].values()) / k["stop_median_s"]
                  for k in cores if k["stop_median_s"]]
        lines.append(
            f"**{verdict}.** Per stop, a checkpointed computation let its worker go "
            f"{1e3 * med:.0f} ms (median) after `cancel()` over {len(lat_req)} cancels of "
            f"{len(req)} ordinary requests ({1e3 * max(lat_req):.0f} ms at most), while a "
            f"killed worker is dead {1e3 * c['kill']:.1f} ms after `kill()` but its slot stays "
            f"empty until the replacement can compute again: {c['ready']:.2f} s with "
            f"`{cheapest}`"
            + "".join(f" ({v['ready']:.2f} s with `{m}`)" for m, v in by_method.items()
                      if m != cheapest)
            + f", medians over the cores. A kill costs the next request {per_kill:.2f} s, "
            f"{per_kill / med:.0f}x the checkpoints' median stop"
            + (f" ({min(ratios):.0f}x to {max(ratios):.0f}x core by core, each against its "
               "own cheapest replacement)" if len(ratios) > 1 else "")
            + f", and the replacement used {c['cpu']:.2f} CPU-seconds (median) of the cores "
            "the other requests compute on.")
    cold = pr.get("cold") or []
    cold_txt = (" With an empty numba cache (the first start after a deploy) a replacement "
                "takes " + ", ".join(f"{r['ready_s']:.0f} s ({r['core']})" for r in cold) + "."
                if cold else "")
    est = max(r["overhead_estimated"] for r in req)
    meas = [r["overhead_measured"] for r in req]
    # How far apart repeats of one and the same mode were: the noise a difference must beat.
    spread = max((max(xs) - min(xs)) / statistics.median(xs)
                 for r in req for xs in (r["none_s"], r["live_s"]))
    noise = ("within" if max(abs(x) for x in meas) <= spread else "not all within")
    ship = max(pr["ship"], key=lambda s: s["triangles"])
    lines.append(
        f"Per job, checkpoints cost {est * 100:.4f} % of the run time at most (checks x "
        f"{ck['check_cost']['live_ns']:.0f} ns per check); the measured differences between "
        f"the medians, {100 * min(meas):+.1f} to {100 * max(meas):+.1f} %, are {noise} the "
        f"spread between repeats of one mode (up to {100 * spread:.0f} % of its median) on "
        "this shared machine. A process "
        f"pool pays on every job {1e3 * c['job']:.1f} ms of pipe round trip to a worker that "
        f"holds the scene, or {1e3 * ship['ship_s']:.1f} ms to ship a "
        f"{ship['pickle_bytes'] / 2**20:.1f} MiB pickled {ship['scene']} to one that does not; "
        "and each worker holds its own scene and numba runtime: "
        f"{c['rss']:.0f} MiB RSS ({c['pss']:.0f} MiB PSS) per `{cheapest}` worker, where "
        f"threads share one copy.{cold_txt}")
    worst_lat, worst_row = max(lat_all, key=lambda t: t[0])
    worst_gap, gap_row, gap_at, gap_run = max(gaps, key=lambda t: t[0])
    own = next((k for k in cores if k["core"] == worst_row["core"]), None)
    own_kill = min(v["seconds"] for v in own["kill"].values()) if own else per_kill
    where = (f"{gap_row['label']}, {worst_gap:.2f} s between two checks, {gap_at:.2f} s "
             + (f"into a {gap_run:.2f} s run" if gap_run is not None else
                "into a run stopped by its cancel"))
    lines.append(
        f"The checkpoints' worst case is where checks are far apart: the longest gap measured "
        f"was {where}; the slowest stop measured was {worst_lat:.2f} s ({worst_row['label']}), "
        f"against {own_kill:.2f} s to kill and replace a {worst_row['core']} worker. "
        + ("There a kill would free the slot sooner: that stretch of the core needs a "
           "checkpoint inside it (or a cap on the parameter that makes it long)."
           if worst_lat > own_kill else "Even that is shorter than a kill and a replacement.")
        + (" The gaps count `checkpoint()` calls only: kernels that poll the token's stop flag "
           "themselves (`visibility.cancel.flag_set`; cos between pixels and within long "
           "lists) stop inside a gap, which is why the slowest stop is shorter than the "
           "longest gap." if worst_lat < 0.5 * worst_gap else ""))
    methods = list(by_method)
    table = ["| core | stop ms median (ordinary) | stop ms max (ordinary) | stop ms max "
             "(hostile) | longest gap ms | " + " | ".join(f"kill + replace s ({m})"
                                                       for m in methods)
             + f" | replacement CPU s ({' / '.join(methods)}) |",
             "|---|---|---|---|---|" + "---|" * len(methods) + "---|"]
    for k in cores:
        cpu = [v["cpu_s"] for v in k["kill"].values() if v["cpu_s"] is not None]
        table.append(
            f"| {k['core']} | {_ms(k['stop_median_s'])} | {_ms(k['stop_max_s'])} | "
            f"{_ms(k['hostile_stop_max_s'])} | {_ms(k['gap_max_s'])} | "
            + " | ".join(f"{k['kill'][m]['seconds']:.2f}" if m in k["kill"] else "–"
                         for m in methods)
            + " | " + ("–" if not cpu else " / ".join(f"{x:.2f}" for x in cpu)) + " |")
    return lines + ["\n".join(table)]


def write_report(res: dict[str, Any], out: Path, name: str) -> Path:
    """``OUT/NAME.md``, ``.json`` and ``.png`` from the results ``res``."""
    out.mkdir(parents=True, exist_ok=True)
    m = res["machine"]

    def load(xs: list[float]) -> str:
        return "/".join(f"{x:.2f}" for x in xs)

    metas = [(p, res[p]["meta"]) for p in ("checkpoints", "process") if p in res]
    md = ["# Stopping a computation: checkpoints against kill-and-replace", "",
          *[f"Command ({p} part): `{mt['command']}`, {mt['seconds']:.0f} s; load average "
            f"(1/5/15 min) {load(mt['load_start'])} at its start, {load(mt['load_end'])} at "
            "its end.  " for p, mt in metas],
          f"Machine: {m['cpu']}, {m['cores']} logical cores, {m['mem_gib']:.1f} GiB RAM; "
          f"{m['os']}; Python {m['python']}, numpy {m['numpy']}, numba {m['numba']} "
          f"({m['threads']} threads). Other jobs shared the cores: times are wall times under "
          "that load.", "",
          "Two ways to stop a computation whose kernels cannot be interrupted: **checkpoints** "
          "(what the server does: `visibility.cancel`, the cores call `checkpoint()` between "
          "views, segments and groups of tiles, a `CancelToken` decides) or **a worker process "
          "killed and replaced**. Each computation ran on the middle cell of its scene's "
          "viewcell grid.", "", "## Conclusion", "", *[x + "\n" for x in conclusion(res)]]
    ck = res.get("checkpoints")
    if ck:
        cost = ck["check_cost"]
        md += ["## Option 1: checkpoints", "",
               f"One `checkpoint()` costs {cost['live_ns']:.0f} ns with a live token (deadline "
               f"set, as the server runs every computation) and {cost['none_ns']:.0f} ns "
               "without one (best of 3 x 200,000 calls).", "",
               "### Overhead per job", "",
               "Seconds: median (min–max) of the same computation without a token and with a "
               f"live one that never fires (deadline {NEVER:g} s away), interleaved, after a "
               "warm-up run. Estimated: checks x cost of one check / run time.", "",
               "| scene | core | params | triangles | no token s | live token s | measured | "
               "checks | estimated |", "|---|---|---|---|---|---|---|---|---|"]
        for r in ck["rows"]:
            if r["kind"] != "request":
                continue
            md.append(f"| {r['scene']} | {r['core']} | `{json.dumps(r['params'])}` | "
                      f"{r['triangles']:,} | {_med_range(r['none_s'])} | "
                      f"{_med_range(r['live_s'])} | {100 * r['overhead_measured']:+.1f} % | "
                      f"{r['timeline']['checks']} | {100 * r['overhead_estimated']:.4f} % |")
        md += ["", "### Stop latency", "",
               "Each computation runs in a thread; the main thread calls `cancel()` t seconds "
               "in (ordinary requests: " + ", ".join(
                   f"{f:g}" for f in next((r["cancel_at"] for r in ck["rows"]
                                           if r["kind"] == "request"), ())) + " of the median "
               "run time; hostile requests, which would run for minutes: the seconds listed). "
               "Stop: from `cancel()` to the thread's `ComputationCancelled`. Gaps: between "
               "consecutive checks of one uncancelled run (start and end included), or, for "
               "hostile requests, of the cancelled runs up to their stop; the largest gap bounds "
               "the stop latency, and a cancel at a random instant waits sum(gap²) / "
               "(2 x run time) on average. Late: how much after t the main thread got to call "
               "`cancel()` (the kernels release the GIL, so it should be ~0).", "",
               "| scene | core | params | kind | run s | cancel at s | stop ms median | "
               "stop ms max | outcomes | gap ms median / max (at s) | random-cancel ms | "
               "late ms max |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in ck["rows"]:
            cs = r["cancels"]
            outs: dict[str, int] = {}
            for c in cs:
                outs[c["outcome"]] = outs.get(c["outcome"], 0) + 1
            if r["kind"] == "request":
                tl, run = r["timeline"], f"{statistics.median(r['none_s']):.2f}"
            else:
                seen = [c for c in cs if "seen_gap_max_s" in c]
                tl = max(({"gap_median_s": c["seen_gap_median_s"],
                           "gap_max_s": c["seen_gap_max_s"],
                           "gap_max_at_s": c["seen_gap_max_at_s"],
                           "expected_s": c["seen_expected_s"]} for c in seen),
                         key=lambda t: t["gap_max_s"], default=None)
                run = "–"
            late = [c["late_s"] for c in cs if c["late_s"] is not None]
            gaps = ("–" if tl is None else f"{_ms(tl['gap_median_s'], 1)} / "
                    f"{_ms(tl['gap_max_s'])} ({tl['gap_max_at_s']:.2f})")
            md.append(
                f"| {r['scene']} | {r['core']} | `{json.dumps(r['params'])}` | {r['kind']} | "
                f"{run} | " + ", ".join(f"{c['after_s']:.2f}" for c in cs) + " | "
                f"{_ms(r['latency_median_s'])} | {_ms(r['latency_max_s'])} | "
                + ", ".join(f"{n} {k}" for k, n in outs.items()) + f" | {gaps} | "
                f"{'–' if tl is None else _ms(tl['expected_s'])} | "
                f"{_ms(max(late) if late else None, 1)} |")
    pr = res.get("process")
    if pr:
        md += ["", "## Option 2: a worker process, killed and replaced", "",
               "Start methods: `spawn` (a fresh interpreter) and `forkserver` with numpy, numba "
               "and the core packages preloaded in the fork server (its own start is paid once "
               "per server). Not `fork`: the parent runs numba's worker threads, and forking a "
               "process with threads is unsafe. The worker (`benchmarks/cancel_worker.py`) "
               "imports numpy, numba and the cores, receives the pickled scene "
               f"({pr['scene']}), runs a small warm-up computation (numba loads its cached "
               "kernels, the core builds its per-scene caches) and is then ready.", "",
               "### Per job: the scene and the pipe", "",
               "A job that brings its scene (a process per job, or a pool whose workers do not "
               "hold it) ships it pickled: size, `pickle.dumps` time (median of 5), and the "
               "round trip to a ready worker that unpickles it (median of 3).", "",
               "| scene | triangles | pickled Scene MiB | its arrays alone MiB | dumps ms | "
               "ship + loads ms | of which loads ms |", "|---|---|---|---|---|---|---|"]
        for s in pr["ship"]:
            md.append(f"| {s['scene']} | {s['triangles']:,} | {s['pickle_bytes'] / 2**20:.2f} | "
                      f"{s['arrays_bytes'] / 2**20:.2f} | {_ms(s['dumps_s'], 2)} | "
                      f"{_ms(s.get('ship_s'), 1)} | {_ms(s.get('loads_s'), 1)} |")
        md += ["", "### Kill and replace", "",
               "Per start method and core, "
               f"{len(pr['rows'][0]['starts']) if pr['rows'] else 0} cycles of: a worker ready, "
               "two jobs (" + ", ".join(f"{k} `{json.dumps(v)}`" for k, v in
                                       res["config"]["job"].items())
               + "), a long job (" + ", ".join(
                   f"{k} `{json.dumps(KILL_JOBS[k])}`" for k in res["config"]["job"])
               + ") killed 0.3 s in. Kill: `kill()` until "
               "`join()` returned. Ready: `start()` until the worker could compute (phases "
               "below: interpreter start, imports of numpy, numba and the cores, the scene "
               "received, the warm-up); CPU: the worker's own CPU seconds by then. Job "
               "overhead: round trip less the worker's compute time (pickles of the job and "
               "of the PVS ids). First-job extra: the first "
               "real job's compute time less the second's (what the warm-up left undone).", "",
               "| method | core | kill ms median (max) | ready s median (min–max) | "
               + " | ".join(PHASES) + " | CPU s | RSS / PSS MiB | job overhead ms | "
               "first-job extra s |",
               "|---|---|---|---|" + "---|" * len(PHASES) + "---|---|---|---|"]
        for r in pr["rows"]:
            ph = {k: statistics.median(s[k] for s in r["starts"]) for k in PHASES}
            mem = r["starts"][-1]
            md.append(
                f"| {r['method']} | {r['core']} | {_ms(r['kill_median_s'], 1)} "
                f"({_ms(max(r['kill_s']), 1)}) | "
                f"{_med_range([s['ready_s'] for s in r['starts']])} | "
                + " | ".join(f"{ph[k]:.2f}" for k in PHASES)
                + f" | {_cpu(r['starts'])} | {mem['rss_mib']:.0f} / {mem['pss_mib']:.0f} | "
                f"{_ms(r['job_overhead_median_s'], 1)} | {r['first_job_extra_s']:+.2f} |")
        fs = [r["forkserver_start_s"] for r in pr["rows"] if r["forkserver_start_s"]]
        if fs:
            md += ["", f"The fork server itself started (with its preloads) in {fs[0]:.2f} s, "
                   "once."]
        if pr["cold"]:
            md += ["", "With an empty numba cache (`NUMBA_CACHE_DIR` a fresh folder: the first "
                   "start after a deploy or a change to a kernel), `spawn`:", "",
                   "| core | ready s | " + " | ".join(PHASES) + " | first job s |",
                   "|---|---|" + "---|" * len(PHASES) + "---|"]
            for r in pr["cold"]:
                md.append(f"| {r['core']} | {r['ready_s']:.2f} | "
                          + " | ".join(f"{r[k]:.2f}" for k in PHASES)
                          + f" | {r['first_job_compute_s']:.2f} |")
    md += ["", f"![stop latency against replacement]({name}.png)", ""]
    path = out / f"{name}.md"
    path.write_text("\n".join(md))
    (out / f"{name}.json").write_text(json.dumps(res, indent=1, default=str))
    plot(res, out / f"{name}.png")
    return path


def plot(res: dict[str, Any], path: Path) -> None:
    """Left: every measured stop (checkpoints) per case, with each case's largest gap, against
    the kill + replacement time per start method. Right: the replacement's phases per method
    and core."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ck, pr = res.get("checkpoints"), res.get("process")
    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [3, 2]})
    if ck:
        rows = ck["rows"]
        for i, r in enumerate(rows):
            # Floored at 0.01 ms: a stop at the very next check would vanish off a log axis.
            lat = [max(c["latency_s"] * 1e3, 0.01) for c in r["cancels"]
                   if c["latency_s"] is not None]
            a.plot(lat, [i] * len(lat), "o", color="C0" if r["kind"] == "request" else "C3",
                   ms=5, alpha=0.8)
            gmax = (r["timeline"]["gap_max_s"] if "timeline" in r else max(
                (c.get("seen_gap_max_s", 0.0) for c in r["cancels"]), default=0.0))
            a.plot([gmax * 1e3], [i], "|", color="k", ms=12)
        a.set_yticks(range(len(rows)))
        a.set_yticklabels([f"{r['scene']} {r['core']} {json.dumps(r['params'])}"[:48]
                           for r in rows], fontsize=7)
        a.invert_yaxis()
    if pr:
        for j, m in enumerate(sorted({r["method"] for r in pr["rows"]})):
            rs = [r for r in pr["rows"] if r["method"] == m]
            t = statistics.median(r["kill_median_s"] + r["ready_median_s"] for r in rs)
            a.axvline(t * 1e3, color=f"C{j + 4}", ls="--",
                      label=f"kill + replace ({m}, median over cores)")
    a.plot([], [], "o", color="C0", label="stop, ordinary request")
    a.plot([], [], "o", color="C3", label="stop, hostile request")
    a.plot([], [], "|", color="k", ms=12, label="largest gap between checks")
    a.set_xscale("log")
    a.set_xlabel("ms from cancel() until the worker is free (log)")
    a.set_title("checkpoints: stop latency")
    a.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3)
    if pr and pr["rows"]:
        labels, left = [], None
        import numpy as np

        data = np.array([[statistics.median(s[k] for s in r["starts"]) for k in PHASES]
                         for r in pr["rows"]])
        labels = [f"{r['method']}\n{r['core']}" for r in pr["rows"]]
        left = np.zeros(len(labels))
        for k, name in enumerate(PHASES):
            b.barh(labels, data[:, k], left=left, label=name)
            left += data[:, k]
        b.invert_yaxis()
        b.set_xlabel("seconds from start() until the worker can compute")
        b.set_title("kill and replace: the replacement")
        b.legend(fontsize=7)
        b.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="a tiny run (5k scene, one repeat, spawn and one core): a smoke test")
    ap.add_argument("--parts", default="checkpoints,process",
                    help="checkpoints and/or process; a part run alone replaces only its own "
                         "numbers in an existing NAME.json")
    ap.add_argument("--repeats", type=int, default=None,
                    help="timed runs per mode for the overhead (default 3; --quick 1)")
    ap.add_argument("--no-cold-jit", action="store_true",
                    help="skip the replacements with an empty numba cache (about a minute)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--name", default=None, help="file stem (default cancel, cancel_quick)")
    args = ap.parse_args(argv)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if not parts or set(parts) - {"checkpoints", "process"}:
        ap.error("--parts takes checkpoints and/or process")
    cfg = presets(args.quick)
    if args.repeats is not None:
        cfg["repeats"] = max(1, args.repeats)
    if args.no_cold_jit:
        cfg["cold_jit"] = False
    name = args.name or ("cancel_quick" if args.quick else "cancel")
    command = "python -m benchmarks.bench_cancel " + " ".join(
        argv if argv is not None else sys.argv[1:])
    from tqdm import tqdm

    t0 = time.perf_counter()
    where = machine()
    print(f"command: {command}\nmachine: {where}", flush=True)
    scenes = {label: load(spec) for label, spec in cfg["scenes"].items()}
    steps = (len(cfg["cases"]) if "checkpoints" in parts else 0) + (
        len(cfg["process_methods"]) * len(cfg["process_cores"])
        + (len(cfg["process_cores"]) if cfg["cold_jit"] else 0) if "process" in parts else 0)
    res: dict[str, Any] = {}
    path = args.out / f"{name}.json"
    if path.exists() and len(parts) < 2:
        res = json.loads(path.read_text())  # a part run alone keeps the other's numbers
    res.update(command=command, machine=where,
               config={"quick": args.quick, "repeats": cfg["repeats"], "job": cfg["job"],
                       "process_repeats": cfg["process_repeats"]})
    runners = {"checkpoints": part_checkpoints, "process": part_process}
    with tqdm(total=steps, desc="bench_cancel", unit="step", file=sys.stderr) as bar:
        for part in parts:
            t1, load0 = time.perf_counter(), list(os.getloadavg())
            res[part] = runners[part](cfg, scenes, tqdm.write, bar)
            # Each part says where it was measured: a part rerun alone replaces only itself.
            res[part]["meta"] = {"command": command, "load_start": load0,
                                 "load_end": list(os.getloadavg()),
                                 "seconds": time.perf_counter() - t1}
    res["seconds"] = time.perf_counter() - t0
    md = write_report(res, args.out, name)
    print("\n".join(conclusion(res)))
    print(f"wrote {md}, .json, .png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
