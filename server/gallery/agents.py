"""Specialist agents attached to gallery levels (table `level_agents`, gallery migration 3).

    agents = LevelAgents(store, data_dir / "agents")
    agent_id = agents.attach(level_id, "run-20261123-a1b2", token=author_token, steps=8192, solve_rate=0.9,
                             mean_return=1.2)
    agents.list(level_id)      # [{"id", "name", "path", "steps", "solve_rate", "mean_return", "created"}], newest first

A row names a checkpoint directory by its plain name inside `agents_dir` (never a path), so a row can never
point outside the data dir; `path` in the listing is the resolved directory. Attaching checks that the
directory holds a checkpoint, so a row never points at a half-written run.

Only the level's author attaches (a decision of issue 26): `attach` needs the author token that owns the level
(or `admin=True`, for server-side tools), checked in the same transaction as the insert. Everyone who opens the
level sees its specialists, so anyone else's agent must not land there; it stays with its tab (server.agents.tab).

Several processes on one PostgreSQL gallery (docs/deploy.md): attaching also stores the packed checkpoint
(server.gallery.checkpoints, ~0.5 MB) in table `agent_checkpoints` in the same transaction, and `list` fetches a
specialist whose folder this process lacks into its own agents dir first, so every process offers every specialist
(as best runs are fetched, server.gallery.runs). With SQLite the folder is the only copy, as before.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

from sqlalchemy import BigInteger, Column, Float, Integer, MetaData, String, Table, delete, select

from server.gallery.checkpoints import CheckpointError, pack_checkpoint, unpack_checkpoint
from server.gallery.checks import Forbidden, Invalid, NotFound, Unauthorized, check_id
from server.gallery.schema import agent_checkpoints_t, now_ms
from server.gallery.store import Store

log = logging.getLogger(__name__)
CHECKPOINT_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}$")
MAX_AGENT_NAME = 64

_meta = MetaData()
level_agents_t = Table(
    "level_agents", _meta, Column("id", BigInteger, primary_key=True), Column("level_id", String(32)),
    Column("name", String(64)), Column("checkpoint", String(255)), Column("steps", Integer),
    Column("solve_rate", Float), Column("mean_return", Float), Column("created", BigInteger))


class LevelAgents:
    def __init__(self, store: Store, agents_dir: str | os.PathLike):
        self.store = store
        self.agents_dir = Path(agents_dir)
        self.shared = store.dialect != "sqlite"  # several processes: the checkpoints live in agent_checkpoints too

    def run_dir(self, name: str) -> Path:
        """The directory of a training run named `name` inside the agents dir (its checkpoint is `/checkpoint`)."""
        if not CHECKPOINT_NAME_RE.match(name or "") or ".." in name:
            raise Invalid(f"agent run name {name!r}: expected a plain directory name")
        return self.agents_dir / name

    def attach(self, level_id: str, run_name: str, *, token: str | None, steps: int, solve_rate: float | None = None,
               mean_return: float | None = None, name: str | None = None, admin: bool = False) -> int:
        """Record the checkpoint of run `run_name` as a specialist of `level_id`; returns the agent's id.

        `token` must be the author token that owns the level (Unauthorized if missing or unknown, Forbidden if
        another author's), unless `admin`."""
        level_id = check_id(level_id)
        checkpoint = self.run_dir(run_name) / "checkpoint"
        if not (checkpoint / "config.json").is_file():
            raise Invalid(f"agent run {run_name!r} has no checkpoint")
        label = (name or f"specialist {run_name}")[:MAX_AGENT_NAME]
        packed = pack_checkpoint(checkpoint) if self.shared else None
        with self.store._write() as conn:
            self._check_author(conn, level_id, token, admin)
            if packed is not None and conn.execute(select(agent_checkpoints_t.c.name).where(
                    agent_checkpoints_t.c.name == run_name)).first() is None:
                conn.execute(agent_checkpoints_t.insert().values(name=run_name, data=packed, created=now_ms()))
            result = conn.execute(level_agents_t.insert().values(
                level_id=level_id, name=label, checkpoint=run_name, steps=int(steps),
                solve_rate=None if solve_rate is None else float(solve_rate),
                mean_return=None if mean_return is None else float(mean_return), created=now_ms()))
            return int(result.inserted_primary_key[0])

    def owns(self, level_id: str, token: str | None) -> bool:
        """Whether `token` is the author token of gallery level `level_id` (False for unknown ones)."""
        try:
            with self.store._read() as conn:
                self._check_author(conn, check_id(level_id), token, admin=False)
        except (Invalid, NotFound, Unauthorized, Forbidden):
            return False
        return True

    def _check_author(self, conn, level_id: str, token: str | None, admin: bool) -> None:
        """The store's owner check (Store._check_owner), with messages that say what attaching needs."""
        try:
            self.store._check_owner(conn, level_id, token, admin)
        except NotFound:
            raise NotFound(f"no level {level_id!r} in the gallery") from None
        except Unauthorized:
            why = "unknown author token" if token else "this needs the author's token"
            raise Unauthorized(f"only the level's author can attach an agent to it: {why}") from None
        except Forbidden:
            raise Forbidden(f"only the level's author can attach an agent to level {level_id!r}; this token does "
                            "not own it (save your own copy of the level to keep your agent with it)") from None

    def list(self, level_id: str) -> list[dict]:
        """The specialists of a level, newest first (rows whose checkpoint is gone are left out)."""
        with self.store._read() as conn:
            rows = conn.execute(select(level_agents_t).where(level_agents_t.c.level_id == level_id)
                                .order_by(level_agents_t.c.created.desc(), level_agents_t.c.id.desc())).all()
        out = []
        for row in rows:
            if not CHECKPOINT_NAME_RE.match(row.checkpoint) or ".." in row.checkpoint:
                continue  # never follow a stored name that could leave the agents dir
            path = self.agents_dir / row.checkpoint / "checkpoint"
            if path.is_dir() or (self.shared and self._fetch(row.checkpoint, path)):
                out.append({"id": int(row.id), "name": row.name, "path": path, "steps": int(row.steps),
                            "solve_rate": row.solve_rate, "mean_return": row.mean_return, "created": row.created})
        return out

    def _fetch(self, run_name: str, path: Path) -> bool:
        """Copy a specialist attached by another process into this one's agents dir; False if it is not stored."""
        with self.store._read() as conn:
            data = conn.execute(select(agent_checkpoints_t.c.data)
                                .where(agent_checkpoints_t.c.name == run_name)).scalar()
        if data is None:
            return False
        try:
            unpack_checkpoint(data, path)
        except (CheckpointError, OSError) as error:
            if path.is_dir():  # another thread of this process fetched it meanwhile
                return True
            log.warning("specialist %s not fetched: %s", run_name, error)
            return False
        return True

    def remove_orphans(self) -> int:
        """Delete stored checkpoints that no specialist names any more (their level was deleted); start-up."""
        if not self.shared:
            return 0
        with self.store._write() as conn:
            return conn.execute(delete(agent_checkpoints_t).where(
                agent_checkpoints_t.c.name.not_in(select(level_agents_t.c.checkpoint)))).rowcount
