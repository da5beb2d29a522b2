"""Issue 26 §3-§5 on the gallery API, on SQLite and PostgreSQL: no client-posted plays, one vote per voter and no
identities minted in a loop, JSON-only bodies, Origin and Host checks, rate limits, text the databases cannot store,
and the security headers."""

from __future__ import annotations

import copy
import importlib.util
import json

import pytest

from server.gallery.limits import RateLimited, RateLimits
from tests.gallery.conftest import ADMIN, level_doc

EMPTY = {"levels": 0, "authors": 0, "level_tags": 0, "votes": 0, "plays": 0}


def auth(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def create(client, name="a level", **extra):
    response = client.post("/api/levels", json={"name": name, "level": level_doc(), **extra})
    assert response.status_code == 201, response.text
    return response.json()


def make_client(store, **kwargs):
    from fastapi.testclient import TestClient

    from server.gallery.app import create_gallery_app

    return TestClient(create_gallery_app(store, admin_token=ADMIN, **kwargs), base_url="http://localhost")


# ---- §3 play statistics come only from the server's own plays

def test_clients_cannot_post_plays(client, store):
    level_id = create(client)["id"]
    body = {"kind": "human", "solved": True, "steps": 0, "seconds": 0}
    for headers in ({}, {"Authorization": f"Bearer {ADMIN}"}):
        response = client.post(f"/api/levels/{level_id}/plays", json=body, headers=headers)
        assert response.status_code in (404, 405), response.text
    stats = client.get(f"/api/levels/{level_id}/stats").json()
    assert stats["plays"] == 0 and stats["best_human_seconds"] is None
    assert "/api/levels/{level_id}/plays" not in client.get("/openapi.json").json()["paths"]
    # The server's sessions record plays through the library (server.play.gallery_tab.GalleryLink.record_play).
    # A best time needs a recording verified by replay too (tests/gallery/test_best_runs.py).
    store.record_play(level_id, "human", solved=True, steps=120, seconds=4.0)
    stats = client.get(f"/api/levels/{level_id}/stats").json()
    assert stats["human_solved"] == 1 and stats["best_human_seconds"] is None


# ---- §3 votes: one per identity and level, only from an identity that played the level (issue 34)

def _player(store, level_id: str) -> str:
    """A token that played the level in a server-run play (as a tab's GalleryLink records it)."""
    token, _ = store.identity(None)
    store.record_play(level_id, "human", solved=False, steps=30, seconds=1.0, author=token)
    return token


def test_ten_fresh_cookie_less_votes_count_nothing_and_mint_no_identity(client, store):
    level_id = create(client)["id"]
    authors = store.counts()["authors"]
    for _ in range(10):
        client.cookies.clear()
        response = client.post(f"/api/levels/{level_id}/vote", json={"value": 1})
        assert response.status_code == 403 and "play it in the browser" in response.json()["detail"]
        assert "set-cookie" not in response.headers
    assert client.get(f"/api/levels/{level_id}/stats").json()["votes_up"] == 0
    assert store.counts()["authors"] == authors, "a refused vote spends no identity"


def test_a_vote_counts_once_per_identity_and_only_after_playing(client, store):
    made = create(client)
    level_id = made["id"]
    # The author has not played it: a saved level is not a played one.
    refused = client.post(f"/api/levels/{level_id}/vote", json={"value": 1}, headers=auth(made["author_token"]))
    assert refused.status_code == 403
    store.record_play(level_id, "agent", solved=True, steps=30, seconds=1.0, author=made["author_token"])
    assert client.post(f"/api/levels/{level_id}/vote", json={"value": 1},
                       headers=auth(made["author_token"])).status_code == 403, "an agent's play is not the identity's"
    player = _player(store, level_id)
    for _ in range(5):
        assert client.post(f"/api/levels/{level_id}/vote", json={"value": 1}, headers=auth(player)).json()["up"] == 1
    assert client.post(f"/api/levels/{level_id}/vote", json={"value": -1}, headers=auth(player)).json() == {
        "up": 0, "down": 1, "score": -1, "value": -1}
    other, _ = store.create_level("other", level_doc())
    assert client.post(f"/api/levels/{other}/vote", json={"value": 1}, headers=auth(player)).status_code == 403, \
        "a play of one level is no vote on another"
    # A voter cookie of an earlier version is read like a token (and must have played too).
    client.cookies.clear()
    by_cookie = client.post(f"/api/levels/{level_id}/vote", json={"value": 0},
                            headers={"Cookie": f"kinetix_voter={player}"})
    assert by_cookie.status_code == 200 and by_cookie.json()["down"] == 0
    unknown = client.post(f"/api/levels/{level_id}/vote", json={"value": 1}, headers=auth("not-a-token-we-issued"))
    assert unknown.status_code == 401


def test_refused_requests_spend_no_identity(store):
    with make_client(store, limits=RateLimits(writes_per_minute=0, identities_per_hour=1)) as client:
        level_id, _ = store.create_level("by the library", level_doc())
        assert client.post("/api/levels/nope/vote", json={"value": 1}).status_code == 404
        assert client.post(f"/api/levels/{level_id}/vote", json={"value": 2}).status_code == 422
        assert client.post(f"/api/levels/{level_id}/vote", content=b'{"value": 1}').status_code == 415
        assert client.post("/api/levels", content=b"{not json", headers={
            "Content-Type": "application/json"}).status_code == 400
        assert store.counts()["authors"] == 1
        assert create(client)["author_token"]  # the one new identity of this address this hour
        assert client.post("/api/levels", json={"name": "x", "level": level_doc()}).status_code == 429


# ---- §3 content types and cross-site requests

@pytest.mark.parametrize("content_type", [None, "text/plain", "application/x-www-form-urlencoded",
                                          "multipart/form-data; boundary=x", "application/jsonp", "text/json"])
def test_bodies_must_be_json(client, store, content_type):
    made = create(client)
    before = store.counts()
    headers = {"Content-Type": content_type} if content_type else {}
    auth = {"Authorization": f"Bearer {made['author_token']}"}
    answers = [
        client.post("/api/levels", content=json.dumps({"name": "x", "level": level_doc()}), headers=headers),
        client.post(f"/api/levels/{made['id']}/vote", content=b'{"value": 1}', headers=headers),
        client.put(f"/api/levels/{made['id']}", content=b'{"name": "y"}', headers={**headers, **auth}),
    ]
    for response in answers:
        assert response.status_code == 415 and "application/json" in response.json()["detail"], response.text
    assert store.counts() == before and client.get(f"/api/levels/{made['id']}").json()["name"] == "a level"
    # With a charset parameter and any capitalisation it is still JSON.
    store.record_play(made["id"], "human", solved=False, steps=3, seconds=0.1, author=made["author_token"])
    ok = client.post(f"/api/levels/{made['id']}/vote", content=b'{"value": 1}', headers={
        "Content-Type": "Application/JSON; charset=utf-8", **auth})
    assert ok.status_code == 200


def test_cross_site_writes_are_refused(client, store):
    made = create(client)
    before = store.counts()
    for origin in ("http://evil.example", "null", "http://localhost.evil.example", "http://localhost:81",
                   "http://127.0.0.1", "file://"):
        headers = {"Origin": origin}
        assert client.post("/api/levels", json={"name": "x", "level": level_doc()},
                           headers=headers).status_code == 403
        assert client.post(f"/api/levels/{made['id']}/vote", json={"value": 1}, headers=headers).status_code == 403
        response = client.delete(f"/api/levels/{made['id']}",
                                 headers={**headers, "Authorization": f"Bearer {made['author_token']}"})
        assert response.status_code == 403 and "cross-site" in response.json()["detail"]
    assert store.counts() == before
    # Reads from anywhere are fine (they change nothing), and the app's own origin may write.
    assert client.get("/api/levels", headers={"Origin": "http://evil.example"}).status_code == 200
    same = client.post(f"/api/levels/{made['id']}/vote", json={"value": 1}, headers={
        "Origin": "http://localhost", **auth(_player(store, made["id"]))})
    assert same.status_code == 200


# ---- §3 rate limits

def test_write_rate_limit_answers_429_with_retry_after(store):
    with make_client(store, limits=RateLimits(writes_per_minute=3, identities_per_hour=0)) as client:
        made = create(client)
        player = auth(_player(store, made["id"]))
        votes = [client.post(f"/api/levels/{made['id']}/vote", json={"value": 1}, headers=player) for _ in range(3)]
        assert [v.status_code for v in votes] == [200, 200, 429]
        assert 1 <= int(votes[2].headers["retry-after"]) <= 20 and "writes" in votes[2].json()["detail"]
        assert client.get(f"/api/levels/{made['id']}").status_code == 200  # reads are not limited


def test_token_bucket_refills_and_keeps_clients_apart(monkeypatch):
    import server.gallery.limits as limits_module

    now = [1000.0]
    monkeypatch.setattr(limits_module.time, "monotonic", lambda: now[0])
    limits = RateLimits(writes_per_minute=2, identities_per_hour=0)
    limits.take("write", "a")
    limits.take("write", "a")
    with pytest.raises(RateLimited) as refused:
        limits.take("write", "a")
    assert refused.value.retry_after == 30  # one token per 30 s
    limits.take("write", "b")  # another client has its own bucket
    for _ in range(100):
        limits.take("identity", "a")  # 0 = no limit
    now[0] += 30
    limits.take("write", "a")
    with pytest.raises(RateLimited):
        limits.take("write", "a")
    with pytest.raises(ValueError, match="writes_per_minute"):
        RateLimits(writes_per_minute=-1)


def test_serve_options_reach_the_server():
    import argparse

    from kinetix.cli import _serve_arguments
    from server.web.security import allowed_hosts_for

    parser = argparse.ArgumentParser()
    _serve_arguments(parser)
    args = parser.parse_args(["--allowed-hosts", "kinetix.lan,192.168.1.20:8080", "--write-limit", "5",
                              "--identity-limit", "0"])
    assert (args.allowed_hosts, args.write_limit, args.identity_limit) == (
        ["kinetix.lan", "192.168.1.20:8080"], 5.0, 0.0)
    defaults = parser.parse_args([])
    assert defaults.allowed_hosts == [] and defaults.write_limit is None and defaults.identity_limit is None
    helped = " ".join(parser.format_help().split())  # the defaults the help states are RateLimits' own
    assert f"minute per client address; 0 = no limit (default: {RateLimits().writes_per_minute:g})" in helped
    assert f"per client address; 0 = no limit (default: {RateLimits().identities_per_hour:g})" in helped
    hosts = allowed_hosts_for("0.0.0.0", args.allowed_hosts)
    assert hosts == {"localhost", "127.0.0.1", "::1", "kinetix.lan", "192.168.1.20"}


# ---- §4 text that the databases cannot store

SURROGATE = "a\ud800b"


def raw(body: dict) -> bytes:
    return json.dumps(body).encode()  # ensure_ascii: the surrogate travels as the JSON escape \ud800


@pytest.mark.parametrize("field", ["name", "description", "parent"])
def test_lone_surrogates_are_refused_naming_the_field(client, store, field):
    made = create(client)
    before = store.counts()
    body = {"name": "ok", "level": level_doc(), field: SURROGATE}
    response = client.post("/api/levels", content=raw(body), headers={"Content-Type": "application/json"})
    assert response.status_code == 422 and response.json()["detail"].startswith(f"{field}: "), response.text
    assert "surrogate" in response.json()["detail"]
    if field != "parent":
        response = client.put(f"/api/levels/{made['id']}", content=raw({field: SURROGATE}), headers={
            "Content-Type": "application/json", "Authorization": f"Bearer {made['author_token']}"})
        assert response.status_code == 422 and response.json()["detail"].startswith(f"{field}: ")
    assert store.counts() == before
    assert client.get(f"/api/levels/{made['id']}").json()["name"] == "a level"
    # The connection is still good for the next request (it was reset after the 500 this used to be).
    assert client.get("/api/levels").status_code == 200


def test_lone_surrogate_inside_the_level_document_is_refused(client, store):
    made = create(client)
    doc = level_doc()
    doc["name"] = SURROGATE
    for method, url, body, headers in [
            ("post", "/api/levels", {"name": "ok", "level": doc}, {}),
            ("put", f"/api/levels/{made['id']}", {"level": doc}, {"Authorization": f"Bearer {made['author_token']}"})]:
        response = client.request(method, url, content=raw(body), headers={"Content-Type": "application/json",
                                                                           **headers})
        assert response.status_code == 422 and response.json()["detail"].startswith("level.name: "), response.text
    assert store.counts()["levels"] == 1 and client.get(f"/api/levels/{made['id']}").status_code == 200


@pytest.mark.parametrize("param", ["q", "tag", "author"])
def test_nul_in_a_query_matches_nothing_or_is_refused(client, param):
    create(client)
    response = client.get(f"/api/levels?{param}=%00")
    assert response.status_code == 422 and response.json()["detail"].startswith(f"{param}: "), response.text
    assert client.get(f"/api/levels?{param}=a%00b").status_code == 422
    assert client.get("/api/levels?q=level").json()["items"]  # an ordinary search still finds it


def test_a_cursor_is_checked_by_its_published_pattern_and_every_match_is_a_page(client):
    create(client)
    for bad in ("1.x\u0000y", f"{2**70}.abc", "WzEsICJ4XHUwMDAweSJd", "1.", ".abc"):
        answer = client.get("/api/levels", params={"cursor": bad})
        assert answer.status_code == 422 and answer.json()["detail"].startswith("cursor: "), answer.text
    for built in ("999999999999999999.zzz", "-5.a", "0.0"):  # any string of the shape: a page, maybe empty
        assert client.get("/api/levels", params={"cursor": built}).status_code == 200


# ---- out-of-range numbers (the ranges themselves are kinetix's: docs/level-format.md)

RANGES_CHECKED = importlib.util.find_spec("kinetix.ranges") is not None


def _out_of_range(path: tuple, value) -> dict:
    doc = copy.deepcopy(level_doc())
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return doc


NEEDS_RANGES = pytest.mark.skipif(not RANGES_CHECKED, reason="env ranges come with kinetix.ranges (issue 26 §1)")
OUT_OF_RANGE = [
    pytest.param(("bodies", 3, "position", 0), 1e300, id="position"),
    pytest.param(("env", "max_timesteps"), 2**31, id="max_timesteps",
                 marks=NEEDS_RANGES),
    pytest.param(("env", "frame_skip"), 10**6, id="frame_skip",
                 marks=NEEDS_RANGES),
    pytest.param(("env", "physics", "dt"), 1e6, id="dt",
                 marks=NEEDS_RANGES),
]


@pytest.mark.parametrize("path,value", OUT_OF_RANGE)
def test_out_of_range_numbers_are_refused_and_nothing_is_stored(client, store, path, value):
    response = client.post("/api/levels", json={"name": "x", "level": _out_of_range(path, value)})
    assert response.status_code == 422 and response.json()["detail"].startswith("level: "), response.text
    assert store.counts() == EMPTY


# ---- §5 headers and hosts

def test_security_headers_on_pages_static_files_and_the_api(client):
    create(client)
    for url in ("/gallery", "/static/gallery.js", "/api/levels", "/api/levels/nope", "/openapi.json"):
        response = client.get(url)
        headers = response.headers
        assert headers["x-content-type-options"] == "nosniff", url
        assert "frame-ancestors 'self'" in headers["content-security-policy"], url
        assert headers["referrer-policy"] == "same-origin", url
        assert headers["x-frame-options"] == "SAMEORIGIN", url


@pytest.mark.parametrize("host,status", [("localhost", 200), ("localhost:8080", 200), ("127.0.0.1:9", 200),
                                         ("[::1]:8080", 200), ("evil.example", 400), ("evil.example:8080", 400),
                                         ("localhost.evil.example", 400), ("", 400)])
def test_host_header_must_name_this_server(client, host, status):
    response = client.get("/api/levels", headers={"Host": host})
    assert response.status_code == status, response.text
    if status == 400:
        assert "--allowed-hosts" in response.json()["detail"]
        assert response.headers["x-content-type-options"] == "nosniff"


def test_allowed_hosts_extend_the_defaults(store):
    from server.web.security import allowed_hosts_for

    with make_client(store, allowed_hosts=allowed_hosts_for("192.168.1.5", ["kinetix.lan"])) as client:
        for host in ("kinetix.lan:8080", "192.168.1.5", "localhost"):
            assert client.get("/api/levels", headers={"Host": host}).status_code == 200
        assert client.get("/api/levels", headers={"Host": "other.lan"}).status_code == 400
    with make_client(store, allowed_hosts=allowed_hosts_for("127.0.0.1", ["*"])) as client:
        assert client.get("/api/levels", headers={"Host": "anything.example"}).status_code == 200
