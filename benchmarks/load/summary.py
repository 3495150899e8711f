"""Every number of a load run (the JSON output; the tables are made from it) and the capacity
drawn from all runs.

Frames are counted by the answer their cell held when drawn: each of
``protocol.messages.ANSWERS`` (iterated, never listed here, so a new kind of answer gets its
own count), ``stalled`` and, for a pose in no cell, ``no_cell``. The core's own answers
(``CORE_ANSWERS``: the core's whole PVS, or a first answer refined to it) are the ones the
share of core-answered frames counts.
"""

from __future__ import annotations

import os
from collections.abc import Iterable

import numpy as np

from benchmarks.load.walkers import STALLED, ClientStats
from protocol.messages import ANSWERS

#: The answers whose stream is the session core's own PVS: "full" (the PVS whole) and
#: "refined" (a first answer completed to it). Every other answer is a stand-in.
CORE_ANSWERS = ("full", "refined")
if not set(CORE_ANSWERS) <= set(ANSWERS):
    raise ImportError(f"CORE_ANSWERS {CORE_ANSWERS} are not all in protocol.messages.ANSWERS "
                      f"{ANSWERS}: say which answers are the core's own")


def answer_keys(present: Iterable[str] = ()) -> list[str]:
    """The frame-source columns: every protocol answer, ``stalled``, then anything else seen
    in ``present`` (``no_cell``, or an answer this protocol version does not know)."""
    keys = [*ANSWERS, STALLED]
    return keys + sorted(set(present) - set(keys))


def latency_summary(delivered: Iterable[float], never: int) -> dict:
    """p50/p95/p99 (nearest rank, seconds) over every frame, a frame never delivered counting as
    later than any delivered one: None when the percentile falls on such a frame (printed
    "never"), or when there are no frames. ``latency_max_s`` is the largest delivered one."""
    d = np.sort(np.asarray(list(delivered), dtype=float))
    n = len(d) + int(never)
    out: dict = {"latency_max_s": float(d[-1]) if len(d) else None}
    for q in (50, 95, 99):
        rank = int(np.ceil(q / 100.0 * n)) - 1  # nearest rank, 0-based
        out[f"latency_p{q}_s"] = float(d[rank]) if 0 <= rank < len(d) else None
    return out


def frames_by_answer(stats: list[ClientStats]) -> dict[str, int]:
    """Frames of all walkers by answer, every ``answer_keys`` column present (0 when none)."""
    seen = {k for s in stats for k in s.answers}
    return {k: sum(s.answers.get(k, 0) for s in stats) for k in answer_keys(seen)}


