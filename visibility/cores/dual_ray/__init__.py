"""The ``dual_ray`` core (Koltun, Chrysanthou, Cohen-Or 2001): from-region visibility of 2.5D
scenes in a dual ray space; importing registers it."""

from visibility.cores.dual_ray.core import DualRayCore, DualRayParams

__all__ = ["DualRayCore", "DualRayParams"]
