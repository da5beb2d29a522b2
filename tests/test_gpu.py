"""jax2d and the environment on a GPU: skipped where JAX has none (CI, the 2-core development machine).

Where there is one (install with `pip install -e '.[cuda]'`; see README "Running on a GPU"), this runs physics
accuracy tests of tests/jax2d on it, a batched environment rollout, and compares GPU against CPU results one step
at a time, from the same state on both, to float32 rounding (XLA compiles other kernels per backend and may
contract multiply-adds differently; bitwise equality across backends is not expected, and whole trajectories
drift apart as the contacts grow the rounding: docs/gpu.md). bench/gpu.sh runs this file. Run alone:

    python -m pytest tests/test_gpu.py -v
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d


def _gpu():
    try:
        return jax.devices("gpu")[0]
    except RuntimeError:  # JAX has no GPU backend here
        return None


GPU = _gpu()
pytestmark = pytest.mark.skipif(
    GPU is None, reason=f"no GPU: JAX's backends here are {jax.default_backend()} only "
                        "(install JAX's CUDA wheels with pip install -e '.[cuda]' on a machine with an NVIDIA GPU)")
CPU = jax.devices("cpu")[0]


def _scenes_apart(a, b, relative: float = 2e-4, absolute: float = 5e-5) -> tuple[np.ndarray, float]:
    """Per scene (the leading axis), whether any float leaf of a and b differs by more than `absolute` +
    `relative` x the leaf's largest magnitude; and the largest gap."""
    apart, worst = None, 0.0
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        gap = np.abs(x - y).reshape(x.shape[0], -1)
        scene = (gap > absolute + relative * float(np.abs(x).max(initial=0.0))).any(axis=1)
        apart = scene if apart is None else apart | scene
        worst = max(worst, float(gap.max(initial=0.0)))
    return apart, worst


def _nudged(sim, seed: int):
    """`sim` (batched jax2d.SimState) with each body's position and velocity moved by about one float32 ulp
    (x (1 +- 1.2e-7), or unmoved, at random): the size of the difference a GPU's rounding makes."""
    import dataclasses

    rng = np.random.default_rng(seed)

    def nudge(x):
        x = np.asarray(x)
        return (x * (1 + rng.choice([-1.0, 0.0, 1.0], x.shape) * 1.2e-7)).astype(x.dtype)

    bodies = sim.bodies
    return dataclasses.replace(sim, bodies=dataclasses.replace(bodies, position=nudge(bodies.position),
                                                               velocity=nudge(bodies.velocity)))


class _Agreement:
    """GPU against CPU, one step at a time from the same state, measured against the engine's own sensitivity.

    A crowded scene's step is not a smooth function of its input: a contact's clamped impulses, a reference
    face picked between two nearly parallel ones, or a contact made at the speculative distance turn a one-ulp
    change of a position into gaps of up to 0.1 rad/s in that scene (measured on the CPU, the same program
    stepped from a state and from the state nudged by one ulp: 244 of 512 crowded l scenes on their first
    step, 0-6 on later ones). So each step is also taken on the CPU from the one-ulp nudged state, and the GPU
    must depart from the CPU in no more scenes, and by no more, than that nudge does, with a margin (twice as
    many scenes, plus 2 % of the batch; ten times the gap). A GPU program that computed something else would
    depart in most scenes at every step."""

    def __init__(self) -> None:
        self.gpu_scenes = self.nudged_scenes = self.steps = 0
        self.gpu_worst = self.nudged_worst = 0.0

    def add(self, gpu, cpu, nudged_cpu) -> None:
        apart, worst = _scenes_apart(gpu, cpu)
        apart_nudged, worst_nudged = _scenes_apart(nudged_cpu, cpu)
        self.gpu_scenes += int(apart.sum())
        self.nudged_scenes += int(apart_nudged.sum())
        self.gpu_worst, self.nudged_worst = max(self.gpu_worst, worst), max(self.nudged_worst, worst_nudged)
        self.steps += 1
        self.batch = apart.shape[0]

    def check(self) -> None:
        report = (f"over {self.steps} steps of {self.batch} scenes: the GPU departed from the CPU in "
                  f"{self.gpu_scenes} scene-steps (largest gap {self.gpu_worst:.3g}), a one-ulp nudge on the CPU "
                  f"in {self.nudged_scenes} (largest gap {self.nudged_worst:.3g})")
        print(report)
        assert self.gpu_scenes <= 2 * self.nudged_scenes + 0.02 * self.batch * self.steps, report
        assert self.gpu_worst <= 10 * max(self.nudged_worst, 5e-5), report


