"""Multi-host training on JAX's distributed runtime: two `kinetix train` processes on this machine (one CPU device
each, coordinator on 127.0.0.1, gloo collectives) train exactly what one process does with the same total batch,
with the default network and PPO settings on a chaotic level (cartpole) as well as in a tiny configuration;
only process 0 writes; a state saved mid-run by the two processes resumes in two processes and in one.
Plus the option checks."""

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kinetix.agents import multihost, resume
from kinetix.cli import main

ROOT = Path(__file__).resolve().parents[3]
TRAIN = ["train", "--level", str(ROOT / "levels" / "unicycle.json"), "--steps", "256", "--num-envs", "4",
         "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "1", "--width", "16", "--hidden", "32",
         "--updates-per-call", "2", "--seed", "1"]  # 8 updates; 4 envs split 2 + 2 over the processes
TIMEOUT_S = 600  # two cold compiles side by side on a loaded 2-core machine take ~3 minutes; warm ~30 s
# The default settings (network, rollout length, epochs, minibatches) on a chaotic level: a rounding difference in
# one physics step grows to O(1) within a 64-step rollout, so this fails unless every env steps bitwise as one
# process steps it (issue 33: the joint projection's sums came out differently for 8 and 16 scenes). 16 envs as in
# the issue, 2 updates of 16 x 64 steps, a state written after each.
DEFAULTS = ["train", "--level", str(ROOT / "levels" / "cartpole.json"), "--num-envs", "16", "--steps", "2048",
            "--updates-per-call", "1", "--checkpoint-every-updates", "1"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_two_processes(out: Path, extra: list[str], train: list[str] = TRAIN) -> list[str]:
    """Start processes 0 and 1, wait for both; kill both if either fails or time runs out. Returns their output."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "SLURM_JOB_ID", "OMPI_MCA_orte_hnp_uri")}
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    port = free_port()
    procs = [subprocess.Popen([sys.executable, "-m", "kinetix", *train, "--out", str(out), *extra,
                               "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)],
                              cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for i in range(2)]
    try:
        outputs = [p.communicate(timeout=TIMEOUT_S)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, output in zip(procs, outputs, strict=True):
        assert p.returncode == 0, output[-3000:]
    return outputs


def assert_states_close(out: Path, reference: Path, updates: int = 8) -> None:
    meta, arrays, _ = resume.load_latest(out)
    ref_meta, ref_arrays, _ = resume.load_latest(reference)
    assert_arrays_close(arrays, ref_arrays)
    assert len(meta["history"]) == len(ref_meta["history"]) == updates
    assert sum(m["episodes"] for m in ref_meta["history"]) > 0  # episodes ended and reset inside the rollouts
    for got, want in zip(meta["history"], ref_meta["history"], strict=True):
        for key in ("value_loss", "actor_loss", "entropy", "mean_return", "episodes", "mean_reward", "solve_rate"):
            assert got[key] == pytest.approx(want[key], rel=1e-4, abs=1e-6), key


def assert_arrays_close(arrays: dict, ref_arrays: dict) -> None:
    """Parameters, optimiser, environments (every scene mid-episode), key, update index: equal to rounding."""
    assert arrays.keys() == ref_arrays.keys()
    for name in ref_arrays:
        np.testing.assert_allclose(arrays[name], ref_arrays[name], rtol=1e-5, atol=1e-6, err_msg=name)


@pytest.mark.slow
def test_two_processes_equal_one_process_with_the_default_settings(tmp_path):
    two, one = tmp_path / "two", tmp_path / "one"
    run_two_processes(two, [], train=DEFAULTS)
    assert main([*DEFAULTS, "--out", str(one), "--no-shard"]) == 0  # one process, the whole batch on one device
    assert json.loads((two / "metrics.json").read_text())["processes"] == 2
    assert_states_close(two, one, updates=2)  # after update 2, and the metrics of both updates
    first, reference = (resume._read(resume.state_dir(run) / "state-000000001.msgpack")[1] for run in (two, one))
    assert_arrays_close(first, reference)  # after update 1
    moved = reference[".env_state.level.sim.bodies.angular_velocity"]
    assert np.abs(moved).max() > 1.0  # the carts and poles really swing (what amplifies any rounding)


@pytest.mark.slow
def test_two_processes_equal_one_process_with_the_same_batch(tmp_path):
    two = tmp_path / "two"
    outputs = run_two_processes(two, ["--checkpoint-every-updates", "4"])
    assert "wrote" in outputs[0] and "wrote" not in outputs[1]  # only process 0 reports and writes
    summary = json.loads((two / "metrics.json").read_text())
    assert summary["processes"] == 2 and summary["devices"] == 2
    one = tmp_path / "one"
    assert main([*TRAIN, "--out", str(one), "--no-shard"]) == 0
    assert_states_close(two, one)
    # the state the two processes saved mid-run (gathered from both) resumes to the same end in two processes
    # (each array placed back on the global mesh) and in one
    for name, processes in (("half-two", 2), ("half-one", 1)):
        half = tmp_path / name
        shutil.copytree(two, half)
        (resume.state_dir(half) / "state-000000008.msgpack").unlink()
        assert resume.load_latest(half)[2].name == "state-000000004.msgpack"
        if processes == 2:
            run_two_processes(half, [], train=["train", "--resume", str(half)])
        else:
            assert main(["train", "--resume", str(half), "--no-shard"]) == 0
        assert json.loads((half / "metrics.json").read_text())["resumed_at_update"] == 4
        assert_states_close(half, one)


def test_multihost_options_are_checked(capsys):
    for argv, message in ((["--coordinator", "127.0.0.1:1234"], "needs all of"),
                          (["--coordinator", "nohost", "--num-processes", "2", "--process-id", "0"], "HOST:PORT"),
                          (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"], "0..1")):
        assert main(["train", "--level", "random-s", *argv]) == 2
        assert message in capsys.readouterr().err
    assert multihost.agree(True, False) == (True, False)


def test_cluster_environment_is_detected(monkeypatch):
    for name in ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_PROCID", "SLURM_LOCALID", "SLURM_NTASKS"):
        monkeypatch.delenv(name, raising=False)
    assert multihost.detected_cluster() is None
    monkeypatch.setenv("SLURM_JOB_ID", "7")
    monkeypatch.setenv("SLURM_STEP_NODELIST", "node[1-2]")
    monkeypatch.setenv("SLURM_PROCID", "0")
    monkeypatch.setenv("SLURM_LOCALID", "0")
    monkeypatch.setenv("SLURM_NTASKS", "1")
    assert multihost.detected_cluster() is None  # one task: nothing to distribute
    monkeypatch.setenv("SLURM_NTASKS", "2")
    assert multihost.detected_cluster() == "SlurmCluster"
