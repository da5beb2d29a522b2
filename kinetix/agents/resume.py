"""Resumable training: the whole state of a `kinetix train` run, saved so another job can continue it exactly.

A run's output directory gets `resume/state-<update>.msgpack`, one file per save (the newest KEEP kept). A file is

    MAGIC  sha256(payload) (32 bytes)  payload

and the payload is flax.serialization msgpack (the serialisation of agent checkpoints) of

    {"meta": JSON text: {"format", "version", "run": what defines the run (compared on resume),
                         "arguments": what `kinetix train --resume DIR` fills in, "history": the per-update
                         metrics so far (the learning curve continues), "elapsed": seconds trained so far},
     "arrays": {tree path: array} for every leaf of the PPO Runner: parameters, optimiser state, environments
               mid-episode, curriculum buffer (PLR/SFL), RNG key (as its raw key data) and update index}

Saving writes a hidden temporary file in the same directory, fsyncs it and renames it into place (os.replace is
atomic), then fsyncs the directory: a kill at any moment leaves the previous file whole. Loading takes the newest
file whose checksum holds and skips (with a warning) damaged ones, so even a file truncated by a crashed disk
falls back to the one before.

Multi-process runs (jax.distributed): every process calls `host_tree` (it gathers the env-batched arrays that
span processes, a collective); only process 0 writes. On resume every process reads the same file (the output
directory must be on a filesystem all processes see) and `restore` places each array on the sharding of a
freshly initialised Runner, so a run may resume on a different number of devices or processes.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization

import jax2d
from kinetix.agents.checkpoint import CheckpointError

FORMAT = "kinetix-train-state"
VERSION = 1
MAGIC = b"KINETIX-TRAIN-STATE\n"
DIR_NAME = "resume"  # inside the run's output directory
KEEP = 2  # newest state files kept: the last good one survives a damaged newest
FILE_PATTERN = re.compile(r"^state-(\d+)\.msgpack$")
# What a compact state keeps (`python -m kinetix.agents.resume compact DIR`): the run's learning (parameters,
# optimiser, curriculum buffer and scores, RNG key, update index) without its environments mid-episode and their
# observations, which are most of a full state's bytes (at 128 envs on random-all: 4.9 MB -> 2.0 MB; they grow
# with the envs, the rest does not). A run resumed from one restarts every environment on a fresh level: one
# episode per env is cut short, nothing learned is lost. Small enough to commit, so a later sitting on a machine
# that has only the repository continues the run.
CARRIED = (".train_state", ".curriculum", ".key", ".update_index")


def state_dir(out: str | os.PathLike) -> Path:
    return Path(out) / DIR_NAME


def _is_key(x: Any) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _paths(tree: Any) -> tuple[list[str], list[Any], Any]:
    flat, treedef = jax.tree_util.tree_flatten_with_path(tree)
    return [jax.tree_util.keystr(path) for path, _ in flat], [leaf for _, leaf in flat], treedef


def _to_host(x: Any) -> np.ndarray:
    """One leaf on the host, whole. For an array spread over several processes this is a collective."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        if not x.sharding.is_fully_replicated:
            from jax.sharding import NamedSharding, PartitionSpec

            replicated = (x.sharding.update(spec=PartitionSpec()) if isinstance(x.sharding, NamedSharding)
                          else NamedSharding(jax.sharding.Mesh(np.asarray(jax.devices()), ("all",)),
                                             PartitionSpec()))
            x = jax2d.jit(lambda a: a, out_shardings=replicated)(x)
        return np.asarray(x.addressable_data(0))
    return np.asarray(jax.device_get(x))


def host_tree(tree: Any) -> Any:
    """`tree` with every leaf a whole numpy array on this host; PRNG keys become their raw key data.

    In a multi-process run every process must call it (gathering arrays that span processes is collective)."""
    return jax.tree.map(lambda x: _to_host(jax.random.key_data(x) if _is_key(x) else x), tree)


def flatten(tree: Any) -> dict[str, Any]:
    """{tree path: leaf}, the form `save` stores and `restore` reads (use it on a `host_tree`)."""
    paths, leaves, _ = _paths(tree)
    return dict(zip(paths, leaves, strict=True))


def _carried(path: str) -> bool:
    return any(path == field or path.startswith((field + ".", field + "[")) for field in CARRIED)


