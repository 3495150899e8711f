"""Hand-built scenes with known visibility, shared by the core tests.

Every builder returns ``(scene, cell, known)`` where ``known`` maps a case name to triangle ids
whose visibility from the cell is certain ("visible" must be in any PVS, "hidden" in none).
"""

from __future__ import annotations

import numpy as np

from visibility.scene import Scene
from visibility.viewcells import Viewcell


class Builder:
    """Accumulates quads and boxes as triangles with object ids and colours."""

    def __init__(self) -> None:
        self.tris: list[np.ndarray] = []
        self.obj: list[int] = []
        self.col: list[tuple[int, int, int]] = []

    def quad(self, a, b, c, d, obj: int, color=(180, 180, 180)) -> list[int]:
        """Two triangles (a, b, c) and (a, c, d); returns their ids."""
        first = len(self.tris)
        for t in ((a, b, c), (a, c, d)):
            self.tris.append(np.array(t, dtype=np.float64))
            self.obj.append(obj)
            self.col.append(color)
        return [first, first + 1]

    def box(self, lo, hi, obj: int, color=(150, 120, 90)) -> list[int]:
        """The six faces of an axis-aligned box (12 triangles, outward winding)."""
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        ids = []
        ids += self.quad((x0, y0, z0), (x0, y1, z0), (x1, y1, z0), (x1, y0, z0), obj, color)
        ids += self.quad((x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1), obj, color)
        ids += self.quad((x0, y0, z0), (x0, y0, z1), (x0, y1, z1), (x0, y1, z0), obj, color)
        ids += self.quad((x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1), obj, color)
        ids += self.quad((x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1), obj, color)
        ids += self.quad((x0, y1, z0), (x0, y1, z1), (x1, y1, z1), (x1, y1, z0), obj, color)
        return ids

    def scene(self, name: str, offset=(0.0, 0.0, 0.0)) -> Scene:
        tris = np.array(self.tris).reshape(-1, 3, 3) + np.asarray(offset, dtype=np.float64)
        return Scene(
            vertices=tris.reshape(-1, 3),
            faces=np.arange(len(tris) * 3).reshape(-1, 3),
            object_ids=np.array(self.obj),
            colors=np.array(self.col, dtype=np.uint8),
            name=name,
        )


def two_rooms_and_a_door(offset=(0.0, 0.0, 0.0)):
    """Room A (x in [0, 6]) and room B (x in [6.2, 12]) share a wall at x = 6..6.2 with a door
    (z in [2.5, 3.5], y < 2.2). The cell is in room A, left of the door. Through the door the
    far wall of room B straight ahead is visible; a box in B's corner behind the wall is hidden;
    a box in A is visible."""
    b = Builder()
    h = 3.0
    b.quad((0, 0, 0), (0, 0, 6), (12, 0, 6), (12, 0, 0), 0, (90, 90, 90))  # floor
    b.quad((0, h, 0), (12, h, 0), (12, h, 6), (0, h, 6), 1, (220, 220, 220))  # ceiling
    b.quad((0, 0, 0), (12, 0, 0), (12, h, 0), (0, h, 0), 2)  # south wall
    b.quad((0, 0, 6), (0, h, 6), (12, h, 6), (12, 0, 6), 2)  # north wall
    b.quad((0, 0, 0), (0, h, 0), (0, h, 6), (0, 0, 6), 2)  # west wall
    far = b.quad((12, 0, 2.0), (12, h, 2.0), (12, h, 4.0), (12, 0, 4.0), 3, (200, 60, 60))
    b.quad((12, 0, 0), (12, h, 0), (12, h, 2.0), (12, 0, 2.0), 3, (200, 60, 60))
    b.quad((12, 0, 4.0), (12, h, 4.0), (12, h, 6), (12, 0, 6), 3, (200, 60, 60))
    # The dividing wall with its door, as a solid slab in three pieces.
    b.box((6.0, 0, 0), (6.2, h, 2.5), 4, (120, 160, 120))
    b.box((6.0, 0, 3.5), (6.2, h, 6), 4, (120, 160, 120))
    b.box((6.0, 2.2, 2.5), (6.2, h, 3.5), 4, (120, 160, 120))
    visible_box = b.box((2.0, 0, 1.0), (2.6, 0.8, 1.6), 5, (60, 60, 200))
    # Tucked into room B's south-west corner: every ray from the cell through the door passes
    # north of it (cell x <= 3.0, z in [2.6, 3.4]; door z >= 2.5 at x = 6.2).
    hidden_box = b.box((6.6, 0, 0.2), (7.2, 0.6, 0.8), 6, (200, 200, 60))
    scene = b.scene("two_rooms", offset)
    o = np.asarray(offset, dtype=np.float64)
    cell = Viewcell(np.array([[2.0, 1.5, 2.6], [3.0, 1.9, 3.4]]) + o)
    # The visible box's top face (its last quad) is seen from above by every eye in the cell.
    return scene, cell, {"visible": far[:1] + visible_box[10:12], "hidden": hidden_box}


