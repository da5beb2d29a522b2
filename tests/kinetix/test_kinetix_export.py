"""Export to the public Kinetix JSON: every shipped level and every polygon the editor can draw (3-8 vertices)
writes a file shaped as their loader expects (static sizes, and max_polygon_vertices 4: their loader opens
nothing else), polygons of 5-8 vertices become welded triangles and quadrilaterals with the same outline, mass
and attachments, and the size class holds the result or the error says what does not fit."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from jax2d import scene
from jax2d.geometry import polygon_mass_properties
from kinetix.formats import describe, kinetix_json
from kinetix.formats.fields import index_keyed_list
from kinetix.formats.split import cut
from kinetix.geometry import body_mass_properties, joint_groups
from kinetix.level import NUM_WALLS, SIZES, LevelError, LevelFile, SizeClass, empty_level, make_level, size_class
from kinetix.levels import dumps, load_level, to_document
from tests.kinetix.test_level_formats import assert_bitwise_equal

LEVELS = sorted((Path(__file__).resolve().parents[2] / "levels").glob("*.json"))


def check_their_shape(doc: dict) -> None:
    """What their loader relies on: every array as long as static_env_params says, max_polygon_vertices 4 (their
    empty scene puts the 4-vertex floor in every polygon slot, so any other value fails to broadcast) and every
    vertex array with exactly 4 slots, n_vertices 3 or 4, the walls fixed in slots 0-3, joint and thruster indices
    naming active bodies (polygons then circles), and the manifold caches of the counts their engine uses."""
    static, state = doc["static_env_params"], doc["env_state"]
    P, C = static["num_polygons"], static["num_circles"]
    assert static["max_polygon_vertices"] == 4
    assert len(state["polygon"]) == P and len(state["circle"]) == C
    assert len(state["joint"]) == static["num_joints"] and len(state["thruster"]) == static["num_thrusters"]
    bodies = state["polygon"] + state["circle"]
    for entry in bodies:
        assert len(index_keyed_list(entry["vertices"])) == 4
    for entry in state["polygon"]:
        if entry["active"]:
            assert 3 <= entry["n_vertices"] <= 4
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


def exported(file: LevelFile, size=None) -> tuple[dict, LevelFile]:
    """(the exported document as a file holds it, that document imported through our importer)."""
    doc = json.loads(dumps(file, "kinetix", size))
    check_their_shape(doc)
    return doc, load_level(doc)


# ---------------------------------------------------------------- outline and mass


def world_polygons(file: LevelFile) -> list[tuple[tuple, np.ndarray, float]]:
    """(material key, world vertices, mass) of every non-wall polygon; the key holds everything a part keeps."""
    spec = describe(file.level, file.params)
    mass = np.asarray(body_mass_properties(file.level)[0], np.float64)
    active = np.nonzero(np.asarray(file.level.sim.bodies.active))[0]
    out = []
    for k, body in enumerate(spec.bodies):
        if body.shape != "polygon" or k < NUM_WALLS:
            continue
        c, s = math.cos(body.angle), math.sin(body.angle)
        local = np.asarray(body.vertices, np.float64)
        world = np.asarray(body.position) + local @ np.array([[c, s], [-s, c]])
        key = (body.role, body.fixed, body.density, body.friction, body.restitution, body.collision_mode)
        out.append((key, world, float(mass[active[k]])))
    return out


def inside(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Points inside or on a counter-clockwise convex polygon (with a tolerance of float32 round-off)."""
    edge = np.roll(polygon, -1, axis=0) - polygon
    rel = points[:, None, :] - polygon[None, :, :]
    cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    return np.all(cross >= -1e-6 * np.linalg.norm(edge, axis=1)[None, :], axis=1)


