"""The gallery inside an editor tab (server.play.gallery_tab): save, remix, open by link, play records, author
tokens."""

from __future__ import annotations

import json

import pytest
from fake_editor import falling_win_spec
from viser_client import KeysSocket

from kinetix.formats import build
from kinetix.levels import to_document
from server.play.gallery_tab import GalleryLink
from tests.server.conftest import running_app, session_of, wait_until


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with running_app(gallery=True, data=tmp_path_factory.mktemp("data"), warm_sizes=("m",), max_sessions=4) as app:
        yield app


def _wait(predicate, timeout=20.0):
    wait_until(predicate, timeout)


def _session(app, client):
    return session_of(app, client, 20.0)


def _html(client) -> list[str]:
    return [e.get("content", "") for e in client.gui().values() if e["type"] == "GuiHtmlMessage"]


def _falling_win_document() -> dict:
    return to_document(build(falling_win_spec()))


def test_save_issues_a_token_once_and_a_later_save_of_an_opened_level_is_a_remix(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    link = GalleryLink(app.store)
    first = link.save(session, "my <b>level</b>", "desc", ["cars"])
    token = session.author_token
    assert token, "the first save issues an author token"
    # The page gets the token (keys.js keeps it in localStorage for the gallery page).
    _wait(lambda: any(token in html for html in _html(client)))
    saved = app.store.get_level(first)
    assert saved["name"] == "my <b>level</b>" and saved["tags"] == ["cars"] and saved["parent"] is None
    edited = json.loads(session.editor.export("ours"))
    assert saved["level"] == {**edited, "name": "my <b>level</b>"}  # the gallery name becomes the level's name

    second = link.save(session, "remix")
    assert session.author_token == token, "a known token is kept"
    assert app.store.get_level(second)["parent"] == first
    assert app.store.get_level(second)["author"] == saved["author"]


def test_a_stale_token_gets_a_new_author_instead_of_an_error(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    session.author_token = "not-a-token-of-this-gallery"
    level_id = GalleryLink(app.store).save(session, "fresh author")
    assert session.author_token != "not-a-token-of-this-gallery"
    assert app.store.get_level(level_id)["name"] == "fresh author"


def test_level_link_opens_and_plays_and_the_finished_play_is_recorded(app, make_client):
    level_id, token = app.store.create_level("falling win", _falling_win_document())
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce, query=f"?level={level_id}&mode=play", token=token)
    try:
        _wait(lambda: session.gallery_id == level_id)
        assert session.author_token == token  # the browser's token arrives with the hello
        _wait(lambda: session.mode == "ready")  # opened for play: it waits for the player's first key
        keys.down("Space")
        _wait(lambda: session.mode == "ended")
        assert session._result == "solved"
        _wait(lambda: app.store.stats(level_id)["human_plays"] == 1)
        stats = app.store.stats(level_id)
        assert stats["human_solved"] == 1 and stats["agent_plays"] == 0
        # Simulated seconds: steps x frame skip x dt, whatever the machine's speed.
        assert stats["best_human_seconds"] == pytest.approx(stats["best_human_steps"] * 2 / 60)
    finally:
        keys.close()


def test_ctrl_z_right_after_a_level_link_keeps_the_opened_level(app, make_client):
    level_id, _ = app.store.create_level("falling win", _falling_win_document())
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce, query=f"?level={level_id}")
    try:
        _wait(lambda: session.gallery_id == level_id)
        opened = session.editor.export("ours")
        seq = keys.down("KeyZ", "z", ctrl=True)
        _wait(lambda: session.last_key_seq >= seq)
        assert session.editor.export("ours") == opened  # not the blank level the tab started with
    finally:
        keys.close()


def test_unknown_level_link_leaves_the_tab_editing_its_level(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    before = session.editor.export("ours")
    keys = KeysSocket(app.port, nonce, query="?level=doesnotexist&mode=play")
    try:
        client.wait_for(lambda m: "Cannot open that level" in json.dumps(m, default=str), 20.0)
        assert session.gallery_id is None and session.mode == "edit"
        assert session.editor.export("ours") == before
    finally:
        keys.close()


def test_save_and_open_buttons_are_in_the_tab(app, make_client):
    client = make_client(app)
    _session(app, client)
    for label in ("Save to gallery", "Open from gallery"):
        assert client.find_gui(label)


def test_the_gallery_page_and_api_are_served_beside_the_editor(app):
    import urllib.request

    page = urllib.request.urlopen(app.url + "gallery", timeout=10).read().decode()
    assert "<template id=\"card\">" in page
    listing = json.loads(urllib.request.urlopen(app.url + "api/levels?limit=1", timeout=10).read())
    assert set(listing) == {"items", "next"}


def _ready_to_play_without_identity(app, make_client):
    """A new gallery level opened by link for play in a fresh tab that has no identity yet, waiting for a key."""
    level_id, _ = app.store.create_level("falling win", _falling_win_document())
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce, query=f"?level={level_id}&mode=play")
    try:
        _wait(lambda: session.mode == "ready")
        assert session.author_token is None
    except BaseException:
        keys.close()
        raise
    return level_id, client, session, keys


def test_a_tab_keeps_one_identity_for_its_plays_saves_and_votes(app, make_client):
    """Issue 34: a tab without a token gets one identity at its first gallery play, hands it to the page, and
    uses it for every later save; that identity may vote on the level it played, a fresh one may not."""
    level_id, client, session, keys = _ready_to_play_without_identity(app, make_client)
    try:
        keys.down("Space")
        _wait(lambda: app.store.stats(level_id)["human_plays"] == 1)
        token = session.author_token
        assert token
        _wait(lambda: any(token in html for html in _html(client)))  # the page gets the tab's identity
        link = GalleryLink(app.store)
        first, second = link.save(session, "one"), link.save(session, "two")
        assert session.author_token == token
        assert app.store.get_level(first)["author"] == app.store.get_level(second)["author"] == \
            app.store.author_of(token)
        assert app.store.vote(level_id, token, 1)["up"] == 1
        fresh, _ = app.store.identity(None)
        with pytest.raises(Exception, match="only someone who played this level may vote"):
            app.store.vote(level_id, fresh, 1)
    finally:
        keys.close()


def test_a_play_cut_short_by_closing_the_tab_is_recorded_without_an_error(app, make_client):
    """A tab closed mid-play ends the play after its client is gone: the play still counts (under a new identity,
    since the tab had none) and handing that identity to a page that no longer exists is skipped, not a crash."""
    level_id, client, session, keys = _ready_to_play_without_identity(app, make_client)
    try:
        session.close()
        assert session.client is None
        GalleryLink(app.store).record_play(session, "stopped", 3, 0.1)
        assert app.store.stats(level_id)["human_plays"] >= 1
        assert session.author_token  # the identity the play was recorded under
    finally:
        keys.close()
