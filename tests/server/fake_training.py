"""A cheap stand-in for server.agents.training.train_worker (runs in a spawned process): reports progress, waits until
the test releases it (a file appears), then writes a checkpoint-shaped directory and reports done."""

from __future__ import annotations

import json
import time
from pathlib import Path


def fake_train_worker(level_path: str, out_dir: str, steps: int, messages, options: dict) -> None:
    Path(out_dir, "started").write_text(level_path)
    for n in (1, 2, 3):
        messages.put(("progress", {"env_steps": n * steps / 4, "total_steps": steps, "mean_return": 0.1 * n,
                                   "solve_rate": 0.25 * n, "steps_per_second": 100.0, "elapsed": float(n)}))
    release = Path(options["release"])
    deadline = time.monotonic() + 60
    while not release.exists():
        if time.monotonic() > deadline:
            messages.put(("error", "the test never released this worker"))
            return
        time.sleep(0.02)
    if options.get("fail"):
        raise SystemExit(3)  # dies without a message: the pool must report the exit code
    checkpoint = Path(out_dir, "checkpoint")
    checkpoint.mkdir(parents=True, exist_ok=True)
    (checkpoint / "config.json").write_text(json.dumps({"fake": True}))
    messages.put(("done", {"steps": steps, "solve_rate": 0.75, "mean_return": 0.3}))
