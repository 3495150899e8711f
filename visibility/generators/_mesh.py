"""Vectorized mesh building blocks shared by the scene generators.

Everything here works on batches (many patches, swept solids, boxes or blobs at once) with no
Python loop over triangles. Conventions follow visibility/raster/camera.py: Y-up,
right-handed, metres. A triangle (a, b, c) faces where ``(b - a) x (c - a)`` points; closed
solids face outward.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from visibility.scene import Scene

#: Smallest and largest triangle budget a generator accepts.
MIN_TRIANGLES = 1_000
MAX_TRIANGLES = 50_000_000
#: Direction of the light baked into face colours (so faces of different orientation differ).
LIGHT_DIR = np.array([0.35, 1.0, 0.55]) / np.linalg.norm([0.35, 1.0, 0.55])
#: Faces per block of the per-face passes (colour conversion, shading, solid tessellation):
#: their float64 and int64 temporaries stay a few tens of MB whatever the mesh's size.
FACE_BLOCK = 1 << 18


def check_request(triangles: int, seed: int) -> tuple[int, int]:
    """Validate a generator's ``triangles`` and ``seed``; return them as ints.

    Raises ValueError for non-integers, budgets outside [MIN_TRIANGLES, MAX_TRIANGLES] or a
    negative seed.
    """
    if isinstance(triangles, bool) or not isinstance(triangles, (int, np.integer)):
        raise ValueError(f"triangles must be an integer, got {triangles!r}")
    if not MIN_TRIANGLES <= int(triangles) <= MAX_TRIANGLES:
        raise ValueError(
            f"triangles must be in [{MIN_TRIANGLES}, {MAX_TRIANGLES}], got {triangles}"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or int(seed) < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(triangles), int(seed)


def to_rgb(values: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 colours from float RGB in [0, 255] (clipped, rounded); many rows are
    converted FACE_BLOCK rows at a time (no whole float64 copy of a mesh's colours)."""
    values = np.asarray(values)
    if values.ndim < 2 or len(values) <= FACE_BLOCK:
        return np.clip(np.rint(np.asarray(values, dtype=np.float64)), 0, 255).astype(np.uint8)
    out = np.empty(values.shape, dtype=np.uint8)
    for s in range(0, len(values), FACE_BLOCK):
        out[s:s + FACE_BLOCK] = to_rgb(values[s:s + FACE_BLOCK])
    return out


def vary(rgb: np.ndarray, rng: np.random.Generator, n: int, amount: float = 0.12) -> np.ndarray:
    """(n, 3) float colours: ``rgb`` (3,) with a random brightness and slight hue jitter each."""
    base = np.asarray(rgb, dtype=np.float64).reshape(1, 3)
    bright = rng.uniform(1.0 - amount, 1.0 + amount, size=(n, 1))
    hue = rng.uniform(1.0 - amount / 3, 1.0 + amount / 3, size=(n, 3))
    return base * bright * hue


