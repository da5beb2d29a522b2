"""Turn on JAX's persistent compilation cache, so a second run on the same machine skips most compiling."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """The cache directory when none is given: env KINETIX_JAX_CACHE, then JAX's own
    JAX_COMPILATION_CACHE_DIR, then the user's cache directory (never inside the repository)."""
    for variable in ("KINETIX_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR"):
        if os.environ.get(variable):
            return Path(os.environ[variable]).expanduser()
    user_cache = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(user_cache) / "kinetix" / "jax"


def enable_compilation_cache(path: str | os.PathLike[str] | None = None) -> Path:
    """Store every compiled JAX program under `path` (default: `default_cache_dir()`) and return the directory.

    Call it before the first compilation: JAX opens the cache once, at its first compile, and keeps that directory.
    """
    import jax  # imported here so that importing this module stays cheap

    cache_dir = Path(path).expanduser() if path is not None else default_cache_dir()
    cache_dir.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(cache_dir))
    # Our steps compile in well under JAX's default 1 s threshold, yet there are many of them:
    # cache them all, whatever their compile time or size.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return cache_dir
