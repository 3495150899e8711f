"""The ``pvs`` command line: ``scenes`` locally, ``query`` (cell, segment, box, bad input) against
the real server on loopback."""

from __future__ import annotations

import json

import pytest

import pvs_cli


def test_scenes_lists_generators_locally(capsys):
    assert pvs_cli.main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in ("city", "rooms", "village", "stress"):
        assert name in out


def test_query_cell_segment_and_box(live_server, capsys):
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--cell", "1",
                         "--core", "sampling", "--param", "samples=4", "--param",
                         "resolution=32", "--ids"]) == 0
    cell = json.loads(capsys.readouterr().out)
    assert cell["cell"] == 1 and cell["core"] == "sampling" and cell["count"] > 0
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--segment",
                         "1,1.7,1,3,1.9,2.5", "--core", "from_segment", "--param",
                         "resolution=32", "--ids"]) == 0
    seg = json.loads(capsys.readouterr().out)
    assert seg["segment"] == [[1, 1.7, 1], [3, 1.9, 2.5]] and seg["count"] > 0
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--box",
                         "1,1.7,1,3,1.9,2.5", "--core", "sampling", "--param", "samples=4",
                         "--param", "resolution=32"]) == 0
    box = json.loads(capsys.readouterr().out)
    assert box["segment"] is None and box["box"] == [[1, 1.7, 1], [3, 1.9, 2.5]]


def test_query_errors_are_reported_not_raised(live_server, capsys):
    assert pvs_cli.main(["query", "--server", live_server, "--scene", "nope", "--cell",
                         "0"]) == 1
    assert "unknown_scene" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        pvs_cli.main(["query", "--server", live_server, "--scene", "tiny", "--segment", "1,2"])
    with pytest.raises(SystemExit):  # exactly one of --cell, --segment, --box
        pvs_cli.main(["query", "--server", live_server, "--scene", "tiny"])
