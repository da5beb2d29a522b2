"""Agent checkpoints: a directory holding

    params.msgpack  the network parameters (flax.serialization msgpack: exact float32 round trip)
    config.json     what is needed to rebuild the network and its environment: {"format": "kinetix-agent",
                    "version": 1, "train": TrainConfig fields, "env": {size, observation, action, frame_skip,
                    pixel_resolution}, plus free-form "info" (level, curriculum, steps, command)}

Saving writes a temporary sibling directory and renames it into place, so a checkpoint is never half-written.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization

from kinetix.agents.ppo import TrainConfig, saved_config_fields
from kinetix.env import EnvConfig

FORMAT = "kinetix-agent"
VERSION = 1
PARAMS_FILE = "params.msgpack"
CONFIG_FILE = "config.json"


class CheckpointError(ValueError):
    """A checkpoint directory is missing, incomplete or of an unknown format."""


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    params: Any
    train_config: TrainConfig
    env: dict  # size (name), observation, action, frame_skip, pixel_resolution
    info: dict


def env_description(config: EnvConfig) -> dict:
    return {"size": config.size.name, "observation": config.observation, "action": config.action,
            "frame_skip": config.frame_skip, "pixel_resolution": config.pixel_resolution}


def save(path: str | os.PathLike, params: Any, train_config: TrainConfig, env_config: EnvConfig,
         info: dict | None = None) -> Path:
    """Write a checkpoint directory at `path` atomically (replacing an older checkpoint there)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists() and not (path / CONFIG_FILE).is_file():
        if any(path.iterdir()):
            raise CheckpointError(f"{path} exists and is not a checkpoint; refusing to replace it")
    params = jax.tree.map(np.asarray, jax.device_get(params))
    document = {"format": FORMAT, "version": VERSION, "train": dataclasses.asdict(train_config),
                "env": env_description(env_config), "info": info or {}}
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        (tmp / PARAMS_FILE).write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(params)))
        (tmp / CONFIG_FILE).write_text(json.dumps(document, indent=2) + "\n")
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            path.rename(old)
            tmp.rename(path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def load(path: str | os.PathLike) -> Checkpoint:
    path = Path(path)
    if not path.is_dir():
        raise CheckpointError(f"agent checkpoint {path} is not a directory")
    for name in (CONFIG_FILE, PARAMS_FILE):
        if not (path / name).is_file():
            raise CheckpointError(f"agent checkpoint {path} has no {name}")
    try:
        document = json.loads((path / CONFIG_FILE).read_text())
    except json.JSONDecodeError as error:
        raise CheckpointError(f"{path / CONFIG_FILE} is not valid JSON: {error}") from None
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise CheckpointError(f"{path / CONFIG_FILE} is not a {FORMAT} config")
    if document.get("version") != VERSION:
        raise CheckpointError(f"{path} has checkpoint version {document.get('version')!r}; this code reads {VERSION}")
    try:
        train_config = TrainConfig(**saved_config_fields(document["train"]))
        env = dict(document["env"])
        params = serialization.msgpack_restore((path / PARAMS_FILE).read_bytes())
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"agent checkpoint {path} is damaged: {error}") from None
    return Checkpoint(params, train_config, env, document.get("info", {}))
