"""`Recorder`: writes one play to an MCAP file on a background thread, finishing atomically.

The caller's loop only appends to a queue (`add_step`, `add_frame` cost microseconds and never wait for the disk or
for JAX arrays to be ready); a daemon thread turns items into messages and writes them to a hidden temporary file
next to the target. `close()` drains the queue, finishes the MCAP summary, fsyncs and renames the file into place,
so the target path holds either a complete recording or nothing. `abort()` (and leaving a `with` block by an
exception) deletes the temporary file.
"""

from __future__ import annotations

import atexit
import base64
import dataclasses
import io
import json
import os
import queue
import tempfile
import threading
import time
import weakref
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

try:
    import fcntl  # ownership of partial files (see remove_partial_files)
except ImportError:  # pragma: no cover - Windows
    fcntl = None

from kinetix.level import LevelFile
from kinetix.recording import schema
from kinetix.recording.errors import RecordingError

_CLOSE, _ABORT = object(), object()
_BURST_SECONDS = 0.1
_OPEN: weakref.WeakSet = weakref.WeakSet()


@atexit.register
def _abort_open_recorders() -> None:
    # A program that exits without close() (an uncaught exception) must not leave a half file, and must stop the
    # writer thread before the interpreter tears down the modules it uses.
    for recorder in list(_OPEN):
        recorder.abort()


def project_version() -> str:
    try:
        from importlib.metadata import version

        return version("kinetix-playground")
    except Exception:  # not installed (PYTHONPATH checkout): the version in pyproject.toml is not worth parsing here
        return "unknown"


