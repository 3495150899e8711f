"""The load benchmark's report: each run's printed table, the markdown tables of all runs
(capacity, frames by answer, image error; the abuse pairs in abuse mode), the capacity lines, a
PNG of the latency distributions and stalls, and the JSON of every number.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import header_lines, md_table
from benchmarks.load.hostile import HOSTILE_STATUSES, hostile_answers_text
from benchmarks.load.summary import CORE_ANSWERS, answer_keys, capacity, latency_summary
from client.metrics import PSNR_CAP_DB


def _get(r: dict, key: str, f: Callable[[Any], str], missing: str = "-") -> str:
    v = r.get(key)
    return missing if v is None or (isinstance(v, float) and np.isnan(v)) else f(v)


def _ms(r: dict, key: str) -> str:
    """A latency in ms; "never" when the percentile fell on a never-delivered frame."""
    v = r.get(key)
    if v is None:
        return ("n/a" if not r["frames"] else "never") if key in r else "-"
    return f"{1e3 * v:.0f}"


def _workers(n: int) -> str:
    return f"{n} worker" + ("" if n == 1 else "s")


def _answers(runs: list[dict]) -> list[str]:
    return answer_keys({k for r in runs for k in (r.get("frames_by_answer") or {})})


def run_rows(r: dict) -> list[tuple[str, str]]:
    """The printed rows of one run's summary ``r``."""
    def ms(key: str) -> str:
        v = _ms(r, key)
        return v if not v[0].isdigit() else f"{1e3 * r[key]:.1f} ms"

    fba = r.get("frames_by_answer") or {}
    walks = r.get("walks") or {}
    rows = [
        ("clients / cache / workers", f"{r['clients']} / {r['cache']} / {r['workers']}"),
        ("scene / kind / triangles / cells",
         f"{r['scene']} / {r.get('scene_kind', 'generated')} / {r['triangles']} / {r['cells']} "
         f"of {r.get('cell_size', 4.0):g} m"),
        ("core / params", f"{r['core']} / {json.dumps(r['params'])}"),
        ("walk", f"{r['walk_seconds']:g} s at {r['speed']:g} m/s, {r['fps']:g} fps"),
        ("walks redrawn / poses off the ground",
         _get(walks, "walks_redrawn", str) + " / " + _get(walks, "poses_off_ground", str)),
        ("frames", f"{r['frames']}"),
        ("stalls", f"{r['stalls']} ({100.0 * r['stall_fraction']:.2f} %)"),
        ("progressive", "server default" if r.get("progressive") is None
         else ("on" if r["progressive"] else "off")),
        ("frames by answer", ", ".join(f"{k} {fba.get(k, 0)}" for k in _answers([r]))),
        ("core-answer frames (" + " + ".join(CORE_ANSWERS) + ")",
         _get(r, "core_answer_share", lambda v: f"{100 * v:.1f} %")),
        *((f"ε {a} (per walker: mean / worst)",
           f"{e['eps_mean']:.3f} % / {e['eps_worst']:.3f} %, PSNR {e['psnr_mean']:.1f} dB, "
           f"SSIM {e['ssim_mean']:.4f} ({e['frames']} frames of {e['walkers']} walkers)")
          for a, e in (r.get("eps_by_answer") or {}).items()),
        ("triangles per walker (mean / max)",
         _get(r, "triangles_per_walker_mean", lambda v: f"{v:.0f}") + " / "
         + _get(r, "triangles_per_walker_max", str)),
        ("triangles per walker by answer (mean)",
         ", ".join(f"{a} {v:.0f}" for a, v in
                   (r.get("triangles_per_walker_by_answer") or {}).items()) or "-"),
        ("clients with stalls", f"{r['clients_with_stalls']}"),
        ("frame latency p50", ms("latency_p50_s")),
        ("frame latency p95", ms("latency_p95_s")),
        ("frame latency p99", ms("latency_p99_s")),
        ("frame latency max (delivered)", ms("latency_max_s")),
        ("frames never delivered", f"{r['frames_never_delivered']}"),
        ("bytes received (clients)", f"{r['bytes_received'] / 1e6:.2f} MB"),
        ("bytes sent (server metrics)", f"{r['bytes_sent'] / 1e6:.2f} MB"),
        ("PVS computations / cache hits", f"{r['computations']:.0f} / {r['cache_hits']:.0f}"),
        ("computations per second",
         _get(r, "computations_per_second", lambda v: f"{v:.2f}")),
        *((("replicas / PVS from Redis", f"{r['replicas']} / {r['redis_hits']:.0f}"),)
          if "replicas" in r else ()),
        ("joined in-flight / prefetch skipped",
         f"{r['computations_shared']:.0f} / {r['prefetch_skipped']:.0f}"),
        ("prefetch yields / slow clients",
         f"{r['prefetch_yields']:.0f} / {r['slow_clients']:.0f}"),
        ("server stalls (metrics)", f"{r['server_stalls']:.0f}"),
        ("server RSS peak", f"{r['server_rss_peak_bytes'] / 2**20:.1f} MiB"),
        ("computation seconds (server)", f"{r['computation_seconds']:.1f} s"),
        ("server CPU", f"{r['server_cpu_seconds']:.1f} s"
         + _get(r, "server_cpu_cores", lambda v: f" ({v:.2f} cores)", "")),
        ("clients CPU (this process)", f"{r['client_cpu_seconds']:.1f} s"),
        ("duplicate triangles", f"{r['duplicates']}"),
        ("triangles dropped", f"{r['dropped']}"),
        ("client errors", f"{r['client_errors']}"),
        ("wall time", f"{r['wall_seconds']:.1f} s"),
    ]
    if "warm_up_seconds" in r:
        rows.append(("warm-up (before the run)", f"{r['warm_up_seconds']:.1f} s"
                     + _get(r, "warm_cells", lambda v: f" for {v} cells", "")))
    return rows + hostile_rows(r)


