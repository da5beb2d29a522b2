"""In real headless Chromium: editing with the real editor (server.editor) through clicks, keys and the panel."""

from __future__ import annotations

import time

import pytest

from server.draw import View
from tests.e2e.conftest import LEVELS, Tab
from tests.server.conftest import running_app

pytestmark = [pytest.mark.e2e, pytest.mark.slow]
editor_module = pytest.importorskip("server.editor", reason="the editor (server.editor) is not merged yet")


@pytest.fixture(scope="module")
def app():
    with running_app(warm_sizes=("m",), level=str(LEVELS / "car_right.json")) as app:
        yield app


def _wait(predicate, timeout=15.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.02)


def _page_xy(tab: Tab, x: float, y: float) -> tuple[float, float]:
    """Page pixel of world point (x, y) on the full-window canvas (the frame is letterboxed into it)."""
    viewport = tab.page.viewport_size
    u, v = View(viewport["width"], viewport["height"]).to_screen(x, y)
    return u * viewport["width"], v * viewport["height"]


def test_delete_then_undo_and_redo(browser, app):
    tab = Tab(browser, app)
    try:
        editor = tab.session.editor
        bodies = len(editor.spec.bodies)
        body = next(b for b in editor.spec.bodies if not b.fixed)  # a moving body (the walls are fixed)
        tab.page.mouse.click(*_page_xy(tab, *body.position))
        _wait(lambda: editor.selection)
        tab.page.keyboard.press("Delete")
        _wait(lambda: len(editor.spec.bodies) < bodies)
        deleted = len(editor.spec.bodies)
        tab.page.keyboard.press("Control+z")
        _wait(lambda: len(editor.spec.bodies) == bodies)
        tab.page.keyboard.press("Control+Shift+z")
        _wait(lambda: len(editor.spec.bodies) == deleted)
        tab.page.keyboard.press("Control+z")
        _wait(lambda: len(editor.spec.bodies) == bodies)
        tab.assert_local_only()
    finally:
        tab.close()
