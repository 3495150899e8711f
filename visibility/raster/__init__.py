"""Rasterization shared by the cores, the sampled ground truth and the near-far baker.

``camera`` holds every camera convention (cube faces in OpenGL order, pixel rays, poses),
``triangles`` the parallel numba triangle rasterizer (entry points in ``render``, culled draws
through ``culling`` and the scene's ``hierarchy``), ``spheres`` the sphere rasterizer,
``face_pixels`` the pixel-range arithmetic the kernels share, ``shading`` the colour shading
of rendered frames. The triangle rasterizer's entry points are re-exported here, where they
lived before this became a package (``from visibility.raster import render_cubemap``).
"""

from visibility.raster.render import render_cubemap, render_cubemap_ids, render_ids

__all__ = ["render_cubemap", "render_cubemap_ids", "render_ids"]
