"""Where one PPO update's time goes: `python -m kinetix.agents.profile [SIZE] [NUM_ENVS] [NUM_STEPS]`.

Times, each jitted alone on the default device (the minimum of 3 runs after a compile), with the trainer of
`kinetix bench train` (random levels of SIZE, dr):
- env: NUM_STEPS steps of the vmapped env (transition + observation) with random actions: the physics' share;
- network forward: the actor-critic on the NUM_ENVS observations, NUM_STEPS times (the rollout's policy passes);
- curriculum: drawing and observing the levels the envs reset to (once per update);
- ppo_update: the epochs of minibatch gradient steps on one rollout's batch;
- update: the whole update as training runs it (rollout, GAE, ppo_update, curriculum, metrics).
The rollout's own overhead (sampling actions, resets, bookkeeping) is what `update` has beyond the parts.
Prints numbers only. docs/agents.md ("Where an update's time goes") has the measured table.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp

import jax2d
from kinetix.agents import curricula, distributions
from kinetix.agents.ppo import TrainConfig, Transition, make_train, ppo_update
from kinetix.agents.rollout import fresh_state
from kinetix.agents.train import RANDOM_DENSE_REWARD
from kinetix.env import EnvConfig, EnvParams, make_env
from kinetix.level import WALLS_SOLVER, size_class


def _best_of(fn: Callable, *args, runs: int = 3) -> tuple[float, float]:
    """(seconds of the fastest of `runs` calls, seconds of the first call, compiling included)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best = float("inf")
    for _ in range(runs):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return best, first


def profile(size: str = "s", num_envs: int = 512, num_steps: int = 64) -> dict[str, float]:
    from kinetix.generate import sample_level

    E, T = num_envs, num_steps
    sc = size_class(size)
    generator = lambda key: sample_level(key, sc)
    env = make_env(EnvConfig(sc, solver=WALLS_SOLVER), generator)
    params = EnvParams(dense_reward_scale=RANDOM_DENSE_REWARD)
    config = TrainConfig(num_envs=E, num_steps=T, updates_per_call=1, total_timesteps=E * T * 8)
    curriculum = curricula.domain_randomisation(generator)
    trainer = make_train(config, env, params, curriculum)
    runner = jax2d.jit(trainer.init)(jax.random.key(0))
    network, action_type = trainer.network, env.config.action
    observe = jax.vmap(env.observe)
    transition = jax.vmap(env.transition, in_axes=(0, 0, None))
    no_logits = jnp.zeros((E, 16))

    @jax2d.jit
    def env_only(state, key):
        def one(state, k):
            state, reward, *_ = transition(state, distributions.sample(k, no_logits, action_type), params)
            return state, reward.sum() + jax.tree.leaves(observe(state))[0].sum()

        return jax.lax.scan(one, state, jax.random.split(key, T))[1]

    @jax2d.jit
    def forward_only(net_params, obs):
        def one(total, _):  # the carry enters the input, so the T passes are not folded into one
            outputs, value = network.apply({"params": net_params}, jax.tree.map(lambda x: x + total * 0, obs))
            return total + value.mean() + outputs.mean(), None

        return jax.lax.scan(one, jnp.zeros(()), None, length=T)[0]

    @jax2d.jit
    def reset_levels(key):
        levels, _ = curriculum.sample(key, runner.curriculum, E)
        return observe(jax.vmap(fresh_state)(levels))

    batch = Transition(jax.tree.map(lambda x: jnp.broadcast_to(x, (T,) + x.shape), runner.obs),
                       jnp.zeros((T, E, 6), jnp.int32), *(jnp.zeros((T, E)) for _ in range(6)))
    update_only = jax2d.jit(lambda ts, b, k: ppo_update(network, action_type, config, ts, b, jnp.ones((T, E)),
                                                        jnp.ones((T, E)), k)[1])
    whole = jax2d.jit(lambda r: trainer.update(r)[1])
    results = {}
    for name, fn, args in (("env", env_only, (runner.env_state, jax.random.key(1))),
                           ("network forward", forward_only, (runner.train_state.params, runner.obs)),
                           ("curriculum", reset_levels, (jax.random.key(2),)),
                           ("ppo_update", update_only, (runner.train_state, batch, jax.random.key(3))),
                           ("update", whole, (runner,))):
        seconds, first = _best_of(fn, *args)
        results[name] = seconds
        print(f"{name:16s} {seconds * 1e3:9.1f} ms   ({E * T / seconds:9.0f} env steps/s; first call {first:.1f} s)",
              flush=True)
    rest = results["update"] - results["env"] - results["network forward"] - results["ppo_update"]
    print(f"{'rollout rest':16s} {rest * 1e3:9.1f} ms   (update - env - network forward - ppo_update)", flush=True)
    return results


if __name__ == "__main__":
    arguments = sys.argv[1:]
    profile(arguments[0] if arguments else "s", *(int(a) for a in arguments[1:3]))