def _on(device, fn, *args):
    """fn(*args) with its computations placed on `device` (arguments are copied there, committed)."""
    with jax.default_device(device):
        return jax.device_get(fn(*jax.device_put(args, device)))


# ---------------------------------------------------------------- physics accuracy tests, run on the GPU

def _physics_tests():
    from tests.jax2d import test_physics as p

    return [
        ("free_fall", p.test_free_fall_matches_symplectic_euler_and_half_g_t_squared, ()),
        ("pendulum", p.test_pendulum_period_and_amplitude, (0.25,)),
        ("bounce", p.test_restitution_bounce_height, (0.8, 0.0)),
        ("incline_slides", p.test_friction_on_incline_sticks_or_slides, (1.25,)),
        ("motor", p.test_motor_reaches_target_speed, (1.0,)),
        ("thruster", p.test_thruster_through_centre_gives_f_over_m, ()),
        ("pyramid", p.test_pyramid_stays_standing, ()),
        ("chain", p.test_chain_stretch, (True,)),
        ("welded_star", p.test_welded_star_spins_as_one_rigid_body, (0.4, 0.001, 0.01)),
        ("light_hub", p.test_light_hub_with_far_anchors_holds_together, ()),
        ("batch_in_parts", p.test_large_batches_stepped_in_parts_equal_one_pass, ()),
        ("vmap_equals_single", p.test_vmap_equals_separate_runs, ()),
    ]


@pytest.mark.parametrize("index", range(12), ids=[name for name, *_ in _physics_tests()] if GPU else None)
def test_physics_accuracy_on_the_gpu(index):
    """The tests/jax2d accuracy test, its computations placed on the GPU by jax.default_device."""
    _, test, args = _physics_tests()[index]
    probe = jax2d.jit(lambda x: x + 1)
    with jax.default_device(GPU):
        assert probe(np.float32(1)).devices() == {GPU}  # placed where we think
        test(*args)


def test_the_cpu_compile_options_do_not_reach_the_gpu():
    """Every CUDA compile failed on xla_cpu_use_fusion_emitters before jax2d.jit chose options per platform."""
    out = jax2d.jit(lambda x: x * 2)(jax.device_put(np.float32(2), GPU))
    assert float(out) == 4.0 and out.devices() == {GPU}


def _engine_rollout(batch: int, steps: int, config):
    from kinetix.bench import scenes

    states = scenes.build_batch("l", batch, seed=7)
    rng = np.random.default_rng(7)
    motor = rng.uniform(-1, 1, (steps, batch, states.num_joints)).astype(np.float32)
    thrust = rng.uniform(0, 1, (steps, batch, states.num_thrusters)).astype(np.float32)
    vstep = jax.vmap(lambda s, m, t: jax2d.step(s, jax2d.SimParams(), m, t, config=config))
    rollout = jax2d.jit(lambda s, m, t: jax.lax.scan(lambda s, a: (vstep(s, *a), None), s, (m, t))[0])
    return rollout, (states, motor, thrust)


def test_a_large_batch_on_the_gpu_agrees_with_the_cpu():
    """512 l scenes (more than SolverConfig.chunk: parts on the CPU, one pass on the GPU), 20 steps, each step
    taken on both from the same state (the GPU's trajectory), so a difference is one step's rounding, judged
    against the engine's own sensitivity to one-ulp changes (_Agreement).

    Not the two trajectories: rounding grows through the contacts of a crowded scene by orders of magnitude
    within a few steps (two CPU programs that differ only in fusion: 4e-8 m after 1 step, 5e-5 after 5, 6 cm
    after 60), and on an H200 the trajectories were 4.4 cm apart after 20 steps (26 Nov 2026). Nor every
    scene to rounding after one step: on an H200 one scene's first step was 0.03 apart (27 Nov 2026), as a
    one-ulp nudge on the CPU makes 0.09."""
    from kinetix.bench import scenes

    states, motor, thrust = _engine_rollout(512, 20, scenes.CONFIG)[1]
    vstep = jax.vmap(lambda s, m, t: jax2d.step(s, jax2d.SimParams(), m, t, config=scenes.CONFIG))
    one = jax2d.jit(vstep)
    start, agreement = states, _Agreement()
    for t in range(motor.shape[0]):
        gpu, cpu = _on(GPU, one, states, motor[t], thrust[t]), _on(CPU, one, states, motor[t], thrust[t])
        agreement.add(gpu, cpu, _on(CPU, one, _nudged(states, t), motor[t], thrust[t]))
        states = gpu
    agreement.check()
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(states) if np.asarray(x).dtype.kind == "f")
    assert float(np.abs(np.asarray(states.bodies.position) - np.asarray(start.bodies.position)).max()) > 1e-3


