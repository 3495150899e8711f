"""Near-far partitioning (Popescu et al. 2022): ``partition`` splits a scene around a cubemap
centre, morphs the intermediate band and bakes the far cubemap; ``cells`` decides which cells
need a cubemap and where blocks of cells anchor a shared one. The partition's names are
re-exported here, where they lived before this became a package."""

from visibility.nearfar.partition import (
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    FarCubemap,
    NearFarConfig,
    NearFarSplit,
    bake_cubemap,
    cube_texels,
    cubemap_lookup,
    horizontal_distance,
    morph,
    needs_cubemap,
    split_ids,
    texel_directions,
)

__all__ = ["MAX_RESOLUTION", "MIN_RESOLUTION", "FarCubemap", "NearFarConfig", "NearFarSplit",
           "bake_cubemap", "cube_texels", "cubemap_lookup", "horizontal_distance", "morph",
           "needs_cubemap", "split_ids", "texel_directions"]
