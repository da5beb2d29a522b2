"""The handmade levels in levels/: each loads, is not solved by doing nothing, stays physically sane under
random actions, and is solved by a scripted controller, the proof that it can be solved.

Every level runs three policies (no-op, uniform random, its scripted solution) for a whole episode,
256 agent steps x frame skip 2 = 512 physics steps, each agent action held for the frame skip as in the
environment. A policy solves a level when green touches blue after some physics step before green ever
touches red (the episode ends at either). Levels of one size class run together in one jitted, vmapped
`lax.scan`, so each size class compiles once.

The scripted solutions are kinetix.solutions.SOLUTIONS (functions of the agent step and the SimState).
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from kinetix.bindings import expand_actions
from kinetix.goal import green_touches_blue, green_touches_red
from kinetix.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, ROLE_BLUE, ROLE_GREEN, Level, SizeClass
from kinetix.levels import dumps, load_level, read_json
from kinetix.solutions import SOLUTIONS, drive

LEVELS_DIR = Path(__file__).resolve().parents[2] / "levels"
LEVEL_PATHS = sorted(LEVELS_DIR.glob("*.json"))
REQUIRED_THEMES = ("car_", "cartpole", "catapult", "lunar_lander", "grasper", "obstacle_course", "pinball", "walker")
MIN_LEVELS = 20
MIN_CAR_VARIANTS = 2

ENV_STEPS = 256
FRAME_SKIP = 2
PHYSICS_STEPS = ENV_STEPS * FRAME_SKIP

WORLD_LOW, WORLD_HIGH = np.array([0.0, 0.4]), np.array([5.0, 5.0])  # inside of the walls
BOUNDS_SLACK = 0.05  # m a body's centre may pass the wall faces (contacts are soft)
MAX_JOINT_GAP = 0.05  # m between a joint's two anchors
MAX_INITIAL_OVERLAP = 0.02  # m of overlap allowed between bodies at the start
NEVER = np.iinfo(np.int32).max


# ---------------------------------------------------------------- simulating every level


def noop_policy(t, sim, key):
    return drive()


def random_policy(t, sim, key):
    motor_key, thruster_key = jax.random.split(jax.random.fold_in(key, t))
    return (jax.random.uniform(motor_key, (NUM_MOTOR_BINDINGS,), minval=-1.0, maxval=1.0),
            jax.random.uniform(thruster_key, (NUM_THRUSTER_BINDINGS,)))


def scripted(solution):
    return lambda t, sim, key: solution(t, sim)


def joint_gaps(sim: jax2d.SimState) -> jax.Array:
    """(J,) distance between each active joint's two anchors in the world (0 for inactive joints)."""
    b, j = sim.bodies, sim.joints

    def world(body, anchor):
        c, s = jnp.cos(b.angle[body]), jnp.sin(b.angle[body])
        return b.position[body] + jnp.stack([c * anchor[:, 0] - s * anchor[:, 1], s * anchor[:, 0] + c * anchor[:, 1]],
                                            axis=-1)

    gap = jnp.linalg.norm(world(j.a, j.anchor_a) - world(j.b, j.anchor_b), axis=-1)
    return jnp.where(j.active, gap, 0.0)


def all_finite(sim: jax2d.SimState) -> jax.Array:
    leaves = [x for x in jax.tree.leaves(sim) if jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def in_world(sim: jax2d.SimState) -> jax.Array:
    """Every active dynamic body's centre lies inside the walls (with a little slack)."""
    b = sim.bodies
    inside = jnp.all((b.position >= WORLD_LOW - BOUNDS_SLACK) & (b.position <= WORLD_HIGH + BOUNDS_SLACK), axis=-1)
    return jnp.all(inside | ~b.active | (b.inv_mass == 0))


def run_episode(level: Level, params: jax2d.SimParams, policies, policy_index, key):
    """One episode of one policy: physics steps of the first win and first loss (NEVER if none), whether the state
    stayed finite and in the world, the largest joint gap, the deepest overlap found by the first step, and how many
    bodies the engine's non-finite guard froze (SimState.frozen, summed over the steps)."""

    def with_sim(sim):
        return Level(sim, level.roles, level.motor_bindings, level.motor_auto, level.thruster_bindings)

    def physics_step(carry, step):
        sim, motor, thrust, first_win, first_loss, finite, inside, gap, frozen = carry
        t = step // FRAME_SKIP
        new_motor, new_thrust = jax.lax.switch(policy_index, policies, t, sim, key)
        act_now = step % FRAME_SKIP == 0  # the agent acts every FRAME_SKIP physics steps; actions are held between
        motor = jnp.where(act_now, new_motor, motor)
        thrust = jnp.where(act_now, new_thrust, thrust)
        sim = jax2d.step(sim, params, *expand_actions(level, motor, thrust), jax2d.SolverConfig())
        first_win = jnp.where((first_win == NEVER) & green_touches_blue(with_sim(sim)), step, first_win)
        first_loss = jnp.where((first_loss == NEVER) & green_touches_red(with_sim(sim)), step, first_loss)
        carry = (sim, motor, thrust, first_win, first_loss, finite & all_finite(sim), inside & in_world(sim),
                 jnp.maximum(gap, jnp.max(joint_gaps(sim), initial=0.0)), frozen + sim.frozen)
        overlap = -jnp.min(jnp.where(sim.contacts.active, sim.contacts.separation, 0.0), initial=0.0)
        return carry, overlap

    zero_motor, zero_thrust = drive()
    never = jnp.int32(NEVER)
    start = (level.sim, zero_motor, zero_thrust, never, never, all_finite(level.sim), in_world(level.sim),
             jnp.max(joint_gaps(level.sim), initial=0.0), jnp.int32(0))
    (_, _, _, first_win, first_loss, finite, inside, gap, frozen), overlaps = jax.lax.scan(
        physics_step, start, jnp.arange(PHYSICS_STEPS))
    return dict(first_win=first_win, first_loss=first_loss, finite=finite, in_world=inside, max_joint_gap=gap,
                initial_overlap=overlaps[0], frozen=frozen)


@functools.cache
def simulate_size_class(size: SizeClass, names: tuple[str, ...]) -> dict[tuple[str, str], dict]:
    """Results per (level name, policy name) for the levels of one size class, in one compiled, vmapped run."""
    files = [load_level(LEVELS_DIR / f"{name}.json") for name in names]
    policies = (noop_policy, random_policy) + tuple(scripted(SOLUTIONS[name]) for name in names)
    runs = [(k, "noop", 0) for k in range(len(names))] + [(k, "random", 1) for k in range(len(names))] \
        + [(k, "solution", 2 + k) for k in range(len(names))]

    def stack(items):
        return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *items)

    levels = stack([files[k].level for k, _, _ in runs])
    params = stack([files[k].params.sim_params() for k, _, _ in runs])
    index = jnp.array([i for _, _, i in runs], jnp.int32)
    keys = jax.random.split(jax.random.key(0), len(runs))
    batch = jax2d.jit(jax.vmap(lambda lv, pa, i, key: run_episode(lv, pa, policies, i, key)))
    out = jax.tree.map(np.asarray, batch(levels, params, index, keys))
    return {(names[k], policy): {field: values[r] for field, values in out.items()}
            for r, (k, policy, _) in enumerate(runs)}


