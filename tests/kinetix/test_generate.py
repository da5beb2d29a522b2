"""The random level generator, the mutators and the no-op triviality filter.

Invariants are checked here in numpy, independently of kinetix.generate.is_valid: geometry against
jax2d.geometry, joints by recomputing anchor positions, overlap from the engine's own contact points.
"""

import dataclasses
import functools
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from jax2d.geometry import circle_mass_properties, polygon_mass_properties, validate_polygon
from kinetix.bindings import expand_actions
from kinetix.generate import (
    DEFAULT_PARAMS,
    GeneratorParams,
    is_trivial,
    is_valid,
    sample_level,
    sample_nontrivial_level,
)
from kinetix.geometry import polygon_mass_properties as jnp_polygon_mass_properties
from kinetix.level import (
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    NUM_WALLS,
    ROLE_BLUE,
    ROLE_GREEN,
    ROLE_NONE,
    ROLE_RED,
    SIZES,
    LevelParams,
    empty_level,
    make_level,
)
from kinetix.levels import load_level, save_level
from kinetix.mutate import (
    MUTATORS,
    mutate,
    mutate_add_shape,
    mutate_add_thruster,
    mutate_move,
    mutate_remove_shape,
    mutate_resize,
    mutate_rotate,
    mutate_swap_roles,
    mutate_toggle_fixed,
)

SIZE_NAMES = ("s", "m", "l")
COUNT = 200  # generated levels checked per size
SIM_PARAMS = LevelParams().sim_params()
X_MIN, X_MAX, Y_MIN, Y_MAX = 0.0, 5.0, 0.4, 5.0
OVERLAP_TOLERANCE = DEFAULT_PARAMS.overlap_tolerance


def unstack(levels, i):
    return jax.tree.map(lambda x: np.asarray(x[i]), levels)


def rotate(angle, v):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def joint_groups(level):
    """Union-find over active joints: the bodies linked by chains of joints share a label."""
    n = level.roles.shape[0]
    label = list(range(n))

    def find(x):
        while label[x] != x:
            x = label[x]
        return x

    j = level.sim.joints
    for s in np.nonzero(j.active)[0]:
        ra, rb = find(int(j.a[s])), find(int(j.b[s]))
        label[max(ra, rb)] = min(ra, rb)
    return np.array([find(i) for i in range(n)])


def world_points(level, k):
    """World positions of body k's polygon vertices, or of its circle's four extreme points."""
    b = level.sim.bodies
    P = b.vertices.shape[0]
    if k < P:
        local = b.vertices[k, : int(b.n_vertices[k])].astype(np.float64)
    else:
        r = float(b.radius[k - P])
        local = r * np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    return b.position[k] + np.array([rotate(float(b.angle[k]), p) for p in local])


@functools.cache
def standard_walls(name):
    return jax.tree.map(np.asarray, empty_level(name).sim.bodies)


