"""The one key of a cached PVS, for every tier and every kind of region.

A ``PVSKey`` names what a PVS depends on and nothing else, so it means the same in every process,
after a restart and on every replica: the scene's content fingerprint
(``visibility.scene.scene_fingerprint``), the region (``"box"``: a viewcell box [min, max],
whether a grid cell's or an ad-hoc one; ``"segment"``: its end points [p, q]; six floats,
metres), the core's name, its parameters (``CoreParams.cache_key()``) and the key's format
version. A grid cell and an ad-hoc box with the same corners share their entry (cores see only
the box). Never a scene name or a cell id: their meaning changes with the catalogue and the
cell size.

Each tier stores the key its own way: memory by the key itself (a tuple), the disk by its
``repr`` (``server.cache.disk``), Redis by ``shared()``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from server.cache.codec import NAMESPACE, box_digest, digest, token

#: Version of the key's layout and meaning; bump it when either changes (entries under older
#: keys are then simply never met again: Redis expires them, the disk keeps them unread).
KEY_VERSION = 2
#: The region kinds a key names.
REGIONS = ("box", "segment")


class PVSKey(NamedTuple):
    """The cache key of one PVS (module docstring). ``points``: the region's six coordinates,
    metres, in the (2, 3) array's row order."""

    fingerprint: str
    region: str
    points: tuple[float, ...]
    core: str
    params: str
    version: int = KEY_VERSION

    @classmethod
    def of(cls, fingerprint: str, region: str, points: np.ndarray, core: str,
           params: str) -> PVSKey:
        """The key of the PVS of ``region`` (``"box"`` or ``"segment"``) with (2, 3) ``points``
        (metres) of the scene with ``fingerprint``, computed by ``core`` with ``params``
        (``CoreParams.cache_key()``). ValueError for another region kind or shape."""
        if region not in REGIONS:
            raise ValueError(f"region must be one of {REGIONS}, got {region!r}")
        a = np.asarray(points, dtype=np.float64)
        if a.shape != (2, 3):
            raise ValueError(f"a {region} is (2, 3) points, got shape {a.shape}")
        return cls(str(fingerprint), region, tuple(float(x) for x in a.ravel()), str(core),
                   str(params))

    def shared(self) -> str:
        """The Redis key: ``pvs:v<version>:<fingerprint>:<core>:<params hash>:<region>:<region
        hash>`` (the hashes: blake2b of the parameters' text and of the points as little-endian
        float64)."""
        where = box_digest(np.asarray(self.points, dtype=np.float64).reshape(2, 3))
        return (f"{NAMESPACE}:v{int(self.version)}:{token(self.fingerprint)}:{token(self.core)}:"
                f"{digest(self.params)}:{self.region}:{where}")

    def __str__(self) -> str:
        return (f"{self.region} {list(self.points)} of scene {self.fingerprint[:16]} by "
                f"{self.core} ({self.params})")
