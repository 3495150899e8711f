"""Walkthroughs: timed eye poses, their JSON files, and random walks over a viewcell grid.

File format (JSON, +Y up, metres, seconds)::

    {"poses": [{"t": 0.0, "position": [x, y, z], "forward": [x, y, z]}, ...],
     "scene": "name", "speed": 1.4}

``scene`` and ``speed`` are optional; other fields (in the file or in a pose) are ignored.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from visibility.viewcells import ViewcellGrid

#: Head yaw sway amplitude (degrees) and period (seconds) of generated walks.
YAW_SWAY_DEG, YAW_PERIOD_S = 30.0, 4.0
#: Head pitch sway amplitude (degrees) and period (seconds), around a slight downward look.
PITCH_SWAY_DEG, PITCH_PERIOD_S, PITCH_BIAS_DEG = 5.0, 2.7, -3.0
#: Time constant (seconds) with which the head follows a change of walking direction.
TURN_SMOOTHING_S = 0.6
#: How strongly generated walks prefer going straight on (weight exp(k * cos(turn angle))).
STRAIGHT_PREFERENCE = 3.0


@dataclass
class Walkthrough:
    """Timed eye poses.

    Attributes
    ----------
    t : (n,) float64 seconds, strictly increasing.
    positions : (n, 3) float64 eye positions, metres.
    forwards : (n, 3) float64 unit view directions.
    scene : optional scene name.
    speed : optional nominal walking speed, m/s.
    """

    t: np.ndarray
    positions: np.ndarray
    forwards: np.ndarray
    scene: str | None = None
    speed: float | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        n = len(self.t)
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.forwards = np.asarray(self.forwards, dtype=np.float64)
        if n == 0:
            raise ValueError("a walkthrough needs at least one pose")
        for name, a in (("positions", self.positions), ("forwards", self.forwards)):
            if a.shape != (n, 3):
                raise ValueError(f"{name} must be ({n}, 3), got {a.shape}")
        for name, a in (("t", self.t), ("positions", self.positions), ("forwards", self.forwards)):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"walkthrough {name} must be finite (no NaN/inf)")
        if n > 1 and not np.all(np.diff(self.t) > 0):
            raise ValueError("walkthrough times must be strictly increasing")
        norms = np.linalg.norm(self.forwards, axis=1)
        if np.any(norms < 1e-12):
            raise ValueError("walkthrough forwards must be non-zero vectors")
        self.forwards = self.forwards / norms[:, None]

    def __len__(self) -> int:
        return int(len(self.t))

    @property
    def duration(self) -> float:
        """Seconds from the first to the last pose."""
        return float(self.t[-1] - self.t[0])

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), unit forward (3,)) at time ``t`` seconds, clamped to the pose range.

        Position is interpolated linearly; forward by normalised lerp (when two consecutive
        forwards are opposite, the earlier one is kept).
        """
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"time must be finite, got {t}")
        if len(self.t) == 1 or t <= self.t[0]:
            return self.positions[0].copy(), self.forwards[0].copy()
        if t >= self.t[-1]:
            return self.positions[-1].copy(), self.forwards[-1].copy()
        i = int(np.searchsorted(self.t, t, side="right") - 1)
        w = (t - self.t[i]) / (self.t[i + 1] - self.t[i])
        pos = (1.0 - w) * self.positions[i] + w * self.positions[i + 1]
        f = (1.0 - w) * self.forwards[i] + w * self.forwards[i + 1]
        n = np.linalg.norm(f)
        fwd = f / n if n > 1e-9 else self.forwards[i].copy()
        return pos, fwd

    def to_dict(self) -> dict:
        """The JSON-friendly form written by ``save_walkthrough``."""
        d: dict = {
            "poses": [
                {"t": float(t), "position": p.tolist(), "forward": f.tolist()}
                for t, p, f in zip(self.t, self.positions, self.forwards, strict=True)
            ]
        }
        if self.scene is not None:
            d["scene"] = self.scene
        if self.speed is not None:
            d["speed"] = float(self.speed)
        return d


