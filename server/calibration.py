"""``auto`` for the server: its calibrations (``visibility.calibration``, measured in the
background on first use, kept in ``settings.cache_dir``) and the one decision every report of
auto's choice reads (``decide_auto``).

What a session with ``core=auto`` runs, what an HTTP PVS answer says in ``chosen_because``,
what ``GET /cores?scene=`` and ``pvs cores --scene`` report as ``auto``: all are
``decide_auto`` of the scene, its cell size and the calibration known at that moment, so they
cannot disagree. With a calibration, the measured trial within the budget wins (its core at its
knob level); without one, the cores' declared fits decide (``Core.fit``), saying so while a
calibration is under way.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from server.catalog import LoadedScene
from server.settings import Settings
from visibility.calibration import Calibration, choose
from visibility.cores.base import all_fits, core_fit_report
from visibility.cores.base import choose_core as registry_choose_core
from visibility.scene import Scene

log = logging.getLogger(__name__)

#: Appended to a declared-fits choice while the scene's calibration is measured.
PENDING = "; calibration under way: the cores' declared fits decide until it is done"


@dataclass(frozen=True)
class AutoDecision:
    """What ``auto`` picks for one scene and cell size, and why.

    core : the core's name; None when no registered core fits (``why`` says why not).
    params : the parameters the choice comes with (a calibrated trial's knob level; {} when
        the declared fits decided).
    why : the reason, with the figures behind it.
    calibrated : whether a calibration decided.
    """

    core: str | None
    why: str
    params: dict[str, Any] = field(default_factory=dict)
    calibrated: bool = False

    def label(self) -> str:
        """``core (knob=level)`` for people."""
        knob = ", ".join(f"{k}={v}" for k, v in self.params.items())
        return f"{self.core}" + (f" ({knob})" if knob else "")

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (``GET /cores``' ``fit.auto``)."""
        return {"core": self.core, "why": self.why, "params": dict(self.params),
                "calibrated": self.calibrated}


def decide_auto(scene: Scene, cell_size: float, calibration: Calibration | None,
                budget_seconds: float, pending: bool = False) -> AutoDecision:
    """THE ``auto`` decision for ``scene`` at ``cell_size`` metres: ``calibration``'s pick
    within ``budget_seconds`` per cell among the cores that fit (``visibility.calibration.
    choose``), else the best declared fit (``Core.fit``; ``pending``: a calibration is under
    way, which ``why`` then says)."""
    if calibration is not None:
        fits = {n: f.ok for n, f in all_fits(scene, cell_size).items()}
        picked = choose(calibration, budget_seconds, allowed=lambda n: fits.get(n, False))
        if picked is not None:
            trial, why = picked
            return AutoDecision(trial.core, why, dict(trial.params), True)
    try:
        name, why = registry_choose_core(scene, cell_size)
    except LookupError as exc:
        return AutoDecision(None, str(exc))
    return AutoDecision(name, why + (PENDING if pending else ""))


def fit_report(scene: Scene, cell_size: float, decision: AutoDecision) -> dict[str, Any]:
    """Every core's fit for ``scene`` at ``cell_size`` metres and ``decision`` as ``auto``,
    JSON-ready (``GET /cores?scene=``, ``pvs cores --scene``)."""
    report = core_fit_report(scene, cell_size)
    report["auto"] = decision.as_dict()
    return report


class AutoCalibration:
    """The server's calibrations of ``auto`` by (scene name, cell size) and its decisions.
    Thread-safe."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        #: Calibrations by (scene name, cell size); None while one is measured.
        self.calibrations: dict[tuple[str, float], Calibration | None] = {}
        self._lock = threading.Lock()

    def decide(self, scene: Scene, cell_size: float) -> AutoDecision:
        """``decide_auto`` with this server's calibration of ``scene`` (one is started in the
        background when there is none yet and ``settings.calibrate`` is on)."""
        cal = self.calibration(scene, cell_size)
        return decide_auto(scene, cell_size, cal, self.settings.auto_budget,
                           pending=cal is None and self.settings.calibrate)

    def report(self, loaded: LoadedScene) -> dict[str, Any]:
        """``fit_report`` of a loaded scene at its grid's cell size with ``decide``'s choice.
        Blocking: scene analysis can take a while."""
        size = float(loaded.grid.cell_size)
        return fit_report(loaded.scene, size, self.decide(loaded.scene, size))

    def calibration(self, scene: Scene, cell_size: float, wait: bool = False,
                    progress: Callable[[str], None] | None = None) -> Calibration | None:
        """The calibration of ``scene`` at ``cell_size`` metres, from memory or
        ``settings.cache_dir``; else one is started in the background (None until it is done)
        or, with ``wait``, measured now. None when ``settings.calibrate`` is off (and not
        ``wait``)."""
        key = (scene.name, float(cell_size))
        with self._lock:
            if key in self.calibrations:
                cal = self.calibrations[key]
                if cal is not None or not wait:
                    return cal
            elif not self.settings.calibrate and not wait:
                return None
            else:
                self.calibrations[key] = None
        if wait:
            return self._calibrate(scene, float(cell_size), progress)
        threading.Thread(target=self._calibrate, args=(scene, float(cell_size), None),
                         name=f"pvs-calibrate-{scene.name}", daemon=True).start()
        return None

    def _calibrate(self, scene: Scene, cell_size: float,
                   progress: Callable[[str], None] | None) -> Calibration | None:
        from visibility.calibration import calibrate, load_calibration, save_calibration
        from visibility.scene import scene_fingerprint

        key = (scene.name, cell_size)
        folder = self.settings.cache_dir
        try:
            cal = None
            if folder is not None:
                cal = load_calibration(folder, scene_fingerprint(scene), cell_size)
            if cal is None:
                log.info("calibrating auto on %s at %g m cells (at most %g s)", scene.name,
                         cell_size, self.settings.calibration_seconds)
                cal = calibrate(scene, cell_size, budget_seconds=self.settings.auto_budget,
                                time_limit=self.settings.calibration_seconds,
                                progress=progress)
                if folder is not None:
                    save_calibration(folder, cal)
                log.info("calibrated auto on %s in %.1f s", scene.name, cal.seconds)
        except Exception:
            log.exception("calibration of %s failed: auto keeps the declared fits", scene.name)
            with self._lock:
                self.calibrations.pop(key, None)
            return None
        with self._lock:
            self.calibrations[key] = cal
        return cal