def problems(level) -> list[str]:
    """Every broken invariant of one (numpy) level; empty when it is valid."""
    out = []
    b, j, t = level.sim.bodies, level.sim.joints, level.sim.thrusters
    P, N = b.vertices.shape[0], b.active.shape[0]
    active, roles = b.active, level.roles
    fixed = b.inv_mass == 0
    groups = joint_groups(level)

    walls = standard_walls(size_name(level))
    for field in ("position", "angle", "inv_mass", "vertices", "n_vertices", "active", "collision_mode"):
        if not np.array_equal(getattr(b, field)[:NUM_WALLS], getattr(walls, field)[:NUM_WALLS]):
            out.append(f"wall field {field} changed")
    if roles.min() < ROLE_NONE or roles.max() > ROLE_RED:
        out.append(f"roles out of range: {roles}")
    green = np.nonzero(active & (roles == ROLE_GREEN))[0]
    blue = np.nonzero(active & (roles == ROLE_BLUE))[0]
    if len(green) == 0 or len(blue) == 0:
        out.append(f"green bodies {green.tolist()}, blue bodies {blue.tolist()}")
    if not any(not (fixed[g] and fixed[c]) and groups[g] != groups[c] for g in green for c in blue):
        out.append("no green-blue pair that is not both fixed and not jointed together")

    for k in np.nonzero(active)[0]:
        if k < NUM_WALLS:
            continue
        if k < P:
            n = int(b.n_vertices[k])
            vertices = b.vertices[k, :n].astype(np.float64)
            try:
                validate_polygon(vertices)  # convex, counter-clockwise, positive area
            except ValueError as error:
                out.append(f"body {k}: {error}")
                continue
            mass, inertia, centroid = polygon_mass_properties(vertices, float(b.density[k]))
            if np.linalg.norm(centroid) > 1e-5 * np.ptp(vertices, axis=0).max():
                out.append(f"body {k}: vertices not centred on the centroid ({centroid})")
        else:
            mass, inertia, _ = circle_mass_properties(float(b.radius[k - P]), float(b.density[k]))
        if fixed[k]:
            if b.inv_inertia[k] != 0:
                out.append(f"body {k}: fixed but inverse inertia {b.inv_inertia[k]}")
        else:
            if not (b.inv_mass[k] > 0 and b.inv_inertia[k] > 0):
                out.append(f"body {k}: dynamic with inverse mass {b.inv_mass[k]}, inertia {b.inv_inertia[k]}")
            elif abs(1 / b.inv_mass[k] - mass) > 1e-4 * mass or abs(1 / b.inv_inertia[k] - inertia) > 1e-4 * inertia:
                out.append(f"body {k}: mass {1 / b.inv_mass[k]}, inertia {1 / b.inv_inertia[k]}; "
                           f"expected {mass}, {inertia}")
        points = world_points(level, k)
        if points[:, 0].min() < X_MIN - 1e-4 or points[:, 0].max() > X_MAX + 1e-4 \
                or points[:, 1].min() < Y_MIN - 1e-4 or points[:, 1].max() > Y_MAX + 1e-4:
            out.append(f"body {k} leaves the world: {points.min(0)} .. {points.max(0)}")

    controllable = False
    for s in np.nonzero(j.active)[0]:
        a, c = int(j.a[s]), int(j.b[s])
        if not (0 <= a < N and 0 <= c < N) or a == c or not (active[a] and active[c]):
            out.append(f"joint {s} links bodies {a} and {c}")
            continue
        if fixed[a] and fixed[c]:
            out.append(f"joint {s} links two fixed bodies")
        world_a = b.position[a] + rotate(float(b.angle[a]), j.anchor_a[s])
        world_b = b.position[c] + rotate(float(b.angle[c]), j.anchor_b[s])
        if np.linalg.norm(world_a - world_b) > 1e-4:
            out.append(f"joint {s} is open: anchors at {world_a} and {world_b}")
        relative = float(b.angle[c]) - float(b.angle[a]) - float(j.ref_angle[s])
        if abs(math.remainder(relative, 2 * math.pi)) > 1e-4:
            out.append(f"joint {s}: ref_angle is off by {relative}")
        if j.fixed[s] and (j.motor_on[s] or j.limit_on[s]):
            out.append(f"joint {s}: a weld with a motor or limits")
        if j.limit_on[s] and not j.lower[s] <= 0 <= j.upper[s]:
            out.append(f"joint {s}: limits [{j.lower[s]}, {j.upper[s]}] exclude the initial angle")
        if j.motor_on[s] and not j.fixed[s]:
            if not (0 < j.motor_speed[s] <= 3.0 + 1e-6 and 0 < j.motor_power[s] <= 2.0 + 1e-6):
                out.append(f"joint {s}: motor speed {j.motor_speed[s]}, power {j.motor_power[s]}")
            controllable |= not (fixed[a] and fixed[c])
    for s in np.nonzero(t.active)[0]:
        k = int(t.body[s])
        if not (0 <= k < N and active[k]):
            out.append(f"thruster {s} on body {k}")
            continue
        if not 0 < t.power[s] <= DEFAULT_PARAMS.max_thruster_power + 1e-6:
            out.append(f"thruster {s}: power {t.power[s]}")
        controllable |= not fixed[k]
    if not controllable:
        out.append("no motor or thruster acts on a dynamic body")

    if level.motor_bindings.size and not (0 <= level.motor_bindings.min() and
                                          level.motor_bindings.max() < NUM_MOTOR_BINDINGS):
        out.append(f"motor bindings {level.motor_bindings}")
    if level.thruster_bindings.size and not (0 <= level.thruster_bindings.min() and
                                             level.thruster_bindings.max() < NUM_THRUSTER_BINDINGS):
        out.append(f"thruster bindings {level.thruster_bindings}")
    if np.any(level.motor_auto):
        out.append("motor_auto set")
    return out