def results(name: str, policy: str) -> dict:
    by_size: dict[SizeClass, list[str]] = {}
    for path in LEVEL_PATHS:
        if path.stem in SOLUTIONS:
            by_size.setdefault(load_level(path).size, []).append(path.stem)
    size = load_level(LEVELS_DIR / f"{name}.json").size
    return simulate_size_class(size, tuple(by_size[size]))[(name, policy)]


def solved(run: dict) -> bool:
    """Green touched blue within the episode, before green ever touched red (either ends an episode)."""
    return bool(run["first_win"] < min(run["first_loss"], PHYSICS_STEPS))


# ---------------------------------------------------------------- the tests


def test_there_are_enough_levels_with_the_required_themes_and_each_has_a_solution():
    names = [path.stem for path in LEVEL_PATHS]
    assert len(names) >= MIN_LEVELS
    for theme in REQUIRED_THEMES:
        assert any(name.startswith(theme) for name in names), f"no level for theme {theme}"
    assert sum(name.startswith("car_") for name in names) >= MIN_CAR_VARIANTS
    assert sorted(SOLUTIONS) == sorted(names), "every level needs exactly one scripted solution"
    sizes = {load_level(path).size.name for path in LEVEL_PATHS}
    assert sizes == {"s", "m", "l"}


@pytest.mark.parametrize("path", LEVEL_PATHS, ids=lambda p: p.stem)
def test_level_loads_in_its_declared_size_and_is_saved_canonically(path):
    file = load_level(path)
    declared = read_json(path)["size"]
    assert file.size.name == declared
    assert file.name and file.warnings == ()
    assert file.params.max_timesteps == ENV_STEPS and file.params.frame_skip == FRAME_SKIP
    roles = np.asarray(file.level.roles)[np.asarray(file.level.sim.bodies.active)]
    assert (roles == ROLE_GREEN).any() and (roles == ROLE_BLUE).any()
    assert dumps(file) == path.read_text(encoding="utf-8"), "write level files with kinetix.levels.save_level"


@pytest.mark.parametrize("path", LEVEL_PATHS, ids=lambda p: p.stem)
def test_doing_nothing_does_not_solve_the_level(path):
    run = results(path.stem, "noop")
    assert not solved(run), f"the no-op policy wins at physics step {run['first_win']}"


@pytest.mark.parametrize("path", LEVEL_PATHS, ids=lambda p: p.stem)
@pytest.mark.parametrize("policy", ["noop", "random", "solution"])
def test_level_stays_physically_sane(path, policy):
    run = results(path.stem, policy)
    assert run["finite"], "the state became NaN or infinite"
    assert run["frozen"] == 0, f"the engine's non-finite guard froze {run['frozen']} bodies"
    assert run["in_world"], "a body left the world box"
    assert run["max_joint_gap"] < MAX_JOINT_GAP, f"a joint came apart by {run['max_joint_gap']:.3f} m"
    assert run["initial_overlap"] < MAX_INITIAL_OVERLAP, f"bodies start {run['initial_overlap']:.3f} m deep"


@pytest.mark.parametrize("path", LEVEL_PATHS, ids=lambda p: p.stem)
def test_scripted_solution_solves_the_level(path):
    run = results(path.stem, "solution")
    assert solved(run), (f"first win at physics step {run['first_win']}, first loss at {run['first_loss']} "
                         f"(episode: {PHYSICS_STEPS} steps)")