# ----------------------------------------------------------------------------------- assembly
class MeshParts:
    """Accumulates mesh pieces (vertices, local faces, object ids, colours); joins them once.

    Pieces are kept in their final dtypes (int32 faces, int32 object ids, uint8 colours), so a
    generator that adds its mesh in pieces holds little more than the finished scene."""

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self._obj: list[np.ndarray] = []
        self._rgb: list[np.ndarray] = []
        self.n_vertices = 0
        self.n_faces = 0

    def add(self, verts: np.ndarray, faces: np.ndarray, obj, rgb) -> np.ndarray:
        """Append a piece; return the (m,) int64 triangle ids it received.

        verts (n, 3) metres; faces (m, 3) indices into ``verts``; obj scalar or (m,) object ids;
        rgb (3,) or (m, 3) colours (float or uint8, clipped to [0, 255]). ValueError when the
        vertices no longer fit int32 face indices.
        """
        verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        m = len(faces)
        if self.n_vertices + len(verts) >= 2**31 - 1:
            raise ValueError(f"too many vertices for int32 faces: "
                             f"{self.n_vertices + len(verts)}")
        self._verts.append(verts)
        self._faces.append((faces + self.n_vertices).astype(np.int32))
        self._obj.append(np.broadcast_to(np.asarray(obj, dtype=np.int64), (m,)).astype(np.int32))
        rgb = np.asarray(rgb)
        rgb = rgb if rgb.dtype == np.uint8 else to_rgb(rgb)
        self._rgb.append(np.broadcast_to(rgb, (m, 3)))
        ids = np.arange(self.n_faces, self.n_faces + m, dtype=np.int64)
        self.n_vertices += len(verts)
        self.n_faces += m
        return ids

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(vertices (n, 3) float64, faces (m, 3) int32, object ids (m,) int32, colours (m, 3)
        uint8). The pieces are handed over: each list is released as soon as it is joined (so
        the peak is the pieces plus one joined array), and the parts are empty afterwards."""
        if not self._faces:
            return (np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.int32),
                    np.zeros((0, 3), np.uint8))
        out = []
        for name, dtype in (("_verts", np.float64), ("_faces", np.int32), ("_obj", np.int32),
                            ("_rgb", np.uint8)):
            pieces = getattr(self, name)
            setattr(self, name, [])
            joined = np.concatenate(pieces)
            pieces.clear()
            out.append(joined if joined.dtype == dtype else joined.astype(dtype))
        self.n_vertices = self.n_faces = 0
        return out[0], out[1], out[2], out[3]


def _face_cross(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, ...]:
    """Components (nx, ny, nz) of (b - a) x (c - a) per face, computed column by column (much
    lighter on memory than np.cross over (m, 3) gathers)."""
    f = np.asarray(faces, dtype=np.int64)
    out = []
    cols = [verts[:, k] for k in range(3)]
    a = [c[f[:, 0]] for c in cols]
    e1 = [cols[k][f[:, 1]] - a[k] for k in range(3)]
    e2 = [cols[k][f[:, 2]] - a[k] for k in range(3)]
    with np.errstate(invalid="ignore", over="ignore"):
        out = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
               e1[0] * e2[1] - e1[1] * e2[0])
    return out


def shade_by_normal(verts: np.ndarray, faces: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """(m, 3) uint8 colours darkened by each face's angle to LIGHT_DIR.

    Baking a fixed light in keeps faces of different orientation distinguishable in flat-shaded
    images. Degenerate or non-finite faces keep their colour. Works through the faces in
    blocks of FACE_BLOCK (each face's colour depends on that face alone).
    """
    rgb = np.asarray(rgb)
    out = np.empty((len(faces), 3), dtype=np.uint8)
    for s in range(0, len(faces), FACE_BLOCK):
        nx, ny, nz = _face_cross(verts, faces[s:s + FACE_BLOCK])
        with np.errstate(invalid="ignore", over="ignore"):
            ln = np.sqrt(nx * nx + ny * ny + nz * nz)
            cos = (nx * LIGHT_DIR[0] + ny * LIGHT_DIR[1] + nz * LIGHT_DIR[2]) / np.where(
                ln > 0, ln, 1)
        factor = np.where(np.isfinite(cos) & (ln > 0), 0.62 + 0.38 * np.clip(cos, 0.0, 1.0), 1.0)
        out[s:s + len(nx)] = to_rgb(rgb[s:s + FACE_BLOCK].astype(np.float32)
                                    * factor[:, None].astype(np.float32))
    return out


def face_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3) unit normals (b - a) x (c - a); zero rows for degenerate faces."""
    n = np.stack(_face_cross(verts, faces), axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        ln = np.sqrt((n * n).sum(axis=1, keepdims=True))
        out = np.where(ln > 0, n / np.where(ln > 0, ln, 1.0), 0.0)
    return np.nan_to_num(out)


# ----------------------------------------------------------------------------------- patches
def patch_grid(
    origin: np.ndarray, u: np.ndarray, v: np.ndarray, nu: np.ndarray, nv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tessellate parallelograms ``origin + a u + b v`` (a, b in [0, 1]) into nu x nv quads each.

    origin, u, v: (p, 3) metres; nu, nv: (p,) ints >= 1. Each quad is two triangles facing
    ``u x v``; vertices are shared within a patch. Returns (verts (sum (nu+1)(nv+1), 3), faces
    (2 sum nu nv, 3), patch of each face, column iu and row iv of each face's quad).
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(-1, 3)
    u = np.asarray(u, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    p = len(origin)
    nu = np.broadcast_to(np.asarray(nu, dtype=np.int64), (p,))
    nv = np.broadcast_to(np.asarray(nv, dtype=np.int64), (p,))
    if p and (nu.min() < 1 or nv.min() < 1):
        raise ValueError("patch subdivisions must be >= 1")
    row = nu + 1
    nvert = row * (nv + 1)
    vstart = np.concatenate([[0], np.cumsum(nvert)[:-1]])
    pid_v = np.repeat(np.arange(p), nvert)
    local = np.arange(int(nvert.sum())) - vstart[pid_v]
    a = (local % row[pid_v]) / nu[pid_v]
    b = (local // row[pid_v]) / nv[pid_v]
    verts = origin[pid_v] + u[pid_v] * a[:, None] + v[pid_v] * b[:, None]
    nq = nu * nv
    qstart = np.concatenate([[0], np.cumsum(nq)[:-1]])
    pid_q = np.repeat(np.arange(p), nq)
    lq = np.arange(int(nq.sum())) - qstart[pid_q]
    iu = lq % nu[pid_q]
    iv = lq // nu[pid_q]
    r = row[pid_q]
    v00 = vstart[pid_q] + iv * r + iu
    faces = np.empty((2 * len(lq), 3), dtype=np.int64)
    faces[0::2, 0] = v00
    faces[0::2, 1] = v00 + 1
    faces[0::2, 2] = v00 + r + 1
    faces[1::2, 0] = v00
    faces[1::2, 1] = v00 + r + 1
    faces[1::2, 2] = v00 + r
    return verts, faces, np.repeat(pid_q, 2), np.repeat(iu, 2), np.repeat(iv, 2)


def grid_xz(
    x_edges: np.ndarray, z_edges: np.ndarray, y: float, up: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A horizontal rectilinear grid at height ``y`` over the given X and Z edge coordinates.

    Returns (verts, faces facing +Y (or -Y when ``up`` is False), ix, iz): the cell column and
    row of each face. Vertices are shared.
    """
    xe = np.asarray(x_edges, dtype=np.float64)
    ze = np.asarray(z_edges, dtype=np.float64)
    nx, nz = len(xe) - 1, len(ze) - 1
    if nx < 1 or nz < 1:
        raise ValueError("a grid needs at least two edges per axis")
    xx, zz = np.meshgrid(xe, ze, indexing="xy")  # (nz+1, nx+1)
    verts = np.stack([xx.ravel(), np.full(xx.size, float(y)), zz.ravel()], axis=1)
    iz, ix = np.meshgrid(np.arange(nz), np.arange(nx), indexing="ij")
    ix, iz = ix.ravel(), iz.ravel()
    v00 = iz * (nx + 1) + ix
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    # (v00, v01, v11) faces +Y: (dz) x (dx + dz) has a positive Y component.
    t0 = np.stack([v00, v01, v11], axis=1)
    t1 = np.stack([v00, v11, v10], axis=1)
    faces = np.empty((2 * len(v00), 3), dtype=np.int64)
    faces[0::2], faces[1::2] = t0, t1
    if not up:
        faces = faces[:, ::-1]
    return verts, faces, np.repeat(ix, 2), np.repeat(iz, 2)


def subdivide(breaks: np.ndarray, step: float) -> np.ndarray:
    """Sorted edge coordinates: the unique ``breaks`` with each gap split into equal pieces no
    longer than ``step`` metres."""
    b = np.unique(np.asarray(breaks, dtype=np.float64))
    gaps = np.diff(b)
    n = np.maximum(1, np.ceil(gaps / step - 1e-9)).astype(np.int64)
    gi = np.repeat(np.arange(len(gaps)), n)
    k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    inner = b[gi] + gaps[gi] * (k / n[gi])
    return np.concatenate([inner, b[-1:]])


def subdivide_count(breaks: np.ndarray, step: float) -> int:
    """Number of pieces ``subdivide(breaks, step)`` makes."""
    gaps = np.diff(np.unique(np.asarray(breaks, dtype=np.float64)))
    return int(np.maximum(1, np.ceil(gaps / step - 1e-9)).sum())


def fit_grid_step(
    x_breaks: np.ndarray, z_breaks: np.ndarray, target_tris: float, lo: float, hi: float
) -> float:
    """The tile step in [lo, hi] metres whose ``grid_xz(subdivide(...))`` triangle count is
    closest to ``target_tris`` (the count falls as the step grows)."""

    def tris(s: float) -> int:
        return 2 * subdivide_count(x_breaks, s) * subdivide_count(z_breaks, s)

    a, b = float(lo), float(hi)
    for _ in range(50):
        mid = np.sqrt(a * b)
        if tris(mid) > target_tris:
            a = mid
        else:
            b = mid
    return a if abs(tris(a) - target_tris) < abs(tris(b) - target_tris) else b


def fit_plan(triangles: int, make, guess: float, share: float, step_range: tuple[float, float],
             tries: int = 12):
    """Choose a layout size and a floor/ground tile step that together meet a triangle budget.

    ``make(n1, n2)`` builds a layout of n1 x n2 units and returns (payload, fixed triangles,
    x breaks, z breaks, grids): the tiled surfaces are ``grids`` rectilinear grids over those
    breaks. The unit count starts at ``guess`` and is rescaled until the tiles can take about
    ``share`` of the budget (within [0.5, 1.6] x share) with a step in ``step_range``.
    Returns (payload, step, total triangles).
    """
    def tiles(xb, zb, grids, step: float) -> int:
        return grids * 2 * subdivide_count(xb, step) * subdivide_count(zb, step)

    target = triangles * (1 - share)
    units = max(1.0, float(guess))
    best = None
    seen: dict[tuple[int, int], tuple] = {}
    for _ in range(tries):
        n1 = max(1, int(round(np.sqrt(units))))
        n2 = max(1, int(round(units / n1)))
        if (n1, n2) not in seen:
            seen[(n1, n2)] = make(n1, n2)
        payload, fixed, xb, zb, grids = seen[(n1, n2)]
        rest = triangles - fixed
        step = fit_grid_step(xb, zb, max(rest, 0) / grids, *step_range)
        total = fixed + tiles(xb, zb, grids, step)
        ok = (max(tiles(xb, zb, grids, step_range[1]), 0.5 * share * triangles) <= rest
              <= min(tiles(xb, zb, grids, step_range[0]), 1.6 * share * triangles))
        # A ground within its share beats a closer total reached by an odd ground.
        err = abs(total - triangles) + (0 if ok else triangles)
        if best is None or err < best[0]:
            best = (err, payload, step, total)
        if ok:
            break
        units = max(1.0, units * target / max(fixed, 1))
    return best[1], best[2], best[3]


# ----------------------------------------------------------------------------------- solids
@dataclass
class Solids:
    """A batch of swept solids: a planar profile polygon moved along a straight vector.

    Point ``(p, q)`` of solid i's profile at sweep parameter s in [0, 1] is
    ``origin[i] + p a[i] + q b[i] + s t[i]`` (a, b unit vectors; profile coordinates in metres).
    ``pts`` holds every profile, solid i's run starting at ``start[i]`` with ``k[i]`` points.
    Side walls are tessellated into ``round(edge / step)`` columns and ``nv`` rows; ``cap0`` /
    ``cap1`` add fan caps (convex profiles only) at s = 0 / s = 1.
    """

    pts: np.ndarray
    k: np.ndarray
    origin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    t: np.ndarray
    step: np.ndarray
    nv: np.ndarray
    cap0: np.ndarray
    cap1: np.ndarray
    obj: np.ndarray
    tag: np.ndarray

    @property
    def start(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.k)[:-1]]).astype(np.int64)

    def __len__(self) -> int:
        return int(len(self.k))


class SolidBatch:
    """Collects solids (single or many with the same point count) and freezes them to Solids."""

    def __init__(self) -> None:
        self._cols: dict[str, list[np.ndarray]] = {
            name: [] for name in ("pts", "k", "origin", "a", "b", "t", "step", "nv", "cap0",
                                  "cap1", "obj", "tag")
        }
        self.count = 0

    def add(self, profiles, origin, a, b, t, *, obj, step=np.inf, nv=1, cap0=False, cap1=True,
            tag=0) -> np.ndarray:
        """Add n solids. ``profiles`` (n, k, 2) or (k, 2); vectors (n, 3) or (3,); scalars or
        (n,) for the rest. Returns the (n,) indices of the new solids."""
        prof = np.asarray(profiles, dtype=np.float64)
        if prof.ndim == 2:
            prof = prof[None]
        n, k = prof.shape[:2]
        if k < 3:
            raise ValueError("a profile needs at least 3 points")

        def vec(x):
            return np.broadcast_to(np.asarray(x, dtype=np.float64).reshape(-1, 3), (n, 3))

        def col(x, dtype):
            return np.broadcast_to(np.asarray(x, dtype=dtype).reshape(-1), (n,))

        c = self._cols
        c["pts"].append(prof.reshape(-1, 2))
        c["k"].append(np.full(n, k, dtype=np.int64))
        c["origin"].append(vec(origin))
        c["a"].append(vec(a))
        c["b"].append(vec(b))
        c["t"].append(vec(t))
        c["step"].append(col(step, np.float64))
        c["nv"].append(np.maximum(1, col(nv, np.int64)))
        c["cap0"].append(col(cap0, bool))
        c["cap1"].append(col(cap1, bool))
        c["obj"].append(col(obj, np.int64))
        c["tag"].append(col(tag, np.int64))
        idx = np.arange(self.count, self.count + n)
        self.count += n
        return idx

    def freeze(self) -> Solids:
        if self.count == 0:
            z3 = np.zeros((0, 3))
            zi = np.zeros(0, dtype=np.int64)
            zb = np.zeros(0, dtype=bool)
            return Solids(np.zeros((0, 2)), zi, z3, z3, z3, z3, np.zeros(0), zi, zb, zb, zi, zi)
        arrays = {name: np.concatenate(parts) for name, parts in self._cols.items()}
        return Solids(**arrays)


def _solid_edges(s: Solids):
    """Per profile edge: solid index, local index, endpoints (oriented so side walls face out)."""
    start = s.start
    se = np.repeat(np.arange(len(s)), s.k)
    j = np.arange(len(s.pts)) - start[se]
    nxt = start[se] + (j + 1) % s.k[se]
    pa, pb = s.pts[start[se] + j], s.pts[nxt]
    # Shoelace sign of each profile times the handedness of (a, b, t) says which way walls face.
    cross = pa[:, 0] * pb[:, 1] - pb[:, 0] * pa[:, 1]
    sigma = np.bincount(se, weights=cross, minlength=len(s))
    hand = np.einsum("ij,ij->i", np.cross(s.a, s.b), s.t)
    flip = (sigma * hand < 0)[se]
    pa, pb = np.where(flip[:, None], pb, pa), np.where(flip[:, None], pa, pb)
    return se, j, pa, pb


def _edge_columns(s: Solids, se: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    d = pb - pa
    length = np.linalg.norm(d[:, :1] * s.a[se] + d[:, 1:] * s.b[se], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = np.where(np.isfinite(s.step[se]), np.rint(length / s.step[se]), 1.0)
    return np.clip(np.nan_to_num(n, nan=1.0), 1, 100_000).astype(np.int64)


def solids_count(s: Solids) -> np.ndarray:
    """(b,) int64 number of triangles ``solids_mesh`` makes for each solid."""
    if len(s) == 0:
        return np.zeros(0, dtype=np.int64)
    se, _, pa, pb = _solid_edges(s)
    nu = _edge_columns(s, se, pa, pb)
    walls = 2 * np.bincount(se, weights=nu * s.nv[se], minlength=len(s)).astype(np.int64)
    return walls + (s.k - 2) * (s.cap0.astype(np.int64) + s.cap1.astype(np.int64))


@dataclass
class SolidMesh:
    """Triangles of a Solids batch with, per face: solid index, kind (0 side wall, 1 cap at
    s = 1, 2 cap at s = 0), profile edge (side walls; -1 on caps), column iu and row iv, and the
    number of columns nu of its wall (1 on caps)."""

    verts: np.ndarray
    faces: np.ndarray
    solid: np.ndarray
    kind: np.ndarray
    edge: np.ndarray
    iu: np.ndarray
    iv: np.ndarray
    nu: np.ndarray


def _runs(counts: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive [i0, i1) ranges of ``counts`` whose sums stay within ``limit`` (a range holds
    at least one item, so a single item over the limit gets a range of its own)."""
    n = len(counts)
    cum = np.concatenate([[0], np.cumsum(counts)])
    runs = []
    i0 = 0
    while i0 < n:
        i1 = int(np.searchsorted(cum, cum[i0] + limit, side="right")) - 1
        i1 = min(max(i1, i0 + 1), n)
        runs.append((i0, i1))
        i0 = i1
    return runs


def solids_mesh_parts(s: Solids, max_faces: int | None = None) -> Iterator[SolidMesh]:
    """``solids_mesh(s)`` in consecutive pieces of ``max_faces`` (default FACE_BLOCK)
    triangles or fewer (a single wall or cap over it comes whole): the side walls, then the caps
    at s = 1, then those at s = 0, each piece's faces indexing its own vertices. Joined in order
    (faces offset by the vertices before them) the pieces are exactly ``solids_mesh(s)``; a
    generator that colours and stores each piece as it comes never holds the whole mesh's
    int64 per-face arrays."""
    if len(s) == 0:
        return
    max_faces = FACE_BLOCK if max_faces is None else int(max_faces)
    se, j, pa, pb = _solid_edges(s)
    nu = _edge_columns(s, se, pa, pb)

    def to3(p, idx, sweep):
        return (s.origin[idx] + p[:, :1] * s.a[idx] + p[:, 1:] * s.b[idx]
                + sweep * s.t[idx])

    org = to3(pa, se, 0.0)
    u = to3(pb, se, 0.0) - org
    for e0, e1 in _runs(2 * nu * s.nv[se], max_faces):
        sl = slice(e0, e1)
        wv, wf, pid, iu, iv = patch_grid(org[sl], u[sl], s.t[se[sl]], nu[sl], s.nv[se[sl]])
        yield SolidMesh(wv, wf, se[e0 + pid], np.zeros(len(wf), np.int64), j[e0 + pid], iu, iv,
                        nu[e0 + pid])
    start = s.start
    hand = np.einsum("ij,ij->i", np.cross(s.a, s.b), s.t)
    for cap_kind, mask, sweep, sign in ((1, s.cap1, 1.0, 1.0), (2, s.cap0, 0.0, -1.0)):
        all_ids = np.flatnonzero(mask)
        for c0, c1 in _runs(s.k[all_ids] - 2, max_faces):
            ids = all_ids[c0:c1]
            k = s.k[ids]
            pidx = np.repeat(start[ids], k) + (np.arange(int(k.sum()))
                                               - np.repeat(np.cumsum(k) - k, k))
            cv = to3(s.pts[pidx], np.repeat(ids, k), sweep)
            vbase = np.repeat(np.cumsum(k) - k, k - 2)  # first cap vertex of each fan triangle
            ntri = k - 2
            jj = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
            tri = np.stack([vbase, vbase + jj, vbase + jj + 1], axis=1)
            owner = np.repeat(ids, ntri)
            p0, p1, p2 = (s.pts[pidx][tri[:, c]] for c in range(3))
            c2 = (p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1]) - (p1[:, 1] - p0[:, 1]) * (
                p2[:, 0] - p0[:, 0])
            flip = c2 * hand[owner] * sign < 0
            tri[flip] = tri[flip][:, ::-1]
            m = len(tri)
            yield SolidMesh(cv, tri, owner, np.full(m, cap_kind, np.int64),
                            np.full(m, -1, np.int64), np.zeros(m, np.int64),
                            np.zeros(m, np.int64), np.ones(m, np.int64))


def solids_mesh(s: Solids) -> SolidMesh:
    """Tessellate a Solids batch (see ``Solids``); side walls face outward, caps face +-t.
    The pieces of ``solids_mesh_parts`` joined."""
    parts = list(solids_mesh_parts(s))
    if not parts:
        z = np.zeros(0, dtype=np.int64)
        return SolidMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), z, z, z, z, z, z)
    offsets = np.cumsum([0] + [len(p.verts) for p in parts[:-1]])
    return SolidMesh(np.concatenate([p.verts for p in parts]),
                     np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]),
                     *(np.concatenate([getattr(p, name) for p in parts])
                       for name in ("solid", "kind", "edge", "iu", "iv", "nu")))


def solid_caps(s: Solids, ids: np.ndarray, tri: np.ndarray, at_end: bool):
    """Caps of non-convex solids from a triangulation of their profile.

    ``ids`` (c,) solids sharing one point count k; ``tri`` (q, 3) indices into that profile.
    Returns (verts, faces, owner solid per face), facing +t at s = 1 (``at_end``) or -t at s = 0.
    """
    ids = np.asarray(ids, dtype=np.int64)
    tri = np.asarray(tri, dtype=np.int64)
    if len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    k = int(s.k[ids[0]])
    if np.any(s.k[ids] != k):
        raise ValueError("solid_caps needs solids with the same point count")
    prof = s.pts[s.start[ids][:, None] + np.arange(k)[None]]  # (c, k, 2)
    sweep = 1.0 if at_end else 0.0
    verts = (s.origin[ids, None] + prof[..., :1] * s.a[ids, None] + prof[..., 1:] * s.b[ids, None]
             + sweep * s.t[ids, None]).reshape(-1, 3)
    p0, p1, p2 = prof[:, tri[:, 0]], prof[:, tri[:, 1]], prof[:, tri[:, 2]]  # (c, q, 2)
    c2 = (p1[..., 0] - p0[..., 0]) * (p2[..., 1] - p0[..., 1]) - (p1[..., 1] - p0[..., 1]) * (
        p2[..., 0] - p0[..., 0])
    hand = np.einsum("ij,ij->i", np.cross(s.a[ids], s.b[ids]), s.t[ids])
    flip = c2 * hand[:, None] * (1.0 if at_end else -1.0) < 0
    faces = np.broadcast_to(tri, (len(ids),) + tri.shape).copy()
    faces[flip] = faces[flip][:, ::-1]
    faces = (faces + k * np.arange(len(ids))[:, None, None]).reshape(-1, 3)
    return verts, faces, np.repeat(ids, len(tri))


def rect_profile(x0, z0, x1, z1) -> np.ndarray:
    """(n, 4, 2) rectangle profiles from corner arrays (any orientation works for solids)."""
    x0, z0, x1, z1 = (np.atleast_1d(np.asarray(c, dtype=np.float64)) for c in (x0, z0, x1, z1))
    return np.stack([np.stack([x0, z0], -1), np.stack([x1, z0], -1), np.stack([x1, z1], -1),
                     np.stack([x0, z1], -1)], axis=1)


# ----------------------------------------------------------------------------------- boxes
def _box_template() -> np.ndarray:
    corners = np.array([[(j >> 0) & 1, (j >> 1) & 1, (j >> 2) & 1] for j in range(8)], float)
    quads = [(0, 2, 6, 4), (1, 3, 7, 5), (0, 1, 5, 4), (2, 3, 7, 6), (0, 1, 3, 2), (4, 5, 7, 6)]
    tris = []
    for q in quads:
        for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3])):
            a, b, c = corners[list(t)]
            n = np.cross(b - a, c - a)
            out = (a + b + c) / 3 - 0.5
            tris.append(t if n @ out > 0 else t[::-1])
    return np.array(tris, dtype=np.int64)


