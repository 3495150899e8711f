"""The ``from_segment`` core: continuous from-segment visibility (Popescu et al. 2024).

A cell's PVS is the union of the segment visible sets (``segment``) of its view segments: by
default the outline of the open floor in the cell (where a person can stand, through no wall or
furniture; ``visibility.cell_walk``), or with ``walk="rectangle"`` the four sides of the cell's
rectangle; at the box's mid height and, when the box has height, at its bottom and top (the
eye-height range), each seen by a full cubemap (by default turned obliquely to the
world axes; see ``FromSegmentParams``); ``runs - 1`` extra runs use randomly rotated cubemaps
(the paper's jitter, deterministic for a seed), and ``subpixel_runs`` more follow where the
first run shows the scene's answer to be made of triangles smaller than a pixel. Dynamic
scenes are solved per pair of consecutive states (vertices and sphere centres move linearly
while the eye sweeps the segment) and united. Spheres are first-class primitives and come
back in ``PVS.sphere_ids``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from visibility.cancel import checkpoint
from visibility.cell_walk import walk_segments
from visibility.cores.base import Core, CoreParams, Cost, param, register
from visibility.cores.from_segment.geometry import CLUSTER, GEOMETRY_BUILD, scene_geometries
from visibility.cores.from_segment.segment import DEFAULT_BATCH, MAX_SPLIT_DEPTH, segment_visible
from visibility.raster.camera import DEFAULT_NEAR, random_rotation
from visibility.scene import Scene
from visibility.scene_cache import Build
from visibility.viewcells import Viewcell

#: Values of ``FromSegmentParams.first_orientation``.
ORIENTATIONS = ("axis", "oblique")
#: How a cell's view segments are chosen (``FromSegmentParams.walk``).
WALKS = ("open", "rectangle")
#: What a primitive that holds no pixel sample gets (``FromSegmentParams.small``).
SMALLS = ("corners", "footprint", "samples")
#: ``FromSegmentParams.subpixel_runs`` are taken when the first run's footprint rule tested
#: more than this many triangles (per tile, ``footprint_candidates``) per triangle of its
#: answer: sub-pixel triangles, most of them far away, crowd the tiles, and the pixel samples
#: pass between some that a turned cube's samples meet. Set between the scenes that need a
#: second run and those that do not (docs/cores/from_segment.md, "Sub-pixel runs").
SUBPIXEL_CANDIDATES = 4.0


def oblique_rotation() -> np.ndarray:
    """(3, 3) the fixed world-to-cube rotation of ``first_orientation="oblique"``: yaw 0.5,
    pitch 0.3, roll 0.2 rad, so no cube axis and no pixel row is parallel to a world axis."""
    def axis_angle(k: int, a: float) -> np.ndarray:
        c, s = np.cos(a), np.sin(a)
        i, j = [(1, 2), (2, 0), (0, 1)][k]
        r = np.eye(3)
        r[i, i] = r[j, j] = c
        r[i, j], r[j, i] = -s, s
        return r

    return axis_angle(1, 0.5) @ axis_angle(0, 0.3) @ axis_angle(2, 0.2)


@dataclass
class FromSegmentParams(CoreParams):
    """Parameters of the from-segment core.

    runs : cubemap orientations per segment (the first, then ``runs - 1`` random rotations).
    subpixel_runs : more random rotations after those ``runs``, taken only where the first
        run's footprint rule tested more than ``SUBPIXEL_CANDIDATES`` triangles per triangle
        it reports (a scene whose answer is mostly sub-pixel triangles: the paper's runs "for
        datasets with small triangles"); 0 never. ``stats["runs"]`` says how many were run.
    first_orientation : "oblique" (default: a fixed rotation aligned with no world axis) or
        "axis" (the paper's axis-aligned cube). Long thin features parallel to the segment
        (ledges, kerbs, roof lines) project to bands that slide along themselves as the eye
        moves; with an axis-aligned cube on an axis-aligned scene such a band lies between two
        pixel rows and covers no pixel centre along the whole segment, while an oblique band
        crosses some. The oblique cube misses less for a little more time (figures:
        benchmarks/results/from_segment.md, "First orientation").
    near : near-plane distance of the visibility cameras, metres.
    jitter : each pixel is sampled at a fixed pseudo-random point up to ``jitter`` pixels off its
        centre per axis (``raster.sample_offset``), a new pattern per segment and run; 0 samples
        the centres (the paper). Sub-pixel triangles slide along a line on the cube as the eye
        walks a side; with centres on a regular grid that line can pass between every row of
        centres, while jittered samples do not line up: far fewer misses on sub-pixel clutter,
        for more time (figures: docs/cores/from_segment.md, benchmarks/results/real_cells.md).
    small : what a triangle that holds no pixel sample along a segment (one far smaller than
        a pixel, sliding between the samples) gets. "corners" (the default): an extra sample
        at its centroid, a ray from the eye on the segment through it, reported when nothing
        stands before it (``raster._footprint_seen``; not in tiles listing more than
        ``raster.FOOTPRINT_MAX_ITEMS`` primitives), then, where the centroid's rays were
        blocked, samples near each corner; and triangles whose pixel box holds pixels closed
        by a nearer surface beside open ones (slivers past a roof line) get them too.
        "footprint": the centroid only, and no triangle passing closed pixels by. Every such
        find is seen by a real eye, so the answer stays exact at its samples. "samples"
        reports what some pixel sample sees and nothing else (the paper). Figures:
        docs/cores/from_segment.md.
    eye_levels : heights at which the segments are walked: 1 = mid height, 2 = bottom and top
        of the box, 3 = all three (a box without height always uses one).
    walk : "open" walks the outline of the open floor inside the cell (``visibility.cell_walk``:
        where a person can stand, found on a 0.2 m lattice), at the eye heights, split where it
        would meet geometry: no segment passes through a wall or furniture. A cell with no open
        part (the lattice finds nowhere to stand, e.g. a cell lying inside a thick wall or
        solid) walks its rectangle's sides instead, as "rectangle" always does, and says so in
        the stats (``walk``): the grid made it a cell someone may enter, so it gets the
        conservative answer rather than an empty one.
    cuts : a side along which near geometry sweeps across much of the cube (pixel boxes adding
        up to more than ``segment.SPLIT_AREA`` cubes) is solved as halves, up to this many times
        over; 0 never cuts. Same set, less time in clutter: the boxes shrink and occlusion bounds
        come nearer (static scenes only).
    depth_knots : depth of moving triangles and spheres is interpolated between multiples of
        1 / depth_knots of the segment (coverage events stay exact).
    batch_triangles : triangles per batch of the box pass (bounds its scratch memory; the pass
        works on clusters of CLUSTER triangles).
    """

    runs: int = param(1, ge=1, le=256, help="cubemap orientations per segment (the first, "
                      "then runs - 1 random rotations: the paper's jitter)")
    subpixel_runs: int = param(
        1, ge=0, le=255,
        help="more randomly turned cubes where the first run finds the answer made of "
        "sub-pixel triangles (its footprint rule busy); 0 never")
    first_orientation: str = param(
        "oblique", choices=ORIENTATIONS,
        help="the first cube: oblique (aligned with no world axis) or axis (the paper's)")
    near: float = param(DEFAULT_NEAR, ge=1e-6, le=10.0, unit="m",
                        help="near-plane distance of the visibility cameras")
    jitter: float = param(0.5, ge=0.0, le=0.5, unit="px",
                          help="how far each pixel's sample lies off its centre (0 = centres)")
    small: str = param("corners", choices=SMALLS,
                       help="corners: a triangle no pixel sample meets gets samples at its "
                       "centroid and near its corners; footprint: at its centroid only; "
                       "samples: only the pixel samples (the paper)")
    eye_levels: int = param(3, ge=1, le=3, help="heights walked: 1 mid, 2 bottom and top, 3 all")
    walk: str = param("open", choices=WALKS,
                      help="segments: open (around where a person can stand in the cell, "
                      "through no geometry) or rectangle (the cell's sides)")
    cuts: int = param(MAX_SPLIT_DEPTH, ge=0, le=16,
                      help="most times a side is halved where near geometry sweeps the cube")
    depth_knots: int = param(16, ge=1, le=1024,
                             help="depth of moving primitives interpolated between these knots")
    batch_triangles: int = param(DEFAULT_BATCH * CLUSTER, ge=1024, le=1 << 26, unit="triangles",
                                 help="triangles per batch of the box pass (bounds its memory)")


def eye_heights(box: np.ndarray, eye_levels: int = 3) -> list[float]:
    """Eye heights (metres) walked in a cell box (2, 3): mid (eye_levels 1), bottom and top (2)
    or all three (3); the mid height alone when the box has no height."""
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    y0, y1 = float(b[0, 1]), float(b[1, 1])
    ym = 0.5 * (y0 + y1)
    if y1 <= y0:
        return [ym]
    return {1: [ym], 2: [y0, y1], 3: [y0, ym, y1]}[int(eye_levels)]


#: Cached (scene, box, eye_levels) -> (segments, how) of ``view_segments``; scenes are held so
#: that an id is never reused while its entry lives.
_SEGMENT_CACHE: dict[tuple, tuple[Scene, np.ndarray, str]] = {}
_SEGMENT_CACHE_MAX = 256


def view_segments(scene: Scene, box: np.ndarray, eye_levels: int = 3,
                  walk: str = "open") -> tuple[np.ndarray, str]:
    """(k, 2, 3) view segments of a cell box (2, 3) and how they were chosen.

    ``walk`` "rectangle": ``cell_segments``. "open": ``cell_walk.walk_segments`` at the
    ``eye_heights``, i.e. the outline of where a person can stand, through no geometry; how is
    "open". A cell with no open part falls back to the rectangle, how "rectangle (no open
    floor in the cell)"; a box flat in X or Z (a line or point of eyes) always walks its
    rectangle, how "rectangle (degenerate box)".
    """
    if walk not in WALKS:
        raise ValueError(f"walk must be one of {WALKS}, got {walk!r}")
    if walk == "rectangle":
        return cell_segments(box, eye_levels), "rectangle"
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    if b[1, 0] <= b[0, 0] or b[1, 2] <= b[0, 2]:
        # A line or point of eye positions: the caller named the segment itself.
        return cell_segments(b, eye_levels), "rectangle (degenerate box)"
    key = (id(scene), b.tobytes(), int(eye_levels))
    hit = _SEGMENT_CACHE.get(key)
    if hit is not None and hit[0] is scene:
        return hit[1], hit[2]
    segs = walk_segments(scene, b, eye_heights(b, eye_levels))
    how = "open"
    if len(segs) == 0:
        segs, how = cell_segments(b, eye_levels), "rectangle (no open floor in the cell)"
    if len(_SEGMENT_CACHE) >= _SEGMENT_CACHE_MAX:
        _SEGMENT_CACHE.pop(next(iter(_SEGMENT_CACHE)))
    _SEGMENT_CACHE[key] = (scene, segs, how)
    return segs, how


def cached_segments(scene: Scene, box: np.ndarray, eye_levels: int = 3,
                    walk: str = "open") -> np.ndarray | None:
    """The (k, 2, 3) segments ``view_segments`` already found for these arguments, else None
    (computes nothing)."""
    if walk != "open":
        return None
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    hit = _SEGMENT_CACHE.get((id(scene), b.tobytes(), int(eye_levels)))
    return hit[1] if hit is not None and hit[0] is scene else None


def cell_segments(box: np.ndarray, eye_levels: int = 3) -> np.ndarray:
    """(k, 2, 3) view segments walking the sides of a cell box's XZ rectangle.

    Sides go around the rectangle (x0,z0) -> (x1,z0) -> (x1,z1) -> (x0,z1) -> back, at the box's
    mid height (eye_levels 1), bottom and top (2) or all three (3). Degenerate boxes give fewer,
    shorter segments: a zero-width rectangle is one segment, a point a zero-length segment
    (from-point visibility).
    """
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
        raise ValueError(f"box must be finite with max >= min, got {b.tolist()}")
    (x0, y0, z0), (x1, y1, z1) = b
    ym = 0.5 * (y0 + y1)
    if y1 <= y0:
        heights = [ym]
    else:
        heights = {1: [ym], 2: [y0, y1], 3: [y0, ym, y1]}[int(eye_levels)]
    corners = [(x0, z0), (x1, z0), (x1, z1), (x0, z1)]
    sides = []
    for k in range(4):
        a, c = corners[k], corners[(k + 1) % 4]
        if a == c:
            continue
        if any({a, c} == {p, q} for p, q in sides):
            continue
        sides.append((a, c))
    if not sides:
        sides = [(corners[0], corners[0])]
    out = np.empty((len(heights) * len(sides), 2, 3))
    n = 0
    for y in heights:
        for (ax, az), (cx, cz) in sides:
            out[n, 0] = (ax, y, az)
            out[n, 1] = (cx, y, cz)
            n += 1
    return out


def cube_rotations(runs: int, seed: int = 0, first: str = "axis") -> np.ndarray:
    """(runs, 3, 3) world-to-cube rotations: the identity (``first="axis"``) or
    ``oblique_rotation()`` (``"oblique"``), then ``runs - 1`` uniform random ones drawn from
    ``np.random.default_rng(seed)``."""
    if first not in ORIENTATIONS:
        raise ValueError(f"first must be one of {ORIENTATIONS}, got {first!r}")
    rng = np.random.default_rng(seed)
    out = np.empty((int(runs), 3, 3))
    out[0] = np.eye(3) if first == "axis" else oblique_rotation()
    for k in range(1, int(runs)):
        out[k] = random_rotation(rng)
    return out


def subpixel_ratio(stats: dict[str, Any], visible: np.ndarray) -> float:
    """Triangles the footprint rule tested (``stats["footprint_candidates"]``, once per tile
    each) per primitive marked in ``visible`` (n_ids,) bool; 0 when nothing is marked."""
    found = int(np.count_nonzero(visible))
    return float(stats.get("footprint_candidates", 0)) / found if found else 0.0


#: Cost model of one segment pass (``estimate_cost``), timed on the 2-core development machine
#: (village 20k and city 100k cells, 128 to 1024 px, 12 segments each): a fixed cost, a cost
#: per triangle of the scene and one per cubemap pixel (6 R^2); the pixel term dominates from
#: 256 px on. ``python -m benchmarks.bench_admission`` (benchmarks/results/admission.md) checks
#: it: close on open scenes, far under on dense clutter, where every triangle is binned into
#: many tiles; the server learns that per scene (``server.admission``).
#: Bytes: the tile bins hold every triangle once per 16 px tile it may cover, which grows with
#: the square of the resolution, so ``BYTES_PER_TRIANGLE`` per triangle at 128 px, times
#: (R / 128)^2 above, plus ``BYTES_PER_PIXEL`` per cubemap pixel (the envelope buffers of the
#: tile groups). An upper bound, loosest on open scenes, whose triangles are mostly small on
#: screen (the same benchmark measures how loose).
SECONDS_PER_SEGMENT = 5e-3
SECONDS_PER_SEGMENT_TRIANGLE = 1.5e-7
SECONDS_PER_SEGMENT_PIXEL = 3.7e-7
BYTES_PER_TRIANGLE = 256
BYTES_PER_TRIANGLE_RESOLUTION = 128
BYTES_PER_PIXEL = 64


@register
class FromSegmentCore(Core):
    """Continuous from-segment visibility on the perimeter of the cell (Popescu et al. 2024)."""

    name = "from_segment"
    description = ("Continuous from-segment visibility (Popescu et al. 2024): exact visibility "
                   "at one jittered sample per cubemap pixel along the cell's sides; static, "
                   "dynamic, spheres")
    Params = FromSegmentParams
    promise = "exact_at_pixel_samples"
    # Orders of magnitude only: the measured figures live in benchmarks/results/ and
    # docs/cores/from_segment.md.
    fits = ("static triangle scenes, any cell size (dynamic scenes too, at a cost linear in "
            "their keyframes): seconds for a 4 m cell of streets and levels, tens of seconds "
            "to minutes in dense clutter (a 1M-triangle kitchen): docs/cores/from_segment.md")
    knob = "resolution"
    knob_levels = (64, 128, 256, 512)
    native_segments = True
    check_params: ClassVar[dict[str, Any]] = {"runs": 1}
    fn_bound = 0.05
    #: The worst FP ``checks.check_fn_fp_against_sampled_ground_truth`` measures, rounded up
    #: (its failure message prints the rate): on the stiff cases the 1e6-aspect sliver pair is
    #: truly visible and found exactly but thinner than a pixel, so the sampled reference
    #: misses it; on rooms cells, grazing views from the cell's sides that interior samples
    #: miss.
    fp_bound = 0.15

    def scene_builds(self, scene: Scene) -> list[Build]:
        """The scene's spatial clusters (``geometry.GEOMETRY_BUILD``) that every segment's box
        pass walks."""
        return [GEOMETRY_BUILD]

    def suitability(self, scene: Scene, cell_size: float | None) -> tuple[float, str]:
        if scene.states is not None:
            # Seconds to minutes per cell of a 100k-triangle swaying meadow
            # (benchmarks/results/from_segment.md): below the sampling fallback there.
            return 0.5, ("dynamic scene: from-segment's cost grows linearly with the keyframes")
        return 3.0, "static triangle scene: exact continuous from-segment visibility"

    def estimate_cost(self, scene: Scene, cell: Viewcell, params: CoreParams) -> Cost:
        """One pass per segment of the cell's sides, cube orientation and state interval, each
        priced by triangles and cubemap pixels (the ``SECONDS_PER_SEGMENT*`` constants)."""
        assert isinstance(params, FromSegmentParams)
        # Estimates must not cast rays: the open outline's segments when already found, else
        # the rectangle's count (an open cell's outline is usually about as many).
        known = cached_segments(scene, cell.box, params.eye_levels, params.walk)
        segments = len(cell_segments(cell.box, params.eye_levels) if known is None else known)
        intervals = 1 if scene.states is None else max(1, scene.states.shape[0] - 1)
        passes = segments * int(params.runs) * intervals
        m, pixels = scene.n_triangles, 6 * int(params.resolution) ** 2
        per_pass = (SECONDS_PER_SEGMENT + m * SECONDS_PER_SEGMENT_TRIANGLE
                    + pixels * SECONDS_PER_SEGMENT_PIXEL)
        growth = max(1.0, (int(params.resolution) / BYTES_PER_TRIANGLE_RESOLUTION) ** 2)
        peak = (m + scene.n_spheres) * BYTES_PER_TRIANGLE * growth + pixels * BYTES_PER_PIXEL
        return Cost(passes * per_pass, int(peak),
                    {"views": passes, "pixels": pixels, "triangles": m})

    def _compute(
        self, scene: Scene, cell: Viewcell, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        assert isinstance(params, FromSegmentParams)
        segs, how = view_segments(scene, cell.box, params.eye_levels, params.walk)
        pvs, stats = self._run(scene, segs, params)
        stats["walk"] = how
        return pvs, stats

    def _compute_segment(
        self, scene: Scene, p: np.ndarray, q: np.ndarray, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        assert isinstance(params, FromSegmentParams)
        return self._run(scene, np.stack([p, q])[None], params)

    def _run(
        self, scene: Scene, segments: np.ndarray, params: FromSegmentParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Union over ``segments`` (k, 2, 3), cube orientations and state intervals."""
        rotations = cube_rotations(int(params.runs) + int(params.subpixel_runs), params.seed,
                                   params.first_orientation)
        runs = int(params.runs)
        t0 = time.perf_counter()
        geoms = scene_geometries(scene)
        n_ids = geoms[0].n_ids
        visible = np.zeros(n_ids, dtype=bool)
        stats: dict[str, Any] = {}
        batch = max(1, int(params.batch_triangles) // CLUSTER)
        if len(geoms[0].tri_sel) or len(geoms[0].sphere_sel):
            k = 0
            while k < runs:
                rot = rotations[k]
                for s, (v0, v1) in enumerate(segments):
                    # A fresh jitter pattern per segment and run: a triangle seen from several
                    # sides gets independent chances to meet a sample.
                    pattern = (int(params.seed) * 256 + k) * 64 + s
                    for g in geoms:
                        checkpoint()
                        segment_visible(g, v0, v1, rot, params.resolution, params.near,
                                        params.depth_knots, batch, visible, stats,
                                        jitter=params.jitter, seed=pattern,
                                        max_cuts=params.cuts,
                                        footprint=params.small != "samples",
                                        corners=params.small == "corners")
                if k == 0:
                    stats["subpixel_ratio"] = subpixel_ratio(stats, visible)
                    if stats["subpixel_ratio"] > SUBPIXEL_CANDIDATES:
                        runs += int(params.subpixel_runs)
                k += 1
        m = scene.n_triangles
        stats.setdefault("subpixel_ratio", 0.0)  # nothing to draw: no run was made
        stats["segments"] = int(len(segments))
        stats["runs"] = runs
        stats["state_intervals"] = int(len(geoms))
        stats["setup_seconds"] = time.perf_counter() - t0 - sum(
            stats.get(k, 0.0) for k in ("box_seconds", "bin_seconds", "envelope_seconds"))
        if scene.n_spheres:
            stats["sphere_ids"] = np.flatnonzero(visible[m:]).astype(np.int32)
        return np.flatnonzero(visible[:m]), stats
