"""Named scratch buffers kept between uses: on these machines first-touch page faults of fresh
buffers cost as much as the work that fills them (the rasterizer's per-view buffers, a
trim_regions view's set-up of a million triangles).

A ``Scratch`` hands out uninitialised arrays by name, each a view of a flat buffer that grows
and is never shrunk; the caller writes every element it reads. Who owns one decides how long
its memory lives: the rasterizer keeps one per thread (``visibility.raster.triangles``), capped
per buffer; trim_regions keeps one per k-buffer, for the views of one computation.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class Scratch:
    """Uninitialised arrays by name, reused while shape and dtype fit (see the module
    docstring). ``keep``: the largest buffer (bytes) kept for the next use; None keeps all."""

    def __init__(self, keep: int | None = None) -> None:
        self.keep = keep
        self._pool: dict[str, np.ndarray] = {}

    def array(self, name: str, shape: int | tuple[int, ...], dtype: Any = np.float64
              ) -> np.ndarray:
        """An uninitialised array ``name`` of ``shape`` and ``dtype``, from the kept buffer
        when it is large enough and of that dtype."""
        dtype = np.dtype(dtype)
        n = int(np.prod(shape))
        buf = self._pool.get(name)
        if buf is None or buf.dtype != dtype or len(buf) < n:
            buf = np.empty(n, dtype=dtype)
            if self.keep is None or buf.nbytes <= self.keep:
                self._pool[name] = buf
        return buf[:n].reshape(shape)

    def release(self) -> None:
        """Drop every kept buffer: their memory goes back."""
        self._pool = {}


__all__ = ["Scratch"]
