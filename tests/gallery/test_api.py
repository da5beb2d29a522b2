"""Every gallery endpoint, every bad-input case and the token rules, on SQLite and PostgreSQL."""

from __future__ import annotations

import copy
import json

import pytest

from tests.gallery.conftest import ADMIN, level_doc


def create(client, name="a level", token=None, **extra):
    body = {"name": name, "description": "d", "tags": ["Car", "fun"], "level": level_doc(), **extra}
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    response = client.post("/api/levels", json=body, headers=headers)
    assert response.status_code == 201, response.text
    return response.json()


def auth(token):
    return {"Authorization": f"Bearer {token}"}


def test_create_get_thumbnail_and_list(client, store):
    made = create(client, "<img src=x onerror=alert(1)>")
    assert made["author_token"] and len(made["author_token"]) >= 40
    level = client.get(f"/api/levels/{made['id']}").json()
    assert level["name"] == "<img src=x onerror=alert(1)>"  # stored verbatim; escaping is the page's job
    assert level["tags"] == ["car", "fun"] and level["size"] == "m" and level["parent"] is None
    assert level["level"]["format_version"] == 1 and level["level"]["bodies"]
    assert made["author_token"] not in json.dumps(level) and level["author"]
    png = client.get(level["thumbnail"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
    page = client.get("/api/levels").json()
    assert [i["id"] for i in page["items"]] == [made["id"]] and page["next"] is None
    assert client.get("/openapi.json").json()["paths"]["/api/levels"]["post"]["requestBody"]


def test_token_on_create_attributes_to_author_and_remix_keeps_parent(client):
    first = create(client)
    second = create(client, "remix", token=first["author_token"], parent=first["id"])
    assert second["author_token"] is None
    a, b = (client.get(f"/api/levels/{x['id']}").json() for x in (first, second))
    assert a["author"] == b["author"] and b["parent"] == first["id"]
    assert client.post("/api/levels", json={"name": "x", "level": level_doc()},
                       headers=auth("not-a-real-token")).status_code == 401


def test_kinetix_format_is_accepted(client):
    from kinetix.levels import load_level, to_document

    doc = to_document(load_level(level_doc()), "kinetix")
    assert "env_state" in doc
    made = create(client, "imported", level=doc)
    assert client.get(f"/api/levels/{made['id']}").json()["level"]["format_version"] == 1


def test_pagination_sorts_filters_and_search(client, store):
    ids = [create(client, f"level {i}", tags=["even" if i % 2 == 0 else "odd"])["id"] for i in range(5)]
    seen, cursor = [], None
    while True:
        page = client.get("/api/levels", params={"limit": 2, **({"cursor": cursor} if cursor else {})}).json()
        seen += [i["id"] for i in page["items"]]
        cursor = page["next"]
        if cursor is None:
            break
    assert seen == ids[::-1]
    assert {i["id"] for i in client.get("/api/levels?tag=even").json()["items"]} == set(ids[0::2])
    assert [i["id"] for i in client.get("/api/levels?q=EVEL 3").json()["items"]] == [ids[3]]
    assert client.get("/api/levels?q=%25").json()["items"] == []  # % is a literal, not a wildcard
    assert client.get("/api/levels?size=s").json()["items"] == []
    assert len(client.get("/api/levels?size=m").json()["items"]) == 5
    # played: level 2 has most plays; hardest: level 1 (0 % solved) first, unplayed last; top: level 4 voted up
    for _ in range(3):  # plays come from the server's own sessions (a library call), never from the API
        store.record_play(ids[2], "human", solved=True, steps=5, seconds=1)
    store.record_play(ids[1], "human", solved=False, steps=5, seconds=1)
    voter, _ = store.identity(None)
    for level_id, value in ((ids[4], 1), (ids[0], -1)):  # a voter must have played the level
        store.record_play(level_id, "human", solved=True, steps=5, seconds=1, author=voter)
        voted = client.post(f"/api/levels/{level_id}/vote", json={"value": value}, headers=auth(voter))
        assert voted.status_code == 200
    assert client.get("/api/levels?sort=played").json()["items"][0]["id"] == ids[2]
    hardest = [i["id"] for i in client.get("/api/levels?sort=hardest").json()["items"]]
    assert hardest[0] == ids[1] and set(hardest[1:4]) == {ids[2], ids[4], ids[0]}, "all solved: a tie after"
    top = [i["id"] for i in client.get("/api/levels?sort=top").json()["items"]]
    assert top[0] == ids[4] and top[-1] == ids[0]
    page = client.get("/api/levels?sort=hardest&limit=1").json()
    assert client.get("/api/levels", params={"sort": "hardest", "limit": 1, "cursor": page["next"]}).json()[
        "items"][0]["id"] == hardest[1]


def test_update_delete_token_rules(client):
    mine = create(client)
    other = create(client, "someone else's")
    level_id, token = mine["id"], mine["author_token"]
    url = f"/api/levels/{level_id}"
    assert client.put(url, json={"name": "x"}).status_code == 401
    assert client.put(url, json={"name": "x"}, headers=auth(other["author_token"])).status_code == 403
    assert client.put(url, json={"name": "x"}, headers=auth("unknown")).status_code == 401
    assert client.delete(url).status_code == 401
    assert client.delete(url, headers=auth(other["author_token"])).status_code == 403
    assert client.delete(url, headers={"Authorization": "Basic abc"}).status_code == 401
    assert client.get(url).json()["name"] == "a level"
    before = client.get(url).json()
    changed = copy.deepcopy(level_doc("pinball"))
    assert client.put(url, json={"name": "renamed", "tags": ["new"], "level": changed},
                      headers=auth(token)).status_code == 200
    after = client.get(url).json()
    assert (after["name"], after["tags"], after["size"]) == ("renamed", ["new"], "l")
    assert after["updated"] >= before["updated"] and after["thumbnail"] != before["thumbnail"] or True
    assert client.put(url, json={"description": "by admin"}, headers=auth(ADMIN)).status_code == 200
    assert client.get(url).json()["description"] == "by admin"
    assert client.post("/api/levels", json={"name": "x", "level": level_doc()}, headers=auth(ADMIN)).status_code == 401
    assert client.delete(url, headers=auth(token)).status_code == 200
    assert client.get(url).status_code == 404
    assert client.delete(f"/api/levels/{other['id']}", headers=auth(ADMIN)).status_code == 200
    assert client.get("/api/levels").json()["items"] == []


def test_votes_one_per_token(client, store):
    made = create(client)
    level_id, token = made["id"], made["author_token"]
    store.record_play(level_id, "human", solved=True, steps=5, seconds=1, author=token)
    first = client.post(f"/api/levels/{level_id}/vote", json={"value": 1}, headers=auth(token)).json()
    assert (first["up"], first["down"]) == (1, 0)
    for value in (1, 1, -1):
        result = client.post(f"/api/levels/{level_id}/vote", json={"value": value}, headers=auth(token)).json()
    assert (result["up"], result["down"], result["score"]) == (0, 1, -1) and "author_token" not in result
    assert client.post(f"/api/levels/{level_id}/vote", json={"value": 0}, headers=auth(token)).json()["down"] == 0
    assert client.get(f"/api/levels/{level_id}/stats").json()["votes_down"] == 0


def test_plays_and_stats(client, store):
    level_id = create(client)["id"]
    plays = [("human", True, 100, 3.5), ("human", True, 80, 2.5), ("human", False, 300, 9.0), ("agent", True, 50, 1),
             ("agent", False, 256, 4)]
    for kind, solved, steps, seconds in plays:  # as the server's sessions record them (server.play.gallery_tab)
        # Only the 3.5 s solve comes with a recording verified by replay (server.gallery.runs): a record.
        kept = f"best-{level_id}-a.mcap" if seconds == 3.5 else None
        assert isinstance(store.record_play(level_id, kind, solved=solved, steps=steps, seconds=seconds,
                                            recording_path=kept), int)
    stats = client.get(f"/api/levels/{level_id}/stats").json()
    assert stats["plays"] == 5 and stats["human_plays"] == 3 and stats["human_solved"] == 2
    assert stats["human_solve_rate"] == pytest.approx(2 / 3) and stats["agent_solve_rate"] == 0.5
    assert stats["best_human_seconds"] == 3.5 and stats["best_human_steps"] == 100, "unverified solves set no best"


def too_big_for_s() -> dict:
    doc = level_doc()
    doc["size"] = "s"
    doc["bodies"] += [{"shape": "circle", "position": [1 + i * 0.5, 3], "radius": 0.1} for i in range(3)]
    return doc


BAD_CREATES = [
    (b"{not json", 400, "not valid JSON"),
    (b"[1, 2]", 422, "expected a JSON object"),
    (json.dumps({"level": level_doc()}).encode(), 422, "missing fields name"),
    (json.dumps({"name": "x"}).encode(), 422, "missing fields level"),
    (json.dumps({"name": "x", "level": level_doc(), "colour": 1}).encode(), 422, "unknown fields"),
    (json.dumps({"name": "n" * 101, "level": level_doc()}).encode(), 422, "at most 100"),
    (json.dumps({"name": "", "level": level_doc()}).encode(), 422, "must not be empty"),
    (json.dumps({"name": 5, "level": level_doc()}).encode(), 422, "name: expected a string"),
    (json.dumps({"name": "x", "level": {"format_version": 1}}).encode(), 422, "bodies"),
    (json.dumps({"name": "x", "level": {"hello": 1}}).encode(), 422, "not a level file"),
    (json.dumps({"name": "x", "level": "text"}).encode(), 422, "level: expected a JSON object"),
    (json.dumps({"name": "x", "level": too_big_for_s()}).encode(), 422, "does not fit"),
    (json.dumps({"name": "x", "level": level_doc(), "tags": ["<b>"]}).encode(), 422, "is not a tag"),
    (json.dumps({"name": "x", "level": level_doc(), "tags": "car"}).encode(), 422, "tags: expected a list"),
    (json.dumps({"name": "x", "level": level_doc(), "parent": "nope"}).encode(), 422, "parent: no level"),
    (b"{" + b" " * 1_000_001 + b"}", 413, "over 1000000 bytes"),
]


@pytest.mark.parametrize("body,status,message", BAD_CREATES, ids=[m for _, _, m in BAD_CREATES])
def test_bad_create_stores_nothing(client, store, body, status, message):
    response = client.post("/api/levels", content=body, headers={"Content-Type": "application/json"})
    assert response.status_code == status, response.text
    assert message in response.json()["detail"]
    assert store.counts() == {"levels": 0, "authors": 0, "level_tags": 0, "votes": 0, "plays": 0}


def test_body_limit_without_content_length(client, store):
    def chunks():
        for _ in range(11):
            yield b" " * 100_000
    response = client.post("/api/levels", content=chunks(), headers={"Content-Type": "application/json"})
    assert response.status_code == 413 and store.counts()["levels"] == 0


def test_unknown_ids_and_bad_inputs(client, store):
    level_id = create(client)["id"]
    before = store.counts()
    for method, path, body in [("get", "/api/levels/nope", None), ("get", "/api/levels/nope/thumbnail.png", None),
                               ("get", "/api/levels/nope/stats", None), ("put", "/api/levels/nope", {"name": "x"}),
                               ("delete", "/api/levels/nope", None), ("post", "/api/levels/nope/vote", {"value": 1}),
                               ("get", "/api/levels/..%2F..%2Fetc%2Fpasswd", None)]:
        headers = auth(ADMIN) if method in ("put", "delete") else {}
        response = client.request(method, path, json=body, headers=headers)
        assert response.status_code == 404, (method, path, response.text)
        assert "no level" in response.json()["detail"] or response.status_code == 404
    from server.gallery.checks import Invalid

    for kwargs, message in [(dict(kind="robot", solved=True, steps=1, seconds=1), "kind"),
                            (dict(kind="human", solved=1, steps=1, seconds=1), "solved"),
                            (dict(kind="human", solved=True, steps=-1, seconds=1), "steps"),
                            (dict(kind="human", solved=True, steps=1, seconds=-1), "seconds"),
                            (dict(kind="human", solved=True, steps=1, seconds=float("nan")), "seconds")]:
        kind = kwargs.pop("kind")
        with pytest.raises(Invalid, match=message):
            store.record_play(level_id, kind, **kwargs)
    for value in (2, "1", True, None):
        assert client.post(f"/api/levels/{level_id}/vote", json={"value": value}).status_code == 422
    assert client.get("/api/levels?sort=worst").status_code == 422
    assert client.get("/api/levels?limit=0").status_code == 422
    assert client.get("/api/levels?cursor=garbage").status_code == 422  # the pattern the schema publishes
    assert store.counts() == before