def hostile_rows(r: dict) -> list[tuple[str, str]]:
    """The printed rows about the hostile client and late first cells (none for a run of the
    default mode)."""
    rows = []
    if "hostile" in r or r.get("first_cell_timeouts"):
        rows.append(("first cells late (walked anyway)", f"{r.get('first_cell_timeouts', 0)}"))
    if "hostile" in r:
        rows.append(("hostile client", "yes" if r["hostile"] else "no"))
    if r.get("hostile"):
        h = r["hostile_answers"]
        rows += [("hostile requests / concurrency / params",
                  f"{h.get('sent', 0)} / {r['hostile_concurrency']} / "
                  f"{json.dumps(r['hostile_params'])}"),
                 ("hostile answers", hostile_answers_text(h))]
    return rows


def run_lines(r: dict) -> list[str]:
    """The printed table of one run."""
    rows = run_rows(r)
    w = max(len(k) for k, _ in rows)
    lines = ["-" * (w + 30), *(f"{k:<{w}}  {v}" for k, v in rows), "-" * (w + 30)]
    return lines + [f"error: {e}" for e in r["errors_sample"]]


def load_table(runs: list[dict]) -> list[str]:
    """One markdown row per run: the load it put on the server and how the server held."""
    head = ["workers", "cache", "walkers", "frames", "stalled %", "walkers with stalls",
            "never delivered", "p50 ms", "p95 ms", "p99 ms", "max ms", "computations",
            "computations/s", "s per computation", "server CPU s (cores)",
            "server RSS peak MiB", "MB sent", "wall s"]
    rows = [[r["workers"], r["cache"], r["clients"], r["frames"],
             f"{100 * r['stall_fraction']:.2f}", r["clients_with_stalls"],
             r["frames_never_delivered"], _ms(r, "latency_p50_s"), _ms(r, "latency_p95_s"),
             _ms(r, "latency_p99_s"), _ms(r, "latency_max_s"), f"{r['computations']:.0f}",
             _get(r, "computations_per_second", lambda v: f"{v:.2f}"),
             _get(r, "seconds_per_computation", lambda v: f"{v:.3f}"),
             f"{r['server_cpu_seconds']:.1f}"
             + _get(r, "server_cpu_cores", lambda v: f" ({v:.2f})", ""),
             f"{r['server_rss_peak_bytes'] / 2**20:.0f}", f"{r['bytes_sent'] / 1e6:.2f}",
             f"{r['wall_seconds']:.1f}"] for r in runs]
    return md_table(head, rows)


def answers_table(runs: list[dict]) -> list[str]:
    """One markdown row per run: frames by answer (% of frames; one column per answer of
    ``protocol.messages.ANSWERS``, then stalled), the core's own share, triangles per walker."""
    keys = _answers(runs)
    head = ["workers", "cache", "walkers", "core answer %", *(f"{k} %" for k in keys),
            "triangles per walker mean", "triangles per walker max"]
    rows = []
    for r in runs:
        f = r.get("frames_by_answer") or {}
        n = max(1, r["frames"])
        rows.append([r["workers"], r["cache"], r["clients"],
                     _get(r, "core_answer_share", lambda v: f"{100 * v:.1f}"),
                     *(f"{100 * f.get(k, 0) / n:.1f}" for k in keys),
                     _get(r, "triangles_per_walker_mean", lambda v: f"{v:.0f}"),
                     _get(r, "triangles_per_walker_max", str)])
    return md_table(head, rows)


