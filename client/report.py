"""Per-run outputs of a client walkthrough: frames.csv, summary.json, metrics.png, frame images.

``summary.json`` top-level keys are a stable interface::

    {"meta": {...}, "frames": [per-frame records], "epsilon": mean %, "psnr": mean dB,
     "ssim": mean, "stalls": number of frames with "stalled" true,
     "psnr_cap_db": 255.0, "summary": {metric: {"mean", "min", "max", "count"}}}

A near-far run's frames also carry the composed frame's metrics (``epsilon_composed``,
``psnr_composed``, ``ssim_composed``, with ``_conventional`` twins for compositing without the
morph) and the discontinuity δ of both (``delta_composed``, ``delta_conventional``); their means
are then top-level keys too (``NEAR_FAR_METRICS``), the plot gets panels for them and the
printed table lists them right after the main metrics.

PSNR means, minima and maxima use PSNR capped at ``client.metrics.PSNR_CAP_DB`` (an identical
frame has PSNR +inf). The file is strict JSON: a non-finite number in a frame record (such as the
+inf PSNR of an identical frame) is written as null. A mean over no frames is null.
"""

from __future__ import annotations

import csv
import json
import math
from numbers import Real
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from client.metrics import PSNR_CAP_DB, capped_psnr, epsilon_mask

#: Metrics plotted and always present in ``summary["summary"]`` (when any frame has them).
MAIN_METRICS = ("epsilon", "psnr", "ssim")
#: Near-far metrics: top-level means in ``summary.json`` when any frame has them.
NEAR_FAR_METRICS = ("epsilon_composed", "psnr_composed", "ssim_composed", "delta_composed",
                    "delta_conventional")
#: Record fields that are indices or times, not metrics.
NON_METRICS = ("t", "frame", "index", "cell", "stalled")


def _is_number(v: Any) -> bool:
    return isinstance(v, Real | np.number) and not isinstance(v, bool | np.bool_)


def _json_safe(v: Any) -> Any:
    """Strict-JSON form of a record value: numpy scalars and arrays to Python (integers stay
    integers), non-finite to None."""
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_safe(x) for x in v]
    if isinstance(v, np.ndarray):
        return _json_safe(v.tolist())
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, int | np.integer):
        return int(v)
    if _is_number(v):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, Path):
        return str(v)
    return v


def metric_stats(frames: list[dict]) -> dict[str, dict[str, float]]:
    """``{metric: {"mean", "min", "max", "count"}}`` over the numeric fields of frame records.

    PSNR is capped at ``PSNR_CAP_DB`` first; other non-finite values are left out.
    """
    keys: list[str] = []
    for f in frames:
        for k, v in f.items():
            if k not in keys and k not in NON_METRICS and _is_number(v):
                keys.append(k)
    out = {}
    for k in keys:
        vals = np.array([float(f[k]) for f in frames if _is_number(f.get(k))])
        if k.startswith("psnr"):
            vals = capped_psnr(vals)
        vals = vals[np.isfinite(vals)]
        if len(vals):
            out[k] = {
                "mean": float(vals.mean()),
                "min": float(vals.min()),
                "max": float(vals.max()),
                "count": int(len(vals)),
            }
    return out


def answer_stats(frames: list[dict]) -> dict[str, dict[str, float]]:
    """Per answer the frames' cell held (``answer``: "first" before refinement, "refined" or
    "full" after, "none" for no complete stream): ``{answer: {"frames", "share", metric means
    (the main and near-far metrics present)}}``; empty when no frame records an answer."""
    out: dict[str, dict[str, float]] = {}
    named = [f for f in frames if f.get("answer")]
    for answer in sorted({str(f["answer"]) for f in named}):
        sub = [f for f in named if f["answer"] == answer]
        stats = metric_stats(sub)
        out[answer] = {"frames": len(sub), "share": len(sub) / len(frames),
                       **{m: stats[m]["mean"] for m in (*MAIN_METRICS, *NEAR_FAR_METRICS)
                          if m in stats}}
    return out


def _write_csv(path: Path, frames: list[dict]) -> None:
    cols: list[str] = []
    for f in frames:
        cols.extend(k for k in f if k not in cols)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for f in frames:
            row = []
            for c in cols:
                v = f.get(c, "")
                if isinstance(v, dict | list | tuple | np.ndarray):
                    v = json.dumps(_json_safe(v))
                elif isinstance(v, np.generic):
                    v = v.item()
                row.append(v)
            w.writerow(row)


