"""The OpenAPI document is the API's contract (issue 34): Schemathesis, with every check on, generates requests
from /openapi.json against a running gallery server and finds nothing the document does not say: every status
code a route answers is declared with its body schema, every request the schema allows is accepted (the one
exception is in schemathesis.toml beside this file, with its reason), every request it forbids is refused, and
every error body matches (422's `detail` is a string like every other error's)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.gallery.test_concurrency import _free_port, _start_server

HERE = Path(__file__).resolve().parent


def _schemathesis() -> str:
    found = shutil.which("st", path=str(Path(sys.executable).parent)) or shutil.which("schemathesis")
    if found is None:
        pytest.skip("schemathesis is not installed (pip install -e '.[dev]')")
    return found


def test_schemathesis_with_all_checks_finds_nothing(tmp_path: Path):
    st = _schemathesis()
    port = _free_port()
    # Rate limits off so that the generated writes reach the store's logic (429 is declared and tested in
    # test_hardening.py); no seeding, the stateful phase creates the levels it reads, changes and deletes.
    server = _start_server(tmp_path / "gallery.sqlite3", port, "--write-limit", "0", "--identity-limit", "0")
    try:
        result = subprocess.run(
            [st, "--config-file", str(HERE / "schemathesis.toml"), "run", f"http://127.0.0.1:{port}/openapi.json",
             "--checks", "all", "--max-examples", "25", "--seed", "34", "--no-color"],
            capture_output=True, text=True, timeout=600, cwd=tmp_path)
    finally:
        server.terminate()
        server.wait(timeout=30)
    report = result.stdout + result.stderr
    assert result.returncode == 0, report[-8000:]
    assert " passed" in report and "Failures:" not in report, report[-4000:]