def eps_table(runs: list[dict]) -> list[str]:
    """One markdown row per run and answer with sampled frames: the image error per walker."""
    head = ["workers", "cache", "walkers", "answer", "frames drawn", "walkers drawn",
            "ε mean over walkers %", "ε worst walker %", "PSNR dB", "SSIM"]
    rows = []
    for r in runs:
        for a, e in (r.get("eps_by_answer") or {}).items():
            rows.append([r["workers"], r["cache"], r["clients"], a, e["frames"], e["walkers"],
                         f"{e['eps_mean']:.4f}", f"{e['eps_worst']:.4f}",
                         f"{e['psnr_mean']:.1f}", f"{e['ssim_mean']:.4f}"])
    return md_table(head, rows)


def capacity_lines(runs: list[dict], cores: int | None = None) -> list[str]:
    """The capacity per worker count and cache state, one markdown bullet each."""
    out = []
    for c in capacity(runs, cores):
        ran = ", ".join(str(n) for n in c["clients_run"])
        if c["most_walkers_without_stall"] is None:
            head = f"no run without a stall (walkers tried: {ran})"
        else:
            head = (f"{c['most_walkers_without_stall']} walkers without a stall "
                    f"({c['walkers_per_worker']:g} per worker, {c['walkers_per_cpu_core']:g} "
                    f"per CPU core of {c['cpu_cores']})")
            if c["fewest_walkers_stalled"] is not None:
                head += f", {c['fewest_walkers_stalled']} stalled"
            head += f"; walkers tried: {ran}"
        cps = [f"{c['computations_per_second_peak']:.2f} computations/s at most"]
        if c["computations_per_second_at_most"] is not None:
            cps.insert(0, f"{c['computations_per_second_at_most']:.2f} computations/s at "
                          f"{c['most_walkers_without_stall']} walkers")
        if c["computations_per_worker_second"] is not None:
            cps.append(f"{c['computations_per_worker_second']:.2f} per second of one "
                       "computing thread")
        out.append(f"- {_workers(c['workers'])}, {c['cache']} cache: {head}; {', '.join(cps)}.")
    return out


def abuse_table(runs: list[dict]) -> list[str]:
    """One markdown row per run of the abuse mode: the walkers with and without the hostile
    client, and the hostile's answers by status."""
    head = ["workers", "cache", "clients", "hostile", "frames", "stalls %",
            "clients with stalls", "p50 ms", "p95 ms", "never delivered", "first cells late",
            "server RSS peak MiB", "hostile sent", *(str(c) for c in HOSTILE_STATUSES),
            "other", "refused", "gave up", "unanswered at stop"]
    rows = []
    for r in runs:
        h = r.get("hostile_answers", {}) if r.get("hostile") else {}

        def n(key: str, h: dict = h, r: dict = r) -> str:
            return str(h.get(key, 0)) if r.get("hostile") else "–"

        rows.append([r["workers"], r["cache"], r["clients"],
                     "yes" if r.get("hostile") else "no", r["frames"],
                     f"{100 * r['stall_fraction']:.2f}", r["clients_with_stalls"],
                     _ms(r, "latency_p50_s"), _ms(r, "latency_p95_s"),
                     r["frames_never_delivered"], r.get("first_cell_timeouts", 0),
                     f"{r['server_rss_peak_bytes'] / 2**20:.0f}", n("sent"),
                     *(n(str(c)) for c in HOSTILE_STATUSES), n("other"), n("refused"),
                     n("timeout"), n("unfinished")])
    return md_table(head, rows)


