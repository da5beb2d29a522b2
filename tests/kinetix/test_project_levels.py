"""The handmade levels in levels/: each loads, is not solved by doing nothing, stays physically sane under
random actions, and is solved by a scripted controller, the proof that it can be solved.

Every level runs three policies (no-op, uniform random, its scripted solution) for a whole episode,
256 agent steps x frame skip 2 = 512 physics steps, each agent action held for the frame skip as in the
environment. A policy solves a level when green touches blue after some physics step before green ever
touches red (the episode ends at either). Levels of one size class run together in one jitted, vmapped
`lax.scan`, so each size class compiles once.

The scripted solutions are functions `(t, sim) -> (motor binding values (4,), thruster binding values (2,))`
of the agent step t and the current SimState, written in jnp. They read bodies by their global index in the
level's own size class (polygons first, then circles from index P = 5 / 6 / 12 for s / m / l).
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

LEVELS_DIR = Path(__file__).resolve().parents[2] / "levels"
LEVEL_PATHS = sorted(LEVELS_DIR.glob("*.json"))
REQUIRED_THEMES = ("car_", "cartpole", "catapult", "lunar_lander", "grasper", "obstacle_course", "pinball", "walker")
MIN_LEVELS = 20
MIN_CAR_VARIANTS = 2

ENV_STEPS = 256
FRAME_SKIP = 2
PHYSICS_STEPS = ENV_STEPS * FRAME_SKIP
ENV_DT = FRAME_SKIP / 60.0  # seconds per agent step

WORLD_LOW, WORLD_HIGH = np.array([0.0, 0.4]), np.array([5.0, 5.0])  # inside of the walls
BOUNDS_SLACK = 0.05  # m a body's centre may pass the wall faces (contacts are soft)
MAX_JOINT_GAP = 0.05  # m between a joint's two anchors
MAX_INITIAL_OVERLAP = 0.02  # m of overlap allowed between bodies at the start
NEVER = np.iinfo(np.int32).max


# ---------------------------------------------------------------- the scripted solutions


def drive(m0=0.0, m1=0.0, m2=0.0, m3=0.0, t0=0.0, t1=0.0):
    """Binding values as the (motor (4,), thruster (2,)) float32 pair a solution returns."""
    def as_vector(values):
        return jnp.stack([jnp.asarray(v, jnp.float32) for v in values])

    return as_vector((m0, m1, m2, m3)), as_vector((t0, t1))


def joint_angle(sim, j):
    """Joint j's angle as its limits measure it: angle_b - angle_a - ref_angle."""
    joints = sim.joints
    return sim.bodies.angle[joints.b[j]] - sim.bodies.angle[joints.a[j]] - joints.ref_angle[j]


def balance_velocity(sim, base, pole, length, goal_x, v_max):
    """Cart-pole rule: the base velocity that keeps `pole` (pivot at its lower end) upright and brings the base to
    goal_x. Linearised, a pole of length L on a base accelerating at a tips as theta'' = 1.5 / L * (g theta + a)
    (theta counter-clockwise); choosing a places the closed-loop poles near 5 rad/s, and the outer loop leans the
    pole towards the goal (a lean is what accelerates the base)."""
    b = sim.bodies
    x, v = b.position[base, 0], b.velocity[base, 0]
    theta, omega = b.angle[pole], b.angular_velocity[pole]
    theta_ref = jnp.clip(0.12 * (x - goal_x) + 0.2 * v, -0.12, 0.12)
    k = 1.5 / length
    accel = -(9.81 + 25.0 / k) * (theta - theta_ref) - (7.0 / k) * omega
    return jnp.clip(v + accel * ENV_DT, -v_max, v_max)


def cartpole(t, sim):
    """Body 4 cart, 5 pole. The wheel motors track a velocity: action 1 = 2 * 6 rad/s * 0.2 m = 2.4 m/s."""
    return drive(balance_velocity(sim, 4, 5, 1.2, 3.6, 2.4) / 2.4)


def unicycle(t, sim):
    """Body 4 seat post, 5 wheel. The motor sets the wheel's spin relative to the post (2 * 6 rad/s at action 1),
    so a ground speed v needs a relative spin of v / r + the post's own spin."""
    v = balance_velocity(sim, 5, 4, 1.0, 3.6, 2.5)
    return drive((v / 0.25 + sim.bodies.angular_velocity[4]) / 12.0)


def lunar_lander(t, sim):
    """Body 4 lander; thruster 0 left engine, 1 right engine. Cruise at 3 m above the terrain to over the pad, then
    descend; the lean that gives the wanted horizontal speed is held by differential thrust."""
    b = sim.bodies
    (x, y), (vx, vy) = b.position[4], b.velocity[4]
    phi, omega = b.angle[4], b.angular_velocity[4]
    pad_x, pad_y = 3.9, 1.6
    above_pad = jnp.abs(x - pad_x) < 0.25
    vx_want = jnp.clip(1.2 * (pad_x - x), -1.0, 1.0)
    phi_want = -jnp.clip(0.6 * (vx_want - vx), -0.35, 0.35)
    vy_want = jnp.clip(2.0 * (jnp.where(above_pad, pad_y, 3.0) - y), -0.9, 0.6)
    lift = (0.61 + 0.5 * (vy_want - vy)) / jnp.cos(phi)  # 0.61: the hover share of both engines
    turn = 0.4 * (phi_want - phi) - 0.15 * omega
    return drive(t0=lift - turn, t1=lift + turn)


def pinball(t, sim):
    """Body 12 ball. Flip the left flipper when the ball rolls onto its middle; otherwise hold both flippers down."""
    x, y = sim.bodies.position[12]
    flip = (x > 1.55) & (x < 2.0) & (y < 1.3)
    return drive(jnp.where(flip, 1.0, -1.0), -1.0)


