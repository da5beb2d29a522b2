"""Reloads, restarts and links in real Chromium: the one port, the reconnect, and drafts with their undo history."""

from __future__ import annotations

import contextlib
import re

import pytest

from tests.e2e.conftest import Tab, expect_page_error, wait_js
from tests.server.conftest import wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

READY = "window.__kinetixKeys && window.__kinetixKeys.ready()"


@contextlib.contextmanager
def server(data, port: int = 0):
    """A server on `port` (0: any) keeping its gallery and drafts in `data`; restarted by leaving and re-entering."""
    from server.app import App, Config

    app = App(Config(port=port, data=data, gallery=True, agents=False, warm_sizes=("m",), warm_batches=False,
                     warm_agent=False)).start()
    try:
        assert app.wait_until_warm(timeout=600)
        yield app
    finally:
        app.stop()


def _session(app, page):
    nonce = page.get_attribute("#kinetix-session", "data-nonce")
    wait_until(lambda: app.manager.session_by_nonce(nonce) is not None)
    return app.manager.session_by_nonce(nonce)


def _reload(app, page):
    page.reload()
    wait_js(page, READY)
    return _session(app, page)


def _draw_rectangle(tab) -> None:
    tab.page.get_by_role("button", name="Rect", exact=True).click()
    wait_until(lambda: tab.session.editor.tool == "rectangle")
    tab.drag((1.0, 1.0), (2.0, 1.4))


def test_draw_reload_restart_reload_keeps_the_drawing_and_undo(browser, tmp_path, page_errors):
    tab = None
    try:
        with server(tmp_path) as app:
            port = app.port
            tab = Tab(browser, app, 1280, 800)
            page = tab.page
            walls = len(tab.session.editor.spec.bodies)
            _draw_rectangle(tab)
            wait_until(lambda: len(tab.session.editor.spec.bodies) == walls + 1)
            drawn = tab.session.editor.spec
            page.wait_for_url(re.compile(r"\?draft=[A-Za-z0-9_-]+$"), timeout=20_000)  # the address names the draft
            address = page.url
            assert "websocket=" not in address

            session = _reload(app, page)  # a reload: the same draft, the same undo history
            wait_until(lambda: session.editor.spec == drawn)
            assert page.url == address and session.editor.can_undo
            nonce = session.nonce
        # The server stops and starts again on the same port under the open page: the page reconnects by itself
        # (a new session) and reopens its draft.
        with server(tmp_path, port) as app:
            wait_js(page, f"document.getElementById('kinetix-session') && document.getElementById("
                          f"'kinetix-session').getAttribute('data-nonce') !== '{nonce}' && {READY}")
            session = _session(app, page)
            wait_until(lambda: session.editor.spec == drawn)
            session = _reload(app, page)  # and a reload after the restart too
            wait_until(lambda: session.editor.spec == drawn)
            assert page.url == address
            page.mouse.click(*tab.xy(4.5, 4.5))  # focus the canvas (an empty spot)
            page.keyboard.press("Control+z")  # the undo history came back with the draft
            wait_until(lambda: len(session.editor.spec.bodies) == walls)
            tab.assert_local_only()
    finally:
        if tab is not None:
            tab.close()
    # while a server was down under the open page (the restart, and the stop before the tab closed), its reconnect
    # attempts were refused: how many depends on the timing
    expect_page_error(page_errors, "/keys' failed: Error in connection establishment", required=False)


def test_save_to_gallery_puts_the_level_in_the_address_and_a_stale_websocket_link_works(browser, tmp_path):
    with server(tmp_path) as app:
        tab = Tab(browser, app, 1280, 800)
        try:
            page, session = tab.page, tab.session
            _draw_rectangle(tab)
            page.wait_for_url(re.compile(r"\?draft="), timeout=20_000)
            page.get_by_role("button", name="Save to gallery", exact=True).click()
            dialog = page.get_by_role("dialog")
            dialog.get_by_label("Name").fill("E2E reload")
            dialog.get_by_role("button", name="Save", exact=True).click()
            wait_until(lambda: session.gallery_id is not None)
            page.wait_for_url(f"**/?level={session.gallery_id}", timeout=20_000)
            # An old bookmark with the internal port of an earlier start still opens the level (through the one port).
            other = tab.context.new_page()
            tab.watch_csp(other)
            other.goto(f"{app.url}?level={session.gallery_id}&websocket=ws://127.0.0.1:9")
            wait_js(other, READY)
            opened = _session(app, other)
            wait_until(lambda: opened.gallery_id == session.gallery_id)
            assert other.url == f"{app.url}?level={session.gallery_id}"
            tab.assert_local_only()
        finally:
            tab.close()