#: Plot label of each metric a panel can show.
_LABELS = {
    "epsilon": "ε (% pixels)",
    "psnr": f"PSNR (dB, cap {PSNR_CAP_DB:g})",
    "ssim": "SSIM",
    "delta": "δ (mean |δ|)",
}


def plot_panels(frames: list[dict]) -> list[tuple[str, tuple[str, ...]]]:
    """The panels ``metrics.png`` draws for these frame records: (title, metric keys) each.

    Always ε, PSNR and SSIM of the geometry-only frame; when any frame carries near-far fields,
    also ε, PSNR and SSIM of the composed frame (the device's picture) and a δ panel comparing
    the morph (``delta_composed``) with conventional compositing (``delta_conventional``).
    """
    panels: list[tuple[str, tuple[str, ...]]] = [
        (f"{m}: geometry only" if _has(frames, f"{m}_composed") else m, (m,))
        for m in MAIN_METRICS
    ]
    panels += [(f"{m}: composed", (f"{m}_composed",)) for m in MAIN_METRICS
               if _has(frames, f"{m}_composed")]
    deltas = tuple(k for k in ("delta_composed", "delta_conventional") if _has(frames, k))
    if deltas:
        panels.append(("delta: morph vs conventional", deltas))
    return panels


def _has(frames: list[dict], key: str) -> bool:
    return any(_is_number(f.get(key)) for f in frames)


def _plot(path: Path, frames: list[dict], meta: dict) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    x = np.array(
        [float(f["t"]) if _is_number(f.get("t")) else float(i) for i, f in enumerate(frames)]
    )
    xlabel = "t (s)" if frames and all(_is_number(f.get("t")) for f in frames) else "frame"
    stalled = np.array([bool(f.get("stalled", False)) for f in frames], dtype=bool)
    panels = plot_panels(frames)
    # Near-far runs: geometry-only metrics on the left, the composed frame's on the right, δ
    # across the bottom.
    two = len(panels) > len(MAIN_METRICS)
    rows = len(MAIN_METRICS) + (1 if two and len(panels) > 2 * len(MAIN_METRICS) else 0)
    fig = Figure(figsize=(12 if two else 8, 6 + 1.5 * (rows - 3)), dpi=80)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(rows, 2 if two else 1)
    axes = []
    for k, (title, keys) in enumerate(panels):
        if k < len(MAIN_METRICS):
            spec = grid[k, 0]
        elif k < 2 * len(MAIN_METRICS):
            spec = grid[k - len(MAIN_METRICS), 1]
        else:
            spec = grid[rows - 1, :]
        ax = fig.add_subplot(spec, sharex=axes[0] if axes else None)
        axes.append(ax)
        for key in keys:
            y = np.array([float(f[key]) if _is_number(f.get(key)) else np.nan for f in frames])
            if key.startswith("psnr"):
                y = capped_psnr(y)  # NaN (missing) stays NaN
            ax.plot(x, y, lw=1.2, marker="." if len(x) < 60 else None, label=key)
        for xs in x[stalled]:
            ax.axvline(xs, color="tab:red", alpha=0.25, lw=1)
        ax.set_ylabel(_LABELS[keys[0].split("_")[0]])
        if two:
            ax.set_title(title, fontsize=9)
        if len(keys) > 1:
            ax.legend(fontsize=8, loc="best")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel(xlabel)
    title = str(meta.get("title") or meta.get("name") or meta.get("scene") or "walkthrough")
    n_stall = int(stalled.sum())
    fig.suptitle(f"{title}: {len(frames)} frames, {n_stall} stalled (red)")
    # Fixed margins: tight_layout costs more than the rest of the plot.
    fig.subplots_adjust(left=0.08 if two else 0.1, right=0.97, top=0.93, bottom=0.08,
                        hspace=0.35 if two else 0.12, wspace=0.2)
    fig.savefig(path)