def grasper(t, sim):
    """Body 5 arm. Close the fingers, swing the arm (speed ramped up so the ball is not flung) to above the bin,
    and open the fingers once the arm has come to rest there."""
    arm, arm_speed = sim.bodies.angle[5], sim.bodies.angular_velocity[5]
    swing = jnp.clip(0.03 * (t - 15), 0.0, 1.0) * jnp.clip(2.0 * (1.3 - arm), -1.0, 1.0)
    at_rest_over_bin = (arm > 1.25) & (jnp.abs(arm_speed) < 0.1)
    return drive(swing, jnp.where(at_rest_over_bin, -0.3, 1.0))  # open gently: a fast finger flicks the ball


def obstacle_course(t, sim):
    """Body 4 car, 6 hammer rod. Creep to a waiting spot outside the hammer's low sweep, then dash as soon as the
    hammer has swung through the bottom to the right: the car follows it and is past before it swings back.
    (Driving flat out from the start gets the car hit.)"""
    x = sim.bodies.position[4, 0]
    phi, omega = sim.bodies.angle[6], sim.bodies.angular_velocity[6]
    hammer_leaving = (phi > -0.1) & (omega > 0.0)
    approach, waiting = x < 1.2, (x >= 1.2) & (x < 1.6)
    go = (x >= 1.6) | (waiting & hammer_leaving)
    return drive(jnp.where(go, 1.0, jnp.where(approach, 0.4, 0.0)))


def thruster_maze(t, sim):
    """Body 4 craft; thruster 0 lifts, 1 pushes right. Climb to the gap's height, cross it, drop and slide into
    the blue ball."""
    (x, y), (vx, vy) = sim.bodies.position[4], sim.bodies.velocity[4]
    before_gap = x < 2.9
    lift = jnp.where(before_gap, 0.6 + 1.5 * (3.45 - y) - 0.8 * vy, 0.0)
    push = ((y > 3.3) & (vx < 1.2)) | ((x > 2.7) & (y < 1.0))
    return drive(t0=lift, t1=push)


def ball_catch(t, sim):
    """Body 4 cart, 8 ball. Drive the cart under the ball's predicted landing point (a velocity command)."""
    (x, y), (vx, vy) = sim.bodies.position[8], sim.bodies.velocity[8]
    fall_time = (vy + jnp.sqrt(vy * vy + 2 * 9.81 * jnp.maximum(y - 0.8, 0.0))) / 9.81
    land_x = x + vx * fall_time
    cart_x = sim.bodies.position[4, 0]
    return drive(jnp.clip(2.0 * (land_x - cart_x), -2.2, 2.2) / 2.25)


def walker(t, sim):
    """Bodies 5/7 back/front thigh; joints 2/3 front/back knee. An open-loop gait found by a small random search
    (it still wins with every parameter perturbed by 3%): hips track sines of the absolute thigh angles, knees
    bend out of phase."""
    freq, hip_amp, hip_mid, knee_amp, knee_mid, leg_phase, knee_phase = 6.5, 0.39, 0.22, 0.37, -0.24, 2.3, -2.4
    phase = freq * t * ENV_DT
    target = jnp.stack([hip_mid + hip_amp * jnp.sin(phase), hip_mid + hip_amp * jnp.sin(phase + leg_phase),
                        knee_mid + knee_amp * jnp.sin(phase + knee_phase),
                        knee_mid + knee_amp * jnp.sin(phase + leg_phase + knee_phase)])
    angle = sim.bodies.angle
    current = jnp.stack([angle[7], angle[5], joint_angle(sim, 2), joint_angle(sim, 3)])
    return drive(*jnp.clip(4.0 * (target - current), -1.0, 1.0))


def crane(t, sim):
    """Body 5 jib. Lower the jib slowly (so the load does not swing into the red post) to the angle that sets the
    load on the platform."""
    jib = sim.bodies.angle[5]
    return drive(jnp.clip(0.02 * t, 0.0, 1.0) * jnp.clip(3.0 * (-1.1 - jib), -1.0, 1.0))


def pendulum_swing(t, sim):
    """Body 4 rod. The motor is too weak to lift the rod: pump energy by always pushing along the swing."""
    return drive(jnp.sign(sim.bodies.angular_velocity[4] + 1e-3))


SOLUTIONS = {
    # s
    "hamster_ball": lambda t, sim: drive(1.0),
    "pendulum_swing": pendulum_swing,
    "thrust_hop": lambda t, sim: drive(t0=sim.bodies.position[4, 0] < 1.6),  # thrust until the hop clears the red
    "unicycle": unicycle,
    # m
    "ball_catch": ball_catch,
    "car_ramp": lambda t, sim: drive(1.0),
    "car_right": lambda t, sim: drive(1.0),
    "octagon_roll": lambda t, sim: drive(t0=1.0),
    "seesaw": lambda t, sim: drive(-1.0),
    "thruster_maze": thruster_maze,
    # l
    "car_jump": lambda t, sim: drive(1.0),
    "cartpole": cartpole,
    "catapult": lambda t, sim: drive(jnp.where(t < 15, 0.0, -1.0)),  # let the ball settle, then fling
    "crane": crane,
    "drawbridge": lambda t, sim: drive(jnp.where(t < 40, 0.0, 1.0), -1.0),  # lower the bridge, then drive
    "grasper": grasper,
    "lunar_lander": lunar_lander,
    "obstacle_course": obstacle_course,
    "pinball": pinball,
    "tower_knockover": lambda t, sim: drive(jnp.clip(0.05 * t, 0.0, 1.0)),
    "walker": walker,
}


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
