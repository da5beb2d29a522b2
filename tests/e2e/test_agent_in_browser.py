"""In real headless Chromium: the gallery card's "Watch agent" opens the level in a tab where the general agent
plays it (frames on the canvas, an agent play in the gallery stats), and the Agent folder's "Race the agent"
button splits the canvas into the human's and the agent's halves."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from kinetix.formats import build
from kinetix.levels import to_document
from tests.e2e.conftest import Screencast, Tab, canvas_box, wait_js
from tests.server.conftest import running_app, wait_until
from tests.server.fake_editor import falling_win_spec

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with running_app(gallery=True, data=tmp_path_factory.mktemp("agent-e2e"), warm_sizes=("m",)) as app:
        yield app


def _wait(predicate, timeout=60.0):
    wait_until(predicate, timeout)


def test_watch_agent_from_a_gallery_card_and_race_from_the_agent_folder(browser, app):
    level_id, _ = app.store.create_level("E2E agent watch", to_document(build(falling_win_spec())))
    tab = Tab(browser, app, 1280, 800)
    try:
        gallery = tab.context.new_page()
        gallery.on("request", lambda request: tab.requests.append(request.url))
        gallery.goto(app.url + "gallery")
        card = gallery.locator("article.card", has_text="E2E agent watch")
        card.wait_for(timeout=30_000)
        card.locator("a.watch").click()
        wait_js(gallery, "window.__kinetixKeys && window.__kinetixKeys.ready()")
        nonce = gallery.get_attribute("#kinetix-session", "data-nonce")
        watcher = app.manager.session_by_nonce(nonce)
        _wait(lambda: watcher.gallery_id == level_id)
        _wait(lambda: watcher.mode == "ended", timeout=180)  # may compile the general agent first
        assert watcher._result == "solved"
        _wait(lambda: app.store.stats(level_id)["agent_plays"] == 1)
        assert app.store.stats(level_id)["human_plays"] == 0

        # Race in the same tab: the canvas shows two halves with a dark divider in the middle.
        gallery.get_by_role("button", name="Race the agent", exact=True).click()
        _wait(lambda: watcher.player == "race")
        race = watcher.controller
        _wait(lambda: watcher.mode == "ready")  # both sides wait for the human's first key
        gallery.mouse.click(300, 300)  # focus the canvas (clicks do nothing while playing)
        gallery.keyboard.press("Space")
        _wait(lambda: race.winner is not None, timeout=120)
        assert race.winner == "tie"  # nobody presses anything and the ball falls onto the goal on both sides
        _wait(lambda: app.store.stats(level_id)["human_plays"] == 1 and app.store.stats(level_id)["agent_plays"] == 2)
        gallery.wait_for_timeout(500)
        # The canvas is the page's largest element left of the docked panel: look at its middle.
        box = canvas_box(gallery)
        shot = np.asarray(Image.open(io.BytesIO(gallery.screenshot(clip=box, timeout=60_000))).convert("RGB"))
        h, w = shot.shape[:2]
        middle = shot[h // 2 - 50: h // 2 + 50, w // 2 - 6: w // 2 + 6].mean(axis=2)
        assert (middle.min(axis=1) < 100).all(), "the divider between the two halves is on the canvas"
        quarter = shot[h // 2 - 50: h // 2 + 50, w // 4 - 6: w // 4 + 6].mean(axis=2)
        assert not (quarter.min(axis=1) < 100).all(), "no such divider a quarter of the way across"
        tab.assert_local_only()
    finally:
        tab.close()


# Logs the kinds of messages viser's worker hands the page, in order (installed before the page's own scripts).
MESSAGE_LOG = """(() => { const Viser = window.Worker; window.__messages = [];
  function Logged(url, options) { const worker = new Viser(url, options);
    worker.addEventListener('message', (event) => { const data = event.data;
      if (data && data.type === 'message_batch') for (const m of data.messages)
        window.__messages.push(m.type === 'BackgroundImageMessage' ? (m.rgb_data ? 'frame' : 'clear') : m.type); });
    return worker; }
  Logged.prototype = Viser.prototype; window.Worker = Logged; })()"""


def test_watch_agent_shows_the_level_before_the_panel(browser, app):
    """The first thing a new tab draws is its level: the session sends its frame before building the panel (which
    keeps the browser busy for a second or more), and no start-up "clear the background" of viser's hides it (the
    canvas stayed blank for ~1.2 s before the level appeared)."""
    level_id, _ = app.store.create_level("E2E agent first frame", to_document(build(falling_win_spec())))
    tab = Tab(browser, app, 1280, 800)
    try:
        page = tab.context.new_page()
        page.add_init_script(MESSAGE_LOG)
        page.goto(app.url + f"?level={level_id}&mode=agent")
        wait_js(page, "window.__kinetixFrames && window.__kinetixFrames.drawn > 0")
        messages = page.evaluate("window.__messages")
        first_frame = messages.index("frame")
        assert "clear" not in messages[:first_frame], messages[:first_frame + 1]
        panel = [k for k, kind in enumerate(messages) if kind == "GuiButtonMessage"]
        assert panel and first_frame < panel[0], f"the panel came first: {messages[:first_frame + 1]}"
        wait_js(page, "window.__kinetixKeys && window.__kinetixKeys.ready()")
        session = app.manager.session_by_nonce(page.get_attribute("#kinetix-session", "data-nonce"))
        _wait(lambda: session.gallery_id == level_id and session.player.startswith("agent"))
        page.close()
        tab.assert_local_only()
    finally:
        tab.close()


BALL, BLOCK = (0, 204, 0), (0, 51, 102)  # falling_win_spec's green ball and fixed blue block (kinetix.draw colours)


def _shows_the_level(picture: bytes) -> bool:
    """Both of the level's bodies are in the picture (a few dozen pixels of each colour at least)."""
    pixels = np.asarray(Image.open(io.BytesIO(picture)).convert("RGB")).astype(int)
    return all((np.abs(pixels - colour).sum(axis=2) < 60).sum() >= 40 for colour in (BALL, BLOCK))


