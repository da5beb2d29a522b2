"""How long a tab shows no level after "Watch agent" (issue 37: a blank canvas for about 1.2 s), in headless Chromium.

    python -m server.bench.first_frame [--loads 4] [--chromium /usr/bin/chromium] [--json]

Two ways to ask for the agent, each `--loads` times, with the general agent compiled beforehand (as a server that
finished its warm-up has it):
- link: a gallery card's "Watch agent" (a new page, `?level=<id>&mode=agent`);
- button: the Agent folder's "Watch agent" in a tab that shows the level.

What the page painted is taken from Chromium's screencast (every picture it composited), from the click until
the agent has played a step. A picture "shows the level" when it has at least LEVEL_PIXELS pixels of the level's
coloured bodies (kinetix.draw's role colours; the empty level of a new tab has none, only grey walls). Printed
per ask: blank_ms, how long the pictures without the level were on screen; level_ms, from the click to the
first picture of the new page that shows the level (link only; the button's page shows it throughout); and
paint_ms, from the click to the new page's first paint. Prints numbers; nothing here passes or fails.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

LEVEL = Path(__file__).resolve().parents[2] / "levels" / "car_right.json"
LEVEL_PIXELS = 200  # a car's wheels and body at 1280x800 are thousands; a gallery card's thumbnail hundreds
COLOUR_TOLERANCE = 60  # summed over R, G and B: JPEG and scaling move colours a little


def shows_level(png: bytes) -> bool:
    import numpy as np
    from PIL import Image

    from kinetix.draw import FIXED_ROLE, ROLE

    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)
    coloured = np.zeros(pixels.shape[:2], bool)
    for colour in ROLE[1:] + FIXED_ROLE[1:]:  # green, blue, red; not the grey of walls and unassigned bodies
        coloured |= np.abs(pixels - np.asarray(colour, np.int16)).sum(axis=2) < COLOUR_TOLERANCE
    return int(coloured.sum()) >= LEVEL_PIXELS


class Pictures:
    """Chromium's screencast of a page: (browser time in s, png) per composited picture."""

    def __init__(self, page):
        self.taken: list[tuple[float, bytes]] = []
        self._cdp = page.context.new_cdp_session(page)
        self._cdp.on("Page.screencastFrame", self._take)
        self._cdp.send("Page.startScreencast", {"format": "png", "everyNthFrame": 1})

    def _take(self, event) -> None:
        self.taken.append((event["metadata"]["timestamp"], base64.b64decode(event["data"])))
        self._cdp.send("Page.screencastFrameAck", {"sessionId": event["sessionId"]})

    def stop(self) -> list[tuple[float, bytes]]:
        self._cdp.send("Page.stopScreencast")
        return self.taken


def blank_ms(pictures: list[tuple[float, bytes]], start: float, end: float) -> float:
    """Milliseconds between `start` and `end` (s) during which the picture on screen did not show the level."""
    total = 0.0
    for n, (t, png) in enumerate(pictures):
        until = pictures[n + 1][0] if n + 1 < len(pictures) else end
        shown_from, shown_until = max(t, start), min(until, end)
        if shown_until > shown_from and not shows_level(png):
            total += shown_until - shown_from
    return total * 1000


def _wait(predicate, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"still waiting after {timeout:.0f} s")
        time.sleep(0.02)


def _session(app, page):
    while not page.evaluate("!!(window.__kinetixKeys && window.__kinetixKeys.ready())"):
        page.wait_for_timeout(20)
    return app.manager.session_by_nonce(page.get_attribute("#kinetix-session", "data-nonce"))


def _playing(session) -> bool:
    return session is not None and session.player.startswith("agent") and session._steps > 0


def by_link(app, context, level_id: str) -> dict:
    """The gallery card's Watch agent (its link: `?level=<id>&mode=agent`; `level_id` names the card)."""
    page = context.new_page()
    try:
        page.goto(app.url + "gallery")
        card = page.locator(f"article.card:has(a.watch[href*='{level_id}'])")
        card.wait_for(timeout=30_000)
        thumbnail = card.locator("img")  # the card shows the level before the click
        _wait(lambda: thumbnail.evaluate("(img) => img.complete && img.naturalWidth > 0"), timeout=30)
        link = card.locator("a.watch")
        pictures = Pictures(page)
        page.wait_for_timeout(300)  # the screencast's first picture (the gallery) is in
        clicked = time.time()
        link.click()
        session = _session(app, page)
        _wait(lambda: _playing(session))
        end = time.time()
        taken = pictures.stop()
        paint = page.evaluate("performance.timeOrigin + (performance.getEntriesByType('paint')[0] || "
                              "{startTime: NaN}).startTime") / 1000
        level = next((t for t, png in taken if t >= paint - 0.001 and shows_level(png)), float("nan"))
        return {"blank_ms": blank_ms(taken, clicked, end), "level_ms": (level - clicked) * 1000,
                "paint_ms": (paint - clicked) * 1000, "pictures": len(taken)}
    finally:
        page.close()


def by_button(app, context, level_id: str) -> dict:
    """The Agent folder's Watch agent in a tab that shows the level."""
    page = context.new_page()
    try:
        page.goto(app.url + f"?level={level_id}")
        session = _session(app, page)
        page.wait_for_timeout(1000)  # the tab has settled
        pictures = Pictures(page)
        page.wait_for_timeout(300)
        clicked = time.time()
        page.get_by_role("button", name="Watch agent", exact=True).click()
        _wait(lambda: _playing(session))
        end = time.time()
        taken = pictures.stop()
        return {"blank_ms": blank_ms(taken, clicked, end), "pictures": len(taken)}
    finally:
        page.close()


def run(args: argparse.Namespace) -> int:
    from playwright.sync_api import sync_playwright

    from kinetix.levels import read_json
    from server.app import App, Config

    with tempfile.TemporaryDirectory(prefix="kinetix-bench-first-frame-") as data:
        app = App(Config(port=0, gallery=True, data=Path(data), warm_sizes=("m",), warm_batches=False)).start()
        try:
            if not app.wait_until_warm(timeout=900, everything=True):  # the general agent compiled too
                print("the warm-up did not finish", file=sys.stderr)
                return 1
            level_id, _ = app.store.create_level("bench first frame", read_json(LEVEL))
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=args.chromium,
                                            args=["--no-sandbox", "--use-gl=swiftshader"])
                context = browser.new_context(viewport={"width": 1280, "height": 800})
                results: dict[str, list[dict]] = {"link": [], "button": []}
                for _ in range(args.loads):
                    for how, ask in (("link", by_link), ("button", by_button)):
                        result = ask(app, context, level_id)
                        results[how].append(result)
                        if args.json:
                            print(json.dumps({"bench": "first_frame", "how": how, **result}))
                        else:
                            print(f"{how:<7}" + "  ".join(f"{k} {v:7.0f}" for k, v in result.items()))
                browser.close()
            if not args.json:
                for how, rows in results.items():
                    blank = [row["blank_ms"] for row in rows]
                    print(f"{how:<7}blank_ms median {statistics.median(blank):.0f}, max {max(blank):.0f} "
                          f"({len(rows)} asks)")
        finally:
            app.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loads", type=int, default=4, help="asks of each kind (default: 4)")
    parser.add_argument("--chromium", default="/usr/bin/chromium", help="Chromium binary")
    parser.add_argument("--json", action="store_true", help="one JSON object per ask")
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