def assert_same_outline_and_mass(original: LevelFile, back: LevelFile) -> None:
    """For every kind of polygon (role, fixed, material, collision mode): the union of the exported polygons
    covers the same area as the original ones (sampled on a grid; symmetric difference < 1% of the area), and
    their total mass is within 1%."""
    before, after = world_polygons(original), world_polygons(back)
    assert {k for k, _, _ in before} == {k for k, _, _ in after}
    for key in {k for k, _, _ in before}:
        shapes = [w for k, w, _ in before if k == key]
        lo, hi = np.min([w.min(0) for w in shapes], axis=0), np.max([w.max(0) for w in shapes], axis=0)
        xs, ys = np.meshgrid(np.linspace(lo[0], hi[0], 240), np.linspace(lo[1], hi[1], 240))
        grid = np.stack([xs.ravel(), ys.ravel()], axis=1)

        def union(polygons):
            return np.any([inside(grid, w) for w in polygons], axis=0)

        a, b = union(shapes), union([w for k, w, _ in after if k == key])
        assert np.sum(a ^ b) <= 0.01 * np.sum(a), key
        mass_before = sum(m for k, _, m in before if k == key)
        mass_after = sum(m for k, _, m in after if k == key)
        assert mass_after == pytest.approx(mass_before, rel=0.01), key


# ---------------------------------------------------------------- every shipped level


@pytest.mark.parametrize("path", LEVELS, ids=[p.stem for p in LEVELS])
def test_every_shipped_level_exports_with_four_vertex_slots_and_the_same_outline_and_mass(path):
    file = load_level(path)
    doc, back = exported(file)
    assert back.format == "kinetix" and back.params == file.params
    big = [b for b in describe(file.level).bodies if b.shape == "polygon" and len(b.vertices) > 4]
    if not big:
        # Nothing to split: every simulated array (bodies, joints, thrusters, gravity, roles, bindings) comes back
        # bit for bit, in the level's own size; only motor_auto is not in their format (no shipped level uses it).
        assert back.size == file.size
        assert not np.asarray(file.level.motor_auto).any()
        assert_bitwise_equal(back.level, file.level)
        return
    assert_same_outline_and_mass(file, back)
    polygons = [e for e in doc["env_state"]["polygon"] if e["active"]]
    assert len(polygons) == sum(b.shape == "polygon" for b in describe(file.level).bodies) + sum(
        math.ceil((len(b.vertices) - 2) / 2) - 1 for b in big)


def test_levels_that_outgrow_size_l_export_with_custom_capacities_the_public_loader_takes():
    file = load_level(LEVELS[[p.stem for p in LEVELS].index("walker")])  # size l; 3 polygons of 5-6 vertices
    export = kinetix_json.prepare(file)
    assert export.size == SizeClass("custom", polygons=13, circles=4, joints=7, thrusters=2)
    assert export.summary() == (
        "split 3 polygons (6, 5 and 5 vertices) into 6 parts welded by 3 fixed joints; exported as size custom "
        "(13 polygons, 4 circles, 7 joints, 2 thrusters); size l is too small for it: 13 polygons > 12 allowed in "
        "size l; 7 joints > 6 allowed in size l; the public Kinetix, whose own sizes are s, m, l, loads it as a "
        "custom size (env_size custom)")
    assert load_level(export.document()).size == export.size


# ---------------------------------------------------------------- random polygons


def random_convex(rng, n: int) -> np.ndarray:
    """n counter-clockwise vertices on a random ellipse (convex), angles at least 0.3 rad apart."""
    while True:
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        if np.min(np.diff(np.append(angles, angles[0] + 2 * np.pi))) > 0.3:
            break
    radii = rng.uniform(0.15, 0.45, 2)
    return np.stack([radii[0] * np.cos(angles), radii[1] * np.sin(angles)], axis=1)


def random_level(seed: int) -> tuple[LevelFile, list[dict]]:
    """An l level with 4 random dynamic convex polygons of 5-8 vertices, moving and spinning, with random
    materials, roles and collision modes; and what each was."""
    rng = np.random.default_rng(seed)
    sim, made = empty_level("l").sim, []
    for k in range(4):
        n = int(rng.integers(5, 9))
        props = dict(position=(0.8 + 1.15 * k, float(rng.uniform(1.0, 4.0))), vertices=random_convex(rng, n),
                     angle=float(rng.uniform(-3, 3)), density=float(rng.uniform(0.2, 5)),
                     friction=float(rng.uniform(0, 1)), restitution=float(rng.uniform(0, 1)),
                     collision_mode=int(rng.integers(0, 3)))
        sim, index = scene.add_polygon(sim, props["position"], props["vertices"], angle=props["angle"],
                                       density=props["density"], friction=props["friction"],
                                       restitution=props["restitution"], collision_mode=props["collision_mode"])
        sim = scene.set_velocity(sim, index, rng.uniform(-2, 2, 2), float(rng.uniform(-3, 3)))
        made.append(dict(props, index=index, n=n))
    roles = np.zeros(sim.num_bodies, np.int32)
    roles[[m["index"] for m in made]] = rng.integers(0, 4, len(made))
    return load_level(to_document(LevelFile(make_level(sim, roles), size=SIZES["l"]))), made


