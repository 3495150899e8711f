"""The image error of the walkers' frames, drawn after the run (so drawing never slows them).

Each sampled frame (``benchmarks.load.walkers.Sample``) is drawn from the triangles its walker
held against the whole scene, at ``FRAME_SIZE`` px with a 90 degree field of view, and scored
with ``client.metrics.frame_metrics``: ε (% of pixels where the walker sees something farther
than it should), PSNR (dB, capped at ``PSNR_CAP_DB``) and SSIM. Per answer, each walker's
sampled frames are averaged first, then the walkers: the mean over walkers and the worst walker.
"""

from __future__ import annotations

import numpy as np

from benchmarks.load.walkers import Sample
from visibility.scene import Scene

#: Side of the frames drawn, pixels.
FRAME_SIZE = 128


def score_samples(scene: Scene, per_walker: list[list[Sample]]) -> list[list[dict]]:
    """``frame_metrics`` of every sample of every walker, in order: [walker][sample] ->
    {"answer", "epsilon" (%), "psnr" (dB, capped), "ssim"}."""
    if not any(per_walker):
        return [[] for _ in per_walker]
    from client.metrics import capped_psnr, frame_metrics
    from client.render import OffscreenRenderer

    n = scene.n_triangles
    valid = scene.valid_faces
    renderer = OffscreenRenderer(FRAME_SIZE, FRAME_SIZE, yfov_deg=90.0)
    out: list[list[dict]] = []
    try:
        for samples in per_walker:
            scored = []
            for s in samples:
                ids = np.flatnonzero(np.unpackbits(s.held, count=n).astype(bool) & valid)
                fr = renderer.render(scene.triangles(ids), scene.colors[ids], s.eye, s.forward)
                gt = renderer.render_scene(scene, s.eye, s.forward)
                m = frame_metrics(fr, gt)
                scored.append({"answer": s.answer, "epsilon": m["epsilon"],
                               "psnr": float(capped_psnr(np.array([m["psnr"]]))[0]),
                               "ssim": m["ssim"]})
            out.append(scored)
    finally:
        renderer.close()
    return out


def eps_by_answer(scored: list[list[dict]]) -> dict[str, dict]:
    """Per answer: frames and walkers sampled, ε mean over walkers of each walker's mean and the
    worst walker's mean (%), PSNR (dB) and SSIM means over walkers the same way."""
    per: dict[str, list[dict]] = {}
    for walker in scored:
        by: dict[str, list[dict]] = {}
        for m in walker:
            by.setdefault(m["answer"], []).append(m)
        for answer, ms in by.items():
            per.setdefault(answer, []).append({
                "frames": len(ms),
                "epsilon": float(np.mean([m["epsilon"] for m in ms])),
                "psnr": float(np.mean([m["psnr"] for m in ms])),
                "ssim": float(np.mean([m["ssim"] for m in ms]))})
    return {a: {"frames": sum(w["frames"] for w in ws), "walkers": len(ws),
                "eps_mean": float(np.mean([w["epsilon"] for w in ws])),
                "eps_worst": float(np.max([w["epsilon"] for w in ws])),
                "psnr_mean": float(np.mean([w["psnr"] for w in ws])),
                "ssim_mean": float(np.mean([w["ssim"] for w in ws])),
                "eps_per_walker": [round(w["epsilon"], 5) for w in ws]}
            for a, ws in sorted(per.items())}
