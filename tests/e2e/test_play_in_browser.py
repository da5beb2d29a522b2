"""In real headless Chromium: keyboard play through keys.js and /keys, frames on the viser canvas."""

from __future__ import annotations

import io
import json
import time

import numpy as np
import pytest
from PIL import Image

from tests.e2e.conftest import LEVELS, Tab
from tests.server.conftest import running_app, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    # The car level with a long episode, so slow software-GL screenshots cannot outlast it.
    doc = json.loads((LEVELS / "car_right.json").read_text())
    doc["env"]["max_timesteps"] = 5000
    level = tmp_path_factory.mktemp("levels") / "car_long.json"
    level.write_text(json.dumps(doc))
    with running_app(warm_sizes=("m",), level=str(level)) as app:
        yield app


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def _wait(predicate, timeout=15.0):
    wait_until(predicate, timeout)


def test_arrow_right_drives_the_motor_and_release_stops_it(browser, app):
    tab = Tab(browser, app)
    try:
        page, session = tab.page, tab.session
        page.mouse.click(400, 300)  # focus the page
        page.keyboard.press("Space")
        _wait(lambda: session.mode == "play")
        time.sleep(1.0)  # let the car settle on its wheels
        still = _pixels(tab.canvas_png(300, 260))  # the ground and the car, away from the HUD text at the top
        page.keyboard.down("ArrowRight")
        _wait(lambda: "ArrowRight" in session.held)
        assert session.keys_action()[0] == 1  # car right's wheels are joint body a: clockwise is +1 (value 1)
        # The car moves on the canvas; on a loaded 2-core machine the browser can lag, so look for up to 20 s.
        deadline = time.monotonic() + 20
        while np.abs(_pixels(tab.canvas_png(300, 260)) - still).sum() <= 10_000:
            assert time.monotonic() < deadline, "the frames did not change while ArrowRight was held"
            time.sleep(0.5)
        page.keyboard.up("ArrowRight")
        _wait(lambda: not session.held)
        assert not session.keys_action().any()  # no key held: the motor is no longer driven
        page.keyboard.press("Space")
        _wait(lambda: session.mode == "edit")
        tab.assert_local_only()
    finally:
        tab.close()


def test_frames_are_drawn_over_viser_canvas_and_clicks_still_reach_it(browser, app):
    # static/frames.js takes the frames out of viser's message batches and draws them on its own 2D canvas over
    # viser's WebGL canvas; viser's background stays empty and the pointer still goes to viser's canvas.
    tab = Tab(browser, app)
    try:
        page, session = tab.page, tab.session
        geometry = page.evaluate(
            "() => { const o = document.getElementById('kinetix-frame'); if (!o) return null; "
            "const v = o.previousElementSibling; const a = o.getBoundingClientRect(), b = v.getBoundingClientRect(); "
            "return {tag: v.tagName, pointer: getComputedStyle(o).pointerEvents, size: [o.width, o.height], "
            "box: [a.x, a.y, a.width, a.height], viser: [b.x, b.y, b.width, b.height]}; }")
        assert geometry is not None, "no frame overlay on the page"
        assert geometry["tag"] == "CANVAS" and geometry["pointer"] == "none"
        assert geometry["box"] == pytest.approx(geometry["viser"], abs=1.0)  # it covers viser's canvas exactly
        assert geometry["size"] == [session._view.width, session._view.height]  # one frame pixel per canvas pixel
        drawn = page.evaluate("() => window.__kinetixFrames.drawn")
        calls = len(session.pointer_log)
        page.mouse.click(400, 300)  # lands on viser's canvas under the overlay: the session sees the click
        _wait(lambda: len(session.pointer_log) > calls)
        page.keyboard.press("Space")
        _wait(lambda: session.mode == "play")
        time.sleep(1.5)
        played = page.evaluate("() => window.__kinetixFrames.drawn") - drawn
        assert played >= 10, f"only {played} frames drawn in 1.5 s of play"
        assert _pixels(tab.canvas_png(300, 260)).std() > 5  # the level is on screen, not a blank canvas
        page.keyboard.press("Space")
        _wait(lambda: session.mode == "edit")
    finally:
        tab.close()
