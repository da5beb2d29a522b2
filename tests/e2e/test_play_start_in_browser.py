"""In real headless Chromium, a player's first minutes: a level opened for play waits for the first key (with a
hint on the canvas), Right rolls the shipped "car right" to the right, notices leave the HUD and key legend clear,
and the best run the gallery shows is the play that set the best time, a race win included."""

from __future__ import annotations

import io
import json
import time

import numpy as np
import pytest
from PIL import Image

from kinetix.recording import read_recording
from server.play import draw
from tests.e2e.conftest import LEVELS, Tab, canvas_box, wait_js
from tests.server.conftest import running_app, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with running_app(gallery=True, data=tmp_path_factory.mktemp("data"), warm_sizes=("m",)) as app:
        yield app


def _wait(predicate, timeout=30.0):
    wait_until(predicate, timeout)


def _car_right(app, name: str) -> str:
    level_id, _ = app.store.create_level(name, json.loads((LEVELS / "car_right.json").read_text()))
    return level_id


def _open(tab: Tab, query: str):
    """Load `/?<query>` in the tab and return its new session."""
    page = tab.page
    page.goto(tab.app.url + query)
    wait_js(page, "window.__kinetixKeys && window.__kinetixKeys.ready()")
    session = tab.app.manager.session_by_nonce(page.get_attribute("#kinetix-session", "data-nonce"))
    assert session is not None
    return session


def _hint_shown(tab: Tab) -> bool:
    """Whether the start hint's banner is on the page: it spans the canvas's whole width at mid-height, where the
    left margin otherwise shows the level's dark left wall."""
    box = canvas_box(tab.page)
    png = tab.page.screenshot(clip={"x": box["x"] + 4, "y": box["y"] + box["height"] / 2, "width": 4, "height": 2},
                              timeout=60_000)
    return int(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).min()) >= 235  # white, after JPEG


def _chassis_x(session) -> float:
    return float(np.asarray(session._play[1].level.sim.bodies.position)[4, 0])  # car right's body 4


def test_play_link_waits_for_the_first_key_then_right_rolls_car_right_right(browser, app):
    level_id = _car_right(app, "car right (play link)")
    tab = Tab(browser, app, 1280, 800)
    try:
        session = _open(tab, f"?level={level_id}&mode=play")
        _wait(lambda: session.mode == "ready")
        start = np.asarray(session._play[1].level.sim.bodies.position).copy()
        _wait(lambda: _hint_shown(tab))  # "Press Space or an arrow key to start" is on the canvas
        time.sleep(1.0)
        assert session.mode == "ready" and session._steps == 0, "the physics started without input"
        assert np.array_equal(np.asarray(session._play[1].level.sim.bodies.position), start)

        tab.page.mouse.click(400, 300)  # focus the page (clicks do nothing in play)
        tab.page.keyboard.down("ArrowRight")  # starts the play and drives it from the first step
        _wait(lambda: session._steps >= 10)
        tab.page.keyboard.up("ArrowRight")  # (released: the car coasts, far from the goal, while the page is read)
        assert _chassis_x(session) > float(start[4, 0]) + 0.05, "the first key drove the car right"
        _wait(lambda: not _hint_shown(tab))  # the hint went with the first key
        assert session.mode == "play"
        tab.page.keyboard.down("ArrowRight")
        _wait(lambda: session.mode == "ended", timeout=60)
        tab.page.keyboard.up("ArrowRight")
        assert session._result == "solved", "holding Right drives car right to the blue ball on its right"
        assert _chassis_x(session) > 2.0 > float(start[4, 0])
        # The play is over: the Play folder offers Play again and Edit, and nothing to stop.
        panel = tab.page.get_by_role("button", name="Play again", exact=True)
        panel.wait_for(timeout=10_000)
        assert tab.page.get_by_role("button", name="Edit", exact=True).is_visible()
        assert tab.page.get_by_role("button", name="Stop (Space)", exact=True).count() == 0
        tab.page.keyboard.press("Space")  # Space goes back to editing, as Edit does
        _wait(lambda: session.mode == "edit")
        tab.page.get_by_role("button", name="Play (Space)", exact=True).wait_for(timeout=10_000)
        tab.assert_local_only()
    finally:
        tab.close()


def test_notices_leave_the_hud_and_key_legend_clear(browser, app):
    tab = Tab(browser, app, 1280, 800)
    try:
        session = _open(tab, f"?level={_car_right(app, 'car right (notices)')}")
        _wait(lambda: session.gallery_id is not None)
        session.client.add_notification("Saved to the gallery", "Share it: /?level=abc", auto_close_seconds=30.0)
        _wait(lambda: tab.page.locator(".mantine-Notification-root", has_text="Saved to the gallery").count() > 0)
        time.sleep(1.0)  # let the notice slide in
        notices = tab.page.evaluate("""() => [...document.querySelectorAll('.mantine-Notification-root')]
            .map(e => e.getBoundingClientRect()).map(r => [r.x, r.y, r.x + r.width, r.y + r.height])""")
        # The HUD line and the legend rows, in page pixels: top left of the level's box in the frame.
        box = canvas_box(tab.page)
        view = session._view
        scale = box["width"] / view.width
        ox, oy = view.origin
        legend_rows = sum(map(len, draw.used_bindings(draw.scene_of(session.editor.level_file().level))))
        hud = [box["x"] + ox * scale, box["y"] + oy * scale, box["x"] + (ox + 340) * scale,
               box["y"] + (oy + draw.TEXT_TOP + draw.LEGEND_ROW * legend_rows) * scale]
        assert legend_rows == 1 and notices
        for x0, y0, x1, y1 in notices:
            assert x1 <= hud[0] or x0 >= hud[2] or y1 <= hud[1] or y0 >= hud[3], f"a notice covers the HUD: {notices}"
            assert box["x"] <= x0 and x1 <= box["x"] + box["width"], "notices stay over the canvas, not the panel"
    finally:
        tab.close()