def plot(runs: list[dict], path: Path) -> None:
    """Frame-latency distribution (CDF) per run and the stalled share of frames against the
    number of walkers, per worker count and cache state (abuse mode: each pair side by side),
    as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for r in runs:
        lat = np.sort(np.asarray(r["latencies_s"], dtype=float)) * 1e3
        label = (f"{r['clients']} walkers, {r['cache']}, {r['workers']} w"
                 + (", hostile" if r.get("hostile") else ""))
        if len(lat):
            # Never-delivered frames stay off the curve, so it ends below 1.
            n = len(lat) + r["frames_never_delivered"]
            a.plot(lat, np.arange(1, len(lat) + 1) / n, drawstyle="steps-post",
                   ls="-" if r["cache"] == "cold" else "--", label=label)
        elif r["frames"]:
            a.plot([], [], ls="none", label=label + ": no frame delivered")
    if runs:
        a.axvline(1e3 / runs[0]["fps"], color="grey", ls=":", label="one frame interval")
    a.set_xscale("symlog", linthresh=1.0)
    a.set_xlim(left=0.0)
    a.set_xlabel("frame delivery latency (ms, 0 when the cell was already there)")
    a.set_ylabel("fraction of frames")
    a.set_title("frame delivery latency")
    a.legend(loc="lower right", fontsize=6)
    if any(r.get("hostile") for r in runs):
        keys = list(dict.fromkeys((r["workers"], r["clients"], r["cache"]) for r in runs))
        x = np.arange(len(keys))
        for off, hostile, colour in ((-0.2, False, "C0"), (0.2, True, "C3")):
            vals = [next((100.0 * r["stall_fraction"] for r in runs
                          if (r["workers"], r["clients"], r["cache"]) == k
                          and bool(r.get("hostile")) == hostile), 0.0) for k in keys]
            b.bar(x + off, vals, 0.4, color=colour,
                  label="with the hostile client" if hostile else "without")
        b.set_xticks(x, [f"{n} walkers\n{cache}, {w} w" for w, n, cache in keys])
        b.set_title("stalls with and without a hostile client")
    else:
        for (w, cache) in dict.fromkeys((r["workers"], r["cache"]) for r in runs):
            rs = sorted((r for r in runs if (r["workers"], r["cache"]) == (w, cache)),
                        key=lambda r: r["clients"])
            b.plot([r["clients"] for r in rs], [100.0 * r["stall_fraction"] for r in rs],
                   "o-" if cache == "cold" else "s--",
                   label=f"{cache} cache, {_workers(w)}")
        b.set_xlabel("concurrent walkers")
        b.set_title("stalls against load")
    b.set_ylabel("stalled frames (%)")
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _setting_text(runs: list[dict]) -> str:
    r0 = runs[0]
    workers = sorted({r["workers"] for r in runs})
    walks = r0.get("walks") or {}
    warm = next((r for r in runs if "warm_up_seconds" in r), None)
    source = r0.get("scene_source") or {}
    what = (f"file `{source['file']}`" if "file" in source else
            f"generator `{source.get('generator', r0['scene'])}`")
    return (
        f"Scene `{r0['scene']}` ({what}, {r0['triangles']} triangles, {r0['cells']} cells of "
        f"{r0.get('cell_size', 4.0):g} m), core `{r0['core']}` with parameters "
        f"`{json.dumps(r0['params'])}`, workers {', '.join(map(str, workers))}; every walker "
        f"walks {r0['walk_seconds']:g} s at {r0['speed']:g} m/s sending {r0['fps']:g} poses/s "
        "(walker i walks the same walk in every run)."
        + (" Walks stay on the ground: a walk with a pose inside a solid, in no cell or with "
           "the eye off the ground is drawn again "
           f"({walks['walks_redrawn']} of the largest run's walks were; "
           f"{walks['poses_off_ground']} poses still off the ground)." if walks else "")
        + " Cold: a fresh server per row, every PVS computed while the walkers walk. Warm: one "
        + ("server per worker count whose cache holds the PVS of every cell the walks pass "
           "through and its neighbours before the walkers come"
           + (f" ({warm['warm_cells']} cells, computed in {warm['warm_up_seconds']:.1f} s "
              f"with {_workers(warm['workers'])})" if warm else "")
           if warm is None or "warm_cells" in warm else
           "server whose cache holds every cell's PVS before the walkers come"
           f" (computed in {warm['warm_up_seconds']:.1f} s)")
        + "; its rows run one after another on it. A stall is a frame whose cell was not "
        "complete one frame interval after its pose was sent; never delivered: still missing "
        f"{r0.get('grace_seconds', 10.0):g} s after the walk ended (the walker had left the "
        "cell). Latency percentiles are over every frame (nearest rank), a never-delivered "
        "frame counting as the latest: 'never' when the percentile falls on one.")


def markdown(name: str, command: str, where: str, runs: list[dict]) -> list[str]:
    """The report's markdown lines."""
    hostile = next((r for r in runs if r.get("hostile")), None)
    r0 = runs[0]
    details = [line for r in runs for line in (
        f"### {r['clients']} walkers, {r['cache']} cache, {_workers(r['workers'])}"
        + {True: ", hostile client", False: ", no hostile client"}.get(r.get("hostile"), ""),
        "", "```", *run_lines(r), "```", "")]
    md = ["# Load benchmark", "", *header_lines(command, where), _setting_text(runs), ""]
    if hostile is None:
        md += ["## Capacity", "",
               "Per worker count and cache state: the most walkers that ran with no stalled "
               "frame, none never delivered and no client error, per worker and per CPU core; "
               "computations per second over the wall time of that run and the most of any "
               "run; per second of one computing thread: 1 / the mean seconds a computation "
               "took (first answers included: they run on a thread of their own beside the "
               "workers).", "", *capacity_lines(runs), "",
               *load_table(runs), ""]
    else:
        md += ["## Abuse: the walkers with and without a hostile client", "",
               f"Each pair runs on the same settings; in the second row a hostile client "
               f"floods `POST /scenes/{r0['scene']}/pvs` from {hostile['hostile_address']} "
               f"with {hostile['hostile_concurrency']} requests at once, each a different "
               f"box near a random cell, core `{r0['core']}` with parameters "
               f"`{json.dumps(hostile['hostile_params'])}`, abandoned after "
               f"{hostile['hostile_timeout']:g} s and sent anew, sent again at once after an "
               f"answer (after {hostile.get('hostile_pause', 0.05):g} s when refused or "
               "answered 429/503), from before the first walker connects until the last one "
               "is done. Cold pairs: two fresh servers; warm pairs: one warmed server, the "
               "hostile row second. First cells late: walkers whose first cell did not come "
               f"within {r0.get('first_cell_timeout', 300):g} s and walked anyway (their "
               "frames count). Hostile answers by status; refused: connections refused or "
               "reset; gave up: no answer within its timeout; unanswered at stop: in flight "
               "when the walkers were done.", "", *abuse_table(runs), ""]
    md += ["## Frames by answer", "",
           "Per run, the share of frames by the answer their cell held when drawn (each answer "
           "of the protocol, then stalled); core answer: " + " + ".join(CORE_ANSWERS)
           + ", the core's own PVS. Triangles per walker: what each walker received, mean and "
           "most over the walkers.", "", *answers_table(runs), "",
           "## Image error by answer", "",
           "Sampled frames (every few frames of each answer of each walker, the first "
           f"included) drawn from the triangles the walker held, {_frame_size(runs)} px, "
           "against the whole scene: ε is the share of pixels where the walker sees something "
           "farther than it should. Each walker's frames of an answer are averaged, then the "
           "walkers: mean over walkers and the worst walker. PSNR (an identical frame counts "
           f"as {PSNR_CAP_DB:g} dB, `client.metrics.PSNR_CAP_DB`) and SSIM are averaged the "
           "same way.", "", *eps_table(runs), "",
           f"![latency and stalls]({name}.png)", "", "## Each run", "", *details]
    return md


