"""kinetix.gym: Gymnasium's own checker on every observation and action type, the vector env against kinetix.env step
by step (bitwise, through episode ends), seeding, rendering, registration and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium", reason="kinetix.gym needs the gym extra: pip install -e '.[gym]'")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402

import jax2d  # noqa: E402
from kinetix.draw import View, level_frame  # noqa: E402
from kinetix.env import make_env  # noqa: E402
from kinetix.gym import ENV_ID, KinetixGymEnv, KinetixVectorEnv  # noqa: E402
from kinetix.level import LevelError  # noqa: E402
from kinetix.level_source import level_source  # noqa: E402
from kinetix.levels import load_level  # noqa: E402
from kinetix.reset_fns import list_index  # noqa: E402

LEVELS = Path(__file__).resolve().parents[2] / "levels"
SMALL = LEVELS / "thrust_hop.json"  # size s: 7 bodies, one thruster


def _level_variant(tmp: Path, name: str, green_at, max_timesteps: int) -> Path:
    """thrust_hop with its green box moved to `green_at` and another episode length."""
    data = json.loads(SMALL.read_text())
    green = next(b for b in data["bodies"] if b["role"] == "green")
    green["position"] = list(green_at)
    data["env"]["max_timesteps"] = max_timesteps
    path = tmp / f"{name}.json"
    path.write_text(json.dumps(data))
    return path


@pytest.fixture(scope="module")
def ends_dir(tmp_path_factory) -> Path:
    """Three levels whose episodes end quickly, each its own way: won (green dropped onto blue), lost (onto red) and
    truncated (the original start, 5 steps long). Their episode lengths differ, so per-level params are exercised."""
    tmp = tmp_path_factory.mktemp("ends")
    _level_variant(tmp, "a_win", (4.3, 1.05), 40)
    _level_variant(tmp, "b_lose", (2.3, 1.3), 30)
    _level_variant(tmp, "c_timeout", (0.6, 0.55), 5)
    return tmp


# ---------------------------------------------------------------- Gymnasium's checker


@pytest.mark.parametrize("observation, action", [("entity", "multi_discrete"), ("flat", "discrete"),
                                                 ("pixels", "continuous")])
def test_check_env_passes_for_every_observation_and_action_type(observation, action):
    env = KinetixGymEnv(str(SMALL), observation, action, render_mode="rgb_array", render_size=64,
                        pixel_resolution=16)
    check_env(env)  # raises on any failure (spaces, seeding determinism, step and render contracts)
    expected = {"multi_discrete": gymnasium.spaces.MultiDiscrete, "discrete": gymnasium.spaces.Discrete,
                "continuous": gymnasium.spaces.Box}[action]
    assert isinstance(env.action_space, expected)
    obs, _ = env.reset(seed=1)
    assert obs in env.observation_space
    if observation == "entity":
        assert isinstance(env.observation_space, gymnasium.spaces.Dict)
        assert all(isinstance(s, gymnasium.spaces.Box) for s in env.observation_space.values())
        assert env.observation_space["polygon_mask"].dtype == np.bool_
        assert env.observation_space["attention_mask"].shape[0] == 4
        assert env.observation_space["joint_indexes"].dtype == np.int32
    else:
        assert isinstance(env.observation_space, gymnasium.spaces.Box)
        assert env.observation_space.shape == ((16, 16, 3) if observation == "pixels" else obs.shape)
    env.close()


# ---------------------------------------------------------------- the vector env against kinetix.env


def test_vector_env_equals_the_jax_env_step_by_step_through_episode_ends(ends_dir):
    num_envs, steps, seed = 6, 24, 7
    envs = KinetixVectorEnv(str(ends_dir), num_envs=num_envs)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP

    # The reference: kinetix.env itself, with the key chains and per-level params kinetix.gym documents.
    source = level_source(ends_dir)
    env = make_env(source.env_config("entity", "multi_discrete"), source.reset_fn())
    level_params = source.level_params
    reset = jax2d.jit(jax.vmap(env.reset))
    step = jax2d.jit(jax.vmap(env.step_no_reset))
    split = jax2d.jit(jax.vmap(jax.random.split))
    pick = jax2d.jit(jax.vmap(lambda k: jax.tree.map(lambda x: x[list_index(k, 3)], level_params)))

    def select(mask, a, b):
        return jax.tree.map(lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)

    def assert_bitwise(got, want, what):
        for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            g, w = np.asarray(g), np.asarray(w)
            assert g.dtype == w.dtype and g.shape == w.shape, what
            assert np.ascontiguousarray(g).tobytes() == np.ascontiguousarray(w).tobytes(), what

    chains = split(jax.random.split(jax.random.PRNGKey(seed), num_envs))
    keys, subs = chains[:, 0], chains[:, 1]
    want_obs, state = reset(subs)
    params = pick(subs)
    obs, info = envs.reset(seed=seed)
    assert_bitwise(obs, want_obs, "reset obs")
    ended = np.zeros(num_envs, bool)
    rng = np.random.default_rng(0)
    seen = {"solved": 0, "failed": 0, "truncated": 0, "restarts": 0}
    for t in range(steps):
        actions = rng.integers(0, [3, 3, 3, 3, 2, 2], size=(num_envs, 6)).astype(np.int32)
        obs, reward, terminated, truncated, info = envs.step(actions)

        chains = split(keys)
        keys, subs = chains[:, 0], chains[:, 1]
        step_obs, stepped, step_reward, step_term, step_trunc, step_info = step(subs, state, jnp.asarray(actions),
                                                                               params)
        fresh_obs, fresh = reset(subs)
        restart = jnp.asarray(ended)
        state = select(restart, fresh, stepped)
        params = select(restart, pick(subs), params)
        want_obs = select(restart, fresh_obs, step_obs)
        assert_bitwise(obs, want_obs, f"obs at step {t}")
        assert_bitwise(reward, np.where(ended, 0.0, step_reward).astype(np.float32), f"reward at step {t}")
        assert_bitwise(terminated, np.asarray(step_term) & ~ended, f"terminated at step {t}")
        assert_bitwise(truncated, np.asarray(step_trunc) & ~ended, f"truncated at step {t}")
        assert_bitwise(info["solved"], np.asarray(step_info["solved"]) & ~ended, f"solved at step {t}")
        assert_bitwise(info["distance"], np.where(ended, fresh.last_distance, step_info["distance"]),
                       f"distance at step {t}")
        assert np.all(info["timestep"][ended] == 0) and np.all(info["_solved"])
        seen["solved"] += int(info["solved"].sum())
        seen["failed"] += int(info["failed"].sum())
        seen["truncated"] += int(truncated.sum())
        seen["restarts"] += int(ended.sum())
        ended = terminated | truncated
    # The comparison went through every kind of episode end and the restarts after them.
    assert all(count > 0 for count in seen.values()), seen
    envs.close()


def test_same_seed_same_episodes_and_other_seeds_other_levels(ends_dir):
    envs = KinetixVectorEnv(str(ends_dir), num_envs=8, max_timesteps=3)

    def run(seed):
        first, _ = envs.reset(seed=seed)
        rng = np.random.default_rng(1)
        out = [first["polygons"]]
        for _ in range(8):
            obs, *_ = envs.step(rng.integers(0, [3, 3, 3, 3, 2, 2], size=(8, 6)))
            out.append(obs["polygons"])
        return np.stack(out)

    a, b, c = run(3), run(3), run(4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)  # other draws of the three levels
    # max_timesteps overrides every level's own: every episode is truncated at step 3.
    envs.reset(seed=0)
    flags = [envs.step(np.zeros((8, 6), np.int32))[3] for _ in range(3)]
    assert not flags[0].any() and not flags[1].any()
    envs.close()


def test_reset_mask_resets_only_those_environments():
    envs = KinetixVectorEnv(str(SMALL), num_envs=3, observation="flat", action="discrete")
    envs.reset(seed=0)
    for _ in range(3):
        envs.step(np.full(3, 9))  # thruster 0 fires: the box moves
    moved, _ = envs.reset(options={"reset_mask": np.array([True, False, True])})
    obs, info = envs.reset(seed=0)  # every environment at its start
    assert np.array_equal(moved[0], obs[0]) and np.array_equal(moved[2], obs[2])
    assert not np.array_equal(moved[1], obs[1])
    with pytest.raises(ValueError, match="reset_mask"):
        envs.reset(options={"reset_mask": np.ones(2, bool)})
    envs.close()


# ---------------------------------------------------------------- rendering, registration, bad input


def test_rgb_array_is_the_browsers_drawing_of_the_level():
    env = KinetixGymEnv(str(SMALL), render_mode="rgb_array", render_size=200)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (200, 200, 3) and frame.dtype == np.uint8
    assert np.array_equal(frame, level_frame(load_level(SMALL).level, View(200, 200)))
    assert env.metadata["render_fps"] == 30  # dt 1/60 s, frame skip 2
    assert KinetixGymEnv(str(SMALL)).render() is None  # no render_mode: a warning, no frame


def test_registered_ids_make_both_envs():
    # The programs of test_reset_mask_resets_only_those_environments and check_env's flat/discrete: cached.
    env = gymnasium.make(ENV_ID, level=str(SMALL), observation="flat", action="discrete")
    assert isinstance(env.unwrapped, KinetixGymEnv)
    env.reset(seed=0)
    envs = gymnasium.make_vec(ENV_ID, num_envs=3, level=str(SMALL), observation="flat", action="discrete")
    assert isinstance(envs, KinetixVectorEnv) and envs.num_envs == 3
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (3, *env.observation_space.shape)
    assert isinstance(envs.action_space, gymnasium.spaces.MultiDiscrete) and envs.action_space.shape == (3,)
    # The module-qualified form imports kinetix.gym by itself.
    assert isinstance(gymnasium.make(f"kinetix.gym:{ENV_ID}", level=str(SMALL)).unwrapped, KinetixGymEnv)


def test_bad_input_gets_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="level is required"):
        KinetixGymEnv()
    with pytest.raises(LevelError, match="does not exist"):
        KinetixGymEnv(str(tmp_path / "missing.json"))
    with pytest.raises(LevelError, match=r"no \*\.json"):
        KinetixVectorEnv(str(tmp_path), num_envs=2)
    with pytest.raises(ValueError, match="num_envs"):
        KinetixVectorEnv(str(SMALL), num_envs=0)
    with pytest.raises(ValueError, match="observation type"):
        KinetixGymEnv(str(SMALL), observation="voxels")
    with pytest.raises(ValueError, match="render_mode"):
        KinetixGymEnv(str(SMALL), render_mode="human")
    env = KinetixGymEnv(str(SMALL), observation="flat", action="discrete")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="out of range"):
        env.step(11)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(6, np.int32))
    with pytest.raises(ValueError, match="integers"):
        env.step(0.5)
    obs, reward, *_ = env.step(8)  # still usable after refused actions
    assert isinstance(reward, float)
