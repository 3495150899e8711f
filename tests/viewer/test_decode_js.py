"""The viewer's JavaScript decoder (``server/viewer/decode.js``, run by node) makes of every
golden sample what the Python decoders make of it: the same values for the valid frames and
messages, a refusal of the same kind (FrameError, or the same ErrorCode) for the others."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

from tests.protocol.golden import GOLDEN_DIR

SCRIPT = Path(__file__).with_name("decode_golden.mjs")


def _close(a, b) -> bool:
    """Equal JSON values; floats within float32 rounding (ranges are decoded through exp)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(b, int | float) and math.isclose(a, b, rel_tol=2**-23, abs_tol=0)
    return a == b


def run_js_decoder(folder: Path) -> list[dict]:
    node = shutil.which("node") or shutil.which("nodejs")
    assert node, "node is not installed (scripts/setup.sh installs nodejs)"
    out = subprocess.run([node, str(SCRIPT), str(folder)], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(out.stdout)


def test_js_decoder_agrees_with_python_on_every_golden_sample():
    manifest = json.loads((GOLDEN_DIR / "manifest.json").read_text())
    results = {r["name"]: r for r in run_js_decoder(GOLDEN_DIR)}
    assert results.keys() == {e["name"] for e in manifest}
    for entry in manifest:
        want, got = entry["expect"], results[entry["name"]]
        assert got["ok"] == want["ok"], (entry["name"], got.get("message"))
        if want["ok"]:
            assert _close(want["value"], got["value"]), entry["name"]
        else:
            assert got["error"] == want["error"], (entry["name"], got.get("message"))


def test_js_decoder_refuses_a_corrupted_valid_frame(tmp_path):
    # The comparison can fail: a frame the manifest calls valid, one byte of its triangle
    # count changed, must come back refused.
    manifest = json.loads((GOLDEN_DIR / "manifest.json").read_text())
    entry = next(e for e in manifest if e["name"] == "geometry")
    data = bytearray((GOLDEN_DIR / entry["files"][0]).read_bytes())
    data[24] += 1
    (tmp_path / entry["files"][0]).write_bytes(bytes(data))
    (tmp_path / "manifest.json").write_text(json.dumps([entry]))
    (result,) = run_js_decoder(tmp_path)
    assert result["ok"] is False and result["error"] == "FrameError"
