"""Exact replay: rebuild the env a recording was made with, re-simulate its actions and compare states bitwise.

Bitwise equality needs the same compiled program on the same machine. Players (the CLI, the server) step with
`step_function(config)` from here, and replay uses the same function, so both run one XLA program per config.
On a machine with a GPU both step on the CPU device (kinetix.devices.interactive_device), where the server's
sessions step too, so a recording replays on the backend it was made on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import itertools
import os
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import jax
import numpy as np

import jax2d
from kinetix.recording.errors import RecordingError
from kinetix.recording.reader import Recording


@functools.cache
def step_function(config):
    """The jitted `(state, action, params) -> (next_state, reward, terminated, truncated, info)` for one EnvConfig
    (no observation, no reset). One per config for the whole process, shared by recording and replay."""
    from kinetix.devices import on_interactive_device
    from kinetix.env import KinetixEnv

    env = KinetixEnv(config, lambda key: None)  # transition never calls the reset function
    return on_interactive_device(jax2d.jit(env.transition))


@functools.cache
def batched_step_function(config, batch: int):
    """The transition vmapped over `batch` plays, jitted: what the browser server runs when it steps several tabs
    at once (its results differ bitwise from `step_function`'s; a play's lane does not depend on the others).
    `step(state, action, params)` runs the play in every lane and returns lane 0, so recorded batched steps
    re-simulate bitwise."""
    import jax.numpy as jnp

    from kinetix.devices import on_interactive_device
    from kinetix.env import KinetixEnv

    env = KinetixEnv(config, lambda key: None)
    many = jax2d.jit(jax.vmap(env.transition))

    def step(state, action, params):
        copies = lambda x: jnp.stack([x] * batch)  # noqa: E731
        out = many(jax.tree.map(copies, state), np.stack([np.asarray(action)] * batch), jax.tree.map(copies, params))
        return jax.tree.map(lambda x: x[0], out)

    return on_interactive_device(step)


def _stepper(config, recording: Recording):
    """step(i, state, action, params) using the program step i was recorded with (single or batched)."""
    single = step_function(config)
    batches = recording.batches

    def step(i, state, action, params):
        if batches is None or batches[i] == 1:
            return single(state, action, params)
        return batched_step_function(config, int(batches[i]))(state, action, params)

    return step


def make_env(recording: Recording, observation: str | None = None):
    """(env, params) as recorded; `observation` overrides the observation type (it does not change the physics)."""
    from jax2d.state import SimParams, SolverConfig
    from kinetix.env import EnvConfig, EnvParams
    from kinetix.env import make_env as make

    desc = recording.env
    try:
        config = EnvConfig(size=recording.level_file.size, observation=observation or desc["observation"],
                           action=desc["action"], frame_skip=int(desc["frame_skip"]),
                           pixel_resolution=int(desc["pixel_resolution"]), solver=SolverConfig(**desc["solver"]))
        p = desc["params"]
        params = EnvParams(max_timesteps=int(p["max_timesteps"]), dense_reward_scale=p["dense_reward_scale"],
                           sim=SimParams(**p["sim"]))
    except (KeyError, TypeError, ValueError) as error:
        raise RecordingError(f"the recording's env description is not usable: {error}") from None
    return make(config, recording.level_file), params


@dataclasses.dataclass(frozen=True)
class ReplayCheck:
    steps: int  # steps re-simulated
    divergent_step: int | None  # first step whose state, reward or flags differ (None: all equal)
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.divergent_step is None


def replay_states(recording: Recording, observation: str | None = None) -> Iterator[tuple[int, object, object]]:
    """Yield (step index, env state after the step, env) by re-simulating the recorded actions.

    After a step that ended an episode the next one starts again from the recorded level, as when playing.
    """
    env, params = make_env(recording, observation)
    step = _stepper(env.config, recording)
    start = env.initial_state(jax.random.PRNGKey(0), params)  # reset_single: the key is not used
    state = start
    for i in range(recording.num_steps):
        state, *_ = step(i, state, recording.actions[i], params)
        yield i, state, env
        if recording.terminated[i] or recording.truncated[i]:
            state = start


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bitwise equality of float32 arrays (NaNs with the same bits are equal, 0.0 and -0.0 are not)."""
    return a.shape == b.shape and np.array_equal(np.ascontiguousarray(a, np.float32).view(np.uint32),
                                                 np.ascontiguousarray(b, np.float32).view(np.uint32))


def verify(recording: Recording) -> ReplayCheck:
    """Re-simulate every step and compare the bodies' states, rewards and end flags with the recorded ones."""
    env, params = make_env(recording)
    step = _stepper(env.config, recording)
    start = env.initial_state(jax.random.PRNGKey(0), params)
    state = start
    b = recording.bodies
    for i in range(recording.num_steps):
        state, reward, terminated, truncated, _ = step(i, state, recording.actions[i], params)
        bodies = state.level.sim.bodies
        checks = (("position", np.asarray(bodies.position)[b], recording.position[i]),
                  ("rotation", np.asarray(bodies.angle)[b], recording.rotation[i]),
                  ("velocity", np.asarray(bodies.velocity)[b], recording.velocity[i]),
                  ("angular velocity", np.asarray(bodies.angular_velocity)[b], recording.angular_velocity[i]),
                  ("reward", np.asarray(reward, np.float32), recording.rewards[i]))
        for what, got, want in checks:
            if not _same(np.asarray(got), np.asarray(want)):
                diff = float(np.max(np.abs(np.asarray(got, np.float64) - np.asarray(want, np.float64))))
                return ReplayCheck(i + 1, i, f"{what} differs (max abs difference {diff:.3g})")
        if bool(terminated) != recording.terminated[i] or bool(truncated) != recording.truncated[i]:
            return ReplayCheck(i + 1, i, "the end-of-episode flags differ")
        if recording.terminated[i] or recording.truncated[i]:
            state = start
    return ReplayCheck(recording.num_steps, None)