def summarise(run: dict, stats: list[ClientStats], m: dict[str, float], peak_rss: int,
              wall: float, server_cpu: float, client_cpu: float) -> dict:
    """The run's summary: ``run`` (what was run: clients, cache, workers, scene, core, walk)
    with what the walkers saw (``stats``), the servers' counters over the run (``m``), their
    peak RSS (bytes) and CPU seconds, this process's CPU seconds and the wall time (s)."""
    lat = np.array([x for s in stats for x in s.latencies], dtype=float)
    finite = lat[np.isfinite(lat)]
    never = int(np.sum(~np.isfinite(lat)))
    frames = sum(s.frames for s in stats)
    stalls = sum(s.stalls for s in stats)
    answers = frames_by_answer(stats)
    tris = [s.triangles_received for s in stats]
    held = [s.triangles_held for s in stats]
    computations = m["pvs_computations_total"]
    out = {
        **run,
        "frames": frames, "stalls": stalls, "stall_fraction": stalls / max(1, frames),
        "clients_with_stalls": sum(1 for s in stats if s.stalls),
        "stalls_per_client": [s.stalls for s in stats],
        "frames_by_answer": answers,
        "answer_share": {k: v / max(1, frames) for k, v in answers.items()},
        "core_answer_share": sum(answers.get(k, 0) for k in CORE_ANSWERS) / max(1, frames),
        **latency_summary(finite, never),
        "latencies_s": [round(float(x), 5) for x in finite],
        "frames_never_delivered": never,
        "triangles_per_walker": tris,
        "triangles_per_walker_mean": float(np.mean(tris)) if tris else 0.0,
        "triangles_per_walker_max": int(max(tris)) if tris else 0,
        # Per answer source: the mean over walkers of the triangles its streams brought.
        "triangles_per_walker_by_answer": {
            a: float(np.mean([s.triangles_by_answer.get(a, 0) for s in stats]))
            for a in sorted({a for s in stats for a in s.triangles_by_answer})},
        "triangles_held_per_walker_mean": float(np.mean(held)) if held else 0.0,
        "triangles_held_per_walker_max": int(max(held)) if held else 0,
        "bytes_received": sum(s.bytes for s in stats),
        "bytes_sent": m["pvs_bytes_sent_total"],
        "triangles_sent": m["pvs_triangles_sent_total"],
        "computations": computations,
        "computation_seconds": m["pvs_computation_seconds_sum"],
        "computations_per_second": computations / wall if wall > 0 else float("nan"),
        "seconds_per_computation": (m["pvs_computation_seconds_sum"] / computations
                                    if computations else None),
        "cache_hits": m["pvs_cache_hits_total"],
        "computations_shared": m["pvs_computations_shared_total"],
        "prefetch_skipped": m["pvs_prefetch_skipped_total"],
        "prefetch_yields": m["pvs_prefetch_yields_total"],
        "slow_clients": m["pvs_slow_clients_total"],
        "server_stalls": m["pvs_stalls_total"],
        "server_rss_peak_bytes": peak_rss,
        "server_cpu_seconds": server_cpu,
        "server_cpu_cores": server_cpu / wall if wall > 0 else float("nan"),
        "client_cpu_seconds": client_cpu,
        "duplicates": sum(s.duplicates for s in stats),
        "dropped": sum(s.dropped for s in stats),
        "client_errors": sum(len(s.errors) for s in stats),
        "first_cell_timeouts": sum(s.first_cell_timeouts for s in stats),
        "errors_sample": [e for s in stats for e in s.errors][:5],
        "wall_seconds": wall,
    }
    return out


def held_without_stall(r: dict) -> bool:
    """Whether run ``r`` kept every walker fed: no stalled frame, none never delivered, no
    client error."""
    return (r["frames"] > 0 and r["stalls"] == 0 and r["frames_never_delivered"] == 0
            and r["client_errors"] == 0)


def capacity(runs: list[dict], cores: int | None = None) -> list[dict]:
    """Per (workers, cache) of ``runs`` (hostile runs left out): the walker counts run, the
    most walkers that ran without a stall (``held_without_stall``; None when none did) and the
    fewest that stalled, walkers per worker and per CPU core (``cores``, default this
    machine's) at that count, and computations per second: at that count and the most of any
    run, and per worker-second of computing (1 / mean seconds per computation)."""
    cores = cores or os.cpu_count() or 1
    out = []
    keys = list(dict.fromkeys((r["workers"], r["cache"]) for r in runs if not r.get("hostile")))
    for workers, cache in keys:
        rs = sorted((r for r in runs if (r["workers"], r["cache"]) == (workers, cache)
                     and not r.get("hostile")), key=lambda r: r["clients"])
        ok = [r for r in rs if held_without_stall(r)]
        bad = [r for r in rs if not held_without_stall(r)]
        best = max(ok, key=lambda r: r["clients"]) if ok else None
        spc = [r["seconds_per_computation"] for r in rs if r.get("seconds_per_computation")]
        out.append({
            "workers": workers, "cache": cache, "clients_run": [r["clients"] for r in rs],
            "most_walkers_without_stall": best["clients"] if best else None,
            "fewest_walkers_stalled": min(r["clients"] for r in bad) if bad else None,
            "walkers_per_worker": best["clients"] / workers if best else None,
            "walkers_per_cpu_core": best["clients"] / cores if best else None,
            "cpu_cores": cores,
            "computations_per_second_at_most": best["computations_per_second"] if best else None,
            "computations_per_second_peak": max(r["computations_per_second"] for r in rs),
            "computations_per_worker_second": (1.0 / float(np.mean(spc))) if spc else None,
        })
    return out
