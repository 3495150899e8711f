"""Near-far partition, morph, cubemap bake and lookup."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.cubemap import decode_cubemap, encode_cubemap
from visibility.generators import make_scene
from visibility.nearfar import (
    NearFarConfig,
    bake_cubemap,
    cube_texels,
    cubemap_lookup,
    horizontal_distance,
    morph,
    needs_cubemap,
    split_ids,
    texel_directions,
)
from visibility.raster.shading import BACKGROUND, shade_colors
from visibility.scene import Scene
from visibility.viewcells import ViewcellGrid

O = np.array([0.0, 1.7, 0.0])


def _tri_at(rho: float, spread: float = 0.5) -> np.ndarray:
    """A small vertical triangle around horizontal distance rho on the +X axis."""
    return np.array([[rho, 0.0, -spread], [rho, 0.0, spread], [rho, 2.0, 0.0]])


def test_config_validation():
    NearFarConfig(r1=1.0, r2=2.0, resolution=16)
    for kw in ({"r1": 0.0}, {"r1": 90.0, "r2": 80.0}, {"r2": np.inf}, {"resolution": 8},
               {"resolution": 4096}, {"resolution": 64.5}, {"r1": np.nan}):
        with pytest.raises(ValueError):
            NearFarConfig(**kw)


def test_horizontal_distance_ignores_height():
    p = np.array([[3.0, 100.0, 4.0], [0.0, -5.0, 0.0]])
    assert np.allclose(horizontal_distance(p, [0, 7, 0]), [5.0, 0.0])
    with pytest.raises(ValueError):
        horizontal_distance(p[:, :2], O)


def test_partition_of_triangles_at_known_distances():
    cfg = NearFarConfig(r1=10.0, r2=20.0)
    straddle = np.array([[15.0, 0, 0], [25.0, 0, 0], [20.0, 3.0, 0]])
    tris = [_tri_at(5), _tri_at(15), _tri_at(30), straddle, _tri_at(40), _tri_at(8)]
    v = np.concatenate(tris)
    faces = np.arange(len(v)).reshape(-1, 3)
    # Triangle 4 (rho 40) moves; triangle 5 (rho 8) moves too but stays near.
    states = np.stack([v, v.copy()])
    states[1, 12:18, 1] += 1.0
    s = Scene(vertices=v, faces=faces, states=states, state_times=[0.0, 1.0])
    sp = split_ids(s, O, cfg)
    assert sp.near_ids.tolist() == [0, 1, 3, 5]
    assert sp.far_static_ids.tolist() == [2, 3]
    assert sp.far_dynamic_ids.tolist() == [4]
    assert sp.straddle_ids.tolist() == [3]
    assert needs_cubemap(s, O, cfg)
    assert not needs_cubemap(s, O, NearFarConfig(r1=10.0, r2=50.0))


def test_degenerate_faces_are_left_out():
    v = np.concatenate([_tri_at(30), _tri_at(30) * [1, 0, 1]])  # second one flat: zero area
    v[4] = v[3]
    s = Scene(vertices=v, faces=np.arange(6).reshape(2, 3))
    sp = split_ids(s, O, NearFarConfig(r1=10.0, r2=20.0))
    assert sp.far_static_ids.tolist() == [0]


def test_morph_continuity_at_r1_and_r2():
    r1, r2 = 10.0, 20.0
    U = np.array([1.5, 1.6, -2.0])
    ang = np.linspace(0, 2 * np.pi, 7)
    for rho, expect in ((r1, "P"), (r2, "far"), (35.0, "far"), (3.0, "P")):
        P = np.stack([rho * np.cos(ang), np.linspace(-3, 30, 7), rho * np.sin(ang)], axis=1)
        Q = morph(P, U, O, r1, r2)
        want = P if expect == "P" else U + (P - O)
        assert np.allclose(Q, want, atol=1e-12)
    # Just inside the band the morph is continuous with both neighbours.
    P = np.stack([np.cos(ang), np.full(7, 2.0), np.sin(ang)], axis=1)
    q_in = morph(P * (r1 + 1e-7), U, O, r1, r2)
    assert np.allclose(q_in, P * (r1 + 1e-7), atol=1e-5)
    q_out = morph(P * (r2 - 1e-7), U, O, r1, r2)
    assert np.allclose(q_out, U + (P * (r2 - 1e-7) - O), atol=1e-5)
    # Halfway: distance from U is the mean of |P - U| and |P - O|, direction in between.
    P = np.array([[15.0, 1.7, 0.0]])
    q = morph(P, U, O, r1, r2)[0]
    t = 0.5 * (np.linalg.norm(P[0] - U) + np.linalg.norm(P[0] - O))
    assert np.isclose(np.linalg.norm(q - U), t)
    # U at O: nothing moves.
    Pm = np.random.default_rng(0).uniform(-40, 40, size=(50, 3))
    assert np.allclose(morph(Pm, O, O, r1, r2), Pm)
    with pytest.raises(ValueError):
        morph(Pm, U, O, 20.0, 10.0)


def test_needs_cubemap_false_for_rooms_true_for_city():
    cfg = NearFarConfig()
    rooms = make_scene("rooms")
    grid = ViewcellGrid.for_scene(rooms, 4.0)
    centres = grid.boxes.mean(axis=1)
    assert not any(needs_cubemap(rooms, c, cfg) for c in centres)
    city = make_scene("city", triangles=20_000)
    cgrid = ViewcellGrid.for_scene(city, 4.0)
    assert needs_cubemap(city, cgrid.boxes[len(cgrid) // 2].mean(axis=0), cfg)


def _wall_scene(x: float = 150.0, half: float = 400.0) -> Scene:
    v = np.array([[x, -half, -half], [x, -half, half], [x, half, half], [x, half, -half]])
    return Scene(vertices=v, faces=[[0, 1, 2], [0, 2, 3]], colors=[[200, 100, 50]] * 2)


def test_bake_range_is_euclidean_distance_to_a_wall():
    wall = _wall_scene()
    cfg = NearFarConfig(r1=50.0, r2=100.0, resolution=32)
    cube = bake_cubemap(wall, O, cfg)
    assert cube.colors.shape == (6, 32, 32, 3) and cube.ranges.dtype == np.float32
    d = texel_directions(32)
    unit = d / np.linalg.norm(d, axis=-1, keepdims=True)
    px = cube.ranges[0]  # +X face sees the wall everywhere
    true = 150.0 / unit[0, ..., 0]
    assert np.all(np.isfinite(px))
    assert np.max(np.abs(px / true - 1)) < 1e-5
    assert np.all(np.isinf(cube.ranges[1]))  # -X sees nothing
    shaded = shade_colors(wall.triangles([0]), wall.colors[:1])[0]
    assert np.all(cube.colors[0] == shaded)
    assert np.all(cube.colors[1] == BACKGROUND)
    # Through the wire and back: within the stated precision of the true distance.
    fr = decode_cubemap(encode_cubemap(7, O, cube.colors, cube.ranges, cfg.r1, cfg.r2))
    assert fr.cell == 7 and fr.precision < 1.3e-4
    assert np.max(np.abs(fr.ranges[0] / true - 1)) <= fr.precision + 1e-5


def test_nothing_far_bakes_an_empty_cubemap():
    cfg = NearFarConfig(r1=50, r2=100, resolution=16)
    cube = bake_cubemap(_wall_scene(x=30.0, half=20.0), O, cfg)
    assert np.all(np.isinf(cube.ranges)) and np.all(cube.colors == BACKGROUND)


def test_cubemap_lookup_finds_each_texel():
    d = texel_directions(24)
    f, r, c = cube_texels(d * 3.0, 24)
    F, R, C = np.meshgrid(np.arange(6), np.arange(24), np.arange(24), indexing="ij")
    assert np.array_equal(f, F) and np.array_equal(r, R) and np.array_equal(c, C)
    cube = bake_cubemap(_wall_scene(), O, NearFarConfig(r1=50, r2=100, resolution=24))
    col, rng = cubemap_lookup(cube, np.array([[1.0, 0.0, 0.0], [-1.0, 0.2, 0.1]]))
    assert np.isclose(rng[0], 150.0, rtol=1e-2) and np.isinf(rng[1])
    with pytest.raises(ValueError):
        cube_texels(np.zeros((2, 3)), 8)