def open_ring(n: int = 8, radius: float = 10.0):
    """``n`` upright quads on a ring around the cell, each in plain view: all are visible."""
    b = Builder()
    ids = []
    for k in range(n):
        a = 2 * np.pi * k / n
        c, s = np.cos(a), np.sin(a)
        t = np.array([-s, 0.0, c])  # tangent
        p = np.array([c, 0.0, s]) * radius
        w = 1.5
        ids += b.quad(p - w * t, p - w * t + [0, 3, 0], p + w * t + [0, 3, 0], p + w * t, k)
    scene = b.scene("open_ring")
    cell = Viewcell(np.array([[-1.0, 1.5, -1.0], [1.0, 1.9, 1.0]]))
    return scene, cell, {"visible": ids, "hidden": []}


def only_degenerate():
    """Faces that are all degenerate (zero area, repeated index, NaN): nothing is visible."""
    v = np.array([[0, 0, 5], [1, 0, 5], [2, 0, 5], [0, 1, 5], [np.nan, 0, 5], [0, 2, 5]], float)
    f = np.array([[0, 1, 2], [0, 0, 3], [4, 3, 5]])
    scene = Scene(v, f, name="degenerate")
    cell = Viewcell(np.array([[-1.0, -0.5, -1.0], [1.0, 0.5, 1.0]]))
    return scene, cell, {"visible": [], "hidden": [0, 1, 2]}


