"""The gallery page in a real headless Chromium: a level named like an XSS payload shows as text, its card has
Play / Edit / Watch links, and the payload never becomes an element."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from server.gallery.store import SavedLevel, Store
from tests.e2e.conftest import wait_js
from tests.gallery.conftest import level_doc
from tests.gallery.test_concurrency import _free_port, _start_server

PAYLOAD = '<img src=x onerror="document.title=\'pwned\'">'


def chromium() -> str:
    path = os.environ.get("KINETIX_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not path:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but no Chromium found (KINETIX_CHROMIUM unset, chromium not on PATH)")
        pytest.skip("the browser test needs Chromium (KINETIX_CHROMIUM or chromium on PATH)")
    return path


@pytest.mark.e2e
def test_gallery_page_renders_payload_as_text(tmp_path: Path):
    browser = chromium()
    db = tmp_path / "gallery.sqlite3"
    store = Store(f"sqlite:///{db}", seed_dir=None)
    import json

    level_id, _ = store.create_level(PAYLOAD, {}, prepared=SavedLevel("m", json.dumps(level_doc()), b"png"),
                                     tags=["xss"])
    store.close()
    port = _free_port()
    server = _start_server(db, port)
    try:
        args = [browser, "--headless", "--disable-gpu", "--virtual-time-budget=8000", "--dump-dom",
                f"http://127.0.0.1:{port}/gallery"]
        if sys.platform.startswith("linux") and os.geteuid() == 0:
            args.insert(1, "--no-sandbox")  # Chromium's sandbox refuses root
        dom = subprocess.run(args, capture_output=True, text=True, timeout=120).stdout
    finally:
        server.kill()
        server.wait()
    assert 'class="name"' in dom, dom[:2000]
    assert "&lt;img src=x onerror=" in dom  # the name is there, escaped, as text
    assert "<img src=\"x\"" not in dom and "<img src=x" not in dom  # and never as an element
    assert dom.count("<img") == 2  # the card template's and the one card's thumbnail: nothing from the name
    assert "<title>Kinetix gallery</title>" in dom  # the onerror handler did not run
    assert f'href="/?level={level_id}&amp;mode=play"' in dom and f'href="/?level={level_id}"' in dom
    assert "#xss" in dom and "Watch agent" in dom


@pytest.mark.e2e
@pytest.mark.slow
def test_more_levels_shows_the_second_page_once_and_then_hides(tmp_path: Path):
    """30 levels: the page shows the API's first 24, "More levels" adds exactly the API's second page, then hides;
    asking for more again adds nothing. A shared link is not shown in the error colour."""
    browser = chromium()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("the browser test needs the playwright package")
    import json

    import httpx

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
        with sync_playwright() as p:
            chrome = p.chromium.launch(executable_path=browser, args=["--no-sandbox"])
            try:
                context = chrome.new_context(permissions=["clipboard-read", "clipboard-write"])
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
                chrome.close()
    finally:
        server.kill()
        server.wait()
