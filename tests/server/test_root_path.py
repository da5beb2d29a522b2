"""`kinetix serve --root-path /kinetix/`: every page, script, websocket and API answer under /kinetix/
(server/web/prefix.py), as a proxy forwarding /kinetix/... sees it; /kinetix redirects to /kinetix/."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import pytest
from viser_client import KeysSocket, ViserTestClient, session_nonce

from tests.server.conftest import running_app, wait_until


@pytest.fixture(scope="module")
def app():
    with running_app(warm_sizes=("m",), gallery=True, root_path="/kinetix/") as app:
        yield app


def _get(app, path: str):
    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *args, **kwargs):
            return None

    opener = urllib.request.build_opener(NoRedirect)
    try:
        response = opener.open(f"http://127.0.0.1:{app.port}{path}", timeout=30)
        return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers), error.read()


def test_pages_scripts_and_api_answer_under_the_prefix_only(app):
    status, headers, _ = _get(app, "/kinetix?level=x")
    assert status == 308 and headers["location"] == "/kinetix/?level=x"
    status, _, page = _get(app, "/kinetix/")
    assert status == 200 and b'src="static/keys.js"' in page, "the page's scripts are relative to it"
    assert _get(app, "/kinetix/static/keys.js")[0] == 200
    status, _, gallery = _get(app, "/kinetix/gallery")
    assert status == 200 and b"/static/" not in gallery and b'href="/' not in gallery, "relative links only"
    assert app.wait_until_warm(timeout=600, everything=True)  # the gallery is seeded by the warm-up
    status, _, body = _get(app, "/kinetix/api/levels?limit=2")
    assert status == 200
    items = json.loads(body)["items"]
    assert items and items[0]["thumbnail"].startswith("/kinetix/api/levels/")
    assert _get(app, items[0]["thumbnail"])[0] == 200
    assert json.loads(_get(app, "/kinetix/openapi.json")[2])["paths"]
    for outside in ("/", "/api/levels", "/static/keys.js", "/kinetixx/"):
        assert _get(app, outside)[0] == 404, outside


def test_a_tab_connects_its_websockets_under_the_prefix(app):
    # viser's client opens its websocket at the page's path without the trailing slash: /kinetix
    client = ViserTestClient(app.port, path="/kinetix")
    keys = None
    try:
        assert client.wait_frame(timeout=30)[:2] == b"\xff\xd8"
        nonce = session_nonce(client)
        wait_until(lambda: app.manager.session_by_nonce(nonce) is not None)
        keys = KeysSocket(app.port, nonce, path="/kinetix")
        assert keys.reply == {"type": "ready"}
        session = app.manager.session_by_nonce(nonce)
        keys.down("Space")
        wait_until(lambda: session.mode == "play")
    finally:
        if keys is not None:
            keys.close()
        client.close()
