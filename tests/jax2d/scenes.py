"""Scene builders and a fast rollout for the physics validation tests (test_physics.py).

Scenes are built with the public jax2d.scene API, outside jit. Every builder takes
its capacity from the caller so that tests share a few capacities, and with them a
few compiled rollouts (one per capacity and action shape).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from jax2d import scene
from jax2d.geometry import regular_polygon_vertices

STEP = jax2d.jit(jax2d.step, static_argnames="config")
DEFAULT_CONFIG = jax2d.SolverConfig()
CHUNK = 60  # steps per compiled scan: rollouts of any multiple of this reuse one compilation

# ---------------------------------------------------------------- rollouts


def kinematics(state: jax2d.SimState) -> dict[str, jax.Array]:
    """The per-step record most tests need: body poses and velocities."""
    b = state.bodies
    return dict(position=b.position, angle=b.angle, velocity=b.velocity, angular_velocity=b.angular_velocity)


@functools.partial(jax2d.jit, static_argnames=("record", "config"))
def _scan(state, params, motor_actions, thruster_actions, record, config):
    def body(s, actions):
        s = STEP(s, params, actions[0], actions[1], config=config)
        return s, record(s)

    return jax.lax.scan(body, state, (motor_actions, thruster_actions))


def _per_step(actions, n_steps: int, width: int) -> np.ndarray:
    """Actions as an (n_steps, width) float32 array: None means zeros, a (width,) row is repeated."""
    if actions is None:
        return np.zeros((n_steps, width), np.float32)
    a = np.asarray(actions, np.float32)
    if a.ndim == 1:
        a = np.broadcast_to(a, (n_steps, width))
    assert a.shape == (n_steps, width), f"actions must be ({n_steps}, {width}), got {a.shape}"
    return a


def rollout(
    state: jax2d.SimState,
    params: jax2d.SimParams,
    n_steps: int,
    motor_actions=None,
    thruster_actions=None,
    record: Callable = kinematics,
    config: jax2d.SolverConfig = DEFAULT_CONFIG,
) -> tuple[jax2d.SimState, dict[str, np.ndarray]]:
    """Step `n_steps` times; return the final state and `record(state)` after every step, stacked on axis 0.

    Runs in chunks of CHUNK scanned steps, so every n_steps that is a multiple of CHUNK
    shares one compilation per capacity (`record` must be a module-level function for
    the same reason: jit caches on its identity).
    """
    motors = _per_step(motor_actions, n_steps, state.num_joints)
    thrusts = _per_step(thruster_actions, n_steps, state.num_thrusters)
    records = []
    for start in range(0, n_steps, CHUNK):
        stop = min(start + CHUNK, n_steps)
        state, rec = _scan(state, params, motors[start:stop], thrusts[start:stop], record, config)
        records.append(rec)
    stacked = jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *records)
    return state, stacked


def stack(states: list[jax2d.SimState]) -> jax2d.SimState:
    """One batched state from scenes of the same capacity."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)


def unstack(batch: jax2d.SimState, i: int) -> jax2d.SimState:
    return jax.tree.map(lambda x: x[i], batch)


# ---------------------------------------------------------------- geometry helpers


def rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def world_anchors(state: jax2d.SimState, position: np.ndarray, angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World anchors of every joint on body a and on body b, given body poses (..., N, 2) and (..., N).

    Works on a recorded trajectory: leading axes of `position` / `angle` are kept.
    """
    j = state.joints
    a, b = np.asarray(j.a), np.asarray(j.b)

    def on(body, local):
        ang = angle[..., body]
        c, s = np.cos(ang), np.sin(ang)
        x = c * local[:, 0] - s * local[:, 1]
        y = s * local[:, 0] + c * local[:, 1]
        return position[..., body, :] + np.stack([x, y], axis=-1)

    return on(a, np.asarray(j.anchor_a, np.float64)), on(b, np.asarray(j.anchor_b, np.float64))


def anchor_gaps(state: jax2d.SimState, position, angle) -> np.ndarray:
    """(..., J) distance between each joint's anchor on a and on b (0 means attached)."""
    pa, pb = world_anchors(state, np.asarray(position, np.float64), np.asarray(angle, np.float64))
    return np.linalg.norm(pb - pa, axis=-1)


# ---------------------------------------------------------------- random crowded scenes

WORLD = 5.0  # random scenes live in the box [0, WORLD]^2 inside four static walls
WALL = 0.5  # wall thickness, outside the box


def add_walls(state: jax2d.SimState) -> jax2d.SimState:
    """Four static walls around [0, WORLD]^2 (floor, ceiling, left, right), in polygon slots 0..3."""
    half = WORLD / 2
    for centre, w, h in (
        ((half, -WALL / 2), WORLD + 2 * WALL, WALL),
        ((half, WORLD + WALL / 2), WORLD + 2 * WALL, WALL),
        ((-WALL / 2, half), WALL, WORLD),
        ((WORLD + WALL / 2, half), WALL, WORLD),
    ):
        state, _ = scene.add_rectangle(state, centre, w, h, fixed=True, friction=0.6)
    return state


def _random_convex(rng: np.random.Generator, max_vertices: int) -> np.ndarray:
    """A random convex polygon: 3..max_vertices points at sorted random angles on an ellipse (so always convex)."""
    n = int(rng.integers(3, max_vertices + 1))
    radius = rng.uniform(0.15, 0.45)
    if rng.random() < 0.3:  # a plain regular polygon now and then
        return regular_polygon_vertices(n, radius, angle=rng.uniform(0, 2 * np.pi))
    # Angles spread by at least a fifth of the even spacing so no edge is a sliver.
    gaps = rng.uniform(0.2, 1.0, n)
    theta = np.cumsum(gaps / gaps.sum() * 2 * np.pi) + rng.uniform(0, 2 * np.pi)
    stretch = rng.uniform(0.6, 1.0)
    return np.stack([radius * np.cos(theta), stretch * radius * np.sin(theta)], axis=1)


def random_scene(seed: int, capacity: jax2d.Capacity) -> tuple[jax2d.SimState, list[tuple[int, int]]]:
    """A crowded random scene: 4 walls, the other polygon and circle slots filled with dynamic bodies that
    overlap on purpose, jointed clusters (motors up to power 3, fixed joints, limits) and thrusters.

    Joints form a forest (each joint brings in a body not yet jointed), so no joint loop
    makes constraints contradict one another; about one in seven pins a body to a wall.
    Returns the state and, per joint, (joint slot, whether both of its bodies are dynamic).
    """
    rng = np.random.default_rng(seed)
    state = add_walls(jax2d.empty_state(capacity))
    bodies = []
    # Bodies cluster around a few centres, so many start overlapping.
    centres = rng.uniform(1.0, WORLD - 1.0, size=(3, 2))
    for kind in ["polygon"] * (capacity.polygons - 4) + ["circle"] * capacity.circles:
        centre = centres[rng.integers(len(centres))] + rng.normal(0, 0.35, 2)
        centre = np.clip(centre, 0.5, WORLD - 0.5)
        common = dict(
            angle=rng.uniform(-np.pi, np.pi),
            density=rng.uniform(0.5, 3.0),
            friction=rng.uniform(0.1, 1.0),
            restitution=rng.choice([0.0, rng.uniform(0, 0.9)]),
            velocity=rng.normal(0, 1.0, 2),
            angular_velocity=rng.normal(0, 2.0),
        )
        if kind == "polygon":
            state, i = scene.add_polygon(state, centre, _random_convex(rng, capacity.max_vertices), **common)
        else:
            state, i = scene.add_circle(state, centre, rng.uniform(0.1, 0.35), **common)
        bodies.append(i)

    joints = []
    in_tree = [bodies[0]]
    free = list(bodies[1:])
    rng.shuffle(free)
    for _ in range(min(capacity.joints, len(free))):
        b = free.pop()
        to_wall = rng.random() < 0.15
        a = int(rng.integers(4)) if to_wall else in_tree[int(rng.integers(len(in_tree)))]
        in_tree.append(b)
        pb = np.asarray(state.bodies.position[b], np.float64)
        if to_wall:
            anchor = pb  # pin b's centre to the wall body (the anchor may lie off the wall)
        else:
            pa = np.asarray(state.bodies.position[a], np.float64)
            anchor = pa + rng.uniform(0.3, 0.7) * (pb - pa)
        if rng.random() < 0.25:
            state, slot = scene.add_fixed_joint(state, a, b, anchor)
        else:
            lo = rng.uniform(-2.0, 0.0)
            limits = (lo, lo + rng.uniform(0.2, 3.0)) if rng.random() < 0.4 else None
            state, slot = scene.add_revolute_joint(
                state, a, b, anchor, motor_on=True, motor_speed=rng.uniform(-3.0, 3.0),
                motor_power=rng.uniform(0.5, 3.0), limits=limits)
        joints.append((slot, not to_wall))

    for _ in range(capacity.thrusters):
        i = bodies[int(rng.integers(len(bodies)))]
        p = np.asarray(state.bodies.position[i], np.float64)
        # At most 3 g on the body alone (power is in units of 10 N): harder pushes make light bodies hit the
        # speed clamp and tunnel through walls, which is legitimate behaviour, not what this scene probes.
        mass, _ = scene.body_mass_properties(state, i)
        power = rng.uniform(0.3, 1.0) * min(3.0, 3.0 * 9.81 * mass / 10.0)
        state, _ = scene.add_thruster(state, i, p + rng.normal(0, 0.1, 2), angle=rng.uniform(-np.pi, np.pi),
                                      power=power)
    return state, joints


# ---------------------------------------------------------------- pyramid


def pyramid(base: int, side: float = 1.0, friction: float = 0.6,
            extra: int = 0) -> tuple[jax2d.SimState, np.ndarray, np.ndarray]:
    """A pyramid of side x side boxes, rows of base, base - 1, ..., 1, on a static 40 m floor (body 0)
    whose top face is y = 0. Capacity: exactly the floor and the boxes, plus `extra` polygon slots.
    Returns the state, the boxes' body indices and each box's row (0 at the bottom)."""
    count = base * (base + 1) // 2
    state = jax2d.empty_state(jax2d.Capacity(polygons=1 + count + extra, circles=0, joints=0, thrusters=0,
                                             max_vertices=4))
    state, _ = scene.add_rectangle(state, (0.0, -0.5), 40.0, 1.0, fixed=True, friction=friction)
    boxes, rows = [], []
    for row in range(base):
        for k in range(base - row):
            x = (k - (base - row - 1) / 2) * side
            state, i = scene.add_rectangle(state, (x, side / 2 + row * side), side, side, friction=friction)
            boxes.append(i)
            rows.append(row)
    return state, np.array(boxes), np.array(rows)
