"""Tests of client.walkthrough: generation on viewcell grids, file round trip, bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from client.walkthrough import (
    Walkthrough,
    generate_walkthrough,
    load_walkthrough,
    save_walkthrough,
)
from visibility.scene import WalkArea
from visibility.viewcells import ViewcellGrid


@pytest.fixture(scope="module")
def grid():
    # An L-shaped walk area: a 40 x 8 m corridor and a 8 x 32 m wing, 4 m cells.
    return ViewcellGrid(WalkArea(np.array([[0, 0, 40, 8, 0.0], [0, 8, 8, 40, 0.0]])), 4.0)


def test_generated_walk_stays_in_cells_at_speed(grid):
    w = generate_walkthrough(grid, duration=30.0, speed=1.4, fps=10.0, seed=3)
    assert len(w) == 301
    np.testing.assert_allclose(w.t, np.arange(301) / 10.0)
    cells = [grid.cell_of(p) for p in w.positions]
    assert all(c is not None for c in cells)
    step = np.linalg.norm(np.diff(w.positions, axis=0), axis=1) / np.diff(w.t)
    assert step.max() <= 1.4 + 1e-9  # chord never longer than the path walked
    assert np.median(step) == pytest.approx(1.4, rel=1e-6)
    assert np.mean(step) > 0.95 * 1.4
    # Eye at the box's mid height (flat floor: 1.7 m).
    np.testing.assert_allclose(w.positions[:, 1], 1.7)
    # Unit forwards, changing smoothly (no jumps at turns), mostly along the walk.
    np.testing.assert_allclose(np.linalg.norm(w.forwards, axis=1), 1.0)
    turn = np.degrees(np.arccos(np.clip((w.forwards[1:] * w.forwards[:-1]).sum(1), -1, 1)))
    assert turn.max() * 10.0 < 250.0  # degrees per second: a head turn, not a jump
    vel = np.diff(w.positions, axis=0)
    vel /= np.linalg.norm(vel, axis=1, keepdims=True)
    ahead = (vel * w.forwards[:-1]).sum(1)
    assert np.mean(ahead > np.cos(np.radians(60))) > 0.8
    # The head sways: yaw relative to the walking direction spans roughly +-30 degrees.
    assert np.degrees(np.arccos(np.clip(ahead, -1, 1))).max() > 20.0


def test_no_backtracking_and_determinism(grid):
    w = generate_walkthrough(grid, duration=60.0, speed=2.0, fps=5.0, seed=7, start_cell=0)
    assert grid.cell_of(w.positions[0]) == 0
    seq = [grid.cell_of(p) for p in w.positions]
    visits = [c for i, c in enumerate(seq) if i == 0 or c != seq[i - 1]]
    # The corridor and the wing end in dead ends; elsewhere no A -> B -> A.
    dead_ends = {c for c in range(len(grid)) if len(grid.neighbours(c)) <= 3}
    for a, b, c in zip(visits, visits[1:], visits[2:], strict=False):
        if a == c:
            assert b in dead_ends
    again = generate_walkthrough(grid, duration=60.0, speed=2.0, fps=5.0, seed=7, start_cell=0)
    np.testing.assert_array_equal(w.positions, again.positions)
    np.testing.assert_array_equal(w.forwards, again.forwards)
    other = generate_walkthrough(grid, duration=60.0, speed=2.0, fps=5.0, seed=8, start_cell=0)
    assert not np.array_equal(w.positions, other.positions)


def test_two_levels_and_isolated_cell():
    walk = WalkArea(np.array([[0, 0, 16, 4, 0.0], [16, 0, 32, 4, 0.8], [100, 100, 104, 104, 5.0]]))
    g = ViewcellGrid(walk, 4.0)
    w = generate_walkthrough(g, duration=40.0, speed=1.4, seed=1, start_cell=0)
    assert all(g.cell_of(p) is not None for p in w.positions)
    assert w.positions[:, 1].min() == pytest.approx(1.7)
    assert w.positions[:, 1].max() > 2.0  # climbs the 0.8 m step
    lone = g.cell_of([102.0, 6.7, 102.0])
    s = generate_walkthrough(g, duration=5.0, seed=0, start_cell=lone)
    np.testing.assert_allclose(s.positions, np.tile(g.cell(lone).center, (len(s), 1)))


def test_bad_generation_arguments(grid):
    with pytest.raises(ValueError):
        generate_walkthrough(ViewcellGrid(WalkArea(np.zeros((0, 5))), 4.0))
    with pytest.raises(ValueError):
        generate_walkthrough(grid, duration=0.0)
    with pytest.raises(ValueError):
        generate_walkthrough(grid, fps=-1.0)
    with pytest.raises(IndexError):
        generate_walkthrough(grid, start_cell=10_000)


def test_round_trip_and_pose_at(tmp_path, grid):
    w = generate_walkthrough(grid, duration=5.0, seed=2)
    w.scene = "lshape"
    path = tmp_path / "walk.json"
    save_walkthrough(w, path)
    data = json.loads(path.read_text())
    assert data["scene"] == "lshape" and data["speed"] == 1.4 and len(data["poses"]) == len(w)
    back = load_walkthrough(path)
    np.testing.assert_array_equal(back.t, w.t)
    np.testing.assert_array_equal(back.positions, w.positions)
    np.testing.assert_allclose(back.forwards, w.forwards, atol=1e-15)
    assert back.scene == "lshape" and back.speed == 1.4

    v = Walkthrough(t=[0.0, 2.0], positions=[[0, 0, 0], [2, 4, 6]], forwards=[[1, 0, 0], [0, 0, 2]])
    p, f = v.pose_at(1.0)
    np.testing.assert_allclose(p, [1, 2, 3])
    np.testing.assert_allclose(f, np.array([1, 0, 1]) / np.sqrt(2))
    np.testing.assert_allclose(v.pose_at(-5.0)[0], [0, 0, 0])
    np.testing.assert_allclose(v.pose_at(9.0)[1], [0, 0, 1])


def test_extra_fields_ignored(tmp_path):
    path = tmp_path / "w.json"
    path.write_text(
        json.dumps(
            {
                "poses": [{"t": 0, "position": [0, 1, 2], "forward": [0, 0, -1], "note": "x"}],
                "comment": "extra",
            }
        )
    )
    w = load_walkthrough(path)
    assert len(w) == 1 and w.scene is None and w.speed is None


@pytest.mark.parametrize(
    "content, message",
    [
        ("not json", "not valid JSON"),
        ("[]", "'poses'"),
        ('{"poses": []}', "non-empty"),
        ('{"poses": [{"t": 0, "position": [0, 0, 0]}]}', "'forward'"),
        ('{"poses": [{"t": 0, "position": [0, 0], "forward": [1, 0, 0]}]}', "3 numbers"),
        ('{"poses": [{"t": 0, "position": [0, NaN, 0], "forward": [1, 0, 0]}]}', "finite"),
        ('{"poses": [{"t": "a", "position": [0, 0, 0], "forward": [1, 0, 0]}]}', "number"),
        ('{"poses": [{"t": 0, "position": [0, 0, 0], "forward": [0, 0, 0]}]}', "non-zero"),
        (
            '{"poses": [{"t": 1, "position": [0, 0, 0], "forward": [1, 0, 0]},'
            ' {"t": 1, "position": [0, 0, 0], "forward": [1, 0, 0]}]}',
            "increasing",
        ),
    ],
)
def test_bad_files_raise(tmp_path, content, message):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=message) as e:
        load_walkthrough(path)
    assert str(path) in str(e.value)
