"""Proof of a record: before a play becomes a level's best time and best run, its recording is read and
re-simulated (kinetix.recording.verify), so a best time is one that the gallery's own level really gives.

`why_not_a_record(path, level_id=, player=, steps=, seconds=, level_document=)` returns None when the recording
proves the claim, else a short reason (for the log). It checks, cheapest first: the file reads as a recording; it
names this level and player; its level (every array, bitwise) and params are the gallery's stored level; it holds
exactly `steps` steps, one episode that ends solved at its last step, and `seconds` is those steps' simulated
time; re-simulating its actions reproduces every recorded state bitwise. Re-simulation costs CPU (measured in
docs/gallery.md), so one runs at a time in the process (VERIFY_LOCK); callers run it off the play thread.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from kinetix.level import LevelFile

VERIFY_LOCK = threading.Lock()  # re-simulations queue up rather than share the CPU with the play threads
SECONDS_TOLERANCE = 1e-6  # relative: the claim and the recording compute steps x frame skip x dt alike


def _same_level(a: LevelFile, b: LevelFile) -> bool:
    import jax

    if a.params != b.params:
        return False
    left, left_tree = jax.tree.flatten(a.level)
    right, right_tree = jax.tree.flatten(b.level)
    if left_tree != right_tree:
        return False
    for x, y in zip(left, right, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape or x.dtype != y.dtype or x.tobytes() != y.tobytes():
            return False
    return True


def why_not_a_record(path: Path | None, *, level_id: str, player: str, steps: int, seconds: float,
                     level_document: dict) -> str | None:
    """None if the recording at `path` proves a solve of the gallery level in `steps` steps; else why not."""
    # Imported here: JAX and the recording reader load in a second or two, which the server's start (it answers
    # HTTP before compiling anything, server.play.warmup) should not wait for.
    from kinetix.levels import load_level
    from kinetix.recording import RecordingError, read_recording, verify

    if path is None:
        return "the play has no recording"
    try:
        recording = read_recording(path)
    except (RecordingError, OSError) as error:
        return f"its recording is unreadable: {error}"
    meta = recording.metadata
    if meta.get("level_id") != level_id or meta.get("player") != player:
        return f"its recording is of another play (level {meta.get('level_id')!r}, player {meta.get('player')!r})"
    try:
        stored = load_level(level_document)
    except Exception as error:  # noqa: BLE001 - a level the gallery cannot load proves nothing
        return f"the gallery level does not load: {error}"
    if not _same_level(recording.level_file, stored):
        return "its recording starts from another level than the gallery's"
    env, p = recording.env, stored.params
    try:
        same_env = (int(env["frame_skip"]) == p.frame_skip and float(env["params"]["sim"]["dt"]) == p.dt
                    and int(env["params"]["max_timesteps"]) == p.max_timesteps)
    except (KeyError, TypeError, ValueError):
        same_env = False
    if not same_env:
        return "its recording steps with other settings (frame skip, dt or time limit) than the level's"
    n = recording.num_steps
    if n != steps or n == 0:
        return f"its recording has {n} steps, the play claims {steps}"
    ends = recording.terminated | recording.truncated
    if ends[:-1].any() or not (recording.terminated[-1] and recording.rewards[-1] > 0.5):
        return "its recording is not one episode solved at its last step"
    expected = n * p.frame_skip * p.dt
    if abs(seconds - expected) > SECONDS_TOLERANCE * max(1.0, expected):
        return f"the play claims {seconds:.6g} s, its {n} steps take {expected:.6g} s"
    with VERIFY_LOCK:
        try:
            check = verify(recording)
        except Exception as error:  # noqa: BLE001 - e.g. actions of the wrong shape in an edited file
            return f"its recording cannot be re-simulated: {type(error).__name__}: {error}"
    if not check.ok:
        return f"its recording does not re-simulate: step {check.divergent_step}: {check.detail}"
    return None
