"""Everything through the user's one port: viser's websocket relayed by the side server (server/web/http.py)."""

from __future__ import annotations

import time

import pytest
import viser
import websockets.sync.client
from fake_editor import FakeEditor, falling_win_spec
from viser_client import KeysSocket, ViserTestClient, session_nonce

from tests.server.conftest import running_app, wait_until


@pytest.fixture(scope="module")
def app():
    editor = lambda level=None, size="m": FakeEditor(falling_win_spec(), size=size)  # noqa: E731
    with running_app(warm_sizes=("m",), max_sessions=3, editor_factory=editor) as app:
        yield app


def test_viser_listens_on_loopback_only(app):
    assert app.viser.get_host() == "127.0.0.1"
    assert app.viser.get_port() != app.port


def test_viser_port_answers_only_the_relay(app):
    """Nothing reaches viser's internal port without the relay's token: no way around the Host and Origin checks
    (server/web/relay.py). The relay itself (the other tests) passes."""
    import urllib.error
    import urllib.request

    with pytest.raises(websockets.InvalidStatus) as refused:
        websockets.sync.client.connect(f"ws://127.0.0.1:{app.viser.get_port()}",
                                       subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10)
    assert refused.value.response.status_code == 403
    with pytest.raises(websockets.InvalidStatus):
        websockets.sync.client.connect(f"ws://127.0.0.1:{app.viser.get_port()}", open_timeout=10,
                                       subprotocols=[f"viser-v{viser.__version__}"],
                                       additional_headers={"X-Kinetix-Relay": "guess"})
    with pytest.raises(urllib.error.HTTPError) as page:  # viser's own copy of the page and its files
        urllib.request.urlopen(f"http://127.0.0.1:{app.viser.get_port()}/", timeout=10)
    assert page.value.code == 403
    assert not app.manager.sessions, "no session was opened by the refused connections"


def test_a_tab_through_the_one_port_gets_frames_and_plays(app):
    client = ViserTestClient(app.port)  # the user's port, not viser's
    keys = None
    try:
        assert client.wait_frame(timeout=30)[:2] == b"\xff\xd8"
        nonce = session_nonce(client)
        wait_until(lambda: app.manager.session_by_nonce(nonce) is not None)
        session = app.manager.session_by_nonce(nonce)
        keys = KeysSocket(app.port, nonce)
        start = client.count()
        keys.down("Space")
        wait_until(lambda: session.mode == "play")
        client.wait_frame(start=start, timeout=10)  # play frames reach the tab through the relay
        keys.down("Space")
        wait_until(lambda: session.mode == "edit")
    finally:
        if keys is not None:
            keys.close()
        client.close()
    # Closing the browser's socket closes viser's side too: the session goes.
    wait_until(lambda: app.manager.session_by_nonce(nonce) is None)


def test_viser_version_check_still_reaches_the_browser(app):
    with websockets.sync.client.connect(f"ws://127.0.0.1:{app.port}/", subprotocols=["viser-v0.0.1"],
                                        open_timeout=10) as ws:
        with pytest.raises(websockets.ConnectionClosed):
            ws.recv(timeout=10)
        assert ws.close_code == 1002
        assert "Version mismatch" in ws.close_reason


def test_relay_keeps_viser_subprotocol(app):
    protocol = f"viser-v{viser.__version__}"
    with websockets.sync.client.connect(f"ws://127.0.0.1:{app.port}/", subprotocols=[protocol],
                                        open_timeout=10) as ws:
        assert ws.subprotocol == protocol
    time.sleep(0.1)


def test_a_cross_site_page_cannot_open_viser_through_the_relay(app):
    # The side server's Host/Origin checks (server/web/security.py) now guard viser's websocket too.
    protocol = f"viser-v{viser.__version__}"
    with pytest.raises(websockets.InvalidStatus) as refused:
        websockets.sync.client.connect(f"ws://127.0.0.1:{app.port}/", subprotocols=[protocol], open_timeout=10,
                                       additional_headers={"Origin": "http://attacker.example"})
    assert refused.value.response.status_code == 403
