"""The side-plane cameras of a box cell (paper Sec. 4.1): what each view sees and from where.

Every ray an eye inside the box casts leaves the box through a side plane F, in a direction d
with d . n_F > 0 (n_F the outward normal). What the eye sees beyond the box is therefore what a
camera somewhere on F's rectangle sees in that direction: the union over the six side planes of
"everything visible from F's rectangle into its outer half-space" is the cell's PVS (plus what
lies inside the box itself, which ``prims.inside_box`` adds).

The outer half-space of F (a 180 degree field of view) is covered by five 90 degree frusta of a
cube around F's normal: the front face, and the halves of the four side faces that lie on F's
outer side. A planar image cannot hold 180 degrees, and a 90 degree cube face keeps pixels
within a factor 2-3 of the same solid angle, so the sampling (and the half-pixel term of
Sec. 4.5, which scales with depth times pixel size) stays even over the hemisphere.

A view is a camera frame (x, y, w) that is an axis permutation of the world with signs, with
its origin on the plane ``w = 0`` and the *camera rectangle* (the positions of F, in camera
coordinates) as four corners. For the front face every position has w = 0: offsets are parallel
to the image plane, the paper's 2D COS. For a side face the forward axis lies in F, so the
positions span w in [0, 2 C] (the origin sits on F's back edge): ``space`` projects them along
each pixel's ray onto w = 0, which turns the offset rectangle into a parallelogram per pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class View:
    """One cube frustum of one side plane.

    Attributes
    ----------
    face : (axis, sign) of the side plane F (axis 0..2, sign +-1).
    kind : "front" or "side".
    perm : (3,) int64, world axis of camera x, y and w.
    sign : (3,) float64, +-1 per camera axis.
    origin : (3,) float64 camera origin relative to the cell centre, metres.
    corners : (4, 3) float64 camera rectangle corners in camera coordinates (x, y, w), metres.
    nx, ny : image columns and rows; pixel (i, j) has its centre at tangents
        ``x = x_lo + (j + 0.5) * pw``, ``y = y_lo + (i + 0.5) * pw``.
    x_lo, y_lo, pw : image origin and pixel width in tangent units (pw = 2 / resolution).
    near_w : depth (camera w, metres) before which the image footprint is not projected: a
        triangle reaching into ``near_box`` is listed at every pixel of the view.
    near_box : (6,) float64 [x0, x1, y0, y1, w0, w1] camera-space box holding every point at
        w <= near_w that a ray of this view from the camera rectangle can reach.
    """

    face: tuple[int, int]
    kind: str
    perm: np.ndarray
    sign: np.ndarray
    origin: np.ndarray
    corners: np.ndarray
    nx: int
    ny: int
    x_lo: float
    y_lo: float
    pw: float
    near_w: float
    near_box: np.ndarray

    @property
    def n_pixels(self) -> int:
        return int(self.nx * self.ny)


def side_plane_views(box: np.ndarray, resolution: int) -> list[View]:
    """The 30 views (6 side planes x (1 front + 4 half side frusta)) of a box cell.

    Parameters
    ----------
    box : (2, 3) float64 [min, max] in metres (may be flat or a point).
    resolution : pixels across a full 90 degree frustum (side frusta have half the rows).

    Returns
    -------
    views : list of ``View``, camera origins relative to the box centre.
    """
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    half = 0.5 * (b[1] - b[0])
    res = int(resolution)
    pw = 2.0 / res
    extent = float(2.0 * half.max())
    # A small depth band in front of the camera rectangle: footprints are projected only beyond
    # it (perspective division near w = 0 is unbounded); whatever reaches into it is listed
    # everywhere. Proportional to the cell, at least a millimetre.
    eps_w = max(1e-3, 0.05 * extent)
    views: list[View] = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        for sgn in (1.0, -1.0):
            centre = np.zeros(3)
            centre[axis] = sgn * half[axis]
            # Front: w along the outward normal, x and y the two in-plane axes.
            c1, c2 = half[others[0]], half[others[1]]
            corners = np.array([[-c1, -c2, 0.0], [c1, -c2, 0.0], [c1, c2, 0.0], [-c1, c2, 0.0]])
            w = eps_w
            m = w * (1.0 + 2.0 * pw) + 1e-9
            near = np.array([-c1 - m, c1 + m, -c2 - m, c2 + m, -1e-9, w])
            views.append(View((axis, int(sgn)), "front",
                              np.array([others[0], others[1], axis], dtype=np.int64),
                              np.array([1.0, 1.0, sgn]), centre.copy(), corners,
                              res, res, -1.0, -1.0, pw, w, near))
            # Side halves: forward along an in-plane axis a (sign tau), y along the outward
            # normal (rows with y >= 0 only), x along the remaining in-plane axis l.
            for a in others:
                l_ax = [k for k in others if k != a][0]
                for tau in (1.0, -1.0):
                    origin = centre.copy()
                    origin[a] -= tau * half[a]
                    ca, cl = half[a], half[l_ax]
                    corners = np.array([[-cl, 0.0, 0.0], [cl, 0.0, 0.0],
                                        [cl, 0.0, 2.0 * ca], [-cl, 0.0, 2.0 * ca]])
                    w = 2.0 * ca + eps_w
                    m = w * (1.0 + 2.0 * pw) + 1e-9
                    near = np.array([-cl - m, cl + m, -m, m, -1e-9, w])
                    ny = (res + 1) // 2
                    views.append(View((axis, int(sgn)), "side",
                                      np.array([l_ax, axis, a], dtype=np.int64),
                                      np.array([1.0, sgn, tau]), origin, corners,
                                      res, ny, -1.0, 0.0, pw, w, near))
    return views