def _plain(value: Any) -> Any:
    """JSON-ready copy of dataclasses / arrays / numbers (float32 widened to double, which is exact)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return np.asarray(value).tolist()
    return value


def env_description(level_file: LevelFile, env_config=None, env_params=None) -> dict:
    """What replay needs to rebuild the env: the action type, frame skip, solver and every runtime parameter.

    Defaults are what playing a level file means: EnvConfig(size, frame_skip=level's) and the level's EnvParams.
    """
    from kinetix.env import EnvConfig, EnvParams

    if env_config is None:
        env_config = EnvConfig(size=level_file.size, frame_skip=level_file.params.frame_skip)
    if env_params is None:
        env_params = EnvParams.from_level_params(level_file.params)
    return {"action": env_config.action, "observation": env_config.observation, "frame_skip": env_config.frame_skip,
            "pixel_resolution": env_config.pixel_resolution, "solver": _plain(env_config.solver),
            "params": _plain(env_params)}


def level_npz(level_file: LevelFile) -> bytes:
    """Every array of the Level, by tree path, as an .npz: the bitwise-exact start of the replay."""
    import jax

    buffer = io.BytesIO()
    arrays = {jax.tree_util.keystr(path): np.asarray(leaf)
              for path, leaf in jax.tree_util.tree_flatten_with_path(level_file.level)[0]}
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _body_arrays(state: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(position, angle, velocity, angular velocity) of all bodies from an EnvState, a Level or a SimState."""
    sim = getattr(getattr(state, "level", state), "sim", state)
    bodies = getattr(sim, "bodies", None)
    if bodies is None:
        raise RecordingError(f"add_step needs an EnvState, Level or SimState, got {type(state).__name__}")
    return (np.asarray(bodies.position, np.float32), np.asarray(bodies.angle, np.float32),
            np.asarray(bodies.velocity, np.float32), np.asarray(bodies.angular_velocity, np.float32))


class Recorder:
    """Record one play of `level_file` to `path` (an .mcap file).

    metadata: free-form, JSON-able; the keys "player" ("human" | "agent"), "name", "level_id" and "seed" are the
    ones readers look for. `env_config` / `env_params` (optional, keyword-only) describe the env when it is not
    the level's default one (EnvConfig(size, frame_skip=level's), EnvParams.from_level_params).

    add_step's `state` is the state *after* the transition and before any auto-reset (what
    `env.step_no_reset` returns); a step that ends an episode is followed by steps from the level's start again.
    """

    def __init__(self, path: str | os.PathLike, level_file: LevelFile, *, metadata: dict | None = None,
                 env_config=None, env_params=None, chunk_size: int = 1 << 20):
        from kinetix.levels import dumps

        self.path = Path(path)
        if self.path.is_dir():
            raise RecordingError(f"{self.path} is a directory, not a file name for the recording")
        if not self.path.parent.is_dir():
            raise RecordingError(f"cannot record to {self.path}: directory {self.path.parent} does not exist")
        metadata = dict(metadata or {})
        try:
            json.dumps(metadata)
        except (TypeError, ValueError) as error:
            raise RecordingError(f"recording metadata must be JSON-serialisable: {error}") from None
        active = np.flatnonzero(np.asarray(level_file.level.sim.bodies.active))
        self._bodies = active
        self._env = env_description(level_file, env_config, env_params)
        self._level_json = dumps(level_file, "ours")
        self._level_npz = level_npz(level_file)
        self._start_ns = time.time_ns()
        self._start_mono = time.monotonic()
        self._last_frame_t = -np.inf
        self._last_log = 0
        self._steps = 0
        self._closed = False
        self._error: BaseException | None = None
        self.writer_cpu_seconds = 0.0
        self._summary = {"steps": 0, "return": 0.0, "solved": False, "failed": False, "episodes": 0, "frames": 0}
        self._meta = {
            "format_version": schema.FORMAT_VERSION,
            "player": str(metadata.get("player", "unknown")),
            "name": str(metadata.get("name", "")),
            "level_id": str(metadata.get("level_id", level_file.name or "")),
            "seed": str(metadata.get("seed", 0)),
            "project_version": project_version(),
            "size": level_file.size.name,
            "env": json.dumps(self._env),
            "bodies": json.dumps(active.tolist()),
            "started_at_ns": str(self._start_ns),
            "extra": json.dumps(metadata),
        }
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".part", dir=self.path.parent)
        # Claim the file for this process (see remove_partial_files) through a second descriptor, so the claim
        # lasts past the writer thread's close of the file until it is renamed into place or deleted.
        self._claim = _claim(fd)
        self._tmp = Path(tmp)
        self._file = os.fdopen(fd, "wb")
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._chunk_size = chunk_size
        self._thread = threading.Thread(target=self._run, name=f"recorder {self.path.name}", daemon=True)
        self._thread.start()
        _OPEN.add(self)

    # ------------------------------------------------------------ caller side (cheap, never waits)

    def _now(self) -> float:
        return time.monotonic() - self._start_mono

    def add_step(self, action, reward, terminated, truncated, state, t: float | None = None, *,
                 batch: int = 1) -> None:
        """One env step. `t`: seconds since the recording started (default: the wall clock). `batch`: the step
        was computed by `jax.vmap` of the transition over this many plays (the browser server batches tabs), whose
        results differ bitwise from a single step; replay then steps the same way (replay.batched_step_function)."""
        self._check_open()
        self._queue.put(("step", self._now() if t is None else float(t), action, reward, terminated, truncated,
                         state, int(batch)))

    def wants_frame(self, t: float | None = None) -> bool:
        """Whether a frame at `t` would be kept (frames are kept at most every 1/10 s): skip encoding otherwise."""
        t = self._now() if t is None else float(t)
        return t >= self._last_frame_t + 1.0 / schema.MAX_FRAME_HZ - 1e-6

    def add_frame(self, jpeg_bytes: bytes, t: float | None = None) -> bool:
        """A rendered JPEG frame at `t` seconds; dropped (returns False) within 1/10 s of the last kept one."""
        self._check_open()
        t = self._now() if t is None else float(t)
        if not self.wants_frame(t):
            return False
        self._last_frame_t = t
        self._queue.put(("frame", t, bytes(jpeg_bytes)))
        return True

    def close(self) -> Path:
        """Finish the file and move it into place; raises RecordingError (leaving nothing) if writing failed."""
        if self._closed:
            return self.path
        self._closed = True
        _OPEN.discard(self)
        self._queue.put(_CLOSE)
        self._thread.join()
        try:
            if self._error is not None:
                self._tmp.unlink(missing_ok=True)
                raise RecordingError(f"writing {self.path} failed: {self._error}") from self._error
            from kinetix.levels import _umask

            os.chmod(self._tmp, 0o666 & ~_umask())  # mkstemp makes it 0600; a finished recording is an ordinary file
            os.replace(self._tmp, self.path)
        finally:
            _release(self._claim)
        return self.path

    def abort(self) -> None:
        """Stop and delete everything written so far; the target path is left untouched."""
        if self._closed:
            return
        self._closed = True
        _OPEN.discard(self)
        self._queue.put(_ABORT)
        self._thread.join()
        self._tmp.unlink(missing_ok=True)
        _release(self._claim)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, kind, error, tb) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"the recording {self.path} is already closed")
        if self._error is not None:
            raise RecordingError(f"writing {self.path} failed: {self._error}")

    # ------------------------------------------------------------ writer thread

    def _log_time(self, t: float) -> int:
        # MCAP readers want log times that do not go backwards within a channel; clamp clock hiccups.
        ns = max(self._start_ns + int(round(t * 1e9)), self._last_log)
        self._last_log = ns
        return ns

    def _run(self) -> None:
        aborted = False
        cpu0 = time.thread_time()
        try:
            writer = Writer(self._file, chunk_size=self._chunk_size, compression=CompressionType.ZSTD)
            writer.start(profile=schema.PROFILE, library=f"kinetix-playground {self._meta['project_version']}")
            ids = {}
            for topic, name, body in ((schema.TOPIC_LEVEL, "kinetix.Level", schema.LEVEL_SCHEMA),
                                      (schema.TOPIC_STEP, "kinetix.Step", schema.STEP_SCHEMA),
                                      (schema.TOPIC_STATE, "kinetix.BodyStates", schema.STATE_SCHEMA),
                                      (schema.TOPIC_CAMERA, "foxglove.CompressedImage", schema.COMPRESSED_IMAGE)):
                schema_id = writer.register_schema(name, "jsonschema", schema.schema_bytes(body))
                ids[topic] = writer.register_channel(topic, "json", schema_id)
            writer.add_metadata(schema.METADATA, self._meta)
            writer.add_message(ids[schema.TOPIC_LEVEL], self._start_ns, self._level_json.encode(), self._start_ns)
            writer.add_attachment(self._start_ns, self._start_ns, schema.LEVEL_ATTACHMENT, "application/x-npz",
                                  self._level_npz)
            while True:
                if self._queue.empty():
                    # Work in bursts: waking on every put would take the GIL from the caller 30+ times a second.
                    time.sleep(_BURST_SECONDS)
                item = self._queue.get()
                if item is _ABORT:
                    aborted = True
                    break
                if item is _CLOSE:
                    break
                if item[0] == "step":
                    self._write_step(writer, ids, *item[1:])
                else:
                    self._write_frame(writer, ids, *item[1:])
            if not aborted:
                writer.add_metadata(schema.SUMMARY, {k: json.dumps(v) for k, v in self._summary.items()})
                writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
        except BaseException as error:  # reported by close(); the caller's loop never sees the thread die
            self._error = error
            while not aborted:  # keep draining so queued jax arrays are released
                item = self._queue.get()
                if item is _CLOSE or item is _ABORT:
                    break
        finally:
            self._file.close()
            self.writer_cpu_seconds = time.thread_time() - cpu0  # what recording cost the machine, for benchmarks

    def _write_step(self, writer: Writer, ids: dict, t: float, action, reward, terminated, truncated, state,
                    batch: int) -> None:
        index = self._summary["steps"]
        log = self._log_time(t)
        action = np.asarray(action)
        reward = float(np.float32(reward))
        terminated, truncated = bool(terminated), bool(truncated)
        step = {"step": index, "action": action.tolist(), "reward": reward, "terminated": terminated,
                "truncated": truncated}
        if batch != 1:  # absent for single steps, so such files are as before
            step["batch"] = batch
        writer.add_message(ids[schema.TOPIC_STEP], log, schema.dumps(step), log, sequence=index)
        position, angle, velocity, angular = _body_arrays(state)
        b = self._bodies
        body = {"step": index, "bodies": b.tolist(), "position": position[b].tolist(), "rotation": angle[b].tolist(),
                "velocity": velocity[b].tolist(), "angular_velocity": angular[b].tolist()}
        writer.add_message(ids[schema.TOPIC_STATE], log, schema.dumps(body), log, sequence=index)
        s = self._summary
        s["steps"] = index + 1
        s["return"] = float(np.float32(s["return"]) + np.float32(reward))
        if terminated or truncated:
            s["episodes"] += 1
            s["solved"] = s["solved"] or (terminated and reward > 0.5)  # +1 win, plus at most a small shaping term
            s["failed"] = s["failed"] or (terminated and reward < -0.5)

    def _write_frame(self, writer: Writer, ids: dict, t: float, jpeg: bytes) -> None:
        log = self._log_time(t)
        message = {"timestamp": {"sec": log // 1_000_000_000, "nsec": log % 1_000_000_000},
                   "frame_id": schema.FRAME_ID, "format": "jpeg", "data": base64.b64encode(jpeg).decode()}
        writer.add_message(ids[schema.TOPIC_CAMERA], log, schema.dumps(message), log, sequence=self._summary["frames"])
        self._summary["frames"] += 1


# Who owns a partial file: the process that writes it holds an exclusive flock on it for as long as the file is
# open. The kernel drops the lock when the process ends however it ends (kill -9 included), so a `.part` file that
# can be locked has no writer left, whatever its age, and a process id reused by another program cannot make a
# dead writer's file look owned (as a pid in the name could). Where flock does not exist (Windows), ownership
# cannot be known and only files older than `older_than` are removed, as before.
PARTIAL_MIN_AGE_S = 10.0  # a file this fresh may be between its creation and its writer's lock: left alone


def _claim(fd: int) -> int | None:
    """Lock the new file `fd` for this process; a duplicate descriptor that holds the lock (None without flock)."""
    if fcntl is None:
        return None
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # cannot fail: mkstemp just created the file
    return os.dup(fd)  # the lock belongs to the open file, so it lasts until both descriptors are closed


def _release(claim: int | None) -> None:
    if claim is not None:
        os.close(claim)


def _unlink_if_unowned(path: Path) -> bool:
    """Delete `path` if no process holds its lock (checked and deleted while holding the lock ourselves)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False  # a live recorder's file
        path.unlink(missing_ok=True)
        return True
    finally:
        os.close(fd)


def remove_partial_files(directory: str | os.PathLike, older_than: float = 3600.0,
                         min_age: float = PARTIAL_MIN_AGE_S) -> list[Path]:
    """Delete the hidden `.NAME.*.part` files that recordings of an ended process left in `directory`: every one
    at least `min_age` seconds old that no live process owns (see _claim), or, without file locks, those older
    than `older_than` seconds. For the server at start-up and after plays; a live recorder's file is never touched."""
    removed = []
    now = time.time()
    for path in Path(directory).glob(".*.mcap.*.part"):
        try:
            age = now - path.stat().st_mtime
            if fcntl is not None:
                if age >= min_age and _unlink_if_unowned(path):
                    removed.append(path)
            elif age >= older_than:
                path.unlink()
                removed.append(path)
        except FileNotFoundError:
            pass
    return removed