def write_report(out_dir: str | Path, frames: list[dict], meta: dict) -> dict:
    """Write ``frames.csv``, ``summary.json`` and ``metrics.png`` into ``out_dir``.

    ``frames`` are per-frame records (dicts of scalars, usually ``t``, ``epsilon``, ``psnr``,
    ``ssim``, ``stalled`` and whatever else the client measured); ``meta`` describes the run.
    Returns the summary dict as written to ``summary.json`` (see the module docstring).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames = [dict(f) for f in frames]
    stats = metric_stats(frames)
    summary = {
        "meta": _json_safe(dict(meta)),
        "frames": _json_safe(frames),
        **{m: (stats[m]["mean"] if m in stats else None) for m in MAIN_METRICS},
        **{m: stats[m]["mean"] for m in NEAR_FAR_METRICS if m in stats},
        "stalls": int(sum(bool(f.get("stalled", False)) for f in frames)),
        "psnr_cap_db": PSNR_CAP_DB,
        "summary": stats,
        "answers": answer_stats(frames),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1, allow_nan=False))
    _write_csv(out / "frames.csv", frames)
    _plot(out / "metrics.png", frames, meta)
    return summary


def format_summary(summary: dict, per_frame: bool = False) -> str:
    """A printable table of a summary (as returned by ``write_report``): optionally one line per
    frame, then mean/min/max per metric and the stall count."""
    lines = []
    frames = summary.get("frames") or []
    if per_frame and frames:
        cols = [c for c in ("t", *MAIN_METRICS, "stalled") if any(c in f for f in frames)]
        lines.append("  ".join(f"{c:>9}" for c in ["frame", *cols]))
        for i, f in enumerate(frames):
            cells = [f"{i:>9d}"]
            for c in cols:
                v = f.get(c)
                if v is None and c == "psnr" and "psnr" in f:
                    cells.append(f"{'inf':>9}")
                elif isinstance(v, bool):
                    cells.append(f"{'yes' if v else '':>9}")
                elif _is_number(v):
                    cells.append(f"{float(v):>9.4g}")
                else:
                    cells.append(f"{'-' if v is None else str(v):>9}")
            lines.append("  ".join(cells))
        lines.append("")
    stats = summary.get("summary") or {}
    first = (*MAIN_METRICS, *NEAR_FAR_METRICS)
    order = [m for m in first if m in stats] + [m for m in stats if m not in first]
    width = max([16, *(len(m) + 2 for m in order)])
    lines.append(f"{'metric':<{width}}{'mean':>12}{'min':>12}{'max':>12}{'n':>7}")
    for m in order:
        s = stats[m]
        name = f"{m} (cap {PSNR_CAP_DB:g})" if m == "psnr" else m
        lines.append(
            f"{name:<{width}}{s['mean']:>12.4g}{s['min']:>12.4g}{s['max']:>12.4g}{s['count']:>7d}"
        )
    answers = summary.get("answers") or {}
    if set(answers) - {"full", "none"}:
        # Progressive streams: the frames drawn from a first answer, and after refinement.
        for a, st in answers.items():
            means = "  ".join(f"{m} {st[m]:.4g}" for m in MAIN_METRICS if m in st)
            lines.append(f"answer {a:<8} {int(st['frames']):5d} frames ({100 * st['share']:.0f} %)"
                         f"  {means}")
    tail = f"frames: {len(frames)}   stalls: {summary.get('stalls', 0)}"
    startup = (summary.get("meta") or {}).get("startup_seconds")
    if _is_number(startup):
        tail += f"   start-up (first cell before walking): {float(startup):.2f} s"
    lines.append(tail)
    return "\n".join(lines)


def save_frame_images(
    out_dir: str | Path,
    name: str,
    color: np.ndarray,
    color_gt: np.ndarray,
    depth: np.ndarray,
    depth_gt: np.ndarray,
) -> Path:
    """Write ``<out_dir>/<name>.png``: frame | ground truth | error overlay, side by side.

    The overlay is the ground truth dimmed with ε pixels (``client.metrics.epsilon_mask``,
    default tolerances) in red. Colours are (H, W, 3) uint8, depths (H, W) metres with +inf
    for empty pixels. Returns the path written.
    """
    color = np.asarray(color, dtype=np.uint8)
    color_gt = np.asarray(color_gt, dtype=np.uint8)
    if color.shape != color_gt.shape or color.ndim != 3 or color.shape[2] != 3:
        raise ValueError(f"colours must be equal (H, W, 3), got {color.shape}, {color_gt.shape}")
    mask = epsilon_mask(depth, depth_gt)
    if mask.shape != color.shape[:2]:
        raise ValueError(f"depth shape {mask.shape} does not match colour {color.shape[:2]}")
    overlay = (color_gt.astype(np.float32) * 0.4).astype(np.uint8)
    overlay[mask] = (255, 0, 0)
    sep = np.full((color.shape[0], 2, 3), 255, dtype=np.uint8)
    img = np.concatenate([color, sep, color_gt, sep, overlay], axis=1)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.png"
    Image.fromarray(img).save(path)
    return path
