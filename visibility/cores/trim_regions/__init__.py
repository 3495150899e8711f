"""The trim region core (Voglreiter et al. 2023); importing registers it."""

from visibility.cores.trim_regions.core import TrimRegionsCore, TrimRegionsParams

__all__ = ["TrimRegionsCore", "TrimRegionsParams"]
