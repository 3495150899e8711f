"""Dynamic scenes on a session's stream: the keyframes of moving triangles and the spheres.

Geometry frames carry a triangle's rest corners (the first keyframe). For a dynamic scene a cell
stream also carries, for the triangles it sends that move, their corners at every keyframe
(``protocol.keyframes`` kind 3), and the spheres of the cell's PVS the client lacks (kind 4; a
core that does not report spheres gets every sphere, which is conservative). A static scene
gets neither.

Keyframes travel with the geometry they animate: the keyframe frames of a geometry part are
queued just before its geometry frame, so a stream cut between frames (a prefetch stream
yielding to the walker's cell) never leaves the client holding a moving triangle without its
keyframes, and a triangle dropped and sent again gets its keyframes again. Spheres are never
dropped (budgets count triangles): each goes once per session, unless its stream was cut
before it went out (``DynamicStream.sent_spheres`` forgets those, see ``heal``).
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Iterator
from typing import Any

import numpy as np

from protocol.frames import FrameKind
from protocol.keyframes import chunk_keyframes, chunk_spheres, frame_plan
from visibility.scene import Scene
from visibility.scene import moving_faces as scene_moving_faces

_moving_cache: weakref.WeakKeyDictionary[Scene, np.ndarray] = weakref.WeakKeyDictionary()
_moving_lock = threading.Lock()


def moving_faces(scene: Scene) -> np.ndarray:
    """(n,) bool, read-only: ``visibility.scene.moving_faces`` of ``scene``, cached per scene
    object (every stream of a dynamic scene asks for it)."""
    with _moving_lock:
        hit = _moving_cache.get(scene)
    if hit is not None:
        return hit
    mask = scene_moving_faces(scene)
    mask.setflags(write=False)
    with _moving_lock:
        _moving_cache[scene] = mask
    return mask


def has_dynamic_updates(scene: Scene) -> bool:
    """Whether streams of ``scene`` carry keyframe or sphere frames: some triangle moves, or
    the scene has spheres (static ones too: they travel as sphere frames with one keyframe)."""
    return bool(moving_faces(scene).any()) or scene.n_spheres > 0


def keyframe_frames(scene: Scene, ids: np.ndarray, *, cell: int, seq: int,
                    max_frame_bytes: int) -> Iterator[bytes]:
    """Keyframe frames for the moving triangles among ``ids`` (triangle ids), each under
    ``max_frame_bytes``; nothing when none moves. The corners are ``scene.states`` gathered by
    face, times ``scene.state_times``."""
    ids = np.asarray(ids, dtype=np.int64)
    mov = ids[moving_faces(scene)[ids]] if len(ids) else ids
    if not len(mov):
        return iter(())
    pos = scene.states[:, scene.faces[mov]]  # (k, n, 3, 3)
    return chunk_keyframes(mov, scene.state_times, pos, cell=cell, seq=seq,
                           max_frame_bytes=max_frame_bytes)


def sphere_frames(scene: Scene, ids: np.ndarray, *, cell: int, seq: int,
                  max_frame_bytes: int) -> Iterator[bytes]:
    """Sphere frames for the spheres ``ids`` (indices into the scene's spheres), each under
    ``max_frame_bytes``: radius, colour and centre at every sphere keyframe."""
    ids = np.asarray(ids, dtype=np.int64)
    if not len(ids):
        return iter(())
    times = scene.sphere_times
    centers = scene.sphere_centers[:, ids]
    return chunk_spheres(ids, times, centers, scene.sphere_radii[ids], scene.sphere_colors[ids],
                         cell=cell, seq=seq, max_frame_bytes=max_frame_bytes)


def fits(scene: Scene, max_frame_bytes: int) -> tuple[bool, str]:
    """Whether one keyframe of one moving triangle (and of one sphere) fits a frame of
    ``max_frame_bytes``; (False, why) for an absurdly small limit, where the client then sees
    triangles at rest and no spheres."""
    try:
        if moving_faces(scene).any():
            frame_plan(FrameKind.KEYFRAMES, scene.states.shape[0], max_frame_bytes)
        if scene.n_spheres:
            frame_plan(FrameKind.SPHERES, scene.sphere_centers.shape[0], max_frame_bytes)
    except ValueError as exc:
        return False, str(exc)
    return True, ""


class DynamicStream:
    """One session's dynamic state: which spheres went out, and in which stream.

    Parameters
    ----------
    scene : the session's scene.
    max_frame_bytes : the frame size limit.
    """

    #: Streams whose sphere ids are remembered for ``heal``.
    MAX_TRACKED = 64

    def __init__(self, scene: Scene, max_frame_bytes: int) -> None:
        self.scene = scene
        self.max_frame_bytes = int(max_frame_bytes)
        self.active = has_dynamic_updates(scene)
        ok, self.why_not = fits(scene, max_frame_bytes)
        self.active = self.active and ok
        self.sent_spheres = np.zeros(scene.n_spheres, dtype=bool)
        self._tracked: list[tuple[Any, np.ndarray]] = []

    def keyframes_for(self, ids: np.ndarray, cell: int, seq: int) -> list[bytes]:
        """The keyframe frames of the moving triangles among ``ids`` (a geometry part about to
        be queued), encoded (call off the event loop)."""
        if not self.active:
            return []
        return list(keyframe_frames(self.scene, ids, cell=cell, seq=seq,
                                    max_frame_bytes=self.max_frame_bytes))

    def spheres_for(self, sphere_ids: np.ndarray | None, cell: int, seq: int,
                    tag: Any = None) -> list[bytes]:
        """The sphere frames of a cell's PVS spheres (``None``: the core does not report
        spheres, send every one) that have not gone out yet, encoded; marks them sent. ``tag``
        is the stream they go in (a ``server.sendqueue.StreamTag``): if that stream is later cut
        (``tag.cut``), ``heal`` forgets them so that a later stream sends them again."""
        if not self.active or not self.scene.n_spheres:
            return []
        self.heal()
        if sphere_ids is None:
            want = np.arange(self.scene.n_spheres)
        else:
            want = np.asarray(sphere_ids, dtype=np.int64)
            want = want[(want >= 0) & (want < self.scene.n_spheres)]
        want = want[~self.sent_spheres[want]]
        if not len(want):
            return []
        self.sent_spheres[want] = True
        if tag is not None:
            self._tracked.append((tag, want))
            del self._tracked[:-self.MAX_TRACKED]
        return list(sphere_frames(self.scene, want, cell=cell, seq=seq,
                                  max_frame_bytes=self.max_frame_bytes))

    def heal(self) -> None:
        """Forget the spheres of streams that were cut before they went out."""
        keep = []
        for tag, ids in self._tracked:
            if getattr(tag, "cut", False):
                self.sent_spheres[ids] = False
            else:
                keep.append((tag, ids))
        self._tracked = keep