def size_name(level) -> str:
    b, j = level.sim.bodies, level.sim.joints
    for name, size in SIZES.items():
        if (size.polygons, size.circles, size.joints) == (b.vertices.shape[0], b.radius.shape[0], j.a.shape[0]):
            return name
    raise AssertionError("not a standard size")


def assert_all_valid(levels, count, what):
    failures = {i: p for i in range(count) if (p := problems(unstack(levels, i)))}
    assert not failures, f"{len(failures)} of {count} {what} break invariants, e.g. {list(failures.items())[:3]}"


# ---------------------------------------------------------------- compiled functions, built once


@pytest.fixture(scope="module")
def batches():
    """COUNT generated levels per size, from one compiled vmapped sampler per size."""
    keys = jax.random.split(jax.random.key(2024), COUNT)
    return {name: jax2d.jit(jax.vmap(lambda k, name=name: sample_level(k, name)))(keys) for name in SIZE_NAMES}


@pytest.fixture(scope="module")
def trivial_flags(batches):
    """Per size, which generated levels the no-op policy solves (one compiled vmapped rollout per size)."""
    check = jax2d.jit(jax.vmap(lambda level: is_trivial(level, SIM_PARAMS)))
    return {name: np.asarray(check(levels)) for name, levels in batches.items()}


# ---------------------------------------------------------------- generator


def test_same_key_same_level_wherever_it_is_in_the_batch(batches):
    """A level depends on its key only: the same keys in another order give the same levels, bitwise."""
    keys = jax.random.split(jax.random.key(2024), COUNT)
    order = np.roll(np.arange(COUNT), 7)
    again = jax2d.jit(jax.vmap(lambda k: sample_level(k, "m")))(keys[order])  # same program as the fixture's
    for x, y in zip(jax.tree.leaves(batches["m"]), jax.tree.leaves(again), strict=True):
        assert np.asarray(x)[order].tobytes() == np.asarray(y).tobytes()
    # Different keys give different levels.
    positions = np.asarray(batches["m"].sim.bodies.position).reshape(COUNT, -1)
    assert len({row.tobytes() for row in positions}) == COUNT


@pytest.mark.parametrize("name", SIZE_NAMES)
def test_generated_levels_keep_the_invariants(batches, name):
    levels = batches[name]
    assert_all_valid(levels, COUNT, f"generated {name} levels")
    assert np.all(np.asarray(jax.vmap(is_valid)(levels)))
    # The generator makes exactly one green and one blue body.
    roles = np.where(np.asarray(levels.sim.bodies.active), np.asarray(levels.roles), -1)
    assert np.all(np.sum(roles == ROLE_GREEN, axis=1) == 1) and np.all(np.sum(roles == ROLE_BLUE, axis=1) == 1)


