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
from kinetix.agents.networks import ActorCritic, check_activation, dead_share
from kinetix.agents.rollout import fresh_state
from kinetix.env import EnvParams, KinetixEnv


def _real(value: Any) -> bool:
    """A real number as a setting: an int or float, not a bool (True would pass as 1)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


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
    activation: str = "tanh"  # of the hidden layers: tanh or relu (kinetix.agents.networks says why tanh)
    pooled_norm: bool = True  # entity network: LayerNorm on the pooled summary (kinetix.agents.networks says why)

    def __post_init__(self):
        for name in ("total_timesteps", "num_envs", "num_steps", "update_epochs", "num_minibatches",
                     "updates_per_call"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not (_real(self.lr) and 0 < self.lr < math.inf):
            raise ValueError(f"lr must be a positive finite number, got {self.lr!r}")
        if not (_real(self.ent_coef) and 0 <= self.ent_coef < math.inf):
            raise ValueError(f"ent_coef must be a finite number >= 0, got {self.ent_coef!r}")
        if not (_real(self.gamma) and 0 < self.gamma <= 1):
            raise ValueError(f"gamma must be a number with 0 < gamma <= 1, got {self.gamma!r}")
        if not (_real(self.gae_lambda) and 0 <= self.gae_lambda <= 1):
            raise ValueError(f"gae_lambda must be a number with 0 <= gae_lambda <= 1, got {self.gae_lambda!r}")
        check_activation(self.activation)
        if not isinstance(self.pooled_norm, bool):
            raise ValueError(f"pooled_norm must be true or false, got {self.pooled_norm!r}")
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


LEGACY_ACTIVATION = "relu"  # the activation of every network saved before TrainConfig had the field
# what every network saved before TrainConfig had a field was built with, where that differs from today's default
LEGACY_FIELDS = {"activation": LEGACY_ACTIVATION, "pooled_norm": False}


def saved_config_fields(fields: dict) -> dict:
    """TrainConfig fields as a checkpoint or a run's state recorded them, with the architecture of their time filled
    in where they predate a field (so an old relu agent loads as relu, not as the tanh default, and one without a
    pooled LayerNorm loads without one)."""
    return {**LEGACY_FIELDS, **fields}


# the TrainConfig fields that shape the network (ActorCritic's fields of the same names): what a checkpoint fixes
ARCHITECTURE = ("network", "width", "hidden", "activation", "pooled_norm")


def make_network(config: TrainConfig, action_type: str) -> ActorCritic:
    return ActorCritic(action=action_type, **{field: getattr(config, field) for field in ARCHITECTURE})


def normalise_advantages(advantages: jax.Array) -> jax.Array:
    """Zero mean and unit spread over a minibatch (the PPO convention), before the loss sees any part of it."""
    return (advantages - advantages.mean()) / (advantages.std() + 1e-8)


def ppo_loss(network: nn.Module, action_type: str, config: TrainConfig, params, batch: Transition,
             advantages: jax.Array, targets: jax.Array):
    """The clipped PPO loss, a mean over the samples of `batch` (so parts of a minibatch average to the whole's).
    `advantages` are already normalised over the whole minibatch (normalise_advantages). Besides the losses, aux
    reports the heads' health: actor_dead / critic_dead, the share of dead units in the head's most dead hidden
    layer on this (part of a) minibatch (networks.dead_share), 1.0 once a head no longer sees its input; and how far
    the policy has moved from the one that collected the batch: approx_kl, the estimator mean((r - 1) - log r) of
    KL(old || new) with r the probability ratio (never negative, unlike mean(-log r)), and clip_frac, the share of
    samples whose ratio is outside the clip range. Both grow with the step size: they are what to read when the
    learning rate is in question."""
    (outputs, value), sown = network.apply({"params": params}, batch.obs, mutable=["intermediates"])
    dead = {f"{head}_dead": dead_share(sown["intermediates"], config.activation, head) for head in ("actor", "critic")}
    log_prob = distributions.log_prob(outputs, batch.action, action_type)
    value_clipped = batch.value + jnp.clip(value - batch.value, -config.clip_eps, config.clip_eps)
    value_loss = 0.5 * jnp.maximum((value - targets) ** 2, (value_clipped - targets) ** 2).mean()
    ratio = jnp.exp(log_prob - batch.log_prob)
    clipped_ratio = jnp.clip(ratio, 1 - config.clip_eps, 1 + config.clip_eps)
    actor_loss = -jnp.minimum(ratio * advantages, clipped_ratio * advantages).mean()
    entropy = distributions.entropy(outputs, action_type).mean()
    total = actor_loss + config.vf_coef * value_loss - config.ent_coef * entropy
    moved = jax.lax.stop_gradient(log_prob - batch.log_prob)
    drift = {"approx_kl": (jnp.expm1(moved) - moved).mean(),
             "clip_frac": (jnp.abs(ratio - 1) > config.clip_eps).astype(jnp.float32).mean()}
    return total, {"value_loss": value_loss, "actor_loss": actor_loss, "entropy": entropy, **dead, **drift}


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
               batch: Transition, advantages: jax.Array, targets: jax.Array, key: jax.Array,
               group_configs: tuple[TrainConfig, ...] | None = None):
    """`update_epochs` epochs of minibatch SGD on one rollout (leading axes (T, E)). Returns (state, mean losses).

    group_configs: with env groups (make_train's `groups`), `batch`, `advantages` and `targets` are tuples, one per
    group (leading axes (T, E_g)), and group_configs their TrainConfigs (num_envs E_g). Each group's samples are
    shuffled into `num_minibatches` minibatches on their own; minibatch i is every group's part i, its advantages
    normalised over all of them, its loss the sample-weighted mean of the groups' (a group's observations have its
    own shapes, so the network runs over each part alone).

    Pure: under a mesh the batch may be sharded over its env axis and XLA inserts the gradient all-reduce."""
    loss = lambda p, mb: ppo_loss(network, action_type, config, p, *mb)

    if group_configs is None:
        def epoch(state, epoch_key):
            def minibatch(state, mb):
                mb_batch, mb_advantages, mb_targets = mb
                aux, grads = parts.mean_grad(loss, state.params,
                                             (mb_batch, normalise_advantages(mb_advantages), mb_targets))
                return state.apply_gradients(grads=grads), aux

            return jax.lax.scan(minibatch, state, shuffle_minibatches((batch, advantages, targets), epoch_key,
                                                                      config))
    else:
        weights = [c.batch_size / config.batch_size for c in group_configs]

        def epoch(state, epoch_key):
            def minibatch(state, mbs):
                every = jnp.concatenate([mb[1] for mb in mbs])
                mean, spread = every.mean(), every.std() + 1e-8
                aux = grads = None
                for weight, (mb_batch, mb_advantages, mb_targets) in zip(weights, mbs, strict=True):
                    part = parts.mean_grad(loss, state.params, (mb_batch, (mb_advantages - mean) / spread, mb_targets))
                    part = jax.tree.map(lambda x, w=weight: w * x, part)
                    aux, grads = part if grads is None else jax.tree.map(jnp.add, (aux, grads), part)
                return state.apply_gradients(grads=grads), aux

            mbs = tuple(shuffle_minibatches(group, jax.random.fold_in(epoch_key, g), c)
                        for g, (group, c) in enumerate(zip(zip(batch, advantages, targets, strict=True),
                                                           group_configs, strict=True)))
            return jax.lax.scan(minibatch, state, mbs)

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
    """Everything the training loop carries between updates. With env groups (make_train's `groups`) the
    per-environment fields (env_state to env_levels) and the curriculum state are tuples, one entry per group."""

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


@dataclasses.dataclass(frozen=True)
class EnvGroup:
    """Environments that step together at one size class: `num_envs` of them on `env`, their levels from
    `curriculum`. `shard(tree)` places arrays whose leading axis is num_envs (kinetix.agents.sharding), None keeps
    them on the default device; `name` labels the group's metrics (solve_rate_NAME)."""

    name: str
    env: KinetixEnv
    curriculum: Curriculum
    num_envs: int
    shard: Callable[[Any], Any] | None = None


def make_train(config: TrainConfig, env: KinetixEnv, env_params: EnvParams, curriculum: Curriculum,
               callback: Callable[[dict], None] | None = None, init_params: Any = None,
               shard: Callable[[Any], Any] | None = None, groups: tuple[EnvGroup, ...] | None = None) -> Trainer:
    """A PPO trainer. `init_params`: start from these network parameters (fine-tuning) instead of fresh ones.
    `shard(tree) -> tree` places env-batched arrays (leading axis num_envs) on devices (see kinetix.agents.sharding);
    None keeps everything on the default device.

    groups: instead of `env`, `curriculum` and `shard`, several groups of environments, each stepping its own
    levels at its own size class (random levels of all sizes: an s level then costs the physics of s, not of l
    padding; kinetix.agents.train). Their num_envs add up to config.num_envs; the network is one (entity
    observations: it plays every size); each group rolls out, and its episodes start from its own curriculum."""
    action_type = env.config.action
    network = make_network(config, action_type)
    T = config.num_steps
    single = groups is None
    if single:
        groups = (EnvGroup("", env, curriculum, config.num_envs, shard),)
    if sum(g.num_envs for g in groups) != config.num_envs:
        raise ValueError(f"the env groups hold {sum(g.num_envs for g in groups)} environments, num_envs is "
                         f"{config.num_envs}")
    group_configs = tuple(dataclasses.replace(config, num_envs=g.num_envs) for g in groups)
    schedule = (optax.linear_schedule(config.lr, 0.0, config.num_updates * config.update_epochs
                                      * config.num_minibatches) if config.anneal_lr else config.lr)
    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(schedule, eps=1e-5))
    observes = [jax.vmap(g.env.observe) for g in groups]
    transitions = []
    for g in groups:
        transition = jax.vmap(g.env.transition, in_axes=(0, 0, None))
        if g.shard is not None:  # each device steps its own environments: no all-reduce inside the physics
            from kinetix.devices import per_device

            transition = per_device(transition, g.num_envs, in_axes=(0, 0, None))
        transitions.append(transition)
    places = [g.shard or (lambda tree: tree) for g in groups]
    # one group keeps the Runner's fields plain (and its random keys those of a run without groups), so training
    # states saved before groups existed still load
    pack = (lambda values: values[0]) if single else tuple
    unpack = (lambda field: (field,)) if single else tuple
    key_of = (lambda key, g: key) if single else jax.random.fold_in

    def init(key: jax.Array) -> Runner:
        k_net, k_cur, k_pool, k_run = jax.random.split(key, 4)
        fields = []
        for g, group in enumerate(groups):
            cstate = group.curriculum.init(key_of(k_cur, g))
            levels, ids = group.curriculum.sample(key_of(k_pool, g), cstate, group.num_envs)
            state = jax.vmap(fresh_state)(levels)
            place = places[g]
            fields.append((place(state), place(observes[g](state)), place(jnp.zeros((group.num_envs,), jnp.float32)),
                           place(ids), place(levels), cstate))
        params = init_params
        if params is None:
            params = network.init(k_net, jax.tree.map(lambda x: x[:1], fields[-1][1]))["params"]
        train_state = TrainState.create(apply_fn=network.apply, params=params, tx=tx)
        return Runner(train_state, *(pack(column) for column in zip(*fields, strict=True)),
                      jax.tree.map(jnp.asarray, env_params), k_run, jnp.asarray(0, jnp.int32))

    def rollout(g: int, runner: Runner, carry: tuple, cstate: Any, k_pool: jax.Array, k_roll: jax.Array):
        """Group g's `num_steps` steps: (carry after them, Transition (T, E_g), level ids per step, episode ends)."""
        group, observe, transition, place = groups[g], observes[g], transitions[g], places[g]
        pool_levels, pool_ids = group.curriculum.sample(k_pool, cstate, group.num_envs)
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

        carry, (batch, step_ids, ep) = jax.lax.scan(env_step, carry, jax.random.split(k_roll, T))
        # the successor of step t is step t + 1's observation unless the episode ended at t
        next_value = jnp.concatenate([batch.value[1:], parts.forward(apply, carry[1])[1][None]])
        ended_by_limit = (batch.done > 0) & (batch.terminated == 0)
        batch = dataclasses.replace(batch, bootstrap_value=jnp.where(ended_by_limit, batch.bootstrap_value,
                                                                     next_value))
        return carry, batch, step_ids, ep

    def update(runner: Runner) -> tuple[Runner, dict]:
        key, k_pool, k_roll, k_upd, k_cur = jax.random.split(runner.key, 5)
        columns = [unpack(f) for f in (runner.env_state, runner.obs, runner.episode_return, runner.env_level_ids,
                                       runner.env_levels)]
        cstates = unpack(runner.curriculum)
        carries, batches, step_ids, eps, advantages, targets = [], [], [], [], [], []
        for g in range(len(groups)):
            carry, batch, ids, ep = rollout(g, runner, tuple(column[g] for column in columns), cstates[g],
                                            key_of(k_pool, g), key_of(k_roll, g))
            adv, target = compute_gae(batch.reward, batch.value, batch.bootstrap_value, batch.terminated,
                                      batch.done, config.gamma, config.gae_lambda)
            for bucket, value in zip((carries, batches, step_ids, eps, advantages, targets),
                                     (carry, batch, ids, ep, adv, target), strict=True):
                bucket.append(value)
        if single:
            train_state, losses = ppo_update(network, action_type, config, runner.train_state, batches[0],
                                             advantages[0], targets[0], k_upd)
        else:
            train_state, losses = ppo_update(network, action_type, config, runner.train_state, tuple(batches),
                                             tuple(advantages), tuple(targets), k_upd, group_configs)
        new_cstates, env_ids = [], []
        for g, group in enumerate(groups):
            _, _, _, ids_now, levels_now = carries[g]
            feedback = Feedback(train_state.params, step_ids[g], advantages[g], ids_now, levels_now,
                                runner.update_index)
            cstate, ids_now = group.curriculum.update(key_of(k_cur, g), cstates[g], feedback)
            new_cstates.append(cstate)
            env_ids.append(ids_now)
        episodes = sum(ep["done"].sum() for ep in eps)
        steps = (runner.update_index + 1) * config.num_envs * T
        metrics = dict(losses, update=runner.update_index + 1, env_steps=steps,
                       episodes=episodes, mean_return=sum(ep["return"].sum() for ep in eps) / jnp.maximum(episodes, 1),
                       solve_rate=sum(ep["solved"].sum() for ep in eps) / jnp.maximum(episodes, 1),
                       mean_reward=(batches[0].reward.mean() if single else
                                    sum(b.reward.sum() for b in batches) / (T * config.num_envs)))
        if not single:  # each size class's own solve rate
            for group, ep in zip(groups, eps, strict=True):
                metrics[f"solve_rate_{group.name}"] = ep["solved"].sum() / jnp.maximum(ep["done"].sum(), 1)
        if callback is not None:
            # unordered: ordered effects are not supported across several devices; metrics carry their "update"
            jax.debug.callback(lambda m: callback({k: float(v) for k, v in m.items()}), metrics)
        state, obs, ep_return, _, levels = zip(*carries, strict=True)
        runner = Runner(train_state, pack(state), pack(obs), pack(ep_return), pack(env_ids), pack(levels),
                        pack(new_cstates), runner.env_params, key, runner.update_index + 1)
        return runner, metrics

    def run_chunk(runner: Runner, length: int):
        return jax.lax.scan(lambda r, _: update(r), runner, None, length=length)

    run = jax2d.jit(lambda runner: run_chunk(runner, config.updates_per_call), donate_argnums=0)

    def train(key: jax.Array) -> dict:
        runner, metrics = run_chunk(init(key), config.num_updates)
        return {"runner": runner, "metrics": metrics}

    return Trainer(config, network, init, update, run, train)
