"""Which cells to stream ahead of a walker, how soon it may reach them, and which held
triangles a client should drop.

Prefetch follows the dual-ray paper (Koltun et al. 2001, Sec. 6, Fig. 5): on entering a cell the
server schedules its neighbours, the ones the walker is heading for first. ``arrival_seconds``
turns a walker's motion into the expected time to each cell, the rank the compute pool orders
work by across walkers (``docs/scheduling.md``). Pure functions on numpy arrays; the session
(``server.ws``) calls them per pose and per cell stream.
"""

from __future__ import annotations

import numpy as np

from visibility.viewcells import ViewcellGrid

#: Below this speed (m/s) or displacement (m) a walker has no usable direction of motion.
MIN_MOTION = 1e-3
#: The speed (m/s) assumed of a walker standing still or whose speed is unknown: a slow walk,
#: so a standing walker's neighbours rank as if it might set off now.
SLOW_WALK = 0.5
#: The fastest speed (m/s) believed of a walker: a client that jumps (or claims a huge
#: velocity) must not rank its cells ahead of everyone else's for it.
MAX_SPEED = 10.0
#: Seconds a walker needs to turn around and head back: a cell straight behind it costs this
#: much on top of the walk, one square to its heading half of it (``arrival_seconds``).
TURN_SECONDS = 3.0


def motion_direction(
    velocity: np.ndarray | None, position: np.ndarray, last_position: np.ndarray | None
) -> np.ndarray | None:
    """The walker's predicted direction of motion in the XZ plane: (2,) unit vector or None.

    Uses ``velocity`` (3,) m/s when given and non-zero, else the step from ``last_position`` to
    ``position`` (3,) metres; None when neither shows motion.
    """
    for v in (velocity, None if last_position is None else position - last_position):
        if v is None:
            continue
        d = np.asarray(v, dtype=np.float64)[[0, 2]]
        n = float(np.hypot(d[0], d[1]))
        if np.isfinite(n) and n > MIN_MOTION:
            return d / n
    return None


def walker_speed(
    velocity: np.ndarray | None,
    position: np.ndarray,
    last_position: np.ndarray | None,
    dt: float | None,
    floor: float = SLOW_WALK,
    cap: float = MAX_SPEED,
) -> float:
    """The walker's speed in the XZ plane, m/s, clamped to [``floor``, ``cap``].

    Uses ``velocity`` (3,) m/s when given and finite, else the step from ``last_position`` to
    ``position`` (3,) metres over ``dt`` seconds (the poses' clock); ``floor`` when neither is
    usable (the first pose, a walker standing still, a pose clock that did not advance).
    """
    speed = None
    if velocity is not None:
        v = np.asarray(velocity, dtype=np.float64)
        speed = float(np.hypot(v[0], v[2]))
    elif last_position is not None and dt is not None and dt > 0:
        d = np.asarray(position, dtype=np.float64) - np.asarray(last_position, dtype=np.float64)
        speed = float(np.hypot(d[0], d[2])) / float(dt)
    if speed is None or not np.isfinite(speed):
        return float(floor)
    return float(min(max(speed, floor), cap))