@pytest.mark.parametrize("name", SIZE_NAMES)
def test_generated_levels_are_varied(batches, name):
    """Free and jointed shapes, triangles, rectangles, other polygons and circles, revolute and fixed joints."""
    levels = batches[name]
    b, j, t = levels.sim.bodies, levels.sim.joints, levels.sim.thrusters
    size = SIZES[name]
    free_slots = size.polygons - NUM_WALLS + size.circles
    counts = np.asarray(b.active).sum(axis=1) - NUM_WALLS
    assert counts.min() >= 2 and counts.max() == free_slots
    n = np.where(np.asarray(b.active)[:, : size.polygons], np.asarray(b.n_vertices), 0)[:, NUM_WALLS:]
    assert np.any(n == 3) and np.any(n == 4)
    if size.polygons - NUM_WALLS >= 2:
        assert np.any(n > 4)
    assert np.asarray(b.active)[:, size.polygons:].any()
    joints = np.asarray(j.active)
    if size.joints >= 2:
        assert np.any(joints & np.asarray(j.fixed)) and np.any(joints & ~np.asarray(j.fixed) & np.asarray(j.limit_on))
    assert np.any(joints & np.asarray(j.motor_on))
    assert np.any(np.asarray(t.active))
    fixed = np.asarray(b.active)[:, NUM_WALLS:] & (np.asarray(b.inv_mass)[:, NUM_WALLS:] == 0)
    assert 0.05 < fixed.any(axis=1).mean() < 0.95
    assert np.any(np.asarray(levels.roles)[:, NUM_WALLS:] == ROLE_RED)
    assert 0 < np.mean(np.asarray(levels.roles)[:, 0] == ROLE_RED) < 0.3  # the floor is sometimes red


def test_motor_and_thruster_strengths_are_sensible(batches):
    for levels in batches.values():
        j = levels.sim.joints
        motors = np.asarray(j.active & j.motor_on)
        speed, power = np.asarray(j.motor_speed)[motors], np.asarray(j.motor_power)[motors]
        assert speed.min() >= 0.5 - 1e-6 and speed.max() <= 3.0 + 1e-6
        assert power.min() >= 0.5 - 1e-6 and power.max() <= 2.0 + 1e-6
        # Wheels (a circle pinned at its centre) are capped lower.
        P = levels.sim.bodies.vertices.shape[1]
        wheels = motors & (np.asarray(j.b) >= P) & (np.linalg.norm(np.asarray(j.anchor_b), axis=-1) < 1e-6)
        assert np.any(wheels) and np.asarray(j.motor_power)[wheels].max() <= DEFAULT_PARAMS.wheel_max_power + 1e-6
        # A thruster's force at full action is 1-3x the weight of the dynamic bodies of its assembly
        # (unless capped at max_thruster_power).
        for i in range(20):
            level = unstack(levels, i)
            groups = joint_groups(level)
            b = level.sim.bodies
            for s in np.nonzero(level.sim.thrusters.active)[0]:
                body = int(level.sim.thrusters.body[s])
                members = (groups == groups[body]) & b.active & (b.inv_mass > 0)
                weight = 9.81 * np.sum(1 / b.inv_mass[members])
                force = level.sim.thrusters.power[s] * SIM_PARAMS.base_thruster_power
                if level.sim.thrusters.power[s] < DEFAULT_PARAMS.max_thruster_power - 1e-4:
                    assert 1.0 - 1e-3 <= force / weight <= 3.0 + 1e-3


def test_jnp_polygon_mass_matches_jax2d_geometry():
    rng = np.random.default_rng(0)
    for n in range(3, 9):
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        vertices = np.stack([np.cos(angles) * 0.7 + 0.3, np.sin(angles) * 0.4 - 0.2], axis=1)
        padded = np.concatenate([vertices, np.repeat(vertices[-1:], 8 - n, axis=0)])
        mass, inertia, centroid = jnp_polygon_mass_properties(jnp.asarray(padded, jnp.float32), n, 1.7)
        expected = polygon_mass_properties(vertices, 1.7)
        np.testing.assert_allclose([mass, inertia], expected[:2], rtol=1e-4)
        np.testing.assert_allclose(centroid, expected[2], atol=1e-5)


