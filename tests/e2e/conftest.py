"""Browser end-to-end tests: the real server in this process and the apt Chromium driven by playwright.

Skipped when Chromium or playwright is missing, unless CI=true (then they fail: CI must run them).

Every page of every browser context a test opens is watched: a console error (a CSP violation among them, which
Chromium reports as one) or an uncaught exception in a page fails the test, after it ran (`page_errors`).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from urllib.parse import urlparse

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "server"))  # the protocol helpers

CHROMIUM = os.environ.get("KINETIX_CHROMIUM", "/usr/bin/chromium")
LEVELS = Path(__file__).resolve().parents[2] / "levels"


def _missing() -> str | None:
    if not Path(CHROMIUM).exists():
        return f"no Chromium at {CHROMIUM} (run .ci/setup-chromium.sh)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the playwright package is not installed (pip install -e .[dev])"
    return None


# What the pages of the running test reported as errors: console errors (CSP violations included) and uncaught
# exceptions, as "<url>: <text>". The autouse fixture `page_errors` empties it before each test and fails the test
# if anything is in it afterwards.
PAGE_ERRORS: list[str] = []


def _console_error(message) -> None:
    if message.type == "error":
        PAGE_ERRORS.append(f"{message.location.get('url') or message.page and message.page.url}: {message.text}")


def _web_error(error) -> None:
    PAGE_ERRORS.append(f"{error.page.url if error.page else '?'}: uncaught {error.error}")


def watch_context(context) -> None:
    """Collect every console error and uncaught exception of the context's pages into PAGE_ERRORS."""
    context.on("console", _console_error)
    context.on("weberror", _web_error)


SHARED_BROWSER = pytest.StashKey[object]()


@pytest.fixture(scope="session")
def browser(request):
    """One Chromium for the whole run. Other test folders import this fixture (tests/deploy), which makes another
    session fixture of the same function; Playwright's sync API cannot start twice in one process, so every copy
    hands out the browser the first one launched (kept in the run's config stash) and only that one closes it."""
    reason = _missing()
    if reason:
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true but {reason}")
        pytest.skip(reason)
    shared = request.config.stash.get(SHARED_BROWSER, None)
    if shared is not None:
        yield shared
        return
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--use-gl=swiftshader"])
        new_context = browser.new_context

        def watched_context(*args, **kwargs):  # every context, the tests' own included, is watched
            context = new_context(*args, **kwargs)
            watch_context(context)
            return context

        browser.new_context = watched_context
        request.config.stash[SHARED_BROWSER] = browser
        try:
            yield browser
        finally:
            del request.config.stash[SHARED_BROWSER]
            browser.close()


@pytest.fixture(autouse=True)
def page_errors():
    """Fail the test if any page reported a console error, a CSP violation or an uncaught exception."""
    PAGE_ERRORS.clear()
    yield PAGE_ERRORS
    errors, PAGE_ERRORS[:] = list(PAGE_ERRORS), []
    assert not errors, "the browser reported errors:\n" + "\n".join(errors)


def expect_page_error(errors: list[str], fragment: str, required: bool = True) -> None:
    """Take the errors a test provoked on purpose (say a refused request, which Chromium logs to the console) off the
    list `page_errors` checks; fails if none was reported, unless not `required` (errors that only timing brings,
    such as reconnect attempts while a server restarts)."""
    matching = [error for error in errors if fragment in error]
    assert matching or not required, f"expected a browser error containing {fragment!r}, got {errors}"
    errors[:] = [error for error in errors if fragment not in error]


def wait_js(page, expression: str, timeout: float = 60.0) -> None:
    """Wait until `expression` is truthy in the page. Polls page.evaluate (the DevTools protocol, which the page's
    Content-Security-Policy does not govern): page.wait_for_function evaluates its predicate with eval inside
    the page, which the server's policy (no 'unsafe-eval', server/web/security.py) rightly refuses."""
    import time

    deadline = time.monotonic() + timeout
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise TimeoutError(f"{expression!r} still false after {timeout} s")
        page.wait_for_timeout(50)


