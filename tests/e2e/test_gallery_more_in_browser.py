"""The gallery page's "More levels" in a real headless Chromium, against the API's own pages."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest

from server.gallery.checks import SavedLevel
from server.gallery.store import Store
from tests.e2e.conftest import wait_js
from tests.gallery.conftest import level_doc
from tests.gallery.test_concurrency import _free_port, _start_server


@pytest.mark.e2e
@pytest.mark.slow
def test_more_levels_shows_the_second_page_once_and_then_hides(browser, tmp_path: Path):
    """30 levels: the page shows the API's first 24, "More levels" adds exactly the API's second page, then hides;
    asking for more again adds nothing. A shared link is not shown in the error colour."""
    db = tmp_path / "gallery.sqlite3"
    store = Store(f"sqlite:///{db}", seed_dir=None)
    for k in range(30):
        store.create_level(f"level {k:02d}", {}, prepared=SavedLevel("m", json.dumps(level_doc()), b"png"))
    store.close()
    port = _free_port()
    server = _start_server(db, port)
    try:
        base = f"http://127.0.0.1:{port}"
        first = httpx.get(f"{base}/api/levels", params={"sort": "newest", "limit": 24}).json()
        second = httpx.get(f"{base}/api/levels", params={"sort": "newest", "limit": 24,
                                                         "cursor": first["next"]}).json()
        assert len(first["items"]) == 24 and len(second["items"]) == 6 and second["next"] is None
        # The session's browser (tests/e2e/conftest.py): a second sync_playwright in one process fails.
        context = browser.new_context(permissions=["clipboard-read", "clipboard-write"])
        try:
            page = context.new_page()
            page.goto(f"{base}/gallery")
            wait_js(page, "document.querySelectorAll('article.card').length === 24")
            names = lambda: page.eval_on_selector_all("article.card .name", "e => e.map(n => n.textContent)")  # noqa: E731
            assert names() == [item["name"] for item in first["items"]]
            # Share link: the link is news, not an error: the status line shows it in the normal text colour.
            page.locator("article.card .share").first.click()
            wait_js(page, "/^Link copied: /.test(document.getElementById('status').textContent)")
            colour = page.evaluate("getComputedStyle(document.getElementById('status')).color")
            assert colour == "rgb(34, 34, 34)", colour
            more = page.locator("#more")
            assert more.is_visible()
            more.click()
            wait_js(page, "document.querySelectorAll('article.card').length === 30")
            assert names() == [item["name"] for item in first["items"] + second["items"]]
            wait_js(page, "document.getElementById('more').hidden")
            assert not more.is_visible()  # hidden on the last page, despite #more {display: block}
            page.evaluate("load(false)")  # what a second click would do: nothing left to fetch
            page.wait_for_timeout(300)
            assert len(names()) == 30
        finally:
            context.close()
    finally:
        server.kill()
        server.wait()