def compact(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays a compact state keeps (CARRIED): a run's learning without its environments mid-episode."""
    return {path: array for path, array in arrays.items() if _carried(path)}


def is_compact(arrays: dict[str, np.ndarray]) -> bool:
    return bool(arrays) and all(_carried(path) for path in arrays)


def restore(template: Any, arrays: dict[str, np.ndarray]) -> Any:
    """`template` (a freshly initialised Runner) with every leaf replaced by the saved array of the same path,
    placed on the template leaf's sharding. A missing, extra or differently shaped array is a CheckpointError;
    from a compact state (`is_compact`) the leaves it lacks (the environments) stay the template's fresh ones."""
    paths, leaves, treedef = _paths(template)
    if is_compact(arrays):
        arrays = {**{p: (jax.random.key_data(x) if _is_key(x) else x) for p, x in zip(paths, leaves, strict=True)
                     if not _carried(p)}, **arrays}
    missing, extra = sorted(set(paths) - set(arrays)), sorted(set(arrays) - set(paths))
    if missing or extra:
        raise CheckpointError(f"the training state does not fit this run's trainer (missing {missing[:3]}, "
                              f"unexpected {extra[:3]}): it was written by another version or configuration")
    restored = []
    for path, leaf in zip(paths, leaves, strict=True):
        saved = np.asarray(arrays[path])
        data = jax.random.key_data(leaf) if _is_key(leaf) else leaf
        if saved.shape != data.shape or saved.dtype != data.dtype:
            raise CheckpointError(f"the training state's {path} is {saved.dtype}{list(saved.shape)}, this run "
                                  f"needs {data.dtype}{list(data.shape)}: it was written by another configuration")
        placed = jax.make_array_from_callback(saved.shape, data.sharding, lambda index, saved=saved: saved[index])
        restored.append(jax.random.wrap_key_data(placed, impl=jax.random.key_impl(leaf)) if _is_key(leaf)
                        else placed)
    return jax.tree_util.tree_unflatten(treedef, restored)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # platforms without directory file descriptors
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save(out: str | os.PathLike, update: int, meta: dict, arrays: dict[str, np.ndarray]) -> Path:
    """Write `out/resume/state-<update>.msgpack` atomically and prune older files (KEEP newest) and leftovers of
    interrupted writes. Returns the file written."""
    directory = state_dir(out)
    directory.mkdir(parents=True, exist_ok=True)
    document = dict(meta, format=FORMAT, version=VERSION)
    payload = serialization.msgpack_serialize({"meta": json.dumps(document), "arrays": arrays})
    final = directory / f"state-{update:09d}.msgpack"
    tmp = directory / f".{final.name}.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as handle:
            handle.write(MAGIC + hashlib.sha256(payload).digest() + payload)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(directory)
    for old in _state_files(directory)[KEEP:]:
        old.unlink(missing_ok=True)
    for leftover in directory.glob(".state-*.tmp"):  # a write killed before its rename
        leftover.unlink(missing_ok=True)
    return final


def _state_files(directory: Path) -> list[Path]:
    """State files, newest (highest update) first."""
    found = [(int(m.group(1)), p) for p in directory.iterdir() if (m := FILE_PATTERN.match(p.name))]
    return [p for _, p in sorted(found, reverse=True)]


def _read(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    data = path.read_bytes()
    head = len(MAGIC)
    if not data.startswith(MAGIC) or len(data) < head + 32:
        raise CheckpointError(f"{path} is not a kinetix training state")
    if hashlib.sha256(data[head + 32:]).digest() != data[head:head + 32]:
        raise CheckpointError(f"{path} is damaged (checksum mismatch: truncated or corrupted)")
    try:
        content = serialization.msgpack_restore(data[head + 32:])
        meta = json.loads(content["meta"])
        arrays = dict(content["arrays"])
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path} is damaged: {error}") from None
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise CheckpointError(f"{path} has format {meta.get('format')!r} version {meta.get('version')!r}; this "
                              f"code reads {FORMAT} version {VERSION}")
    return meta, arrays


def load_latest(out: str | os.PathLike) -> tuple[dict, dict[str, np.ndarray], Path]:
    """(meta, arrays, file) of the newest intact state of the run in `out`; damaged newer files are skipped with
    a warning. CheckpointError when there is none."""
    directory = state_dir(out)
    if not directory.is_dir():
        raise CheckpointError(f"{out} has no training state to resume ({directory} does not exist): start it without "
                              f"--resume (every run writes its state there at the end, and along the way with "
                              f"--checkpoint-every)")
    problems = []
    for path in _state_files(directory):
        try:
            meta, arrays = _read(path)
        except (OSError, CheckpointError) as error:
            problems.append(str(error))
            continue
        for problem in problems:
            warnings.warn(f"skipping {problem}; resuming from the older {path.name}", stacklevel=2)
        return meta, arrays, path
    detail = f": {'; '.join(problems)}" if problems else ""
    raise CheckpointError(f"no intact training state in {directory}{detail}")


def compare_runs(saved: dict, current: dict, ignore: tuple[str, ...] = ()) -> None:
    """CheckpointError naming every setting where the saved run differs from the one being started; settings
    named in `ignore` (dotted paths, e.g. "train.total_timesteps") may differ."""
    differences = []

    def walk(a: Any, b: Any, prefix: str) -> None:
        if prefix in ignore:
            return
        if isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(set(a) | set(b)):
                walk(a.get(key), b.get(key), f"{prefix}.{key}" if prefix else key)
        elif a != b:
            differences.append(f"{prefix}: {a!r} in the checkpoint, {b!r} now")

    walk(saved, current, "")
    if differences:
        raise CheckpointError("the checkpoint was written by a different training configuration (resume with the "
                              "same settings, or start a new run): " + "; ".join(differences))


def compact_latest(out: str | os.PathLike) -> tuple[Path, int, int]:
    """Rewrite the newest intact state of the run in `out` as a compact one (same file name, atomically) and
    remove the older state files. Returns (file, bytes before, bytes after)."""
    meta, arrays, path = load_latest(out)
    before = path.stat().st_size
    update = int(FILE_PATTERN.match(path.name).group(1))
    meta = {k: v for k, v in meta.items() if k not in ("format", "version")}
    written = save(out, update, dict(meta, compact=True), compact(arrays))
    for old in _state_files(state_dir(out)):
        if old != written:
            old.unlink(missing_ok=True)
    return written, before, written.stat().st_size


def main(argv: list[str] | None = None) -> int:
    """`python -m kinetix.agents.resume compact DIR`: shrink a run's training state to commit it."""
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog="python -m kinetix.agents.resume",
                                     description="compact a run's newest training state (see CARRIED)")
    parser.add_argument("action", choices=["compact"])
    parser.add_argument("out", metavar="DIR", help="the run's output directory")
    args = parser.parse_args(argv)
    try:
        path, before, after = compact_latest(args.out)
    except CheckpointError as error:
        print(f"compact: {error}", file=sys.stderr)
        return 2
    print(f"{path}: {before / 1e6:.1f} MB -> {after / 1e6:.1f} MB (environments restart on fresh levels on resume)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