def welded_groups(file: LevelFile) -> dict[int, list[int]]:
    """Slots of the bodies linked by joints, keyed by the group (what our engine uses to skip collisions)."""
    groups: dict[int, list[int]] = {}
    active = np.asarray(file.level.sim.bodies.active)
    for slot, group in enumerate(np.asarray(joint_groups(file.level))):
        if active[slot]:
            groups.setdefault(int(group), []).append(slot)
    return groups


@pytest.mark.parametrize("seed", range(8))
def test_random_polygons_of_five_to_eight_vertices_export_as_welded_parts_of_the_same_body(seed):
    file, made = random_level(seed)
    doc, back = exported(file)
    assert_same_outline_and_mass(file, back)

    b0, b1 = file.level.sim.bodies, back.level.sim.bodies
    mass0, inertia0 = (np.asarray(x, np.float64) for x in body_mass_properties(file.level))
    mass1, inertia1 = (np.asarray(x, np.float64) for x in body_mass_properties(back.level))
    groups = welded_groups(back)
    pos1, vel1 = np.asarray(b1.position, np.float64), np.asarray(b1.velocity, np.float64)
    for polygon in made:
        i = polygon["index"]
        # Its parts: the welded group whose centre of mass is this polygon's (any other group is far away).
        parts = min(groups.values(), key=lambda slots: np.linalg.norm(
            np.average(pos1[slots], axis=0, weights=mass1[slots]) - np.asarray(b0.position[i])))
        assert len(parts) == math.ceil((polygon["n"] - 2) / 2)
        assert all(3 <= int(b1.n_vertices[s]) <= 4 for s in parts)
        m = mass1[parts]
        centre = np.average(pos1[parts], axis=0, weights=m)
        size = float(np.ptp(polygon["vertices"], axis=0).max())
        assert m.sum() == pytest.approx(mass0[i], rel=0.01)
        assert np.linalg.norm(centre - np.asarray(b0.position[i])) < 0.01 * size
        # Inertia about the common centre (parallel axis) and momentum are the polygon's: it moves as one body.
        inertia = np.sum(inertia1[parts] + m * np.sum((pos1[parts] - centre) ** 2, axis=1))
        assert inertia == pytest.approx(inertia0[i], rel=0.01)
        assert np.sum(m[:, None] * vel1[parts], axis=0) == pytest.approx(
            mass0[i] * np.asarray(b0.velocity[i]), rel=0.01, abs=1e-4)
        r, w = pos1[parts] - centre, np.asarray(b1.angular_velocity, np.float64)[parts]
        spin = np.sum(inertia1[parts] * w + m * (r[:, 0] * vel1[parts, 1] - r[:, 1] * vel1[parts, 0]))
        assert spin == pytest.approx(inertia0[i] * float(b0.angular_velocity[i]), rel=0.01, abs=1e-6)
        for s in parts:  # what each part keeps
            for field in ("angle", "angular_velocity", "density", "friction", "restitution", "collision_mode"):
                assert float(getattr(b1, field)[s]) == pytest.approx(float(getattr(b0, field)[i]), abs=1e-6), field
            assert int(back.level.roles[s]) == int(file.level.roles[i])
        # The file's collision matrix (what their engine rebuilds from the joints) never lets two parts collide.
        matrix = np.array([index_keyed_list(row) for row in index_keyed_list(doc["env_state"]["collision_matrix"])])
        assert not matrix[np.ix_(parts, parts)].any()


