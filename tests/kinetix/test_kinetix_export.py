"""Export to the public Kinetix JSON: every shipped level and every polygon the editor can draw (3-8 vertices)
writes a file shaped as their loader expects (static sizes and the vertex limit the level needs), and importing
it gives back the same simulated level."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from jax2d import scene
from kinetix.formats import describe, kinetix_json
from kinetix.formats.fields import index_keyed_list
from kinetix.level import NUM_WALLS, SIZES, LevelError, LevelFile, empty_level, make_level
from kinetix.levels import load_level, to_document
from tests.kinetix.test_level_formats import assert_bitwise_equal

LEVELS = sorted((Path(__file__).resolve().parents[2] / "levels").glob("*.json"))


def check_their_shape(doc: dict) -> None:
    """What their loader relies on: every array as long as static_env_params says, every polygon with exactly
    max_polygon_vertices vertex slots and n_vertices within them, the walls fixed in slots 0-3, joint and thruster
    indices naming active bodies (polygons then circles), and the manifold caches of the counts their engine uses."""
    static, state = doc["static_env_params"], doc["env_state"]
    P, C, V = static["num_polygons"], static["num_circles"], static["max_polygon_vertices"]
    assert len(state["polygon"]) == P and len(state["circle"]) == C
    assert len(state["joint"]) == static["num_joints"] and len(state["thruster"]) == static["num_thrusters"]
    bodies = state["polygon"] + state["circle"]
    for entry in bodies:
        assert len(index_keyed_list(entry["vertices"])) == V
    for entry in state["polygon"]:
        if entry["active"]:
            assert 3 <= entry["n_vertices"] <= V
    assert all(state["polygon"][k]["active"] and state["polygon"][k]["inverse_mass"] == 0 for k in range(NUM_WALLS))
    assert static["num_static_fixated_polys"] == NUM_WALLS
    for joint in state["joint"]:
        if joint["active"]:
            assert bodies[joint["a_index"]]["active"] and bodies[joint["b_index"]]["active"]
    for thruster in state["thruster"]:
        if thruster["active"]:
            assert bodies[thruster["object_index"]]["active"]
    S = NUM_WALLS
    assert len(state["acc_rr_manifolds"]) == 2 * (P * (P - 1) // 2 - S * (S - 1) // 2)
    assert len(state["acc_cr_manifolds"]) == P * C and len(state["acc_cc_manifolds"]) == C * (C - 1) // 2
    assert len(state["collision_matrix"]) == P + C


@pytest.mark.parametrize("path", LEVELS, ids=[p.stem for p in LEVELS])
def test_every_shipped_level_round_trips_through_the_kinetix_format(path):
    file = load_level(path)
    doc = json.loads(json.dumps(to_document(file, "kinetix")))  # what a file holds
    check_their_shape(doc)
    needed = max([4] + [len(b.vertices) for b in describe(file.level, file.params).bodies if b.shape == "polygon"])
    assert doc["static_env_params"]["max_polygon_vertices"] == needed
    back = load_level(doc)
    assert back.format == "kinetix" and back.size == file.size and back.params == file.params
    # Every simulated array (bodies, joints, thrusters, gravity, roles, bindings) comes back bit for bit; only
    # motor_auto is not in their format (no shipped level uses it).
    assert not np.asarray(file.level.motor_auto).any()
    assert_bitwise_equal(back.level, file.level)


def test_polygons_of_five_to_eight_vertices_export_with_the_vertex_limit_they_need():
    sim = empty_level("l").sim
    for k, n in enumerate(range(5, 9)):
        ring = [[math.cos(a), math.sin(a)] for a in np.arange(n) * 2 * math.pi / n]
        sim, _ = scene.add_polygon(sim, (0.8 + 1.1 * k, 2.0), np.array(ring) * 0.3)
    file = load_level(to_document(LevelFile(make_level(sim), size=SIZES["l"])))
    doc = json.loads(json.dumps(to_document(file, "kinetix")))
    check_their_shape(doc)
    assert doc["static_env_params"]["max_polygon_vertices"] == 8
    assert [e["n_vertices"] for e in doc["env_state"]["polygon"] if e["active"]][NUM_WALLS:] == [5, 6, 7, 8]
    assert_bitwise_equal(load_level(doc).level, file.level)
    notes = kinetix_json.export_notes(describe(file.level, file.params))
    assert len(notes) == 1 and "the 8-vertex polygon at (4.10, 2.00)" in notes[0] and "first 4 vertices" in notes[0]


def test_a_level_of_quadrilaterals_keeps_their_four_vertex_slots_and_has_no_notes():
    file = load_level(LEVELS[[p.stem for p in LEVELS].index("car_right")])
    doc = to_document(file, "kinetix")
    assert doc["static_env_params"]["max_polygon_vertices"] == 4
    assert kinetix_json.export_notes(describe(file.level, file.params)) == []


def test_what_cannot_be_written_is_refused_with_the_reason():
    sim = scene.remove_body(empty_level("s").sim, 2)
    with pytest.raises(LevelError, match="fixed polygons .* in polygon slots 0-3"):
        to_document(LevelFile(make_level(sim), size=SIZES["s"]), "kinetix")
