"""Hypothesis fuzz of the gallery API: random methods, ids, query strings, headers and JSON bodies never
get a 5xx, and every 2xx JSON answer has the fields its OpenAPI schema requires. Bounded: a fixed number of
examples, so it runs in CI in a few seconds."""

from __future__ import annotations

import json
import urllib.parse

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from server.gallery.limits import RateLimits
from server.gallery.store import Store
from tests.gallery.conftest import level_doc

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**40, 2**40) | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12)
field_values = st.sampled_from([level_doc(), {"format_version": 1, "bodies": []}]) | json_values
bodies = st.one_of(
    json_values,
    st.fixed_dictionaries({}, optional={"name": field_values, "description": field_values, "tags": field_values,
                                        "level": field_values, "parent": field_values}),
    st.fixed_dictionaries({"value": json_values}),
    st.fixed_dictionaries({}, optional={"kind": st.sampled_from(["human", "agent", "x"]) | json_values,
                                        "solved": json_values, "steps": json_values, "seconds": json_values}),
    st.binary(max_size=64),
)
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
        yield client, made
    store.close()


def required_fields(schema: dict, spec: dict) -> set[str]:
    if "$ref" in schema:
        schema = spec["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    return set(schema.get("required", []))


# No "explain" phase: it reruns a failure hundreds of times and only adds commentary.
@settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck),
          phases=[Phase.explicit, Phase.reuse, Phase.generate, Phase.shrink])
@given(method=st.sampled_from(["GET", "POST", "PUT", "DELETE"]),
       target=st.sampled_from(["", "/{level_id}", "/{level_id}/thumbnail.png", "/{level_id}/vote", "/{level_id}/plays",
                               "/{level_id}/stats", "/{level_id}/best-run.mcap"]),
       level_id=st.sampled_from(["known", "unknown", "a b", "%2e%2e", "x" * 40])
       | st.text(min_size=1, max_size=6).filter(lambda s: s.strip(". ")),
       params=query, body=bodies,
       auth=st.sampled_from([None, "Bearer adm", "Bearer token", "Bearer bad", "Basic x", "Bearer "]))
def test_api_fuzz(fuzz_client, method, target, level_id, params, body, auth):
    client, made = fuzz_client
    level_id = made["id"] if level_id == "known" else level_id
    path = "/api/levels" + target.replace("{level_id}", urllib.parse.quote(level_id, safe=""))
    headers = {}
    if auth:
        headers["Authorization"] = auth.replace("token", made["author_token"])
    if method == "DELETE" and auth in ("Bearer adm", "Bearer token"):
        method = "GET"  # keep the known level for the other examples
    content = body if isinstance(body, bytes) else json.dumps(body)
    try:
        response = client.request(method, path, params=params, headers=headers,
                                  content=content if method in ("POST", "PUT") else None)
    except UnicodeEncodeError:
        return  # httpx cannot put such text in a URL; nothing reached the server
    client.calls += 1
    assert response.status_code < 500, (method, path, params, response.text)
    if 200 <= response.status_code < 300 and response.headers.get("content-type", "").startswith("application/json"):
        spec = client.app.openapi()
        route = "/api/levels" + target
        operation = spec["paths"].get(route, {}).get(method.lower())
        assert operation is not None, (method, route)
        ok = next(iter(operation["responses"][str(response.status_code)]["content"].values()))["schema"]
        assert required_fields(ok, spec) <= set(response.json()), (route, response.json())
