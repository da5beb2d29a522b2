"""What a tab shows first when its address names a level (issue 37: Watch agent showed a blank canvas, then an empty
level, for about a second): the page carries the level's picture, and the session starts with that level because
viser's websocket carries the page's query (server.web.relay), not only the /keys hello that comes a second later.
The browser side (static/frames.js) is tests/e2e/test_agent_in_browser.py's."""

from __future__ import annotations

import asyncio
import base64
import io
import re
import urllib.request

import numpy as np
import pytest
from fake_editor import falling_win_spec
from PIL import Image
from viser_client import KeysSocket, ViserTestClient

from kinetix.formats import build
from kinetix.levels import to_document
from server.drafts.store import draft_document, snapshot_json
from tests.server.conftest import running_app, session_of, wait_until

BALL = (0, 204, 0)  # falling_win_spec's green ball (kinetix.draw.ROLE[1])


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with running_app(gallery=True, data=tmp_path_factory.mktemp("data"), warm_sizes=("m",), max_sessions=4) as app:
        yield app


@pytest.fixture(scope="module")
def level_id(app) -> str:
    return app.store.create_level("first frame", to_document(build(falling_win_spec())))[0]


def _ball_pixels(jpeg: bytes) -> int:
    pixels = np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")).astype(int)
    return int((np.abs(pixels - BALL).sum(axis=2) < 60).sum())


def _preview(app, query: str) -> bytes | None:
    with urllib.request.urlopen(app.url + query, timeout=30) as response:
        page = response.read().decode()
    found = re.search(r'<img id="kinetix-preview"[^>]*src="data:image/jpeg;base64,([^"]+)"', page)
    return None if found is None else base64.b64decode(found.group(1))


def test_the_page_of_a_level_or_draft_address_carries_the_levels_picture(app, level_id):
    picture = _preview(app, f"?level={level_id}&mode=agent")
    assert picture is not None
    width, height = Image.open(io.BytesIO(picture)).size
    assert width == height >= 256, "square, as the world is (the page letterboxes it into its canvas)"
    assert _ball_pixels(picture) > 100, "the level's ball is in the picture"

    draft_id = app.drafts.new_id()
    app.drafts.save_later(draft_id, draft_document(snapshot_json(falling_win_spec(), build(falling_win_spec()).size),
                                                   [], [], None))
    assert app.drafts.flush(draft_id)
    draft_picture = _preview(app, f"?draft={draft_id}")
    assert draft_picture is not None and _ball_pixels(draft_picture) > 100

    # Nothing named, or nothing found: the page comes as it always did.
    for query in ("", "?level=no-such-level", "?draft=../../etc", f"?draft={app.drafts.new_id()}"):
        assert _preview(app, query) is None, query


def test_a_tab_whose_address_names_a_level_starts_with_it(app, level_id):
    client = ViserTestClient(app.port, path=f"/?level={level_id}&mode=play")  # as frames.js connects
    keys = None
    try:
        first = client.wait_frame(timeout=30)
        assert _ball_pixels(first) > 100, "the first frame shows the level, not a new one"
        session, nonce = session_of(app, client)
        # Opened without the /keys hello: the gallery knows it, and the play waits for the first key.
        wait_until(lambda: session.gallery_id == level_id and session.mode == "ready", 30)
        assert not session.editor.can_undo, "opening the address over its own level adds no undo step"
        revision = session.editor.revision
        keys = KeysSocket(app.port, nonce, query=f"?level={level_id}&mode=play")
        assert keys.reply == {"type": "ready"}
        assert session.mode == "ready" and session.editor.revision == revision, "the hello reopens nothing"
    finally:
        if keys is not None:
            keys.close()
        client.close()


def test_a_tab_without_a_query_on_its_socket_still_opens_its_address_at_the_hello(app, level_id):
    client = ViserTestClient(app.port)  # an older page: the query comes only with the /keys hello
    keys = None
    try:
        session, nonce = session_of(app, client)
        assert session.gallery_id is None
        keys = KeysSocket(app.port, nonce, query=f"?level={level_id}")
        wait_until(lambda: session.gallery_id == level_id, 30)
    finally:
        if keys is not None:
            keys.close()
        client.close()


def test_the_first_frame_goes_out_before_the_panel_when_visers_sender_starts_late(app, level_id, monkeypatch):
    """On a loaded server viser's sender for a new tab can start only after its session has queued the first frame,
    the panel and a second frame; viser keeps only the newest background image, so without waiting
    (server.play.frames.wait_until_sent) the first frame was dropped and the second came after the panel (CI of
    stop 61). Here the sender of every new tab's own buffer starts 0.5 s late."""
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    window_generator = AsyncMessageBuffer.window_generator

    def late(self, client_id, backlog_done_message=None):
        windows = window_generator(self, client_id, backlog_done_message)
        if self.persistent_messages:  # the broadcast buffer: as it is
            return windows

        async def delayed():
            await asyncio.sleep(0.5)
            async for window in windows:
                yield window

        return delayed()

    monkeypatch.setattr(AsyncMessageBuffer, "window_generator", late)
    client = ViserTestClient(app.port, path=f"/?level={level_id}&mode=play")
    try:
        client.wait_frame(timeout=30)
        client.wait_for(lambda m: m["type"] == "GuiButtonMessage", timeout=30)
        kinds = client.kinds()
        assert kinds.index("frame") < kinds.index("GuiButtonMessage"), kinds
        assert _ball_pixels(client.frames()[0]) > 100, "the first frame shows the level"
    finally:
        client.close()
