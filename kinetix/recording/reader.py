"""Reading recordings back: `read_recording(path_or_bytes) -> Recording`, with a RecordingError for anything else."""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from kinetix.level import LevelFile
from kinetix.recording import schema
from kinetix.recording.errors import RecordingError

MAGIC = b"\x89MCAP0\r\n"
# Decompressed bytes a recording may hold. A 10-minute play with frames is tens of MB; the bound is what keeps a
# small upload that inflates to many GB (a compression bomb) from filling the server's memory.
MAX_UNCOMPRESSED = 1 << 30


@dataclasses.dataclass
class Recording:
    """A whole recording in memory. Arrays have one row per env step (T of them); K = number of active bodies."""

    level_file: LevelFile  # bitwise the level the play started from
    level_json: str  # the /level message (our format)
    metadata: dict  # player, name, level_id, seed, project_version, size, started_at_ns, extra (dict), env (dict)
    summary: dict  # steps, return, solved, failed, episodes, frames
    env: dict  # action, observation, frame_skip, pixel_resolution, solver, params (see writer.env_description)
    actions: np.ndarray  # (T, ...) int32 or float32, exactly as played
    rewards: np.ndarray  # (T,) float32
    terminated: np.ndarray  # (T,) bool
    truncated: np.ndarray  # (T,) bool
    step_times: np.ndarray  # (T,) float64 seconds since the start
    bodies: np.ndarray  # (K,) int32 global body indices
    position: np.ndarray  # (T, K, 2) float32, after each step
    rotation: np.ndarray  # (T, K) float32
    velocity: np.ndarray  # (T, K, 2) float32
    angular_velocity: np.ndarray  # (T, K) float32
    frame_times: np.ndarray  # (F,) float64 seconds since the start
    frames: list[bytes]  # (F,) JPEG bytes
    batches: np.ndarray | None = None  # (T,) int32: 1 for a single step, n for a step vmapped over n plays

    @property
    def num_steps(self) -> int:
        return len(self.rewards)

    @property
    def solved(self) -> bool:
        return bool(np.any(self.terminated & (self.rewards > 0.5)))

    def frame_step(self, i: int) -> int:
        """The index of the last step at or before frame i (-1: before the first step)."""
        return int(np.searchsorted(self.step_times, self.frame_times[i], side="right")) - 1

    def iter_frames(self) -> Iterator[tuple[float, bytes]]:
        yield from zip(self.frame_times.tolist(), self.frames, strict=True)


def _open(source: str | os.PathLike | bytes) -> tuple[bytes, str]:
    if isinstance(source, bytes | bytearray | memoryview):
        return bytes(source), "the recording"
    path = Path(source)
    try:
        return path.read_bytes(), str(path)
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise RecordingError(f"{path} is a directory, not a recording") from None
    except OSError as error:
        raise RecordingError(f"{path}: cannot read: {error.strerror}") from None


def _level_from(level_json: str, npz: bytes | None, name: str) -> LevelFile:
    import jax
    import jax.numpy as jnp

    from kinetix.level import LevelError
    from kinetix.levels import load_level

    try:
        level_file = load_level(json.loads(level_json))
    except (LevelError, ValueError) as error:
        raise RecordingError(f"{name}: the recorded level does not load: {error}") from None
    if npz is None:
        return level_file
    try:
        arrays = np.load(io.BytesIO(npz), allow_pickle=False)
        leaves, treedef = jax.tree_util.tree_flatten_with_path(level_file.level)
        exact = []
        for path, leaf in leaves:
            value = arrays[jax.tree_util.keystr(path)]
            if value.shape != leaf.shape or value.dtype != leaf.dtype:
                raise ValueError(f"{jax.tree_util.keystr(path)} has shape {value.shape} {value.dtype}, "
                                 f"expected {leaf.shape} {leaf.dtype}")
            exact.append(jnp.asarray(value))
    except (ValueError, KeyError, OSError) as error:
        raise RecordingError(f"{name}: the exact level attachment is damaged: {error}") from None
    return dataclasses.replace(level_file, level=jax.tree_util.tree_unflatten(treedef, exact))


def _check_chunk_sizes(data: bytes, name: str) -> None:
    """Refuse, before decompressing anything, chunks that would inflate past MAX_UNCOMPRESSED bytes in all.

    A chunk's declared size bounds what the reader allocates only if the zstd frame agrees with it, so the
    frame's own content size is checked too; lz4 chunks have no such bound and are refused (we never write them).
    """
    limit, total = MAX_UNCOMPRESSED, 0
    for record in StreamReader(io.BytesIO(data), emit_chunks=True).records:
        if not isinstance(record, Chunk):
            continue
        if record.compression not in ("", "zstd"):
            raise RecordingError(f"{name} uses {record.compression!r} chunk compression; recordings use zstd")
        size = record.uncompressed_size
        if record.compression == "zstd":
            framed = zstandard.frame_content_size(record.data)
            if framed > size:
                raise RecordingError(f"{name} is corrupt: a chunk inflates to {framed} bytes, declared {size}")
        total += size
        if total > limit:
            raise RecordingError(f"{name} is too large: it inflates to more than {limit // 2**20} MB")


