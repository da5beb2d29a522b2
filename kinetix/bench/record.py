"""`kinetix bench record`: what recording adds per frame to a session-like loop.

The loop is what a play session does per frame at `--fps`: one jitted env step, a 512 px render, a JPEG encode
(the server pushes it to the browser anyway), then sleeping until the next frame. It runs twice, without and
with a Recorder (add_step every frame, add_frame for the kept 10 Hz frames); the busy time per frame is compared,
and the time spent inside the recorder calls is measured on its own. Prints numbers; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import jax
import numpy as np


def _loop(level_file, frames: int, fps: float, recorder=None) -> tuple[np.ndarray, np.ndarray]:
    from kinetix.actions import sample_random_action
    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.recording.play import encode_jpeg
    from kinetix.recording.replay import step_function
    from kinetix.render import render_pixels, to_uint8

    config = EnvConfig(size=level_file.size, frame_skip=level_file.params.frame_skip)
    env = make_env(config, level_file)
    params = EnvParams.from_level_params(level_file.params)
    step = step_function(config)
    state = env.initial_state(jax.random.PRNGKey(0), params)
    start = state
    keys = jax.random.split(jax.random.PRNGKey(1), frames)
    actions = [np.asarray(sample_random_action(k, config)) for k in keys]
    busy, inside = np.zeros(frames), np.zeros(frames)
    period = 1.0 / fps
    t0 = time.perf_counter()
    for i in range(frames):
        began = time.perf_counter()
        state, reward, terminated, truncated, _ = step(state, actions[i], params)
        jpeg = encode_jpeg(to_uint8(render_pixels(state.level, 512)))
        if recorder is not None:
            r0 = time.perf_counter()
            recorder.add_step(actions[i], reward, terminated, truncated, state)
            if recorder.wants_frame():
                recorder.add_frame(jpeg)
            inside[i] = time.perf_counter() - r0
        if bool(terminated) or bool(truncated):
            state = start
        done = time.perf_counter()
        busy[i] = done - began
        time.sleep(max(0.0, t0 + (i + 1) * period - done))
    return busy * 1e3, inside * 1e3


def run(args: argparse.Namespace) -> int:
    from kinetix.levels import load_level
    from kinetix.recording.writer import Recorder

    level_file = load_level(args.level)
    _loop(level_file, 20, 1000.0)  # compile and warm up
    # Alternate blocks with and without the recorder so that load from other processes hits both alike.
    blocks = 6
    base_parts, rec_parts, inside_parts = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.mcap")
        recorder = Recorder(path, level_file, metadata={"player": "agent", "name": "bench"})
        for _ in range(blocks):
            base_parts.append(_loop(level_file, args.frames // blocks, args.fps)[0])
            busy, inside = _loop(level_file, args.frames // blocks, args.fps, recorder)
            rec_parts.append(busy)
            inside_parts.append(inside)
        c0 = time.perf_counter()
        recorder.close()
        close_ms = (time.perf_counter() - c0) * 1e3
        size = os.path.getsize(path)
    base, rec, inside = np.concatenate(base_parts), np.concatenate(rec_parts), np.concatenate(inside_parts)
    writer_ms = recorder.writer_cpu_seconds * 1e3 / len(rec)
    print(f"level {args.level}, {args.frames} frames at {args.fps:g} fps (step + 512 px render + JPEG per frame)")
    print(f"busy ms/frame without recorder: mean {base.mean():.2f}  p50 {np.median(base):.2f}  "
          f"p95 {np.percentile(base, 95):.2f}")
    print(f"busy ms/frame with recorder:    mean {rec.mean():.2f}  p50 {np.median(rec):.2f}  "
          f"p95 {np.percentile(rec, 95):.2f}")
    added, added50 = rec.mean() - base.mean(), np.median(rec) - np.median(base)
    print(f"added ms/frame (difference): mean {added:+.2f}  p50 {added50:+.2f}")
    print(f"inside recorder calls ms/frame:  mean {inside.mean():.3f}  p50 {np.median(inside):.3f}  "
          f"p95 {np.percentile(inside, 95):.3f}  max {inside.max():.3f}")
    print(f"writer thread CPU ms/frame: {writer_ms:.3f} (runs in 0.1 s bursts, off the caller's thread)")
    print(f"close() {close_ms:.1f} ms; file {size / 1e6:.3f} MB = {size / 1e6 * 1000 / len(rec):.2f} MB per 1000 "
          "steps (frames at 10 Hz of wall time)")
    return 0
