"""The gallery API refuses levels with out-of-range numbers as 422 naming the field (issue 26 §1), on SQLite and
PostgreSQL alike; nothing is stored."""

from tests.gallery.conftest import level_doc


def _bad_levels():
    huge = level_doc()
    huge["env"]["max_timesteps"] = 2147483648
    skip = level_doc()
    skip["env"]["frame_skip"] = 1_000_000
    dt = level_doc()
    dt["env"]["physics"]["dt"] = 1e6
    dense = level_doc()
    dense["bodies"][4]["density"] = 1e5
    return [(huge, "env.max_timesteps: 2147483648 is out of range [1, 100000]"),
            (skip, "env.frame_skip: 1000000 is out of range [1, 16]"),
            (dt, "env.physics.dt: 1e+06 is out of range [0.001, 0.1]"),
            (dense, "bodies[4].density: 100000 is out of range [0.001, 1000]")]


def test_out_of_range_levels_are_refused_on_create_and_update(client, store):
    made = client.post("/api/levels", json={"name": "ok", "level": level_doc()})
    assert made.status_code == 201, made.text
    url, token = f"/api/levels/{made.json()['id']}", made.json()["author_token"]
    before, stored = store.counts(), client.get(url).json()
    assert "level" in stored
    for level, message in _bad_levels():
        response = client.post("/api/levels", json={"name": "bad", "level": level})
        assert response.status_code == 422 and message in response.json()["detail"], response.text
        response = client.put(url, json={"level": level}, headers={"Authorization": f"Bearer {token}"})
        assert response.status_code == 422 and message in response.json()["detail"], response.text
    assert store.counts() == before
    assert client.get(url).json()["level"] == stored["level"]  # the update changed nothing
