"""In real headless Chromium: the gallery card's "Watch agent" opens the level in a tab where the general agent
plays it (frames on the canvas, an agent play in the gallery stats), and the Agent folder's "Race the agent"
button splits the canvas into the human's and the agent's halves."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from kinetix.formats import build
from kinetix.levels import to_document
from tests.e2e.conftest import Tab, canvas_box, wait_js
from tests.server.conftest import running_app, wait_until
from tests.server.fake_editor import falling_win_spec

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with running_app(gallery=True, data=tmp_path_factory.mktemp("agent-e2e"), warm_sizes=("m",)) as app:
        yield app


def _wait(predicate, timeout=60.0):
    wait_until(predicate, timeout)


def test_watch_agent_from_a_gallery_card_and_race_from_the_agent_folder(browser, app):
    level_id, _ = app.store.create_level("E2E agent watch", to_document(build(falling_win_spec())))
    tab = Tab(browser, app, 1280, 800)
    try:
        gallery = tab.context.new_page()
        gallery.on("request", lambda request: tab.requests.append(request.url))
        gallery.goto(app.url + "gallery")
        card = gallery.locator("article.card", has_text="E2E agent watch")
        card.wait_for(timeout=30_000)
        card.locator("a.watch").click()
        wait_js(gallery, "window.__kinetixKeys && window.__kinetixKeys.ready()")
        nonce = gallery.get_attribute("#kinetix-session", "data-nonce")
        watcher = app.manager.session_by_nonce(nonce)
        _wait(lambda: watcher.gallery_id == level_id)
        _wait(lambda: watcher.mode == "ended", timeout=180)  # may compile the general agent first
        assert watcher._result == "solved"
        _wait(lambda: app.store.stats(level_id)["agent_plays"] == 1)
        assert app.store.stats(level_id)["human_plays"] == 0

        # Race in the same tab: the canvas shows two halves with a dark divider in the middle.
        gallery.get_by_role("button", name="Race the agent", exact=True).click()
        _wait(lambda: watcher.player == "race")
        race = watcher.controller
        _wait(lambda: watcher.mode == "ready")  # both sides wait for the human's first key
        gallery.mouse.click(300, 300)  # focus the canvas (clicks do nothing while playing)
        gallery.keyboard.press("Space")
        _wait(lambda: race.winner is not None, timeout=120)
        assert race.winner == "tie"  # nobody presses anything and the ball falls onto the goal on both sides
        _wait(lambda: app.store.stats(level_id)["human_plays"] == 1 and app.store.stats(level_id)["agent_plays"] == 2)
        gallery.wait_for_timeout(500)
        # The canvas is the page's largest element left of the docked panel: look at its middle.
        box = canvas_box(gallery)
        shot = np.asarray(Image.open(io.BytesIO(gallery.screenshot(clip=box, timeout=60_000))).convert("RGB"))
        h, w = shot.shape[:2]
        middle = shot[h // 2 - 50: h // 2 + 50, w // 2 - 6: w // 2 + 6].mean(axis=2)
        assert (middle.min(axis=1) < 100).all(), "the divider between the two halves is on the canvas"
        quarter = shot[h // 2 - 50: h // 2 + 50, w // 4 - 6: w // 4 + 6].mean(axis=2)
        assert not (quarter.min(axis=1) < 100).all(), "no such divider a quarter of the way across"
        tab.assert_local_only()
    finally:
        tab.close()
