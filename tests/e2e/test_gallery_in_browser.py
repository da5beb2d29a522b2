"""In real headless Chromium: save a level from the editor, find its card in the gallery, open it and play it."""

from __future__ import annotations

import json

import pytest

from kinetix.formats import build
from kinetix.levels import to_document
from tests.e2e.conftest import Tab
from tests.server.conftest import running_app, wait_until
from tests.server.fake_editor import falling_win_spec

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gallery-e2e")
    level = folder / "falling_win.json"
    level.write_text(json.dumps(to_document(build(falling_win_spec()))))  # a green ball that falls onto blue
    with running_app(gallery=True, data=folder / "data", warm_sizes=("m",), level=str(level)) as app:
        yield app


def _wait(predicate, timeout=30.0):
    wait_until(predicate, timeout)


def test_save_from_the_editor_see_the_card_open_it_and_play(browser, app):
    tab = Tab(browser, app, 1280, 800)
    try:
        page, session = tab.page, tab.session
        page.get_by_role("button", name="Save to gallery", exact=True).click()
        dialog = page.get_by_role("dialog")
        dialog.locator("input").first.fill("E2E <i>falling</i> win")
        dialog.get_by_role("button", name="Save", exact=True).click()
        _wait(lambda: session.gallery_id is not None)
        level_id = session.gallery_id
        # The author token the save issued reaches the page's localStorage, where the gallery page reads it.
        _wait(lambda: page.evaluate("localStorage.getItem('kinetix.author_token')") == session.author_token)

        gallery = tab.context.new_page()
        gallery.on("request", lambda request: tab.requests.append(request.url))
        gallery.goto(app.url + "gallery")
        card = gallery.locator("article.card", has_text="E2E <i>falling</i> win")
        card.wait_for(timeout=30_000)
        assert card.locator(".name").inner_text() == "E2E <i>falling</i> win"  # shown as text, not as HTML
        assert card.locator(".plays").inner_text() == "0"

        card.locator("a.play").click()
        gallery.wait_for_function("window.__kinetixKeys && window.__kinetixKeys.ready()", timeout=60_000)
        nonce = gallery.get_attribute("#kinetix-session", "data-nonce")
        player = app.manager.session_by_nonce(nonce)
        _wait(lambda: player.gallery_id == level_id)
        _wait(lambda: player.mode == "ready")  # opened for play: it waits for the player's first key
        gallery.mouse.click(300, 300)  # focus the canvas (clicks do nothing while playing)
        gallery.keyboard.press("Space")
        _wait(lambda: player.mode == "ended")
        assert player._result == "solved"
        _wait(lambda: app.store.stats(level_id)["human_plays"] == 1)

        gallery.goto(app.url + "gallery")
        card = gallery.locator("article.card", has_text="E2E <i>falling</i> win")
        card.wait_for(timeout=30_000)
        assert card.locator(".plays").inner_text() == "1"
        assert card.locator(".human").inner_text() == "100%"
        tab.assert_local_only()
    finally:
        tab.close()
