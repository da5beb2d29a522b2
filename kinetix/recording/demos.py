"""`kinetix export-demos`: recordings -> a demonstration dataset (.npz shards + manifest.json).

Observations are recomputed by re-simulating each recording (they are not stored in recordings). Per step i a
shard holds the observation the player saw before acting, the action, the reward and the end flags:
  obs (flat: (T, D) float32; pixels: (T, R, R, 3) float32) or obs_<name> for each entity-observation array,
  actions (T, 6) int32 / (T,) int32 / (T, 6) float32, rewards (T,) float32, terminated, truncated, dones (T,) bool,
  episode (T,) int32 (index into the manifest's "episodes").
The output directory is built under a temporary name and renamed into place, so it is complete or absent.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

import jax2d
from kinetix.level import LevelError, size_class
from kinetix.recording.errors import RecordingError
from kinetix.recording.reader import Recording, read_recording
from kinetix.recording.replay import replay_states

MANIFEST_VERSION = 1


@functools.cache
def _observe(kind: str, resolution: int):
    from kinetix.observations import observe

    return jax2d.jit(lambda level: observe(level, kind, resolution))


def find_recordings(inputs: list[str]) -> list[Path]:
    found: list[Path] = []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            found.extend(sorted(path.rglob("*.mcap")))
        elif path.is_file():
            found.append(path)
        else:
            raise RecordingError(f"{path}: no such file or directory")
    if not found:
        raise RecordingError(f"no .mcap recordings found in {', '.join(inputs)}")
    return found


def _resized(recording: Recording, size) -> Recording:
    if recording.level_file.size.capacity == size.capacity:
        return recording
    from kinetix.levels import resize

    return dataclasses.replace(recording, level_file=resize(recording.level_file, size))


def episode_arrays(recording: Recording, kind: str, resolution: int = 64) -> dict[str, np.ndarray]:
    """The per-step arrays of one recording (observations before each action)."""
    observe = _observe(kind, resolution)
    obs = [observe(recording.level_file.level)]
    for i, state, _ in replay_states(recording, kind):
        ended = recording.terminated[i] or recording.truncated[i]
        obs.append(observe(recording.level_file.level if ended else state.level))
    obs = obs[: recording.num_steps]
    if isinstance(obs[0], dict):
        arrays = {f"obs_{k}": np.stack([np.asarray(o[k]) for o in obs]) for k in obs[0]} if obs else {}
    else:
        arrays = {"obs": np.stack([np.asarray(o) for o in obs])} if obs else {}
    return {**arrays, "actions": recording.actions, "rewards": recording.rewards,
            "terminated": recording.terminated, "truncated": recording.truncated,
            "dones": recording.terminated | recording.truncated}


def export_demos(inputs: list[str], out: str | os.PathLike, *, size: str | None = None, solved_only: bool = False,
                 obs: str = "flat", shard_steps: int = 100_000, log=print) -> dict:
    """Write the dataset to `out` (must not exist or be empty); returns the manifest."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise RecordingError(f"{out} already exists and is not an empty directory")
    paths = find_recordings(inputs)
    recordings: list[tuple[Path, Recording]] = []
    skipped: list[dict] = []
    for path in paths:
        try:
            recording = read_recording(path, frames=False)
        except RecordingError as error:
            skipped.append({"file": str(path), "reason": str(error)})
            continue
        if solved_only and not recording.solved:
            skipped.append({"file": str(path), "reason": "not solved"})
            continue
        recordings.append((path, recording))
    if not recordings:
        raise RecordingError(f"none of the {len(paths)} recordings can be exported: "
                             + "; ".join(f"{s['file']}: {s['reason']}" for s in skipped[:3]))
    action_types = {r.env["action"] for _, r in recordings}
    if len(action_types) > 1:
        raise RecordingError(f"recordings use different action types ({', '.join(sorted(action_types))}); "
                             "export them separately")
    target = size_class(size) if size else max((r.level_file.size for _, r in recordings),
                                               key=lambda s: (s.polygons + s.circles, s.joints, s.thrusters))
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        manifest = _write(recordings, tmp, target, obs, shard_steps, skipped, log)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


def _write(recordings, tmp: Path, target, obs: str, shard_steps: int, skipped: list, log) -> dict:
    episodes, shards, pending = [], [], []
    pending_steps = 0

    def flush():
        nonlocal pending, pending_steps
        if not pending:
            return
        arrays = {k: np.concatenate([p[k] for p in pending]) for k in pending[0]}
        name = f"shard_{len(shards):05d}.npz"
        np.savez_compressed(tmp / name, **arrays)
        shards.append({"file": name, "steps": int(len(arrays["rewards"])),
                       "arrays": {k: {"shape": list(v.shape), "dtype": str(v.dtype)} for k, v in arrays.items()}})
        pending, pending_steps = [], 0

    for path, recording in recordings:
        try:
            resized = _resized(recording, target)
        except LevelError as error:
            skipped.append({"file": str(path), "reason": f"does not fit size {target.name}: {error}"})
            continue
        arrays = episode_arrays(resized, obs)
        arrays["episode"] = np.full(recording.num_steps, len(episodes), np.int32)
        episodes.append({"file": str(path), "steps": recording.num_steps, "return": float(recording.rewards.sum()),
                         "solved": recording.solved, "player": recording.metadata.get("player", ""),
                         "name": recording.metadata.get("name", ""), "level_id": recording.metadata.get("level_id", ""),
                         "seed": recording.metadata.get("seed", "")})
        log(f"{path}: {recording.num_steps} steps{' (solved)' if recording.solved else ''}")
        pending.append(arrays)
        pending_steps += recording.num_steps
        if pending_steps >= shard_steps:
            flush()
    flush()
    if not episodes:
        raise RecordingError("no recording fits the requested size class")
    manifest = {"version": MANIFEST_VERSION, "observation": obs, "size": target.name,
                "frame_skip": int(recordings[0][1].env["frame_skip"]),
                "action_type": recordings[0][1].env["action"], "steps": sum(e["steps"] for e in episodes),
                "episodes": episodes, "shards": shards, "skipped": skipped}
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def run(args: argparse.Namespace) -> int:
    try:
        manifest = export_demos(args.inputs, args.out, size=args.size, solved_only=args.solved_only, obs=args.obs,
                                shard_steps=args.shard_steps)
    except (RecordingError, LevelError) as error:
        print(f"kinetix export-demos: {error}", file=sys.stderr)
        return 2
    for item in manifest["skipped"]:
        print(f"skipped {item['file']}: {item['reason']}", file=sys.stderr)
    print(f"{args.out}: {len(manifest['episodes'])} episodes, {manifest['steps']} steps, "
          f"{len(manifest['shards'])} shards")
    return 0