def test_generated_levels_simulate_sanely(batches):
    """64 levels per size, 300 physics steps of random actions: no NaN, every body stays inside the walls.

    Also: shapes start (almost) without overlap. The first step reports the separation, at its start, of
    the contact points of every pair that may collide (the engine's own narrow phase, not the generator's).
    """

    def rollout(level, key):
        def one(carry, k):
            sim, finite, low, high = carry
            k_motor, k_thrust = jax.random.split(k)
            motor, thrust = expand_actions(level, jax.random.uniform(k_motor, (4,), minval=-1.0, maxval=1.0),
                                           jax.random.uniform(k_thrust, (2,)))
            sim = jax2d.step(sim, SIM_PARAMS, motor, thrust)
            floats = [x for x in jax.tree.leaves(sim) if jnp.issubdtype(x.dtype, jnp.floating)]
            finite = finite & jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in floats]))
            moving = (sim.bodies.active & (jnp.arange(sim.num_bodies) >= NUM_WALLS))[:, None]
            low = jnp.minimum(low, jnp.min(jnp.where(moving, sim.bodies.position, np.inf), axis=0))
            high = jnp.maximum(high, jnp.max(jnp.where(moving, sim.bodies.position, -np.inf), axis=0))
            separation = jnp.min(jnp.where(sim.contacts.active, sim.contacts.separation, np.inf))
            return (sim, finite, low, high), separation

        start = (level.sim, jnp.asarray(True), jnp.full(2, np.inf), jnp.full(2, -np.inf))
        (_, finite, low, high), separation = jax.lax.scan(one, start, jax.random.split(key, 300))
        return finite, low, high, separation[0]

    run = jax2d.jit(jax.vmap(rollout))
    keys = jax.random.split(jax.random.key(9), 64)
    for name, levels in batches.items():
        first = jax.tree.map(lambda x: x[:64], levels)
        finite, low, high, separation = (np.asarray(x) for x in run(first, keys))
        assert finite.all(), f"{name}: NaN or inf in levels {np.nonzero(~finite)[0]}"
        # Body centres stay in the box (a centre outside would mean it went through a wall).
        assert low.min(axis=0).tolist() > [X_MIN, Y_MIN] and high.max(axis=0).tolist() < [X_MAX, Y_MAX], name
        assert separation.min() >= -OVERLAP_TOLERANCE - 1e-3, f"{name}: initial overlap {-separation.min()} m"


def test_generated_levels_round_trip_through_our_format(batches, tmp_path):
    for name, levels in batches.items():
        for i in range(10):
            level = unstack(levels, i)
            path = tmp_path / f"{name}{i}.json"
            save_level(jax.tree.map(jnp.asarray, level), path)
            loaded = load_level(path)
            assert loaded.size == SIZES[name]
            # Generated levels use the first free slots, so slots match one to one.
            for struct in ("bodies", "joints", "thrusters"):
                ours, theirs = getattr(level.sim, struct), getattr(loaded.level.sim, struct)
                active = np.asarray(ours.active)
                np.testing.assert_array_equal(active, np.asarray(theirs.active))
                for field in dataclasses.fields(ours):
                    x, y = np.asarray(getattr(ours, field.name)), np.asarray(getattr(theirs, field.name))
                    if struct == "bodies" and field.name in ("vertices", "n_vertices", "radius"):
                        continue  # per-kind arrays, compared below
                    if field.name == "impulse":
                        continue
                    if np.issubdtype(x.dtype, np.floating):
                        np.testing.assert_allclose(x[active], y[active], rtol=1e-5, err_msg=f"{struct}.{field.name}")
                    else:
                        np.testing.assert_array_equal(x[active], y[active], err_msg=f"{struct}.{field.name}")
            b, lb = level.sim.bodies, loaded.level.sim.bodies
            P = b.vertices.shape[0]
            polygons, circles = np.asarray(b.active)[:P], np.asarray(b.active)[P:]
            np.testing.assert_array_equal(b.vertices[polygons], np.asarray(lb.vertices)[polygons])
            np.testing.assert_array_equal(b.n_vertices[polygons], np.asarray(lb.n_vertices)[polygons])
            np.testing.assert_array_equal(b.radius[circles], np.asarray(lb.radius)[circles])
            np.testing.assert_array_equal(level.roles, np.asarray(loaded.level.roles))
            for field, mask in (("motor_bindings", level.sim.joints.active),
                                ("thruster_bindings", level.sim.thrusters.active)):
                theirs = np.asarray(getattr(loaded.level, field))
                np.testing.assert_array_equal(getattr(level, field)[mask], theirs[mask])
            # Saving what was loaded gives the same document (but for the name, taken from the file name).
            again = tmp_path / f"{name}{i}b.json"
            save_level(loaded, again)
            first, second = json.loads(path.read_text()), json.loads(again.read_text())
            assert second.pop("name") == f"{name}{i}" and first.pop("name") == ""
            assert first == second


