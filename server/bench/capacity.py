"""Capacity for docs/deploy.md's sizing rule: how many tabs can play at >= 25 frames per second, per CPU core, with
1 server process and with 2 (part of `kinetix bench server`; `--capacity-only` runs just this).

Each server is a real process started as `kinetix serve` starts (the level's size class warm, its batched steps
compiled, then the malloc settings), serving the bench's level (levels/car_right.json) to every new tab, gallery
off. The tabs are headless protocol clients (tests/server/viser_client.py) in one child process, spread
round-robin over the servers through their one port, each pressing Space on its own /keys socket, as a browser
tab does. For N = 1, 2, 3, 4, 6, 8, ... (TABS_TRIED) the clients count the frames each tab received over
`seconds`; the capacity is the largest N whose slowest tab got >= MIN_FPS, and the figure is N / the machine's
cores. The clients share the machine (they decode every frame): the figure is what one machine does with its
clients on it, a floor for a real server.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
LEVEL = ROOT / "levels" / "car_right.json"
MIN_FPS = 25.0


def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def serve_child() -> None:
    """A server process for the bench: argv = port, most sessions; prints "ready" once everything is compiled."""
    from kinetix.levels import load_level
    from server.app import App, Config
    from server.play import steps

    port, max_sessions = int(sys.argv[1]), int(sys.argv[2])
    size = load_level(LEVEL).size.name  # only the level's size class is played: compile only that one
    app = App(Config(port=port, max_sessions=max_sessions, level=str(LEVEL), gallery=False, agents=False,
                     record=False, drafts=False, warm_sizes=(size,))).start()
    app.wait_until_warm(everything=True)
    steps.wait_for_compiles()
    print("ready", flush=True)
    try:
        sys.stdin.readline()  # until the bench closes our stdin
    finally:
        app.stop()


def client_child() -> None:
    """argv = comma-separated ports, tabs, seconds: connects the tabs round-robin, starts every play, prints
    "playing", waits for a line, then prints each tab's frames per second as a JSON list."""
    sys.path.insert(0, str(ROOT / "tests" / "server"))
    from viser_client import KeysSocket, ViserTestClient, session_nonce

    ports = [int(p) for p in sys.argv[1].split(",")]
    tabs, seconds = int(sys.argv[2]), float(sys.argv[3])
    clients = [ViserTestClient(ports[i % len(ports)], 640, 480) for i in range(tabs)]
    keys = []
    for i, client in enumerate(clients):
        client.wait_frame(timeout=60)
        keys.append(KeysSocket(ports[i % len(ports)], session_nonce(client)))
    for socket in keys:
        socket.down("Space")
        socket.up("Space")
    time.sleep(1.0)  # the plays are running
    print("playing", flush=True)
    print_rates_when_asked(clients, seconds)
    for socket in keys:
        socket.close()
    for client in clients:
        client.close()


def print_rates_when_asked(clients, seconds: float) -> None:
    """Wait for a line on stdin, then print the frames per second each client received over `seconds` (JSON)."""
    sys.stdin.readline()
    starts = [client.count() for client in clients]
    t0 = time.monotonic()
    time.sleep(seconds)
    elapsed = time.monotonic() - t0
    print(json.dumps([len(c.frames(start)) / elapsed for c, start in zip(clients, starts, strict=True)]), flush=True)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _python(code: str, *args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=ROOT, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, **kwargs)


def _rates(ports: list[int], tabs: int, seconds: float) -> list[float]:
    child = _python("from server.bench.capacity import client_child; client_child()",
                    ",".join(map(str, ports)), str(tabs), str(seconds), stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE)
    try:
        if child.stdout.readline().strip() != "playing":
            raise RuntimeError("the bench's client process did not start its tabs")
        child.stdin.write("go\n")
        child.stdin.flush()
        rates = json.loads(child.stdout.readline())
        child.wait(timeout=60)
        return rates
    finally:
        if child.poll() is None:
            child.kill()


def _wait_empty(ports: list[int]) -> None:
    """Until every server has let its sessions go (the next round starts from none)."""
    deadline = time.monotonic() + 30
    for port in ports:
        while time.monotonic() < deadline:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=10) as answer:
                if answer.read().decode().startswith("ok 0 "):
                    break
            time.sleep(0.1)


# Tabs tried, in order, until the slowest tab drops below MIN_FPS: finer where small machines end up.
TABS_TRIED = (1, 2, 3, 4, 6, 8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56, 64)


def capacity(processes: int, *, seconds: float = 4.0, max_tabs: int = 64,
             report=print) -> tuple[int, dict[int, float]]:
    """(the most tabs whose slowest got >= MIN_FPS, {tabs: slowest tab's fps} for each round) with `processes`
    server processes."""
    ports = [_free_port() for _ in range(processes)]
    servers = [_python("from server.bench.capacity import serve_child; serve_child()", str(port), str(max_tabs),
                       stdin=subprocess.PIPE, stdout=subprocess.PIPE) for port in ports]
    rounds: dict[int, float] = {}
    best = 0
    try:
        for server in servers:
            if server.stdout.readline().strip() != "ready":
                raise RuntimeError("a bench server did not start")
        for tabs in (n for n in TABS_TRIED if n <= max_tabs):
            slowest = min(_rates(ports, tabs, seconds))
            rounds[tabs] = slowest
            report(f"  {processes} process(es), {tabs} tabs: slowest tab {slowest:.1f} fps")
            if slowest < MIN_FPS:
                break
            best = tabs
            _wait_empty(ports)
    finally:
        for server in servers:
            if server.poll() is None:
                server.stdin.close()  # the server stops cleanly
        for server in servers:
            try:
                server.wait(timeout=120)
            except subprocess.TimeoutExpired:
                server.kill()
    return best, rounds
