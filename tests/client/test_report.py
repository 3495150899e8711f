"""Tests of client.report: the files of a run and their documented keys."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from PIL import Image

from client.metrics import PSNR_CAP_DB
from client.report import format_summary, plot_panels, save_frame_images, write_report


def _frames():
    return [
        {"t": 0.0, "epsilon": 0.0, "psnr": math.inf, "ssim": 1.0, "stalled": False, "tris": 10},
        {"t": 0.1, "epsilon": 2.0, "psnr": 30.0, "ssim": 0.9, "stalled": True, "tris": 12},
        {
            "t": 0.2,
            "epsilon": 1.0,
            "psnr": np.float64(40.0),
            "ssim": 0.8,
            "stalled": np.bool_(True),
        },
    ]


def _strict(text: str):
    def reject(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=reject)


def test_write_report_files_and_keys(tmp_path):
    meta = {"scene": "room", "core": "dummy", "cell_size": 4.0}
    summary = write_report(tmp_path / "run", _frames(), meta)
    out = tmp_path / "run"
    on_disk = _strict((out / "summary.json").read_text())
    assert on_disk == summary
    for key in ("meta", "frames", "epsilon", "psnr", "ssim", "stalls", "summary"):
        assert key in on_disk
    assert on_disk["meta"] == meta
    assert on_disk["epsilon"] == pytest.approx(1.0)
    assert on_disk["psnr"] == pytest.approx((PSNR_CAP_DB + 30.0 + 40.0) / 3)
    assert on_disk["ssim"] == pytest.approx(0.9)
    assert on_disk["stalls"] == 2
    assert on_disk["summary"]["psnr"]["max"] == PSNR_CAP_DB
    assert on_disk["summary"]["epsilon"] == {"mean": 1.0, "min": 0.0, "max": 2.0, "count": 3}
    assert on_disk["summary"]["tris"]["mean"] == pytest.approx(11.0)
    assert "t" not in on_disk["summary"] and "stalled" not in on_disk["summary"]
    assert len(on_disk["frames"]) == 3
    assert on_disk["frames"][0]["psnr"] is None  # +inf in strict JSON
    assert on_disk["frames"][2]["stalled"] is True

    with (out / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 3
    assert list(rows[0]) == ["t", "epsilon", "psnr", "ssim", "stalled", "tris"]
    assert float(rows[0]["psnr"]) == math.inf and float(rows[1]["epsilon"]) == 2.0
    assert rows[2]["tris"] == ""

    with Image.open(out / "metrics.png") as im:
        assert im.size[0] > 300 and im.size[1] > 300


def test_empty_run(tmp_path):
    summary = write_report(tmp_path, [], {})
    assert summary["epsilon"] is None and summary["stalls"] == 0 and summary["summary"] == {}
    assert (tmp_path / "metrics.png").exists() and (tmp_path / "frames.csv").exists()
    assert "stalls: 0" in format_summary(summary)


def test_format_summary(tmp_path):
    summary = write_report(tmp_path, _frames(), {"scene": "room"})
    text = format_summary(summary)
    for word in ("epsilon", "psnr", "ssim", "mean", "min", "max", "stalls: 2"):
        assert word in text
    long = format_summary(summary, per_frame=True)
    assert len(long.splitlines()) >= len(text.splitlines()) + 4
    assert "inf" in long


def test_save_frame_images_marks_epsilon_pixels(tmp_path):
    h, w = 20, 30
    gt = np.full((h, w, 3), 200, np.uint8)
    color = gt.copy()
    color[5:10, 5:10] = (135, 206, 235)
    depth_gt = np.full((h, w), 5.0, np.float32)
    depth = depth_gt.copy()
    depth[5:10, 5:10] = np.inf
    path = save_frame_images(tmp_path / "img", "f0001", color, gt, depth, depth_gt)
    img = np.asarray(Image.open(path))
    assert img.shape == (h, 3 * w + 4, 3)
    np.testing.assert_array_equal(img[:, :w], color)
    np.testing.assert_array_equal(img[:, w + 2 : 2 * w + 2], gt)
    overlay = img[:, 2 * w + 4 :]
    red = np.all(overlay == (255, 0, 0), axis=-1)
    assert red.sum() == 25 and red[5:10, 5:10].all()
    with pytest.raises(ValueError):
        save_frame_images(tmp_path, "bad", color, gt[:-1], depth, depth_gt)


def _near_far_frames():
    return [
        {"frame": i, "t": 0.2 * i, "cell": 3, "epsilon": 20.0 + i, "psnr": 15.0, "ssim": 0.7,
         "epsilon_composed": 0.5 * i, "psnr_composed": 30.0 + i, "ssim_composed": 0.98,
         "delta_composed": 0.01 * i, "delta_conventional": 0.1 + 0.01 * i,
         "triangles_held": 1000 + i, "stalled": False}
        for i in range(4)
    ]


def test_integers_stay_integers(tmp_path):
    summary = write_report(tmp_path, _near_far_frames(), {"image": [256, 256], "frames": 4})
    on_disk = _strict((tmp_path / "summary.json").read_text())
    f = on_disk["frames"][1]
    assert f["frame"] == 1 and isinstance(f["frame"], int)
    assert isinstance(f["cell"], int) and isinstance(f["triangles_held"], int)
    assert isinstance(f["t"], float) and isinstance(f["epsilon_composed"], float)
    assert on_disk["meta"]["image"] == [256, 256] and isinstance(on_disk["meta"]["frames"], int)
    assert summary["frames"][1]["frame"] == 1
    assert '"frame": 1,' in (tmp_path / "summary.json").read_text()


def test_near_far_report_has_composed_metrics_and_delta(tmp_path):
    frames = _near_far_frames()
    summary = write_report(tmp_path, frames, {"scene": "city"})
    # Top-level means of the composed frame and of delta, next to the geometry-only ones.
    assert summary["epsilon_composed"] == pytest.approx(0.75)
    assert summary["delta_composed"] == pytest.approx(0.015)
    assert summary["delta_conventional"] == pytest.approx(0.115)
    assert summary["epsilon"] == pytest.approx(21.5)
    # The table lists them right after the main metrics.
    names = [line.split()[0] for line in format_summary(summary).splitlines()[1:]]
    assert names[:8] == ["epsilon", "psnr", "ssim", "epsilon_composed", "psnr_composed",
                         "ssim_composed", "delta_composed", "delta_conventional"]
    # Plot: geometry-only panels, composed panels, and delta morph vs conventional.
    panels = plot_panels(frames)
    keys = [k for _title, k in panels]
    assert keys == [("epsilon",), ("psnr",), ("ssim",), ("epsilon_composed",),
                    ("psnr_composed",), ("ssim_composed",),
                    ("delta_composed", "delta_conventional")]
    assert [k for _t, k in plot_panels(_frames())] == [("epsilon",), ("psnr",), ("ssim",)]
    with Image.open(tmp_path / "metrics.png") as im:
        wide, tall = im.size
    write_report(tmp_path / "plain", _frames(), {})
    with Image.open(tmp_path / "plain" / "metrics.png") as im:
        assert wide > im.size[0] and tall > im.size[1]  # the extra panels take room
