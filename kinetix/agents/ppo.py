"""PPO in the PureJaxRL style: the whole training loop is one jittable function.

    trainer = make_train(config, env, env_params, curriculum)
    out = jax2d.jit(trainer.train)(key)              # everything: rollouts, GAE, minibatch epochs, logging
    # or in chunks, for progress bars, checkpoints and cancellation (what `kinetix train` does):
    runner = trainer.init(key)
    runner, metrics = trainer.run(runner)          # `updates_per_call` updates, jitted once

One update: `num_steps` steps of `num_envs` environments in a lax.scan (vmapped env, auto-reset to a level
from the curriculum), GAE, then `update_epochs` epochs of `num_minibatches` minibatches of the clipped PPO loss
(a stratified shuffle, `shuffle_minibatches`). On the CPU the network runs over parts of 256 samples
(kinetix.agents.parts). Metrics go to `callback(metrics: dict)` through jax.debug.callback after every update
(host floats).

Truncation is not termination: the TD target of a transition is r + gamma * V(s') unless the episode
*terminated*; when it was *truncated* (time limit) s' is the last observation before the reset, whose value
the rollout computes for those rows alone (`bootstrap_value`; elsewhere V(s') is the next step's value), so time
limits do not look like failures to the critic.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax.training.train_state import TrainState

import jax2d
from kinetix.agents import distributions, parts
from kinetix.agents.curricula import Curriculum, Feedback
from kinetix.agents.networks import ActorCritic
from kinetix.agents.rollout import fresh_state
from kinetix.env import EnvParams, KinetixEnv


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    total_timesteps: int = 1_000_000
    num_envs: int = 32
    num_steps: int = 64  # rollout length per update
    update_epochs: int = 4
    num_minibatches: int = 4
    lr: float = 3e-4
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    network: str = "entity"
    width: int = 64
    hidden: int = 128
    updates_per_call: int = 4  # updates per jitted chunk in `run`

    def __post_init__(self):
        for name in ("total_timesteps", "num_envs", "num_steps", "update_epochs", "num_minibatches",
                     "updates_per_call"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if isinstance(self.lr, bool) or not isinstance(self.lr, int | float) or not 0 < self.lr < math.inf:
            raise ValueError(f"lr must be a positive finite number, got {self.lr!r}")
        if (self.num_envs * self.num_steps) % self.num_minibatches:
            raise ValueError(f"num_envs * num_steps ({self.num_envs * self.num_steps}) must be divisible by "
                             f"num_minibatches ({self.num_minibatches})")

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def num_updates(self) -> int:
        return max(1, math.ceil(self.total_timesteps / self.batch_size))

    @property
    def num_chunks(self) -> int:
        """Jitted chunks of `updates_per_call` updates that `kinetix train` runs (rounding the updates up)."""
        return math.ceil(self.num_updates / self.updates_per_call)

    @property
    def planned_steps(self) -> int:
        return self.num_chunks * self.updates_per_call * self.batch_size


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Transition:
    obs: Any
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array  # V(s)
    reward: jax.Array
    terminated: jax.Array  # won, lost or non-finite: no bootstrap
    done: jax.Array  # terminated or truncated: the episode ended here (GAE does not look past it)
    bootstrap_value: jax.Array  # V(s') of the true successor (the last observation before any reset)


def compute_gae(reward: jax.Array, value: jax.Array, bootstrap_value: jax.Array, terminated: jax.Array,
                done: jax.Array, gamma: float, lam: float) -> tuple[jax.Array, jax.Array]:
    """(advantages, returns) over time axis 0.

    delta_t = r_t + gamma * V(s'_t) * (1 - terminated_t) - V(s_t)
    A_t     = delta_t + gamma * lam * (1 - done_t) * A_{t+1}
    so a truncated step bootstraps from its own successor's value but does not chain into the next episode."""
    delta = reward + gamma * bootstrap_value * (1.0 - terminated) - value

    def back(carry, x):
        d, dn = x
        carry = d + gamma * lam * (1.0 - dn) * carry
        return carry, carry

    _, adv = jax.lax.scan(back, jnp.zeros_like(delta[0]), (delta, done.astype(delta.dtype)), reverse=True)
    return adv, adv + value


def make_network(config: TrainConfig, action_type: str) -> ActorCritic:
    return ActorCritic(network=config.network, action=action_type, width=config.width, hidden=config.hidden)


def normalise_advantages(advantages: jax.Array) -> jax.Array:
    """Zero mean and unit spread over a minibatch (the PPO convention), before the loss sees any part of it."""
    return (advantages - advantages.mean()) / (advantages.std() + 1e-8)


def ppo_loss(network: nn.Module, action_type: str, config: TrainConfig, params, batch: Transition,
             advantages: jax.Array, targets: jax.Array):
    """The clipped PPO loss, a mean over the samples of `batch` (so parts of a minibatch average to the whole's).
    `advantages` are already normalised over the whole minibatch (normalise_advantages)."""
    outputs, value = network.apply({"params": params}, batch.obs)
    log_prob = distributions.log_prob(outputs, batch.action, action_type)
    value_clipped = batch.value + jnp.clip(value - batch.value, -config.clip_eps, config.clip_eps)
    value_loss = 0.5 * jnp.maximum((value - targets) ** 2, (value_clipped - targets) ** 2).mean()
    ratio = jnp.exp(log_prob - batch.log_prob)
    clipped_ratio = jnp.clip(ratio, 1 - config.clip_eps, 1 + config.clip_eps)
    actor_loss = -jnp.minimum(ratio * advantages, clipped_ratio * advantages).mean()
    entropy = distributions.entropy(outputs, action_type).mean()
    total = actor_loss + config.vf_coef * value_loss - config.ent_coef * entropy
    return total, {"value_loss": value_loss, "actor_loss": actor_loss, "entropy": entropy}


SHUFFLE_BLOCKS = 8  # env blocks the minibatch shuffle draws evenly from (see shuffle_minibatches)


def shuffle_blocks(config: TrainConfig) -> int:
    """The largest divisor of SHUFFLE_BLOCKS that splits the envs and every minibatch evenly."""
    blocks = SHUFFLE_BLOCKS
    while config.num_envs % blocks or config.batch_size % (blocks * config.num_minibatches):
        blocks //= 2
    return blocks


def shuffle_minibatches(tree: Any, key: jax.Array, config: TrainConfig) -> Any:
    """(T, E, ...) leaves -> (num_minibatches, minibatch, ...): every sample once, in a random order.

    The envs are cut into `shuffle_blocks` blocks of consecutive envs; each block's samples are permuted within the
    block and every minibatch takes the same number from each block (a stratified shuffle). When the env axis is
    split over devices (kinetix.agents.sharding), whole blocks sit on one device and the shuffle moves no data
    between devices; a permutation of the whole batch made XLA gather it onto every device (training on 2 CPU
    devices ran at half the speed of one). The blocks do not depend on the device count, so one device and several
    draw the same minibatches."""
    blocks, minibatches = shuffle_blocks(config), config.num_minibatches
    per_block = config.batch_size // blocks
    orders = jax.vmap(lambda k: jax.random.permutation(k, per_block))(jax.random.split(key, blocks))

    def one(x):
        rest = x.shape[2:]
        x = jnp.swapaxes(x, 0, 1).reshape((blocks, per_block) + rest)  # env-major: an env's steps stay together
        x = jax.vmap(lambda block, order: block[order])(x, orders)
        x = x.reshape((blocks, minibatches, per_block // minibatches) + rest)
        return jnp.swapaxes(x, 0, 1).reshape((minibatches, config.batch_size // minibatches) + rest)

    return jax.tree.map(one, tree)


def ppo_update(network: nn.Module, action_type: str, config: TrainConfig, train_state: TrainState,
               batch: Transition, advantages: jax.Array, targets: jax.Array, key: jax.Array):
    """`update_epochs` epochs of minibatch SGD on one rollout (leading axes (T, E)). Returns (state, mean losses).

    Pure: under a mesh the batch may be sharded over its env axis and XLA inserts the gradient all-reduce."""
    loss = lambda p, mb: ppo_loss(network, action_type, config, p, *mb)

    def epoch(state, epoch_key):
        def minibatch(state, mb):
            mb_batch, mb_advantages, mb_targets = mb
            aux, grads = parts.mean_grad(loss, state.params,
                                         (mb_batch, normalise_advantages(mb_advantages), mb_targets))
            return state.apply_gradients(grads=grads), aux

        return jax.lax.scan(minibatch, state, shuffle_minibatches((batch, advantages, targets), epoch_key, config))

    train_state, aux = jax.lax.scan(epoch, train_state, jax.random.split(key, config.update_epochs))
    return train_state, jax.tree.map(jnp.mean, aux)


def rebase_schedule(train_state: TrainState, config: TrainConfig, update: int) -> TrainState:
    """`train_state` with its learning-rate schedule's step count set to `update` updates of `config`'s gradient
    steps (epochs x minibatches each).

    The annealed rate is lr * (1 - count / (updates x epochs x minibatches)) with count the gradient steps taken.
    A run resumed with another epoch or minibatch count would otherwise jump along that line (8x more minibatches:
    the count covers 1/8 of the new total); re-based, the rate stays lr * (1 - update / updates), the plan's rate at
    the same update. Unchanged settings give the count it already holds, so an exact resume stays exact. Adam's own
    count (its bias correction) is the optimiser's history and is left alone."""
    steps = update * config.update_epochs * config.num_minibatches

    def rebase(node):
        if isinstance(node, optax.ScaleByScheduleState):  # count * 0 + steps keeps the leaf's dtype and placement
            return node._replace(count=node.count * 0 + steps)
        return node

    is_schedule = lambda node: isinstance(node, optax.ScaleByScheduleState)
    return train_state.replace(opt_state=jax.tree.map(rebase, train_state.opt_state, is_leaf=is_schedule))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Runner:
    """Everything the training loop carries between updates."""

    train_state: TrainState
    env_state: Any  # batched EnvState
    obs: Any
    episode_return: jax.Array
    env_level_ids: jax.Array
    env_levels: Any  # initial scene of each env's current level (for plr)
    curriculum: Any
    env_params: EnvParams  # an argument of the compiled update, not a constant: one program serves many levels
    key: jax.Array
    update_index: jax.Array


@dataclasses.dataclass(frozen=True)
class Trainer:
    config: TrainConfig
    network: ActorCritic
    init: Callable[[jax.Array], Runner]
    update: Callable[[Runner], tuple[Runner, dict]]  # one update (jittable)
    run: Callable[[Runner], tuple[Runner, dict]]  # `updates_per_call` updates, jitted; metrics stacked
    train: Callable[[jax.Array], dict]  # the whole run, jittable: {"runner": Runner, "metrics": stacked}


TRUNCATED_ROWS = 1 / 16  # share of the env batch whose truncated successor values one gathered pass computes


def _values_where(value_fn: Callable[[Any], jax.Array], obs: Any, wanted: jax.Array) -> jax.Array:
    """value_fn(obs) on the rows where `wanted`, 0 elsewhere.

    Few rows are wanted in a step (an episode reaches its time limit once in hundreds of steps), so on the CPU the
    first TRUNCATED_ROWS of the batch that are wanted are gathered and evaluated alone, and all rows only when more
    are wanted (lax.cond: envs that started together can time out together). On a GPU, where a data-dependent
    branch costs a round trip to the host and the pass costs little, every row is evaluated."""
    batch = wanted.shape[0]
    capacity = max(1, int(batch * TRUNCATED_ROWS))

    def every_row(obs, wanted):
        return jnp.where(wanted, value_fn(obs), 0.0)

    if capacity >= batch:
        return every_row(obs, wanted)

    def gathered(obs, wanted):
        rows = jnp.nonzero(wanted, size=capacity, fill_value=batch)[0]  # batch: past the end, dropped below
        values = value_fn(jax.tree.map(lambda x: x.at[rows].get(mode="clip"), obs))
        return jnp.zeros((batch,), values.dtype).at[rows].set(values, mode="drop")

    def on_cpu(obs, wanted):
        return jax.lax.cond(wanted.sum() <= capacity, gathered, every_row, obs, wanted)

    return parts.by_platform(on_cpu, every_row, obs, wanted)


def _batch_where(pred, a, b):
    return jax.tree.map(lambda x, y: jnp.where(pred.reshape(pred.shape + (1,) * (x.ndim - 1)), x, y), a, b)


def make_train(config: TrainConfig, env: KinetixEnv, env_params: EnvParams, curriculum: Curriculum,
               callback: Callable[[dict], None] | None = None, init_params: Any = None,
               shard: Callable[[Any], Any] | None = None) -> Trainer:
    """A PPO trainer. `init_params`: start from these network parameters (fine-tuning) instead of fresh ones.
    `shard(tree) -> tree` places env-batched arrays (leading axis num_envs) on devices (see kinetix.agents.sharding);
    None keeps everything on the default device."""
    action_type = env.config.action
    network = make_network(config, action_type)
    E, T = config.num_envs, config.num_steps
    schedule = (optax.linear_schedule(config.lr, 0.0, config.num_updates * config.update_epochs
                                      * config.num_minibatches) if config.anneal_lr else config.lr)
    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(schedule, eps=1e-5))
    observe = jax.vmap(env.observe)
    transition = jax.vmap(env.transition, in_axes=(0, 0, None))
    if shard is not None:  # each device steps its own environments: no all-reduce inside the physics
        from kinetix.devices import per_device

        transition = per_device(transition, E, in_axes=(0, 0, None))
    place = shard or (lambda tree: tree)

    def init(key: jax.Array) -> Runner:
        k_net, k_cur, k_pool, k_run = jax.random.split(key, 4)
        cstate = curriculum.init(k_cur)
        levels, ids = curriculum.sample(k_pool, cstate, E)
        state = jax.vmap(fresh_state)(levels)
        obs = observe(state)
        params = init_params
        if params is None:
            params = network.init(k_net, jax.tree.map(lambda x: x[:1], obs))["params"]
        train_state = TrainState.create(apply_fn=network.apply, params=params, tx=tx)
        return Runner(train_state, place(state), place(obs), place(jnp.zeros((E,), jnp.float32)), place(ids),
                      place(levels), cstate, jax.tree.map(jnp.asarray, env_params), k_run, jnp.asarray(0, jnp.int32))

    def update(runner: Runner) -> tuple[Runner, dict]:
        key, k_pool, k_roll, k_upd, k_cur = jax.random.split(runner.key, 5)
        pool_levels, pool_ids = curriculum.sample(k_pool, runner.curriculum, E)
        pool_levels, pool_ids = place(pool_levels), place(pool_ids)
        pool_state = jax.vmap(fresh_state)(pool_levels)
        pool_obs = observe(pool_state)  # observed once per update, not once per step
        params = runner.train_state.params
        apply = lambda obs: network.apply({"params": params}, obs)

        def env_step(carry, step_key):
            state, obs, ep_return, ids, levels = carry
            k_act, _ = jax.random.split(step_key)
            outputs, value = parts.forward(apply, obs)
            action = distributions.sample(k_act, outputs, action_type)
            log_prob = distributions.log_prob(outputs, action, action_type)
            next_state, reward, terminated, truncated, info = transition(state, action, runner.env_params)
            final_obs = observe(next_state)
            # V(s') is needed only where a time limit cut the episode: elsewhere s' is the next step's observation,
            # whose value the next step computes (or a terminal state: no bootstrap)
            truncated_value = _values_where(lambda o: parts.forward(apply, o)[1], final_obs, truncated & ~terminated)
            done = terminated | truncated
            step_ids = ids
            ep_return = ep_return + reward
            metrics = {"return": jnp.where(done, ep_return, 0.0), "solved": done & info["solved"], "done": done}
            carry = (_batch_where(done, pool_state, next_state), _batch_where(done, pool_obs, final_obs),
                     jnp.where(done, 0.0, ep_return), jnp.where(done, pool_ids, ids),
                     _batch_where(done, pool_levels, levels))
            t = Transition(obs, action, log_prob, value, reward, terminated.astype(jnp.float32),
                           done.astype(jnp.float32), truncated_value)
            return carry, (t, step_ids, metrics)

        carry = (runner.env_state, runner.obs, runner.episode_return, runner.env_level_ids, runner.env_levels)
        carry, (batch, step_ids, ep) = jax.lax.scan(env_step, carry, jax.random.split(k_roll, T))
        env_state, obs, ep_return, env_ids, env_levels = carry
        # the successor of step t is step t + 1's observation unless the episode ended at t
        next_value = jnp.concatenate([batch.value[1:], parts.forward(apply, obs)[1][None]])
        ended_by_limit = (batch.done > 0) & (batch.terminated == 0)
        batch = dataclasses.replace(batch, bootstrap_value=jnp.where(ended_by_limit, batch.bootstrap_value,
                                                                     next_value))
        advantages, targets = compute_gae(batch.reward, batch.value, batch.bootstrap_value, batch.terminated,
                                          batch.done, config.gamma, config.gae_lambda)
        train_state, losses = ppo_update(network, action_type, config, runner.train_state, batch, advantages,
                                         targets, k_upd)
        feedback = Feedback(train_state.params, step_ids, advantages, env_ids, env_levels, runner.update_index)
        cstate, env_ids = curriculum.update(k_cur, runner.curriculum, feedback)
        episodes = ep["done"].sum()
        metrics = dict(losses, update=runner.update_index + 1, env_steps=(runner.update_index + 1) * E * T,
                       episodes=episodes, mean_return=ep["return"].sum() / jnp.maximum(episodes, 1),
                       solve_rate=ep["solved"].sum() / jnp.maximum(episodes, 1),
                       mean_reward=batch.reward.mean())
        if callback is not None:
            # unordered: ordered effects are not supported across several devices; metrics carry their "update"
            jax.debug.callback(lambda m: callback({k: float(v) for k, v in m.items()}), metrics)
        runner = Runner(train_state, env_state, obs, ep_return, env_ids, env_levels, cstate, runner.env_params, key,
                        runner.update_index + 1)
        return runner, metrics

    def run_chunk(runner: Runner, length: int):
        return jax.lax.scan(lambda r, _: update(r), runner, None, length=length)

    run = jax2d.jit(lambda runner: run_chunk(runner, config.updates_per_call), donate_argnums=0)

    def train(key: jax.Array) -> dict:
        runner, metrics = run_chunk(init(key), config.num_updates)
        return {"runner": runner, "metrics": metrics}

    return Trainer(config, network, init, update, run, train)
