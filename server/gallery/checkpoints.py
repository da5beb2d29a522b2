"""A checkpoint directory as one value for the database, and back: how a trained specialist travels between server
processes (server.agents.queue: a run's result; server.gallery.agents: a gallery level's specialists). It lives with
the gallery's storage, which must not import server.agents (tests/server/test_layout.py).

    data = pack_checkpoint(run_dir / "checkpoint")         # bytes: a plain tar of its files (~0.5 MB)
    unpack_checkpoint(data, other_run_dir / "checkpoint")  # written whole or not at all

A checkpoint (kinetix.agents.checkpoint) is a flat folder of a few files: config.json and params.msgpack (517 KB for
the default entity network). Plain tar, not gzip: float32 parameters do not compress (tar.gz of one was 480 KB of
517 KB). Unpacking trusts nothing: only regular files with plain names, within a size cap, into a temporary folder
renamed into place, so a bad value leaves no half-written checkpoint.
"""

from __future__ import annotations

import io
import os
import re
import secrets
import shutil
import tarfile
from pathlib import Path

MAX_CHECKPOINT_BYTES = 64 << 20  # far above any network the tab can train (the default one is 0.5 MB)
MAX_FILES = 16
FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,100}")


class CheckpointError(ValueError):
    """A packed checkpoint that cannot be unpacked; the message says why."""


def pack_checkpoint(folder: str | os.PathLike) -> bytes:
    """The files of a checkpoint folder (no subfolders) as a tar archive."""
    folder = Path(folder)
    files = sorted(path for path in folder.iterdir() if path.is_file())
    if not files:
        raise CheckpointError(f"{folder} holds no checkpoint files")
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as archive:
        for path in files:
            archive.add(path, arcname=path.name, recursive=False)
    return buffer.getvalue()


def unpack_checkpoint(data: bytes, folder: str | os.PathLike) -> Path:
    """Write a packed checkpoint to `folder` (which must not exist yet); returns it."""
    folder = Path(folder)
    if len(data) > MAX_CHECKPOINT_BYTES:
        raise CheckpointError(f"a packed checkpoint of {len(data)} bytes is more than a checkpoint can be")
    partial = folder.with_name(f".{folder.name}.{secrets.token_hex(4)}.part")
    partial.mkdir(parents=True)
    try:
        try:
            with tarfile.open(fileobj=io.BytesIO(bytes(data)), mode="r:") as archive:
                members = archive.getmembers()
                if not members or len(members) > MAX_FILES:
                    raise CheckpointError(f"a packed checkpoint holds {len(members)} files")
                for member in members:
                    if not member.isfile() or not FILE_NAME.fullmatch(member.name):
                        raise CheckpointError(f"a packed checkpoint holds {member.name!r}, not a plain file")
                    (partial / member.name).write_bytes(archive.extractfile(member).read())
        except tarfile.TarError as error:
            raise CheckpointError(f"not a packed checkpoint ({error})") from None
        os.replace(partial, folder)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return folder