# ---------------------------------------------------------------- triviality


def resting_level(green_on_blue: bool, red_between: bool = False):
    """A blue box on the floor and a green ball: dropped onto it, or held fixed far away."""
    sim = empty_level("m").sim
    sim, box = scene.add_rectangle(sim, (2.5, 0.65), 1.0, 0.5)
    x, fixed = (2.5, False) if green_on_blue else (0.5, True)
    sim, ball = scene.add_circle(sim, (x, 1.5), 0.2, fixed=fixed)
    roles = np.zeros(sim.num_bodies, np.int32)
    roles[box], roles[ball] = ROLE_BLUE, ROLE_GREEN
    if red_between:
        sim, slab = scene.add_rectangle(sim, (2.5, 1.0), 0.6, 0.1, fixed=True)
        roles[slab] = ROLE_RED
    sim, _ = scene.add_thruster(sim, box, (2.5, 0.4), angle=math.pi / 2, power=1.0)
    return make_level(sim, roles=roles)


CHECK_BATCH = 8


@pytest.fixture(scope="module")
def check_m():
    """is_trivial over a batch of CHECK_BATCH size-m levels (one compiled program for the tests below)."""
    check = jax2d.jit(jax.vmap(lambda level: is_trivial(level, SIM_PARAMS)))

    def run(levels):
        batch = jax.tree.map(lambda *xs: jnp.stack(xs), *levels) if isinstance(levels, list) else levels
        count = batch.roles.shape[0]
        padded = jax.tree.map(lambda x: jnp.concatenate([x] + [x[-1:]] * (CHECK_BATCH - count)), batch)
        return np.asarray(check(padded))[:count]

    return run


def test_hand_made_levels_trivial_or_not(check_m):
    flags = check_m([resting_level(green_on_blue=True), resting_level(green_on_blue=False),
                     resting_level(green_on_blue=True, red_between=True)])
    assert flags[0]  # the ball falls 0.4 m onto the box
    assert not flags[1]  # the ball is fixed 2 m away
    assert not flags[2]  # it falls onto red first: a loss, not a win, even though blue is just below


def test_most_generated_levels_are_not_trivial(trivial_flags):
    for name, flags in trivial_flags.items():
        assert flags.mean() < 0.25, f"{name}: {flags.mean():.0%} of generated levels are solved by doing nothing"


def test_nontrivial_sampler_keeps_the_first_nontrivial_candidate(check_m):
    """Levels holding only the two goal roots, the second placed near the first, are often trivial: with two
    candidates some keys find a non-trivial one (returned, flag True), others do not (a trivial one, False)."""
    easy = GeneratorParams(connected_chance=0.0, free_chance=0.0, goal_spread=-2.0, fixed_chance=0.0)
    keys = jax.random.split(jax.random.key(31), CHECK_BATCH)
    levels, found = jax2d.jit(jax.vmap(lambda k: sample_nontrivial_level(k, "m", easy, candidates=2)))(keys)
    found = np.asarray(found)
    assert found.any() and not found.all()
    np.testing.assert_array_equal(check_m(levels), ~found)
    assert_all_valid(levels, CHECK_BATCH, "filtered levels")


# ---------------------------------------------------------------- mutators


@pytest.fixture(scope="module")
def mutation_start(batches):
    return jax.tree.map(lambda x: x[:50], batches["m"])


