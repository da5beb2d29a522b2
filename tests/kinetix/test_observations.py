"""Observations: shapes per size class and type, column contents, masks, attention, permutation, flat layout."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from jax2d.state import COLLIDE_ALL, COLLIDE_NORMAL
from kinetix.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED, SIZES, empty_level, make_level
from kinetix.observations import (
    BODY_FEATURES,
    JOINT_FEATURES,
    OBS_CLIP,
    THRUSTER_FEATURES,
    entity_observation,
    flat_observation,
    flat_size,
    observe,
    polygon_features,
)

entity = jax2d.jit(entity_observation)
flat = jax2d.jit(flat_observation)


def set_body(level, index, **fields):
    b = level.sim.bodies
    new = {name: getattr(b, name).at[index].set(value) for name, value in fields.items()}
    return dataclasses.replace(level, sim=dataclasses.replace(level.sim, bodies=dataclasses.replace(b, **new)))


@pytest.fixture(scope="module")
def robot():
    """Size l. Box A (green, angle 0.3) -motor joint 0- box B (triangle) -weld 1- circle C (blue);
    circle D (red, fixed, collides with everything) stands alone; a thruster on A."""
    sim = empty_level("l").sim
    sim, a = scene.add_rectangle(sim, (1.0, 2.0), 0.6, 0.4, angle=0.3, density=2.0, friction=0.7,
                                 velocity=(0.5, -1.0), angular_velocity=3.0)
    sim, b = scene.add_polygon(sim, (1.6, 2.0), [[-0.2, -0.2], [0.2, -0.2], [0.0, 0.25]], restitution=0.3)
    sim, c = scene.add_circle(sim, (2.1, 2.0), 0.25)
    sim, d = scene.add_circle(sim, (4.0, 1.0), 0.3, fixed=True, collision_mode=COLLIDE_ALL)
    sim, j0 = scene.add_revolute_joint(sim, a, b, (1.3, 2.0), motor_on=True, motor_speed=1.5, motor_power=0.8,
                                       limits=(-0.4, 0.9))
    sim, j1 = scene.add_fixed_joint(sim, b, c, (1.85, 2.0))
    behind_a = (1.0 - 0.2 * np.cos(0.3), 2.0 - 0.2 * np.sin(0.3))  # 0.2 m behind A's centre along its axis
    sim, t0 = scene.add_thruster(sim, a, behind_a, angle=0.3 + 0.5, power=2.0)  # world anchor and direction
    roles = np.zeros(sim.num_bodies, np.int32)
    roles[[a, c, d]] = [ROLE_GREEN, ROLE_BLUE, ROLE_RED]
    level = make_level(sim, roles=roles, motor_bindings=[2, 0, 0, 0, 0, 0], motor_auto=[1, 0, 0, 0, 0, 0],
                       thruster_bindings=[1, 0])
    return level, dict(a=a, b=b, c=c, d=d, j0=j0, j1=j1, t0=t0)


# ---------------------------------------------------------------- shapes


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_shapes_per_size(size):
    s = SIZES[size]
    P, C, J, T, N, V = s.polygons, s.circles, s.joints, s.thrusters, s.polygons + s.circles, s.max_vertices
    level = empty_level(size)
    obs = entity(level)
    expected = {
        "polygons": (P, 22 + 2 * V + V - 2), "circles": (C, 23), "joints": (2 * J, 23), "thrusters": (T, 8),
        "polygon_mask": (P,), "circle_mask": (C,), "joint_mask": (2 * J,), "thruster_mask": (T,),
        "joint_indexes": (2 * J, 2), "thruster_indexes": (T,), "attention_mask": (4, N, N),
    }
    assert {k: v.shape for k, v in obs.items()} == expected
    for name in ("polygons", "circles", "joints", "thrusters"):
        assert obs[name].dtype == jnp.float32
    for name in ("polygon_mask", "circle_mask", "joint_mask", "thruster_mask", "attention_mask"):
        assert obs[name].dtype == jnp.bool_
    # Flat: every body slot [active + 20 + shape columns], joints with two one-hots over N, thrusters with one.
    length = P * (1 + 20 + 2 * V + V - 2) + C * (1 + 20 + 1) + J * (23 + 2 * N) + T * (8 + N) + 2
    assert flat(level).shape == (length,) == (flat_size(s),)
    assert length == {"s": 313, "m": 442, "l": 984}[size]


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_pixels(size):
    try:
        from kinetix.render import render_pixels  # noqa: F401
    except ImportError as error:
        pytest.skip(f"kinetix.render.render_pixels is not available yet ({error}); the pixel renderer is separate")
    image = jax2d.jit(lambda lv: observe(lv, "pixels", 32))(empty_level(size))
    assert image.shape == (32, 32, 3) and image.dtype == jnp.float32
    assert float(image.min()) >= 0.0 and float(image.max()) <= 1.0


def test_unknown_type():
    with pytest.raises(ValueError, match="observation type"):
        observe(empty_level("s"), "blind")


# ---------------------------------------------------------------- contents


def test_masks_and_inactive_rows(robot):
    level, _ = robot
    obs = entity(level)
    active = np.asarray(level.sim.bodies.active)
    P = level.sim.num_polygons
    np.testing.assert_array_equal(obs["polygon_mask"], active[:P])
    np.testing.assert_array_equal(obs["circle_mask"], active[P:])
    joints = np.asarray(level.sim.joints.active)
    np.testing.assert_array_equal(obs["joint_mask"], np.concatenate([joints, joints]))
    np.testing.assert_array_equal(obs["thruster_mask"], level.sim.thrusters.active)
    assert int(active.sum()) == 4 + 4 and int(joints.sum()) == 2
    for name, mask in (("polygons", "polygon_mask"), ("circles", "circle_mask"), ("joints", "joint_mask"),
                       ("thrusters", "thruster_mask")):
        rows = np.asarray(obs[name])
        off = ~np.asarray(obs[mask])
        assert not np.any(rows[off]), f"inactive {name} rows must be zero"
        assert np.all(np.abs(rows[~off]).sum(axis=1) > 0)


def test_body_columns(robot):
    level, ids = robot
    obs = entity(level)
    P = level.sim.num_polygons
    a = np.asarray(obs["polygons"][ids["a"]])
    b = level.sim.bodies
    np.testing.assert_allclose(a[0:2], b.position[ids["a"]], rtol=1e-6)
    np.testing.assert_allclose(a[2:4], [0.5, -1.0])
    # Mass 0.6 * 0.4 * 2 = 0.48 kg, inertia m (w^2 + h^2) / 12 = 0.0208 kg m^2, entered as log(1 + 1/x).
    assert a[4] == pytest.approx(np.log1p(1 / 0.48), rel=1e-5)
    assert a[5] == pytest.approx(np.log1p(12 / (0.48 * (0.36 + 0.16))), rel=1e-5)
    assert a[6] == 2.0 and a[7] == pytest.approx(np.tanh(0.3))
    np.testing.assert_array_equal(a[8:12], [0, 1, 0, 0])  # green
    np.testing.assert_allclose(a[12:14], [np.sin(0.3), np.cos(0.3)], rtol=1e-6)
    assert a[14] == pytest.approx(0.7) and a[15] == 0.0 and a[16] == 0.0
    np.testing.assert_array_equal(a[17:20], np.eye(3)[COLLIDE_NORMAL])
    np.testing.assert_allclose(a[20:22], [0.0, -9.81], rtol=1e-6)
    # A 0.6 x 0.4 box: four body-frame corners at (+-0.3, +-0.2), zero padding after, "4 vertices" one-hot.
    vertices = a[22:38].reshape(8, 2)
    np.testing.assert_allclose(np.sort(np.abs(vertices[:4]), axis=0), [[0.3, 0.2]] * 4, rtol=1e-5)
    assert not np.any(vertices[4:])
    np.testing.assert_array_equal(a[38:44], [0, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(obs["polygons"][ids["b"], 38:44], [1, 0, 0, 0, 0, 0])  # a triangle
    d = np.asarray(obs["circles"][ids["d"] - P])
    assert d[4] == 0.0 and d[16] == 1.0 and d[22] == pytest.approx(0.3)  # fixed, radius
    np.testing.assert_array_equal(d[8:12], [0, 0, 0, 1])
    np.testing.assert_array_equal(d[17:20], np.eye(3)[COLLIDE_ALL])
    wall = np.asarray(obs["polygons"][0])
    assert wall[16] == 1.0 and wall[4] == 0.0


def test_joint_rows_read_from_either_body(robot):
    level, ids = robot
    rel = 0.5  # turn B by 0.5 rad relative to A: theta = +0.5 seen from A, -0.5 seen from B
    level = set_body(level, ids["b"], angle=level.sim.bodies.angle[ids["b"]] + rel)
    obs = entity(level)
    J = level.sim.num_joints
    j0, j1 = ids["j0"], ids["j1"]
    fwd, back = np.asarray(obs["joints"][j0]), np.asarray(obs["joints"][J + j0])
    joints = level.sim.joints
    assert fwd[0] == back[0] == 1.0 and fwd[1] == back[1] == 0.0
    np.testing.assert_allclose(fwd[2:4], joints.anchor_a[j0], rtol=1e-6)
    np.testing.assert_allclose(fwd[4:6], joints.anchor_b[j0], rtol=1e-6)
    np.testing.assert_allclose(back[2:4], joints.anchor_b[j0], rtol=1e-6)
    np.testing.assert_allclose(fwd[6:8], [np.sin(rel), np.cos(rel)], atol=1e-6)
    np.testing.assert_allclose(back[6:8], [np.sin(-rel), np.cos(rel)], atol=1e-6)
    assert fwd[8] == 1.0 and fwd[9] == pytest.approx(1.5) and back[9] == pytest.approx(-1.5)
    assert fwd[10] == back[10] == pytest.approx(0.8) and fwd[11] == 1.0
    np.testing.assert_allclose(fwd[12:16], [np.sin(-0.4), np.cos(-0.4), np.sin(0.9), np.cos(0.9)], atol=1e-6)
    np.testing.assert_allclose(back[12:16], [np.sin(-0.9), np.cos(-0.9), np.sin(0.4), np.cos(0.4)], atol=1e-6)
    np.testing.assert_allclose(fwd[16:18], [-0.4 - rel, 0.9 - rel], atol=1e-5)
    np.testing.assert_allclose(back[16:18], [-0.9 + rel, 0.4 + rel], atol=1e-5)
    np.testing.assert_array_equal(fwd[18:23], [0, 0, 1, 0, 1])  # binding 2, motor auto
    weld = np.asarray(obs["joints"][j1])
    assert weld[1] == 1.0 and not np.any(weld[8:])  # a weld has no motor or limits
    np.testing.assert_array_equal(obs["joint_indexes"][j0], [ids["a"], ids["b"]])
    np.testing.assert_array_equal(obs["joint_indexes"][J + j0], [ids["b"], ids["a"]])
    np.testing.assert_array_equal(obs["joint_indexes"][J + j1], [ids["c"], ids["b"]])


def test_thruster_row(robot):
    level, ids = robot
    row = np.asarray(entity(level)["thrusters"][ids["t0"]])
    assert row[0] == 1.0
    # Anchor 0.2 m behind A's centre along A's axis; direction 0.5 rad from A's axis (body frame).
    np.testing.assert_allclose(row[1:3], [-0.2, 0.0], atol=1e-5)
    np.testing.assert_allclose(row[3:5], [np.sin(0.5), np.cos(0.5)], atol=1e-5)
    assert row[5] == pytest.approx(2.0)
    np.testing.assert_array_equal(row[6:8], [0, 1])
    assert int(entity(level)["thruster_indexes"][ids["t0"]]) == ids["a"]


def test_attention_masks(robot):
    level, ids = robot
    m = np.asarray(entity(level)["attention_mask"])
    active = np.asarray(level.sim.bodies.active)
    a, b, c, d = ids["a"], ids["b"], ids["c"], ids["d"]
    np.testing.assert_array_equal(m[0], active[:, None] & active[None, :])
    assert m[1][a, c] and m[1][c, a] and m[1][a, b], "A-B-C are one chain"
    assert not m[2][a, c] and m[2][a, b] and m[2][c, b], "but A and C are not jointed directly"
    assert not m[1][a, d] and not m[1][d, c] and not m[1][0, a], "D and the walls are not in the chain"
    assert not np.any(m[3] & ~np.eye(len(active), dtype=bool)), "nothing touched yet (no physics step)"
    for k in range(4):
        np.testing.assert_array_equal(np.diag(m[k]), active)  # every active body attends to itself
        np.testing.assert_array_equal(m[k], m[k].T)
        assert not np.any(m[k][~active]) and not np.any(m[k][:, ~active])


@pytest.mark.parametrize("seed", range(4))
def test_joint_masks_on_random_joint_graphs(seed: int) -> None:
    """Masks 1 and 2 against a plain graph search: random joints (some inactive, some repeated, some a body's
    joint with itself) between the bodies of an l level, all active."""
    level = empty_level("l")
    sim = level.sim
    N, J = sim.num_bodies, sim.num_joints
    rng = np.random.default_rng(seed)
    a, b = rng.integers(0, N, J), rng.integers(0, N, J)
    on = rng.random(J) < 0.8
    joints = dataclasses.replace(sim.joints, a=jnp.asarray(a, jnp.int32), b=jnp.asarray(b, jnp.int32),
                                 active=jnp.asarray(on))
    bodies = dataclasses.replace(sim.bodies, active=jnp.ones(N, bool))
    level = dataclasses.replace(level, sim=dataclasses.replace(sim, joints=joints, bodies=bodies))
    m = np.asarray(entity(level)["attention_mask"])
    direct = np.eye(N, dtype=bool)
    for i, j, o in zip(a, b, on, strict=True):
        if o:
            direct[i, j] = direct[j, i] = True
    reach = direct.copy()
    for _ in range(N):  # closure by repeated relaxation, the slow and obvious way
        reach = reach | np.any(reach[:, :, None] & reach[None, :, :], axis=1)
    np.testing.assert_array_equal(m[2], direct)
    np.testing.assert_array_equal(m[1], reach)
    assert reach.sum() > direct.sum(), "some chain longer than one joint"


def test_finite_and_clipped_under_extreme_values(robot):
    level, ids = robot
    level = set_body(level, ids["a"], velocity=jnp.array([jnp.inf, jnp.nan]), position=jnp.array([1e6, -3.0]))
    obs = entity(level)
    for name in ("polygons", "circles", "joints", "thrusters"):
        x = np.asarray(obs[name])
        assert np.all(np.isfinite(x)) and np.all(np.abs(x) <= OBS_CLIP)
    np.testing.assert_array_equal(obs["polygons"][ids["a"], 0:4], [OBS_CLIP, -3.0, OBS_CLIP, 0.0])
    f = np.asarray(flat(level))
    assert np.all(np.isfinite(f)) and np.all(np.abs(f) <= OBS_CLIP)


def test_flat_layout_matches_entity_rows(robot):
    level, ids = robot
    obs, f = entity(level), np.asarray(flat(level))
    P, C, J, N = level.sim.num_polygons, level.sim.num_circles, level.sim.num_joints, level.sim.num_bodies
    poly = polygon_features(8) - 1  # active column + entity row without gravity
    circle = BODY_FEATURES
    # Polygon A's block: active, columns 0-19, then the vertex and count columns.
    block = f[ids["a"] * poly:(ids["a"] + 1) * poly]
    row = np.asarray(obs["polygons"][ids["a"]])
    np.testing.assert_array_equal(block, np.concatenate([[1.0], row[:20], row[22:]]))
    # Circle C's block.
    start = P * poly + (ids["c"] - P) * circle
    row = np.asarray(obs["circles"][ids["c"] - P])
    np.testing.assert_array_equal(f[start:start + circle], np.concatenate([[1.0], row[:20], row[22:]]))
    # Joint 0: the a -> b entity row, then one-hot(A) and one-hot(B) over N bodies.
    start = P * poly + C * circle + ids["j0"] * (JOINT_FEATURES + 2 * N)
    block = f[start:start + JOINT_FEATURES + 2 * N]
    np.testing.assert_array_equal(block[:JOINT_FEATURES], obs["joints"][ids["j0"]])
    np.testing.assert_array_equal(block[JOINT_FEATURES:JOINT_FEATURES + N], np.eye(N)[ids["a"]])
    np.testing.assert_array_equal(block[JOINT_FEATURES + N:], np.eye(N)[ids["b"]])
    start = P * poly + C * circle + J * (JOINT_FEATURES + 2 * N) + ids["t0"] * (THRUSTER_FEATURES + N)
    np.testing.assert_array_equal(f[start + THRUSTER_FEATURES:start + THRUSTER_FEATURES + N], np.eye(N)[ids["a"]])
    np.testing.assert_allclose(f[-2:], [0.0, -9.81], rtol=1e-6)


# ---------------------------------------------------------------- permutation


def two_balls(first_is_green: bool):
    """A box jointed to the green ball, plus a free grey ball; the balls' circle slots depend on the flag."""
    sim, box = scene.add_rectangle(empty_level("m").sim, (1.0, 2.0), 0.4, 0.4)
    specs = [("green", (1.5, 2.0), 0.2), ("grey", (3.0, 1.5), 0.35)]
    if not first_is_green:
        specs.reverse()
    index = {}
    for name, position, radius in specs:
        sim, index[name] = scene.add_circle(sim, position, radius)
    sim, _ = scene.add_revolute_joint(sim, box, index["green"], (1.25, 2.0), motor_on=True)
    roles = np.zeros(sim.num_bodies, np.int32)
    roles[index["green"]] = ROLE_GREEN
    return make_level(sim, roles=roles), index


def test_permuting_two_circles_permutes_their_rows():
    level, i = two_balls(True)
    swapped, k = two_balls(False)
    assert (i["green"], i["grey"]) == (k["grey"], k["green"])
    P, N = level.sim.num_polygons, level.sim.num_bodies
    perm = np.arange(N)
    perm[[i["green"], i["grey"]]] = perm[[i["grey"], i["green"]]]  # body index in level -> index in swapped
    obs, obs_swapped = entity(level), entity(swapped)
    np.testing.assert_array_equal(obs["circles"], np.asarray(obs_swapped["circles"])[perm[P:] - P])
    np.testing.assert_array_equal(obs["polygons"], obs_swapped["polygons"])
    np.testing.assert_array_equal(obs["joints"], obs_swapped["joints"])
    np.testing.assert_array_equal(perm[np.asarray(obs["joint_indexes"])], obs_swapped["joint_indexes"])
    attention = np.asarray(obs_swapped["attention_mask"])
    np.testing.assert_array_equal(obs["attention_mask"], attention[:, perm][:, :, perm])
    assert not np.array_equal(obs["circles"], obs_swapped["circles"])  # the swap is visible at all
