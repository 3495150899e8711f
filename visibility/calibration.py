"""Calibration: each fitting core's time and misses measured on a few cells of a scene, so that
``auto`` picks by what it measured rather than by a fixed rule.

A few cells spread over the scene's grid (``pick``) get a dense sampled reference
(``visibility.ground_truth.sample_pvs``: many points, a fine cubemap, its own seed). Every core
that fits the scene at that cell size runs there at each level of its knob, cheapest first, under
a deadline; a core's ladder stops at the first level slower than the budget. A trial records the
median seconds per cell, the share of the reference it missed (FN) and its PVS against the
reference's size (overestimation). ``choose`` takes, among the trials within the time budget,
the one that misses least, preferring those whose PVS stays under ``max_overestimation`` times
the reference while missing at most ``max_fn`` of it (a PVS most of a scene is not worth
streaming when a small one is nearly complete); ties go to the faster. Results are plain JSON,
keyed by the scene's content hash (``visibility.scene.scene_fingerprint``) and the cell size, so
they can be cached with the scene and reused across restarts.

Units: seconds, metres; FN is a share of the reference's triangles (0..1).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from visibility.cancel import CancelToken, ComputationCancelled
from visibility.scene import Scene, scene_fingerprint
from visibility.viewcells import ViewcellGrid, spread_evenly

log = logging.getLogger(__name__)

#: Version of the calibration's JSON; a file of another version is measured anew.
FORMAT = 1
#: Defaults: cells measured, reference points and face resolution, time budget per cell
#: (seconds), largest PVS relative to the reference, and the whole calibration's time limit.
CELLS = 3
REFERENCE_POINTS = 96
REFERENCE_RESOLUTION = 192
BUDGET_SECONDS = 1.0
MAX_OVERESTIMATION = 4.0
#: Misses (share of the sample) a lean trial may have; above it, fewer misses win over size.
MAX_FN = 0.05
TIME_LIMIT = 120.0


@dataclass
class Trial:
    """One core at one knob level over the calibration cells.

    seconds : median seconds per cell (a cell stopped by the deadline counts as the deadline).
    fn : mean share of each cell's reference missed (0..1).
    overestimation : mean PVS size over reference size.
    stopped : the deadline stopped it on some cell (its figures are then lower bounds).
    """

    core: str
    params: dict[str, Any]
    seconds: float
    fn: float
    overestimation: float
    stopped: bool = False

    def label(self) -> str:
        knob = ", ".join(f"{k}={v}" for k, v in self.params.items())
        return f"{self.core}" + (f" ({knob})" if knob else "")


@dataclass
class Calibration:
    """What ``calibrate`` measured for one scene and cell size (module docstring)."""

    fingerprint: str
    scene: str
    cell_size: float
    cells: list[int]
    reference_triangles: list[int]
    budget_seconds: float
    trials: list[Trial] = field(default_factory=list)
    seconds: float = 0.0
    skipped: dict[str, str] = field(default_factory=dict)
    format: int = FORMAT

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)

    @classmethod
    def from_json(cls, text: str) -> Calibration:
        """Parse ``to_json``'s output; ValueError when it is not one of this version."""
        data = json.loads(text)
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ValueError("not a calibration of this format")
        trials = [Trial(**t) for t in data.pop("trials")]
        return cls(trials=trials, **data)


def pick(grid: ViewcellGrid, k: int) -> list[int]:
    """``k`` cell ids spread evenly over the grid's id order, ends excluded (deterministic)."""
    return spread_evenly(np.arange(len(grid)), k)