def changed(before, after, i):
    return any(not np.array_equal(np.asarray(x[i]), np.asarray(y[i]))
               for x, y in zip(jax.tree.leaves(before), jax.tree.leaves(after), strict=True))


@pytest.mark.parametrize("mutator", MUTATORS, ids=lambda m: m.__name__)
def test_each_mutator_keeps_levels_valid(mutation_start, mutator):
    out = jax2d.jit(jax.vmap(lambda k, level: mutator(k, level, "m")))(jax.random.split(jax.random.key(8), 50),
                                                                       mutation_start)
    assert_all_valid(out, 50, f"levels after {mutator.__name__}")
    edited = [i for i in range(50) if changed(mutation_start, out, i)]
    assert len(edited) >= 20, f"{mutator.__name__} changed only {len(edited)} of 50 levels"
    before, after = mutation_start, out
    for i in edited:
        b0, b1 = unstack(before, i).sim.bodies, unstack(after, i).sim.bodies
        n0, n1 = b0.active.sum(), b1.active.sum()
        t0, t1 = unstack(before, i).sim.thrusters.active.sum(), unstack(after, i).sim.thrusters.active.sum()
        if mutator is mutate_add_shape:
            assert n1 == n0 + 1
        elif mutator is mutate_remove_shape:
            assert n1 == n0 - 1
        elif mutator is mutate_add_thruster:
            assert t1 == t0 + 1 and n1 == n0
        elif mutator is mutate_swap_roles:
            r0, r1 = unstack(before, i).roles, unstack(after, i).roles
            assert (r0 != r1).sum() == 2 and sorted(r0) == sorted(r1)
        elif mutator is mutate_toggle_fixed:
            assert ((b0.inv_mass == 0) != (b1.inv_mass == 0)).sum() == 1
        elif mutator in (mutate_move, mutate_rotate):
            moved = np.any(b0.position != b1.position, axis=1) | (b0.angle != b1.angle)
            assert moved.any() and n0 == n1
            # Everything jointed to a moved body moved with it (joints stay closed: checked by problems()).
            groups = joint_groups(unstack(before, i))
            assert set(groups[moved]).isdisjoint(set(groups[~moved & b0.active]))
            if mutator is mutate_move:
                shift = (b1.position - b0.position)[moved]
                np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-5)
                assert np.abs(shift).max() <= 0.5 + 1e-5
        elif mutator is mutate_resize:
            P = b0.vertices.shape[0]
            resized = [k for k in range(len(b0.active)) if (k < P and np.any(b0.vertices[k] != b1.vertices[k]))
                       or (k >= P and b0.radius[k - P] != b1.radius[k - P])]
            assert len(resized) == 1


@pytest.mark.parametrize("name", SIZE_NAMES)
def test_mutation_chains_keep_levels_valid(batches, name):
    """50 chains of 10 random mutations each (applied two at a time); every other level is checked."""
    step = jax2d.jit(jax.vmap(lambda k, level: mutate(k, level, n=2)))
    levels = jax.tree.map(lambda x: x[:50], batches[name])
    edited = 0
    for round_ in range(5):
        keys = jax.random.split(jax.random.key(100 + round_), 50)
        new = step(keys, levels)
        if round_ == 0:  # the same keys give the same edits
            for x, y in zip(jax.tree.leaves(new), jax.tree.leaves(step(keys, levels)), strict=True):
                assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
        edited += sum(changed(levels, new, i) for i in range(50))
        levels = new
        assert_all_valid(levels, 50, f"{name} levels after {2 * round_ + 2} mutations")
    assert edited >= 0.8 * 250


def test_mutate_rejects_bad_arguments(mutation_start):
    level = unstack(mutation_start, 0)
    with pytest.raises(ValueError, match="weights"):
        mutate(jax.random.key(0), level, weights=(1.0,))
    with pytest.raises(ValueError, match="does not match"):
        mutate_move(jax.random.key(0), level, "l")
