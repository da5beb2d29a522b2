"""Where training episodes start: fixed levels or a curriculum over random levels. All pure and jittable.

Every curriculum has the same three functions (state is a pytree carried inside the jitted training loop):

    init(key) -> state
    sample(key, state, n) -> (levels (n, ...), ids (n,) int32)
        the levels that environments which finish an episode during the next rollout reset to; ids name a
        buffer slot (>= 0) or a fresh level (-1)
    update(key, state, feedback: Feedback) -> (state, env_ids (num_envs,) int32)
        after each PPO update; env_ids is the new id of the level each environment is playing (buffers move)

    fixed  one level or a list (reset uniformly); nothing to update
    dr     domain randomisation: a fresh random level from kinetix.generate for every episode
    sfl    sampling for learnability: every `refresh_every` updates, roll out the current policy `attempts`
           times on `candidates` fresh random levels, score each by p (1 - p) with p its solve rate, and keep the
           top `buffer_size`; episodes start from the buffer with probability `replay_prob`, else from a fresh level
    plr    prioritized level replay: a buffer of `buffer_size` levels ranked by score, the mean positive
           advantage (positive value loss) of the steps played on them; episodes replay a level with probability
           `replay_prob` (rank-prioritised, temperature `temperature`), else play a fresh level, which enters the
           buffer if it scores above the buffer's lowest
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from kinetix.level import Level

CURRICULA = ("dr", "sfl", "plr")
NEG = -1e9  # score of an empty buffer slot


@dataclasses.dataclass(frozen=True)
class CurriculumConfig:
    """Defaults sized for a 2-core machine: an sfl refresh rolls out candidates * attempts whole episodes
    (128 * 4 * 256 steps, about one update's worth of env steps per 50 updates of 2048)."""

    buffer_size: int = 64
    replay_prob: float = 0.8
    # sfl
    candidates: int = 128
    attempts: int = 4
    refresh_every: int = 50
    # plr
    temperature: float = 0.3

    def __post_init__(self):
        for name in ("buffer_size", "candidates", "attempts", "refresh_every"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value > 0):
                raise ValueError(f"curriculum {name.replace('_', ' ')} must be a positive integer, got {value!r}")
        if not 0.0 <= self.replay_prob <= 1.0:
            raise ValueError(f"curriculum replay probability must be in [0, 1], got {self.replay_prob!r}")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Feedback:
    """What the training loop tells the curriculum after an update."""

    net_params: Any  # the current network parameters (sfl rolls them out)
    step_level_ids: jax.Array  # (T, E) int32: id of the level each env played at each step (-1 fresh, -2 untracked)
    advantages: jax.Array  # (T, E) float32
    env_level_ids: jax.Array  # (E,) int32: id of the level each env plays now
    env_levels: Level  # (E, ...) the initial scene of the level each env plays now
    update_index: jax.Array  # int32


@dataclasses.dataclass(frozen=True)
class Curriculum:
    init: Callable
    sample: Callable
    update: Callable


def _take(levels: Level, index: jax.Array) -> Level:
    return jax.tree.map(lambda x: x[index], levels)


def _where(pred: jax.Array, a: Level, b: Level) -> Level:
    def pick(x, y):
        return jnp.where(pred.reshape(pred.shape + (1,) * (x.ndim - pred.ndim)), x, y)

    return jax.tree.map(pick, a, b)


def _keep_ids(state, key, feedback: Feedback):
    return state, feedback.env_level_ids


def fixed(levels: Level) -> Curriculum:
    """Uniformly one of `levels` (a stacked Level, leading axis) every episode; ids are -2 (untracked).

    The levels are the curriculum's state, not constants of the compiled program, so training on another level
    of the same size class reuses the compiled update (and JAX's persistent cache)."""
    count = levels.sim.bodies.active.shape[0]

    def sample(key, state, n):
        return _take(state, jax.random.randint(key, (n,), 0, count)), jnp.full((n,), -2, jnp.int32)

    return Curriculum(lambda key: levels, sample, lambda key, state, feedback: _keep_ids(state, key, feedback))


def domain_randomisation(generator: Callable[[jax.Array], Level]) -> Curriculum:
    def sample(key, state, n):
        return jax.vmap(generator)(jax.random.split(key, n)), jnp.full((n,), -2, jnp.int32)

    return Curriculum(lambda key: (), sample, lambda key, state, feedback: _keep_ids(state, key, feedback))


def _mixed_sample(generator, config: CurriculumConfig, replay_index_fn):
    """Fresh levels, replaced by buffer levels with probability replay_prob once the buffer has any."""

    def sample(key, state, n):
        k_fresh, k_replay, k_coin = jax.random.split(key, 3)
        fresh = jax.vmap(generator)(jax.random.split(k_fresh, n))
        index = replay_index_fn(k_replay, state, n)
        filled = state["scores"][index] > NEG / 2
        replay = jax.random.uniform(k_coin, (n,)) < config.replay_prob
        use = replay & filled
        levels = _where(use, _take(state["levels"], index), fresh)
        return levels, jnp.where(use, index, -1).astype(jnp.int32)

    return sample


def _empty_buffer(generator, size: int) -> dict:
    levels = jax.vmap(generator)(jax.random.split(jax.random.PRNGKey(0), size))
    return {"levels": levels, "scores": jnp.full((size,), NEG, jnp.float32)}


def sfl(generator: Callable[[jax.Array], Level], solve_rate_fn: Callable, config: CurriculumConfig) -> Curriculum:
    """`solve_rate_fn(key, net_params, levels (M, ...), attempts) -> (M,)` solve rates of the current policy."""
    if config.buffer_size > config.candidates:
        raise ValueError(f"sfl keeps the best {config.buffer_size} of {config.candidates} scored levels: the buffer "
                         f"cannot be larger than the candidates (raise --sfl-candidates or lower --buffer-size)")

    def init(key):
        return _empty_buffer(generator, config.buffer_size)

    def replay_index(key, state, n):
        return jax.random.randint(key, (n,), 0, config.buffer_size)  # uniform over the learnable set

    def refresh(key, state, net_params):
        k_levels, k_roll = jax.random.split(key)
        levels = jax.vmap(generator)(jax.random.split(k_levels, config.candidates))
        p = solve_rate_fn(k_roll, net_params, levels, config.attempts)
        scores, top = jax.lax.top_k(p * (1.0 - p), config.buffer_size)
        return {"levels": _take(levels, top), "scores": scores.astype(jnp.float32)}

    def update(key, state, feedback: Feedback):
        due = feedback.update_index % config.refresh_every == 0
        state = jax.lax.cond(due, lambda: refresh(key, state, feedback.net_params), lambda: state)
        # episodes in progress keep playing their level; their ids stop naming buffer slots
        return state, jnp.where(due, -2, feedback.env_level_ids).astype(jnp.int32)

    return Curriculum(init, _mixed_sample(generator, config, replay_index), update)


def plr(generator: Callable[[jax.Array], Level], config: CurriculumConfig) -> Curriculum:
    K = config.buffer_size

    def init(key):
        return _empty_buffer(generator, K)

    def replay_index(key, state, n):
        # rank prioritisation: weight (1 / rank) ^ (1 / temperature) over filled slots
        ranks = jnp.argsort(jnp.argsort(-state["scores"])) + 1
        weights = jnp.where(state["scores"] > NEG / 2, (1.0 / ranks) ** (1.0 / config.temperature), 0.0)
        weights = jnp.where(weights.sum() > 0, weights, 1.0)
        return jax.random.choice(key, K, (n,), p=weights / weights.sum())

    def update(key, state, feedback: Feedback):
        E = feedback.env_level_ids.shape[0]
        positive = jnp.maximum(feedback.advantages, 0.0)
        ids = feedback.step_level_ids
        # buffer slots: mean positive advantage over the steps played on them (unchanged if not played)
        slot = jnp.where(ids >= 0, ids, K)
        total = jax.ops.segment_sum(positive.reshape(-1), slot.reshape(-1), K + 1)[:K]
        count = jax.ops.segment_sum(jnp.ones_like(positive).reshape(-1), slot.reshape(-1), K + 1)[:K]
        scores = jnp.where(count > 0, total / jnp.maximum(count, 1.0), state["scores"])
        # fresh levels being played now: scored by the steps of this rollout that env spent on a fresh level
        fresh_steps = ids == -1
        fresh_score = (positive * fresh_steps).sum(0) / jnp.maximum(fresh_steps.sum(0), 1)
        candidate = (feedback.env_level_ids == -1) & (fresh_steps.sum(0) > 0)
        cand_scores = jnp.where(candidate, fresh_score, NEG)
        all_scores = jnp.concatenate([scores, cand_scores])
        new_scores, top = jax.lax.top_k(all_scores, K)
        all_levels = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), state["levels"], feedback.env_levels)
        new_state = {"levels": _take(all_levels, top), "scores": new_scores}
        # where each old id went: position in `top`, or -2 if it fell out of the buffer
        where_now = jnp.full((K + E,), -2, jnp.int32).at[top].set(jnp.arange(K, dtype=jnp.int32))
        env_ids = feedback.env_level_ids
        lookup = jnp.where(env_ids >= 0, env_ids, jnp.where(env_ids == -1, K + jnp.arange(E), 0))
        moved = where_now[lookup]
        new_env_ids = jnp.where(env_ids >= 0, moved, jnp.where(candidate, moved, env_ids))
        return new_state, new_env_ids.astype(jnp.int32)

    return Curriculum(init, _mixed_sample(generator, config, replay_index), update)
