"""Dynamic scenes end to end over the real server: moving triangles' keyframes and spheres are
streamed after their geometry, the client renders what it holds at the pose's scene time, and in
near-far mode a moving object beyond r2 is displaced by Q = U + (P - O) and depth-composited
against the cubemap range. A static scene gets no keyframe frames.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from client.metrics import frame_metrics
from client.render import OffscreenRenderer, shade_colors
from client.replay import ReplayOptions, composed_metrics_at, replay, scene_time
from client.session import Session, SyncSession
from server.dynamic import moving_faces
from tests.conftest import _box, make_tiny_scene, serving
from visibility.scene import Scene

#: Sampling settings that stay fast on 2 cores (as in tests/client/test_replay.py).
GOOD = {"resolution": 128, "samples": 24}
#: The magenta of the moving far box (no other face of the designed scene has it).
MAGENTA = np.array([255, 0, 255], dtype=np.uint8)


def _stream_all(url: str, scene: str, core: str, params: dict, poses: list) -> Session:
    """Connect, stand at each pose until its cell is complete, close; the finished session."""

    async def main() -> Session:
        s = await Session.connect(url, scene, core, params, prefetch=False)
        try:
            for i, pos in enumerate(poses):
                await s.send_pose(i, 0.0, pos, (0, 0, -1))
                for _ in range(1200):
                    if len(s.complete) > i or s.errors:
                        break
                    await asyncio.sleep(0.05)
        finally:
            await s.close()
        return s

    return asyncio.run(asyncio.wait_for(main(), 240))


# --------------------------------------------------------------------------- swaying grass
def test_swaying_grass_walk_is_rendered_at_the_pose_time(live_server, tmp_path):
    """A replay of swaying grass renders client frames and ground truth at the same scene time:
    frames match (the keyframes arrived and are used)."""
    opts = ReplayOptions(server=live_server, scene="swaying_grass", params=dict(GOOD),
                         out_dir=tmp_path, duration=1.0, fps=10.0, width=128, height=128,
                         quiet=True)
    summary = replay(opts, "sampling", tmp_path)
    assert summary["frames_rendered"] == len(summary["frames"]) >= 10
    assert summary["epsilon"] <= 0.5, summary["summary"]
    assert summary["ssim"] >= 0.99, summary["summary"]


def test_grass_keyframes_matter_and_go_once(live_server):
    """Walking every cell, each moving triangle held got its keyframes exactly once and no static
    one got any; frames at several scene times match ground truth, and a client that renders rest
    positions (ignoring the keyframes) is clearly worse at the same poses."""
    s = SyncSession.connect(live_server, "swaying_grass", "sampling", dict(GOOD), prefetch=False)
    r = OffscreenRenderer(128, 128)
    try:
        from client.replay import local_scene
        from visibility.viewcells import ViewcellGrid

        assert s.welcome.features["dynamic_updates"]["on"] is True
        scene = local_scene(s.welcome.scene, None)
        grid = ViewcellGrid.for_scene(scene, s.welcome.grid.cell_size)
        # Walk through every cell (they share triangles), ending in cell 0.
        for i, cell in enumerate(list(range(1, len(grid))) + [0]):
            s.send_pose(i, 0.0, grid.boxes[cell].mean(axis=0), (1.0, -0.3, 1.0))
            s.wait_cell(cell, timeout=240)
        centre = grid.boxes[0].mean(axis=0)
        held = s.store.ids
        kf_ids, times, _ = s.store.keyframes()
        moving = moving_faces(scene)
        assert np.array_equal(times, scene.state_times)
        assert np.array_equal(kf_ids, held[moving[held]]), "keyframes for exactly the movers"
        assert len(kf_ids) > 100 and s.keyframe_duplicates == 0 and not s.local_errors
        good, rest = [], []
        for t in (0.25, 0.5, 0.85):
            for fwd in ((1.0, -0.3, 1.0), (1.0, -0.4, 0.2)):
                gt = r.render_scene(scene, centre, fwd, t=scene_time(scene, t))
                good.append(frame_metrics(r.render_store(s.store, centre, fwd, t=t), gt))
                rest.append(frame_metrics(r.render_store(s.store, centre, fwd, t=None), gt))
        eps_good = np.mean([m["epsilon"] for m in good])
        eps_rest = np.mean([m["epsilon"] for m in rest])
        assert eps_good <= 0.5, good
        assert eps_rest > max(1.0, 5 * eps_good), (eps_good, eps_rest)
        assert np.mean([m["ssim"] for m in good]) > np.mean([m["ssim"] for m in rest]) + 0.05
    finally:
        r.close()
        s.close()


def test_static_scene_gets_no_keyframe_frames(live_server):
    s = _stream_all(live_server, "tiny", "test_near", {"radius": 30.0}, [(2.0, 1.7, 2.0)])
    assert s.complete and len(s.store) > 0
    assert s.welcome.features["dynamic_updates"]["on"] is False
    assert s.keyframe_frames == s.sphere_frames == 0
    assert s.store.keyframes()[0].size == 0 and s.store.n_spheres == 0


@pytest.fixture(scope="module")
def sphere_server(settings, registered_test_cores):
    """A server with a small scene of bouncing spheres (few, so the test stays light)."""
    from visibility.generators import make_scene

    scene = make_scene("spheres", spheres=12, states=5)
    with serving(settings, {"few_spheres": scene}) as (url, _):
        yield url, scene


def test_spheres_arrive_once_with_their_keyframes(sphere_server):
    url, scene = sphere_server
    grid_pose = scene.walk.rects[0, :2] + 0.5
    pos = (float(grid_pose[0]), 1.7, float(grid_pose[1]))
    s = _stream_all(url, "few_spheres", "test_near", {"radius": 1000.0}, [pos])
    assert s.welcome.features["dynamic_updates"]["on"] is True
    assert s.complete and not s.local_errors
    ids, centres, radii, _ = s.store.spheres_at(None)
    # test_near reports no spheres: every sphere goes (conservative), each once.
    assert np.array_equal(ids, np.arange(scene.n_spheres))
    assert s.spheres_received == scene.n_spheres
    np.testing.assert_allclose(radii, scene.sphere_radii, rtol=1e-6)
    t = float(scene.sphere_times[-1]) * 0.37
    _, at_t, _, _ = s.store.spheres_at(t)
    np.testing.assert_allclose(at_t, scene.sphere_centers_at(t), atol=1e-3)


# --------------------------------------------------------------------------- near-far
def _far_box_scene() -> Scene:
    """The tiny scene plus, beyond r2 of every cell, a static wall (x = 60 m), a static pillar
    (x = 25..27 m, z = 0..4 m) and a magenta box (x = 34..37 m, 4 m wide) moving along z: centre
    z = -8 m at t = 0 s, 2 m at 1 s (right behind the pillar seen from the cell at z = 2), 12 m
    at 2 s."""
    base = make_tiny_scene()
    verts, faces, cols = [base.vertices], [base.faces], [base.colors]
    n = len(base.vertices)
    extra = [((59.0, 0.0, -40.0), (60.0, 20.0, 40.0), (120, 120, 120)),
             ((25.0, 0.0, 0.0), (27.0, 8.0, 4.0), (30, 160, 30))]
    for lo, hi, c in extra:
        v, f = _box(lo, hi)
        verts.append(v)
        faces.append(f + n)
        cols.append(np.tile(np.array(c, dtype=np.uint8), (12, 1)))
        n += 8
    bv, bf = _box((34.0, 0.0, -10.0), (37.0, 4.0, -6.0))
    verts.append(bv)
    faces.append(bf + n)
    cols.append(np.tile(MAGENTA, (12, 1)))
    v = np.concatenate(verts)
    states = np.repeat(v[None], 3, axis=0)
    for k, dz in enumerate((0.0, 10.0, 20.0)):
        states[k, -8:, 2] += dz
    f = np.concatenate(faces)
    obj = np.concatenate([base.object_ids, np.repeat(np.arange(3) + base.object_ids.max() + 1,
                                                     12)]).astype(np.int32)
    return Scene(vertices=v, faces=f, object_ids=obj, colors=np.concatenate(cols),
                 name="far_box", states=states, state_times=np.array([0.0, 1.0, 2.0]),
                 walk=base.walk)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b)) / max(1, int(np.count_nonzero(a | b)))


def test_far_moving_box_is_displaced_and_depth_composited(settings, registered_test_cores):
    """Live near-far path: the moving box beyond r2 arrives as geometry with its keyframes, and
    the replay's composition shows it at Q = U + (P(t) - O), i.e. where the box at time t is seen
    from the cubemap centre O, and hidden behind the far pillar of the cubemap when the range
    says it is behind."""
    from visibility.nearfar import NearFarConfig, split_ids

    scene = _far_box_scene()
    with serving(settings, {"far_box": scene}, near_far=True, near_far_r1=8.0,
                 near_far_r2=16.0, near_far_resolution=256) as (url, _):
        s = _stream_all(url, "far_box", "test_near", {"radius": 12.0}, [(2.0, 1.7, 2.0)])
    assert s.complete and not s.local_errors, s.errors
    cell = next(iter(s.complete))
    cube = s.cubemaps[cell]
    O = np.asarray(cube.center, dtype=np.float64)
    box = np.arange(scene.n_triangles - 12, scene.n_triangles)
    split = split_ids(scene, O, NearFarConfig(r1=8.0, r2=16.0, resolution=256))
    assert set(box) <= set(split.far_dynamic_ids.tolist())
    assert set(box) <= set(s.store.ids.tolist()), "far dynamic faces come as geometry"
    assert set(box) <= set(s.store.keyframes()[0].tolist()), "... with their keyframes"

    # A narrow field of view, so the 4 m box 34 m away covers a few hundred pixels.
    r = OffscreenRenderer(128, 128, yfov_deg=40.0)
    shaded = shade_colors(scene.triangles()[box], scene.colors[box]).astype(int)
    try:
        # U - O is as wide as the box: Q = P + (U - O) and P seen from U do not overlap.
        U = O + np.array([0.0, 0.0, 4.0])
        fwd = np.array([1.0, 0.0, 0.0])
        tris_at = scene.vertices_at  # the box's true corners at time t

        def seen(eye, t):
            """The box alone at time t seen from ``eye``: its pixel mask."""
            tri = tris_at(t)[scene.faces[box]]
            return np.isfinite(r.render(tri, scene.colors[box], eye, fwd).depth)

        def composed(t):
            gt = r.render_scene(scene, U, fwd, t=t)
            frame, extra = composed_metrics_at(r, s.store, t, cube, U, fwd, gt)
            assert np.isfinite(extra["epsilon_composed"])
            # The box's pixels: one of its faces' shaded colours (no other face has them).
            diff = np.abs(frame.color.astype(int)[:, :, None] - shaded[None, None])
            return np.any(diff.max(axis=-1) <= 2, axis=-1)

        for t in (0.5, 1.5):
            got, want = composed(t), seen(O, t)
            assert want.sum() > 20
            # Displaced: where O sees the box at t, not where U sees it, nor the rest pose.
            assert _iou(got, want) > 0.8, (t, _iou(got, want))
            assert _iou(got, seen(U, t)) < 0.3
            assert _iou(got, seen(O, 0.0)) < 0.3
        # At t = 1 s the box is behind the pillar baked in the cubemap: the range hides it.
        assert seen(O, 1.0).sum() > 20
        assert composed(1.0).sum() <= 0.05 * seen(O, 1.0).sum()
    finally:
        r.close()
