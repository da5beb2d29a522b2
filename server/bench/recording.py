"""What recording every play costs the live server: one tab playing car_ramp at 30 fps, with and without recording.

    python -m server.bench.recording [--seconds 10] [--json]

Prints, per frame: the time inside the recorder's hooks on the play thread (play_stepped) and on the encoder
thread (frame_pushed), the recorder's writer-thread CPU, the process CPU with and without recording, the frame
rate the tab received, and the one-off cost of opening a recording when a play starts. Numbers, not pass/fail.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

LEVEL = Path(__file__).resolve().parents[2] / "levels" / "car_ramp.json"


def _timed(recorder, name: str, samples: list[float]):
    original = getattr(recorder, name)

    def wrapper(*args):
        t0 = time.perf_counter()
        try:
            return original(*args)
        finally:
            samples.append((time.perf_counter() - t0) * 1000)

    setattr(recorder, name, wrapper)


def _run(record: bool, seconds: float) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "server"))
    from viser_client import KeysSocket, ViserTestClient, session_nonce

    from server.app import App, Config

    out: dict = {}
    with tempfile.TemporaryDirectory() as data:
        app = App(Config(port=0, gallery=False, warm_sizes=("m",), warm_batches=False, level=str(LEVEL),
                         data=Path(data), record=record)).start()
        app.wait_until_warm()
        stepped, pushed, started = [], [], []
        _timed(app.recorder, "play_stepped", stepped)
        _timed(app.recorder, "frame_pushed", pushed)
        _timed(app.recorder, "play_started", started)
        client = ViserTestClient(app.viser.get_port(), 640, 480, token=app.relay_token)
        try:
            nonce = session_nonce(client)
            while app.manager.session_by_nonce(nonce) is None:
                time.sleep(0.01)
            session = app.manager.session_by_nonce(nonce)
            keys = KeysSocket(app.port, nonce)
            session.play()  # a short warm-up play (first frames, first recorder), then the measured one
            time.sleep(1.0)
            session.stop()
            stepped.clear(), pushed.clear(), started.clear()
            first = client.count()
            cpu0, t0 = time.process_time(), time.perf_counter()
            session.play()
            keys.down("ArrowRight")
            time.sleep(seconds)
            keys.up("ArrowRight")
            steps = session._steps
            session.stop()
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - t0
            frames = len(client.frames(first))
            keys.close()
            finished = app.recorder.last_finished(session) if record else None
            writer_cpu = app.recorder._last[session].recorder.writer_cpu_seconds if record else 0.0
        finally:
            client.close()
            app.stop()
        out = {"steps": steps, "fps": frames / wall, "process_cpu_ms_per_frame": 1000 * cpu / max(steps, 1)}
        if record and finished is not None and finished.path is None:
            raise RuntimeError("the recording failed")
        if record:
            out.update(play_stepped_ms_mean=statistics.fmean(stepped), play_stepped_ms_p95=_p95(stepped),
                       frame_pushed_ms_mean=statistics.fmean(pushed), frame_pushed_ms_p95=_p95(pushed),
                       play_started_ms=started[0] if started else None,
                       writer_cpu_ms_per_frame=1000 * writer_cpu / max(steps, 1))
    return out


def _p95(samples: list[float]) -> float:
    ordered = sorted(samples)
    return ordered[int(0.95 * (len(ordered) - 1))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=7.0)  # car_ramp ends at 256 steps (8.5 s)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    results = {"without": _run(False, args.seconds), "with": _run(True, args.seconds)}
    if args.json:
        print(json.dumps(results))
        return 0
    for name, numbers in results.items():
        print(f"{name} recording: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                                               for k, v in numbers.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