def test_the_best_run_is_the_play_that_set_the_best_time_a_race_win_included(browser, app):
    from kinetix.agents.policy import load_policy
    from server.agents.play import observing_env

    level_id = _car_right(app, "car right (best run)")
    tab = Tab(browser, app, 1280, 800)
    try:
        page = tab.page
        # A slow human solve: started with Space, Right held only after a pause.
        session = _open(tab, f"?level={level_id}&mode=play")
        _wait(lambda: session.mode == "ready")
        page.mouse.click(400, 300)
        page.keyboard.press("Space")
        _wait(lambda: session._steps >= 15)
        page.keyboard.down("ArrowRight")
        _wait(lambda: session.mode == "ended", timeout=60)
        page.keyboard.up("ArrowRight")
        assert session._result == "solved"
        slow = session._steps
        _wait(lambda: app.store.stats(level_id)["has_best_run"])

        # A faster race win: Right held from the first key; the agent (no-op) never solves car right.
        noop = load_policy("noop", observing_env(session.editor.level_file().size))
        race = app.agents.race(session, policy=noop)
        assert session.mode == "ready"
        page.keyboard.down("ArrowRight")
        _wait(lambda: race.winner is not None, timeout=60)
        page.keyboard.up("ArrowRight")
        assert race.winner == "human" and race.recorded.wait(30)
        assert race.human.steps < slow
        stats = app.store.stats(level_id)
        assert stats["best_human_steps"] == race.human.steps and stats["has_best_run"]

        # "Watch best run" replays the race's run: its step count is the best time's.
        session = _open(tab, f"?level={level_id}&mode=replay")
        _wait(lambda: session.mode == "replay" and session.replay is not None)
        assert session.replay.recording.num_steps == stats["best_human_steps"]
        kept = read_recording(app.agents.runs.best_run_file(level_id), frames=False)
        assert kept.num_steps == race.human.steps and kept.solved
        tab.assert_local_only()
    finally:
        tab.close()


def test_notices_leave_the_race_banner_and_the_middle_banner_clear(browser, app):
    from kinetix.agents.policy import load_policy
    from server.agents.play import observing_env, race_banner_box

    tab = Tab(browser, app, 1280, 800)
    try:
        session = _open(tab, f"?level={_car_right(app, 'car right (race notices)')}")
        _wait(lambda: session.gallery_id is not None)
        noop = load_policy("noop", observing_env(session.editor.level_file().size))
        app.agents.race(session, policy=noop)
        _wait(lambda: session.mode == "ready")  # "Press Space or an arrow key to start" on the race's banner
        for title in ("Saved to the gallery", "Something else", "And a third notice"):
            session.client.add_notification(title, "Share it: /?level=abc " * 4, auto_close_seconds=30.0)
        _wait(lambda: tab.page.locator(".mantine-Notification-root").count() >= 3)
        time.sleep(1.0)  # let the notices slide in
        notices = tab.page.evaluate("""() => [...document.querySelectorAll('.mantine-Notification-root')]
            .map(e => e.getBoundingClientRect()).filter(r => r.height > 0)
            .map(r => [r.x, r.y, r.x + r.width, r.y + r.height])""")
        # Where the notices' stack is cut off, if it is (a stack that scrolls shows nothing below its box).
        clip = tab.page.evaluate("""() => { const e = document.querySelector('.mantine-Notifications-root');
            const r = e.getBoundingClientRect();
            return getComputedStyle(e).overflowY === 'visible' ? 1e9 : r.y + r.height; }""")
        box = canvas_box(tab.page)
        view = session._view
        scale = box["height"] / view.height
        left, top, right, bottom = race_banner_box(view.width, view.height)
        banner = [box["x"] + left * scale, box["y"] + top * scale, box["x"] + right * scale, box["y"] + bottom * scale]
        middle = box["y"] + box["height"] / 2 - 36 * scale  # a one-line banner at mid-height (server.play.draw)
        assert notices
        for x0, y0, x1, y1 in notices:
            visible_bottom = min(y1, clip)
            assert visible_bottom <= banner[1] or y0 >= banner[3] or x1 <= banner[0] or x0 >= banner[2], \
                f"a notice covers the race banner: {notices}, banner {banner}"
            assert visible_bottom <= middle, f"a notice reaches the middle banner: {notices}, cut at {clip}"
    finally:
        tab.close()
