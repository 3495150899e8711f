"""Occluders joined across an edge the pixel does not list (``resolve.NEIGHBOUR_RINGS``) and
the scene's edge adjacency they come from (``fusion.face_neighbours``)."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.cores.cos.core import cos_pvs
from visibility.cores.cos.fusion import face_neighbours
from visibility.scene import Scene

#: A floor split into a fan of five welded triangles, 6.1 m above a 0.3 m cell (cell-centred
#: metres; the fan's front faces point up, away from the cell), and a triangle 0.4 m above it
#: whose every ray from the cell meets the floor first. Along some pixels of the view up, the
#: rays that reach the triangle pass a few centimetres from the diagonal between two of the
#: fan's triangles, and only one of them is listed: the other is met by no ray of the pixel.
#: (Taken from a Quake level's floor, where the cell kept the triangle at 128 px.)
FAN = np.array([
    [[6.749, 6.14, 0.04], [6.749, 6.14, -0.57], [5.961, 6.14, -0.57]],
    [[6.749, 6.14, 0.04], [5.961, 6.14, -0.57], [3.929, 6.14, -0.57]],
    [[6.749, 6.14, 0.04], [3.929, 6.14, -0.57], [3.929, 6.14, -0.367]],
    [[6.749, 6.14, 0.04], [3.929, 6.14, -0.367], [3.929, 6.14, 5.323]],
    [[6.749, 6.14, 0.04], [3.929, 6.14, 5.323], [6.749, 6.14, 5.323]],
])
BEHIND = np.array([[5.961, 6.547, -0.291], [6.876, 6.547, 0.954], [5.733, 6.547, 0.954]])
BOX = np.array([[-0.15, -0.175, -0.15], [0.15, 0.175, 0.15]])


def _fan_scene() -> Scene:
    tris = np.concatenate([FAN, BEHIND[None]])
    return Scene(tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3))


def _first_hits(tris: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Index of the triangle each ray (o, d) (k, 3) meets first, float64 (-1: none)."""
    best = np.full(len(o), np.inf)
    hit = np.full(len(o), -1)
    for i, t in enumerate(tris):
        e1, e2 = t[1] - t[0], t[2] - t[0]
        p = np.cross(d, e2)
        det = p @ e1
        s = o - t[0]
        u = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", d, q) / det
        tt = (q @ e2) / det
        ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (tt > 0) & (tt < best)
        best[ok] = tt[ok]
        hit[ok] = i
    return hit


def test_the_triangle_behind_the_fan_is_hidden_from_the_whole_cell():
    """The scene is what the next test needs: float64 rays from eyes all over the cell (its
    corners too) to points all over the triangle behind meet the fan first."""
    rng = np.random.default_rng(3)
    corners = np.array([[BOX[i, 0], BOX[j, 1], BOX[k, 2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    eyes = np.concatenate([corners, BOX[0] + rng.random((400, 3)) * (BOX[1] - BOX[0])])
    w = np.concatenate([rng.dirichlet([0.3, 0.3, 0.3], 400), np.eye(3) * 0.999 + 1e-3 / 3])
    pts = w @ BEHIND
    o = np.repeat(eyes, len(pts), axis=0)
    d = np.tile(pts, (len(eyes), 1)) - o
    hits = _first_hits(np.concatenate([FAN, BEHIND[None]]), o, d)
    assert np.all((hits >= 0) & (hits < len(FAN)))


@pytest.mark.parametrize("resolution", [96, 104, 112, 120, 128])
def test_a_neighbour_no_ray_meets_closes_the_silhouette(resolution):
    """Without the fan's triangles that the pixel does not list, the diagonal stays on the
    silhouette and the cover test fails: the triangle behind was kept at these resolutions."""
    pvs, stats = cos_pvs(_fan_scene(), BOX, resolution)
    assert len(FAN) not in set(pvs.tolist())
    assert stats["neighbour_occluders"] > 0


def test_face_neighbours_pairs_welded_edges_only():
    """Two triangles of a quad are each other's neighbour across the diagonal; an edge held by
    three triangles, an open edge and a degenerate triangle get -1."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [0, 0, 1],
                  [5, 5, 5], [5, 5, 5], [6, 5, 5]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3],        # a quad: diagonal 0-2 shared
                  [1, 4, 2], [2, 4, 1],        # edge 1-2... held by faces 0, 2, 3
                  [6, 7, 8]])                  # degenerate (two equal corners)
    nb = face_neighbours(Scene(v, f))
    assert nb[0, 2] == 1 and nb[1, 0] == 0  # across 2 -> 0 and 0 -> 2
    assert nb[0, 1] == -1  # edge 1-2: three triangles share it
    assert nb[1, 1] == -1 and nb[1, 2] == -1  # open edges
    assert np.all(nb[4] == -1)
