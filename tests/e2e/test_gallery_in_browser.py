"""In real headless Chromium: save a level from the editor, find its card in the gallery, open it and play it."""

from __future__ import annotations

import json

import pytest

from kinetix.formats import build
from kinetix.levels import to_document
from tests.e2e.conftest import Tab, expect_page_error, wait_js
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


def _server_text_values(session) -> set:
    """The values the server holds for the tab's GUI inputs (viser keeps one handle per input)."""
    handles = list(session.client.gui._gui_input_handle_from_uuid.values())
    return {h.value for h in handles if isinstance(getattr(h, "value", None), str)}


def _fill(session, field, text: str) -> None:
    """Type into a dialog field and wait until the server holds the value. Each field reaches the server as a GUI
    update of its own; on a loaded machine one was seen to be lost after a fill, so the fill is retried."""
    for _ in range(3):
        field.fill(text)
        try:
            wait_until(lambda: text in _server_text_values(session), 10.0)
            return
        except TimeoutError:
            field.fill("")
    raise AssertionError(f"the server never received {text!r} (held: {_server_text_values(session)})")


def test_save_from_the_editor_see_the_card_open_it_and_play(browser, app, page_errors):
    tab = Tab(browser, app, 1280, 800)
    try:
        page, session = tab.page, tab.session
        page.get_by_role("button", name="Save to gallery", exact=True).click()
        dialog = page.get_by_role("dialog")
        # Every field of the dialog is found by its label (viser's labels tied to the inputs by labels.js).
        for label, text in (("Name", "E2E <i>falling</i> win"), ("Description", "a ball falls"),
                            ("Tags (comma-separated)", "e2e, falls")):
            _fill(session, dialog.get_by_label(label, exact=True), text)
        dialog.get_by_role("button", name="Save", exact=True).click()
        _wait(lambda: session.gallery_id is not None)
        level_id = session.gallery_id
        saved = app.store.get_level(level_id)
        assert (saved["description"], saved["tags"]) == ("a ball falls", ["e2e", "falls"])
        # The author token the save issued reaches the page's localStorage, where the gallery page reads it.
        _wait(lambda: page.evaluate("localStorage.getItem('kinetix.author_token')") == session.author_token)

        gallery = tab.context.new_page()
        gallery.on("request", lambda request: tab.requests.append(request.url))
        tab.watch_csp(gallery)
        gallery.goto(app.url + "gallery")
        card = gallery.locator("article.card", has_text="E2E <i>falling</i> win")
        card.wait_for(timeout=30_000)
        assert card.locator(".name").inner_text() == "E2E <i>falling</i> win"  # shown as text, not as HTML
        assert card.locator(".plays").inner_text() == "0"

        card.locator("a.play").click()
        wait_js(gallery, "window.__kinetixKeys && window.__kinetixKeys.ready()")
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

        # A vote from the page passes the JSON and Origin checks, twice counts once, and the page's author token
        # (from the save; the tab played the level with it) is the voter.
        card.locator(".up").click()
        _wait(lambda: app.store.stats(level_id)["votes_up"] == 1)
        card = gallery.locator("article.card", has_text="E2E <i>falling</i> win")
        # The page replaces the card once the vote's answer is in (a click on the old card voted up again).
        card.locator(".up.mine").wait_for(timeout=30_000)
        card.locator(".up").click()  # toggles the vote off: value 0
        _wait(lambda: app.store.stats(level_id)["votes_up"] == 0)
        card.locator(".up:not(.mine)").wait_for(timeout=30_000)
        gallery.locator("article.card", has_text="E2E <i>falling</i> win").locator(".up").click()
        _wait(lambda: app.store.stats(level_id)["votes_up"] == 1)
        assert gallery.locator("#status").inner_text() == ""  # no "Vote failed"

        # A visitor who never played the level cannot vote (issue 34): the page says why, nothing counts and no
        # identity or cookie is issued.
        visitor = tab.context.browser.new_context()
        try:
            page = visitor.new_page()
            tab.watch_csp(page)
            page.on("request", lambda request: tab.requests.append(request.url))
            page.goto(app.url + "gallery")
            theirs = page.locator("article.card", has_text="E2E <i>falling</i> win")
            authors = app.store.counts()["authors"]
            theirs.locator(".up").click()
            _wait(lambda: "only someone who played this level may vote" in page.locator("#status").inner_text())
            assert app.store.stats(level_id)["votes_up"] == 1 and app.store.counts()["authors"] == authors
            assert visitor.cookies() == [] and page.evaluate("localStorage.getItem('kinetix.author_token')") is None
            expect_page_error(page_errors, "/vote: Failed to load resource: the server responded with a status of 403")
        finally:
            visitor.close()
        tab.assert_local_only()
    finally:
        tab.close()


def test_save_keeps_every_field_typed_right_before_the_click(browser, app):
    """viser's client sends panel updates through one throttled sender that keeps only the newest: a Description
    filled right before Tags was never sent, and the level was saved without it (6 times in 7)."""
    tab = Tab(browser, app, 1280, 800)
    try:
        page, session = tab.page, tab.session
        for attempt in range(3):
            page.get_by_role("button", name="Save to gallery", exact=True).click()
            dialog = page.get_by_role("dialog")
            name = f"fast fill {attempt}"
            dialog.get_by_label("Name", exact=True).fill(name)  # no pause between the fields, nor before Save
            dialog.get_by_label("Description", exact=True).fill(f"typed just before the tags ({attempt})")
            dialog.get_by_label("Tags (comma-separated)", exact=True).fill("fast, fill")
            dialog.get_by_role("button", name="Save", exact=True).click()
            _wait(lambda: session.gallery_id is not None and app.store.get_level(session.gallery_id)["name"] == name)
            saved = app.store.get_level(session.gallery_id)
            assert (saved["description"], saved["tags"]) == (f"typed just before the tags ({attempt})",
                                                             ["fast", "fill"])
            page.get_by_role("dialog").wait_for(state="detached", timeout=10_000)
        tab.assert_local_only()
    finally:
        tab.close()
