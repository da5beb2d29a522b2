"""Random levels: a pure-JAX generator, a no-op triviality filter and the shape operations mutators share.

    level = sample_level(jax.random.key(0), "m")                     # one level
    levels = jax.vmap(lambda k: sample_level(k, "m"))(keys)           # a batch, one compiled program
    level, found = sample_nontrivial_level(key, "m")                  # skip levels the no-op policy solves

Everything is `jnp` with fixed shapes and no Python control flow on traced values, so it runs under
`jit` and `vmap`, and one key always gives the same level.

How a level is built (all decisions random, knobs in `GeneratorParams`):
1. Start from the 4 standard static walls (polygon slots 0-3 of `empty_level`); the floor is sometimes red.
2. Visit every free body slot once, in random order of polygons and circles. The first two visits add
   the two *goal roots* (free shapes; the second prefers to lie far from the first), the third adds a
   motor-driven shape jointed to one of them when the control mode asks for a motor, every later visit
   adds a free shape, a jointed shape or nothing. A shape is kept only when one of a few placement
   proposals lies inside the world with (almost) no overlap with shapes it can collide with.
3. Goal roles: green from the first root's assembly (bodies linked by joints), blue from the second's,
   so they can always collide; some roots and free shapes are fixed, never both goal bodies.
4. Thrusters: one is forced when the control mode asks for it (or the motor found no room), more at
   random; powers give a force of a few times the weight of the assembly they push.
5. Random motor and thruster bindings; mass and inertia from the shapes (as jax2d computes them).

Each level therefore has at least one controllable element (a motor joint or a thruster) acting on a
dynamic body, and `is_valid` holds (see kinetix.mutate for the mutators that keep it).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

import jax2d
from jax2d.state import SimParams, SolverConfig
from kinetix.bindings import expand_actions
from kinetix.geometry import joint_groups, set_fixed, wall_mask
from kinetix.goal import green_touches_blue, green_touches_red
from kinetix.level import (
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    NUM_WALLS,
    ROLE_BLUE,
    ROLE_GREEN,
    ROLE_NONE,
    ROLE_RED,
    Level,
    SizeClass,
    size_class,
)
from kinetix.padding import constant_empty_level
from kinetix.placement import (
    DEFAULT_PARAMS,
    THRUSTER_DRAWS,
    GeneratorParams,
    Stream,
    add_body,
    add_body_draws,
    add_thruster,
    )

# ---------------------------------------------------------------- validity

SOLVER = SolverConfig()  # the no-op rollouts' solver settings (the environment's defaults)



def is_valid(level: Level) -> jax.Array:
    """Whether the level satisfies what the generator and mutators promise (jit/vmap-able).

    A green and a blue body that are active, not both fixed and not linked by joints (so they can touch);
    at least one motor joint or thruster acting on a dynamic body; every active joint links two distinct
    active bodies that are not both fixed; every active thruster sits on an active body.
    """
    b, j, t = level.sim.bodies, level.sim.joints, level.sim.thrusters
    fixed = b.inv_mass == 0
    return valid_masks(level.roles, b.active, fixed, joint_groups(level), j.active, j.a, j.b,
                       j.active & ~j.fixed & j.motor_on, t.active, t.body)


def valid_masks(roles, active, fixed, groups, joint_active, joint_a, joint_b, motor, thruster_active, thruster_body):
    """is_valid on the arrays it reads (so mutators can test candidate edits without building levels)."""
    green = active & (roles == ROLE_GREEN)
    blue = active & (roles == ROLE_BLUE)
    goal_pair = green[:, None] & blue[None, :] & ~(fixed[:, None] & fixed[None, :]) \
        & (groups[:, None] != groups[None, :])
    dynamic = active & ~fixed
    controllable = jnp.any(motor & (dynamic[joint_a] | dynamic[joint_b])) | jnp.any(
        thruster_active & dynamic[thruster_body])
    joints_ok = jnp.all(~joint_active | (active[joint_a] & active[joint_b] & (joint_a != joint_b)
                                         & ~(fixed[joint_a] & fixed[joint_b])))
    thrusters_ok = jnp.all(~thruster_active | active[thruster_body])
    return jnp.any(goal_pair) & controllable & joints_ok & thrusters_ok


# ---------------------------------------------------------------- the generator


def sample_level(key: jax.Array, size: SizeClass | str, params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """A random level of this size class; pure JAX, the same key always gives the same level.

    Needs room for the walls and at least two free bodies; the guarantee of a controllable element needs a
    thruster slot or (for a motor) a joint slot and three free bodies.
    """
    size = size_class(size)
    level = constant_empty_level(size)
    level = dataclasses.replace(level, sim=dataclasses.replace(
        level.sim, gravity=jnp.asarray([0.0, params.gravity], jnp.float32)))
    P, C, J, T = size.polygons, size.circles, size.joints, size.thrusters
    N = P + C
    F = max(P - NUM_WALLS, 0) + C
    if F < 2:
        raise ValueError(f"size {size.name} has {F} free body slots; a level needs at least 2 (green and blue)")
    step_draws = 1 + add_body_draws(params)
    u = Stream.of(key, 8 + 3 * F + F * step_draws + 2 * N + J + max(T, 1) * (1 + THRUSTER_DRAWS) + T)

    # Control mode: 0 motor, 1 thruster, 2 both (a motor needs a joint and a third body, a thruster a slot).
    can_motor, can_thruster = J > 0 and F >= 3, T > 0
    mode = u.choice(jnp.array([params.control_motor_weight * can_motor,
                               params.control_thruster_weight * can_thruster,
                               params.control_both_weight * (can_motor and can_thruster)], jnp.float32))
    want_motor = mode != 1

    # What each visit adds: 0 nothing, 1 a free shape, 2 a jointed shape.
    roll = u.take((F,))
    plan = jnp.where(roll < params.connected_chance, 2,
                     jnp.where(roll < params.connected_chance + params.free_chance, 1, 0))
    plan = plan.at[0].set(1).at[1].set(1)
    if F >= 3:
        plan = plan.at[2].set(jnp.where(want_motor, 2, plan[2]))
    fixed_roll = u.chance(params.fixed_chance, (F,))
    kind_roll = u.take((F,))
    step_numbers = u.sub(F, step_draws - 1)

    def visit(carry, inputs):
        level, roots, motor_added = carry
        k, numbers, step_plan, fixed, kind = inputs
        b = level.sim.bodies
        polygons_left = jnp.sum(~b.active[NUM_WALLS:P])
        circles_left = jnp.sum(~b.active[P:])
        is_circle = kind * (polygons_left + circles_left) >= polygons_left
        forced_motor = (k == 2) & want_motor
        result = add_body(Stream(numbers), level, params, is_circle=is_circle, connect=step_plan == 2,
                          force_motor=forced_motor, always=k < 2, far_from=jnp.where(k == 1, roots[0], -1),
                          fixed=fixed, enabled=step_plan > 0)
        roots = jnp.where((jnp.arange(2) == k) & result.added, result.index, roots)
        motor_added = motor_added | (forced_motor & result.jointed)
        return (result.level, roots, motor_added), None

    start = (level, jnp.array([-1, -1], jnp.int32), jnp.asarray(False))
    (level, roots, motor_added), _ = jax.lax.scan(
        visit, start, (jnp.arange(F), step_numbers, plan, fixed_roll, kind_roll))

    # Goal roles: green from the first root's joint group, blue from the second's; never both fixed.
    b = level.sim.bodies
    groups = joint_groups(level)
    fixed = b.inv_mass == 0
    green = u.choice(b.active & (groups == groups[roots[0]]))
    blue = u.choice(b.active & (groups == groups[roots[1]]))
    unfix = jnp.where(u.chance(0.5), green, blue)
    fixed = fixed.at[unfix].set(fixed[unfix] & ~(fixed[green] & fixed[blue]))
    level = set_fixed(level, fixed)

    index = jnp.arange(N)
    others = b.active & ~wall_mask(level) & (index != green) & (index != blue)
    roles = jnp.where(others & u.chance(params.red_chance, (N,)), ROLE_RED, ROLE_NONE).astype(jnp.int32)
    roles = roles.at[0].set(jnp.where(u.chance(params.floor_red_chance), ROLE_RED, ROLE_NONE))
    roles = roles.at[green].set(ROLE_GREEN).at[blue].set(ROLE_BLUE)
    # Random bindings for revolute joints; welds and empty slots keep 0, as the level loader stores them.
    motor_bindings = jnp.minimum(jnp.floor(u.take((J,)) * NUM_MOTOR_BINDINGS), NUM_MOTOR_BINDINGS - 1)
    revolute = level.sim.joints.active & ~level.sim.joints.fixed
    motor_bindings = jnp.where(revolute, motor_bindings, 0)
    level = dataclasses.replace(level, roles=roles, motor_bindings=motor_bindings.astype(jnp.int32),
                                motor_auto=jnp.zeros((J,), bool))

    # Thrusters: the first is forced when the mode asks for one or the motor found no room.
    force_thruster = (mode != 0) | ~motor_added
    extra = u.chance(params.extra_thruster_chance, (max(T, 1),))
    for slot in range(T):
        allowed = (force_thruster if slot == 0 else False) | extra[slot]
        level, _ = add_thruster(Stream(u.take((THRUSTER_DRAWS,))), level, params, prefer=green, allowed=allowed)
    return level


# ---------------------------------------------------------------- triviality


def no_op_outcome(level: Level, sim_params: SimParams, steps: int = 64, frame_skip: int = 2,
                  config: SolverConfig = SOLVER) -> tuple[jax.Array, jax.Array]:
    """(won, lost) when every binding is held at 0 for `steps` agent steps of `frame_skip` physics steps.

    The episode ends at the first physics step where green touches red (a loss, even if it also touches
    blue) or blue (a win). motor_auto joints still run, as they would in the environment.
    """
    motor, thrust = expand_actions(level, jnp.zeros(NUM_MOTOR_BINDINGS), jnp.zeros(NUM_THRUSTER_BINDINGS))

    def physics_step(carry, _):
        sim, done, won = carry
        sim = jax2d.step(sim, sim_params, motor, thrust, config)
        now = dataclasses.replace(level, sim=sim)
        red, blue = green_touches_red(now), green_touches_blue(now)
        won = won | (~done & ~red & blue)
        return (sim, done | red | blue, won), None

    (_, done, won), _ = jax.lax.scan(physics_step, (level.sim, jnp.asarray(False), jnp.asarray(False)),
                                     None, length=steps * frame_skip)
    return won, done & ~won


def is_trivial(level: Level, sim_params: SimParams, steps: int = 64, frame_skip: int = 2,
               config: SolverConfig = SOLVER) -> jax.Array:
    """Whether doing nothing wins: green touches blue (before any red) within `steps` agent steps."""
    return no_op_outcome(level, sim_params, steps, frame_skip, config)[0]


def sample_nontrivial_level(key: jax.Array, size: SizeClass | str, params: GeneratorParams = DEFAULT_PARAMS,
                            candidates: int = 8, sim_params: SimParams | None = None, steps: int = 64,
                            frame_skip: int = 2) -> tuple[Level, jax.Array]:
    """(level, found): the first of `candidates` sampled levels that the no-op policy does not solve.

    The candidates are sampled and simulated as one vmapped batch (fixed cost: `candidates` x `steps` x
    `frame_skip` physics steps). If every candidate is trivial, the last one is returned with found False;
    callers that must not train on it can resample with another key or down-weight it.
    """
    sim_params = sim_params if sim_params is not None else SimParams()
    levels = jax.vmap(lambda k: sample_level(k, size, params))(jax.random.split(key, candidates))
    trivial = jax.vmap(lambda lv: is_trivial(lv, sim_params, steps, frame_skip))(levels)
    found = jnp.any(~trivial)
    index = jnp.where(found, jnp.argmax(~trivial), candidates - 1)
    return jax.tree.map(lambda x: x[index], levels), found
