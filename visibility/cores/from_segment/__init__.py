"""The ``from_segment`` core (Popescu et al. 2024): ``core`` holds the core and its parameters,
``segment`` a view segment's visible set (the driver of the parts below), ``geometry`` the
scene's cached geometry and clusters, ``boxes`` the primitives' screen boxes and their binning
into tiles, ``raster`` the pixel samples and the tiles' rasterization and resolution,
``envelope`` the per-pixel depth envelopes, ``static`` the static-triangle coverage kernels,
``dynamic`` the moving-triangle kernels, ``spheres`` the sphere kernels."""

from visibility.cores.from_segment.core import (
    ORIENTATIONS,
    SUBPIXEL_CANDIDATES,
    WALKS,
    FromSegmentCore,
    FromSegmentParams,
    cell_segments,
    cube_rotations,
    eye_heights,
    oblique_rotation,
    view_segments,
)

__all__ = ["ORIENTATIONS", "SUBPIXEL_CANDIDATES", "WALKS", "FromSegmentCore",
           "FromSegmentParams", "cell_segments", "cube_rotations", "eye_heights",
           "oblique_rotation", "view_segments"]
