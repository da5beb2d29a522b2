"""jax2d.static_walls.centre_out, the walls' last stage, called on its own (one scene, batch-last arrays)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from jax2d import narrow_phase, scene, static_walls
from jax2d.math2d import Pose

SLOP = jax2d.SimParams().linear_slop


def _corner_scene():
    """A floor (top at y = 0) and a left wall overlapping it at the corner (x in [-2.5, -2], y in [-0.5, 0]);
    box A with its centre 5 cm in the floor and box B welded on top of it; box D jointed to nothing, its
    centre in the left wall, 0.1 m from its left face and 0.4 m from its right one; circle C with its centre
    in the corner, inside both."""
    state = jax2d.empty_state(jax2d.Capacity(polygons=6, circles=2, joints=2, thrusters=1))
    state, floor = scene.add_rectangle(state, (0.0, -0.25), 6.0, 0.5, fixed=True)
    state, wall = scene.add_rectangle(state, (-2.25, 1.0), 0.5, 3.0, fixed=True)
    state, a = scene.add_rectangle(state, (0.3, -0.05), 0.3, 0.3)
    state, b = scene.add_rectangle(state, (0.3, 0.25), 0.3, 0.3)
    state, d = scene.add_rectangle(state, (-2.4, 1.0), 0.2, 0.2)
    state, c = scene.add_circle(state, (-2.05, -0.1), 0.1)
    state, _ = scene.add_fixed_joint(state, a, b, (0.3, 0.1))
    return state, dict(floor=floor, wall=wall, a=a, b=b, d=d, c=c)


def _centre_out(state: jax2d.SimState, start: np.ndarray) -> np.ndarray:
    """centre_out on the state's poses as the step's end, `start` (N, 2) as its start; the new centres (N, 2)."""
    last = jax.tree.map(lambda x: jnp.asarray(x)[..., None], state)  # batch-last, a batch of one
    b = last.bodies
    N = b.active.shape[0]
    group = narrow_phase.joint_labels_batch_last(last.joints, N)
    shapes = static_walls.shapes(b, group, jnp.zeros((N, 1)), jnp.full((1,), 0.04), N)
    pose = Pose(b.position[:, 0], b.position[:, 1], b.angle)
    pose0 = Pose(jnp.asarray(start[:, 0])[:, None], jnp.asarray(start[:, 1])[:, None], b.angle)
    slop = jnp.full((1,), SLOP)
    out = jax2d.jit(lambda p0, p: static_walls.centre_out(shapes, p0, p, slop))(pose0, pose)
    return np.stack([np.asarray(out.x)[:, 0], np.asarray(out.y)[:, 0]], axis=1)


def test_a_centre_goes_out_the_way_it_came_in_and_its_welded_partner_goes_with_it() -> None:
    state, i = _corner_scene()
    start = np.asarray(state.bodies.position).copy()
    start[i["a"]] = (0.25, 0.2)  # A came down from above the floor
    start[i["d"]] = (-1.9, 1.05)  # D came in through the wall's right face
    start[i["c"]] = (-2.05, -0.1)  # C started where it is: it leaves through the face it is nearest to now
    end = _centre_out(state, start)
    before = np.asarray(state.bodies.position)
    # A's centre is CENTRE_MARGIN slops above the floor; B moved with it, so the weld did not open.
    np.testing.assert_allclose(end[i["a"]], (0.3, static_walls.CENTRE_MARGIN * SLOP), atol=1e-6)
    np.testing.assert_allclose(end[i["b"]] - before[i["b"]], end[i["a"]] - before[i["a"]], atol=1e-6)
    # D came in through the wall's right face (x = -2) and leaves through it, not through the nearer left one.
    np.testing.assert_allclose(end[i["d"]], (-2.0 + static_walls.CENTRE_MARGIN * SLOP, 1.0), atol=1e-6)
    # C, in both the floor and the wall: out of the deeper one, then the other (two rounds).
    assert end[i["c"]][0] > -2.0 and end[i["c"]][1] > 0.0
    # Static bodies never move.
    np.testing.assert_array_equal(end[[i["floor"], i["wall"]]], before[[i["floor"], i["wall"]]])


def test_a_centre_outside_every_static_body_is_left_where_it_is() -> None:
    state, i = _corner_scene()
    position = np.asarray(state.bodies.position).copy()
    position[[i["a"], i["b"], i["d"], i["c"]]] = [(0.3, 0.2), (0.3, 0.5), (-1.5, 1.0), (-1.5, 0.5)]
    state = dataclasses.replace(state, bodies=dataclasses.replace(state.bodies, position=jnp.asarray(position)))
    np.testing.assert_array_equal(_centre_out(state, position), position)


def _plank_scene():
    """A free upright plank 3 cm x 2 m at (1, 0) (its left face at x = 0.985) and four balls: A and B collide
    with it, C is welded to it, D passes beyond its top end."""
    state = jax2d.empty_state(jax2d.Capacity(polygons=2, circles=4, joints=1, thrusters=1), gravity=(0.0, 0.0))
    state, plank = scene.add_rectangle(state, (1.0, 0.0), 0.03, 2.0)
    balls = {}
    for name, at in (("a", (1.005, 0.3)), ("b", (1.2, -0.5)), ("c", (1.0, 0.8)), ("d", (1.2, 1.5))):
        state, balls[name] = scene.add_circle(state, at, 0.05, density=0.1)
    state, _ = scene.add_fixed_joint(state, plank, balls["c"], (1.0, 0.8))
    return state, dict(plank=plank, **balls)


def _last_stage(state: jax2d.SimState, start: np.ndarray, num_static: int = 0, token: bool = False) -> np.ndarray:
    """sweep_back_then_centre_out with every body's travel inside its speculative margin (so none is "fast"):
    only centres inside or through a polygon are moved. The new centres (N, 2). num_static, token: the
    stage's own arguments (token True: a traced one, as the step passes)."""
    last = jax.tree.map(lambda x: jnp.asarray(x)[..., None], state)
    b = last.bodies
    N = b.active.shape[0]
    group = narrow_phase.joint_labels_batch_last(last.joints, N)
    shapes = static_walls.shapes(b, group, jnp.full((N, 1), 10.0), jnp.full((1,), 0.04), N)
    pose = Pose(b.position[:, 0], b.position[:, 1], b.angle)
    pose0 = Pose(jnp.asarray(start[:, 0])[:, None], jnp.asarray(start[:, 1])[:, None], b.angle)
    slop = jnp.full((1,), SLOP)
    out = jax2d.jit(lambda p0, p, t: static_walls.sweep_back_then_centre_out(
        shapes, p0, p, slop, num_static=num_static, token=t if token else None))(pose0, pose, jnp.int32(0))
    return np.stack([np.asarray(out.x)[:, 0], np.asarray(out.y)[:, 0]], axis=1)


