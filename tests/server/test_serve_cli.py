"""`kinetix serve` as a user runs it: prints one URL, serves the page there, and exits cleanly on Ctrl+C."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _serve(tmp_path, *options: str, until: str) -> tuple[subprocess.Popen, list[str]]:
    """`kinetix serve` on a free port with its data in tmp_path (away from the user's own gallery), and its output up
    to the first line that starts with `until`. JAX_PLATFORMS is left for kinetix to choose."""
    # PYTHONFAULTHANDLER: a SIGABRT (what _rest_after_ctrl_c sends a hung server) prints every thread's stack
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONFAULTHANDLER": "1"}
    env.pop("JAX_PLATFORMS", None)
    process = subprocess.Popen([sys.executable, "-m", "kinetix", "serve", "--port", "0", "--data", str(tmp_path),
                                *options], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)
    lines = []
    for line in process.stdout:
        lines.append(line)
        if line.startswith(until):
            break
    return process, lines


def _rest_after_ctrl_c(process: subprocess.Popen, timeout: float) -> str:
    """The process's remaining output once it exits; if it does not within `timeout` s, the test fails with that
    output and every thread's stack. (A shutdown that hangs prints them after 20 s, server/app.py; but in two CI runs
    the server never even printed "Shutting down", so the Ctrl+C itself went unanswered: a SIGABRT makes the
    faulthandler that _serve enables print them wherever the process is stuck, before it is killed.)"""
    try:
        return process.communicate(timeout=timeout)[0]
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGABRT)
        try:
            rest = process.communicate(timeout=15)[0]
        except subprocess.TimeoutExpired:
            process.kill()
            rest = process.communicate()[0]
        pytest.fail(f"kinetix serve did not exit within {timeout} s of Ctrl+C; it printed (then its stacks on "
                    f"SIGABRT):\n{rest}")


def test_serve_prints_the_url_and_stops_on_ctrl_c(tmp_path):
    process, lines = _serve(tmp_path, "--warm", "none", "--allowed-hosts", "kinetix.test", until="Open ")
    try:
        url = lines[-1].split()[-1]
        assert url.startswith("http://127.0.0.1:") and url.endswith("/"), lines
        assert sum("http" in line for line in lines) == 1  # one URL only (viser's internal one is not shown)
        page = urllib.request.urlopen(url, timeout=10)
        assert "keys.js" in page.read().decode()
        assert page.headers["X-Content-Type-Options"] == "nosniff"  # server/web/security.py
        # --allowed-hosts reached the server: its name is served, any other name is refused (DNS rebinding).
        assert urllib.request.urlopen(urllib.request.Request(url + "health", headers={"Host": "kinetix.test:1"}),
                                      timeout=10).status == 200
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(urllib.request.Request(url + "health", headers={"Host": "rebound.example"}),
                                   timeout=10)
        assert refused.value.code == 400
        process.send_signal(signal.SIGINT)
        rest = _rest_after_ctrl_c(process, 30)
        assert process.returncode == 0, rest
        assert "Shutting down" in rest
    finally:
        if process.poll() is None:
            process.kill()


def test_serve_refuses_a_busy_port(tmp_path):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        result = subprocess.run([sys.executable, "-m", "kinetix", "serve", "--port", str(port), "--warm", "none",
                                 "--data", str(tmp_path)],
                                cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
                                timeout=60)
    assert result.returncode == 2
    assert f"cannot listen on 127.0.0.1:{port}" in result.stdout


@pytest.mark.parametrize("option, value, message", [
    ("--trusted-proxies", "proxy.lan", "--trusted-proxies: 'proxy.lan' is not an IP address or network"),
    ("--root-path", "/a b/", "--root-path: '/a b/' must be a plain path such as /kinetix/"),
])
def test_serve_refuses_a_bad_proxy_or_root_path_before_starting(tmp_path, option, value, message):
    result = subprocess.run([sys.executable, "-m", "kinetix", "serve", "--port", "0", "--warm", "none",
                             "--data", str(tmp_path), option, value],
                            cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 2 and f"kinetix serve: {message}" in result.stdout, result.stdout + result.stderr


def test_serve_parses_the_training_cap_and_refuses_zero(capsys):
    from kinetix.cli import build_parser

    args = build_parser().parse_args(["serve", "--max-training-runs", "2"])
    assert args.max_training_runs == 2
    assert build_parser().parse_args(["serve"]).max_training_runs == 1  # one run at a time by default
    with pytest.raises(SystemExit):
        build_parser().parse_args(["serve", "--max-training-runs", "0"])
    assert "max-training-runs" in capsys.readouterr().err


def test_serve_parses_the_training_queue_and_per_client_limits(capsys):
    import pytest

    from kinetix.cli import build_parser

    defaults = build_parser().parse_args(["serve"])
    assert (defaults.max_training_queue, defaults.max_training_per_client) == (8, 1)
    args = build_parser().parse_args(["serve", "--max-training-queue", "0", "--max-training-per-client", "2"])
    assert (args.max_training_queue, args.max_training_per_client) == (0, 2)
    for option, bad in (("--max-training-queue", "-1"), ("--max-training-per-client", "0")):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["serve", option, bad])
        assert option.lstrip("-") in capsys.readouterr().err


def test_make_serve_passes_args_to_the_server():
    import shutil

    import pytest

    if shutil.which("make") is None:
        pytest.skip("no make")
    # -n prints the commands without running them (nor building .venv).
    out = subprocess.run(["make", "-n", "serve", "ARGS=--port 9000 --data /tmp/k"], cwd=ROOT, capture_output=True,
                         text=True, timeout=30, check=True).stdout
    assert ".venv/bin/kinetix serve --port 9000 --data /tmp/k\n" in out, out


def test_ctrl_c_during_the_warm_up_exits_at_once_and_jax_tries_no_missing_platform(tmp_path):
    """A Ctrl+C while the first start compiles (or fills the gallery) closes everything and ends the process without
    waiting for the compile under way (it took ~10 s); JAX tries only the platforms present, so no start prints
    "Unable to initialize backend 'tpu'"."""
    process, lines = _serve(tmp_path, until="Compiling the physics")
    try:
        process.send_signal(signal.SIGINT)  # the warm-up has just begun: its first task is under way
        rest = _rest_after_ctrl_c(process, 60)
        output = "".join(lines) + rest
        assert process.returncode == 0, output
        assert "Shutting down" in rest and "the compile under way is abandoned" in rest, output
        after = rest.split("Shutting down", 1)[1]
        assert " done in " not in after, "a warm-up task was waited for after Ctrl+C"
        assert "Unable to initialize backend" not in output, output
    finally:
        if process.poll() is None:
            process.kill()
