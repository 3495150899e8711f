"""Rays aimed at chosen triangles (``visibility.ray_aimed``): what a dense reference misses
far away and small, found; what no eye sees, never found."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.cores.designed_scenes import Builder
from visibility.ray_aimed import EYES_PER_ROUND, aimed_seen, seen_from
from visibility.ray_frames import ray_frames, seen_ids

BOX = np.array([[-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]])


def _slit_scene():
    """A wall at x = 1 m, 20 x 20 m, split along z = 0 by a 1 cm slit, and behind it at x =
    50 m two squares 5 cm across: one at z = 2 m, which eyes of ``BOX`` with z near -0.04 m
    see through the slit, and one at z = 8 m, which would need an eye at z = -0.16 m."""
    b = Builder()
    wall = b.quad((1.0, -10.0, -10.0), (1.0, 10.0, -10.0), (1.0, 10.0, -0.005),
                  (1.0, -10.0, -0.005), 0)
    wall += b.quad((1.0, -10.0, 0.005), (1.0, 10.0, 0.005), (1.0, 10.0, 10.0),
                   (1.0, -10.0, 10.0), 0)
    seen = b.quad((50.0, -0.025, 1.975), (50.0, 0.025, 1.975), (50.0, 0.025, 2.025),
                  (50.0, -0.025, 2.025), 1)
    hidden = b.quad((50.0, -0.025, 7.975), (50.0, 0.025, 7.975), (50.0, 0.025, 8.025),
                    (50.0, -0.025, 8.025), 1)
    return b.scene("slit"), list(seen), list(hidden), list(wall)


def test_a_small_far_triangle_behind_a_slit_is_found_and_a_hidden_one_is_not():
    scene, seen, hidden, wall = _slit_scene()
    frames = seen_ids(ray_frames(scene, BOX, n_eyes=8, resolution=64, seed=1))
    # The frames' rays are 1.4 degrees apart; the triangle spans 0.06: they pass it by.
    assert not np.isin(seen, frames).any() and np.isin(wall, frames).all()
    got = aimed_seen(scene, BOX, seen + hidden, known=frames, rays=32, most=1024, seed=2)
    assert got.ids.tolist() == seen
    assert got.rounds[0]["added"] == 2
    # Nothing more to find: the second round adds nothing and the rounds stop there.
    assert got.converged and len(got.rounds) == 2 and got.rounds[-1]["added"] == 0
    assert got.rounds[-1]["total"] == len(frames) + 2
    assert got.rays == 4 * 32 + 2 * 32 and got.rounds[1]["rays_per_candidate"] == 64


def test_what_stands_in_front_of_the_aim_is_seen_too():
    scene, seen, hidden, wall = _slit_scene()
    got = aimed_seen(scene, BOX, hidden, rays=16, most=16)
    # The rays to the square at z = 8 m meet the upper wall's triangle that lies across them.
    assert len(got.ids) > 0 and set(got.ids.tolist()) <= set(wall[2:])


def test_rounds_double_the_rays_until_the_most():
    scene, seen, hidden, wall = _slit_scene()
    got = aimed_seen(scene, BOX, hidden, known=wall, rays=16, most=128, converge=-1.0, seed=0)
    assert got.ids.tolist() == [] and not got.converged
    assert [r["rays_per_candidate"] for r in got.rounds] == [16, 32, 64, 128]
    assert [r["rays"] for r in got.rounds] == [32, 32, 64, 128]


def test_known_and_unknown_ids_are_skipped():
    scene, seen, hidden, wall = _slit_scene()
    got = aimed_seen(scene, BOX, seen + [-1, 10_000], known=seen, rays=8, most=8)
    assert got.ids.tolist() == [] and got.rays == 0 and got.converged


def test_a_first_round_that_finds_nothing_is_not_convergence():
    scene, _, hidden, wall = _slit_scene()
    got = aimed_seen(scene, BOX, hidden, known=wall, rays=8, most=8)
    assert got.rounds[0]["added"] == 0 and not got.converged
    got = aimed_seen(scene, BOX, hidden, known=wall, rays=8, most=64)
    assert len(got.rounds) == 2 and got.converged


def test_bad_parameters_are_refused():
    scene, seen, _, _ = _slit_scene()
    with pytest.raises(ValueError, match="near"):
        aimed_seen(scene, BOX, seen, near=-1.0)
    with pytest.raises(ValueError, match="rays"):
        aimed_seen(scene, BOX, seen, rays=64, most=32)


def test_eyes_drawn_by_the_caller_are_the_only_eyes():
    scene, seen, hidden, wall = _slit_scene()
    asked = []

    def at(z):
        def draw(n, rng):
            asked.append(n)
            return np.column_stack([rng.uniform(-0.01, 0.01, n), rng.uniform(-0.01, 0.01, n),
                                    np.full(n, z)])
        return draw

    # Eyes at z = -0.04 m look through the slit at the square 2 m up; eyes at +0.04 m cannot.
    below = aimed_seen(scene, BOX, seen, rays=32, most=64, seed=3, eyes=at(-0.04))
    above = aimed_seen(scene, BOX, seen, known=wall, rays=32, most=64, seed=3, eyes=at(0.04))
    assert below.ids.tolist() == seen
    assert above.ids.tolist() == [] and above.rays == 2 * 64
    assert asked and set(asked) == {EYES_PER_ROUND}


def test_seen_from_names_the_first_eye_set_that_looks_through_the_slit():
    scene, seen, hidden, wall = _slit_scene()
    # Eyes on a line across z: those near z = -0.04 m look through the slit at the square at
    # z = 2 m; none sees the square at z = 8 m (it would need z = -0.16 m). Eyes at z >= 0.02
    # m see neither through it.
    line = np.stack([np.zeros(41), np.zeros(41), np.linspace(-0.1, 0.1, 41)], axis=1)
    upper = line[line[:, 2] >= 0.02]
    targets = np.array(seen + hidden)
    got = seen_from(scene, targets, [upper, line], rays=2048, seed=3)
    assert got.tolist() == [1] * len(seen) + [-1] * len(hidden)
    assert seen_from(scene, targets, [line, upper], rays=2048, seed=3).tolist() == (
        [0] * len(seen) + [-1] * len(hidden))
    # An id outside the scene, or no eyes, is never seen.
    assert seen_from(scene, np.array([10**9, -1]), [line]).tolist() == [-1, -1]
    assert seen_from(scene, np.array(seen), [np.zeros((0, 3))]).tolist() == [-1] * len(seen)
