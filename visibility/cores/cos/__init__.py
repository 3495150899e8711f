"""The camera offset space core (Hladky, Seidel, Steinberger 2019); importing registers it."""

from visibility.cores.cos.core import CosCore, CosParams

__all__ = ["CosCore", "CosParams"]