def empty():
    """A scene with no triangles at all."""
    scene = Scene(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), name="empty")
    cell = Viewcell(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    return scene, cell, {"visible": [], "hidden": []}


def stiff_cases(offset=(0.0, 0.0, 0.0)):
    """Stiff and extreme inputs around a cell, each with a known answer where there is one:
    a sliver of aspect ratio 1e6 in plain view, a triangle edge-on to the cell (its plane holds
    the cell's x axis), one whose plane is at the cell's eye height, coplanar overlapping
    triangles, intersecting triangles, a triangle crossing every near plane (it passes through
    the cell), a huge triangle, degenerate faces, and a box hidden behind a closed wall."""
    b = Builder()
    known: dict[str, list[int]] = {}
    known["sliver"] = b.quad((-2, 1.0, 8), (2, 1.0, 8), (2, 1.0 + 4e-6, 8), (-2, 1.0 + 4e-6, 8), 1)[
        :1
    ]
    # Edge-on: its plane z = -1 holds the cell's south side (a from-segment view segment).
    known["edge_on"] = b.quad((3, 1.7, -1), (5, 1.7, -1), (5, 2.7, -1), (3, 2.7, -1), 2)[:1]
    known["eye_plane"] = b.quad((-6, 1.7, -6), (-4, 1.7, -6), (-4, 1.7, -4), (-6, 1.7, -4), 3)
    known["coplanar"] = b.quad(
        (-3, 0, -8), (-1, 0, -8), (-1, 2, -8), (-3, 2, -8), 4, (250, 0, 0)
    ) + b.quad((-2.5, 0.5, -8), (-0.5, 0.5, -8), (-0.5, 2.5, -8), (-2.5, 2.5, -8), 5, (0, 250, 0))
    known["intersecting"] = b.quad((1, 0, -9), (4, 0, -9), (4, 3, -7), (1, 3, -7), 6) + b.quad(
        (1, 3, -9), (4, 3, -9), (4, 0, -7), (1, 0, -7), 7
    )
    # Through the cell: crosses the near plane of every camera in the cell.
    known["through_cell"] = [
        b.quad((-0.2, 0.0, -0.3), (0.2, 0.0, -0.3), (0.2, 3.0, 0.3), (-0.2, 3.0, 0.3), 8)[0]
    ]
    known["huge"] = b.quad(
        (-1e4, -1.0, -1e4), (1e4, -1.0, -1e4), (1e4, -1.0, 1e4), (-1e4, -1.0, 1e4), 9, (60, 120, 60)
    )[:1]
    # A closed room of walls around a hidden box, away from the cell.
    room = b.box((20, 0, -2), (26, 3, 4), 10, (130, 130, 130))
    known["hidden"] = b.box((22, 0.5, 0), (23, 1.5, 1), 11, (255, 0, 255))
    known["room"] = room
    scene = b.scene("stiff", offset)
    # Degenerate faces appended last (ids after every case above).
    n = scene.n_vertices
    extra_v = np.array([[0, 0, 12], [1, 0, 12], [2, 0, 12], [np.inf, 0, 12]]) + np.asarray(offset)
    v = np.concatenate([scene.vertices, extra_v])
    f = np.concatenate([scene.faces, [[n, n + 1, n + 2], [n, n, n + 1], [n, n + 1, n + 3]]])
    m = scene.n_triangles
    known["degenerate"] = [m, m + 1, m + 2]
    scene = Scene(
        v,
        f,
        np.concatenate([scene.object_ids, [12, 12, 12]]),
        np.concatenate([scene.colors, np.full((3, 3), 90, np.uint8)]),
        name="stiff",
    )
    o = np.asarray(offset, dtype=np.float64)
    cell = Viewcell(np.array([[-1.0, 1.5, -1.0], [1.0, 1.9, 1.0]]) + o)
    # The sliver is in plain view but far thinner than a pixel: sampling cannot be held to it.
    known["visible"] = (
        known["coplanar"][:1]
        + known["intersecting"][:1]
        + known["huge"]
        + known["through_cell"]
    )
    return scene, cell, known


def city_blocks(offset=(0.0, 0.0, 0.0)):
    """A 2.5D scene (closed boxes standing on a ground quad) around a 10 m cell at the origin,
    one designed case per side:

    * +z, a wall between: a 120 m long, 15 m high block; a small box behind it is hidden.
    * -z, a gap between two buildings: two 15 m high blocks 2 m apart; the box behind the gap
      shows its near face through it.
    * +x, occluder fusion: three 8 m blocks side by side, none of which alone hides the low box
      behind them; together they do.
    * -x, a tall building behind a low one: a 4 m high block hides a 2 m box behind it but not
      the 40 m tower further back, whose near face rises above it.

    ``known`` also names each case's ids ("wall_hidden", "gap_visible", "fusion_hidden",
    "tall_visible", "low_hidden")."""
    b = Builder()
    b.quad((-150, 0, -150), (-150, 0, 150), (150, 0, 150), (150, 0, -150), 0, (90, 110, 80))
    # +z: a wall between.
    b.box((-60, 0, 20), (60, 15, 22), 1)
    wall_hidden = b.box((-3, 0, 40), (3, 5, 44), 2, (200, 60, 60))
    # -z: a gap between two buildings.
    b.box((-60, 0, -22), (-1, 15, -20), 3)
    b.box((1, 0, -22), (60, 15, -20), 4)
    gap_target = b.box((-1, 0, -44), (1, 5, -40), 5, (60, 200, 60))
    # +x: occluder fusion.
    for k, (z0, z1) in enumerate(((-12, -4), (-4, 4), (4, 12))):
        b.box((20, 0, z0), (24, 15, z1), 6 + k)
    fusion_hidden = b.box((40, 0, -1), (42, 5, 1), 9, (60, 60, 200))
    # -x: a tall building behind a low one.
    b.box((-24, 0, -15), (-20, 4, 15), 10)
    low_hidden = b.box((-34, 0, -1), (-32, 2, 1), 11, (200, 200, 60))
    tower = b.box((-44, 0, -3), (-40, 40, 3), 12, (120, 120, 200))
    scene = b.scene("city_blocks", offset)
    scene.meta["is_2_5d"] = None  # decided from the geometry, as for a loaded tile
    o = np.asarray(offset, dtype=np.float64)
    cell = Viewcell(np.array([[-5.0, 1.5, -5.0], [5.0, 1.9, 5.0]]) + o)
    # Box faces: z0, z1, x0, x1, y0, y1 quads. The gap box's z1 face (z = -40) faces the cell;
    # the tower's x1 face (x = -40) faces it, and its upper part shows over the low block.
    known = {"wall_hidden": wall_hidden, "gap_visible": gap_target[2:4],
             "fusion_hidden": fusion_hidden, "tall_visible": tower[6:8],
             "low_hidden": low_hidden}
    known["visible"] = known["gap_visible"] + known["tall_visible"]
    known["hidden"] = known["wall_hidden"] + known["fusion_hidden"] + known["low_hidden"]
    return scene, cell, known