def test_gpu_reruns_are_bitwise_identical():
    """The same program on the same inputs twice. Holds on the CPU; on a GPU only if XLA's GPU kernels are
    deterministic (scatter-adds with atomics are not unless XLA_FLAGS=--xla_gpu_deterministic_ops=true)."""
    from kinetix.bench import scenes

    rollout, args = _engine_rollout(256, 20, scenes.CONFIG)
    first, second = _on(GPU, rollout, *args), _on(GPU, rollout, *args)
    for x, y in zip(jax.tree.leaves(first), jax.tree.leaves(second), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# ---------------------------------------------------------------- the environment, batched, on the GPU

def _env_rollout(batch: int, steps: int):
    from kinetix.actions import sample_random_action
    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.levels import load_level

    level_file = load_level("levels/cartpole.json")
    env = make_env(EnvConfig(size=level_file.size, observation="entity", action="multi_discrete",
                             frame_skip=level_file.params.frame_skip), level_file)
    params = EnvParams.from_level_params(level_file.params)

    def rollout(keys):
        obs, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

        def one(carry, _):
            keys, states, total = carry
            split = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
            actions = jax.vmap(lambda k: sample_random_action(k, env.config.action))(split[:, 1])
            obs, states, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                split[:, 2], states, actions, params)
            return (split[:, 0], states, total + reward), None

        (_, states, total), _ = jax.lax.scan(one, (keys, states, jnp.zeros(keys.shape[0])), None, length=steps)
        return states, total

    return jax2d.jit(rollout), jax.random.split(jax.random.PRNGKey(24), batch)


@functools.cache
def _env_results(batch: int = 1024, steps: int = 10):
    rollout, keys = _env_rollout(batch, steps)
    return _on(GPU, rollout, keys)


def test_a_batched_env_rollout_runs_on_the_gpu():
    states, total = _env_results()
    bodies = states.level.sim.bodies
    assert np.isfinite(np.asarray(bodies.position)).all() and np.isfinite(np.asarray(total)).all()
    assert np.asarray(bodies.position).shape[0] == 1024


def test_the_batched_env_steps_agree_with_the_cpu():
    """1,024 cartpole envs, 10 agent steps with random actions, each taken on both from the same state (the
    GPU's): the same states and rewards to one step's rounding, judged against the engine's own sensitivity to
    one-ulp changes (_Agreement: on an H200 one env's seventh step was 2.9 mm apart, 27 Nov 2026). The
    trajectories themselves drift apart as the contacts grow the rounding: 0.15 m after 10 steps on an H200
    (26 Nov 2026)."""
    import dataclasses

    from kinetix.actions import sample_random_action
    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.levels import load_level

    level_file = load_level("levels/cartpole.json")
    env = make_env(EnvConfig(size=level_file.size, observation="entity", action="multi_discrete",
                             frame_skip=level_file.params.frame_skip), level_file)
    params = EnvParams.from_level_params(level_file.params)
    batch = 1024
    keys = jax.random.split(jax.random.PRNGKey(24), batch)
    _, states = _on(GPU, jax2d.jit(jax.vmap(env.reset, in_axes=(0, None))), keys, params)
    step = jax2d.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    agreement, rewards = _Agreement(), _Agreement()
    for t in range(10):
        keys = jax.vmap(lambda k: jax.random.split(k, 3))(keys)
        actions = jax.vmap(lambda k: sample_random_action(k, env.config.action))(keys[:, 1])
        gpu = _on(GPU, step, keys[:, 2], states, actions, params)
        cpu = _on(CPU, step, keys[:, 2], states, actions, params)
        level = dataclasses.replace(states.level, sim=_nudged(states.level.sim, t))
        nudged = _on(CPU, step, keys[:, 2], dataclasses.replace(states, level=level), actions, params)
        agreement.add(gpu[1].level.sim, cpu[1].level.sim, nudged[1].level.sim)
        rewards.add(gpu[2:4], cpu[2:4], nudged[2:4])  # rewards and terminations
        states, keys = gpu[1], keys[:, 0]
    agreement.check()
    rewards.check()
