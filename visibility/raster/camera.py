"""Camera conventions shared by every rasterizer, core and renderer of the project.

World: Y-up, right-handed, metres. Camera space is OpenGL's: the camera looks along -Z, +X is
right, +Y is up. A camera orientation is a 3x3 rotation ``R`` whose rows are the camera's
right, up and back (= -forward) axes in world coordinates, so ``p_cam = R @ (p_world - eye)``.

Images are row-major (H, W); row 0 is the top. The centre of pixel (row i, column j) is at
``ndc_x = 2 (j + 0.5) / W - 1`` and ``ndc_y = 1 - 2 (i + 0.5) / H``; its ray in camera space is
``(ndc_x * tan_x, ndc_y * tan_y, -1)`` with ``tan_x, tan_y`` the tangents of the half field of view.
Depth is the camera-space distance along the view axis (``-z_cam``), in metres.

Cubemap faces come in the OpenGL order +X, -X, +Y, -Y, +Z, -Z, each a 90-degree square frustum
whose forward axis is the face's axis; the up axis is +Y for the four side faces, +Z for +Y and
-Z for -Y (see ``CUBE_FACE_FORWARD_UP``).
"""

from __future__ import annotations

import numpy as np

CUBE_FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

#: (6, 2, 3) forward and up axis of each cubemap face, in OpenGL face order.
CUBE_FACE_FORWARD_UP = np.array(
    [
        [[1, 0, 0], [0, 1, 0]],
        [[-1, 0, 0], [0, 1, 0]],
        [[0, 1, 0], [0, 0, 1]],
        [[0, -1, 0], [0, 0, -1]],
        [[0, 0, 1], [0, 1, 0]],
        [[0, 0, -1], [0, 1, 0]],
    ],
    dtype=np.float64,
)

#: Default near-plane distance (metres) for visibility rendering.
DEFAULT_NEAR = 0.05


def look_rotation(forward: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) world-to-camera rotation for a camera looking along ``forward``.

    ``up`` defaults to +Y; when forward is (nearly) parallel to up, another up is chosen so the
    basis stays orthonormal. Rows are right, up, back.
    """
    f = np.asarray(forward, dtype=np.float64)
    n = np.linalg.norm(f)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"forward must be a finite non-zero vector, got {forward!r}")
    f = f / n
    u = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)
    r = np.cross(f, u)
    if np.linalg.norm(r) < 1e-9:
        u = np.array([0.0, 0.0, -1.0]) if f[1] > 0 else np.array([0.0, 0.0, 1.0])
        r = np.cross(f, u)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    return np.stack([r, u, -f])


def cube_face_rotations(base: np.ndarray | None = None) -> np.ndarray:
    """(6, 3, 3) world-to-camera rotations of the six cubemap faces.

    ``base`` (3, 3) rotates the whole cube (a world-to-cube rotation; identity by default): the
    face cameras are the axis-aligned faces expressed in the rotated frame.
    """
    # The axis-aligned faces are built once: a core asks for a cube per segment or eye, and
    # six look_rotation calls cost more than a small segment's rasterization.
    if base is None:
        return _AXIS_FACES.copy()
    return _AXIS_FACES @ np.asarray(base, dtype=np.float64)


def _axis_faces() -> np.ndarray:
    """(6, 3, 3) the rotations of the axis-aligned cube's faces (``cube_face_rotations``)."""
    rots = np.empty((6, 3, 3))
    for k, (f, u) in enumerate(CUBE_FACE_FORWARD_UP):
        rots[k] = look_rotation(f, u)
    return rots


_AXIS_FACES = _axis_faces()


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) rotation drawn uniformly from SO(3) (normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) rotations drawn uniformly from SO(3), vectorized; the same draws from ``rng``
    as ``n`` calls of ``random_rotation`` (one Gaussian quaternion each, in order)."""
    q = rng.normal(size=(int(n), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def pixel_rays(width: int, height: int, tan_x: float = 1.0, tan_y: float = 1.0) -> np.ndarray:
    """(H, W, 3) float64 camera-space ray directions through pixel centres (z = -1)."""
    j = (np.arange(width) + 0.5) * (2.0 / width) - 1.0
    i = 1.0 - (np.arange(height) + 0.5) * (2.0 / height)
    rays = np.empty((height, width, 3))
    rays[..., 0] = j[None, :] * tan_x
    rays[..., 1] = i[:, None] * tan_y
    rays[..., 2] = -1.0
    return rays


def projection_matrix(tan_x: float, tan_y: float, near: float, far: float) -> np.ndarray:
    """(4, 4) OpenGL perspective projection for the given half-angle tangents and clip planes."""
    p = np.zeros((4, 4))
    p[0, 0] = 1.0 / tan_x
    p[1, 1] = 1.0 / tan_y
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2.0 * far * near / (far - near)
    p[3, 2] = -1.0
    return p


def camera_pose_matrix(eye: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world pose (what pyrender's camera node takes) for eye and rotation."""
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(rotation, dtype=np.float64).T
    pose[:3, 3] = np.asarray(eye, dtype=np.float64)
    return pose