def _first_picture_with_the_level(page, screencast: Screencast, timeout_ms: int = 30_000) -> int:
    """The number of the screencast's first picture that shows the level. Playwright hands the screencast its
    pictures only while the test is inside one of its calls, hence page.wait_for_timeout, not time.sleep."""
    checked = 0  # pictures already looked at
    for _ in range(timeout_ms // 50):
        for n in range(checked, len(screencast.pictures)):
            if _shows_the_level(screencast.pictures[n]):
                return n
        checked = len(screencast.pictures)
        page.wait_for_timeout(50)
    raise AssertionError(f"none of {len(screencast.pictures)} pictures of the gallery shows the card's thumbnail")


def test_watch_agent_never_shows_a_blank_canvas(browser, app):
    """Every picture the browser paints, from a gallery card showing the level through the click on its Watch agent
    until the agent plays, shows the level (issue 37: the canvas stayed blank for about a second, then showed an
    empty level, before the level appeared). The card's link asks for the random agent: the general one compiles for
    up to a minute first (the canvas shows the level meanwhile), and which agent plays changes nothing the page shows
    before it does."""
    level_id, _ = app.store.create_level("E2E agent never blank", to_document(build(falling_win_spec())))
    tab = Tab(browser, app, 1280, 800)
    try:
        page = tab.context.new_page()
        page.goto(app.url + "gallery")
        card = page.locator("article.card", has_text="E2E agent never blank")
        card.wait_for(timeout=30_000)
        # The card shows the level (its thumbnail) before the click: from then on every picture must.
        thumbnail = card.locator("img")
        _wait(lambda: thumbnail.evaluate("(img) => img.complete && img.naturalWidth > 0"), timeout=30)
        link = card.locator("a.watch")
        link.evaluate("(a) => { a.href += '&agent=random'; }")
        screencast = Screencast(page)
        # "complete" is not "painted": under load Chromium painted the gallery once or twice more before the
        # thumbnail (CI, stop 55). The check starts at the first picture that shows it, as the user sees it.
        first = _first_picture_with_the_level(page, screencast)
        link.click()
        wait_js(page, "window.__kinetixKeys && window.__kinetixKeys.ready()")
        session = app.manager.session_by_nonce(page.get_attribute("#kinetix-session", "data-nonce"))
        _wait(lambda: session.player == "agent:random" and session._steps > 0)
        page.wait_for_timeout(300)  # the agent's first frames reach the page
        pictures = screencast.stop()[first:]
        blank = [n for n, picture in enumerate(pictures) if not _shows_the_level(picture)]
        assert len(pictures) >= 3, "the screencast saw the gallery, the new page and the agent's play"
        assert not blank, f"{len(blank)} of {len(pictures)} pictures without the level: numbers {blank}"
        tab.assert_local_only()
    finally:
        tab.close()
