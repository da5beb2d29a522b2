"""The editor refuses out-of-range values with the level format's own ranges (kinetix.ranges; issue 26 §1)."""

import json

import pytest

from server.editor import Editor, EditorError
from server.editor.properties import PARAM_RANGES
from tests.server.editor.scenes import hinged_editor


def test_an_upload_with_an_out_of_range_field_is_refused_naming_it():
    ed = Editor()
    document = json.loads(ed.export("ours"))
    document["env"]["max_timesteps"] = 2147483648
    before = ed.export("ours")
    with pytest.raises(EditorError, match=r"env.max_timesteps: 2147483648 is out of range \[1, 100000\]"):
        ed.import_bytes(json.dumps(document).encode(), "huge.json")
    assert ed.export("ours") == before  # nothing changed


def test_edits_beyond_the_ranges_are_refused_and_change_nothing():
    ed = hinged_editor()
    before = ed.export("ours")
    assert "frame_skip" in ed.set_params(frame_skip=1_000_000)
    assert "dt" in ed.set_params(dt=1e6)
    assert "gravity" in ed.set_gravity(0.0, -1e4)
    ed.selection = [("body", 5)]
    refusal = ed.set_properties(density=5000.0)  # positive, so only the range check can refuse it
    assert refusal is not None and "density: 5000 is out of range [0.001, 1000]" in refusal
    assert ed.export("ours") == before


def test_the_settings_panel_uses_the_format_ranges():
    assert PARAM_RANGES["max_timesteps"] == (int, 1, 100_000) and PARAM_RANGES["frame_skip"] == (int, 1, 16)
    ed = hinged_editor()
    assert ed.set_params(max_timesteps=100_000, frame_skip=16) is None
