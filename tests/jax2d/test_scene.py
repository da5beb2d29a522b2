"""Scene building: placement, mass, slot use, capacity errors, joints and thrusters, removal."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from jax2d.geometry import GeometryError
from jax2d.pairs import contact_layout
from jax2d.scene import CapacityError
from jax2d.state import Capacity, SolverConfig, empty_state

CAP = Capacity(polygons=3, circles=2, joints=2, thrusters=2, max_vertices=5)
P = CAP.polygons


def rot(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def arr(x):
    return np.asarray(x, np.float64)


def assert_same_layout(state, reference):
    """Same tree structure and identical leaf shapes and dtypes."""
    assert jax.tree_util.tree_structure(state) == jax.tree_util.tree_structure(reference)
    for leaf, ref in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(reference), strict=True):
        assert isinstance(leaf, jax.Array)
        assert leaf.shape == ref.shape and leaf.dtype == ref.dtype


@pytest.fixture
def empty():
    return empty_state(CAP)


@pytest.fixture
def pendulum(empty):
    """A static rectangle (body 0) and a dynamic circle (body P) hanging from it."""
    state, anchor = scene.add_rectangle(empty, (0.0, 2.0), 4.0, 0.5, fixed=True)
    state, bob = scene.add_circle(state, (1.0, 0.0), 0.3)
    return state, anchor, bob


# ---------------------------------------------------------------- bodies


def test_rectangle_is_centred_with_analytic_mass(empty):
    state, i = scene.add_rectangle(empty, (1.0, -2.0), 2.0, 0.5, density=3.0, angle=0.4, friction=0.6)
    b = state.bodies
    assert i == 0 and bool(b.active[0]) and not bool(np.any(b.active[1:]))
    mass = 3.0 * 2.0 * 0.5
    np.testing.assert_allclose(b.position[0], [1.0, -2.0], atol=1e-6)
    assert float(b.angle[0]) == pytest.approx(0.4)
    assert float(b.inv_mass[0]) == pytest.approx(1 / mass, rel=1e-6)
    assert float(b.inv_inertia[0]) == pytest.approx(12 / (mass * (4.0 + 0.25)), rel=1e-6)
    assert float(b.friction[0]) == pytest.approx(0.6) and float(b.density[0]) == pytest.approx(3.0)
    assert int(b.n_vertices[0]) == 4
    np.testing.assert_allclose(b.vertices[0, 4], b.vertices[0, 3])  # padding repeats the last vertex


def test_polygon_position_becomes_centroid_and_world_shape_is_kept(empty):
    verts = np.array([(0.0, 0.0), (3.0, 0.0), (0.0, 3.0)])  # centroid (1, 1) relative to position
    position, angle = np.array([2.0, 5.0]), 0.9
    state, i = scene.add_polygon(empty, position, verts, angle=angle)
    b = state.bodies
    np.testing.assert_allclose(b.position[i], position + rot(angle) @ [1.0, 1.0], atol=1e-5)
    stored = arr(b.vertices[i, :3])
    np.testing.assert_allclose(stored, verts - [1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(stored.mean(axis=0), 0.0, atol=1e-6)
    world_from_state = arr(b.position[i]) + stored @ rot(angle).T
    np.testing.assert_allclose(world_from_state, position + verts @ rot(angle).T, atol=1e-5)
    np.testing.assert_allclose(b.vertices[i, 3:], np.repeat(b.vertices[i, 2:3], 2, axis=0))


def test_circle_gets_global_index_after_polygons(empty):
    state, i = scene.add_circle(empty, (0.5, 0.5), 0.25, density=2.0, restitution=0.5, collision_mode=2)
    assert i == P
    assert float(state.bodies.radius[0]) == pytest.approx(0.25)
    mass = np.pi * 0.25**2 * 2.0
    assert float(state.bodies.inv_mass[i]) == pytest.approx(1 / mass, rel=1e-6)
    assert float(state.bodies.inv_inertia[i]) == pytest.approx(2 / (mass * 0.25**2), rel=1e-6)
    assert int(state.bodies.collision_mode[i]) == 2 and float(state.bodies.restitution[i]) == 0.5


def test_velocity_is_stored(empty):
    state, i = scene.add_circle(empty, (0, 0), 1.0, velocity=(1.5, -2.0), angular_velocity=3.0)
    np.testing.assert_allclose(state.bodies.velocity[i], [1.5, -2.0])
    assert float(state.bodies.angular_velocity[i]) == 3.0


def test_fixed_body_has_zero_inverse_mass(empty):
    state, i = scene.add_rectangle(empty, (0, 0), 1.0, 1.0, fixed=True)
    state, c = scene.add_circle(state, (0, 3), 1.0, fixed=True)
    for body in (i, c):
        assert float(state.bodies.inv_mass[body]) == 0.0 and float(state.bodies.inv_inertia[body]) == 0.0
    with pytest.raises(ValueError, match="cannot be given a velocity"):
        scene.add_circle(state, (0, 0), 1.0, fixed=True, velocity=(1.0, 0.0))


def test_set_fixed_round_trip_recomputes_mass(empty):
    state, i = scene.add_rectangle(empty, (0, 0), 2.0, 1.0, density=2.0, velocity=(1.0, 1.0), angular_velocity=2)
    fixed = scene.set_fixed(state, i, True)
    assert float(fixed.bodies.inv_mass[i]) == 0.0 and float(fixed.bodies.inv_inertia[i]) == 0.0
    np.testing.assert_array_equal(fixed.bodies.velocity[i], [0.0, 0.0])
    assert float(fixed.bodies.angular_velocity[i]) == 0.0
    free = scene.set_fixed(fixed, i, False)
    assert float(free.bodies.inv_mass[i]) == pytest.approx(1 / 4.0, rel=1e-6)
    assert float(free.bodies.inv_inertia[i]) == pytest.approx(12 / (4.0 * 5.0), rel=1e-5)


def test_set_velocity(pendulum):
    state, wall, bob = pendulum
    moved = scene.set_velocity(state, bob, (2.0, 1.0), 0.5)
    np.testing.assert_allclose(moved.bodies.velocity[bob], [2.0, 1.0])
    assert float(moved.bodies.angular_velocity[bob]) == 0.5
    kept = scene.set_velocity(moved, bob, (0.0, 1.0))
    assert float(kept.bodies.angular_velocity[bob]) == 0.5
    with pytest.raises(ValueError, match="fixed"):
        scene.set_velocity(state, wall, (1.0, 0.0))


def test_functions_never_mutate_their_input(empty):
    before = jax.tree_util.tree_map(np.array, empty)
    scene.add_rectangle(empty, (0, 0), 1.0, 1.0)
    scene.add_circle(empty, (0, 0), 1.0)
    for old, now in zip(jax.tree_util.tree_leaves(before), jax.tree_util.tree_leaves(empty), strict=True):
        np.testing.assert_array_equal(old, now)


def test_new_bodies_take_the_first_free_slot(empty):
    state = empty
    for x in range(3):
        state, _ = scene.add_rectangle(state, (x, 0), 1.0, 1.0)
    state = scene.remove_body(state, 1)
    state, again = scene.add_rectangle(state, (9, 9), 1.0, 1.0)
    assert again == 1
    np.testing.assert_allclose(state.bodies.position[1], [9.0, 9.0])


@pytest.mark.parametrize(
    "call,message",
    [
        (lambda s: scene.add_polygon(s, (0, 0), [(0, 0), (0, 1), (1, 0)]), "counter-clockwise"),
        (lambda s: scene.add_polygon(s, (0, 0), [(0, 0), (2, 0), (1, 0.5), (2, 2), (0, 2)]), "not convex: vertex 2"),
        (lambda s: scene.add_circle(s, (0, 0), -1.0), "radius must be > 0"),
        (lambda s: scene.add_circle(s, (0, 0), 1.0, density=0.0), "density must be > 0"),
        (lambda s: scene.add_circle(s, (np.nan, 0), 1.0), "position must be finite"),
        (lambda s: scene.add_rectangle(s, (0, 0), 1.0, 1.0, friction=-1.0), "friction"),
        (lambda s: scene.add_rectangle(s, (0, 0), 1.0, 1.0, restitution=2.0), "restitution"),
        (lambda s: scene.add_rectangle(s, (0, 0), 1.0, 1.0, collision_mode=3), "collision_mode"),
        (lambda s: scene.add_rectangle(s, (0, 0), 1.0, 1.0, angle=np.inf), "angle must be finite"),
    ],
)
def test_invalid_bodies_raise(empty, call, message):
    with pytest.raises(ValueError) as info:
        call(empty)
    assert message in str(info.value)


def test_geometry_errors_keep_their_type(empty):
    with pytest.raises(GeometryError):
        scene.add_circle(empty, (0, 0), 0.0)


# ---------------------------------------------------------------- capacity


def test_circle_overflow_names_the_circles(empty):
    state = empty
    for k in range(CAP.circles):
        state, _ = scene.add_circle(state, (k, 0), 0.5)
    with pytest.raises(CapacityError, match="no free circle slot: all 2 circle slots are in use"):
        scene.add_circle(state, (5, 0), 0.5)
    # Polygons still fit: the overflow is per kind.
    state, i = scene.add_rectangle(state, (0, 3), 1.0, 1.0)
    assert i == 0


def test_polygon_joint_and_thruster_overflow(pendulum):
    state, wall, bob = pendulum
    for _ in range(CAP.polygons - 1):
        state, _ = scene.add_rectangle(state, (0, 5), 1.0, 1.0)
    with pytest.raises(CapacityError, match="no free polygon slot: all 3 polygon slots"):
        scene.add_rectangle(state, (0, 5), 1.0, 1.0)
    for _ in range(CAP.joints):
        state, _ = scene.add_revolute_joint(state, wall, bob, (0, 1))
    with pytest.raises(CapacityError, match="no free joint slot: all 2 joint slots"):
        scene.add_fixed_joint(state, wall, bob, (0, 1))
    for _ in range(CAP.thrusters):
        state, _ = scene.add_thruster(state, bob, (1, 0), angle=0.0)
    with pytest.raises(CapacityError, match="no free thruster slot: all 2 thruster slots"):
        scene.add_thruster(state, bob, (1, 0), angle=0.0)


def test_zero_capacity_and_too_many_vertices():
    state = empty_state(Capacity(polygons=1, circles=0, joints=0, thrusters=0, max_vertices=4))
    with pytest.raises(CapacityError, match="0 circle slots"):
        scene.add_circle(state, (0, 0), 1.0)
    pentagon = [(np.cos(a), np.sin(a)) for a in np.linspace(0, 2 * np.pi, 5, endpoint=False)]
    with pytest.raises(CapacityError, match="5 vertices but this scene's capacity allows at most 4"):
        scene.add_polygon(state, (0, 0), pentagon)


# ---------------------------------------------------------------- joints


def two_bodies(empty):
    state, a = scene.add_rectangle(empty, (-1.0, 0.5), 2.0, 0.4, angle=0.3)
    state, b = scene.add_polygon(state, (1.5, -0.2), [(0, 0), (1, 0), (1, 1), (0, 1)], angle=-1.1)
    return state, a, b


def test_revolute_anchor_round_trips_through_both_bodies(empty):
    state, a, b = two_bodies(empty)
    anchor = np.array([0.4, 0.7])
    state, j = scene.add_revolute_joint(state, a, b, anchor, motor_on=True, motor_speed=-0.5, limits=(-0.2, 0.8))
    jt, bd = state.joints, state.bodies
    for body, local in ((a, jt.anchor_a[j]), (b, jt.anchor_b[j])):
        world = arr(bd.position[body]) + rot(float(bd.angle[body])) @ arr(local)
        np.testing.assert_allclose(world, anchor, atol=1e-5)
    assert float(jt.ref_angle[j]) == pytest.approx(-1.1 - 0.3, abs=1e-6)
    assert (int(jt.a[j]), int(jt.b[j])) == (a, b)
    assert bool(jt.active[j]) and not bool(jt.fixed[j]) and bool(jt.motor_on[j]) and bool(jt.limit_on[j])
    assert float(jt.motor_speed[j]) == -0.5 and float(jt.motor_power[j]) == 1.0
    assert (float(jt.lower[j]), float(jt.upper[j])) == pytest.approx((-0.2, 0.8))
    np.testing.assert_array_equal(jt.impulse[j], 0.0)


def test_fixed_joint_has_no_motor_or_limits(empty):
    state, a, b = two_bodies(empty)
    state, j = scene.add_fixed_joint(state, a, b, (0.0, 0.0))
    jt = state.joints
    assert bool(jt.fixed[j]) and not bool(jt.motor_on[j]) and not bool(jt.limit_on[j])
    world = arr(state.bodies.position[b]) + rot(float(state.bodies.angle[b])) @ arr(jt.anchor_b[j])
    np.testing.assert_allclose(world, [0.0, 0.0], atol=1e-5)


@pytest.mark.parametrize(
    "args,kwargs,message",
    [
        ((0, 0), {}, "two different bodies"),
        ((0, 7), {}, "out of range"),
        ((0, 2), {}, "not an active body"),
        ((0, 1), {"limits": (0.5, -0.5)}, "lower limit 0.5 is above upper limit -0.5"),
        ((0, 1), {"limits": (0.5,)}, "limits must be"),
        ((0, 1.5), {}, "must be an integer"),
    ],
)
def test_joint_errors(empty, args, kwargs, message):
    state, _, _ = two_bodies(empty)
    with pytest.raises(ValueError) as info:
        scene.add_revolute_joint(state, *args, (0, 0), **kwargs)
    assert message in str(info.value)


def test_joint_between_two_static_bodies_is_refused(empty):
    state, a = scene.add_rectangle(empty, (0, 0), 1.0, 1.0, fixed=True)
    state, b = scene.add_circle(state, (1, 0), 0.5, fixed=True)
    with pytest.raises(ValueError, match="both fixed"):
        scene.add_fixed_joint(state, a, b, (0.5, 0))


# ---------------------------------------------------------------- thrusters


def test_thruster_world_anchor_and_direction_convert_to_body_frame(empty):
    state, i = scene.add_rectangle(empty, (2.0, 1.0), 1.0, 2.0, angle=0.6)
    anchor, direction = np.array([2.3, 0.2]), 2.0
    state, t = scene.add_thruster(state, i, anchor, angle=direction, power=2.5)
    th, bd = state.thrusters, state.bodies
    world = arr(bd.position[i]) + rot(0.6) @ arr(th.anchor[t])
    np.testing.assert_allclose(world, anchor, atol=1e-5)
    world_angle = float(th.angle[t]) + 0.6
    np.testing.assert_allclose([np.cos(world_angle), np.sin(world_angle)], [np.cos(direction), np.sin(direction)])
    assert int(th.body[t]) == i and bool(th.active[t]) and float(th.power[t]) == 2.5


def test_thruster_in_body_frame_is_stored_as_given(empty):
    state, i = scene.add_circle(empty, (5.0, 5.0), 1.0, angle=1.0)
    state, t = scene.add_thruster(state, i, (0.0, -1.0), angle=0.25, world=False)
    np.testing.assert_allclose(state.thrusters.anchor[t], [0.0, -1.0])
    assert float(state.thrusters.angle[t]) == 0.25


@pytest.mark.parametrize("body,message", [(-1, "out of range"), (P + 1, "not an active body"), (True, "integer")])
def test_thruster_on_bad_body(empty, body, message):
    state, _ = scene.add_circle(empty, (0, 0), 1.0)
    with pytest.raises(ValueError, match=message):
        scene.add_thruster(state, body, (0, 0), angle=0.0)


# ---------------------------------------------------------------- removal


def test_remove_body_deactivates_what_is_attached(pendulum):
    state, wall, bob = pendulum
    state, other = scene.add_circle(state, (3.0, 0.0), 0.3)
    state, j_bob = scene.add_revolute_joint(state, wall, bob, (1.0, 2.0))
    state, j_other = scene.add_revolute_joint(state, wall, other, (3.0, 2.0))
    state, t_bob = scene.add_thruster(state, bob, (1.0, 0.0), angle=0.0)
    state, t_other = scene.add_thruster(state, other, (3.0, 0.0), angle=0.0)
    removed = scene.remove_body(state, bob)
    assert not bool(removed.bodies.active[bob]) and float(removed.bodies.inv_mass[bob]) == 0.0
    assert not bool(removed.joints.active[j_bob]) and bool(removed.joints.active[j_other])
    assert not bool(removed.thrusters.active[t_bob]) and bool(removed.thrusters.active[t_other])
    with pytest.raises(ValueError, match="not an active body"):
        scene.remove_body(removed, bob)


def test_remove_body_forgets_its_contacts(pendulum):
    state, wall, bob = pendulum
    ones = jax.tree_util.tree_map(jnp.ones_like, state.contacts)
    state = dataclasses.replace(state, contacts=ones)
    removed = scene.remove_body(state, bob)
    layout = contact_layout(CAP.polygons, CAP.circles)
    rows = (layout.slot_a == bob) | (layout.slot_b == bob)
    assert rows.any() and not rows.all()
    np.testing.assert_array_equal(removed.contacts.normal_impulse[rows], 0.0)
    np.testing.assert_array_equal(removed.contacts.key[rows], -1)
    assert not np.asarray(removed.contacts.active[rows]).any()
    np.testing.assert_array_equal(removed.contacts.separation[rows], 0.0)
    np.testing.assert_array_equal(removed.contacts.normal_impulse[~rows], 1.0)


def test_remove_joint_and_thruster(pendulum):
    state, wall, bob = pendulum
    state, j = scene.add_revolute_joint(state, wall, bob, (1.0, 2.0))
    state, t = scene.add_thruster(state, bob, (1.0, 0.0), angle=0.0)
    state = scene.remove_joint(scene.remove_thruster(state, t), j)
    assert not bool(state.joints.active[j]) and not bool(state.thrusters.active[t])
    with pytest.raises(ValueError, match="joint 0 is not active"):
        scene.remove_joint(state, j)
    with pytest.raises(ValueError, match="out of range"):
        scene.remove_thruster(state, 5)


# ---------------------------------------------------------------- layout


def test_state_layout_never_changes(empty):
    state, _ = scene.add_rectangle(empty, (0, 2), 4.0, 0.5, fixed=True)
    steps = [
        lambda s: scene.add_circle(s, (1, 0), 0.3)[0],
        lambda s: scene.add_polygon(s, (3, 0), [(0, 0), (1, 0), (0, 1)])[0],
        lambda s: scene.add_revolute_joint(s, 0, P, (1, 2), limits=(-1, 1))[0],
        lambda s: scene.add_fixed_joint(s, 0, 1, (3, 1))[0],
        lambda s: scene.add_thruster(s, P, (1, 0), angle=1.0)[0],
        lambda s: scene.set_velocity(s, P, (1, 1), 2.0),
        lambda s: scene.set_fixed(s, 1, True),
        lambda s: scene.remove_joint(s, 1),
        lambda s: scene.remove_thruster(s, 0),
        lambda s: scene.remove_body(s, P),
    ]
    assert_same_layout(state, empty)
    for step in steps:
        state = step(state)
        assert_same_layout(state, empty)


def test_batched_state_is_refused(empty):
    batch = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), empty)
    with pytest.raises(ValueError, match="one scene"):
        scene.add_circle(batch, (0, 0), 1.0)


def test_position_projection_without_the_projection_stage_is_refused():
    SolverConfig(joint_projection=None, joint_position_projection=None)  # the stage off: fine
    with pytest.raises(ValueError, match="needs joint_projection"):
        SolverConfig(joint_projection=None)


def test_stiff_relax_passes_without_a_relax_pass_are_refused():
    SolverConfig(relax_iterations=0, stiff_relax_iterations=0)  # no relax at all: fine
    with pytest.raises(ValueError, match="need relax_iterations >= 1"):
        SolverConfig(relax_iterations=0)


def test_a_scene_with_no_polygon_slots_steps():
    """Circles only (Capacity(polygons=0)): the step has no polygon to collide or store a rotation for. Two
    overlapping balls fall and are pushed apart."""
    state = empty_state(Capacity(polygons=0, circles=3, joints=1, thrusters=1))
    state, _ = scene.add_circle(state, (0.0, 1.0), 0.2)
    state, _ = scene.add_circle(state, (0.3, 1.0), 0.2)
    step = jax2d.jit(jax2d.step)
    for _ in range(10):
        state = step(state, jax2d.SimParams(), jnp.zeros(1), jnp.zeros(1))
    position = np.asarray(state.bodies.position)
    assert np.isfinite(position).all()
    assert (position[:2, 1] < 1.0).all() and position[1, 0] - position[0, 0] > 0.35
