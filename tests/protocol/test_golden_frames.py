"""The committed golden samples (``tests/protocol/golden/``) are what the Python encoders write
today and decode as the manifest says; the browser viewer's decoder is checked against the same
files (``tests/viewer/test_decode_js.py``). ``PVS_WRITE_GOLDEN=1`` rewrites them after a
deliberate protocol change."""

from __future__ import annotations

import json
import os

import pytest

from protocol.messages import parse_server_message
from tests.protocol.golden import GOLDEN_DIR, _assemble, decode_frame, normalise, write_golden

#: Samples whose bytes depend on the zlib build (compressed cubemaps): compared decoded only.
ZLIB_DEPENDENT = ("cubemap_zlib", "cubemap_empty", "cubemap_one_range", "bad_cubemap_zlib")


def test_golden_files_are_what_the_encoders_write(tmp_path):
    if os.environ.get("PVS_WRITE_GOLDEN"):
        write_golden(GOLDEN_DIR)
    fresh = write_golden(tmp_path)
    committed = json.loads((GOLDEN_DIR / "manifest.json").read_text())
    assert [e["name"] for e in committed] == [e["name"] for e in fresh]
    for old, new in zip(committed, fresh, strict=True):
        # The decoders' verdict on each sample holds for the committed files too.
        assert old["expect"] == new["expect"], old["name"]
        if old["name"] in ZLIB_DEPENDENT:
            continue
        for f in old["files"]:
            assert (GOLDEN_DIR / f).read_bytes() == (tmp_path / f).read_bytes(), f


def test_golden_samples_cover_every_kind_and_refusal():
    manifest = json.loads((GOLDEN_DIR / "manifest.json").read_text())
    kinds = {e["expect"]["value"].get("kind", e["expect"]["value"].get("type"))
             for e in manifest if e["expect"]["ok"]}
    assert {1, 2, 3, 4, "welcome", "cell_begin", "cell_end", "drop", "error"} <= kinds
    errors = {e["expect"]["error"] for e in manifest if not e["expect"]["ok"]}
    assert errors == {"FrameError", "bad_json", "invalid_message", "unknown_type"}
    assert sum(not e["expect"]["ok"] for e in manifest) >= 25


@pytest.mark.parametrize("name", ["geometry", "keyframe_windows", "msg_welcome"])
def test_committed_samples_decode_as_the_manifest_says(name):
    entry = next(e for e in json.loads((GOLDEN_DIR / "manifest.json").read_text())
                 if e["name"] == name)
    data = [(GOLDEN_DIR / f).read_bytes() for f in entry["files"]]
    got = {"frame": lambda: decode_frame(data[0]), "assemble": lambda: _assemble(data),
           "message": lambda: parse_server_message(data[0])}[entry["what"]]()
    assert normalise(got) == entry["expect"]["value"]
