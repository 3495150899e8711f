"""The ``from_segment`` core (Popescu et al. 2024): ``core`` holds the core and its parameters,
``kernels`` the static per-pixel coverage kernels, ``dynamic`` the moving-triangle kernels,
``spheres`` the sphere kernels."""

from visibility.cores.from_segment.core import (
    ORIENTATIONS,
    WALKS,
    FromSegmentCore,
    FromSegmentParams,
    cell_segments,
    cube_rotations,
    eye_heights,
    oblique_rotation,
    view_segments,
)

__all__ = ["ORIENTATIONS", "WALKS", "FromSegmentCore", "FromSegmentParams", "cell_segments",
           "cube_rotations", "eye_heights", "oblique_rotation", "view_segments"]