def test_the_cut_has_the_fewest_parts_and_no_slivers():
    for n in range(5, 9):
        ring = np.array([[math.cos(a), math.sin(a)] for a in np.arange(n) * 2 * math.pi / n])
        parts = cut(ring)
        assert len(parts) == math.ceil((n - 2) / 2) and all(3 <= len(p) <= 4 for p in parts)
        assert set().union(*parts) == set(range(n))
        areas = [polygon_mass_properties(ring[list(p)], 1.0)[0] for p in parts]
        assert sum(areas) == pytest.approx(polygon_mass_properties(ring, 1.0)[0])
        assert areas == sorted(areas, reverse=True)  # the largest part first (it keeps the polygon's index)
    # A rectangle with a vertex in the middle of its right side: cutting off the three points in a line would
    # leave a zero-area triangle; the cut avoids it.
    flat = np.array([[-1, -0.5], [1, -0.5], [1, 0], [1, 0.5], [-1, 0.5]])
    parts = cut(flat)
    assert all(abs(polygon_mass_properties(flat[list(p)], 1.0)[0]) > 0.1 for p in parts)


# ---------------------------------------------------------------- joints, thrusters, motors


def octagon(radius: float) -> np.ndarray:
    return np.array([[math.cos(a), math.sin(a)] for a in np.arange(8) * math.pi / 4]) * radius


def world(file: LevelFile, body: int, anchor) -> np.ndarray:
    b = file.level.sim.bodies
    angle = float(b.angle[body])
    c, s = math.cos(angle), math.sin(angle)
    return np.asarray(b.position[body], np.float64) + np.array([[c, -s], [s, c]]) @ np.asarray(anchor, np.float64)


def test_joints_and_thrusters_move_to_the_part_under_their_anchor_and_motors_keep_their_strength():
    sim = empty_level("l").sim
    sim, body = scene.add_polygon(sim, (2.5, 2.0), octagon(0.5), angle=0.4, density=2.0)
    sim, wheel = scene.add_circle(sim, (2.8, 1.8), 0.15)
    sim, _ = scene.add_revolute_joint(sim, body, wheel, (2.8, 1.8), motor_on=True, motor_power=1.5, limits=(-1, 1))
    sim, _ = scene.add_thruster(sim, body, (2.2, 2.3), angle=0.7, power=0.8)
    file = load_level(to_document(LevelFile(make_level(sim), size=SIZES["l"])))
    doc, back = exported(file)
    j0, j1 = file.level.sim.joints, back.level.sim.joints
    t0, t1 = file.level.sim.thrusters, back.level.sim.thrusters
    b1 = back.level.sim.bodies
    # The original joint and thruster come first; the welds after.
    assert int(np.sum(np.asarray(j1.active))) == 1 + 2 and np.asarray(j1.fixed)[1:3].all()
    part, circle = int(j1.a[0]), int(j1.b[0])
    assert part != body and 3 <= int(b1.n_vertices[part]) <= 4  # the part under (2.8, 1.8), not the largest
    assert inside(world(file, body, j0.anchor_a[0])[None], world_outline(back, part))[0]
    np.testing.assert_allclose(world(back, part, j1.anchor_a[0]), world(file, body, j0.anchor_a[0]), atol=1e-5)
    np.testing.assert_allclose(world(back, circle, j1.anchor_b[0]), world(file, wheel, j0.anchor_b[0]), atol=1e-5)
    assert float(j1.ref_angle[0]) == pytest.approx(float(j0.ref_angle[0]), abs=1e-6)
    assert (float(j1.lower[0]), float(j1.upper[0]), bool(j1.motor_on[0])) == (-1.0, 1.0, True)
    # Motor torque limit = power x axial mass 1 / (1/I_a + 1/I_b) in both engines: the same as on the octagon.
    i0, i1 = file.level.sim.bodies.inv_inertia, b1.inv_inertia

    def limit(joints, inv_inertia):
        return float(joints.motor_power[0]) / (float(inv_inertia[joints.a[0]]) + float(inv_inertia[joints.b[0]]))

    assert float(j1.motor_power[0]) > 1.5 and limit(j1, i1) == pytest.approx(limit(j0, i0), rel=1e-4)
    thruster_part = int(t1.body[0])
    assert inside(world(file, body, t0.anchor[0])[None], world_outline(back, thruster_part))[0]
    np.testing.assert_allclose(world(back, thruster_part, t1.anchor[0]), world(file, body, t0.anchor[0]), atol=1e-5)
    assert float(t1.angle[0]) + float(b1.angle[thruster_part]) == pytest.approx(
        float(t0.angle[0]) + float(file.level.sim.bodies.angle[body]), abs=1e-6)
    assert float(t1.power[0]) == pytest.approx(0.8)
    # One group for collisions: the octagon's parts and the wheel jointed to it never collide with each other.
    group = next(g for g in welded_groups(back).values() if circle in g)
    assert len(group) == 3 + 1
    notes = kinetix_json.export_notes(back)  # already split: nothing more to split
    assert notes[0] == "exported as size l"
    notes = kinetix_json.export_notes(file)
    assert notes[0] == "split 1 polygon (8 vertices) into 3 parts welded by 2 fixed joints; exported as size l"
    assert any(n.startswith("Motor power scaled (joints[0] x") for n in notes)


