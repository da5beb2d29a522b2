"""The gallery page in a real headless Chromium: a level named like an XSS payload shows as text, its card has
Play / Edit / Watch links, and the payload never becomes an element."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from server.gallery.checks import SavedLevel
from server.gallery.store import Store
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
    assert f'href="./?level={level_id}&amp;mode=play"' in dom and f'href="./?level={level_id}"' in dom  # relative
    assert "#xss" in dom and "Watch agent" in dom