def _vec3(pose: dict, key: str, i: int) -> list[float]:
    v = pose.get(key)
    if not isinstance(v, list | tuple) or len(v) != 3:
        raise ValueError(f"pose {i}: '{key}' must be a list of 3 numbers, got {v!r}")
    try:
        return [float(x) for x in v]
    except (TypeError, ValueError) as e:
        raise ValueError(f"pose {i}: '{key}' must hold numbers, got {v!r}") from e


def walkthrough_from_dict(data: dict) -> Walkthrough:
    """A Walkthrough from the file format's dict; ValueError naming the problem when invalid."""
    if not isinstance(data, dict) or "poses" not in data:
        raise ValueError("walkthrough must be a JSON object with a 'poses' list")
    poses = data["poses"]
    if not isinstance(poses, list) or not poses:
        raise ValueError("walkthrough 'poses' must be a non-empty list")
    ts, ps, fs = [], [], []
    for i, pose in enumerate(poses):
        if not isinstance(pose, dict):
            raise ValueError(f"pose {i} must be an object, got {pose!r}")
        for k in ("t", "position", "forward"):
            if k not in pose:
                raise ValueError(f"pose {i} has no '{k}'")
        try:
            ts.append(float(pose["t"]))
        except (TypeError, ValueError) as e:
            raise ValueError(f"pose {i}: 't' must be a number, got {pose['t']!r}") from e
        ps.append(_vec3(pose, "position", i))
        fs.append(_vec3(pose, "forward", i))
    speed = data.get("speed")
    scene = data.get("scene")
    return Walkthrough(
        t=np.array(ts),
        positions=np.array(ps),
        forwards=np.array(fs),
        scene=None if scene is None else str(scene),
        speed=None if speed is None else float(speed),
    )


