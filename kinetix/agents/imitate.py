"""Imitation of a level's scripted solution: the warm start for levels PPO does not explore its way into.

Why: fine-tuning the general agent on levels/car_jump.json for 1.25M env steps never solved it once, although
"motor +1 with probability 0.6, else a uniform action" solves it in 61 of 100 attempts (27 Nov 2026). A stochastic
policy approaches the red pit slowly and falls in, so PPO learns to stay away from it; the run-up that wins is
never seen. A demonstration shows it.

1. **Demonstrations.** The level's scripted solution (kinetix.solutions) gives continuous binding values. Each
   becomes the multi-discrete distribution whose mean it is (`target_probabilities`; or, with `--dither round`,
   the nearest action), and the environment steps with an action sampled from it, so the closed-loop solution
   sees and corrects the dither. `episodes` copies run vmapped; the steps of the solved episodes are kept, with
   their discounted returns.
2. **Cloning.** A network (`--init`'s checkpoint, normally the general agent) is fitted by Adam minibatches: its
   actor to those distributions (cross-entropy per binding), its critic to the returns, so PPO fine-tuning starts
   with a critic that knows the level.
3. The result is an ordinary agent checkpoint: `kinetix eval --agent DIR` scores it and
   `kinetix train --init DIR` fine-tunes it.

    python -m kinetix.agents.imitate levels/car_jump.json --init general --out /tmp/imitate/car_jump
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.actions import action_space

Solution = Callable[[jax.Array, jax2d.SimState], tuple[jax.Array, jax.Array]]


DITHERS = ("sample", "round")


def target_probabilities(motor: jax.Array, thrust: jax.Array, dither: str = "sample") -> jax.Array:
    """(16,) a multi-discrete distribution for these binding values, in the network's logit layout: per motor
    (off, +1, -1), per thruster (off, on); values clipped to the action ranges.

    "sample": the distribution whose mean they are (+1 at probability max(u, 0), -1 at max(-u, 0); a thruster on
    at probability u). "round": all on the nearest action (a motor at |u| >= 0.5 runs, a thruster at u >= 0.5
    fires), for solutions that need their values held, not averaged over steps (cartpole's balance)."""
    u = jnp.clip(jnp.asarray(motor, jnp.float32), -1.0, 1.0)
    v = jnp.clip(jnp.asarray(thrust, jnp.float32), 0.0, 1.0)
    if dither == "round":
        u, v = jnp.where(jnp.abs(u) >= 0.5, jnp.sign(u), 0.0), jnp.where(v >= 0.5, 1.0, 0.0)
    elif dither != "sample":
        raise ValueError(f"dither {dither!r}: use one of {', '.join(DITHERS)}")
    motors = jnp.stack([1.0 - jnp.abs(u), jnp.maximum(u, 0.0), jnp.maximum(-u, 0.0)], -1)
    thrusters = jnp.stack([1.0 - v, v], -1)
    return jnp.concatenate([motors.reshape(-1), thrusters.reshape(-1)])


def _split(x: jax.Array) -> list[jax.Array]:
    cuts = np.cumsum(action_space("multi_discrete").nvec)[:-1]
    return jnp.split(x, cuts, axis=-1)


def sample_actions(key: jax.Array, probabilities: jax.Array) -> jax.Array:
    """(..., 6) int32 actions drawn from (..., 16) target probabilities."""
    parts = _split(jnp.log(jnp.maximum(probabilities, 1e-12)))
    keys = jax.random.split(key, len(parts))
    return jnp.stack([jax.random.categorical(k, p) for k, p in zip(keys, parts, strict=True)], -1).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class Demonstrations:
    obs: object  # observation pytree, leading axis N
    probabilities: np.ndarray  # (N, 16) what the solution asked for
    returns: np.ndarray  # (N,) discounted return from each step on
    solve_rate: float  # of all demonstrated episodes, before only the solved ones were kept
    episodes: int


def demonstrate(env, env_params, level, solution: Solution, episodes: int, key: jax.Array,
                gamma: float = 0.99, dither: str = "sample") -> Demonstrations:
    """Roll `solution` out `episodes` times (dithered, see the module docstring) and keep the solved episodes."""
    steps = int(env_params.max_timesteps)
    step = jax.vmap(env.step_no_reset, in_axes=(None, 0, 0, None))

    def rollout(key):
        from kinetix.agents.rollout import fresh_state

        levels = jax.tree.map(lambda x: jnp.repeat(x[None], episodes, 0), level)
        state = jax.vmap(fresh_state)(levels)
        obs = jax.vmap(env.observe)(state)

        def one(carry, k):
            state, obs, done = carry
            motor, thrust = jax.vmap(lambda s: solution(s.timestep, s.level.sim))(state)
            probabilities = jax.vmap(lambda m, t: target_probabilities(m, t, dither))(motor, thrust)
            action = sample_actions(k, probabilities)
            next_obs, next_state, reward, terminated, truncated, info = step(k, state, action, env_params)
            keep = lambda a, b: jax.tree.map(
                lambda x, y: jnp.where(done.reshape(done.shape + (1,) * (x.ndim - 1)), x, y), a, b)
            record = (obs, probabilities, jnp.where(done, 0.0, reward), ~done, ~done & info["solved"])
            return (keep(state, next_state), keep(obs, next_obs), done | terminated | truncated), record

        start = (state, obs, jnp.zeros((episodes,), bool))
        _, (obs, probabilities, rewards, valid, solved) = jax.lax.scan(one, start, jax.random.split(key, steps))

        def discount(after, reward):
            now = reward + gamma * after
            return now, now

        _, returns = jax.lax.scan(discount, jnp.zeros((episodes,)), rewards, reverse=True)
        return obs, probabilities, returns, valid, solved.any(0)

    obs, probabilities, returns, valid, solved = jax.device_get(jax2d.jit(rollout)(key))
    keep = (valid & solved[None, :]).reshape(-1)  # (T * B,) steps of solved episodes
    flat = lambda x: np.asarray(x).reshape((-1,) + x.shape[2:])[keep]
    return Demonstrations(jax.tree.map(flat, obs), flat(probabilities), flat(returns), float(solved.mean()),
                          episodes)


def clone(network, params, demos: Demonstrations, *, epochs: int = 30, batch_size: int = 256, lr: float = 3e-4,
          value_weight: float = 0.5, seed: int = 0, log: Callable[[str], None] = print):
    """`params` fitted to the demonstrations (actor: cross-entropy to the target probabilities; critic: the
    returns). Returns (params, {"loss", "cross_entropy", "value_error"} of the last epoch)."""
    import optax

    n = len(demos.returns)
    if n < batch_size:
        raise ValueError(f"only {n} demonstrated steps (of solved episodes): fewer than one batch of {batch_size}")
    optimiser = optax.chain(optax.clip_by_global_norm(0.5), optax.adam(lr))
    opt_state = optimiser.init(params)

    def loss_fn(p, obs, target, returns):
        outputs, value = network.apply({"params": p}, obs)
        cross = sum(-(t * jax.nn.log_softmax(o)).sum(-1) for o, t in zip(_split(outputs), _split(target), strict=True))
        value_error = jnp.mean((value - returns) ** 2)
        cross = jnp.mean(cross)
        return cross + value_weight * value_error, (cross, value_error)

    @jax2d.jit
    def update(p, s, obs, target, returns):
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(p, obs, target, returns)
        updates, s = optimiser.update(grads, s, p)
        return optax.apply_updates(p, updates), s, loss, aux

    rng = np.random.default_rng(seed)
    result = {}
    for epoch in range(epochs):
        order = rng.permutation(n)
        logs = []
        for start in range(0, n - batch_size + 1, batch_size):  # whole batches only: one compiled shape
            idx = order[start:start + batch_size]
            batch = jax.tree.map(lambda x: jnp.asarray(x[idx]), demos.obs)
            params, opt_state, loss, (cross, value_error) = update(
                params, opt_state, batch, jnp.asarray(demos.probabilities[idx]), jnp.asarray(demos.returns[idx]))
            logs.append((float(loss), float(cross), float(value_error)))
        result = dict(zip(("loss", "cross_entropy", "value_error"), np.mean(logs, 0).tolist(), strict=True))
        log(f"epoch {epoch + 1}/{epochs}: cross-entropy {result['cross_entropy']:.4f}, "
            f"value error {result['value_error']:.4f}")
    return params, result


def imitate(level_path: str | Path, init: str, out: str | Path, *, episodes: int = 64, epochs: int = 30,
            attempts: int = 100, seed: int = 0, dither: str = "sample", command: str | None = None,
            log: Callable[[str], None] = print) -> dict:
    """Demonstrate, clone, score and save (see the module docstring). Returns the checkpoint's info."""
    from kinetix.agents import checkpoint
    from kinetix.agents.policy import resolve
    from kinetix.agents.ppo import make_network
    from kinetix.agents.rollout import run_episodes
    from kinetix.env import make_env
    from kinetix.level_source import level_source
    from kinetix.solutions import SOLUTIONS

    level_path = Path(level_path)
    if level_path.stem not in SOLUTIONS:
        raise ValueError(f"{level_path.stem} has no scripted solution (kinetix.solutions has one for each level in "
                         f"levels/: {', '.join(sorted(SOLUTIONS))})")
    if init in ("noop", "random"):
        raise ValueError(f"--init {init}: imitation starts from a network: general or a checkpoint directory")
    ckpt = checkpoint.load(resolve(init))
    if ckpt.env["action"] != "multi_discrete" or ckpt.env["observation"] != "entity":
        raise ValueError(f"--init {init}: imitation needs an entity network with multi_discrete actions, this one "
                         f"has {ckpt.env['observation']} observations and {ckpt.env['action']} actions")
    source = level_source(level_path)
    env = make_env(source.env_config("entity", "multi_discrete"), source.files[0])
    env_params = jax.tree.map(lambda x: x[0], source.level_params)
    level = source.files[0].level
    key_demo, key_eval = jax.random.split(jax.random.key(seed))

    demos = demonstrate(env, env_params, level, SOLUTIONS[level_path.stem], episodes, key_demo,
                        gamma=ckpt.train_config.gamma, dither=dither)
    log(f"{level_path.stem}: the dithered solution solved {demos.solve_rate:.2f} of {episodes} episodes; "
        f"{len(demos.returns)} steps kept")
    network = make_network(ckpt.train_config, "multi_discrete")
    params, fit = clone(network, jax.tree.map(jnp.asarray, ckpt.params), demos, epochs=epochs, seed=seed, log=log)

    def act(key, obs):
        from kinetix.agents.distributions import sample

        outputs, _ = network.apply({"params": params}, jax.tree.map(lambda x: x[None], obs))
        return sample(key, outputs, "multi_discrete")[0]

    levels = jax.tree.map(lambda x: jnp.repeat(x[None], attempts, 0), level)
    solved, _ = jax2d.jit(lambda k: run_episodes(env, env_params, act, levels, k, int(env_params.max_timesteps)))(
        key_eval)
    info = {"trained_by": "python -m kinetix.agents.imitate", "level": str(level_path), "init": init,
            "episodes": episodes, "dither": dither, "demo_solve_rate": demos.solve_rate,
            "demo_steps": len(demos.returns), "epochs": epochs, "seed": seed, **fit,
            "solve_rate": float(solved.mean()), "attempts": attempts, "command": command}
    log(f"{level_path.stem}: the cloned policy solves {info['solve_rate']:.2f} of {attempts} attempts (sampled)")
    checkpoint.save(out, params, ckpt.train_config, env.config, info)
    return info


def main(argv: list[str] | None = None) -> int:
    from kinetix.agents.checkpoint import CheckpointError
    from kinetix.level import LevelError

    parser = argparse.ArgumentParser(prog="python -m kinetix.agents.imitate",
                                     description="clone a project level's scripted solution into an agent checkpoint")
    parser.add_argument("level", help="a level file in levels/ (its stem names the solution)")
    parser.add_argument("--init", default="general", help="the checkpoint to start from (default: general)")
    parser.add_argument("--out", required=True, help="checkpoint directory to write")
    parser.add_argument("--episodes", type=int, default=64, help="demonstrated episodes (default: 64)")
    parser.add_argument("--epochs", type=int, default=30, help="passes over the demonstrations (default: 30)")
    parser.add_argument("--attempts", type=int, default=100, help="attempts to score the result (default: 100)")
    parser.add_argument("--dither", choices=DITHERS, default="sample",
                        help="how a solution's continuous values become actions (default: sample)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for name in ("episodes", "epochs", "attempts"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1")
    command = "python -m kinetix.agents.imitate " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    try:
        imitate(args.level, args.init, args.out, episodes=args.episodes, epochs=args.epochs, attempts=args.attempts,
                seed=args.seed, dither=args.dither, command=command)
    except (ValueError, CheckpointError, LevelError) as error:
        print(f"python -m kinetix.agents.imitate: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

