"""Rays aimed at chosen triangles from eyes in a cell: which of them some eye sees first.

A dense reference (``ray_frames``) casts its rays evenly over the sphere of directions, so a
triangle far away and smaller than its pixels is seen only when a ray happens to pass
through it; a reference that keeps finding such triangles as its eyes double has not
converged, and a PVS measured against it looks looser than it is. Rays aimed at the
triangles themselves give each candidate as many chances as asked for: every round casts,
for each candidate not yet seen, rays from random eyes in the cell's open space (drawn
afresh each round, ``ray_reference.draw_eyes``, an eye inside geometry dropped as
``ray_frames.in_open_space`` does, by ``ray_frames.open_mask`` on the caster at hand) to
uniformly random points of the candidate, each ray clipped by the clients' near plane of a
randomly turned cube (as ``ray_frames``). A triangle counts as seen when such a ray meets it
first in float32 (Embree), the candidate aimed at or any triangle in front of it, and the
same ray cast again in float64 over every triangle (``ray_reference.ExactCaster``) agrees: a
float32 crack between welded triangles does not count. Rounds double the rays per candidate
until one after the first adds at most ``converge`` of all the triangles seen (those
``known`` before included) or ``most`` rays per candidate are cast.

What it finds is seen (a lower bound on what eyes of the cell see); what it does not find may
still be seen by rays it did not cast. Given the PVS of a conservative core as the candidates
it aims at the whole visible set, since that PVS holds all of it; a triangle seen outside
the candidates is a miss of every answer they came from.

Conventions: Y-up, right-handed, metres; triangle ids are row indices of ``scene.faces``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from visibility.raster.camera import DEFAULT_NEAR, random_rotations
from visibility.ray_frames import open_mask
from visibility.ray_reference import (
    BATCH_RAYS,
    EmbreeCaster,
    ExactCaster,
    draw_eyes,
    frame_triangles,
    front_normals,
)
from visibility.scene import Scene

#: Eyes drawn per round before dropping those inside geometry.
EYES_PER_ROUND = 1024


@dataclass
class AimedSample:
    """What rays aimed at the candidates of one cell saw.

    ids : (k,) int64 sorted ids seen (float64-confirmed), not in ``known``: the candidates
        and whatever the rays met in front of them.
    rounds : one dict per round: ``rays_per_candidate`` (cast at each candidate so far),
        ``rays`` (cast this round), ``added`` (triangles first seen), ``total`` (``known``
        plus all seen so far), ``unconfirmed`` (float32 first hits float64 did not confirm).
    rays : rays cast in all.
    converged : whether the last round, a doubling (not the first), added at most ``converge``
        of ``total``.
    known : the ``known`` ids counted (``total`` when no round ran).
    """

    ids: np.ndarray
    rounds: list[dict[str, int]] = field(default_factory=list)
    rays: int = 0
    converged: bool = False
    known: int = 0

    @property
    def total(self) -> int:
        """Triangles seen in all, ``known`` included."""
        return int(self.rounds[-1]["total"]) if self.rounds else self.known

    @property
    def rays_per_candidate(self) -> int:
        """Rays cast at each candidate in all rounds."""
        return int(self.rounds[-1]["rays_per_candidate"]) if self.rounds else 0

    @property
    def added_last(self) -> float:
        """What the last round added, as a share of what was seen before it."""
        if not self.rounds:
            return 0.0
        added = self.rounds[-1]["added"]
        return added / max(1, self.total - added)


def _random_points(tri: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) uniformly random points of the triangles ``tri`` (n, 3, 3), one each."""
    n = len(tri)
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1.0
    a[flip], b[flip] = 1.0 - a[flip], 1.0 - b[flip]
    return tri[:, 0] + a[:, None] * (tri[:, 1] - tri[:, 0]) + b[:, None] * (tri[:, 2] - tri[:, 0])