def load_walkthrough(path: str | Path) -> Walkthrough:
    """Read a walkthrough JSON file; ValueError (with the path) for malformed content."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON: {e}") from e
    try:
        return walkthrough_from_dict(data)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e


def save_walkthrough(w: Walkthrough, path: str | Path) -> None:
    """Write ``w`` as a walkthrough JSON file (one pose per line)."""
    d = w.to_dict()
    lines = ",\n    ".join(json.dumps(p) for p in d.pop("poses"))
    head = json.dumps(d)[1:-1]
    text = "{" + (head + ", " if head else "") + '"poses": [\n    ' + lines + "\n]}\n"
    Path(path).write_text(text)


# --------------------------------------------------------------------------------- generation
def _cell_centre(grid: ViewcellGrid, cid: int) -> np.ndarray:
    # The box centre, or where one may walk in a cell over a street narrower than a cell.
    return grid.walk_point(cid)


def _next_cell(
    grid: ViewcellGrid, cur: int, prev: int | None, heading: np.ndarray, rng: np.random.Generator
) -> int | None:
    """A neighbour of ``cur``: no back-tracking unless at a dead end, straight on preferred,
    diagonal steps only where both cells beside the diagonal are walkable (no corner cutting)."""
    nbrs = grid.neighbours(cur)
    if not nbrs:
        return None
    ij = grid.ij
    cols = {tuple(x) for x in ij[nbrs].tolist()}

    def clear(n: int) -> bool:
        di, dk = ij[n] - ij[cur]
        if di == 0 or dk == 0:
            return True
        a, b = (int(ij[cur][0] + di), int(ij[cur][1])), (int(ij[cur][0]), int(ij[cur][1] + dk))
        return a in cols and b in cols

    cand = [n for n in nbrs if n != prev and clear(n)]
    if not cand:
        cand = [n for n in nbrs if n != prev] or nbrs
    c0 = _cell_centre(grid, cur)
    d = np.array([_cell_centre(grid, n) - c0 for n in cand])[:, [0, 2]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cos = d @ heading if np.linalg.norm(heading) > 0 else np.zeros(len(cand))
    w = np.exp(STRAIGHT_PREFERENCE * cos)
    return int(cand[rng.choice(len(cand), p=w / w.sum())])


def generate_walkthrough(
    grid: ViewcellGrid,
    duration: float = 20.0,
    speed: float = 1.4,
    fps: float = 10.0,
    seed: int = 0,
    start_cell: int | None = None,
) -> Walkthrough:
    """A random walk from cell centre to neighbouring cell centre at ``speed`` m/s.

    The walk prefers going straight on and does not turn back except at dead ends. Poses come
    every ``1 / fps`` s over ``[0, duration]``; the eye is at the cell box's mid height
    (interpolated across floor steps) and looks along the smoothed walking direction with a head
    yaw sway of ±30° (period 4 s) and a small pitch sway. Every position lies in a cell. A cell
    without neighbours gives a walker standing at its centre, looking around. Deterministic for
    a given seed.
    """
    if len(grid) == 0:
        raise ValueError("the viewcell grid has no cells to walk in")
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be positive seconds, got {duration}")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    if not (math.isfinite(speed) and speed >= 0):
        raise ValueError(f"speed must be >= 0 m/s, got {speed}")
    rng = np.random.default_rng(seed)
    cur = int(rng.integers(len(grid))) if start_cell is None else int(start_cell)
    grid.cell(cur)  # IndexError for an unknown cell

    # Waypoints (cell centres) until the path is long enough.
    need = speed * duration
    path = [_cell_centre(grid, cur)]
    length, prev, heading = 0.0, None, np.zeros(2)
    while length < need:
        nxt = _next_cell(grid, cur, prev, heading, rng)
        if nxt is None:
            break
        p = _cell_centre(grid, nxt)
        step = p - path[-1]
        heading = step[[0, 2]] / np.linalg.norm(step[[0, 2]])
        length += float(np.linalg.norm(step))
        path.append(p)
        prev, cur = cur, nxt
    pts = np.array(path)

    n = int(math.floor(duration * fps + 1e-9)) + 1
    t = np.arange(n) / fps
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s_knots = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.minimum(speed * t, s_knots[-1])
    positions = np.stack([np.interp(s, s_knots, pts[:, k]) for k in range(3)], axis=1)

    # Walking yaw per pose (direction of the segment being walked), then low-pass filtered.
    if len(pts) > 1:
        seg_i = np.clip(np.searchsorted(s_knots, s, side="right") - 1, 0, len(seg) - 1)
        d = pts[seg_i + 1] - pts[seg_i]
        walk_yaw = np.unwrap(np.arctan2(d[:, 0], d[:, 2]))
    else:
        walk_yaw = np.full(n, rng.uniform(-np.pi, np.pi))
    # Two cascaded first-order low-passes (time constant TURN_SMOOTHING_S / 2 each), starting at
    # the first heading: the head starts and ends a turn with no jump in turning rate.
    alpha = 1.0 - math.exp(-2.0 / (fps * TURN_SMOOTHING_S))
    yaw = walk_yaw
    for _ in range(2):
        yaw, _ = lfilter([alpha], [1.0, alpha - 1.0], yaw, zi=[(1.0 - alpha) * yaw[0]])
    ph_yaw, ph_pitch = rng.uniform(0, 2 * np.pi, size=2)
    yaw = yaw + np.radians(YAW_SWAY_DEG) * np.sin(2 * np.pi * t / YAW_PERIOD_S + ph_yaw)
    pitch = np.radians(PITCH_BIAS_DEG) + np.radians(PITCH_SWAY_DEG) * np.sin(
        2 * np.pi * t / PITCH_PERIOD_S + ph_pitch
    )
    forwards = np.stack(
        [np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)], axis=1
    )
    return Walkthrough(t=t, positions=positions, forwards=forwards, speed=float(speed))
