"""Recording an agent's episode from the CLI: `kinetix play --agent SPEC --level FILE --record OUT.mcap`."""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

import jax
import numpy as np

import jax2d
from kinetix.level import LevelError, LevelFile
from kinetix.recording.errors import RecordingError
from kinetix.recording.replay import step_function
from kinetix.recording.writer import Recorder

FRAME_RESOLUTION = 256
JPEG_QUALITY = 85


def encode_jpeg(image: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


def _policy(spec: str, env):
    """A function (key, obs) -> action for noop / random here, or the agents package's policy."""
    from kinetix.actions import noop_action, sample_random_action

    if spec == "noop":
        action = noop_action(env.config)
        return lambda key, obs: action
    if spec == "random":
        return jax2d.jit(lambda key, obs: sample_random_action(key, env.config))
    try:
        from kinetix.agents import load_policy
    except ImportError as error:
        raise RecordingError(f"agent {spec!r} needs kinetix.agents, which is not available ({error}); "
                             "use --agent noop or --agent random") from None
    policy = load_policy(spec, env)
    act = jax2d.jit(policy.act)
    return lambda key, obs: act(key, obs)[0]


def _observation_for(spec: str) -> str:
    if spec in ("noop", "random"):
        return "entity"
    try:
        from kinetix.agents.policy import required_observation

        return required_observation(spec) or "entity"
    except (ImportError, AttributeError):
        return "entity"
    except Exception as error:  # a bad checkpoint directory: load_policy will say so clearly
        del error
        return "entity"


def play_episode(agent: str, level_file: LevelFile, out: str | Path, *, seed: int = 0, max_steps: int | None = None,
                 frames: bool = True, name: str | None = None) -> dict:
    """Play one episode with `agent` and record it to `out`; returns the summary (steps, return, solved, ...)."""
    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.render import render_pixels, to_uint8

    config = EnvConfig(size=level_file.size, observation=_observation_for(agent),
                       frame_skip=level_file.params.frame_skip)
    env = make_env(config, level_file)
    params = EnvParams.from_level_params(level_file.params)
    act = _policy(agent, env)
    step = step_function(config)
    # noop and random ignore the observation: skip computing (and compiling) it
    observe = (lambda s: None) if agent in ("noop", "random") else jax2d.jit(env.observe)
    key = jax.random.PRNGKey(seed)
    reset_key, key = jax.random.split(key)
    state = env.initial_state(reset_key, params)
    limit = int(params.max_timesteps) if max_steps is None else max_steps
    dt = float(params.sim.dt) * config.frame_skip
    metadata = {"player": "agent", "name": name or agent, "level_id": level_file.name, "seed": seed}
    ret = 0.0
    with Recorder(out, level_file, metadata=metadata, env_config=config, env_params=params) as recorder:
        if frames:
            recorder.add_frame(encode_jpeg(to_uint8(render_pixels(state.level, FRAME_RESOLUTION))), 0.0)
        for i in range(limit):
            action = act(jax.random.fold_in(key, i), observe(state))
            state, reward, terminated, truncated, _ = step(state, action, params)
            t = (i + 1) * dt
            recorder.add_step(action, reward, terminated, truncated, state, t=t)
            ret += float(reward)
            if frames and recorder.wants_frame(t):
                recorder.add_frame(encode_jpeg(to_uint8(render_pixels(state.level, FRAME_RESOLUTION))), t)
            if bool(terminated) or bool(truncated):
                break
        steps = i + 1 if limit else 0
    return {"steps": steps, "return": ret, "solved": bool(terminated) and float(reward) > 0.5 if limit else False}


def run_play(args: argparse.Namespace) -> int:
    from kinetix.levels import load_level

    try:
        level_file = load_level(args.level)
    except LevelError as error:
        print(f"kinetix play: {error}", file=sys.stderr)
        return 2
    try:
        result = play_episode(args.agent, level_file, args.record, seed=args.seed, max_steps=args.max_steps)
    except (RecordingError, LevelError, FileNotFoundError, ValueError) as error:
        print(f"kinetix play: {error}", file=sys.stderr)
        return 2
    outcome = "solved" if result["solved"] else "not solved"
    print(f"{args.record}: {result['steps']} steps, return {result['return']:.3f}, {outcome}")
    return 0


def run_replay(args: argparse.Namespace) -> int:
    from kinetix.recording.reader import read_recording
    from kinetix.recording.replay import verify, write_gif, write_mp4

    try:
        recording = read_recording(args.file, frames=False)
        check = verify(recording)
        if check.ok:
            print(f"{args.file}: replay matches the recording bitwise ({check.steps} steps)")
        else:
            print(f"{args.file}: replay diverges at step {check.divergent_step}: {check.detail}")
        if args.gif:
            count = write_gif(recording, args.gif, resolution=args.resolution)
            print(f"wrote {args.gif} ({count} frames)")
        if args.mp4:
            count = write_mp4(recording, args.mp4, resolution=args.resolution)
            print(f"wrote {args.mp4} ({count} frames)")
    except RecordingError as error:
        print(f"kinetix replay: {error}", file=sys.stderr)
        return 2
    return 0 if check.ok else 1