def calibrate(scene: Scene, cell_size: float, *, cells: int = CELLS,
              budget_seconds: float = BUDGET_SECONDS, time_limit: float = TIME_LIMIT,
              reference_points: int = REFERENCE_POINTS,
              reference_resolution: int = REFERENCE_RESOLUTION, cores: list[str] | None = None,
              progress: Callable[[str], None] | None = None) -> Calibration:
    """Measure every fitting core (or ``cores``) on ``cells`` cells of ``scene`` at
    ``cell_size`` metres (module docstring).

    ``time_limit`` bounds the whole calibration (seconds): trials left when it runs out are
    skipped and named in ``skipped``. ``progress`` gets one line per trial.
    """
    from visibility.cores.base import all_fits, get_core
    from visibility.ground_truth import fn_fp_rates, sample_pvs

    t_start = time.perf_counter()
    say = progress or (lambda line: None)
    grid = ViewcellGrid.for_scene(scene, cell_size)
    ids = pick(grid, cells)
    refs = [sample_pvs(scene, grid.cell(c), n_points=reference_points,
                       resolution=reference_resolution, seed=7919 + c).triangle_ids
            for c in ids]
    cal = Calibration(scene_fingerprint(scene), scene.name, float(cell_size), ids,
                      [int(len(r)) for r in refs], float(budget_seconds))
    fits = all_fits(scene, cell_size)
    names = [n for n, f in fits.items() if f.ok and (cores is None or n in cores)]
    for n, f in fits.items():
        if not f.ok and (cores is None or n in cores):
            cal.skipped[n] = f.why
    # A trial may run past the budget by this factor before it is stopped: enough to rank it,
    # not enough for one slow core to take the whole calibration.
    deadline = 3.0 * budget_seconds
    for name in names:
        core = get_core(name)
        levels = list(core.knob_levels) or [None]
        for level in levels:
            left = time_limit - (time.perf_counter() - t_start)
            if left <= deadline * len(ids):
                cal.skipped[f"{name} {core.knob}={level}"] = "the calibration's time limit"
                continue
            params = {} if level is None else {core.knob: level}
            secs, fns, over, stopped = [], [], [], False
            for c, ref in zip(ids, refs, strict=True):
                try:
                    pvs = core.compute(scene, grid.cell(c), core.make_params(**params),
                                       token=CancelToken.after(deadline))
                except ComputationCancelled:
                    stopped = True
                    secs.append(deadline)
                    break
                except Exception as exc:  # a core that fails here is not a candidate
                    cal.skipped[name] = f"failed: {type(exc).__name__}: {exc}"
                    secs = []
                    break
                fn, _ = fn_fp_rates(pvs.triangle_ids, ref)
                secs.append(pvs.seconds)
                fns.append(fn)
                over.append(len(pvs.triangle_ids) / max(1, len(ref)))
            if not secs:
                break
            trial = Trial(name, params, float(np.median(secs)),
                          float(np.mean(fns)) if fns else 1.0,
                          float(np.mean(over)) if over else float("inf"), stopped)
            cal.trials.append(trial)
            say(f"{trial.label():40s} stopped at the {deadline:g} s deadline" if stopped else
                f"{trial.label():40s} {trial.seconds:7.3f} s/cell  FN {100 * trial.fn:6.2f} %  "
                f"PVS {trial.overestimation:5.2f}x the reference")
            if stopped or trial.seconds > budget_seconds:
                break  # its next levels cost more still
    cal.seconds = time.perf_counter() - t_start
    return cal


def choose(cal: Calibration, budget_seconds: float | None = None,
           max_overestimation: float = MAX_OVERESTIMATION, max_fn: float = MAX_FN,
           allowed: Callable[[str], bool] | None = None) -> tuple[Trial, str] | None:
    """The trial ``auto`` takes and why, with the figures behind it; None when no trial was
    measured (or ``allowed`` refuses every core).

    Among the trials within the time budget: those whose PVS stays under ``max_overestimation``
    times the sample and that miss at most ``max_fn`` of it, the one that misses least (ties:
    the faster); when none is both small and complete enough, the one that misses least
    whatever its PVS (a whole answer, however large, beats a small one with holes); when none
    is within the budget, the fastest."""
    budget = cal.budget_seconds if budget_seconds is None else float(budget_seconds)
    trials = [t for t in cal.trials if allowed is None or allowed(t.core)]
    if not trials:
        return None
    timely = [t for t in trials if not t.stopped and t.seconds <= budget]
    lean = [t for t in timely if t.overestimation <= max_overestimation and t.fn <= max_fn]
    pool = lean or timely
    head = f"calibrated on {len(cal.cells)} cells of {cal.cell_size:g} m: "
    if pool:
        ranked = sorted(pool, key=lambda t: (round(t.fn, 4), t.seconds))
        best = ranked[0]
        why = (head + f"{best.label()} missed {100 * best.fn:.2f} % of a dense sample in "
               f"{best.seconds:.3f} s per cell (budget {budget:g} s), PVS "
               f"{best.overestimation:.1f}x the sample")
        if not lean:
            why += (f" (no core within the budget missed at most {100 * max_fn:g} % with a "
                    f"PVS under {max_overestimation:g}x the sample: the fewest misses win)")
        if len(ranked) > 1:
            nxt = ranked[1]
            why += f"; next: {nxt.label()} {100 * nxt.fn:.2f} % in {nxt.seconds:.3f} s"
        return best, why
    best = min(trials, key=lambda t: t.seconds)
    return best, (head + f"no core met the budget of {budget:g} s per cell; the fastest is "
                  f"{best.label()} ({best.seconds:.3f} s, missed {100 * best.fn:.2f} %)")


def calibration_path(folder: Path, fingerprint: str, cell_size: float) -> Path:
    """Where a calibration of a scene (by content hash) at a cell size is kept in ``folder``."""
    return Path(folder) / f"calibration-{fingerprint[:32]}-{cell_size:g}m.json"


def load_calibration(folder: Path, fingerprint: str, cell_size: float) -> Calibration | None:
    """The calibration kept in ``folder``, or None when there is none (or it is unreadable,
    of another format, or of another scene)."""
    path = calibration_path(folder, fingerprint, cell_size)
    try:
        cal = Calibration.from_json(path.read_text())
    except (OSError, ValueError, TypeError, KeyError) as exc:
        if path.exists():
            log.warning("calibration %s unreadable (%s): measured anew", path, exc)
        return None
    return cal if cal.fingerprint == fingerprint else None


def save_calibration(folder: Path, cal: Calibration) -> Path:
    """Write ``cal`` into ``folder`` (atomically); its path."""
    path = calibration_path(folder, cal.fingerprint, cal.cell_size)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(cal.to_json())
    tmp.replace(path)
    return path
