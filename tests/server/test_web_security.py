"""The side server's web safety (server/web/security.py, issue 26 §5): security headers on the page, static files
and errors; the Host check (DNS rebinding) and the Origin check, also on the /keys websocket."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from server.web.http import create_app
from server.web.security import allowed_hosts_for, origin_matches

KEYS = "ws://127.0.0.1:8080/keys"


class NoSessions:
    """The little of a SessionManager the side server needs when no tab is open."""

    sessions: dict = {}
    on_query = None

    def session_by_nonce(self, nonce):
        return None


@pytest.fixture(scope="module")
def client():
    app = create_app(NoSessions(), viser_port=1, allowed_hosts=allowed_hosts_for("127.0.0.1", ["kinetix.test"]))
    with TestClient(app, base_url="http://127.0.0.1:8080") as c:
        yield c


def test_headers_on_the_page_static_files_and_errors(client):
    for url in ("/", "/static/keys.js", "/static/frames.js", "/health", "/nothing-here", "/gallery"):
        headers = client.get(url).headers
        assert headers["x-content-type-options"] == "nosniff", url
        csp = headers["content-security-policy"]
        assert "frame-ancestors 'self'" in csp and "object-src 'none'" in csp, url
        assert headers["referrer-policy"] == "same-origin", url
    assert "keys.js" in client.get("/").text  # the page itself is unchanged
    docs = client.get("/docs").headers["content-security-policy"]  # Swagger UI loads from its CDN
    assert "https://cdn.jsdelivr.net" in docs and "frame-ancestors 'self'" in docs
    assert "cdn.jsdelivr.net" not in client.get("/").headers["content-security-policy"]
    # viser's client evaluates strings as it loads (its embind module): only its page allows that, once.
    page = client.get("/").headers.get_list("content-security-policy")
    assert len(page) == 1 and "'unsafe-eval'" in page[0]
    for url in ("/gallery", "/static/keys.js", "/health"):
        assert "'unsafe-eval'" not in client.get(url).headers["content-security-policy"], url


@pytest.mark.parametrize("host,status", [("127.0.0.1:8080", 200), ("localhost:1", 200), ("kinetix.test", 200),
                                         ("KINETIX.test:9", 200), ("attacker.example", 400),
                                         ("127.0.0.1.attacker.example", 400), ("", 400)])
def test_host_check(client, host, status):
    assert client.get("/health", headers={"Host": host}).status_code == status


def test_keys_websocket_refuses_other_origins_and_hosts(client):
    for url, headers, why in [(KEYS, {"Origin": "http://attacker.example"}, "cross-site"),
                              ("ws://attacker.example/keys", {}, "not served here")]:
        with pytest.raises(WebSocketDisconnect) as refused:
            with client.websocket_connect(url, headers=headers) as socket:
                socket.receive_text()
        assert why in refused.value.reason
    # The page's own origin reaches the handler (which closes: the hello has no nonce).
    with client.websocket_connect(KEYS, headers={"Origin": "http://127.0.0.1:8080"}) as socket:
        socket.send_text('{"type": "hello", "nonce": 5}')
        with pytest.raises(WebSocketDisconnect) as closed:
            socket.receive_text()
        assert closed.value.reason == "expected hello with a nonce"


@pytest.mark.parametrize("origin,host,same", [
    ("http://localhost:8080", "localhost:8080", True), ("http://localhost", "localhost:80", True),
    ("https://example.org", "example.org", True), ("http://[::1]:8080", "[::1]:8080", True),
    ("http://localhost:8081", "localhost:8080", False), ("http://evil.example", "localhost", False),
    ("null", "localhost", False), ("http://localhost/path", "localhost", False), ("ftp://localhost", "localhost",
                                                                                  False)])
def test_origin_matching(origin, host, same):
    assert origin_matches(origin, host) is same