def world_outline(file: LevelFile, body: int) -> np.ndarray:
    b = file.level.sim.bodies
    return np.array([world(file, body, v) for v in np.asarray(b.vertices[body])[: int(b.n_vertices[body])]])


def test_a_fixed_polygon_is_welded_only_when_something_is_jointed_to_it():
    sim = empty_level("l").sim
    sim, free = scene.add_polygon(sim, (1.0, 1.0), octagon(0.3), fixed=True)
    sim, pivot = scene.add_polygon(sim, (3.0, 3.0), octagon(0.3), fixed=True)
    sim, arm = scene.add_rectangle(sim, (3.5, 3.0), 1.0, 0.1)
    sim, _ = scene.add_revolute_joint(sim, pivot, arm, (3.0, 3.0))
    file = load_level(to_document(LevelFile(make_level(sim), size=SIZES["l"])))
    _, back = exported(file)
    assert int(np.sum(np.asarray(back.level.sim.joints.active))) == 1 + 2  # the arm's joint and the pivot's welds
    assert back.warnings == ()  # welds between fixed parts are not "joints that do nothing"
    assert sorted(len(g) for g in welded_groups(back).values() if len(g) > 1) == [3 + 1]
    assert kinetix_json.prepare(file).summary().startswith(
        "split 2 polygons (8 and 8 vertices) into 6 parts welded by 2 fixed joints (the parts of 1 fixed polygon "
        "without joints are not welded: they never move)")


# ---------------------------------------------------------------- size classes and messages


