"""`kinetix train-bc`: behaviour cloning on an export-demos dataset with the agents' PPO actor-critic network.

Maximises the log-likelihood of the demonstrated actions under the actor head (the critic head is left
untrained) and writes an ordinary agent checkpoint, so `kinetix eval --agent DIR`, `kinetix play --agent DIR`
and the server's `load_policy(DIR, env)` use the result like a PPO agent.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.recording.errors import RecordingError


def load_dataset(path: str | Path) -> tuple[dict, object, np.ndarray]:
    """(manifest, observations (array or dict of arrays), actions) of an export-demos directory."""
    path = Path(path)
    try:
        manifest = json.loads((path / "manifest.json").read_text())
    except FileNotFoundError:
        raise RecordingError(f"{path} has no manifest.json: make it with kinetix export-demos") from None
    except json.JSONDecodeError as error:
        raise RecordingError(f"{path / 'manifest.json'} is not valid JSON: {error}") from None
    parts: dict[str, list[np.ndarray]] = {}
    for shard in manifest.get("shards", []):
        with np.load(path / shard["file"]) as data:
            for name in data.files:
                parts.setdefault(name, []).append(data[name])
    if not parts:
        raise RecordingError(f"{path} holds no demonstration steps")
    arrays = {name: np.concatenate(chunks) for name, chunks in parts.items()}
    if "obs" in arrays:
        obs = arrays["obs"]
    else:
        obs = {name[4:]: value for name, value in arrays.items() if name.startswith("obs_")}
    return manifest, obs, arrays["actions"]


def train_bc(dataset: str | Path, out: str | Path, *, epochs: int = 20, batch_size: int = 256, lr: float = 3e-4,
             seed: int = 0, log=print) -> dict:
    """Train and save a checkpoint at `out`; returns {"loss": ..., "accuracy": ...} of the last epoch."""
    import optax

    from kinetix.agents import checkpoint
    from kinetix.agents.distributions import log_prob, mode
    from kinetix.agents.ppo import TrainConfig, make_network
    from kinetix.env import EnvConfig

    manifest, obs, actions = load_dataset(dataset)
    kind, action_type = manifest["observation"], manifest["action_type"]
    n = len(actions)
    # The checkpoint's record of the run, built first: a bad setting (such as an lr that is not positive) is an
    # error before the epochs run, not after.
    config = TrainConfig(network=kind, total_timesteps=n * epochs, lr=lr)
    batch_size = min(batch_size, n)
    network = make_network(config, action_type)
    key = jax.random.PRNGKey(seed)
    params = network.init(key, jax.tree.map(lambda x: jnp.asarray(x[:1]), obs))["params"]
    optimiser = optax.chain(optax.clip_by_global_norm(0.5), optax.adam(lr))
    opt_state = optimiser.init(params)

    def loss_fn(p, o, a):
        outputs, _ = network.apply({"params": p}, o)
        accuracy = jnp.mean(jnp.all(mode(outputs, action_type) == a, axis=-1) if a.ndim > 1
                            else mode(outputs, action_type) == a)
        return -jnp.mean(log_prob(outputs, a, action_type)), accuracy

    @jax2d.jit
    def update(p, s, o, a):
        (loss, accuracy), grads = jax.value_and_grad(loss_fn, has_aux=True)(p, o, a)
        updates, s = optimiser.update(grads, s, p)
        return optax.apply_updates(p, updates), s, loss, accuracy

    rng = np.random.default_rng(seed)
    result = {}
    for epoch in range(epochs):
        order = rng.permutation(n)
        losses, accuracies = [], []
        for start in range(0, n - batch_size + 1, batch_size):  # whole batches only: one compiled shape
            idx = order[start:start + batch_size]
            batch = jax.tree.map(lambda x: jnp.asarray(x[idx]), obs)
            params, opt_state, loss, accuracy = update(params, opt_state, batch, jnp.asarray(actions[idx]))
            losses.append(float(loss))
            accuracies.append(float(accuracy))
        result = {"loss": float(np.mean(losses)), "accuracy": float(np.mean(accuracies))}
        log(f"epoch {epoch + 1}/{epochs}: loss {result['loss']:.4f}, action accuracy {result['accuracy']:.3f}")
    env_config = EnvConfig(size=manifest["size"], observation=kind, action=action_type,
                           frame_skip=int(manifest.get("frame_skip", 2)))
    checkpoint.save(out, params, config, env_config, {"trained_by": "kinetix train-bc", "dataset": str(dataset),
                                                      "steps": n, "epochs": epochs, **result})
    return result


def run(args: argparse.Namespace) -> int:
    try:
        result = train_bc(args.data, args.out, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                          seed=args.seed)
    except (RecordingError, ValueError) as error:
        print(f"kinetix train-bc: {error}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} (loss {result['loss']:.4f}, action accuracy {result['accuracy']:.3f}); "
          f"measure it with: kinetix eval --agent {args.out} --level LEVEL")
    return 0
