"""Near-far composition of a client frame (Popescu et al. 2022, the papers' README equations).

What a frame is made of, for the user viewpoint U, the cubemap centre O and radii r1 < r2:

- geometry (the near triangles: near, intermediate and straddling ones, plus dynamic far ones),
  each vertex moved by ``visibility.nearfar.morph``: near vertices stay, intermediate vertices
  are morphed from U toward O, vertices beyond r2 (straddling corners, dynamic far objects) are
  displaced by Q = U + (P - O), so they land where the cubemap shows what O sees there;
- the cubemap as background, looked up per pixel with the pixel's world ray from U. The texel's
  surface is shown at U + r_O(dir) dir, so its view depth is r_O(dir) / |ray| (ray with z = -1);
- per pixel, geometry wins where its depth is nearer than the cubemap's. This is Eq. 3 of the
  paper (cull a fragment with |Q - U| > r_O(dir(Q - U))) applied after the depth test: the
  nearest fragment of a pixel failing it means every farther fragment fails it too.

``morph=False`` gives the conventional near-far compositing the paper compares against: the
geometry is drawn as it is from U (dynamic far objects included), and the cubemap is a plain
background behind it.

Shading: the renderer shades each triangle from its (morphed) corners; far displacement is a
translation and keeps normals, intermediate morphing turns faces slightly, so their colours may
differ from ground truth by a few levels.

Per-pixel surface points (``points``) say which original 3D point each pixel shows, for the
discontinuity metric δ: for geometry, the un-morphed point with the same barycentric coordinates
in its triangle as the pixel's morphed point (triangle ids from the CPU rasterizer
``visibility.raster.render_ids`` run on the morphed triangles); for cubemap pixels,
O + r_O(dir) dir. Pixels where the GL frame and the CPU raster disagree on coverage (triangle
edges, about 0.1 % of pixels) get NaN.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from visibility.nearfar import cube_texels
from visibility.nearfar import morph as morph_vertices
from visibility.raster import render_ids
from visibility.raster.camera import look_rotation, pixel_rays

#: ``ComposedFrame.source`` values.
SOURCE_EMPTY, SOURCE_GEOMETRY, SOURCE_CUBEMAP = 0, 1, 2


@dataclass(frozen=True)
class ComposedFrame:
    """One composed near-far frame.

    Attributes
    ----------
    color : (H, W, 3) uint8 RGB.
    depth : (H, W) float32 view depth (``-z_cam``, metres) of what each pixel shows: the morphed
        geometry's, or r_O / |ray| for cubemap pixels; +inf where empty.
    source : (H, W) uint8, SOURCE_EMPTY / SOURCE_GEOMETRY / SOURCE_CUBEMAP.
    points : (H, W, 3) float64 original world point each pixel shows (NaN where none or
        unknown), or None when not asked for.
    geometry_depth : (H, W) float32 depth of the geometry alone (before the cubemap), +inf empty.
    """

    color: np.ndarray
    depth: np.ndarray
    source: np.ndarray
    points: np.ndarray | None
    geometry_depth: np.ndarray


def _tris(tris: Any, colors: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    if tris is None:
        return np.zeros((0, 3, 3)), np.zeros((0, 3), dtype=np.uint8)
    t = np.asarray(tris, dtype=np.float64)
    if t.size == 0:
        t = t.reshape(0, 3, 3)
    if t.ndim != 3 or t.shape[1:] != (3, 3):
        raise ValueError(f"{name} must be (k, 3, 3), got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} must be finite")
    c = np.asarray(colors if colors is not None else np.zeros((0, 3)), dtype=np.uint8)
    if c.shape != (len(t), 3):
        raise ValueError(f"{name} colours must be ({len(t)}, 3), got {c.shape}")
    return t, c


def world_rays(rotation: np.ndarray, width: int, height: int, tan_x: float,
               tan_y: float) -> tuple[np.ndarray, np.ndarray]:
    """World directions (H, W, 3) of the pixel rays (camera-space z = -1, not unit) of a camera
    with world-to-camera ``rotation`` (3, 3), and their lengths (H, W)."""
    rays = pixel_rays(width, height, tan_x, tan_y)
    return rays @ np.asarray(rotation, dtype=np.float64), np.linalg.norm(rays, axis=2)


def _barycentric_points(
    q_tris: np.ndarray, p_tris: np.ndarray, ids: np.ndarray, x: np.ndarray
) -> np.ndarray:
    """Points (n, 3) with the barycentric coordinates in ``p_tris[ids]`` that points ``x``
    (n, 3) have in ``q_tris[ids]`` (x lies on that triangle's plane). NaN for degenerate ones."""
    q = q_tris[ids]
    v0, v1, v2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0], x - q[:, 0]
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    with np.errstate(invalid="ignore", divide="ignore"):
        b1 = (d11 * d20 - d01 * d21) / den
        b2 = (d00 * d21 - d01 * d20) / den
    b0 = 1.0 - b1 - b2
    p = p_tris[ids]
    return b0[:, None] * p[:, 0] + b1[:, None] * p[:, 1] + b2[:, None] * p[:, 2]


