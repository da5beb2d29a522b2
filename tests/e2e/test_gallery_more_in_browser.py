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


@pytest.mark.e2e
@pytest.mark.slow
def test_a_first_visit_while_the_gallery_fills_shows_its_levels_by_itself(browser, tmp_path: Path, page_errors):
    """Right after a server starts, the gallery may still be filling: an empty first page, or 503 with Retry-After.
    The page says so and loads again by itself (it used to stay on "No levels match."). Cards sit right under the
    controls (no empty band) and show the level's description."""
    db = tmp_path / "gallery.sqlite3"
    Store(f"sqlite:///{db}", seed_dir=None).close()
    port = _free_port()
    server = _start_server(db, port)
    context = browser.new_context()
    try:
        page = context.new_page()
        page.goto(f"http://127.0.0.1:{port}/gallery")
        wait_js(page, "/no levels yet/.test(document.getElementById('status').textContent)")
        store = Store(f"sqlite:///{db}", seed_dir=None)  # the levels arrive after the page was loaded
        store.create_level("ramp", {}, description="Jump the gap\nwith the blue car.",
                           prepared=SavedLevel("m", json.dumps(level_doc()), b"png"))
        store.close()
        wait_js(page, "document.querySelectorAll('article.card').length === 1", timeout=20)
        card = page.locator("article.card")
        assert card.locator(".description").inner_text() == "Jump the gap\nwith the blue car."
        assert card.locator(".description").is_visible()
        wait_js(page, "document.getElementById('status').textContent === ''")
        gap = page.evaluate("""() => document.getElementById('grid').getBoundingClientRect().top
                                      - document.getElementById('controls').getBoundingClientRect().bottom""")
        assert gap < 12, f"an empty band of {gap} px above the cards"

        # A server still preparing answers 503 with Retry-After: the page says so and asks again after it.
        answers = []

        def preparing_once(route):
            answers.append(route.request.url)
            if len(answers) == 1:
                route.fulfill(status=503, headers={"Retry-After": "1", "Content-Type": "application/json"},
                              body=json.dumps({"detail": "the gallery is being prepared"}))
            else:
                route.continue_()

        page.route("**/api/levels?*", preparing_once)
        page.reload()
        wait_js(page, "/being prepared/.test(document.getElementById('status').textContent)")
        wait_js(page, "document.querySelectorAll('article.card').length === 1", timeout=20)
        assert len(answers) == 2
        page_errors[:] = [e for e in page_errors if "status of 503" not in e]  # the 503 itself, as Chromium logs it
    finally:
        context.close()
        server.kill()
        server.wait()