#: (12, 3) outward box triangles over corners j = (x bit 0, y bit 1, z bit 2); pairs in the
#: order -x, +x, -y, +y, -z, +z.
BOX_FACES = _box_template()
BOX_SIDE = np.repeat(np.arange(6), 2)


def box_mesh(lo: np.ndarray, hi: np.ndarray, bottom: bool = True):
    """Axis-aligned boxes [lo, hi] (b, 3) metres as outward triangles sharing 8 corners each.

    Returns (verts (8b, 3), faces, box index per face, side per face: 0 -x, 1 +x, 2 -y, 3 +y,
    4 -z, 5 +z). ``bottom=False`` leaves out the -y faces (boxes standing on something).
    """
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    n = len(lo)
    bits = np.array([[(j >> 0) & 1, (j >> 1) & 1, (j >> 2) & 1] for j in range(8)], bool)
    verts = np.where(bits[None], hi[:, None], lo[:, None]).reshape(-1, 3)
    keep = np.ones(12, bool) if bottom else BOX_SIDE != 2
    tpl, side = BOX_FACES[keep], BOX_SIDE[keep]
    faces = (tpl[None] + 8 * np.arange(n)[:, None, None]).reshape(-1, 3)
    return verts, faces, np.repeat(np.arange(n), len(tpl)), np.tile(side, n)