def test_the_last_stage_moves_the_same_centres_when_it_knows_the_walls_are_static():
    """The environment's solver says its first polygons are static (SolverConfig.num_static) and passes a
    traced token, so the last stage leaves those polygons' rows out of its test for a centre inside and
    computes each polygon's rotation once: the same centres move, to the same places. Only A, the first
    dynamic body, has its centre inside (the stage runs only where some centre is)."""
    state, i = _corner_scene()
    position = np.asarray(state.bodies.position).copy()
    position[[i["d"], i["c"]]] = [(-1.5, 1.0), (-1.5, 0.5)]
    state = dataclasses.replace(state, bodies=dataclasses.replace(state.bodies, position=jnp.asarray(position)))
    start = position.copy()
    start[i["a"]] = (0.25, 0.2)
    plain = _last_stage(state, start)
    assert (i["floor"], i["wall"], i["a"]) == (0, 1, 2)  # the two static polygons come first, then A
    np.testing.assert_array_equal(_last_stage(state, start, num_static=2, token=True), plain)
    moved = np.any(plain != position, axis=1)
    assert moved[[i["a"], i["b"]]].all() and not moved[[i["floor"], i["wall"], i["d"], i["c"]]].any()


def test_a_centre_inside_or_through_a_dynamic_plank_goes_back_the_way_it_came():
    """A light ball crushed into a free plank ends the step with its centre inside it, or, within one step,
    behind it: both go back out through the face they came in by. The plank itself does not move, nor does a
    ball welded to it, nor one that passed beyond its end."""
    state, i = _plank_scene()
    end = np.asarray(state.bodies.position).copy()
    start = end.copy()
    start[i["a"]] = (0.8, 0.3)  # A came in from the left and ends 2 cm deep
    start[i["b"]] = (0.8, -0.3)  # B went through: from 0.8 to 1.2 in x, entering at x = 0.985
    start[i["c"]] = (0.5, 0.8)  # C is welded to the plank
    start[i["d"]] = (0.8, 1.5)  # D passed above the plank's top end (y = 1)
    out = _last_stage(state, start)
    np.testing.assert_allclose(out[i["a"]], (0.985 - static_walls.CENTRE_MARGIN * SLOP, 0.3), atol=1e-5)
    # B goes back to where its centre entered (0.985, on the face: a hair inside, centre_out takes it the
    # margin out), on its own path.
    t = (0.985 - 0.8) / 0.4
    assert 0.985 - static_walls.CENTRE_MARGIN * SLOP - 1e-5 <= out[i["b"]][0] <= 0.985 + 1e-5
    np.testing.assert_allclose(out[i["b"]][1], -0.3 - 0.2 * t, atol=1e-5)
    np.testing.assert_array_equal(out[[i["plank"], i["c"], i["d"]]], end[[i["plank"], i["c"], i["d"]]])


def test_a_centre_that_started_inside_a_dynamic_plank_or_passed_beside_it_is_left_alone_by_the_through_test():
    """Through needs a start and an end outside the polygon and a segment that crosses it: a centre that
    moved within the plank's front region, or along it, stays where it is."""
    state, i = _plank_scene()
    position = np.asarray(state.bodies.position).copy()
    position[i["a"]] = (0.9, 0.3)
    position[i["b"]] = (0.9, -0.9)
    state = dataclasses.replace(state, bodies=dataclasses.replace(state.bodies, position=jnp.asarray(position)))
    start = position.copy()
    start[i["a"]] = (0.7, 0.3)  # moved toward the plank, stopped short of it
    start[i["b"]] = (0.9, 0.9)  # moved along its left face, outside it
    np.testing.assert_array_equal(_last_stage(state, start), position)