def read_recording(source: str | os.PathLike | bytes, *, frames: bool = True) -> Recording:
    """Read a whole recording; `frames=False` skips decoding the JPEGs (faster for replay checks and exports)."""
    data, name = _open(source)
    if not data.startswith(MAGIC):
        raise RecordingError(f"{name} is not an MCAP file (it does not start with the MCAP magic bytes)")
    if len(data) < 2 * len(MAGIC) or not data.endswith(MAGIC):
        raise RecordingError(f"{name} is truncated: the MCAP file ends before its footer (cut short?)")
    try:
        _check_chunk_sizes(data, name)
        reader = make_reader(io.BytesIO(data), validate_crcs=True)
        header = reader.get_header()
        if header.profile != schema.PROFILE:
            raise RecordingError(f"{name} is an MCAP file but not a kinetix recording "
                                 f"(profile {header.profile!r}, expected {schema.PROFILE!r})")
        meta: dict = {}
        summary: dict = {}
        for record in reader.iter_metadata():
            if record.name == schema.METADATA:
                meta = dict(record.metadata)
            elif record.name == schema.SUMMARY:
                summary = {k: json.loads(v) for k, v in record.metadata.items()}
        npz = None
        for attachment in reader.iter_attachments():
            if attachment.name == schema.LEVEL_ATTACHMENT:
                npz = attachment.data
        level_json = None
        steps, states, frame_list = [], [], []
        topics = [schema.TOPIC_LEVEL, schema.TOPIC_STEP, schema.TOPIC_STATE] + ([schema.TOPIC_CAMERA] if frames else [])
        for _, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
            if channel.topic == schema.TOPIC_LEVEL:
                level_json = message.data.decode()
            elif channel.topic == schema.TOPIC_STEP:
                steps.append((message.log_time, json.loads(message.data)))
            elif channel.topic == schema.TOPIC_STATE:
                states.append(json.loads(message.data))
            else:
                frame_list.append((message.log_time, json.loads(message.data)))
    except RecordingError:
        raise
    except (McapError, ValueError, KeyError, EOFError, UnicodeDecodeError, AssertionError) as error:
        raise RecordingError(f"{name} is corrupt: {type(error).__name__}: {error}") from None
    missing = [what for what, ok in (("metadata", meta), ("level", level_json)) if not ok]
    if missing or "env" not in meta:
        raise RecordingError(f"{name} is not a complete kinetix recording: missing {', '.join(missing) or 'env'}")
    if len(steps) != len(states):
        raise RecordingError(f"{name} is corrupt: {len(steps)} step messages but {len(states)} state messages")
    return _assemble(name, meta, summary, level_json, npz, steps, states, frame_list)


def _assemble(name, meta, summary, level_json, npz, steps, states, frame_list) -> Recording:
    try:
        env = json.loads(meta["env"])
        meta = dict(meta, env=env, extra=json.loads(meta.get("extra", "{}")))
        start = int(meta["started_at_ns"])
        bodies = np.asarray(json.loads(meta["bodies"]), np.int32)
        steps.sort(key=lambda item: item[1]["step"])
        states.sort(key=lambda item: item["step"])
        if [s["step"] for _, s in steps] != list(range(len(steps))) or [s["step"] for s in states] != list(
                range(len(states))):
            raise ValueError("step numbers are not 0, 1, 2, ...")
        dtype = np.float32 if env["action"] == "continuous" else np.int32
        k = len(bodies)

        def column(key, shape):
            out = np.asarray([s[key] for s in states], np.float32)
            return out.reshape((len(states), k, *shape))

        frame_list.sort(key=lambda item: item[0])
        recording = Recording(
            level_file=_level_from(level_json, npz, name), level_json=level_json, metadata=meta, summary=summary,
            env=env,
            actions=np.asarray([s["action"] for _, s in steps], dtype),
            rewards=np.asarray([s["reward"] for _, s in steps], np.float32),
            terminated=np.asarray([s["terminated"] for _, s in steps], bool),
            truncated=np.asarray([s["truncated"] for _, s in steps], bool),
            step_times=(np.asarray([t for t, _ in steps], np.int64) - start) / 1e9,
            bodies=bodies, position=column("position", (2,)), rotation=column("rotation", ()),
            velocity=column("velocity", (2,)), angular_velocity=column("angular_velocity", ()),
            frame_times=(np.asarray([t for t, _ in frame_list], np.int64) - start) / 1e9,
            frames=[base64.b64decode(f["data"]) for _, f in frame_list],
            batches=np.asarray([int(s.get("batch", 1)) for _, s in steps], np.int32),
        )
        if np.any(recording.batches < 1):
            raise ValueError("a step's batch size is below 1")
    except RecordingError:
        raise
    except (ValueError, KeyError, TypeError) as error:
        raise RecordingError(f"{name} is corrupt: {type(error).__name__}: {error}") from None
    if recording.actions.ndim == 1 and env["action"] != "discrete" and len(steps):
        raise RecordingError(f"{name} is corrupt: actions have the wrong shape {recording.actions.shape}")
    return recording