def level_with(size, *polygons: int) -> LevelFile:
    """Walls and regular polygons of these vertex counts (ten to a row, overlapping when there are many)."""
    sim = empty_level(size).sim
    for k, n in enumerate(polygons):
        ring = [[math.cos(a), math.sin(a)] for a in np.arange(n) * 2 * math.pi / n]
        sim, _ = scene.add_polygon(sim, (0.5 + 0.45 * (k % 10), 1.0 + 0.45 * (k // 10)), np.array(ring) * 0.2)
    return load_level(to_document(LevelFile(make_level(sim), size=size_class(size))))


def test_the_summary_says_what_was_split_and_the_size_written():
    export = kinetix_json.prepare(level_with("l", 8, 6))
    assert export.summary() == ("split 2 polygons (8 and 6 vertices) into 5 parts welded by 3 fixed joints; "
                                "exported as size l")
    assert export.notes() == []


def test_a_level_that_outgrows_its_size_moves_to_the_next_public_size_and_says_why():
    file = level_with("m", 8)  # 4 walls + 3 parts = 7 polygons > 6 in m; 2 welds fit m's 2 joints
    export = kinetix_json.prepare(file)
    assert export.size == SIZES["l"]
    assert export.summary() == ("split 1 polygon (8 vertices) into 3 parts welded by 2 fixed joints; exported as "
                                "size l (size m is too small for it: 7 polygons > 6 allowed in size m)")
    assert exported(file)[1].size == SIZES["l"]


def test_a_size_asked_for_must_hold_the_split_level_and_the_error_names_what_does_not_fit():
    file = level_with("l", 8)
    with pytest.raises(LevelError, match=r"in size m after it split 1 polygon \(8 vertices\) into 3 parts welded "
                                         r"by 2 fixed joints: 7 polygons > 6 allowed in size m$"):
        dumps(file, "kinetix", "m")
    assert exported(file, "xl")[1].size == SIZES["xl"]


def test_a_level_too_big_for_any_size_after_splitting_is_refused_naming_the_counts():
    file = level_with(SizeClass("custom", polygons=4 + 90, circles=0, joints=0, thrusters=0), *[8] * 90)
    with pytest.raises(LevelError, match=r"the level needs 274 bodies \(274 polygons, 0 circles\) > 256 allowed in "
                                         r"any size class$"):
        kinetix_json.prepare(file)


def test_what_cannot_be_written_is_refused_with_the_reason():
    sim = scene.remove_body(empty_level("s").sim, 2)
    with pytest.raises(LevelError, match="fixed polygons .* in polygon slots 0-3"):
        to_document(LevelFile(make_level(sim), size=SIZES["s"]), "kinetix")


def test_kinetix_convert_says_what_it_split_and_refuses_a_size_too_small(capsys, tmp_path):
    from kinetix import cli

    source, out = LEVELS[[p.stem for p in LEVELS].index("octagon_roll")], tmp_path / "octagon_roll.kinetix.json"
    assert cli.main(["convert", str(source), str(out)]) == 0
    printed, notes = capsys.readouterr()
    assert printed == (f"wrote {out} (kinetix format: split 2 polygons (8 and 7 vertices) into 6 parts welded by 2 "
                       "fixed joints (the parts of 1 fixed polygon without joints are not welded: they never move); "
                       "exported as size l (size m is too small for it: 10 polygons > 6 allowed in size m))\n")
    assert "the split polygon bodies[4] (green, 3 parts) counts once per part" in notes
    check_their_shape(json.loads(out.read_text()))
    before = out.read_text()
    assert cli.main(["convert", str(source), str(out), "--size", "m"]) == 1
    assert "10 polygons > 6 allowed in size m" in capsys.readouterr().err
    assert out.read_text() == before  # nothing half-written


def test_a_split_level_simulates_as_the_original_in_our_engine():
    """octagon_roll (a thrusted green octagon rolling over a fixed heptagon): 120 steps at full thrust, original
    and exported side by side (both in size l: one compiled program). Measured: the octagon's centre of mass
    ends 0.2 mm from the original's, and its welds stretch by 0.03 mm."""
    import jax
    import jax.numpy as jnp

    import jax2d
    from kinetix.bindings import expand_actions
    from kinetix.level import solver_for

    path = LEVELS[[p.stem for p in LEVELS].index("octagon_roll")]
    original = load_level(path, size="l")
    _, back = exported(load_level(path))
    assert back.size == original.size == SIZES["l"]

    config, params = solver_for(original.level), original.params.sim_params()

    @jax2d.jit
    def run(level):
        motor, thrust = expand_actions(level, jnp.ones(4), jnp.ones(2))

        def one(state, _):
            state = jax2d.step(state, params, motor, thrust, config)
            return state, state.bodies.position
        return jax.lax.scan(one, level.sim, None, length=120)[1]

    before, after = np.asarray(run(original.level)), np.asarray(run(back.level))
    assert np.isfinite(after).all()
    octagon = NUM_WALLS  # the green octagon; its parts: the welded group holding its slot
    parts = next(g for g in welded_groups(back).values() if octagon in g)
    mass = np.asarray(body_mass_properties(back.level)[0])[parts]
    centre = np.sum(after[:, parts] * mass[None, :, None], axis=1) / mass.sum()
    assert np.linalg.norm(centre - before[:, octagon], axis=1).max() < 0.005
    gaps = np.linalg.norm(after[:, parts[1:]] - after[:, parts[:1]], axis=2)
    assert np.abs(gaps - gaps[0]).max() < 0.002
