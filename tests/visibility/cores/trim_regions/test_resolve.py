"""The per-pixel resolve (paper Sec. 4.3) on hand-made trim sequences with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.cores.trim_regions.kbuffer import ANY_PIECE, BACK, FRONT, TRIM, KBuffer
from visibility.cores.trim_regions.resolve import Reach, resolve_pixel
from visibility.cores.trim_regions.silhouettes import AMBIGUOUS

INF = np.inf

# One worker for the module: ``resolve_pixel`` is the tests' own entry to the per-pixel
# resolve (the cores reach it inlined, through ``resolve_layer``), so no warm-up compiles it,
# and each worker the module's tests were spread over compiled it again (seconds each).
pytestmark = pytest.mark.xdist_group("trim_resolve")


def _reach(normals=None, lateral=INF) -> Reach:
    """A one-pixel view looking along -z (pixel 0's ray straight ahead), eyes up to
    ``lateral`` from v*; ``normals``: {id: world normal} of the 16 triangle ids."""
    normal = np.zeros((16, 3))
    for ident, n in (normals or {}).items():
        normal[ident] = np.asarray(n, dtype=np.float64) / np.linalg.norm(n)
    return Reach(normal, np.eye(3), 1.0, 1, float(lateral))


def _resolve(entries, final=True, cover=0.0, closed=None, piece=None, reach=None):
    """Resolve one pixel holding ``entries`` [(kind, depth, id, umbra)], triangle ids below 16
    (``closed``: {id: closed part}, the rest of no closed part; ``piece``: (16,) each id's
    connected piece, a trim's id its piece, -1 any; ``reach``: the view, ``_reach()`` when
    None); returns (visible ids, sealed,
    seal depth, cover after, entries left)."""
    kb = KBuffer.empty(1)
    for q, (kind, d, ident, um) in enumerate(entries):
        kb.put(0, q, kind, d, ident, um)
    kb.count[0] = len(entries)
    kb.cover[0] = cover
    vis = np.zeros(16, dtype=np.uint8)
    stats = np.zeros(4, dtype=np.int64)
    part = np.full(16, -1, dtype=np.int64)
    for ident, label in (closed or {}).items():
        part[ident] = label
    sealed = resolve_pixel(kb, part, np.full(16, -1, dtype=np.int64) if piece is None
                           else np.asarray(piece, dtype=np.int64),
                           _reach() if reach is None else reach, 0, final, vis, stats)
    return set(np.flatnonzero(vis).tolist()), sealed, kb.seal[0], kb.cover[0], int(kb.count[0])


def test_an_untrimmed_box_hides_what_is_behind_it():
    vis, sealed, seal, _, _ = _resolve([(BACK, 2.0, 1, 0), (FRONT, 1.0, 0, 0),
                                        (FRONT, 5.0, 2, 0), (BACK, 6.0, 3, 0)])
    assert vis == {0} and sealed and seal == 1.0


def test_a_trimmed_box_shows_what_lies_behind_its_umbra_only():
    # Trim fragment inside [1, 2] with umbra at 4: the box at 3 (trimmed too) is in the
    # umbra, the one at 5 is seen (and terminates the ray).
    seq = [(FRONT, 1.0, 0, 0), (TRIM, 1.5, -1, 4.0), (BACK, 2.0, 1, 0), (FRONT, 3.0, 2, 0),
           (TRIM, 3.2, -1, 3.6), (BACK, 3.5, 3, 0), (FRONT, 5.0, 4, 0), (BACK, 5.5, 5, 0)]
    vis, sealed, seal, cover, _ = _resolve(seq)
    assert vis == {0, 4} and sealed and seal == 5.0 and cover == 4.0
    # Untrimmed, the box in the umbra is not seen but still ends the ray: no eye sees past
    # it here.
    untrimmed = seq[:4] + seq[5:]
    for closed in ({2: 1, 3: 1}, None):
        vis, sealed, seal, cover, _ = _resolve(untrimmed, closed=closed)
        assert vis == {0} and sealed and seal == 3.0 and cover == 4.0
    # A trim of theirs behind the back face, before the next surface: on a closed part it is
    # not the box's (which is solid); faces of open geometry (a level's walls) need not bound
    # a solid, and that trim would validate the back face read on its own: the ray goes on.
    rim = untrimmed[:5] + [(TRIM, 3.8, -1, 4.6)] + untrimmed[5:]
    vis, _, seal, _, _ = _resolve(rim, closed={2: 1, 3: 1})
    assert vis == {0} and seal == 3.0
    vis, _, seal, _, _ = _resolve(rim)
    assert vis == {0, 4} and seal == 5.0


def test_a_trim_fragment_outside_the_interval_does_not_validate_it():
    seq = [(FRONT, 1.0, 0, 0), (BACK, 2.0, 1, 0), (TRIM, 2.5, -1, 9.0), (FRONT, 5.0, 4, 0),
           (BACK, 5.5, 5, 0)]
    vis, sealed, _, _, _ = _resolve(seq)
    assert vis == {0} and sealed


def test_an_open_run_is_carried_to_the_next_layer():
    seq = [(FRONT, 1.0, 0, 0), (TRIM, 1.5, -1, 4.0), (FRONT, 2.0, 2, 0)]
    vis, sealed, _, _, left = _resolve(seq, final=False)
    assert vis == set() and not sealed and left == 3
    vis, sealed, seal, _, _ = _resolve(seq, final=True)
    # Single-sided reading: the first face is trimmed by the fragment behind it, its umbra
    # (4) hides the second.
    assert vis == {0} and not sealed


def test_a_single_sided_wall_without_trims_terminates():
    vis, sealed, seal, _, _ = _resolve([(FRONT, 1.0, 0, 0), (FRONT, 3.0, 2, 0)])
    assert vis == {0} and sealed and seal == 1.0


def test_a_back_face_is_reported_unless_a_front_face_of_its_closed_part_hid_before_it():
    vis, sealed, _, _, _ = _resolve([(BACK, 1.0, 7, 0), (FRONT, 3.0, 2, 0)])
    assert vis == {7} and sealed
    # Behind a trimmed interval's umbra: the back of a closed object whose front hid in the
    # umbra is hidden with it; a back face with no hidden front before it is single-sided
    # geometry seen from behind, reported.
    hidden = [(FRONT, 1.0, 0, 0), (TRIM, 1.5, -1, 4.0), (BACK, 2.0, 1, 0), (FRONT, 3.0, 6, 0),
              (BACK, 4.5, 7, 0)]
    vis, sealed, _, _, _ = _resolve(hidden, closed={6: 3, 7: 3})
    assert vis == {0} and sealed
    alone = [(FRONT, 1.0, 0, 0), (TRIM, 1.5, -1, 4.0), (BACK, 2.0, 1, 0), (BACK, 4.5, 7, 0)]
    vis, sealed, _, _, _ = _resolve(alone)
    assert vis == {0, 7} and sealed
    # The hidden front face belongs to another closed part: the back face behind the umbra
    # may be seen (single-sided or inward-wound geometry). On no closed part, the two bound
    # an untrimmed interval, which ends the ray.
    vis, sealed, _, _, _ = _resolve(hidden, closed={6: 3, 7: 4})
    assert vis == {0, 7} and sealed
    vis, sealed, seal, _, _ = _resolve(hidden)
    assert vis == {0} and sealed and seal == 3.0
    # Unless more may come in a later layer: then the back face waits, carried.
    vis, sealed, _, _, left = _resolve(hidden, final=False)
    assert vis == {0} and not sealed and left >= 1


def test_an_inward_wound_corner_is_trimmed_by_the_edge_it_shares_with_its_exit_face():
    # Lavaducts (issue 15): a ray from v* enters a thin inward-wound pillar through a back face
    # (0) and leaves through a front face (1) right at their shared silhouette edge, whose
    # trim lies at the exit face's depth; a far wall seen from behind (2) lies past the
    # umbra and is seen from eyes of the cell. The corner must not terminate the ray.
    seq = [(BACK, 1.066, 0, 0), (TRIM, 1.106, -1, 1.415), (FRONT, 1.106, 1, 0),
           (BACK, 7.3, 2, 0)]
    vis, _, seal, cover, _ = _resolve(seq)
    assert {0, 2} <= vis and cover == 1.415 and seal == 7.3



def test_a_back_face_met_first_is_trimmed_by_its_rim_in_front_of_it():
    # Lavaducts, a cube across a wall whose centre stands in the void behind it: from v* the
    # ray starts behind a sloped wall (0) seen from its back, which recedes from its rim (the
    # edge it shares with the wall through the cell, which eyes in the room see past), so the
    # rim's trim lies in front of the face. The wall must not end the ray there: eyes in the
    # room see the far wall (1) past the rim (3,585 pixels of a frame were missed).
    seq = [(TRIM, 1.135, 5, 1.63), (BACK, 1.40, 0, 0), (FRONT, 19.65, 1, 0)]
    piece = np.full(16, 5)
    vis, sealed, seal, cover, _ = _resolve(seq, piece=piece)
    assert vis == {0, 1} and cover == 1.63 and seal == 19.65
    # Carried over layers (the far wall comes in a later layer), the face keeps its rim's
    # trim in the residual sequence.
    vis, sealed, _, _, left = _resolve(seq[:2], final=False, piece=piece)
    assert vis == set() and not sealed and left == 2
    # A trim of another piece is not its rim: the wall ends the ray.
    other = [(TRIM, 1.135, 6, 1.63)] + seq[1:]
    vis, sealed, seal, _, _ = _resolve(other, piece=piece)
    assert vis == {0} and sealed and seal == 1.40
    # (Nor does a trim at the depth of a surface met before the back face count: that
    # surface's, as the inward-wound corner above shows.)

def test_a_board_crossed_nearly_edge_on_takes_its_far_rims_trim_behind_its_back():
    # The kitchen's 1.8 cm cabinet panels seen nearly edge-on: the ray leaves the board (0, 1)
    # 5 cm after entering it, and the far rim the eyes see past lies behind its back face on
    # the ray (its trim at 1.2, piece 7), behind the next board's front (2) too. Eyes of the
    # sphere pass that rim: the board must not end the ray (67 pixels of a frame missed).
    normals = {0: (1.0, 0.0, 0.2), 1: (-1.0, 0.0, -0.2)}
    seq = [(FRONT, 1.0, 0, 0), (BACK, 1.05, 1, 0), (FRONT, 1.1, 2, 0), (TRIM, 1.12, 9, 1.3),
           (BACK, 1.15, 3, 0), (TRIM, 1.2, 7, 3.0), (FRONT, 4.0, 4, 0)]
    piece = np.full(16, 9)
    piece[[0, 1]] = 7
    # An eye passes the face's rim no deeper than 1 + 2 lateral tan(angle to the ray).
    vis, sealed, seal, cover, _ = _resolve(seq, piece=piece, reach=_reach(normals, 0.1))
    assert vis == {0, 4} and sealed and seal == 4.0 and cover == 3.0
    # Eyes too close to v* to pass a rim that deep: the board ends the ray, as it does for
    # the paper (its trims only between the interval's faces), or with no bound on the eyes.
    for reach in (_reach(normals, 0.001), _reach(normals)):
        vis, sealed, seal, _, _ = _resolve(seq, piece=piece, reach=reach)
        assert vis == {0} and sealed and seal == 1.0


def test_a_hidden_span_needs_its_face_across_the_whole_pixel():
    # The span a validated interval hides is what the footprint tests of small triangles
    # read for the pixel's whole square: a 3 mm strip of a bevelled edge under a 5 cm pixel
    # hid the table top the eyes see above it. One pixel of tan 1: its square's corner rays
    # (+-1, +-1, -1).
    from visibility.cores.trim_regions.resolve import _covers_square

    def reach(tri):
        return Reach(np.zeros((1, 3)), np.eye(3), 1.0, 1, INF,
                     np.asarray(tri, dtype=np.float64), np.array([[0, 1, 2]], dtype=np.int64))

    assert _covers_square(reach([(-4.0, -4.0, -1.0), (4.0, -4.0, -1.0), (0.0, 4.0, -1.0)]), 0, 0)
    assert _covers_square(reach([(-4.0, 4.0, -1.0), (0.0, -4.0, -1.0), (4.0, 4.0, -1.0)]), 0, 0)
    # A corner on its edge is not inside.
    assert not _covers_square(reach([(-3.0, -3.0, -1.0), (3.0, -3.0, -1.0), (0.0, 3.0, -1.0)]),
                              0, 0)
    strip = [(-3.0, -0.1, -1.0), (3.0, -0.1, -1.0), (0.0, 0.1, -1.0)]
    assert not _covers_square(reach(strip), 0, 0)
    # Far off the pixel, and through v* (edge-on): not across it either.
    assert not _covers_square(reach([(5.0, 5.0, -1.0), (6.0, 5.0, -1.0), (5.0, 6.0, -1.0)]), 0, 0)
    assert not _covers_square(reach([(0.0, 0.0, -1.0), (0.0, 0.0, -2.0), (0.0, 1.0, -1.0)]), 0, 0)


def test_each_front_face_of_a_run_but_the_last_reads_single_sided():
    # A small single-sided face with its own trim in front of an untrimmed closed wall: the
    # small face is seen and trimmed, so the wall behind it is seen past it, and terminates
    # (the small trim's umbra does not open it).
    seq = [(FRONT, 1.0, 0, 0), (TRIM, 1.2, -1, 1.3), (FRONT, 4.0, 1, 0), (BACK, 4.4, 2, 0),
           (FRONT, 6.0, 3, 0), (BACK, 7.0, 4, 0)]
    vis, sealed, seal, _, _ = _resolve(seq)
    assert vis == {0, 1} and sealed and seal == 4.0
    # Untrimmed, the small face terminates: the trims of what lies behind it (inside the
    # paper's run extended at the front) do not open it.
    seq = [(FRONT, 1.0, 0, 0), (FRONT, 4.0, 1, 0), (TRIM, 4.2, -1, 9.0), (BACK, 4.4, 2, 0),
           (FRONT, 6.0, 3, 0), (BACK, 7.0, 4, 0)]
    vis, sealed, seal, _, _ = _resolve(seq)
    assert vis == {0} and sealed and seal == 1.0


# The 1M kitchen's room seen from a cell outside it: its near wall (id 0, piece 0, "the pane")
# 1.9 m from v*, clutter behind it whose rim trims (piece 2), wider than the clutter, reach
# pixels its faces do not cover, and a wall seen from behind (id 1, piece 1) 7.7 m off.
PANE = [(FRONT, 1.9, 0, 0), (TRIM, 7.3, 2, 7.3), (TRIM, 7.4, 2, 9.4), (BACK, 7.7, 1, 0),
        (FRONT, 9.0, 3, 0), (BACK, 9.5, 4, 0)]
PIECES = [0, 1, 2, 3, 3] + [9] * 11


def test_trims_of_another_piece_do_not_validate_an_interval():
    vis, sealed, seal, _, _ = _resolve(PANE, piece=PIECES)
    assert vis == {0} and sealed and seal == 1.9
    # A merged trim whose piece set holds every piece counts for any, as the paper's depth
    # test does.
    anyone = [(k, d, ANY_PIECE if k == TRIM else i, u) for k, d, i, u in PANE]
    vis, sealed, seal, cover, _ = _resolve(anyone, piece=PIECES)
    assert vis == {0, 1, 3} and seal == 9.0 and cover == 7.3
    # A trim of the pane itself (its own rim) or of the wall that closes the interval does.
    for own in (0, 1):
        mine = [(k, d, own if k == TRIM else i, u) for k, d, i, u in PANE]
        vis, _, _, _, _ = _resolve(mine, piece=PIECES)
        assert {0, 3} <= vis


def test_a_single_sided_front_face_takes_only_trims_an_eye_can_pass_by():
    # A room's wall (id 0, piece 0) 1.9 m ahead, one piece with the room behind it whose rim
    # trim lies at 6 m; the room's clutter (ids 2, 3) at 7 m. Eyes up to 0.3 m from v* that
    # see past the wall cross its plane within 0.3 m of the ray: a wall facing the ray has its
    # passable rim at 1.9 m, so the trim at 6 m cannot open it.
    seq = [(FRONT, 1.9, 0, 0), (TRIM, 6.0, 0, 6.5), (FRONT, 7.0, 2, 0), (BACK, 7.5, 3, 0)]
    pieces = [0, 0, 1, 1] + [9] * 12
    vis, _, _, _, _ = _resolve(seq, piece=pieces)
    assert vis == {0, 2}
    for angle, opened in ((0.0, False), (80.0, False), (85.0, True)):
        a = np.radians(angle)
        reach = _reach({0: [np.sin(a), 0.0, np.cos(a)]}, lateral=0.3)
        vis, sealed, seal, _, _ = _resolve(seq, piece=pieces, reach=reach)
        # 2 * 0.3 * tan(80 deg) = 3.4 m: the rim reaches 5.3 m; at 85 degrees 8.8 m.
        assert (vis == {0, 2}) if opened else (vis == {0} and sealed and seal == 1.9), angle


def test_a_hidden_span_starts_where_its_face_lies_deepest_over_the_pixel():
    # A face trimmed at 2 m, its umbra at 9 m: what lies in front of the face anywhere in
    # the pixel is not hidden by it. Seen at 30 degrees across a one-pixel view (tan 1: the
    # square spans u in [-1, 1]) the face lies from 1.27 to 4.73 m over the pixel; facing
    # the ray, at 2 m over all of it; turning edge-on within the square (50 degrees), it
    # hides nothing.
    seq = [(FRONT, 2.0, 0, 0), (TRIM, 2.5, 0, 9.0), (FRONT, 12.0, 2, 0), (BACK, 12.5, 3, 0)]
    for angle, front in ((30.0, 2.0 / (1.0 - np.tan(np.radians(30.0)))), (0.0, 2.0),
                         (50.0, INF)):
        a = np.radians(angle)
        kb = KBuffer.empty(1)
        for q, (kind, d, ident, um) in enumerate(seq):
            kb.put(0, q, kind, d, ident, um)
        kb.count[0] = len(seq)
        vis = np.zeros(16, dtype=np.uint8)
        reach = _reach({0: [np.sin(a), 0.0, np.cos(a)]})
        resolve_pixel(kb, np.full(16, -1, dtype=np.int64), np.zeros(16, dtype=np.int64),
                      reach, 0, True, vis, np.zeros(4, dtype=np.int64))
        assert kb.n_spans[0] == 1 and kb.spans[0, 0, 1] == 9.0
        assert np.isclose(kb.spans[0, 0, 0], front) if front < INF else kb.spans[0, 0, 0] == INF


def test_a_front_face_apart_from_its_back_face_reads_single_sided():
    # The pane (no closed part) before the back face of a closed box (part 5) whose front lies
    # elsewhere: no solid between them. Trims of the box's piece between the two do not open
    # the pane; read on its own it terminates.
    box = [(FRONT, 1.9, 0, 0), (TRIM, 7.3, 1, 9.4), (BACK, 7.7, 1, 0), (FRONT, 9.0, 3, 0),
           (BACK, 9.5, 4, 0)]
    vis, sealed, seal, _, _ = _resolve(box, closed={1: 5}, piece=PIECES)
    assert vis == {0} and sealed and seal == 1.9
    # Both faces on no closed part (a soup: a building of unwelded walls): the paper's
    # interval, validated by the trim of the back face's piece: hidden up to its umbra, which
    # ends inside the untrimmed box behind (9.0-9.5); the box, a closed part, hidden, ends
    # the ray there.
    vis, sealed, seal, cover, _ = _resolve(box, closed={3: 6, 4: 6}, piece=PIECES)
    assert vis == {0} and sealed and seal == 9.0 and cover == 9.4


def test_entries_in_a_carried_umbra_are_hidden():
    # A trimmed box in a carried umbra is hidden, the one behind the umbra seen; an untrimmed
    # one in the umbra is hidden and ends the ray.
    seq = [(FRONT, 5.0, 2, 0), (TRIM, 5.2, -1, 5.8), (BACK, 5.5, 3, 0), (FRONT, 9.0, 4, 0),
           (BACK, 9.5, 5, 0)]
    vis, sealed, seal, _, _ = _resolve(seq, cover=6.0)
    assert vis == {4} and sealed and seal == 9.0
    vis, sealed, seal, _, _ = _resolve(seq[:1] + seq[2:], cover=6.0, closed={2: 1, 3: 1})
    assert vis == set() and sealed and seal == 5.0


def test_a_back_face_beyond_the_umbra_is_seen_unless_it_is_the_occluders_own():
    # A trimmed single-sided wall (0) and, 4 m behind its umbra's end, a wall seen from behind
    # (1): an eye that sees past the first wall's silhouette may see the second.
    seq = [(FRONT, 1.0, 0, 0), (TRIM, 1.05, -1, 2.0), (BACK, 5.0, 1, 0)]
    vis, sealed, _, cover, _ = _resolve(seq)
    assert vis == {0, 1} and not sealed and cover == 2.0
    # The back of a closed part whose front was seen is never seen.
    vis, _, _, _, _ = _resolve(seq, closed={0: 3, 1: 3})
    assert vis == {0}
    # Within the umbra the back face stays hidden whatever it belongs to.
    vis, _, _, _, _ = _resolve([(FRONT, 1.0, 0, 0), (TRIM, 1.05, -1, 9.0), (BACK, 5.0, 1, 0)])
    assert vis == {0}


def test_a_back_face_whose_plane_cuts_the_sphere_is_seen_past_the_umbra():
    # A post (closed part 3) below the cell: v*'s ray enters its top (0) and leaves by a side
    # face (1) whose plane passes through the sphere. Eyes beyond that plane see the side
    # face on, so it is not the part's unseen back (the kitchen's random cube 6 at Δ 0.41 m:
    # 35 pixels of one frame until it was reported).
    facing = np.ones(16, dtype=np.int8)
    facing[1] = AMBIGUOUS
    sphere = _reach()._replace(facing_of=facing)
    seq = [(FRONT, 1.0, 0, 0), (TRIM, 1.05, -1, 2.0), (BACK, 5.0, 1, 0)]
    vis, _, _, _, _ = _resolve(seq, closed={0: 3, 1: 3}, reach=sphere)
    assert vis == {0, 1}
    # Within the umbra no eye sees it, whatever its plane.
    vis, _, _, _, _ = _resolve([(FRONT, 1.0, 0, 0), (TRIM, 1.05, -1, 9.0), (BACK, 5.0, 1, 0)],
                               closed={0: 3, 1: 3}, reach=sphere)
    assert vis == {0}
    # Its front hidden in an earlier umbra, the post's untrimmed top and side still end the
    # ray; the side beyond that umbra is reported.
    seq = [(FRONT, 3.0, 0, 0), (BACK, 5.0, 1, 0), (FRONT, 9.0, 4, 0)]
    vis, sealed, seal, _, _ = _resolve(seq, cover=4.0, closed={0: 3, 1: 3}, reach=sphere)
    assert vis == {1} and sealed and seal == 3.0
    vis, sealed, seal, _, _ = _resolve(seq, cover=4.0, closed={0: 3, 1: 3})
    assert vis == set() and sealed and seal == 3.0
    vis, _, _, _, _ = _resolve(seq, cover=6.0, closed={0: 3, 1: 3}, reach=sphere)
    assert vis == set()
    # Read on its own behind its part's hidden front (a carried umbra), it is reported too.
    seq = [(FRONT, 1.0, 0, 0), (TRIM, 1.5, -1, 4.0), (BACK, 2.0, 5, 0), (FRONT, 3.0, 6, 0),
           (BACK, 4.5, 1, 0)]
    vis, _, _, _, _ = _resolve(seq, closed={6: 3, 1: 3})
    assert vis == {0}
    vis, _, _, _, _ = _resolve(seq, closed={6: 3, 1: 3}, reach=sphere)
    assert vis == {0, 1}


def test_the_back_of_a_closed_box_inside_a_trimmed_run_stays_hidden():
    # A room's wall (part 3) and, inside the room, a box (part 4): the run room wall, box
    # front closes at the box's back; the box's back belongs to the part of the face before
    # it, so it is the box's own back even past a short umbra (the stiff cases' closed room).
    seq = [(FRONT, 1.0, 0, 0), (TRIM, 1.05, -1, 1.5), (FRONT, 3.0, 1, 0),
           (TRIM, 3.05, -1, 3.5), (BACK, 4.0, 2, 0)]
    vis, _, _, _, _ = _resolve(seq, closed={0: 3, 1: 4, 2: 4})
    assert 2 not in vis
    vis, _, _, _, _ = _resolve(seq, closed={0: 3, 1: 4})
    assert 2 in vis


def test_a_merged_trim_validates_every_interval_its_depth_range_meets():
    # A trim entry spanning [1.2, 3.85] (fragments merged on a full buffer) with umbra 4:
    # the boxes [2, 2.5] and [3.8, 3.9] hold no fragment's own depth, but the range meets
    # them, so they are trimmed (the first one's front seen, what lies in the umbra hidden)
    # and the face at 5 is seen beyond.
    kb = KBuffer.empty(1)
    seq = [(FRONT, 2.0, 0, 0.0), (BACK, 2.5, 1, 0.0), (FRONT, 3.8, 2, 0.0), (BACK, 3.9, 3, 0.0),
           (FRONT, 5.0, 4, 0.0), (BACK, 6.0, 5, 0.0), (TRIM, 1.2, -1, 4.0)]
    for q, (kind, d, ident, um) in enumerate(seq):
        kb.put(0, q, kind, d, ident, um, 3.85 if q == len(seq) - 1 else None)
    kb.count[0] = len(seq)
    vis = np.zeros(16, dtype=np.uint8)
    none = np.full(16, -1, dtype=np.int64)
    sealed = resolve_pixel(kb, none, none, _reach(), 0, True, vis, np.zeros(4, dtype=np.int64))
    assert set(np.flatnonzero(vis).tolist()) == {0, 4} and sealed and kb.seal[0] == 5.0
    # Without the range (the trim at 1.2 only) the first box terminates the ray.
    kb2 = KBuffer.empty(1)
    for q, (kind, d, ident, um) in enumerate(seq):
        kb2.put(0, q, kind, d, ident, um)
    kb2.count[0] = len(seq)
    vis2 = np.zeros(16, dtype=np.uint8)
    resolve_pixel(kb2, none, none, _reach(), 0, True, vis2, np.zeros(4, dtype=np.int64))
    assert set(np.flatnonzero(vis2).tolist()) == {0} and kb2.seal[0] == 2.0


def _one_triangle_view(tri, res, back, delta):
    """A view of ``res`` px (tan 1) whose only triangle, id 0, has camera-space corners
    ``tri`` (3, 3); v* at the origin, the sphere of radius ``delta`` around (0, 0, -back)."""
    normal = np.zeros((16, 3))
    n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    normal[0] = n / np.linalg.norm(n)
    faces = np.zeros((16, 3), dtype=np.int64)
    faces[0] = (0, 1, 2)
    return Reach(normal, np.eye(3), 1.0, res, float(back + delta),
                 np.ascontiguousarray(tri, dtype=np.float64), faces, float(back), float(delta))


def _crosses(e, x, tri):
    """(k,) whether segments e-x (k, 3) cross triangle ``tri`` (Moller-Trumbore, float64)."""
    d = x - e
    e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
    pv = np.cross(d, e2)
    inv = 1.0 / np.einsum("ij,j->i", pv, e1)
    tv = e - tri[0]
    u = np.einsum("ij,ij->i", tv, pv) * inv
    qv = np.cross(tv, e1)
    v = np.einsum("ij,ij->i", d, qv) * inv
    t = (qv @ e2) * inv
    return (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < 1)


def test_a_triangle_hides_on_its_own_up_to_its_umbra_from_every_eye():
    # _self_umbra's bound, sampled: eyes anywhere in the sphere, rays through random points of
    # the pixel's square, points on them between the triangle and its umbra: every segment
    # from an eye to such a point crosses the triangle. Random triangles facing v* or turned
    # away, near and far, large and small; the bound is not vacuous (finite and infinite
    # umbrae both occur).
    from visibility.cores.trim_regions.resolve import _self_umbra

    rng = np.random.default_rng(11)
    res, checked, finite, infinite = 16, 0, 0, 0
    for _ in range(300):
        back, delta = rng.uniform(0.0, 0.4), rng.uniform(0.01, 0.3)
        p = int(rng.integers(res * res))
        rx = (p % res + 0.5) / (0.5 * res) - 1.0
        ry = 1.0 - (p // res + 0.5) / (0.5 * res)
        d = rng.uniform(0.5, 8.0)
        hit = d * np.array([rx, ry, -1.0])
        # A triangle around the hit: random plane and size, the hit inside it.
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        ang = rng.uniform(0, 2 * np.pi) + np.array([0.0, 2.1, 4.2]) + rng.uniform(-0.3, 0.3, 3)
        rad = rng.uniform(0.05, 6.0) * rng.uniform(0.3, 1.0, 3)
        tri = hit + (rad * np.cos(ang))[:, None] * a + (rad * np.sin(ang))[:, None] * b
        reach = _one_triangle_view(tri, res, back, delta)
        u = _self_umbra(reach, 0, p, d)
        assert u >= d
        if u == d:
            continue
        finite += u < INF
        infinite += u == INF
        m = 400
        e = rng.normal(size=(m, 3))
        e *= (delta * rng.uniform(0, 1, m) ** (1 / 3) / np.linalg.norm(e, axis=1))[:, None]
        e[:, 2] -= back
        h = 1.0 / res
        r = np.stack([rx + rng.uniform(-h, h, m), ry + rng.uniform(-h, h, m), -np.ones(m)], 1)
        # The triangle's depth along each ray, then a point between it and the umbra (none
        # where the triangle lies deeper than the umbra on that ray).
        t = (tri[0] @ reach.normal[0]) / (r @ reach.normal[0])
        top = np.minimum(u, t + 50.0)
        z = t + rng.uniform(0, 1, m) * (top - t)
        ok = (t > 0) & (top > t)
        assert _crosses(e[ok], z[ok, None] * r[ok], tri).all()
        checked += int(ok.sum())
    assert checked > 10_000 and finite > 20 and infinite > 5


def test_a_large_face_hides_what_a_shallow_umbra_of_another_edge_would_show():
    # A wall facing v* 2 m ahead, metres wide around the pixel's ray; a trim fragment of
    # another edge (its back edge) validates the interval with an umbra at its own depth. The
    # wall alone still hides the surface 3 m behind it from every eye of a 5 cm sphere: the
    # pixel seals there and only the wall is seen. With no geometry (the paper's resolve) the
    # surface behind is seen. Pixel 0 of a 64 px view: its ray runs to the top left corner.
    res = 64
    ray = np.array([1.0 / res - 1.0, 1.0 - 1.0 / res, -1.0])
    wall = np.array([[-9.0, -3.0, -2.0], [5.0, -3.0, -2.0], [-9.0, 9.0, -2.0]])
    seq = [(FRONT, 2.0, 0, 0), (TRIM, 2.2, -1, 2.2), (BACK, 2.2, 1, 0), (FRONT, 5.0, 2, 0),
           (BACK, 5.5, 3, 0)]
    vis, sealed, seal, _, _ = _resolve(seq, reach=_one_triangle_view(wall, res, 0.07, 0.05))
    assert vis == {0} and sealed and seal == 2.0
    vis, sealed, _, _, _ = _resolve(seq)
    assert vis == {0, 2} and sealed
    # A plane through the sphere stands beside some eyes: no umbra of its own.
    hit, centre = 2.0 * ray, np.array([0.0, 0.0, -0.07])
    u1 = (hit - centre) / np.linalg.norm(hit - centre)
    u2 = np.cross(u1, [0.0, 0.0, 1.0])
    u2 /= np.linalg.norm(u2)
    through = hit + np.array([[-9.0, -9.0], [9.0, -9.0], [0.0, 9.0]]) @ np.stack([u1, u2])
    vis, _, _, _, _ = _resolve(seq, reach=_one_triangle_view(through, res, 0.07, 0.05))
    assert 2 in vis


def test_an_interval_takes_the_trim_of_its_front_faces_rim_in_front_of_it():
    # Lavaducts at Δ 0.4 m: from v* the ray passes the back of a wall (0) at the corner it
    # makes with a second wall (1), which recedes from that corner to 2.8 m, and meets the
    # back of a third wall (2) 4.9 m away. The corner edge is both walls' rim: its trim lies
    # at the first wall's depth, in front of where the ray meets the second. Eyes of the
    # sphere past the corner see the third wall's back (a frame's pixels were missed there):
    # the interval [1, 2] takes its front face's rim, and the back face is reported.
    cam = np.array([[-1.4, -0.4, -1.386], [1.0, -0.4, -1.386], [-1.4, 1.6, -1.386],
                    [-0.4, -0.4, -1.386], [-0.4, -0.4, -2.808], [-0.4, 1.6, -2.808],
                    [-1.1, 1.0, -4.942], [-0.4, 1.0, -4.942], [-1.1, 1.7, -4.942]])
    faces = np.zeros((16, 3), dtype=np.int64)
    faces[0], faces[1], faces[2] = (0, 1, 2), (3, 4, 5), (6, 7, 8)
    reach = Reach(np.zeros((16, 3)), np.eye(3), 1.0, 1, INF, cam, faces, 0.561, 0.4)
    seq = [(TRIM, 1.386, -1, 1.682), (BACK, 1.386, 0, 0), (FRONT, 2.265, 1, 0),
           (TRIM, 4.942, -1, 22.953), (BACK, 4.942, 2, 0)]
    vis, sealed, _, _, _ = _resolve(seq, reach=reach)
    assert vis == {0, 1, 2} and not sealed
    # Over layers (the third wall comes later), the carried front face keeps that trim.
    vis, sealed, _, _, left = _resolve(seq[:3], final=False, reach=reach)
    assert vis == {0} and not sealed and left == 2
    vis, _, _, _, _ = _resolve([(TRIM, 1.386, -1, 1.682), (FRONT, 2.265, 1, 0)] + seq[3:],
                               reach=reach, cover=1.682)
    assert 2 in vis
    # A wall facing the ray squarely has no rim in front of it: the corner's trim is not its.
    square = cam.copy()
    square[3:6, 2] = -2.265
    flat = Reach(np.zeros((16, 3)), np.eye(3), 1.0, 1, INF, square, faces, 0.561, 0.4)
    vis, _, _, _, _ = _resolve(seq, reach=flat)
    assert 2 not in vis
