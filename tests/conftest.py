"""Shared test setup: the persistent JAX compilation cache, compiled programs freed after each test module, and
the path to ../shared."""

import os
import tempfile
from pathlib import Path

import jax
import pytest

from kinetix.jaxcache import enable_compilation_cache

SHARED_DIR = Path(__file__).resolve().parents[1].parent / "shared"


def pytest_configure(config: pytest.Config) -> None:
    # Before any test compiles: a second run on the same machine then mostly loads compiled steps from disk.
    enable_compilation_cache()
    # No test may read or change the user's own gallery (~/.local/share/kinetix): anything that falls back to
    # the default data directory gets a throwaway one. Subprocesses inherit it.
    if "KINETIX_DATA" not in os.environ:
        os.environ["KINETIX_DATA"] = tempfile.mkdtemp(prefix="kinetix-test-data-")


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop JAX's in-memory compiled programs after each test module. A worker kept every program it had compiled:
    one of the two grew by ~0.7 GB a minute to 15 GB, and the 24 GB machine swapped (CI took 40 minutes instead of
    22). A later module that needs a program again loads it from the persistent cache above (every program is
    stored there, kinetix.jaxcache), which takes far less than compiling it."""
    yield
    jax.clear_caches()


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The read-only ../shared directory beside the checkout (Kinetix levels, notes)."""
    if not SHARED_DIR.is_dir():
        pytest.skip(f"../shared not found: compatibility tests need the shared Kinetix levels (looked in {SHARED_DIR})")
    return SHARED_DIR
