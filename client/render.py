"""Offscreen frames of triangle sets with pyrender: flat per-face colours, linear depth.

Conventions are those of ``visibility.raster.camera`` (Y-up world, camera looking down -Z,
depth is the view depth ``-z_cam`` in metres). Every triangle is drawn two-sided with its own
three vertices, coloured by its face colour times a fixed CPU-side lambert term, so colours do
not depend on GPU lighting and the same triangle always gets the same colour in every frame.

Geometry is uploaded to the GPU per *geometry set* (a ``key``): a set is rebuilt only when its
``(key, version, triangle count)`` changes, or when the renderer's origin moves (see below).

Precision: vertices are uploaded as float32 relative to a renderer-wide origin (the eye position
rounded to whole metres, in float64 on the CPU), so scenes 1e5 m from the world origin render
like scenes at the origin. The origin moves (and every set is re-uploaded once) only when the eye
gets more than ``recenter_distance`` metres from it, which bounds the float32 error of vertex and
eye positions to about ``recenter_distance * 6e-8`` m plus the vertices' own distance from the eye
times 6e-8. One origin is shared by every set, so ground truth and client frames see bit-identical
coordinates for the same triangle.

Calls on one renderer are serialised by a lock; any thread may make them (pyrender makes the
context current in the calling thread for every frame).
"""

from __future__ import annotations

import functools
import os
import threading

# pyrender picks its GL platform at import time; OSMesa is exact and needs no display.
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from dataclasses import dataclass  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
import trimesh  # noqa: E402

from visibility.raster.camera import DEFAULT_NEAR, camera_pose_matrix, look_rotation  # noqa: E402

# Shading lives in visibility so server-baked cubemaps and client frames shade identically;
# the names stay importable from here.
from visibility.raster.shading import AMBIENT, BACKGROUND, LIGHT_DIR, shade_colors  # noqa: E402, F401
from visibility.scene import Scene, moving_faces  # noqa: E402

#: Icosphere subdivisions used for a scene's spheres (320 faces each).
SPHERE_SUBDIVISIONS = 2

_FLAGS = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.SKIP_CULL_FACES
_SCENE_STATIC = "__scene_static__"
_SCENE_DYNAMIC = "__scene_dynamic__"
_STORE_STATIC, _STORE_MOVING, _STORE_SPHERES = "static", "moving", "spheres"
_ADHOC = "__adhoc__"


@dataclass(frozen=True)
class Frame:
    """One rendered view.

    Attributes
    ----------
    color : (H, W, 3) uint8 RGB, row 0 at the top.
    depth : (H, W) float32 view depth (``-z_cam``) in metres; +inf where nothing was drawn.
    """

    color: np.ndarray
    depth: np.ndarray


@dataclass
class _GpuSet:
    token: tuple
    origin: np.ndarray
    node: Any  # pyrender.Node, or None for an empty set


def _locked(method):
    """Run a renderer method under the renderer's lock (one GL context, one caller at a time)."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper


def scene_sphere_centers(scene: Scene, t: float | None) -> np.ndarray:
    """(s, 3) float64 sphere centres of ``scene`` at time ``t`` (seconds; None = first key).

    Piecewise linear between the sphere keyframes at ``Scene.sphere_times`` (the times the
    server streams with the spheres), clamped to their range: ``Scene.sphere_centers_at``.
    """
    c = scene.sphere_centers
    if c is None:
        return np.zeros((0, 3))
    if c.shape[0] == 1 or t is None:
        return c[0]
    return scene.sphere_centers_at(float(t))


def sphere_triangles(
    centers: np.ndarray, radii: np.ndarray, colors: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Icosphere triangles for spheres: ((s * f, 3, 3) float64 metres, (s * f, 3) uint8)."""
    ico = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS)
    unit = np.asarray(ico.vertices, dtype=np.float64)[np.asarray(ico.faces)]  # (f, 3, 3)
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    tris = unit[None] * radii[:, None, None, None] + centers[:, None, None, :]
    cols = np.repeat(np.asarray(colors, dtype=np.uint8).reshape(-1, 3), len(unit), axis=0)
    return tris.reshape(-1, 3, 3), cols


