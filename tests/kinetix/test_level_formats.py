"""Level files: the shared public Kinetix levels, our format, conversions, size classes and malformed input."""

import copy
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from kinetix.bindings import expand_actions
from kinetix.formats import ours
from kinetix.formats.fields import index_keyed_list
from kinetix.level import (
    NUM_WALLS,
    ROLE_BLUE,
    ROLE_GREEN,
    ROLE_RED,
    SIZES,
    LevelError,
    LevelFile,
    LevelParams,
    SizeClass,
    empty_level,
    make_level,
)
from kinetix.levels import dumps, load_level, resize, save_level, to_document

SIZE_DIRS = ("s", "m", "l")


def shared_files(shared_dir):
    files = sorted(p for size in SIZE_DIRS for p in (shared_dir / "kinetix-levels" / size).glob("*.json"))
    assert len(files) == 60, f"expected the 60 shared Kinetix levels, found {len(files)}"
    return files


def assert_bitwise_equal(a, b):
    """Same tree, and every leaf has the same dtype, shape and bytes (so -0.0 != 0.0 and NaN == NaN)."""
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    paths = jax.tree_util.tree_flatten_with_path(a)[0]
    for (path, x), y in zip(paths, jax.tree_util.tree_leaves(b), strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape, jax.tree_util.keystr(path)
        assert x.tobytes() == y.tobytes(), f"{jax.tree_util.keystr(path)} differs:\n{x}\n{y}"


def rotate(angle, v):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def joint_world_points(level):
    """(J, 2, 2) world positions of both anchors of every active joint."""
    b, j = level.sim.bodies, level.sim.joints
    out = []
    for k in np.nonzero(np.asarray(j.active))[0]:
        ends = []
        for body, anchor in ((j.a[k], j.anchor_a[k]), (j.b[k], j.anchor_b[k])):
            ends.append(np.asarray(b.position[body], np.float64) + rotate(float(b.angle[body]), np.asarray(anchor)))
        out.append(ends)
    return np.array(out)


def their_vertices(entry):
    vs = index_keyed_list(entry["vertices"])
    return [[v["0"], v["1"]] for v in vs[: entry["n_vertices"]]]


# ---------------------------------------------------------------- a level built in code


def robot_level(size="l") -> LevelFile:
    """Walls, a triangle body with a motored wheel, a box on a limited joint, a welded circle and a thruster."""
    sim = empty_level(size).sim
    sim, body = scene.add_polygon(sim, (2.0, 1.2), [[-0.4, -0.2], [0.4, -0.2], [0.0, 0.35]], angle=0.3)
    sim, box = scene.add_rectangle(sim, (3.2, 1.0), 0.4, 0.6, density=2.0, friction=0.5)
    sim, wheel = scene.add_circle(sim, (2.3, 0.8), 0.2, restitution=0.25)
    sim, ball = scene.add_circle(sim, (1.7, 1.3), 0.1, collision_mode=0)
    sim, _ = scene.add_revolute_joint(sim, body, wheel, (2.3, 0.8), motor_on=True, motor_speed=2.0, motor_power=1.5)
    sim, _ = scene.add_revolute_joint(sim, body, box, (2.8, 1.1), limits=(-0.5, 0.25))
    sim, _ = scene.add_fixed_joint(sim, body, ball, (1.75, 1.25))
    sim, _ = scene.add_thruster(sim, body, (2.0, 1.2), angle=1.2, power=0.5)
    roles = np.zeros(sim.num_bodies, np.int32)
    roles[[body, wheel, box]] = ROLE_GREEN, ROLE_GREEN, ROLE_BLUE
    roles[0] = ROLE_RED
    bindings = np.zeros(sim.num_joints, np.int32)
    bindings[:2] = 2, 3
    auto = np.zeros(sim.num_joints, bool)
    auto[1] = True
    thruster_bindings = np.zeros(sim.num_thrusters, np.int32)
    thruster_bindings[0] = 1
    level = make_level(sim, roles, bindings, auto, thruster_bindings)
    params = LevelParams(max_timesteps=300, frame_skip=3, dense_reward_scale=0.25, dt=0.02, base_motor_speed=5.0)
    return LevelFile(level, params, SIZES[size] if isinstance(size, str) else size, "robot")


@pytest.fixture(scope="module")
def robot() -> LevelFile:
    """The robot level after one trip through our format: the canonical form of a level built in code."""
    return load_level(to_document(robot_level()))


# ---------------------------------------------------------------- the shared public levels


def test_every_shared_level_loads_in_its_size_and_round_trips_bitwise(shared_dir):
    for path in shared_files(shared_dir):
        file = load_level(path)
        assert file.format == "kinetix" and file.size == SIZES[path.parent.name], path
        assert file.warnings == (), path
        assert file.name == path.stem

        again = load_level(json.loads(json.dumps(to_document(file, "kinetix"))))
        assert_bitwise_equal(again.level, file.level)
        assert (again.params, again.size) == (file.params, file.size)

        text = dumps(file)
        ours_again = load_level(json.loads(text))
        assert_bitwise_equal(ours_again.level, file.level)
        assert (ours_again.params, ours_again.size, ours_again.name) == (file.params, file.size, file.name)
        assert dumps(ours_again) == text, f"{path}: save -> load -> save changed the file"


def test_import_keeps_exactly_the_active_entities_with_their_values(shared_dir):
    for path in shared_files(shared_dir):
        data = json.loads(path.read_text())
        state = data["env_state"]
        file = load_level(path)
        sim, P = file.level.sim, file.size.polygons
        active = {kind: [e for e in state[kind] if e["active"]] for kind in ("polygon", "circle", "joint", "thruster")}
        assert int(np.sum(sim.bodies.active[:P])) == len(active["polygon"])
        assert int(np.sum(sim.bodies.active[P:])) == len(active["circle"])
        assert int(np.sum(sim.joints.active)) == len(active["joint"])
        assert int(np.sum(sim.thrusters.active)) == len(active["thruster"])
        # Slots are filled in order: polygons 0.., circles P..
        assert bool(np.all(sim.bodies.active[: len(active["polygon"])]))
        for k, entry in enumerate(active["polygon"][NUM_WALLS:], start=NUM_WALLS):
            np.testing.assert_array_equal(sim.bodies.position[k], np.float32([entry["position"]["0"],
                                                                              entry["position"]["1"]]))
            n = entry["n_vertices"]
            # Their clockwise order, reversed.
            np.testing.assert_array_equal(sim.bodies.vertices[k, :n], np.float32(their_vertices(entry)[::-1]))
            assert int(file.level.roles[k]) == entry["role"]
            assert bool(sim.bodies.inv_mass[k] == 0) == (entry["inverse_mass"] == 0)
        for k, entry in enumerate(active["circle"]):
            assert float(sim.bodies.radius[k]) == np.float32(entry["radius"])
            assert int(file.level.roles[P + k]) == entry["role"]


def test_imported_masses_agree_with_the_files(shared_dir):
    """Masses are recomputed from geometry and density; the files' own values agree to float32 round-off.

    Circle inertia is the exception: their engine uses m r^2 / 4 for a disc, ours the textbook m r^2 / 2,
    so our inverse inertia of a circle is half of theirs.
    """
    worst_mass = worst_polygon_inertia = worst_circle_ratio = 0.0
    for path in shared_files(shared_dir):
        state = json.loads(path.read_text())["env_state"]
        file = load_level(path)
        b, P = file.level.sim.bodies, file.size.polygons
        for offset, kind in ((0, "polygon"), (P, "circle")):
            for k, entry in enumerate(e for e in state[kind] if e["active"]):
                if entry["inverse_mass"] == 0:
                    assert float(b.inv_mass[offset + k]) == 0.0
                    continue
                worst_mass = max(worst_mass, abs(float(b.inv_mass[offset + k]) / entry["inverse_mass"] - 1))
                ratio = float(b.inv_inertia[offset + k]) / entry["inverse_inertia"]
                if kind == "polygon":
                    worst_polygon_inertia = max(worst_polygon_inertia, abs(ratio - 1))
                else:
                    worst_circle_ratio = max(worst_circle_ratio, abs(ratio - 0.5))
    print(f"largest relative difference of inverse mass from the files: {worst_mass:.2e}; "
          f"polygon inverse inertia: {worst_polygon_inertia:.2e}; circle inverse inertia vs half theirs: "
          f"{worst_circle_ratio:.2e}")
    assert worst_mass < 1e-4 and worst_polygon_inertia < 1e-4 and worst_circle_ratio < 1e-4


def test_imported_walls_are_the_standard_walls(shared_dir):
    standard = empty_level("s").sim.bodies
    for path in shared_files(shared_dir):
        b = load_level(path).level.sim.bodies
        for name in ("position", "angle", "inv_mass", "inv_inertia", "collision_mode", "active", "n_vertices",
                     "restitution", "density"):
            np.testing.assert_array_equal(getattr(b, name)[:NUM_WALLS], getattr(standard, name)[:NUM_WALLS], name)
        np.testing.assert_array_equal(b.vertices[:NUM_WALLS, :4], standard.vertices[:NUM_WALLS, :4])
    # The geometry the docs describe: floor top at y = 0.4, walls at x = 0 and x = 5, ceiling at y = 5.
    top = lambda i, axis, pick: float(pick(standard.position[i, axis] + standard.vertices[i, :4, axis]))  # noqa: E731
    assert top(0, 1, np.max) == pytest.approx(0.4, abs=1e-6)
    assert top(1, 0, np.max) == 0.0 and top(2, 0, np.min) == 5.0 and top(3, 1, np.min) == pytest.approx(5.0)


def test_export_has_the_shape_of_their_files_and_reproduces_their_values(shared_dir):
    def skeleton(x):
        if isinstance(x, dict):
            return {k: skeleton(v) for k, v in x.items()}
        if isinstance(x, list):
            return [skeleton(x[0])] if x else []
        return type(x).__name__

    for path in shared_files(shared_dir):
        theirs = json.loads(path.read_text())
        exported = json.loads(json.dumps(to_document(load_level(path), "kinetix")))
        assert skeleton(exported) == skeleton(theirs), path
        state, their_state = exported["env_state"], theirs["env_state"]
        for kind in ("polygon", "circle", "joint", "thruster", "acc_rr_manifolds", "acc_cr_manifolds",
                     "acc_cc_manifolds"):
            assert len(state[kind]) == len(their_state[kind]), (path, kind)
        assert exported["static_env_params"] == theirs["static_env_params"]
        assert exported["env_params"] == theirs["env_params"]
        ours_active = [e for e in state["polygon"] if e["active"]][NUM_WALLS:]
        their_active = [e for e in their_state["polygon"] if e["active"]][NUM_WALLS:]
        for mine, their in zip(ours_active, their_active, strict=True):
            for key in ("position", "rotation", "velocity", "vertices", "role", "density", "friction", "restitution",
                        "collision_mode", "n_vertices"):
                assert mine[key] == their[key], (path, key)
        # Body slots keep their indices when no inactive body sits before an active one.
        flags = [e["active"] for e in their_state["polygon"]], [e["active"] for e in their_state["circle"]]
        if all(f == sorted(f, reverse=True) for f in flags):
            assert state["collision_matrix"] == their_state["collision_matrix"], path
            for mine, their in zip(state["joint"], their_state["joint"], strict=True):
                if their["active"]:
                    for key in ("a_index", "b_index", "a_relative_pos", "b_relative_pos", "rotation", "is_fixed_joint"):
                        assert mine[key] == their[key], (path, key)


# ---------------------------------------------------------------- levels built in code, synthetic public files


def test_our_format_keeps_a_level_built_in_code(robot):
    original = robot_level().level
    loaded = robot.level
    for name in ("active", "angle", "collision_mode", "friction", "restitution", "density", "n_vertices", "radius"):
        np.testing.assert_array_equal(getattr(loaded.sim.bodies, name), getattr(original.sim.bodies, name), name)
    for name in ("position", "vertices", "inv_mass", "inv_inertia"):
        np.testing.assert_allclose(getattr(loaded.sim.bodies, name), getattr(original.sim.bodies, name), rtol=1e-6,
                                   atol=1e-6, err_msg=name)
    for name in ("a", "b", "active", "fixed", "motor_on", "limit_on", "motor_speed", "motor_power", "lower", "upper"):
        np.testing.assert_array_equal(getattr(loaded.sim.joints, name), getattr(original.sim.joints, name), name)
    np.testing.assert_allclose(loaded.sim.joints.anchor_a, original.sim.joints.anchor_a, atol=1e-6)
    for name in ("roles", "motor_bindings", "motor_auto", "thruster_bindings"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(original, name), name)
    assert robot.params == robot_level().params and robot.name == "robot"
    # From now on the level is canonical: every further trip is bitwise stable.
    assert_bitwise_equal(load_level(json.loads(dumps(robot))).level, robot.level)


def test_synthetic_public_file_with_triangles_dict_arrays_and_unknown_fields_loads(robot):
    data = json.loads(json.dumps(to_document(robot, "kinetix")))
    triangle = data["env_state"]["polygon"][NUM_WALLS]
    assert triangle["n_vertices"] == 3
    # Key the top-level entity arrays "0".."n" as other published files do, and add fields from the future.
    state = data["env_state"]
    for kind in ("polygon", "circle", "joint", "thruster"):
        state[kind] = {str(i): entry for i, entry in enumerate(state[kind])}
    state["polygon"]["5"]["sparkle"] = 3
    state["joint"]["0"]["motor_auto_future"] = True
    data["version"] = "1.0.0"
    data["env_params"]["brand_new_param"] = {"0": 1}
    loaded = load_level(data)
    assert loaded.format == "kinetix" and loaded.size == robot.size
    # motor_auto is not part of their format: it is lost, as in their own tools; everything else is kept.
    r = robot.level
    expected = make_level(r.sim, r.roles, r.motor_bindings, np.zeros_like(r.motor_auto), r.thruster_bindings)
    assert_bitwise_equal(loaded.level, expected)
    assert loaded.params == robot.params


def test_vertex_order_is_reversed_between_the_formats(robot):
    data = to_document(robot, "kinetix")
    triangle = data["env_state"]["polygon"][NUM_WALLS]
    theirs = np.array(their_vertices(triangle))
    area = 0.5 * np.sum(theirs[:, 0] * np.roll(theirs[:, 1], -1) - theirs[:, 1] * np.roll(theirs[:, 0], -1))
    assert area < 0, "their vertices must be clockwise"
    np.testing.assert_array_equal(theirs[::-1], np.asarray(robot.level.sim.bodies.vertices[NUM_WALLS, :3]))


def test_export_collision_matrix_excludes_jointed_bodies(robot):
    data = to_document(robot, "kinetix")
    P = robot.size.polygons
    matrix = data["env_state"]["collision_matrix"]
    body, box, wheel, ball = NUM_WALLS, NUM_WALLS + 1, P, P + 1  # triangle, box, then the circles
    N = P + robot.size.circles
    assert len(matrix) == N and all(len(row) == N for row in matrix.values())
    linked = {body, box, wheel, ball}  # all joined to the triangle
    for i in range(N):
        for j in range(N):
            expected = not (i == j or (i in linked and j in linked))
            assert matrix[str(i)][str(j)] == expected, (i, j)
    P, C = robot.size.polygons, robot.size.circles
    assert len(data["env_state"]["acc_rr_manifolds"]) == 2 * (P * (P - 1) // 2 - 6)
    assert len(data["env_state"]["acc_cr_manifolds"]) == P * C
    assert len(data["env_state"]["acc_cc_manifolds"]) == C * (C - 1) // 2


def test_eight_vertex_polygon_exports_to_kinetix_as_welded_parts_of_four_vertex_slots():
    sim = empty_level("l").sim
    octagon = [[math.cos(a), math.sin(a)] for a in np.arange(8) * math.pi / 4]
    sim, _ = scene.add_polygon(sim, (2.5, 2.0), np.array(octagon) * 0.3)
    file = load_level(to_document(LevelFile(make_level(sim), size=SIZES["l"])))
    data = to_document(file, "kinetix")
    assert data["static_env_params"]["max_polygon_vertices"] == 4
    back = load_level(data)
    assert [int(n) for n in back.level.sim.bodies.n_vertices[NUM_WALLS:7]] == [4, 4, 4]
    joints = back.level.sim.joints
    assert int(np.sum(np.asarray(joints.active))) == 2 and np.asarray(joints.fixed)[:2].all()
    # The same level again: a second export splits nothing and round-trips bitwise.
    assert_bitwise_equal(load_level(to_document(back, "kinetix")).level, back.level)


def test_kinetix_export_needs_the_walls_first():
    sim = scene.remove_body(empty_level("s").sim, 2)
    with pytest.raises(LevelError, match="fixed polygons .* in polygon slots 0-3"):
        to_document(LevelFile(make_level(sim), size=SIZES["s"]), "kinetix")


# ---------------------------------------------------------------- size classes


def test_small_level_loads_into_a_larger_size_with_joint_and_thruster_indices_fixed(shared_dir):
    path = shared_dir / "kinetix-levels" / "s" / "h3_point_the_thruster.json"  # a joint and a thruster on circles
    small = load_level(path)
    large = load_level(path, size="l")
    assert large.size == SIZES["l"] and large.level.capacity == SIZES["l"].capacity
    sb, lb = small.level.sim.bodies, large.level.sim.bodies
    Ps, Pl = SIZES["s"].polygons, SIZES["l"].polygons
    n_poly, n_circ = int(np.sum(sb.active[:Ps])), int(np.sum(sb.active[Ps:]))
    assert int(np.sum(lb.active[:Pl])) == n_poly and int(np.sum(lb.active[Pl:])) == n_circ
    assert n_circ > 0, "the level must have circles, whose global index changes"
    np.testing.assert_array_equal(lb.position[Pl : Pl + n_circ], sb.position[Ps : Ps + n_circ])
    sj, lj = small.level.sim.joints, large.level.sim.joints
    assert bool(sj.active[0]) and bool(lj.active[0]) and not bool(np.any(lj.active[1:]))
    for side in ("a", "b"):
        np.testing.assert_array_equal(lb.position[int(getattr(lj, side)[0])], sb.position[int(getattr(sj, side)[0])])
    assert int(lj.b[0]) >= Pl  # the circle's index moved past the larger polygon block
    np.testing.assert_array_equal(joint_world_points(large.level), joint_world_points(small.level))
    st, lt = small.level.sim.thrusters, large.level.sim.thrusters
    np.testing.assert_array_equal(lb.position[int(lt.body[0])], sb.position[int(st.body[0])])
    np.testing.assert_array_equal(large.level.roles[Pl : Pl + n_circ], small.level.roles[Ps : Ps + n_circ])
    # Resizing a loaded level gives the same arrays, and back again gives the original.
    assert_bitwise_equal(resize(small, "l").level, large.level)
    assert_bitwise_equal(resize(large, "s").level, small.level)


def test_level_too_big_for_the_size_lists_every_overflow():
    data = ours.write(load_level(to_document(empty_level("l"))))
    circle = {"shape": "circle", "position": [1.0, 1.0], "radius": 0.1}
    data["bodies"] += [copy.deepcopy(circle) for _ in range(7)]
    with pytest.raises(LevelError, match=r"^level does not fit: 7 circles > 4 allowed in size l$"):
        load_level(data)
    box = {"shape": "polygon", "position": [1.0, 2.0], "vertices": [[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1]]}
    data["bodies"] += [copy.deepcopy(box) for _ in range(9)]
    with pytest.raises(LevelError, match="13 polygons > 12 allowed in size l; 7 circles > 4 allowed in size l"):
        load_level(data)
    data["size"] = "m"
    with pytest.raises(LevelError, match="13 polygons > 6 allowed in size m; 7 circles > 3 allowed in size m"):
        load_level(data)


def test_large_level_does_not_fit_a_small_size(shared_dir):
    with pytest.raises(LevelError, match=r"polygons > 5 allowed in size s"):
        load_level(shared_dir / "kinetix-levels" / "l" / "car_swing_around.json", size="s")


def test_custom_size_round_trips_and_missing_size_picks_the_smallest_that_fits(robot):
    custom = SizeClass("custom", polygons=9, circles=3, joints=4, thrusters=1, max_vertices=6)
    file = resize(robot, custom)
    data = ours.write(file)
    assert data["size"] == {"polygons": 9, "circles": 3, "joints": 4, "thrusters": 1, "max_vertices": 6}
    again = load_level(data)
    assert again.size == custom
    assert_bitwise_equal(again.level, file.level)
    del data["size"]
    assert load_level(data).size == SIZES["l"]  # 3 joints do not fit m
    tiny = {"format_version": 1, "bodies": [{"shape": "circle", "position": [0, 1], "radius": 0.5}]}
    assert load_level(tiny).size == SIZES["s"]
    assert LevelFile(file.level).size == custom  # derived from the arrays when not given
    with pytest.raises(LevelError, match="use kinetix.levels.resize"):
        LevelFile(robot.level, size=SIZES["s"])


def test_inactive_slots_in_the_middle_are_compacted_on_save(robot):
    sim = scene.remove_body(robot.level.sim, NUM_WALLS + 1)  # the box, and its limited joint with it
    level = make_level(sim, robot.level.roles, robot.level.motor_bindings, robot.level.motor_auto,
                       robot.level.thruster_bindings)
    data = ours.write(LevelFile(level, robot.params, robot.size))
    assert len(data["bodies"]) == int(np.sum(sim.bodies.active))
    assert [j["b"] for j in data["joints"]] == [NUM_WALLS + 1, NUM_WALLS + 2]  # the circles moved up one
    loaded = load_level(data)
    np.testing.assert_array_equal(joint_world_points(loaded.level), joint_world_points(level))


# ---------------------------------------------------------------- our format in detail


def minimal_document():
    return {
        "format_version": 1,
        "bodies": [
            {"shape": "polygon", "position": [0.0, 0.0], "vertices": [[-2, -0.5], [2, -0.5], [2, 0.5], [-2, 0.5]],
             "fixed": True},
            {"shape": "circle", "position": [0.0, 1.0], "radius": 0.25},
            {"shape": "polygon", "position": [1.0, 1.0], "vertices": [[0, 0], [1, 0], [0, 1]], "angle": 0.5},
        ],
        "joints": [{"a": 1, "b": 2, "anchor": [0.5, 1.0], "motor": {"speed": -2}}],
        "thrusters": [{"body": 2, "anchor": [0, 0]}],
    }


def test_missing_optional_fields_get_the_documented_defaults():
    file = load_level(minimal_document())
    assert file.params == LevelParams() and file.size == SIZES["s"] and file.name == ""
    b, j, t = file.level.sim.bodies, file.level.sim.joints, file.level.sim.thrusters
    np.testing.assert_array_equal(file.level.sim.gravity, np.float32([0.0, -9.81]))
    for i in (0, 1, SIZES["s"].polygons):
        assert float(b.density[i]) == 1 and float(b.friction[i]) == 1 and float(b.restitution[i]) == 0
        assert int(b.collision_mode[i]) == 1 and int(file.level.roles[i]) == 0
    assert bool(j.motor_on[0]) and float(j.motor_speed[0]) == -2 and float(j.motor_power[0]) == 1
    assert not bool(j.limit_on[0]) and not bool(j.fixed[0]) and int(file.level.motor_bindings[0]) == 0
    assert float(t.power[0]) == 1 and float(t.angle[0]) == 0 and int(file.level.thruster_bindings[0]) == 0
    written = ours.write(file)
    assert written["bodies"][1]["friction"] == 1.0 and written["thrusters"][0]["binding"] == 0
    assert written["joints"][0]["motor"] == {"on": True, "speed": -2.0, "power": 1.0, "binding": 0, "auto": False}


def test_off_centre_polygons_are_recentred_and_their_anchors_follow():
    data = minimal_document()
    file = load_level(data)
    P = SIZES["s"].polygons
    b = file.level.sim.bodies
    # Triangle (0,0),(1,0),(0,1) at (1, 1) turned by 0.5: the centroid (1/3, 1/3) becomes the position.
    np.testing.assert_allclose(b.position[1], np.array([1.0, 1.0]) + rotate(0.5, [1 / 3, 1 / 3]), atol=1e-6)
    np.testing.assert_allclose(np.mean(b.vertices[1, :3], axis=0), [0, 0], atol=1e-7)
    assert float(b.inv_mass[1]) == pytest.approx(2.0, rel=1e-6)  # area 1/2, density 1
    # The joint anchor was given as the world point (0.5, 1.0) and both ends still meet there.
    np.testing.assert_allclose(joint_world_points(file.level)[0], [[0.5, 1.0], [0.5, 1.0]], atol=1e-6)
    # The thruster anchor (the old body origin) is now relative to the centroid.
    np.testing.assert_allclose(file.level.sim.thrusters.anchor[0], [-1 / 3, -1 / 3], atol=1e-6)
    assert int(file.level.sim.joints.a[0]) == P and int(file.level.sim.joints.b[0]) == 1  # circle, triangle
    # Saving writes the recentred form, which then loads without moving (bitwise).
    text = dumps(file)
    assert_bitwise_equal(load_level(json.loads(text)).level, file.level)


def test_joint_between_two_fixed_bodies_loads_with_a_warning():
    data = minimal_document()
    data["bodies"][1]["fixed"] = True
    data["joints"][0]["b"] = 0
    file = load_level(data)
    assert file.warnings == ("joints[0]: both bodies are fixed, so the joint does nothing",)
    assert resize(file, "m").warnings == file.warnings


def test_unknown_fields_are_errors_with_suggestions():
    data = minimal_document()
    data["bodies"][1]["restitusion"] = 0.5
    data["bodies"][1]["colour"] = "red"
    with pytest.raises(LevelError, match=r"bodies\[1\]: unknown fields colour, restitusion \(did you mean "
                                         r"restitution\?\)"):
        load_level(data)
    data = minimal_document()
    data["comment"] = "hi"
    with pytest.raises(LevelError, match="^file: unknown field comment"):
        load_level(data)
    data = minimal_document()
    data["bodies"][1]["vertices"] = [[0, 0], [1, 0], [0, 1]]  # a circle has no vertices
    with pytest.raises(LevelError, match=r"bodies\[1\]: unknown field vertices"):
        load_level(data)


def test_save_writes_atomically_and_reloads(tmp_path, robot):
    path = tmp_path / "robot.json"
    save_level(robot, path)
    assert_bitwise_equal(load_level(path).level, robot.level)
    save_level(robot, tmp_path / "robot.kinetix.json", format="kinetix", size="l")
    assert load_level(tmp_path / "robot.kinetix.json").format == "kinetix"
    before = path.read_text()
    with pytest.raises(LevelError):
        save_level(robot, path, size="s")  # does not fit: nothing is written
    with pytest.raises(LevelError, match="unknown format"):
        save_level(robot, path, format="yaml")
    assert path.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.json", "robot.kinetix.json"]


# ---------------------------------------------------------------- malformed input


def _set(data, path, value):
    *head, last = path
    for key in head:
        data = data[key]
    if value is DELETE:
        del data[last]
    else:
        data[last] = value


DELETE = object()

OURS_CASES = [
    (("format_version",), 2, "format_version: this program reads version 1, got 2"),
    (("format_version",), DELETE, "not a level file: expected format_version .* found keys"),
    (("bodies",), DELETE, "missing required field bodies"),
    (("bodies",), {"0": 1}, "bodies: expected a list, got object"),
    (("bodies", 1), "ball", r"bodies\[1\]: expected an object, got string"),
    (("bodies", 1, "position"), DELETE, r"bodies\[1\]: missing required field position"),
    (("bodies", 1, "radius"), DELETE, r"bodies\[1\]: missing required field radius"),
    (("bodies", 1, "radius"), "big", r"bodies\[1\].radius: expected a number, got 'big'"),
    (("bodies", 1, "radius"), -1, r"bodies\[1\].radius: -1 is out of range \[0.001, 50\]"),
    (("bodies", 1, "radius"), float("nan"), r"bodies\[1\].radius: must be finite, got nan"),
    (("bodies", 1, "position"), [0, float("inf")], r"bodies\[1\].position\[1\]: must be finite"),
    (("bodies", 1, "position"), [1, 2, 3], r"bodies\[1\].position: expected \[x, y\]"),
    (("bodies", 1, "position"), [1e9, 0], r"bodies\[1\].position\[0\]: 1e\+09 is out of range \[-100, 100\]"),
    (("bodies", 1, "fixed"), "yes", r"bodies\[1\].fixed: expected true or false"),
    (("bodies", 1, "shape"), "star", r"bodies\[1\].shape: expected polygon or circle"),
    (("bodies", 1, "role"), "purple", r"bodies\[1\].role: expected one of none, green, blue, red"),
    (("bodies", 1, "collision_mode"), 3, r"bodies\[1\].collision_mode: 3 is out of range"),
    (("bodies", 1, "restitution"), 1.5, r"bodies\[1\].restitution: 1.5 is out of range \[0, 1\]"),
    (("bodies", 1, "density"), 0, r"bodies\[1\].density: 0 is out of range \[0.001, 1000\]"),
    (("bodies", 2, "vertices"), [[0, 0], [1, 0], [0.2, 0.2], [0, 1]],
     r"bodies\[2\].vertices: polygon is not convex: vertex 2"),
    (("bodies", 2, "vertices"), [[0, 0], [0, 1], [1, 0]], r"bodies\[2\].vertices: .*counter-clockwise"),
    (("bodies", 2, "vertices"), [[0, 0], [1, 0]], r"bodies\[2\].vertices: a polygon needs 3 to 8 vertices"),
    (("bodies", 2, "vertices"), [[0, 0], [1, 0], [2, 0]], r"bodies\[2\].vertices: polygon has \(near\) zero area"),
    (("bodies", 2, "vertices"), [[0, 0], [1, 0], "x"], r"bodies\[2\].vertices\[2\]: expected \[x, y\]"),
    (("bodies", 2, "vertices"), [[0, 0], [1, 0], [0, 1e-300]], r"bodies\[2\].vertices"),
    (("bodies", 1, "velocity"), [1, 0], None),  # fine on a dynamic body
    (("bodies", 0, "velocity"), [1, 0], r"bodies\[0\]: a fixed body never moves"),
    (("joints", 0, "a"), 7, r"joints\[0\].a: 7 is out of range \[0, 2\]"),
    (("joints", 0, "a"), 2, r"joints\[0\]: a joint needs two different bodies"),
    (("joints", 0, "a"), 1.5, r"joints\[0\].a: expected an integer, got 1.5"),
    (("joints", 0, "a"), True, r"joints\[0\].a: expected an integer, got True"),
    (("joints", 0, "anchor"), DELETE, r"joints\[0\]: missing required fields anchor_a, anchor_b"),
    (("joints", 0, "anchor_a"), [0, 0], r"joints\[0\]: give either anchor \(world\) or anchor_a and anchor_b"),
    (("joints", 0, "type"), "prismatic", r"joints\[0\].type: expected revolute or fixed"),
    (("joints", 0, "limits"), [1, -1], r"joints\[0\].limits: lower 1.0 is above upper -1.0"),
    (("joints", 0, "motor"), {"binding": 4}, r"joints\[0\].motor.binding: 4 is out of range \[0, 3\]"),
    (("joints", 0, "motor"), {"speed": None}, r"joints\[0\].motor.speed: expected a number, got None"),
    (("joints", 0, "motor"), {"sped": 1}, r"joints\[0\].motor: unknown field sped \(did you mean speed\?\)"),
    (("joints", 0, "type"), "fixed", r"joints\[0\]: unknown field motor"),
    (("thrusters", 0, "body"), -1, r"thrusters\[0\].body: -1 is out of range"),
    (("thrusters", 0, "binding"), 2, r"thrusters\[0\].binding: 2 is out of range \[0, 1\]"),
    (("thrusters", 0, "power"), -0.5, r"thrusters\[0\].power: -0.5 is out of range \[0, 100\]"),
    (("size",), "xxl", "size: expected one of s, m, l, xl"),
    (("size",), {"polygons": 2}, "size: missing required fields circles, joints, thrusters"),
    (("size",), {"polygons": -2, "circles": 1, "joints": 1, "thrusters": 1}, r"size.polygons: -2 is out of range"),
    (("env",), {"frame_skip": 0}, r"env.frame_skip: 0 is out of range \[1, 16\]"),
    (("env",), {"physics": {"dt": 0}}, r"env.physics.dt: 0 is out of range \[0.001, 0.1\]"),
    (("env",), {"physics": {"gravity": 1}}, r"env.physics: unknown field gravity"),
    (("gravity",), "down", r"gravity: expected a list, got string"),
    (("name",), 5, r"name: expected a string, got number"),
]


@pytest.mark.parametrize("path, value, message", OURS_CASES, ids=[".".join(map(str, c[0])) for c in OURS_CASES])
def test_malformed_our_format_gives_a_level_error_naming_the_field(path, value, message):
    data = minimal_document()
    _set(data, path, value)
    if message is None:
        load_level(data)
        return
    with pytest.raises(LevelError, match=message):
        load_level(data)


KINETIX_CASES = [
    (("env_state",), DELETE, "not a level file: expected format_version .* or env_state"),
    (("env_state", "polygon"), DELETE, "env_state: missing required field polygon"),
    (("env_state", "polygon"), 5, "env_state.polygon: expected a list, got number"),
    (("env_state", "polygon", 4, "active"), DELETE, r"env_state.polygon\[4\]: missing required field active"),
    (("env_state", "polygon", 4, "inverse_mass"), DELETE, r"env_state.polygon\[4\]: missing required field "
                                                          "inverse_mass"),
    (("env_state", "polygon", 4, "n_vertices"), 9, r"env_state.polygon\[4\].n_vertices: 9 is out of range"),
    (("env_state", "polygon", 4, "vertices", "1"), {"0": -0.1, "1": 0.1},
     r"env_state.polygon\[4\].vertices: polygon is not convex"),
    (("env_state", "polygon", 4, "vertices", "2"), {"0": "a", "1": 0.0},
     r"env_state.polygon\[4\].vertices\[2\]\[0\]: expected a number"),
    (("env_state", "polygon", 4, "position"), {"0": float("nan"), "1": 0.0},
     r"env_state.polygon\[4\].position\[0\]: must be finite"),
    (("env_state", "polygon", 4, "role"), 4, r"env_state.polygon\[4\].role: 4 is out of range"),
    (("env_state", "circle", 0, "radius"), 0.0, r"env_state.circle\[0\].radius: 0 is out of range \[0.001, 50\]"),
    (("env_state", "joint", 0, "a_index"), 99, r"env_state.joint\[0\].a_index: 99 is not a body \(the file has 7 "),
    (("env_state", "joint", 0, "b_relative_pos"), DELETE, r"env_state.joint\[0\]: missing required field "
                                                          "b_relative_pos"),
    (("env_state", "joint", 0, "motor_binding"), 7, r"env_state.joint\[0\].motor_binding: 7 is out of range"),
    (("env_state", "thruster", 0, "object_index"), "five", r"env_state.thruster\[0\].object_index: expected an "
                                                             "integer"),
    (("env_params", "dt"), -1, r"env_params.dt: -1 is out of range \[0.001, 0.1\]"),
    (("static_env_params", "frame_skip"), 0.5, "static_env_params.frame_skip: expected an integer"),
]


@pytest.mark.parametrize("path, value, message", KINETIX_CASES, ids=[".".join(map(str, c[0])) for c in KINETIX_CASES])
def test_malformed_kinetix_files_give_a_level_error_naming_the_field(shared_dir, path, value, message):
    data = json.loads((shared_dir / "kinetix-levels" / "s" / "h3_point_the_thruster.json").read_text())
    _set(data, path, value)
    with pytest.raises(LevelError, match=message):
        load_level(data)


def test_joint_on_an_inactive_body_is_dropped_with_a_warning(shared_dir):
    data = json.loads((shared_dir / "kinetix-levels" / "s" / "h3_point_the_thruster.json").read_text())
    data["env_state"]["circle"][0]["active"] = False
    file = load_level(data)
    assert not bool(np.any(file.level.sim.joints.active))
    assert any("joint[0]: dropped" in w for w in file.warnings), file.warnings


@pytest.mark.parametrize("content, message", [
    (b"", "is not valid JSON"),
    (b"{\"format_version\": 1,", "is not valid JSON"),
    (b"\xff\xfe\x00garbage", "cannot read"),
    (b"[1, 2, 3]", "not a level file"),
    (b"{\"hello\": 1}", r"not a level file: expected format_version .* found keys \['hello'\]"),
    (b"[" * 100000 + b"]" * 100000, "nested too deeply|not valid JSON"),
])
def test_files_that_are_not_levels(tmp_path, content, message):
    path = tmp_path / "level.json"
    path.write_bytes(content)
    with pytest.raises(LevelError, match=message):
        load_level(path)
    with pytest.raises(LevelError, match="cannot read"):
        load_level(tmp_path / "missing.json")


def _mutations(document, prefix=()):
    """Every (path, replacement) for the leaves and objects of a document (DELETE removes the entry)."""
    replacements = [DELETE, None, "x", [], {}, -1, 2.5, True, float("nan"), [1.0, 2.0], 1e7]
    items = document.items() if isinstance(document, dict) else enumerate(document)
    for key, value in items:
        path = (*prefix, key)
        for replacement in replacements:
            yield path, replacement
        if isinstance(value, (dict, list)) and len(path) < 4:
            yield from _mutations(value, path)


def test_no_mutation_of_a_valid_file_escapes_as_anything_but_level_error():
    base = minimal_document()
    base["joints"].append({"type": "fixed", "a": 0, "b": 1, "anchor_a": [0, 1], "anchor_b": [0, 0]})
    base["env"] = {"max_timesteps": 10, "physics": {"dt": 0.01}}
    base["size"] = {"polygons": 3, "circles": 1, "joints": 2, "thrusters": 1}
    outcomes = {"loaded": 0, "rejected": 0}
    for path, replacement in _mutations(base):
        data = copy.deepcopy(base)
        try:
            _set(data, path, replacement)
        except (KeyError, IndexError, TypeError):
            continue
        try:
            load_level(data)
            outcomes["loaded"] += 1
        except LevelError as error:
            # A reader that foresaw the problem names it; the catch-all "invalid level (...)" means it did not.
            assert str(error) and not str(error).startswith("invalid level ("), (path, replacement, str(error))
            outcomes["rejected"] += 1
    assert outcomes["loaded"] > 20 and outcomes["rejected"] > 200, outcomes


# ---------------------------------------------------------------- bindings


def test_expand_actions_follows_bindings_auto_and_activity(robot):
    level = robot.level
    motor_values = jnp.array([0.1, -0.2, 0.3, -0.4])
    thruster_values = jnp.array([0.25, 0.75])
    motor, thrust = jax2d.jit(expand_actions)(level, motor_values, thruster_values)
    bindings, auto = np.asarray(level.motor_bindings), np.asarray(level.motor_auto)
    active = np.asarray(level.sim.joints.active)
    expected = np.where(active, np.where(auto, 1.0, np.asarray(motor_values)[bindings]), 0.0)
    np.testing.assert_array_equal(motor, expected.astype(np.float32))
    assert motor.shape == (robot.size.joints,) and thrust.shape == (robot.size.thrusters,)
    assert float(motor[0]) == np.float32(0.3) and float(motor[1]) == 1.0  # binding 2; auto
    assert float(thrust[0]) == 0.75 and float(thrust[1]) == 0.0  # binding 1; inactive slot
    # Batched: each level with its own values.
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), level)
    values = jnp.stack([motor_values, -motor_values])
    m, t = jax.vmap(expand_actions)(batch, values, jnp.stack([thruster_values, thruster_values[::-1]]))
    assert float(m[1, 0]) == np.float32(-0.3) and float(m[1, 1]) == 1.0 and float(t[1, 0]) == 0.25


