"""The wire protocol's version.

Bump ``PROTOCOL_VERSION`` on any change a peer of the previous version could misread: a new
required field, a changed meaning, a changed binary layout. Additive optional fields in JSON
messages do not need a bump only when both ends already accept them (they are strict: unknown
fields are rejected), so in practice every schema change bumps it.

History: 1, the first; 2, ``hello.progressive`` and ``cell_begin``/``cell_end.answer``
(progressive PVS); 3, the answer ``"known"`` (a first answer assembled from the cached PVS of
neighbouring cells); 4, ``welcome.near_plane`` (the near plane the answers assume).
"""

from __future__ import annotations

#: The version this code speaks, in ``hello``/``welcome`` and every binary frame header.
PROTOCOL_VERSION = 4

#: Versions a server built from this code accepts in ``hello``.
SUPPORTED_VERSIONS: tuple[int, ...] = (PROTOCOL_VERSION,)