def _frame_size(runs: list[dict]) -> str:
    s = runs[0].get("frame_size")
    return f"{s} x {s}" if s else "128 x 128"


def write_outputs(out: Path, name: str, command: str, where: str, runs: list[dict]) -> None:
    """``OUT/NAME.md`` (tables, plot, each run's table), ``NAME.png`` and ``NAME.json``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text("\n".join(markdown(name, command, where, runs)))
    (out / f"{name}.json").write_text(json.dumps(
        {"command": command, "machine": where, "runs": runs}, indent=1))
    plot(runs, out / f"{name}.png")
    print(f"wrote {out / name}.md, .png, .json")


def rerender(path: Path) -> None:
    """Rewrite ``path`` (a NAME.json of a measured run) and its .md/.png with the current
    layout: the latency summary is recomputed from the stored latencies and never-delivered
    counts, what older runs did not record shows as "-"; nothing is measured again, command
    and machine stay the run's."""
    data = json.loads(path.read_text())
    for r in data["runs"]:
        r.update(latency_summary(np.asarray(r["latencies_s"], dtype=float),
                                 r["frames_never_delivered"]))
        r.setdefault("workers", 2)
        if "computations_per_second" not in r and r.get("wall_seconds"):
            r["computations_per_second"] = r["computations"] / r["wall_seconds"]
        fba = r.get("frames_by_answer")
        if "core_answer_share" not in r and fba:
            r["core_answer_share"] = (sum(fba.get(a, 0) for a in CORE_ANSWERS)
                                      / max(1, r["frames"]))
    write_outputs(path.parent, path.stem, data["command"], data["machine"], data["runs"])
