"""The benchmark scenes: four size classes with every capacity slot in use, built with jax2d only.

Each scene sits in the public Kinetix world, 5 m x 5 m, walled by four big static boxes in polygon
slots 0-3 (so SolverConfig(num_static=4) applies): floor top at y = 0.4, walls at x = 0 and x = 5,
ceiling at y = 5. About half the dynamic bodies move from the start (motors, thrusters, initial
velocities) and most touch the floor or each other, so contacts and joints are all exercised.

A batch is a few layout variants (assemblies jittered by a seeded RNG) picked per element, each
element then nudged sideways and given a little velocity noise, so no two elements evolve alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jax2d import COLLIDE_ALL, Capacity, SimState, SolverConfig, empty_state
from jax2d.scene import add_circle, add_fixed_joint, add_polygon, add_rectangle, add_revolute_joint, add_thruster

FLOOR = 0.4  # y of the floor's top face
WORLD = 5.0  # side of the square world
NUM_STATIC = 4  # the four walls
CONFIG = SolverConfig(num_static=NUM_STATIC)

# Capacity per size class, exactly the slots the scenes fill (polygons include the 4 walls).
CAPACITIES = {
    "s": Capacity(polygons=5, circles=2, joints=1, thrusters=1),
    "m": Capacity(polygons=6, circles=3, joints=2, thrusters=2),
    "l": Capacity(polygons=12, circles=4, joints=6, thrusters=2),
    "xl": Capacity(polygons=64, circles=16, joints=24, thrusters=8),
}


def add_walls(state: SimState) -> SimState:
    """Floor, left wall, right wall and ceiling as static boxes in polygon slots 0-3 (overlapping corners)."""
    thick, long = 1.0, WORLD + 2.0
    walls = [
        ((WORLD / 2, FLOOR - thick / 2), long, thick),  # floor
        ((-thick / 2, WORLD / 2), thick, long),  # left
        ((WORLD + thick / 2, WORLD / 2), thick, long),  # right
        ((WORLD / 2, WORLD + thick / 2), long, thick),  # ceiling
    ]
    for centre, width, height in walls:
        state, _ = add_rectangle(state, centre, width, height, fixed=True, collision_mode=COLLIDE_ALL)
    return state


def _car(state: SimState, x: float, rng: np.random.Generator) -> tuple[SimState, int]:
    """A chassis on two motor-driven wheels resting on the floor; returns the state and the chassis index."""
    radius, length = 0.18, 1.0
    y = FLOOR + radius
    state, chassis = add_rectangle(state, (x, y + 0.05), length, 0.2, density=1.0)
    for dx in (-0.4, 0.4):
        state, wheel = add_circle(state, (x + dx, y), radius, density=1.0)
        speed = float(rng.uniform(0.6, 1.0))
        state, _ = add_revolute_joint(state, chassis, wheel, (x + dx, y), motor_on=True, motor_speed=speed)
    return state, chassis


def build_s(rng: np.random.Generator) -> SimState:
    """1 dynamic box with one motor wheel and a thruster, plus a ball rolling towards it."""
    state = add_walls(empty_state(CAPACITIES["s"]))
    x = 1.5 + rng.uniform(-0.2, 0.2)
    state, cart = add_rectangle(state, (x, FLOOR + 0.125), 0.8, 0.25)
    radius = 0.2
    state, wheel = add_circle(state, (x + 0.4, FLOOR + radius), radius)
    state, _ = add_revolute_joint(state, cart, wheel, (x + 0.4, FLOOR + radius), motor_on=True)
    state, _ = add_thruster(state, cart, (x - 0.4, FLOOR + 0.125), angle=np.pi / 4, power=0.2)
    state, _ = add_circle(state, (3.5 + rng.uniform(-0.2, 0.2), FLOOR + 0.25), 0.25, velocity=(-1.5, 0.0))
    return state


def build_m(rng: np.random.Generator) -> SimState:
    """A two-wheeled car with a thruster, and a sliding box carrying a ball, pushed by a second thruster."""
    state = add_walls(empty_state(CAPACITIES["m"]))
    x = 1.2 + rng.uniform(-0.2, 0.2)
    state, chassis = _car(state, x, rng)
    state, _ = add_thruster(state, chassis, (x, FLOOR + 0.33), angle=np.pi / 2 + 0.3, power=0.3)
    bx = 3.5 + rng.uniform(-0.2, 0.2)
    state, box = add_rectangle(state, (bx, FLOOR + 0.2), 0.4, 0.4, velocity=(-1.0, 0.0))
    state, _ = add_thruster(state, box, (bx + 0.2, FLOOR + 0.2), angle=np.pi, power=0.15)
    state, _ = add_circle(state, (bx + rng.uniform(-0.05, 0.05), FLOOR + 0.6), 0.2)
    return state


def build_l(rng: np.random.Generator) -> SimState:
    """A car, a two-link motor arm with a pendulum ball, a rolling ball, and a box stack topped by a welded
    trapezoid with a thruster."""
    state = add_walls(empty_state(CAPACITIES["l"]))
    x = 0.9 + rng.uniform(-0.15, 0.15)
    state, chassis = _car(state, x, rng)
    state, _ = add_thruster(state, chassis, (x - 0.5, FLOOR + 0.23), angle=0.2, power=0.3)

    ax = 2.5 + rng.uniform(-0.1, 0.1)
    state, base = add_rectangle(state, (ax, FLOOR + 0.15), 0.5, 0.3, density=4.0)
    top = FLOOR + 0.3
    state, link1 = add_rectangle(state, (ax, top + 0.35), 0.1, 0.7)
    state, _ = add_revolute_joint(state, base, link1, (ax, top), motor_on=True, limits=(-1.2, 1.2))
    state, link2 = add_rectangle(state, (ax, top + 0.95), 0.1, 0.5)
    state, _ = add_revolute_joint(state, link1, link2, (ax, top + 0.7), motor_on=True, motor_speed=1.5)
    state, ball = add_circle(state, (ax, top + 1.2), 0.12)
    state, _ = add_revolute_joint(state, link2, ball, (ax, top + 1.2))

    state, _ = add_circle(state, (3.4, FLOOR + 0.15), 0.15, velocity=(-2.0 + rng.uniform(-0.3, 0.3), 0.0))

    sx = 4.3 + rng.uniform(-0.1, 0.1)
    side = 0.4
    stacked = None
    for level in range(3):
        jitter = rng.uniform(-0.03, 0.03)
        state, stacked = add_rectangle(state, (sx + jitter, FLOOR + side * (level + 0.5)), side, side)
    trapezoid = np.array([[-0.2, -0.1], [0.2, -0.1], [0.1, 0.1], [-0.1, 0.1]])
    roof_y = FLOOR + 3 * side + 0.1
    state, roof = add_polygon(state, (sx, roof_y), trapezoid)
    state, _ = add_fixed_joint(state, stacked, roof, (sx, roof_y - 0.1))
    state, _ = add_thruster(state, roof, (sx + 0.2, roof_y), angle=np.pi - 0.3, power=0.2)
    return state


def build_xl(rng: np.random.Generator) -> SimState:
    """Two cars with thrusters, each carrying a box with a thruster; a pyramid of 36 small boxes between
    them; four chains of five links hanging from the ceiling, two with motors, each ending in a thruster;
    twelve balls thrown sideways from above onto the pyramid and the cars."""
    state = add_walls(empty_state(CAPACITIES["xl"]))
    for x in (0.75 + rng.uniform(-0.1, 0.1), 4.25 + rng.uniform(-0.1, 0.1)):
        state, chassis = _car(state, x, rng)
        state, _ = add_thruster(state, chassis, (x - 0.5, FLOOR + 0.23), angle=0.2, power=0.3)
        state, box = add_rectangle(state, (x + rng.uniform(-0.2, 0.2), FLOOR + 0.44), 0.2, 0.2)
        state, _ = add_thruster(state, box, (x, FLOOR + 0.54), angle=-np.pi / 2, power=0.1)
    side, base = 0.22, 8
    for row in range(base):
        for k in range(base - row):
            x = 2.5 + (k - (base - row - 1) / 2) * side + rng.uniform(-0.01, 0.01)
            state, _ = add_rectangle(state, (x, FLOOR + side * (row + 0.5)), side, side)
    ceiling, link = WORLD, 0.3
    for i, cx in enumerate((1.0, 2.0, 3.0, 4.0)):
        above = 3  # the ceiling
        for k in range(5):
            state, body = add_rectangle(state, (cx, ceiling - link * (k + 0.5)), 0.06, link)
            motor = i % 2 == 0 and k == 1
            state, _ = add_revolute_joint(state, above, body, (cx, ceiling - link * k), motor_on=motor,
                                          motor_speed=float(rng.uniform(0.5, 1.0)))
            above = body
        state, _ = add_thruster(state, above, (cx, ceiling - 5 * link), angle=0.0, power=0.2)
    for k in range(12):
        state, _ = add_circle(state, (0.85 + 0.3 * k + rng.uniform(-0.03, 0.03), 2.8), 0.1,
                              velocity=(1.0 if k % 2 else -1.0, 0.0))
    return state


BUILDERS: dict[str, Callable[[np.random.Generator], SimState]] = {"s": build_s, "m": build_m, "l": build_l,
                                                                 "xl": build_xl}


def with_max_vertices(state: SimState, max_vertices: int) -> SimState:
    """The same scene with polygon vertex arrays cut or padded to `max_vertices` (every polygon must fit)."""
    bodies = state.bodies
    if int(np.max(np.asarray(bodies.n_vertices), initial=0)) > max_vertices:
        raise ValueError(f"a polygon has more than {max_vertices} vertices")
    vertices = np.asarray(bodies.vertices)
    if vertices.shape[1] >= max_vertices:
        vertices = vertices[:, :max_vertices]
    else:
        pad = np.repeat(vertices[:, -1:], max_vertices - vertices.shape[1], axis=1)
        vertices = np.concatenate([vertices, pad], axis=1)
    return dataclasses.replace(state, bodies=dataclasses.replace(bodies, vertices=jnp.asarray(vertices)))


def build_batch(size: str, batch: int, seed: int = 0, variants: int = 4, max_vertices: int = 8) -> SimState:
    """`batch` heterogeneous scenes of class `size` stacked on a leading axis."""
    rng = np.random.default_rng(seed)
    layouts = [with_max_vertices(BUILDERS[size](rng), max_vertices) for _ in range(min(batch, variants))]
    stacked = jax.tree.map(lambda *leaves: np.stack([np.asarray(leaf) for leaf in leaves]), *layouts)
    pick = rng.integers(len(layouts), size=batch)
    scenes = jax.tree.map(lambda leaf: leaf[pick], stacked)

    # Per element: shift every dynamic body sideways together (keeps joints intact) and add velocity noise.
    bodies = scenes.bodies
    dynamic = (bodies.inv_mass > 0)[..., None]
    shift = np.stack([rng.uniform(-0.05, 0.05, batch), np.zeros(batch)], axis=-1)[:, None, :]
    position = bodies.position + dynamic * shift
    velocity = bodies.velocity + dynamic * rng.normal(0.0, 0.02, bodies.velocity.shape)
    bodies = dataclasses.replace(bodies, position=position.astype(np.float32), velocity=velocity.astype(np.float32))
    scenes = dataclasses.replace(scenes, bodies=bodies)
    return jax.tree.map(jnp.asarray, scenes)