def subdivide_for_morph(
    tris: np.ndarray, colors: np.ndarray, O: np.ndarray, r1: float, r2: float,
    max_edge: float, max_triangles: int = 2_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """Split triangles that reach into the morph band (r1 < ρ < r2) until their edges are at
    most ``max_edge`` metres, so that the per-vertex morph follows the surface closely.

    The morph moves vertices, and a triangle's interior follows its corners linearly: a long
    facade crossing the band would be bent as one flat piece, far from where the per-point
    morph puts its interior. Splitting is 1-to-4 at edge midpoints, exact in world space (the
    pieces tile the original triangle), applied to a triangle whose corners are not all on one
    side of the band (all ρ <= r1 or all ρ >= r2: those move rigidly). Returns (t, 3, 3) float64
    and (t, 3) uint8; stops early rather than exceed ``max_triangles``.
    """
    tris = np.asarray(tris, dtype=np.float64)
    colors = np.asarray(colors, dtype=np.uint8)
    O = np.asarray(O, dtype=np.float64).reshape(3)
    done_t, done_c = [], []
    total = len(tris)
    while len(tris):
        rho = np.hypot(tris[..., 0] - O[0], tris[..., 2] - O[2])
        touches = (rho.max(axis=1) > r1) & (rho.min(axis=1) < r2)
        edges = np.linalg.norm(tris - np.roll(tris, -1, axis=1), axis=2).max(axis=1)
        split = touches & (edges > max_edge)
        if total + 3 * int(np.count_nonzero(split)) > max_triangles:
            split[:] = False
        done_t.append(tris[~split])
        done_c.append(colors[~split])
        if not np.any(split):
            break
        a, b, c = (tris[split, k] for k in range(3))
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tris = np.concatenate([
            np.stack([a, ab, ca], axis=1), np.stack([ab, b, bc], axis=1),
            np.stack([ca, bc, c], axis=1), np.stack([ab, bc, ca], axis=1),
        ])
        colors = np.tile(colors[split], (4, 1))
        total += 3 * int(np.count_nonzero(split))
    return np.concatenate(done_t), np.concatenate(done_c)


def split_far_dynamic(
    store: Any, t: float | None, center: np.ndarray, r2: float
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """What a ``client.store.GeometryStore`` holds at scene time ``t`` (seconds; None: at rest),
    split for ``compose_frame``: ((near_tris, near_colors), (far_dynamic_tris,
    far_dynamic_colors)), (k, 3, 3) float64 metres and (k, 3) uint8.

    Far dynamic: moving triangles (those with keyframes) whose every corner lies at ρ >= r2 from
    the vertical axis through ``center`` (the cubemap centre O) at time t, and spheres (as
    icospheres) wholly beyond r2; the server sends these as geometry rather than baking them.
    Everything else, straddling moving triangles included, goes with the near geometry (whose
    corners beyond r2 the morph displaces just the same).
    """
    from client.render import sphere_triangles

    O = np.asarray(center, dtype=np.float64).reshape(3)
    (_, st, sc), (_, mt, mc) = store.layers_at(t)
    rho = np.hypot(mt[..., 0] - O[0], mt[..., 2] - O[2])  # (m, 3)
    far = np.all(rho >= r2, axis=1)
    near_t, near_c = [st, mt[~far]], [sc, mc[~far]]
    far_t, far_c = [mt[far]], [mc[far]]
    _, centers, radii, colors = store.spheres_at(t)
    if len(centers):
        sfar = np.hypot(centers[:, 0] - O[0], centers[:, 2] - O[2]) - radii >= r2
        for mask, tl, cl in ((~sfar, near_t, near_c), (sfar, far_t, far_c)):
            if np.any(mask):
                tt, cc = sphere_triangles(centers[mask], radii[mask], colors[mask])
                tl.append(tt)
                cl.append(cc)
    return ((np.concatenate(near_t), np.concatenate(near_c)),
            (np.concatenate(far_t), np.concatenate(far_c)))


def compose_frame(
    renderer: Any,
    near_tris: np.ndarray,
    near_colors: np.ndarray,
    cube: Any,
    U: np.ndarray,
    forward: np.ndarray,
    r1: float,
    r2: float,
    far_dynamic_tris: np.ndarray | None = None,
    far_dynamic_colors: np.ndarray | None = None,
    morph: bool = True,
    points: bool = True,
    max_edge: float | None = None,
    key: Any = None,
    version: Any = None,
) -> ComposedFrame:
    """Compose a near-far frame seen from ``U`` looking along ``forward``.

    Parameters
    ----------
    renderer : a ``client.render.OffscreenRenderer`` (its size, field of view and near plane
        define the frame).
    near_tris : (k, 3, 3) float64 world corners (metres) of the geometry within r2 (near,
        intermediate, straddling); ``near_colors`` (k, 3) uint8 face colours.
    cube : the far cubemap: anything with ``center`` (3,), ``colors`` (6, R, R, 3) uint8 and
        ``ranges`` (6, R, R) metres (``protocol.cubemap.CubemapFrame`` or
        ``visibility.nearfar.FarCubemap``); None when the cell has nothing far (then nothing is
        morphed: without O there is no far viewpoint to morph toward).
    U : (3,) user eye position, metres. ``forward`` : (3,) view direction (up is +Y).
    r1, r2 : the near-far radii, metres (0 < r1 < r2).
    far_dynamic_tris, far_dynamic_colors : moving faces beyond r2 at the current time, (d, 3, 3)
        and (d, 3); displaced by U - O and depth-composited against the cubemap range.
    morph : False gives conventional compositing (no morph, no displacement, the cubemap as a
        plain background).
    points : also compute ``ComposedFrame.points`` (one CPU raster pass of the geometry).
    max_edge : with the morph, triangles reaching into the band r1 < ρ < r2 are split until
        their edges are at most this long (metres; see ``subdivide_for_morph``); default
        (r2 - r1) / 16. 0 or inf: no splitting.
    key, version : passed to ``renderer.render`` for its geometry cache; only useful when the
        morphed geometry does not change (U fixed), so None (upload per frame) by default.

    Returns a ``ComposedFrame``. Raises ValueError on bad shapes, non-finite input or radii.
    """
    nt, nc = _tris(near_tris, near_colors, "near_tris")
    dt, dc = _tris(far_dynamic_tris, far_dynamic_colors, "far_dynamic_tris")
    U = np.asarray(U, dtype=np.float64).reshape(-1)
    if U.shape != (3,) or not np.all(np.isfinite(U)):
        raise ValueError(f"U must be a finite 3-vector, got {U!r}")
    r1, r2 = float(r1), float(r2)
    if not (np.isfinite(r1) and np.isfinite(r2) and 0.0 < r1 < r2):
        raise ValueError(f"need finite radii 0 < r1 < r2, got r1={r1}, r2={r2}")
    rot = look_rotation(forward)

    P = np.concatenate([nt, dt]) if len(dt) else nt
    colors = np.concatenate([nc, dc]) if len(dt) else nc
    O = None
    if cube is not None:
        O = np.asarray(cube.center, dtype=np.float64).reshape(3)
    if morph and O is not None:
        me = (r2 - r1) / 16.0 if max_edge is None else float(max_edge)
        if 0.0 < me < np.inf and len(nt):
            nt, nc = subdivide_for_morph(nt, nc, O, r1, r2, me)
            P = np.concatenate([nt, dt]) if len(dt) else nt
            colors = np.concatenate([nc, dc]) if len(dt) else nc
        Qn = morph_vertices(nt.reshape(-1, 3), U, O, r1, r2).reshape(-1, 3, 3)
        Q = np.concatenate([Qn, dt + (U - O)]) if len(dt) else Qn
    else:
        Q = P
    frame = renderer.render(Q, colors, U, forward, key=key, version=version)
    gdepth = np.asarray(frame.depth, dtype=np.float32)
    color = np.array(frame.color, dtype=np.uint8, copy=True)
    h, w = gdepth.shape
    source = np.where(np.isfinite(gdepth), SOURCE_GEOMETRY, SOURCE_EMPTY).astype(np.uint8)
    depth = gdepth.copy()
    dirs, ray_len = world_rays(rot, w, h, renderer.tan_x, renderer.tan_y)

    cube_rng = None
    if cube is not None:
        res = int(np.asarray(cube.colors).shape[1])
        f, r, c = cube_texels(dirs, res)
        cube_rng = np.asarray(cube.ranges)[f, r, c].astype(np.float64)
        cube_col = np.asarray(cube.colors)[f, r, c]
        cube_depth = cube_rng / ray_len
        has_cube = np.isfinite(cube_depth)
        if morph:
            use = has_cube & ~(gdepth.astype(np.float64) < cube_depth)
        else:
            use = has_cube & ~np.isfinite(gdepth)
        color[use] = cube_col[use]
        depth[use] = cube_depth[use].astype(np.float32)
        source[use] = SOURCE_CUBEMAP

    pts = None
    if points:
        pts = np.full((h, w, 3), np.nan)
        if len(Q):
            cd, ids = render_ids(
                Q.reshape(-1, 3), np.arange(3 * len(Q), dtype=np.int32).reshape(-1, 3), U, rot,
                w, h, renderer.tan_x, renderer.tan_y, near=renderer.znear,
            )
            geo = (source == SOURCE_GEOMETRY) & (ids >= 0)
            if np.any(geo):
                x = U + cd[geo].astype(np.float64)[:, None] * dirs[geo]
                pts[geo] = _barycentric_points(Q, P, ids[geo], x)
        if cube_rng is not None:
            cm = source == SOURCE_CUBEMAP
            pts[cm] = O + (cube_rng[cm] / ray_len[cm])[:, None] * dirs[cm]
    return ComposedFrame(color=color, depth=depth, source=source, points=pts,
                         geometry_depth=gdepth)
