"""Train Stable-Baselines3's PPO on one Kinetix level through kinetix.gym, then compare its solve rate with random
actions (docs/gymnasium.md). Needs stable-baselines3 (and so PyTorch) beside the gym extra:

    pip install -e '.[gym]' stable-baselines3
    python docs/examples/sb3_ppo.py --level levels/car_right.json --steps 20000
"""

from __future__ import annotations

import argparse
import time

import gymnasium
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env

import kinetix.gym  # noqa: F401  (registers kinetix/Level-v0)


def solve_rate(env: gymnasium.Env, act, episodes: int, seed: int) -> tuple[float, float]:
    """(fraction of episodes solved, mean return) of `act(obs) -> action` over `episodes` episodes."""
    solved, returns = 0, 0.0
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done = False
        while not done:
            obs, reward, terminated, truncated, info = env.step(act(obs))
            returns += reward
            done = terminated or truncated
        solved += bool(info["solved"])
    return solved / episodes, returns / episodes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", default="levels/car_right.json")
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--envs", type=int, default=4)
    parser.add_argument("--episodes", type=int, default=20)
    args = parser.parse_args()

    kwargs = {"level": args.level, "observation": "flat", "action": "multi_discrete"}
    # SB3 keeps its own vector env (a DummyVecEnv of gymnasium.make("kinetix/Level-v0", ...) copies): it does not
    # take Gymnasium's VectorEnv, so KinetixVectorEnv is for libraries that do.
    envs = make_vec_env("kinetix/Level-v0", n_envs=args.envs, seed=0, env_kwargs=kwargs)
    model = PPO("MlpPolicy", envs, n_steps=256, batch_size=256, learning_rate=3e-4, seed=0, verbose=0)
    start = time.perf_counter()
    model.learn(total_timesteps=args.steps)
    seconds = time.perf_counter() - start
    print(f"trained {model.num_timesteps} steps in {seconds:.0f} s ({model.num_timesteps / seconds:.0f} steps/s)")

    env = gymnasium.make("kinetix/Level-v0", **kwargs)
    trained = solve_rate(env, lambda obs: model.predict(obs, deterministic=True)[0], args.episodes, seed=1000)
    random = solve_rate(env, lambda obs: env.action_space.sample(), args.episodes, seed=1000)
    print(f"PPO:    solve rate {trained[0]:.2f}, mean return {trained[1]:.3f} over {args.episodes} episodes")
    print(f"random: solve rate {random[0]:.2f}, mean return {random[1]:.3f}")


if __name__ == "__main__":
    main()