def box_count(n: int, bottom: bool = True) -> int:
    return int(n) * (12 if bottom else 10)


# ----------------------------------------------------------------------------------- blobs
@lru_cache(maxsize=8)
def icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    """(verts on the unit sphere, outward faces) of an icosahedron subdivided ``level`` times
    (20 * 4**level triangles)."""
    g = (1 + 5**0.5) / 2
    v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                  [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(int(level)):
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        key = np.sort(e, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        mid = v[uniq].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = len(f)
        ab, bc, ca = (inv[i * m:(i + 1) * m] + len(v) for i in range(3))
        v = np.concatenate([v, mid])
        f = np.concatenate([
            np.stack([f[:, 0], ab, ca], 1), np.stack([ab, f[:, 1], bc], 1),
            np.stack([ca, bc, f[:, 2]], 1), np.stack([ab, bc, ca], 1)])
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = np.einsum("ij,ij->i", n, v[f].mean(axis=1)) < 0
    f[flip] = f[flip][:, ::-1]
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def blob_mesh(centers: np.ndarray, radii: np.ndarray, level: int, rng: np.random.Generator,
              roughness: float = 0.12):
    """Lumpy closed blobs: unit icospheres scaled by ``radii`` (b, 3) around ``centers`` (b, 3)
    with each vertex pushed radially by a random factor in [1 - roughness, 1 + roughness].

    Returns (verts, outward faces, blob index per face).
    """
    tv, tf = icosphere(level)
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1, 3)
    b = len(centers)
    bump = rng.uniform(1 - roughness, 1 + roughness, size=(b, len(tv), 1))
    verts = (centers[:, None] + tv[None] * radii[:, None] * bump).reshape(-1, 3)
    faces = (tf[None] + len(tv) * np.arange(b)[:, None, None]).reshape(-1, 3)
    return verts, faces, np.repeat(np.arange(b), len(tf))


# ----------------------------------------------------------------------------------- checks
def tri_box_overlap(tris: np.ndarray, center: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(m,) bool: which triangles (m, 3, 3) intersect the closed box ``center +- half``.

    Exact separating-axis test (box axes, triangle normal, 9 edge cross products).
    """
    v = np.asarray(tris, dtype=np.float64) - np.asarray(center, dtype=np.float64)
    h = np.asarray(half, dtype=np.float64)
    sep = np.zeros(len(v), dtype=bool)
    for ax in range(3):
        sep |= (v[:, :, ax].min(axis=1) > h[ax]) | (v[:, :, ax].max(axis=1) < -h[ax])
    e = [v[:, 1] - v[:, 0], v[:, 2] - v[:, 1], v[:, 0] - v[:, 2]]
    axes = [np.cross(e[0], e[1])]
    for ei in e:
        for k in range(3):
            unit = np.zeros(3)
            unit[k] = 1.0
            axes.append(np.cross(ei, unit))
    for a in axes:
        p = np.einsum("mjk,mk->mj", v, a)
        r = np.abs(a) @ h
        sep |= (p.min(axis=1) > r) | (p.max(axis=1) < -r)
    return ~sep


def triangles_in_boxes(scene: Scene, boxes: np.ndarray) -> np.ndarray:
    """Sorted ids of valid triangles that intersect any of the closed boxes (b, 2, 3)
    [min, max] (metres). Small triangles are found through a uniform XZ hash of their
    bounding boxes; big ones are checked against every box."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)
    ids = np.flatnonzero(scene.valid_faces)
    if len(ids) == 0 or len(boxes) == 0:
        return np.zeros(0, dtype=np.int64)
    tris = scene.triangles(ids)
    bmin, bmax = tris.min(axis=1), tris.max(axis=1)
    g = 8.0
    small = np.all(bmax[:, [0, 2]] - bmin[:, [0, 2]] <= g, axis=1)
    org = bmin[:, [0, 2]].min(axis=0)
    cell = np.floor((bmin[:, [0, 2]] - org) / g).astype(np.int64)
    ncz = int(cell[:, 1].max()) + 3
    key = cell[:, 0] * ncz + cell[:, 1]
    sm = np.flatnonzero(small)
    order = sm[np.argsort(key[sm], kind="stable")]
    keys = key[order]
    big = np.flatnonzero(~small)
    bad: list[np.ndarray] = []
    for lo, hi in boxes:
        if np.any(hi < lo):
            continue
        c0 = np.floor((lo[[0, 2]] - g - org) / g).astype(np.int64)
        c1 = np.floor((hi[[0, 2]] - org) / g).astype(np.int64)
        cz0, cz1 = max(c0[1], 0), min(c1[1], ncz - 1)
        parts = [big]
        for cx in range(max(c0[0], 0), max(c1[0] + 1, 0)):
            i0, i1 = np.searchsorted(keys, [cx * ncz + cz0, cx * ncz + cz1 + 1])
            parts.append(order[i0:i1])
        cand = np.concatenate(parts)
        cand = cand[np.all((bmin[cand] <= hi) & (bmax[cand] >= lo), axis=1)]
        if len(cand):
            # Relative to the box centre: exact enough far from the origin.
            hit = tri_box_overlap(tris[cand], (lo + hi) / 2, (hi - lo) / 2)
            bad.append(ids[cand[hit]])
    return np.unique(np.concatenate(bad)) if bad else np.zeros(0, dtype=np.int64)


def walk_violations(scene: Scene, low: float = 0.1, high: float = 2.0,
                    margin: float = 1e-3) -> np.ndarray:
    """Sorted triangle ids of valid faces that enter any walk rectangle's open space.

    The space of rect ``[x0, z0, x1, z1, floor, ...]`` is the box from ``floor + low`` to
    ``floor + high`` over the rectangle shrunk by ``margin`` metres (so walls standing exactly on
    the border do not count).
    """
    if scene.walk is None or len(scene.walk.rects) == 0:
        return np.zeros(0, dtype=np.int64)
    r = scene.walk.rects
    boxes = np.stack([np.stack([r[:, 0] + margin, r[:, 4] + low, r[:, 1] + margin], 1),
                      np.stack([r[:, 2] - margin, r[:, 4] + high, r[:, 3] - margin], 1)], 1)
    return triangles_in_boxes(scene, boxes)