def replay_frames(recording: Recording, resolution: int = 256, every: int = 1) -> Iterator[tuple[int, np.ndarray]]:
    """(step index, uint8 RGB image) of every `every`-th re-simulated step, starting with the initial level (-1)."""
    from kinetix.render import render_pixels, to_uint8

    yield -1, to_uint8(render_pixels(recording.level_file.level, resolution))
    for i, state, _ in replay_states(recording):
        if (i + 1) % every == 0 or i == recording.num_steps - 1:
            yield i, to_uint8(render_pixels(state.level, resolution))


def step_seconds(recording: Recording) -> float:
    """Simulated seconds per env step."""
    return float(recording.env["params"]["sim"]["dt"]) * int(recording.env["frame_skip"])


def write_gif(recording: Recording, path, resolution: int = 256, fps: float = 15.0) -> int:
    """Write the re-simulated play as an animated GIF (real-time speed); returns the number of frames."""
    from PIL import Image

    every = max(1, round(1.0 / (fps * step_seconds(recording))))
    images = [Image.fromarray(image) for _, image in replay_frames(recording, resolution, every)]
    duration = max(20, int(round(1000 * every * step_seconds(recording) / 10)) * 10)  # GIF delays are 10 ms units
    tmp = f"{path}.part"
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)
    os.replace(tmp, path)  # never a half-written GIF at the target
    return len(images)


def write_mp4(recording: Recording, path, resolution: int = 256, fps: float = 30.0) -> int:
    """Write the re-simulated play as an H.264 MP4 with the ffmpeg binary of the imageio-ffmpeg wheel; returns
    the number of frames. RecordingError if that package is missing or ffmpeg fails; the target is then untouched.

    ffmpeg is started here rather than through imageio's writer: that one starts it with a `preexec_fn`, which
    runs Python in the forked child of this multithreaded (JAX) process, a documented deadlock hazard (JAX warns
    about it). `start_new_session` does the same job (Ctrl+C does not reach ffmpeg) in C, before the exec.
    """
    try:
        import imageio_ffmpeg
    except ImportError:
        raise RecordingError("writing MP4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); "
                             "use --gif instead") from None
    every = max(1, round(1.0 / (fps * step_seconds(recording))))
    rate = 1.0 / (every * step_seconds(recording))
    tmp = Path(f"{path}.part.mp4")
    frames = replay_frames(recording, resolution, every)
    _, first = next(frames)
    height, width = first.shape[:2]
    try:
        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError as error:  # the wheel without a binary for this platform, and none on the PATH
        raise RecordingError(f"writing MP4 needs an ffmpeg binary: {error}; use --gif instead") from None
    command = [exe, "-y", "-loglevel", "error",
               "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}", "-r", f"{rate:.6g}", "-i", "-",
               "-an", "-c:v", "libx264", "-crf", "20", "-pix_fmt", "yuv420p",
               "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2",  # yuv420p needs even sides
               "-movflags", "+faststart", "-f", "mp4", str(tmp)]
    count = 0
    with tempfile.TemporaryFile() as log:
        process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log,
                                   start_new_session=True)
        try:
            broken = False
            try:
                for image in itertools.chain([first], (image for _, image in frames)):
                    process.stdin.write(np.ascontiguousarray(image[..., :3], np.uint8).tobytes())
                    count += 1
                process.stdin.close()
            except BrokenPipeError:  # ffmpeg stopped reading: its exit status and log say why
                broken = True
                with contextlib.suppress(BrokenPipeError):
                    process.stdin.close()
            code = process.wait()
        except BaseException:  # Ctrl+C or a replay error: no half-written video left behind
            process.kill()
            process.wait()
            tmp.unlink(missing_ok=True)
            raise
        if code != 0 or broken:
            tmp.unlink(missing_ok=True)
            log.seek(0)
            raise RecordingError(f"ffmpeg failed writing {path} (exit status {code}): {_tail(log.read())}")
    os.replace(tmp, path)  # never a half-written video at the target
    return count


def _tail(data: bytes, limit: int = 400) -> str:
    text = data.decode(errors="replace").strip()
    return text[-limit:] or "no message"


def recorded_level(recording: Recording, step: int):
    """The Level as recorded after `step` (-1: the start), without re-simulating: the initial level with the
    recorded position, rotation and velocities of its bodies. Cheap enough for scrubbing a timeline; render it
    with kinetix.render.render_pixels."""
    import jax.numpy as jnp

    level = recording.level_file.level
    if step < 0:
        return level
    if step >= recording.num_steps:
        raise IndexError(f"step {step} is past the recording's {recording.num_steps} steps")
    b = recording.bodies
    bodies = level.sim.bodies
    bodies = dataclasses.replace(
        bodies,
        position=jnp.asarray(bodies.position).at[b].set(recording.position[step]),
        angle=jnp.asarray(bodies.angle).at[b].set(recording.rotation[step]),
        velocity=jnp.asarray(bodies.velocity).at[b].set(recording.velocity[step]),
        angular_velocity=jnp.asarray(bodies.angular_velocity).at[b].set(recording.angular_velocity[step]),
    )
    return dataclasses.replace(level, sim=dataclasses.replace(level.sim, bodies=bodies))