class OffscreenRenderer:
    """Offscreen pyrender renderer of flat-coloured triangle sets.

    Parameters
    ----------
    width, height : image size in pixels.
    yfov_deg : vertical field of view in degrees; the horizontal one follows the aspect ratio
        (``tan_x = tan_y * width / height``, as ``visibility.raster.camera.pixel_rays`` expects).
    znear, zfar : clip planes in metres.
    recenter_distance : how far (metres, per axis) the eye may get from the upload origin before
        the origin moves to the eye and every set is re-uploaded.

    Attributes
    ----------
    uploads : number of geometry sets built and uploaded so far (for cache checks).
    """

    def __init__(
        self,
        width: int = 256,
        height: int = 256,
        yfov_deg: float = 90.0,
        znear: float = DEFAULT_NEAR,
        zfar: float = 5000.0,
        recenter_distance: float = 1024.0,
    ) -> None:
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if not 0.0 < yfov_deg < 180.0:
            raise ValueError(f"yfov_deg must be in (0, 180), got {yfov_deg}")
        if not 0.0 < znear < zfar:
            raise ValueError(f"need 0 < znear < zfar, got {znear}, {zfar}")
        self.width, self.height = int(width), int(height)
        self.yfov_deg = float(yfov_deg)
        self.znear, self.zfar = float(znear), float(zfar)
        self.recenter_distance = float(recenter_distance)
        self.tan_y = float(np.tan(np.radians(self.yfov_deg) / 2.0))
        self.tan_x = self.tan_y * self.width / self.height
        self.uploads = 0
        self._lock = threading.RLock()
        self._origin: np.ndarray | None = None
        self._sets: dict[Any, _GpuSet] = {}
        self._scene_ref: Scene | None = None
        self._moving: np.ndarray | None = None
        self._pscene = pyrender.Scene(bg_color=[c / 255.0 for c in BACKGROUND] + [1.0])
        cam = pyrender.PerspectiveCamera(
            yfov=np.radians(self.yfov_deg),
            znear=self.znear,
            zfar=self.zfar,
            aspectRatio=self.width / self.height,
        )
        self._cam_node = self._pscene.add(cam, pose=np.eye(4))
        self._gl = pyrender.OffscreenRenderer(self.width, self.height)

    # ----------------------------------------------------------------------------- lifecycle
    @_locked
    def close(self) -> None:
        """Free the GL context and every uploaded set."""
        if self._gl is not None:
            self._gl.delete()
            self._gl = None
        self._sets.clear()

    def __enter__(self) -> OffscreenRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @_locked
    def drop(self, key: Any) -> None:
        """Forget the geometry set ``key`` and free its GPU buffers (no-op if unknown)."""
        cached = self._sets.pop(key, None)
        if cached is not None and cached.node is not None:
            self._pscene.remove_node(cached.node)

    # ----------------------------------------------------------------------------- rendering
    @_locked
    def render(
        self,
        tris: np.ndarray,
        colors: np.ndarray,
        eye: np.ndarray,
        forward: np.ndarray,
        key: Any = None,
        version: Any = None,
    ) -> Frame:
        """Render triangles seen from ``eye`` looking along ``forward``.

        Parameters
        ----------
        tris : (k, 3, 3) float64 world corner positions, metres.
        colors : (k, 3) uint8 face colours.
        eye : (3,) eye position, metres.
        forward : (3,) view direction (need not be unit); up is +Y (see ``look_rotation``).
        key : hashable name of the geometry set; None uploads ``tris`` for this call only.
        version : the set's version; with a key, the set is re-uploaded only when ``version``
            or the triangle count changes (so a caller that edits triangles in place must bump
            ``version``).

        Returns
        -------
        Frame with (H, W, 3) uint8 colour and (H, W) float32 depth (+inf where empty).
        """
        self._check_open()
        tris = np.asarray(tris, dtype=np.float64)
        if tris.size == 0:
            tris = tris.reshape(0, 3, 3)
        if tris.ndim != 3 or tris.shape[1:] != (3, 3):
            raise ValueError(f"tris must be (k, 3, 3), got {tris.shape}")
        colors = np.asarray(colors)
        if colors.shape != (len(tris), 3):
            raise ValueError(f"colors must be ({len(tris)}, 3), got {colors.shape}")
        eye = self._check_eye(eye)
        rot = look_rotation(forward)  # ValueError for a zero or non-finite forward
        self._update_origin(eye)
        if key is None:
            key, token = _ADHOC, (object(),)  # a fresh token: never reused
        else:
            token = (version, len(tris))
        self._ensure(key, token, lambda: (tris, colors))
        return self._draw([key], eye, rot)

    @_locked
    def render_scene(
        self, scene: Scene, eye: np.ndarray, forward: np.ndarray, t: float | None = None
    ) -> Frame:
        """Render a whole scene (valid faces, plus its spheres) as ground truth.

        Static geometry is uploaded once per scene object; for a dynamic scene only the faces and
        spheres that move are re-uploaded when ``t`` (seconds; None = rest state) changes.
        """
        self._check_open()
        eye = self._check_eye(eye)
        rot = look_rotation(forward)
        self._update_origin(eye)
        if self._scene_ref is not scene:
            # A new scene object: forget the old one's sets (its id may be reused later).
            self.drop(_SCENE_STATIC)
            self.drop(_SCENE_DYNAMIC)
            self._scene_ref = scene
            self._moving = _moving_faces(scene)
        moving = self._moving
        sid = id(scene)
        spheres_move = scene.sphere_centers is not None and scene.sphere_centers.shape[0] > 1

        def static_geometry() -> tuple[np.ndarray, np.ndarray]:
            ids = np.flatnonzero(scene.valid_faces & ~moving)
            tris, cols = scene.triangles(ids), scene.colors[ids]
            if scene.n_spheres and not spheres_move:
                st, sc = sphere_triangles(
                    scene_sphere_centers(scene, None), scene.sphere_radii, scene.sphere_colors
                )
                tris, cols = np.concatenate([tris, st]), np.concatenate([cols, sc])
            return tris, cols

        def dynamic_geometry() -> tuple[np.ndarray, np.ndarray]:
            ids = np.flatnonzero(scene.valid_faces & moving)
            tris, cols = scene.triangles(ids, t=t), scene.colors[ids]
            if scene.n_spheres and spheres_move:
                st, sc = sphere_triangles(
                    scene_sphere_centers(scene, t), scene.sphere_radii, scene.sphere_colors
                )
                tris, cols = np.concatenate([tris, st]), np.concatenate([cols, sc])
            return tris, cols

        keys = [_SCENE_STATIC]
        self._ensure(_SCENE_STATIC, (sid,), static_geometry)
        if np.any(moving) or spheres_move:
            self._ensure(_SCENE_DYNAMIC, (sid, None if t is None else float(t)), dynamic_geometry)
            keys.append(_SCENE_DYNAMIC)
        return self._draw(keys, eye, rot)

    @_locked
    def render_store(
        self, store: Any, eye: np.ndarray, forward: np.ndarray, t: float | None = None,
        key: Any = "store",
    ) -> Frame:
        """Render what a ``client.store.GeometryStore`` holds at scene time ``t`` (seconds;
        None: moving triangles and spheres at their first keyframe, i.e. at rest):
        the triangles without keyframes (uploaded once per store version), the moving ones at t
        and the spheres at t (uploaded per t). ``key`` names this store's geometry sets."""
        self._check_open()
        eye = self._check_eye(eye)
        rot = look_rotation(forward)
        self._update_origin(eye)
        # Read before the data: data newer than its version only costs one extra upload later.
        version = store.version
        t = None if t is None else float(t)
        static, moving = store.layers_at(t)
        keys = [(key, _STORE_STATIC), (key, _STORE_MOVING), (key, _STORE_SPHERES)]
        self._ensure(keys[0], (version, len(static[1])), lambda: (static[1], static[2]))
        self._ensure(keys[1], (version, t, len(moving[1])), lambda: (moving[1], moving[2]))

        def spheres() -> tuple[np.ndarray, np.ndarray]:
            _, centers, radii, colors = store.spheres_at(t)
            return sphere_triangles(centers, radii, colors)

        self._ensure(keys[2], (version, t, store.n_spheres), spheres)
        return self._draw(keys, eye, rot)

    # ----------------------------------------------------------------------------- internals
    def _check_open(self) -> None:
        if self._gl is None:
            raise RuntimeError("renderer is closed")

    @staticmethod
    def _check_eye(eye: np.ndarray) -> np.ndarray:
        eye = np.asarray(eye, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(eye)):
            raise ValueError(f"eye must be finite, got {eye.tolist()}")
        return eye

    def _update_origin(self, eye: np.ndarray) -> None:
        if self._origin is None or np.max(np.abs(eye - self._origin)) > self.recenter_distance:
            self._origin = np.round(eye)

    def _ensure(self, key: Any, token: tuple, geometry) -> None:
        """Upload the set ``key`` unless it is cached with the same token and origin."""
        cached = self._sets.get(key)
        if (
            cached is not None
            and cached.token == token
            and np.array_equal(cached.origin, self._origin)
        ):
            return
        # Removing the node frees its GPU buffers on the next render.
        self.drop(key)
        tris, colors = geometry()
        node = None
        if len(tris):
            node = self._pscene.add(self._build_mesh(tris, colors))
        self._sets[key] = _GpuSet(token, self._origin.copy(), node)
        self.uploads += 1

    def _build_mesh(self, tris: np.ndarray, colors: np.ndarray) -> pyrender.Mesh:
        shaded = shade_colors(tris, colors)
        positions = (tris - self._origin).reshape(-1, 3).astype(np.float32)
        rgba = np.empty((len(positions), 4), dtype=np.float32)
        rgba[:, :3] = np.repeat(shaded, 3, axis=0) / np.float32(255.0)
        rgba[:, 3] = 1.0
        prim = pyrender.Primitive(positions=positions, color_0=rgba, mode=pyrender.GLTF.TRIANGLES)
        return pyrender.Mesh([prim])

    def _draw(self, keys: list, eye: np.ndarray, rot: np.ndarray) -> Frame:
        self._pscene.set_pose(self._cam_node, camera_pose_matrix(eye - self._origin, rot))
        for k, s in self._sets.items():
            if s.node is not None:
                s.node.mesh.is_visible = k in keys
        color, depth = self._gl.render(self._pscene, flags=_FLAGS)
        depth = np.array(depth, dtype=np.float32)
        depth[depth == 0] = np.inf
        return Frame(color=np.ascontiguousarray(color[..., :3], dtype=np.uint8), depth=depth)


def _moving_faces(scene: Scene) -> np.ndarray:
    """(m,) bool: faces with a vertex that moves between the scene's keyframes (the scene's one
    definition, ``visibility.scene.moving_faces``; callers mask invalid faces anyway)."""
    return moving_faces(scene)
