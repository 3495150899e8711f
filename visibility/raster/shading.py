"""The fixed face shading shared by the client's frames and the server's near-far cubemaps.

Every triangle is drawn with its face colour times a two-sided lambert term against a fixed
light direction, computed on the CPU, so the same triangle gets the same colour in a client
frame, in a ground-truth frame and in a cubemap baked on the server.
"""

from __future__ import annotations

import numpy as np

#: Background (sky blue), RGB uint8: what a pixel that sees nothing shows.
BACKGROUND = (135, 206, 235)
#: Fixed light direction (world, towards the light) of the baked lambert term.
LIGHT_DIR = np.array([0.35, 0.85, 0.4]) / np.linalg.norm([0.35, 0.85, 0.4])
#: Share of the face colour a face gets when lit edge-on; the rest scales with |n . l|.
AMBIENT = 0.45


def shade_colors(tris: np.ndarray, colors: np.ndarray) -> np.ndarray:
    """(k, 3) uint8 face colours with the fixed two-sided lambert term baked in.

    ``tris`` is (k, 3, 3) float64 metres, ``colors`` (k, 3) uint8. Degenerate faces (no normal)
    get the ambient share only.
    """
    tris = np.asarray(tris, dtype=np.float64)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    length = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(n @ LIGHT_DIR) / length
    cos = np.where(np.isfinite(cos), cos, 0.0)
    shade = AMBIENT + (1.0 - AMBIENT) * cos
    out = np.asarray(colors, dtype=np.float64) * shade[:, None]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
