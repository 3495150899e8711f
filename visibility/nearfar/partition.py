"""Near-far partitioning (Popescu et al. 2022): the near / intermediate / far split of a scene
around a cell centre, the intermediate-region morph, and the far cubemap with per-pixel range.

Two vertical cylinders share the axis through the cubemap centre O, radii r1 < r2. A vertex's
region follows from its horizontal distance ρ from that axis: near (ρ ≤ r1), intermediate
(r1 < ρ < r2), far (ρ ≥ r2). Near and intermediate triangles travel as geometry; static far
triangles are baked into a cubemap rendered from O with colour and range (Euclidean distance
from O); dynamic far triangles travel as geometry and are displaced on the client. Triangles with
vertices on both sides of r2 (straddling) go both ways, so the seam has no hairline cracks.

Default radii. The server's cells are 4 m squares and O is a cell's centre, so the user U is at
most 2.83 m (horizontally) from O. r1 = 50 m keeps every street and room the user can walk to in
the next cells in the near region, and the 50 m wide intermediate band spreads the U-to-O
viewpoint change (at most 2.83 m, i.e. under 3.3 degrees at 50 m) over a wide band, so the morph
bends lines only gently. r2 = 100 m puts the whole generated ``rooms`` building (at most 86 m
from any cell centre at the default 100k triangles) inside r2, so an indoor scene needs no
cubemap, while a city (blocks of 55-95 m, streets 10-16 m) gets its distant blocks baked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from visibility.raster import render_cubemap
from visibility.raster.camera import DEFAULT_NEAR, cube_face_rotations, pixel_rays
from visibility.raster.hierarchy import ready_hierarchy
from visibility.raster.shading import BACKGROUND, shade_colors
from visibility.scene import Scene

_FACE_ROTS = cube_face_rotations()

#: Smallest and largest cubemap face resolution (pixels) a config accepts.
MIN_RESOLUTION, MAX_RESOLUTION = 16, 2048


@dataclass(frozen=True)
class NearFarConfig:
    """Radii (metres) of the near-far cylinders and the cubemap face resolution (pixels).

    Validated: ``0 < r1 < r2`` (finite) and ``MIN_RESOLUTION <= resolution <= MAX_RESOLUTION``;
    ValueError otherwise. See the module docstring for why the defaults suit 4 m cells.
    """

    r1: float = 50.0
    r2: float = 100.0
    resolution: int = 256

    def __post_init__(self) -> None:
        r1, r2 = float(self.r1), float(self.r2)
        if not (math.isfinite(r1) and math.isfinite(r2) and 0.0 < r1 < r2):
            raise ValueError(f"need finite radii 0 < r1 < r2, got r1={self.r1}, r2={self.r2}")
        res = self.resolution
        if isinstance(res, bool) or not isinstance(res, int | np.integer):
            raise ValueError(f"resolution must be an integer, got {res!r}")
        if not MIN_RESOLUTION <= int(res) <= MAX_RESOLUTION:
            raise ValueError(
                f"resolution must be in [{MIN_RESOLUTION}, {MAX_RESOLUTION}], got {res}"
            )
        object.__setattr__(self, "r1", r1)
        object.__setattr__(self, "r2", r2)
        object.__setattr__(self, "resolution", int(res))


@dataclass(frozen=True)
class NearFarSplit:
    """Triangle ids (int64, sorted, valid faces only) of each part of a near-far split.

    Attributes
    ----------
    near_ids : faces with a vertex at ρ < r2 (near + intermediate, static and dynamic,
        straddling included): what travels as geometry.
    far_static_ids : static faces with a vertex at ρ >= r2 (far + straddling): what is baked.
    far_dynamic_ids : moving faces with a vertex at ρ >= r2 in some keyframe: geometry displaced
        on the client.
    straddle_ids : static faces with vertices on both sides of r2 (in near_ids and baked).
    """

    near_ids: np.ndarray
    far_static_ids: np.ndarray
    far_dynamic_ids: np.ndarray
    straddle_ids: np.ndarray


@dataclass(frozen=True)
class FarCubemap:
    """The far region seen from O.

    Attributes
    ----------
    center : (3,) float64 O, metres.
    colors : (6, R, R, 3) uint8 shaded colour per texel (``BACKGROUND`` where empty).
    ranges : (6, R, R) float32 Euclidean distance from O in metres, +inf where empty.
    resolution : R, pixels per face side. Faces and texels follow ``visibility.raster.camera``
        (face order +X, -X, +Y, -Y, +Z, -Z, row 0 at the top).
    """

    center: np.ndarray
    colors: np.ndarray
    ranges: np.ndarray
    resolution: int


# --------------------------------------------------------------------------------- geometry
def _check_center(center: np.ndarray) -> np.ndarray:
    c = np.asarray(center, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center must be a finite 3-vector, got {center!r}")
    return c


def horizontal_distance(points: np.ndarray, center: np.ndarray) -> np.ndarray:
    """(n,) float64 distance ρ (metres) of ``points`` (n, 3) from the vertical axis through
    ``center`` (3,): the XZ distance (Y is up)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (n, 3), got {p.shape}")
    c = _check_center(center)
    return np.hypot(p[:, 0] - c[0], p[:, 2] - c[2])