def _aimed_rays(targets: np.ndarray, eye: np.ndarray, rng: np.random.Generator, near: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One ray per triangle of ``targets`` (n, 3, 3): from an eye drawn from ``eye`` (m, 3)
    to a uniformly random point of it, as origins (n, 3), unit directions (n, 3) and the
    distance (n,) below which the near plane of a randomly turned cube clips it (at view
    depth ``near`` along the face's axis, as ``ray_frames``)."""
    e = eye[rng.integers(0, len(eye), len(targets))]
    d = _random_points(targets, rng) - e
    d /= np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
    cube = random_rotations(rng, len(targets))
    return e, d, near / np.abs(np.einsum("nij,nj->ni", cube, d)).max(axis=1)


def aimed_seen(scene: Scene, box: np.ndarray, candidates: np.ndarray,
               known: np.ndarray | None = None, rays: int = 64, most: int = 4096,
               converge: float = 1e-3, seed: int = 0, near: float = DEFAULT_NEAR,
               eyes: Callable[[int, np.random.Generator], np.ndarray] | None = None
               ) -> AimedSample:
    """What rays aimed at ``candidates`` from eyes in ``box`` see first: the candidates and
    whatever stands in front of them (module docstring).

    Parameters
    ----------
    scene : a static scene; its valid faces are cast against.
    box : (2, 3) float64 [min, max] metres, the cell.
    candidates : (k,) triangle ids to aim at; those in ``known`` are skipped.
    known : (j,) ids already seen (by ``ray_frames``, say): counted in each round's total.
    rays : rays per candidate in the first round; each later round casts as many as all
        before it, doubling them.
    most : rays per candidate in all rounds, at most.
    converge : a doubling (a round after the first) adding at most this share of the total
        ends the rounds.
    seed : seeds eyes, points and cube orientations.
    near : the clients' near plane, metres (>= 0).
    eyes : draws the eyes of a round, ``eyes(n, rng)`` -> (k, 3) world points, k <= n (where
        a person can stand in the cell, say: ``cell_walk.open_eyes``); they are used as
        drawn. None: ``n`` stratified points of ``box`` kept where in open space.
    """
    if not (np.isfinite(near) and near >= 0.0):
        raise ValueError(f"near must be a finite distance >= 0, got {near}")
    if int(rays) < 1 or int(most) < int(rays):
        raise ValueError(f"need 1 <= rays <= most, got rays={rays}, most={most}")
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    centre = 0.5 * (b[0] + b[1])
    tri, tri_ids = frame_triangles(scene, centre)
    row = np.full(len(scene.faces), -1, dtype=np.int64)
    row[tri_ids] = np.arange(len(tri_ids))
    known_ids = np.unique(np.asarray(known if known is not None else [], dtype=np.int64))
    known_ids = known_ids[(known_ids >= 0) & (known_ids < len(row))]
    done_known = np.zeros(len(tri), dtype=bool)
    done_known[row[known_ids][row[known_ids] >= 0]] = True
    cand = np.asarray(candidates, dtype=np.int64)
    cand = row[cand[(cand >= 0) & (cand < len(row))]]
    cand = np.unique(cand[cand >= 0])
    cand = cand[~done_known[cand]]
    out = AimedSample(np.zeros(0, dtype=np.int64), known=len(known_ids))
    if len(cand) == 0:
        out.converged = True
        return out
    rng = np.random.default_rng(seed)
    caster = EmbreeCaster(tri)
    normals = front_normals(tri, scene)
    exact = ExactCaster(tri)
    seen = np.zeros(len(tri), dtype=bool)
    cast = done = 0
    per = int(rays)
    while True:
        left = cand[~seen[cand]]
        if eyes is None:
            eye = draw_eyes(b, EYES_PER_ROUND, rng) - centre
            # In open space (``ray_frames.in_open_space``), judged with the caster at hand.
            eye = eye[open_mask(caster, normals, eye, seed=int(rng.integers(1 << 31)))]
        else:
            eye = np.asarray(eyes(EYES_PER_ROUND, rng), dtype=np.float64).reshape(-1, 3) - centre
        added = unconfirmed = sent = 0
        if len(eye) and len(left):
            step = max(1, BATCH_RAYS // per)
            for c0 in range(0, len(left), step):
                c = np.repeat(left[c0:c0 + step], per)
                e, d, tmin = _aimed_rays(tri[c], eye, rng, near)
                hit, _ = caster.first_hits(e, d, tmin)
                sent += len(c)
                # Whatever a ray meets first is seen, the candidate it was aimed at or a
                # triangle in front of it.
                got = np.flatnonzero(hit >= 0)
                got = got[~seen[hit[got]] & ~done_known[hit[got]]]
                if len(got) == 0:
                    continue
                # One witness per triangle, cast again in float64.
                _, first = np.unique(hit[got], return_index=True)
                w = got[first]
                hit64, _ = exact.first_hits(e[w], d[w], tmin[w])
                ok = hit64 == hit[w]
                seen[hit[w[ok]]] = True
                added += int(ok.sum())
                unconfirmed += int((~ok).sum())
        cast += sent
        done += per
        total = len(known_ids) + int(seen.sum())
        out.rounds.append({"rays_per_candidate": done, "rays": sent, "added": added,
                           "total": total, "unconfirmed": unconfirmed})
        # The first round grows the known set by a new method; only a doubling of the rays
        # can show that more rays add next to nothing.
        out.converged = len(out.rounds) > 1 and added <= converge * total
        if out.converged or done >= int(most):
            break
        # As many again as all rounds so far: the rays per candidate double.
        per = min(done, int(most) - done)
    out.ids = np.sort(tri_ids[seen])
    out.rays = cast
    return out


def seen_from(scene: Scene, targets: np.ndarray, eye_sets: list[np.ndarray],
              rays: int = 4096, seed: int = 0, near: float = DEFAULT_NEAR) -> np.ndarray:
    """(k,) int64: for each triangle of ``targets`` (k,) ids, the first set of ``eye_sets``
    (each (m, 3) world metres) from which some eye sees it; -1 where none does.

    Set by set, ``rays`` rays per target not yet seen, from eyes drawn from the set to
    uniformly random points of the target, near-plane clipped as ``aimed_seen``'s, are cast
    in float64 over every valid triangle (``ray_reference.ExactCaster``, built once); a
    target is seen when one of them meets it first. Used to say where a core's misses are
    seen from (the segments it walked, or only eyes off them): a set named is proven to see
    the target, a -1 may be a sight these rays did not draw."""
    ids = np.asarray(targets, dtype=np.int64).reshape(-1)
    sets = [np.asarray(e, dtype=np.float64).reshape(-1, 3) for e in eye_sets]
    out = np.full(len(ids), -1, dtype=np.int64)
    points = [e for e in sets if len(e)]
    if not len(ids) or not points:
        return out
    centre = np.concatenate(points).mean(axis=0)
    tri, tri_ids = frame_triangles(scene, centre)
    row = np.full(len(scene.faces), -1, dtype=np.int64)
    row[tri_ids] = np.arange(len(tri_ids))
    ok = (ids >= 0) & (ids < len(row))
    rows = np.where(ok, row[np.where(ok, ids, 0)], -1)
    exact = ExactCaster(tri)
    rng = np.random.default_rng(seed)
    per = int(rays)
    step = max(1, BATCH_RAYS // per)
    for k, eyes in enumerate(sets):
        left = np.flatnonzero((out < 0) & (rows >= 0))
        if not len(eyes) or not len(left):
            continue
        for c0 in range(0, len(left), step):
            which = np.repeat(left[c0:c0 + step], per)
            e, d, tmin = _aimed_rays(tri[rows[which]], eyes - centre, rng, near)
            hit, _ = exact.first_hits(e, d, tmin)
            got = np.unique(which[hit == rows[which]])
            out[got] = k
    return out