def arrival_seconds(
    boxes: np.ndarray,
    position: np.ndarray,
    direction: np.ndarray | None,
    speed: float,
    turn_seconds: float = TURN_SECONDS,
) -> np.ndarray:
    """Expected seconds until a walker reaches each of ``boxes`` (k, 2, 3) [min, max] corners,
    metres: (k,) float64, 0 for a box that holds ``position`` (3,) in the XZ plane.

    The walk is the XZ distance from ``position`` to the nearest point of the box over
    ``speed`` (m/s, > 0); with a ``direction`` (2,) XZ unit vector of motion, a box off the
    walker's heading also costs ``turn_seconds * (1 - cos) / 2``, where cos is the cosine
    between the heading and the way to the box (its nearest point; its centre for a box the
    walker touches): nothing ahead, ``turn_seconds`` straight behind. Without a direction
    (standing still) every way is as good.
    """
    if not (np.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be a positive number of m/s, got {speed}")
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)[:, :, [0, 2]]
    p = np.asarray(position, dtype=np.float64)[[0, 2]]
    nearest = np.clip(p, b[:, 0], b[:, 1])
    to = nearest - p
    dist = np.hypot(to[:, 0], to[:, 1])
    out = dist / float(speed)
    if direction is None:
        return out
    touching = dist <= MIN_MOTION
    to = np.where(touching[:, None], b.mean(axis=1) - p, to)
    norm = np.hypot(to[:, 0], to[:, 1])
    inside = touching & np.all((b[:, 0] <= p) & (p <= b[:, 1]), axis=1)
    cos = np.divide(to @ np.asarray(direction, dtype=np.float64), norm,
                    out=np.ones_like(norm), where=norm > MIN_MOTION)
    turn = float(turn_seconds) * (1.0 - np.clip(cos, -1.0, 1.0)) / 2.0
    return np.where(inside, 0.0, out + turn)


def prefetch_order(
    grid: ViewcellGrid,
    cell: int,
    position: np.ndarray,
    direction: np.ndarray | None,
    ahead: float = -0.2,
) -> list[int]:
    """Neighbours of ``cell`` to prefetch, most urgent first.

    With a ``direction`` (2,) XZ unit vector, a neighbour is kept when the cosine between the
    direction and the XZ vector from ``position`` (3,) metres to the neighbour's centre exceeds
    ``ahead`` (cells behind the walker are dropped), ordered by that cosine, then distance.
    Without one, every neighbour, nearest centre first.
    """
    nbrs = grid.neighbours(cell)
    if not nbrs:
        return []
    ids = np.asarray(nbrs, dtype=np.int64)
    centres = grid.boxes[ids].mean(axis=1)[:, [0, 2]]
    to = centres - np.asarray(position, dtype=np.float64)[[0, 2]]
    dist = np.hypot(to[:, 0], to[:, 1])
    if direction is None:
        return ids[np.argsort(dist, kind="stable")].tolist()
    cos = (to @ np.asarray(direction, dtype=np.float64)) / np.maximum(dist, 1e-9)
    keep = cos > ahead
    order = np.lexsort((dist[keep], -cos[keep]))
    return ids[keep][order].tolist()


def choose_drops(
    held: np.ndarray,
    need: int,
    protect: np.ndarray,
    spare_last: np.ndarray,
    centroids: np.ndarray,
    centre: np.ndarray,
) -> np.ndarray:
    """Up to ``need`` held triangle ids to drop so a new stream fits the client's budget.

    Parameters
    ----------
    held : (n,) bool, triangles the client holds (n = scene triangles).
    need : how many to drop.
    protect : (n,) bool, never dropped (the current cell's PVS and the stream being sent).
    spare_last : (n,) bool, dropped only once nothing else is left (the prefetched neighbours'
        PVS); None-equivalent: all False.
    centroids : (n, 3) triangle centroids, metres (non-finite ones count as farthest).
    centre : (3,) the current cell's centre, metres.

    Returns int32 ids: first those in neither set, farthest from ``centre`` first, then those
    of ``spare_last``, farthest first. Fewer than ``need`` when not enough may go.
    """
    if need <= 0:
        return np.zeros(0, dtype=np.int32)
    out = []
    left = int(need)
    for tier in (held & ~protect & ~spare_last, held & ~protect & spare_last):
        cand = np.flatnonzero(tier)
        if len(cand) == 0:
            continue
        d = centroids[cand] - centre
        d2 = np.einsum("ij,ij->i", d, d)
        d2 = np.where(np.isfinite(d2), d2, np.inf)
        if len(cand) > left:
            part = np.argpartition(-d2, left - 1)[:left]
            cand, d2 = cand[part], d2[part]
        cand = cand[np.argsort(-d2, kind="stable")]
        out.append(cand)
        left -= len(cand)
        if left <= 0:
            break
    if not out:
        return np.zeros(0, dtype=np.int32)
    return np.concatenate(out).astype(np.int32)
