"""Measure agents in the server: ms per agent step (observe + policy, jitted, one call per play step) at s/m/l,
and the frame rate of a Watch agent tab (frames the session sent per second, and frames a headless client got).

    python -m server.bench.agent [--agent general] [--sizes s,m,l] [--seconds 5]

Prints numbers; nothing here passes or fails.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

LEVELS = Path(__file__).resolve().parents[2] / "levels"


def level_of_size(name: str):
    """A project level of this size class (the largest by file size: the most bodies), else the empty level."""
    from kinetix.level import LevelFile, LevelParams, empty_level, size_class
    from kinetix.levels import load_level

    found = [lf for lf in (load_level(p) for p in sorted(LEVELS.glob("*.json"))) if lf.size.name == name]
    return found[0] if found else LevelFile(empty_level(size_class(name)), LevelParams())


def step_cost(agent: str, size_name: str, calls: int = 300) -> dict:
    from server.agents.play import AgentRunner
    from server.play.steps import stepper_for

    level_file = level_of_size(size_name)
    stepper = stepper_for(level_file)
    state, params = stepper.start(level_file)
    runner = AgentRunner(agent, level_file.size)
    t0 = time.perf_counter()
    runner.act(state)
    compile_s = time.perf_counter() - t0
    runner.step_seconds.clear()
    for _ in range(calls):
        action = runner.act(state)
        state, result = stepper.step(state, action, params)
        if result.terminated or result.truncated:
            state, params = stepper.start(level_file)
    ms = sorted(1000 * s for s in runner.step_seconds)
    return {"size": size_name, "level": level_file.level and getattr(level_file, "name", ""), "first_call_s": compile_s,
            "p50_ms": statistics.median(ms), "p90_ms": ms[int(0.9 * len(ms))], "mean_ms": statistics.fmean(ms)}


def watch_fps(agent: str | None, size_name: str, seconds: float) -> dict:
    """Frames per second of a tab watching `agent` (None: a human play with no keys, for comparison)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "server"))
    from viser_client import ViserTestClient, session_nonce

    from server.app import App, Config

    app = App(Config(port=0, gallery=False, warm_sizes=(size_name,), warm_batches=False, warm_agent=False)).start()
    app.wait_until_warm()
    try:
        client = ViserTestClient(app.viser.get_port(), 640, 480, token=app.relay_token)
        nonce = session_nonce(client)
        while app.manager.session_by_nonce(nonce) is None:
            time.sleep(0.02)
        session = app.manager.session_by_nonce(nonce)
        import json

        from kinetix.levels import to_document

        session.open_level(json.dumps(to_document(level_of_size(size_name))).encode(), "bench.json")
        waits: list[float] = []  # seconds the play thread waited for the agent per step (with prefetch)

        def start() -> None:
            if agent:
                waits.extend(session.controller.runner.step_seconds if session.controller is not None else ())
                app.agents.watch(session, agent)
            else:
                session.play()

        start()
        time.sleep(2.0)  # past the first frames
        sent0, got0, t0 = session.frames_sent, len(client.frames()), time.perf_counter()
        restarts = 0
        while time.perf_counter() - t0 < seconds:
            if session.mode == "ended":  # keep it playing for the whole measurement
                start()
                restarts += 1
            time.sleep(0.05)
        elapsed = time.perf_counter() - t0
        sent, got = session.frames_sent - sent0, len(client.frames()) - got0
        if agent and session.controller is not None:
            waits.extend(session.controller.runner.step_seconds)
        wait_ms = sorted(1000 * w for w in waits)
        client.close()
        return {"size": size_name, "agent": agent, "sent_fps": sent / elapsed, "received_fps": got / elapsed,
                "restarts": restarts, "agent_wait_ms_p50": wait_ms[len(wait_ms) // 2] if wait_ms else None,
                "agent_wait_ms_p90": wait_ms[int(0.9 * len(wait_ms))] if wait_ms else None}
    finally:
        app.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agent", default="general")
    parser.add_argument("--sizes", default="s,m,l")
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args(argv)
    sizes = [s for s in args.sizes.split(",") if s]
    for size in sizes:
        print("agent step", step_cost(args.agent, size), flush=True)
    for size in sizes:
        print("watch agent", watch_fps(args.agent, size, args.seconds), flush=True)
        print("human play (no keys), same conditions", watch_fps(None, size, args.seconds), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