def canvas_box(page) -> dict:
    """The page box of viser's 3D canvas (the largest canvas; the control panel is docked beside it)."""
    return page.evaluate("""() => {
        const c = [...document.querySelectorAll('canvas')].map(e => e.getBoundingClientRect())
            .sort((a, b) => b.width * b.height - a.width * a.height)[0];
        return {x: c.x, y: c.y, width: c.width, height: c.height};
    }""")


class Tab:
    """A page on the server that records every request, to check all traffic stays on 127.0.0.1."""

    def __init__(self, browser, app, width: int = 800, height: int = 600):
        self.app = app
        self.context = browser.new_context(viewport={"width": width, "height": height}, accept_downloads=True)
        self.page = self.context.new_page()
        self.requests: list[str] = []
        self.csp_violations: list[str] = []  # server/web/security.py's policy must let the app run
        self.page.on("request", lambda request: self.requests.append(request.url))
        self.page.on("websocket", lambda ws: self.requests.append(ws.url))
        self.watch_csp(self.page)
        self.page.goto(app.url)
        wait_js(self.page, "window.__kinetixKeys && window.__kinetixKeys.ready()")
        nonce = self.page.get_attribute("#kinetix-session", "data-nonce")
        self.session = app.manager.session_by_nonce(nonce)
        assert self.session is not None

    def xy(self, x: float, y: float) -> tuple[float, float]:
        """Page pixel of world point (x, y): the frame is letterboxed into the canvas (left of the docked panel)."""
        from server.play.draw import View

        box = canvas_box(self.page)
        u, v = View(round(box["width"]), round(box["height"])).to_screen(x, y)
        return box["x"] + u * box["width"], box["y"] + v * box["height"]

    def drag(self, a: tuple[float, float], b: tuple[float, float], steps: int = 6) -> None:
        """A left-button drag between two world points."""
        (x0, y0), (x1, y1) = self.xy(*a), self.xy(*b)
        self.page.mouse.move(x0, y0)
        self.page.mouse.down()
        for i in range(1, steps + 1):
            self.page.mouse.move(x0 + (x1 - x0) * i / steps, y0 + (y1 - y0) * i / steps)
            self.page.wait_for_timeout(40)
        self.page.mouse.up()

    def canvas_png(self, top: int = 0, height: int | None = None, width: int | None = None) -> bytes:
        """A screenshot of a band of the page (the canvas fills it); a page clip does not wait for the WebGL
        canvas to be "stable", which it never is while frames stream in."""
        size = self.page.viewport_size
        clip = {"x": 0, "y": top, "width": width or size["width"], "height": height or size["height"] - top}
        return self.page.screenshot(clip=clip, timeout=60_000)

    def watch_csp(self, page) -> None:
        """Collect the Content-Security-Policy violations Chromium reports on `page` (as console messages)."""
        page.on("console", lambda message: self.csp_violations.append(message.text)
                if "Content Security Policy" in message.text else None)

    def assert_local_only(self) -> None:
        hosts = {urlparse(url).hostname for url in self.requests if not url.startswith(("blob:", "data:"))}
        assert hosts == {"127.0.0.1"}, self.requests
        assert self.csp_violations == []

    def close(self) -> None:
        self.context.close()


class Screencast:
    """What Chromium painted for a page, picture by picture (the DevTools screencast), across navigations: a test
    can check every picture the user saw, not just the state at the moments it looked."""

    def __init__(self, page, width: int = 640, height: int = 400):
        """Pictures at most `width` x `height` (JPEG): smaller than the page, so they are quick to look at."""
        self.pictures: list[bytes] = []
        self._cdp = page.context.new_cdp_session(page)
        self._cdp.on("Page.screencastFrame", self._take)
        self._cdp.send("Page.startScreencast", {"format": "jpeg", "quality": 90, "maxWidth": width,
                                                "maxHeight": height, "everyNthFrame": 1})

    def _take(self, event) -> None:
        import base64

        self.pictures.append(base64.b64decode(event["data"]))
        self._cdp.send("Page.screencastFrameAck", {"sessionId": event["sessionId"]})

    def stop(self) -> list[bytes]:
        self._cdp.send("Page.stopScreencast")
        return self.pictures
