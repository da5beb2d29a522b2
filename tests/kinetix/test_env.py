"""The RL environment: rewards, termination and truncation, auto-reset, shaping, frame skip, batching,
the log wrapper and the shared public levels.

Compiling a step is the slow part, so every test of one config shares one jitted function: the
handmade levels enter as states (`start`), never as separate reset functions.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d import scene
from kinetix.actions import noop_action, sample_random_action
from kinetix.env import EnvConfig, EnvParams, EnvState, StepOutput, make_env
from kinetix.goal import goal_distance
from kinetix.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED, LevelError, LevelParams, empty_level, make_level
from kinetix.levels import load_level
from kinetix.observations import flat_size
from kinetix.reset_fns import reset_list, reset_random, reset_single, stack_levels
from kinetix.wrappers import LogWrapper

G, DT = 9.81, 1.0 / 60.0
FLOOR = 0.4  # top of the standard floor


# ---------------------------------------------------------------- handmade size-s levels


def with_roles(sim, roles: dict):
    r = np.zeros(sim.num_bodies, np.int32)
    for body, role in roles.items():
        r[body] = role
    return make_level(sim, roles=r)


def ball_over_floor(floor_role):
    """A green ball 10 cm above the floor, which has `floor_role`."""
    sim, ball = scene.add_circle(empty_level("s").sim, (2.5, FLOOR + 0.2 + 0.1), 0.2)
    return with_roles(sim, {0: floor_role, ball: ROLE_GREEN})


def ball_on_blue_and_red():
    """A flat green plank falling onto a blue and a red post at once (a tie: losing must win)."""
    sim, plank = scene.add_rectangle(empty_level("s").sim, (2.5, 1.3), 1.0, 0.2)
    sim, blue = scene.add_circle(sim, (2.1, 1.0), 0.1, fixed=True)
    sim, red = scene.add_circle(sim, (2.9, 1.0), 0.1, fixed=True)
    return with_roles(sim, {plank: ROLE_GREEN, blue: ROLE_BLUE, red: ROLE_RED})


def resting_ball():
    """A green ball resting on a plain floor, nothing blue or red: nothing ever happens."""
    sim, ball = scene.add_circle(empty_level("s").sim, (2.5, FLOOR + 0.2), 0.2)
    return with_roles(sim, {ball: ROLE_GREEN})


def drifting_ball(vx):
    """No gravity: a green ball moving at vx along y = 2.5 with a fixed blue ball at x = 4.5."""
    sim, ball = scene.add_circle(empty_level("s", gravity=(0.0, 0.0)).sim, (2.0, 2.5), 0.2, velocity=(vx, 0.0))
    sim, goal = scene.add_circle(sim, (4.5, 2.5), 0.2, fixed=True)
    return with_roles(sim, {ball: ROLE_GREEN, goal: ROLE_BLUE})


def start(level):
    """The state an episode on `level` starts from (what reset gives for it)."""
    return EnvState(level=level, timestep=jnp.asarray(0, jnp.int32),
                    last_distance=goal_distance(level).astype(jnp.float32))


# ---------------------------------------------------------------- compiled once per module


@pytest.fixture(scope="module")
def env():
    # Resets draw from two levels that are told apart by their green ball's height.
    return make_env(EnvConfig("s"), reset_list([resting_ball(), ball_over_floor(ROLE_BLUE)]))


@pytest.fixture(scope="module")
def step(env):
    return jax2d.jit(env.step)


@pytest.fixture(scope="module")
def step_no_reset(env):
    return jax2d.jit(env.step_no_reset)


@pytest.fixture(scope="module")
def step3_no_reset():
    """Another config: flat observations, discrete actions, frame skip 3."""
    env3 = make_env(EnvConfig("s", observation="flat", action="discrete", frame_skip=3), resting_ball())
    return jax2d.jit(env3.step_no_reset)


@pytest.fixture(scope="module")
def reset(env):
    return jax2d.jit(env.reset)


NOOP = noop_action("multi_discrete")
DISCRETE_NOOP = noop_action("discrete")
KEY = jax.random.PRNGKey(0)


def run_until_done(step_fn, state, params, limit=60, action=NOOP):
    """Step with `action` until terminated or truncated; returns (steps, the last step's outputs)."""
    for t in range(1, limit + 1):
        out = step_fn(jax.random.PRNGKey(t), state, action, params)
        _, state, reward, terminated, truncated, info = out
        if terminated or truncated:
            return t, out
        assert float(reward) == 0.0 and not info["solved"] and not info["failed"]
    raise AssertionError(f"no episode end within {limit} steps")


# ---------------------------------------------------------------- goal, loss, truncation


def test_green_falling_onto_blue_wins(step_no_reset):
    level = ball_over_floor(ROLE_BLUE)
    t, (_, state, reward, terminated, truncated, info) = run_until_done(step_no_reset, start(level),
                                                                         EnvParams(max_timesteps=100))
    assert float(reward) == 1.0 and bool(terminated) and not bool(truncated)
    assert bool(info["solved"]) and not bool(info["failed"]) and not bool(info["nan"])
    assert int(info["timestep"]) == t == int(state.timestep)
    assert int(info["frozen"]) == 0  # the engine's non-finite guard did not fire
    # Free fall of 10 cm takes sqrt(2 * 0.1 / g) = 0.143 s = 4.3 agent steps of 2 / 60 s, so it ends within steps 4-7.
    assert 4 <= t <= 7


def test_green_falling_onto_red_loses(step_no_reset):
    _, (_, _, reward, terminated, truncated, info) = run_until_done(step_no_reset, start(ball_over_floor(ROLE_RED)),
                                                                    EnvParams(max_timesteps=100))
    assert float(reward) == -1.0 and bool(terminated) and not bool(truncated)
    assert bool(info["failed"]) and not bool(info["solved"])


def test_touching_blue_and_red_at_once_is_a_loss(step_no_reset):
    _, (_, _, reward, terminated, _, info) = run_until_done(step_no_reset, start(ball_on_blue_and_red()),
                                                            EnvParams(max_timesteps=100))
    assert float(reward) == -1.0 and bool(terminated)
    assert bool(info["failed"]) and not bool(info["solved"])


def test_touch_outcome_is_both_single_checks():
    """The env's one-read goal check (kinetix.goal.touch_outcome) gives what green_touches_blue and
    green_touches_red give, on every physics step of a ball falling onto a blue floor and onto a red one."""
    from kinetix.goal import green_touches_blue, green_touches_red, touch_outcome

    step = jax2d.jit(lambda s: jax2d.step(s, jax2d.SimParams(), jnp.zeros(1), jnp.zeros(1)))
    seen = set()
    for level in (ball_over_floor(ROLE_BLUE), ball_over_floor(ROLE_RED)):
        sim = level.sim
        for _ in range(20):
            sim = step(sim)
            now = dataclasses.replace(level, sim=sim)
            blue, red = (bool(x) for x in touch_outcome(now))
            assert (blue, red) == (bool(green_touches_blue(now)), bool(green_touches_red(now)))
            seen.add((blue, red))
    assert seen == {(False, False), (True, False), (False, True)}, seen  # every outcome was exercised


def test_truncated_exactly_at_max_timesteps(step_no_reset):
    state = start(resting_ball())
    params = EnvParams(max_timesteps=10)
    for t in range(1, 11):
        _, state, reward, terminated, truncated, info = step_no_reset(KEY, state, NOOP, params)
        assert not bool(terminated) and float(reward) == 0.0
        assert bool(truncated) == (t == 10), f"step {t}"
        assert int(info["timestep"]) == t


def test_terminal_scene_is_the_first_touching_physics_step(step_no_reset, step3_no_reset):
    """The scene is frozen at the physics step that touched blue, so frame skips 2 and 3 (which group the same
    physics steps differently) end on the very same scene; a free-falling box counts the physics steps run."""
    sim, box = scene.add_rectangle(empty_level("s").sim, (1.0, 3.0), 0.3, 0.3)
    sim, ball = scene.add_circle(sim, (3.5, FLOOR + 0.2 + 0.1), 0.2)
    level = with_roles(sim, {0: ROLE_BLUE, ball: ROLE_GREEN})
    params = EnvParams(max_timesteps=100)
    t2, (_, s2, r2, *_) = run_until_done(step_no_reset, start(level), params)
    t3, (_, s3, r3, *_) = run_until_done(step3_no_reset, start(level), params, action=DISCRETE_NOOP)
    assert float(r2) == float(r3) == 1.0
    steps = -float(s2.level.sim.bodies.velocity[box, 1]) / (G * DT)
    m = round(steps)
    assert abs(steps - m) < 1e-3, "the box's speed is a whole number of physics steps of free fall"
    assert m % 6 != 0, "choose another drop height: this one cannot tell frozen from unfrozen"
    assert (t2, t3) == (-(-m // 2), -(-m // 3))
    jax.tree.map(np.testing.assert_array_equal, s2.level, s3.level)


# ---------------------------------------------------------------- auto-reset


def test_auto_reset_returns_the_reset_levels_observation(step, reset):
    params = EnvParams(max_timesteps=100)
    state = start(ball_over_floor(ROLE_RED))  # a level the reset function never gives
    for t in range(1, 60):
        key = jax.random.PRNGKey(100 + t)
        obs, new_state, reward, terminated, truncated, info = step(key, state, NOOP, params)
        if terminated:
            break
        state = new_state
    else:
        raise AssertionError("the episode did not end")
    assert float(reward) == -1.0 and bool(info["failed"])  # the finished transition is reported...
    reset_obs, reset_state = reset(key, params)  # ...while obs and state are a fresh episode's
    jax.tree.map(np.testing.assert_array_equal, obs, reset_obs)
    jax.tree.map(np.testing.assert_array_equal, new_state, reset_state)
    assert int(new_state.timestep) == 0
    assert not np.any(np.asarray(new_state.level.roles) == ROLE_RED)


def test_step_no_reset_keeps_the_terminal_state(step_no_reset):
    level = ball_over_floor(ROLE_RED)
    _, (obs, state, _, terminated, _, _) = run_until_done(step_no_reset, start(level), EnvParams(max_timesteps=100))
    assert bool(terminated) and int(state.timestep) > 0
    np.testing.assert_array_equal(state.level.roles, level.roles)
    ball = level.sim.num_polygons
    assert float(state.level.sim.bodies.position[ball, 1]) < float(level.sim.bodies.position[ball, 1]) - 0.05
    np.testing.assert_array_equal(obs["circles"][0, :2], state.level.sim.bodies.position[ball])


def test_truncation_also_resets(step):
    params = EnvParams(max_timesteps=3)
    state = start(drifting_ball(0.0))  # no gravity, nothing moves: only the time limit ends it
    for t in range(1, 4):
        _, state, _, terminated, truncated, _ = step(jax.random.PRNGKey(t), state, NOOP, params)
        assert not bool(terminated) and bool(truncated) == (t == 3)
    assert int(state.timestep) == 0 and float(state.level.sim.gravity[1]) == pytest.approx(-G)


# ---------------------------------------------------------------- shaping and frame skip


@pytest.mark.parametrize("vx", [1.0, -1.0])
def test_dense_reward_follows_the_distance_to_blue(step_no_reset, vx):
    """Moving at vx for 2 physics steps changes the distance to blue by -vx * 2 dt; shaping is its decrease."""
    state = start(drifting_ball(vx))
    params = EnvParams(dense_reward_scale=0.5)
    _, state, reward, _, _, info = step_no_reset(KEY, state, NOOP, params)
    assert float(reward) == pytest.approx(0.5 * vx * 2 * DT, rel=1e-3)
    assert float(info["distance"]) == pytest.approx(2.5 - vx * 2 * DT, rel=1e-5)
    _, _, reward2, _, _, _ = step_no_reset(KEY, state, NOOP, params)  # the second step is shaped the same way
    assert float(reward2) == pytest.approx(float(reward), rel=1e-3)
    _, _, unshaped, _, _, _ = step_no_reset(KEY, state, NOOP, EnvParams())  # off by default
    assert float(unshaped) == 0.0


def test_frame_skip_advances_that_many_physics_steps(step_no_reset, step3_no_reset):
    """In free fall each physics step adds g dt to the downward speed, so one agent step adds frame_skip g dt."""
    sim, ball = scene.add_circle(empty_level("s").sim, (2.5, 3.0), 0.2)
    level = with_roles(sim, {ball: ROLE_GREEN})
    _, state, *_ = step_no_reset(KEY, start(level), NOOP, EnvParams())
    assert float(state.level.sim.bodies.velocity[ball, 1]) == pytest.approx(-2 * G * DT, rel=1e-5)
    obs, state3, *_ = step3_no_reset(KEY, start(level), DISCRETE_NOOP, EnvParams())
    assert float(state3.level.sim.bodies.velocity[ball, 1]) == pytest.approx(-3 * G * DT, rel=1e-5)
    assert obs.shape == (flat_size(EnvConfig("s").size),)


# ---------------------------------------------------------------- observations through the env


def test_resting_bodies_are_flagged_touching(step_no_reset):
    state = start(resting_ball())
    obs, state, *_ = step_no_reset(KEY, state, NOOP, EnvParams())
    _, state, *_ = step_no_reset(KEY, state, NOOP, EnvParams())
    obs, *_ = step_no_reset(KEY, state, NOOP, EnvParams())
    touching = np.asarray(obs["attention_mask"][3])
    ball = 5  # the first circle of size s (5 polygons)
    assert touching[0, ball] and touching[ball, 0], "ball on the floor (polygon 0)"
    assert not touching[1, ball] and not touching[3, ball], "the left wall and ceiling are far away"


def test_nan_in_the_scene_ends_the_episode_without_propagating(step, step_no_reset):
    """A NaN density passes through the physics untouched, so the env's own guard must catch it."""
    level = drifting_ball(1.0)
    ball = level.sim.num_polygons
    bodies = level.sim.bodies
    bad = dataclasses.replace(bodies, density=bodies.density.at[ball].set(jnp.nan))
    state = start(dataclasses.replace(level, sim=dataclasses.replace(level.sim, bodies=bad)))
    params = EnvParams(dense_reward_scale=1.0)
    obs, new, reward, terminated, truncated, info = step_no_reset(KEY, state, NOOP, params)
    assert bool(info["nan"]) and bool(terminated) and not bool(truncated) and float(reward) == 0.0
    assert not bool(info["solved"]) and not bool(info["failed"])
    for leaf in jax.tree.leaves(obs):
        assert np.all(np.isfinite(np.asarray(leaf, np.float32)))
    np.testing.assert_array_equal(new.level.sim.bodies.position, level.sim.bodies.position)  # rolled back
    obs, new, *_ = step(KEY, state, NOOP, params)  # with auto-reset the episode starts afresh
    for leaf in jax.tree.leaves((obs, new)):
        assert np.all(np.isfinite(np.asarray(leaf, np.float32)))


def test_info_counts_the_bodies_the_engines_guard_froze(step_no_reset):
    """A NaN velocity makes the ball's step result non-finite: the engine's guard keeps its pose and stops it
    (the state stays finite, so info["nan"] stays False), and info["frozen"] shows that it fired."""
    level = drifting_ball(1.0)
    ball = level.sim.num_polygons
    bodies = level.sim.bodies
    bad = dataclasses.replace(bodies, velocity=bodies.velocity.at[ball].set(jnp.array([jnp.nan, 0.0])))
    state = start(dataclasses.replace(level, sim=dataclasses.replace(level.sim, bodies=bad)))
    _, new, _, terminated, _, info = step_no_reset(KEY, state, NOOP, EnvParams())
    assert int(info["frozen"]) == 1 and not bool(info["nan"]) and not bool(terminated)
    np.testing.assert_array_equal(new.level.sim.bodies.position[ball], level.sim.bodies.position[ball])
    _, _, _, _, _, info = step_no_reset(KEY, new, NOOP, EnvParams())
    assert int(info["frozen"]) == 0


# ---------------------------------------------------------------- construction


def test_make_env_checks_the_reset_functions_size():
    with pytest.raises(LevelError, match="capacity"):
        make_env(EnvConfig("m"), reset_single(resting_ball()))
    with pytest.raises(ValueError, match="observation"):
        EnvConfig("s", observation="image")
    with pytest.raises(ValueError, match="action"):
        EnvConfig("s", action="keyboard")
    with pytest.raises(ValueError, match="frame_skip"):
        EnvConfig("s", frame_skip=0)
    medium = empty_level("m")
    with pytest.raises(LevelError, match="different capacities"):
        stack_levels([resting_ball(), medium])
    with pytest.raises(LevelError, match="size s"):
        reset_random("s", lambda key: medium)


def test_spaces_and_params_from_a_level_file():
    env = make_env(EnvConfig("s", action="discrete"), resting_ball())
    assert env.action_space.n == 11 and env.num_actions == 11
    assert make_env(EnvConfig("s"), resting_ball()).action_space.nvec == (3, 3, 3, 3, 2, 2)
    space = env.observation_space
    assert space["polygons"].shape == (5, 44) and space["circles"].shape == (2, 23)
    assert space["attention_mask"].shape == (4, 7, 7) and space["joints"].shape == (2, 23)
    params = EnvParams.from_level_params(LevelParams(max_timesteps=77, dense_reward_scale=0.3, base_motor_speed=4.0))
    assert params.max_timesteps == 77 and params.dense_reward_scale == 0.3 and params.sim.base_motor_speed == 4.0


def test_reset_random_uses_the_generator():
    levels = stack_levels([resting_ball(), ball_over_floor(ROLE_BLUE)])
    reset_fn = reset_random("s", lambda key: jax.tree.map(lambda x: x[jax.random.randint(key, (), 0, 2)], levels))
    heights = {round(float(reset_fn(jax.random.PRNGKey(k)).sim.bodies.position[5, 1]), 3) for k in range(20)}
    assert heights == {0.6, 0.7}


def test_reset_random_defaults_to_the_level_generator():
    pytest.importorskip("kinetix.generate", reason="the random level generator is written separately")
    reset_fn = reset_random("m")  # checks the generated capacity by tracing the generator once
    level = jax.eval_shape(reset_fn, KEY)
    assert level.capacity == EnvConfig("m").size.capacity


# ---------------------------------------------------------------- batches, determinism, public levels


@pytest.fixture(scope="module")
def public_levels(shared_dir):
    names = ("h2_one_wheel_car", "h3_point_the_thruster", "h0_weak_thrust", "h1_thrust_over_ball")
    return [load_level(shared_dir / "kinetix-levels" / "s" / f"{name}.json").level for name in names]


def test_public_levels_batched_random_rollout(public_levels):
    """8 environments over 4 public levels, 100 random steps under jit + vmap: finite, deterministic,
    and the log wrapper's episode statistics match a count kept here."""
    env = LogWrapper(make_env(EnvConfig("s"), reset_list(public_levels)))
    params = EnvParams(max_timesteps=20, dense_reward_scale=0.1)
    n = 8
    reset = jax2d.jit(jax.vmap(env.reset, in_axes=(0, None)))
    step = jax2d.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    sample = jax2d.jit(jax.vmap(lambda k: sample_random_action(k, "multi_discrete")))

    def rollout(seed):
        key = jax.random.PRNGKey(seed)
        obs, state = reset(jax.random.split(key, n), params)
        returns, lengths, finished = np.zeros(n), np.zeros(n, int), 0
        for _ in range(100):
            key, k_act, k_step = jax.random.split(key, 3)
            action = sample(jax.random.split(k_act, n))
            obs, state, reward, terminated, truncated, info = step(jax.random.split(k_step, n), state, action, params)
            for leaf in jax.tree.leaves(obs):
                assert np.all(np.isfinite(np.asarray(leaf, np.float32)))
            assert not np.any(info["nan"])
            reward, done = np.asarray(reward), np.asarray(terminated | truncated)
            assert np.all(np.isfinite(reward))
            returns += reward
            lengths += 1
            np.testing.assert_array_equal(info["returned_episode"], done)
            np.testing.assert_allclose(info["returned_episode_returns"][done], returns[done], rtol=1e-5, atol=1e-5)
            np.testing.assert_array_equal(info["returned_episode_lengths"][done], lengths[done])
            np.testing.assert_array_equal(info["returned_episode_solved"][done], np.asarray(info["solved"])[done])
            assert np.all(lengths <= params.max_timesteps)
            finished += int(done.sum())
            returns[done], lengths[done] = 0.0, 0
        return state, finished

    state_a, finished = rollout(1)
    assert finished >= n * (100 // 20)  # every episode ends by its 20th step
    assert np.all(np.isfinite(np.asarray(state_a.env_state.level.sim.bodies.position)))
    state_b, _ = rollout(1)
    jax.tree.map(np.testing.assert_array_equal, state_a, state_b)


# ---------------------------------------------------------------- the packed step (one scene from Python)


def test_packed_step_equals_step_bitwise_through_an_auto_reset(env, step, reset):
    from jax2d.compact import layout_of, pack, unpack_host

    params = EnvParams()
    packed_params = jax2d.jit(pack)(params)
    step_compact, reset_compact = jax2d.jit(env.step_compact), jax2d.jit(env.reset_compact)
    obs, state = reset(KEY, params)
    packed = reset_compact(KEY, packed_params)
    # reset and step give one layout, so the packed step compiles once for both.
    assert packed.layout == layout_of(StepOutput(*jax.eval_shape(env.step, KEY, state, NOOP, params)))
    ended = 0
    for t in range(1, 80):
        key = jax.random.PRNGKey(t)
        out = step(key, state, NOOP, params)
        packed = step_compact(key, packed, NOOP, packed_params)
        host = unpack_host(packed)
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(tuple(host)), strict=True):
            np.testing.assert_array_equal(np.asarray(a), b)
        state = out[1]
        ended += bool(out[3] | out[4])
    assert ended >= 1  # an episode ended, so the auto-reset path was compared too


def test_packed_step_rejects_a_buffer_that_is_not_a_packed_step_output(env):
    from jax2d.compact import pack

    params = jax2d.jit(pack)(EnvParams())
    obs, state = env.reset(KEY, EnvParams())
    with pytest.raises(ValueError, match="reset_compact or step_compact"):
        env.step_compact(KEY, pack((obs, state)), NOOP, params)  # (obs, state) alone: no reward, flags, info


def test_a_python_loop_of_env_step_compiles_once_per_env():
    """The gymnax-style loop without a jit of one's own: reset and step are jitted with the env static. Before,
    every eager step traced and compiled the physics scan afresh (seconds each) and the process aborted in LLVM
    after ~40 steps at m, out of memory to map compiled code."""
    from kinetix.env import KinetixEnv

    env = make_env(EnvConfig("s"), ball_over_floor(ROLE_BLUE))
    other = make_env(EnvConfig("s"), ball_over_floor(ROLE_BLUE))
    obs, state = env.reset(KEY)
    before = KinetixEnv.step._cache_size()
    wins = []
    for t in range(6):
        obs, state, reward, terminated, truncated, info = env.step(jax.random.PRNGKey(t), state, NOOP)
        wins.append(bool(terminated) and float(reward) == 1.0)
    assert KinetixEnv.step._cache_size() == before + 1  # one compile for six calls
    other.step(KEY, other.reset(KEY)[1], NOOP)
    assert KinetixEnv.step._cache_size() == before + 2  # another env is another static argument
    assert any(wins)  # the ball fell onto the blue floor within the six steps
