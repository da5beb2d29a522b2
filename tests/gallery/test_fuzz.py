"""Hypothesis fuzz of the gallery API: random methods, ids, query strings, headers, content types and JSON bodies
(with lone UTF-16 surrogates and NUL in the text, and levels whose numbers are out of range) never get a 5xx, a 4xx
stores nothing, a body that is not application/json is never accepted, and every 2xx JSON answer has the fields its
OpenAPI schema requires. Bounded: a fixed number of examples, so it runs in CI in a few seconds."""

from __future__ import annotations

import json
import urllib.parse

import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st

from server.gallery.limits import RateLimits
from server.gallery.store import Store
from tests.gallery.conftest import level_doc

# Text with lone surrogates and NUL, which JSON can carry ("\\ud800", "\\u0000") but the databases cannot store.
texts = st.text(max_size=20) | st.sampled_from(["\ud800", "a\udfffb", "\x00", "x\x00", "\ud83d"])
numbers = (st.integers(-2**40, 2**40) | st.floats(allow_nan=False)
           | st.sampled_from([2**31, 2**63, 10**30, -2**31 - 1, 1e6, 1e300, -1e300, float("inf")]))
json_values = st.recursive(
    st.none() | st.booleans() | numbers | texts,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12)


@st.composite
def out_of_range_levels(draw) -> dict:
    """A valid level with one number replaced by a huge, negative or infinite one (docs/level-format.md ranges)."""
    doc = level_doc()
    body = draw(st.integers(0, len(doc["bodies"]) - 1))
    target, key = draw(st.sampled_from([
        (doc["env"], "max_timesteps"), (doc["env"], "frame_skip"), (doc["env"], "dense_reward_scale"),
        (doc["env"]["physics"], "dt"), (doc["env"]["physics"], "base_motor_power"), (doc["gravity"], 1),
        (doc["bodies"][body]["position"], 0), (doc["bodies"][body], "angle"), (doc["bodies"][body], "density"),
        (doc["bodies"][body], "friction"), (doc["bodies"][body], "collision_mode")]))
    target[key] = draw(st.sampled_from([2**31, 2**63, 10**30, -1, -2**31 - 1, 1e6 + 1, 1e300, -1e300,
                                        float("inf"), float("-inf")]))
    return doc


field_values = st.sampled_from([level_doc(), {"format_version": 1, "bodies": []}]) | out_of_range_levels() | json_values
bodies = st.one_of(
    json_values,
    st.fixed_dictionaries({}, optional={"name": field_values, "description": field_values, "tags": field_values,
                                        "level": field_values, "parent": field_values}),
    st.fixed_dictionaries({"value": json_values}),
    st.fixed_dictionaries({}, optional={"kind": st.sampled_from(["human", "agent", "x"]) | json_values,
                                        "solved": json_values, "steps": json_values, "seconds": json_values}),
    st.binary(max_size=64),
)
content_types = st.sampled_from(["application/json", "application/json", "application/json; charset=utf-8", None,
                                 "text/plain", "application/x-www-form-urlencoded", "multipart/form-data",
                                 "text/json", "application/jsonx"])
query = st.dictionaries(st.sampled_from(["sort", "size", "tag", "q", "limit", "cursor", "author"]),
                        st.sampled_from(["newest", "top", "hardest", "s", "l", "0", "101", "-1", "%", "_"])
                        | st.text(max_size=12), max_size=4)


@pytest.fixture(scope="module")
def fuzz_client(tmp_path_factory):
    from fastapi.testclient import TestClient

    from server.gallery.app import create_gallery_app

    store = Store(f"sqlite:///{tmp_path_factory.mktemp('fuzz') / 'g.sqlite3'}", seed_dir=None)
    with TestClient(create_gallery_app(store, admin_token="adm", limits=RateLimits(0, 0)),
                    base_url="http://localhost") as client:
        made = client.post("/api/levels", json={"name": "fuzz", "level": level_doc()}).json()
        client.calls = 0
        client.store = store
        yield client, made
    store.close()


def required_fields(schema: dict, spec: dict) -> set[str]:
    if "$ref" in schema:
        schema = spec["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    return set(schema.get("required", []))


# No "explain" phase: it reruns a failure hundreds of times and only adds commentary.
@settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck),
          phases=[Phase.explicit, Phase.reuse, Phase.generate, Phase.shrink])