# ---------------------------------------------------------------- physics on every shared level


@pytest.mark.slow
def test_every_shared_level_runs_a_thousand_random_steps_finite(shared_dir):
    from kinetix.validate import simulate, stack

    files = {size: [] for size in SIZE_DIRS}
    for path in shared_files(shared_dir):
        files[path.parent.name].append(load_level(path))
    for size, group in files.items():
        levels = stack([f.level for f in group])
        params = stack([f.params.sim_params() for f in group])
        keys = jnp.stack([jax.random.key(i) for i in range(len(group))])
        final, finite = simulate(levels, params, keys, 1000)
        broken = [f.name for f, ok in zip(group, np.asarray(finite), strict=True) if not ok]
        assert not broken, f"size {size}: the state became non-finite in {broken}"
        # No moving body leaves the walled world (x in [0, 5], y in [0.4, 5]) by more than a body size.
        x, y = np.asarray(final.bodies.position[..., 0]), np.asarray(final.bodies.position[..., 1])
        inside = (x > -1) & (x < 6) & (y > -0.6) & (y < 6)
        moving = np.asarray(final.bodies.active & (final.bodies.inv_mass > 0))
        escaped = [group[i].name for i in np.nonzero(np.any(moving & ~inside, axis=1))[0]]
        assert not escaped, f"size {size}: bodies left the world in {escaped}"