def _moving_vertices(scene: Scene) -> np.ndarray:
    """(n,) bool: vertices whose position differs between the scene's keyframes."""
    if scene.states is None or scene.states.shape[0] < 2:
        return np.zeros(scene.n_vertices, dtype=bool)
    return np.any(scene.states != scene.states[:1], axis=(0, 2))


def _face_rho(scene: Scene, center: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per valid face: (face index, min ρ over its corners and keyframes, max ρ likewise)."""
    faces = np.flatnonzero(scene.valid_faces)
    f = scene.faces[faces]
    if scene.states is None or scene.states.shape[0] < 2:
        rho = horizontal_distance(scene.vertices, center)
        r = rho[f]
        return faces, r.min(axis=1), r.max(axis=1)
    c = _check_center(center)
    st = scene.states
    rho = np.hypot(st[..., 0] - c[0], st[..., 2] - c[2])  # (k, n)
    lo, hi = rho.min(axis=0), rho.max(axis=0)
    return faces, lo[f].min(axis=1), hi[f].max(axis=1)


def split_ids(scene: Scene, center: np.ndarray, cfg: NearFarConfig) -> NearFarSplit:
    """Partition the scene's valid faces around ``center`` (3,) by ``cfg.r2``.

    A face is near when some corner has ρ < r2 (in any keyframe for a moving face) and far when
    some corner has ρ >= r2; a static face that is both straddles (it goes into ``near_ids`` and
    is baked). Moving faces are never baked. See ``NearFarSplit``.
    """
    c = _check_center(center)
    faces, lo, hi = _face_rho(scene, c)
    moving_v = _moving_vertices(scene)
    dyn = np.any(moving_v[scene.faces[faces]], axis=1) if len(faces) else np.zeros(0, bool)
    near = lo < cfg.r2
    far = hi >= cfg.r2
    return NearFarSplit(
        near_ids=faces[near].astype(np.int64),
        far_static_ids=faces[far & ~dyn].astype(np.int64),
        far_dynamic_ids=faces[far & dyn].astype(np.int64),
        straddle_ids=faces[near & far & ~dyn].astype(np.int64),
    )


def needs_cubemap(scene: Scene, center: np.ndarray, cfg: NearFarConfig) -> bool:
    """True when some valid static face has a corner at ρ >= r2 around ``center`` (3,): only
    then is there anything to bake."""
    return bool(len(split_ids(scene, center, cfg).far_static_ids))


def morph(P: np.ndarray, U: np.ndarray, O: np.ndarray, r1: float, r2: float) -> np.ndarray:
    """(n, 3) float64 morphed positions Q of vertices ``P`` (n, 3) for viewpoint ``U`` (3,) and
    cubemap centre ``O`` (3,), radii r1 < r2 metres (the papers' README equations).

    Near (ρ <= r1): Q = P. Intermediate (r1 < ρ < r2): w_O = (ρ - r1) / (r2 - r1), w_U = 1 - w_O,
    d = normalize(w_U d_U + w_O d_O), t = w_U |P - U| + w_O |P - O|, Q = U + t d, with d_U, d_O
    the unit directions from U and O to P. Far (ρ >= r2): Q = U + (P - O). ρ is the horizontal
    distance from the axis through O. Continuous at ρ = r1 and ρ = r2.
    """
    P = np.asarray(P, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"P must be (n, 3), got {P.shape}")
    U = _check_center(U)
    O = _check_center(O)
    r1, r2 = float(r1), float(r2)
    if not (math.isfinite(r1) and math.isfinite(r2) and 0.0 < r1 < r2):
        raise ValueError(f"need finite radii 0 < r1 < r2, got r1={r1}, r2={r2}")
    rho = np.hypot(P[:, 0] - O[0], P[:, 2] - O[2])
    Q = P.copy()
    far = rho >= r2
    Q[far] = P[far] + (U - O)
    mid = (rho > r1) & ~far
    if np.any(mid):
        p = P[mid]
        w_o = ((rho[mid] - r1) / (r2 - r1))[:, None]
        w_u = 1.0 - w_o
        vu, vo = p - U, p - O
        lu = np.linalg.norm(vu, axis=1, keepdims=True)
        lo = np.linalg.norm(vo, axis=1, keepdims=True)  # >= ρ > r1 > 0
        # P at U (|P - U| = 0) has no direction from U; it is then seen from O alone.
        du = np.divide(vu, lu, out=np.zeros_like(vu), where=lu > 0)
        d = w_u * du + w_o * vo / lo
        ld = np.linalg.norm(d, axis=1, keepdims=True)
        # d_U = -d_O with w_U = w_O cancels out; P is then on the segment UO: keep it.
        ok = ld[:, 0] > 1e-12
        t = w_u * lu + w_o * lo
        q = p.copy()
        q[ok] = U + t[ok] * d[ok] / ld[ok]
        Q[mid] = q
    return Q


# --------------------------------------------------------------------------------- cubemap
def texel_directions(resolution: int) -> np.ndarray:
    """(6, R, R, 3) float64 world directions (not unit: camera-space z = -1) through the texel
    centres of a cubemap with identity base rotation (``visibility.raster.camera`` conventions)."""
    rays = pixel_rays(resolution, resolution)  # (R, R, 3)
    rots = _FACE_ROTS
    # World direction = R^T @ ray_cam (rows of R are the camera axes in world coordinates).
    return np.einsum("kji,rcj->krci", rots, rays)


def bake_cubemap(
    scene: Scene, center: np.ndarray, cfg: NearFarConfig, t: float | None = None
) -> FarCubemap:
    """Render the far static faces (straddling ones included) into a cubemap around ``center``.

    Depth and ids come from ``visibility.raster.render_cubemap``; a texel's colour is the
    ``shade_colors`` colour of its face (what the client's frames show for that face), its range
    the depth times the length of its camera-space ray (Euclidean distance from O, metres).
    ``t`` (seconds) picks the vertex positions of a dynamic scene (static faces do not move).
    """
    c = _check_center(center)
    split = split_ids(scene, c, cfg)
    res = cfg.resolution
    verts = scene.vertices if t is None else scene.vertices_at(float(t))
    mask = np.zeros(scene.n_triangles, dtype=bool)
    mask[split.far_static_ids] = True
    if len(split.far_static_ids):
        depth, ids = render_cubemap(verts, scene.faces, c, res, near=DEFAULT_NEAR, face_mask=mask,
                                    hierarchy=ready_hierarchy(scene))
    else:
        depth = np.full((6, res, res), np.inf, dtype=np.float32)
        ids = np.full((6, res, res), -1, dtype=np.int32)
    ray_len = np.linalg.norm(pixel_rays(res, res), axis=2)  # same for every face
    ranges = (depth.astype(np.float64) * ray_len[None]).astype(np.float32)
    colors = np.empty((6, res, res, 3), dtype=np.uint8)
    colors[:] = np.asarray(BACKGROUND, dtype=np.uint8)
    hit = ids >= 0
    if np.any(hit):
        # Shade only the faces that show up, once each.
        used, inv = np.unique(ids[hit], return_inverse=True)
        shaded = shade_colors(verts[scene.faces[used]], scene.colors[used])
        colors[hit] = shaded[inv]
    ranges[~hit] = np.inf
    return FarCubemap(center=c, colors=colors, ranges=ranges, resolution=res)


def cube_texels(dirs: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest texel (face (…,), row (…,), column (…,), int64) of world directions ``dirs``
    (…, 3) in a cubemap of ``resolution`` with identity base rotation. Zero or non-finite
    directions raise ValueError."""
    d = np.asarray(dirs, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"dirs must be (..., 3), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("dirs must be finite")
    a = np.abs(d)
    axis = np.argmax(a, axis=-1)  # ties: x before y before z, like the rasterizer's home view
    major = np.take_along_axis(a, axis[..., None], axis=-1)[..., 0]
    if np.any(major == 0):
        raise ValueError("dirs must be non-zero")
    comp = np.take_along_axis(d, axis[..., None], axis=-1)[..., 0]
    face = 2 * axis + (comp < 0)
    # Camera coordinates on the chosen face (rows of its rotation: right, up, back); the
    # forward component -c_z equals the major axis' magnitude.
    c = np.einsum("...ij,...j->...i", _FACE_ROTS[face], d)
    u = c[..., 0] / major  # ndc x in [-1, 1]
    v = c[..., 1] / major  # ndc y in [-1, 1]
    res = int(resolution)
    col = np.clip(np.floor((u + 1.0) * 0.5 * res), 0, res - 1).astype(np.int64)
    row = np.clip(np.floor((1.0 - v) * 0.5 * res), 0, res - 1).astype(np.int64)
    return face.astype(np.int64), row, col


def cubemap_lookup(cube: FarCubemap, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-texel colours (…, 3) uint8 and ranges (…,) float32 metres (+inf: nothing far) of
    world directions ``dirs`` (…, 3) (need not be unit) in ``cube``."""
    face, row, col = cube_texels(dirs, cube.resolution)
    return cube.colors[face, row, col], cube.ranges[face, row, col]