# Explicit examples: each must fail if its rule is broken (random ones rarely hit a valid body with a wrong type).
@example(method="POST", target="/{level_id}/vote", level_id="known", params={}, body={"value": 1},
         content_type="text/plain", auth=None)
@example(method="POST", target="", level_id="known", params={}, body={"name": "simple", "level": level_doc()},
         content_type="application/x-www-form-urlencoded", auth=None)
@example(method="PUT", target="/{level_id}", level_id="known", params={}, body={"name": "renamed"},
         content_type=None, auth="Bearer token")
@example(method="POST", target="", level_id="known", params={}, body={"name": "\ud800", "level": level_doc()},
         content_type="application/json", auth=None)
@example(method="PUT", target="/{level_id}", level_id="known", params={}, body={"description": "x\udfff"},
         content_type="application/json", auth="Bearer token")
@example(method="POST", target="", level_id="known", params={}, body={"name": "p", "level": level_doc(),
                                                                     "parent": "\ud800"},
         content_type="application/json", auth=None)
@example(method="GET", target="", level_id="known", params={"q": "\x00"}, body=None, content_type=None, auth=None)
@example(method="POST", target="/{level_id}/plays", level_id="known", params={},
         body={"kind": "human", "solved": True, "steps": 0, "seconds": 0}, content_type="application/json",
         auth=None)
@given(method=st.sampled_from(["GET", "POST", "PUT", "DELETE"]),
       target=st.sampled_from(["", "/{level_id}", "/{level_id}/thumbnail.png", "/{level_id}/vote", "/{level_id}/plays",
                               "/{level_id}/stats", "/{level_id}/best-run.mcap"]),
       level_id=st.sampled_from(["known", "unknown", "a b", "%2e%2e", "x" * 40])
       | st.text(min_size=1, max_size=6).filter(lambda s: s.strip(". ")),
       params=query, body=bodies, content_type=content_types,
       auth=st.sampled_from([None, "Bearer adm", "Bearer token", "Bearer bad", "Basic x", "Bearer "]))
def test_api_fuzz(fuzz_client, method, target, level_id, params, body, content_type, auth):
    client, made = fuzz_client
    level_id = made["id"] if level_id == "known" else level_id
    path = "/api/levels" + target.replace("{level_id}", urllib.parse.quote(level_id, safe=""))
    headers = {}
    if auth:
        headers["Authorization"] = auth.replace("token", made["author_token"])
    if method == "DELETE" and auth in ("Bearer adm", "Bearer token"):
        method = "GET"  # keep the known level for the other examples
    if content_type is not None:
        headers["Content-Type"] = content_type
    content = body if isinstance(body, bytes) else json.dumps(body)  # ensure_ascii: surrogates travel as escapes
    before = client.store.counts()
    try:
        response = client.request(method, path, params=params, headers=headers,
                                  content=content if method in ("POST", "PUT") else None)
    except UnicodeEncodeError:
        return  # httpx cannot put such text in a URL; nothing reached the server
    client.calls += 1
    assert response.status_code < 500, (method, path, params, response.text)
    if response.status_code >= 400:
        assert client.store.counts() == before, (method, path, response.status_code, response.text)
    if method in ("POST", "PUT") and not (content_type or "").lower().startswith("application/json"):
        assert response.status_code >= 400, (method, path, content_type, response.text)
    if target == "" and method == "GET" and params.get("q") and "\x00" in params["q"]:
        assert response.status_code == 422 or response.json()["items"] == [], response.text  # not every level
    if target == "/{level_id}/plays":
        assert response.status_code in (404, 405), response.text  # plays are the server's own, never posted
    if 200 <= response.status_code < 300 and response.headers.get("content-type", "").startswith("application/json"):
        spec = client.app.openapi()
        route = "/api/levels" + target
        operation = spec["paths"].get(route, {}).get(method.lower())
        assert operation is not None, (method, route)
        ok = next(iter(operation["responses"][str(response.status_code)]["content"].values()))["schema"]
        assert required_fields(ok, spec) <= set(response.json()), (route, response.json())
