"""Resumable training: a run split into jobs (a graceful stop, or a kill after periodic checkpoints, with the
newest state file damaged) ends exactly where the uninterrupted run ends; a finished run extended with
`--resume DIR --steps N` (constant learning rate) ends where a run planned for N steps ends; one resumed with another
batch cut, learning rate or entropy weight trains on with it and records it; state files are written
atomically and a checkpoint of another configuration is refused with a clear error."""

import dataclasses
import json
import math
import os
import shutil
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

import jax2d
from kinetix.agents import resume
from kinetix.agents.checkpoint import CheckpointError
from kinetix.agents.curricula import NEG, CurriculumConfig
from kinetix.agents.ppo import TrainConfig, make_train
from kinetix.agents.train import batch_offset, checkpoint_due, replan, settled, setup_levels, train_agent
from kinetix.cli import main

# Tiny and short: 4 chunks of 2 updates of 4 envs x 8 steps on random s levels with PLR (its buffer is filled
# from the first update, so the curriculum state matters), about 15 s with a warm compile cache.
CONFIG = TrainConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1, width=16, hidden=32,
                     updates_per_call=2)
CURRICULUM = CurriculumConfig(buffer_size=4, candidates=4, attempts=1)
STEPS = 4 * 8 * 8  # 8 updates
RUN = dict(steps=STEPS, config=CONFIG, seed=3, curriculum="plr", curriculum_config=CURRICULUM)
TIMING = ("elapsed", "steps_per_second")  # wall-clock fields: the only ones allowed to differ


def final_state(out: Path) -> tuple[dict, dict]:
    meta, arrays, path = resume.load_latest(out)
    assert path.name == f"state-{8:09d}.msgpack"
    return meta, arrays


def assert_same_run(out: Path, reference: Path, also_differ: tuple[str, ...] = ()) -> None:
    """Every array of the final training state (parameters, Adam moments and count, environments mid-episode,
    PLR buffer levels and scores, RNG key, update index) and every logged metric (but the wall-clock ones and
    `also_differ`) equal the reference run's."""
    meta, arrays = final_state(out)
    ref_meta, ref_arrays = final_state(reference)
    assert arrays.keys() == ref_arrays.keys()
    for name in ref_arrays:
        np.testing.assert_allclose(arrays[name], ref_arrays[name], rtol=1e-6, atol=1e-7, err_msg=name)
    assert len(meta["history"]) == len(ref_meta["history"]) == 8
    for got, want in zip(meta["history"], ref_meta["history"], strict=True):
        for key in want:
            if key not in TIMING + also_differ:
                assert got[key] == pytest.approx(want[key], rel=1e-5, abs=1e-7), key
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    assert [m["update"] for m in metrics] == list(range(1, 9))  # the learning curve continues, not restarts
    elapsed = [m["elapsed"] for m in metrics]
    assert elapsed == sorted(elapsed)  # wall time adds up over the jobs


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("uninterrupted")
    train_agent("random-s", out, **RUN, save_state=True)
    _, arrays = final_state(out)
    scores = next(v for k, v in arrays.items() if k.startswith(".curriculum") and "scores" in k)
    assert (scores > NEG / 2).any()  # the PLR buffer holds levels: its state is exercised
    return out


@pytest.mark.slow
def test_stopped_run_resumed_from_the_command_line_equals_uninterrupted(reference, tmp_path):
    chunks = []
    first = train_agent("random-s", tmp_path, **RUN, save_state=True, should_stop=lambda: len(chunks) >= 2,
                        progress=lambda m: chunks.append(m) if m["update"] % 2 == 0 else None)
    assert first["stopped"] and len(first["metrics"]) == 4 and not first["complete"]
    # the second job: everything (level, curriculum, config, seed) comes from the saved run
    assert main(["train", "--resume", str(tmp_path)]) == 0
    assert_same_run(tmp_path, reference)
    summary = json.loads((tmp_path / "metrics.json").read_text())
    assert summary["resumed_at_update"] == 4 and not summary["stopped"] and summary["complete"]


class Killed(Exception):
    pass


@pytest.mark.slow
def test_killed_run_resumes_from_last_good_checkpoint(reference, tmp_path):
    def kill_in_chunk_four(m):
        if m["update"] == 7:
            raise Killed  # like SIGKILL: nothing written after the last periodic checkpoint

    with pytest.raises(Killed):
        train_agent("random-s", tmp_path, **RUN, checkpoint_every_updates=2, progress=kill_in_chunk_four)
    directory = resume.state_dir(tmp_path)
    assert sorted(p.name for p in directory.iterdir()) == ["state-000000004.msgpack", "state-000000006.msgpack"]
    # the newest file was cut short (as by a crash that lost unsynced data), and a write was killed mid-way
    newest = directory / "state-000000006.msgpack"
    newest.write_bytes(newest.read_bytes()[:1000])
    (directory / ".state-000000008.msgpack.999.tmp").write_bytes(b"half a file")
    with pytest.warns(UserWarning, match="state-000000006.msgpack is damaged"):
        train_agent("random-s", tmp_path, **RUN, resume=True)
    assert_same_run(tmp_path, reference)
    assert not list(directory.glob(".*.tmp"))  # leftovers are cleaned up by the next save


@pytest.mark.slow
def test_finished_run_extended_with_steps_equals_a_run_planned_that_long(tmp_path):
    constant = dict(RUN, config=dataclasses.replace(CONFIG, anneal_lr=False))
    planned = tmp_path / "planned"
    train_agent("random-s", planned, **constant, save_state=True)
    extended = tmp_path / "extended"
    first = train_agent("random-s", extended, **dict(constant, steps=STEPS // 2), save_state=True)
    assert first["complete"] and len(first["metrics"]) == 4
    assert main(["train", "--resume", str(extended), "--steps", str(STEPS)]) == 0
    # total_steps is the plan each update was logged under: 128 for the first job's updates, 256 after
    assert_same_run(extended, planned, also_differ=("total_steps",))
    summary = json.loads((extended / "metrics.json").read_text())
    assert summary["complete"] and summary["resumed_at_update"] == 4 and summary["config"]["total_timesteps"] == STEPS
    assert summary["plans"] == [{"update": 0, "steps": STEPS // 2}, {"update": 4, "steps": STEPS}]


@pytest.mark.slow
def test_annealed_run_extended_trains_on_and_shortening_below_done_is_refused(reference, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    assert main(["train", "--resume", str(out), "--steps", str(STEPS // 2)]) == 2
    assert f"has trained {STEPS} steps already" in capsys.readouterr().err
    # the finished run's learning rate had decayed to 0; extended, it follows a 2 x STEPS run's schedule (lr / 2
    # at the resume) and the parameters move on
    assert main(["train", "--resume", str(out), "--steps", str(2 * STEPS)]) == 0
    meta, arrays, _ = resume.load_latest(out)
    _, before = final_state(reference)
    assert [m["update"] for m in meta["history"]] == list(range(1, 17))
    params = [k for k in before if k.startswith(".train_state.params")]
    assert max(np.abs(arrays[k] - before[k]).max() for k in params) > 1e-4
    assert meta["plans"] == [{"update": 0, "steps": STEPS}, {"update": 8, "steps": 2 * STEPS}]


@pytest.mark.slow
def test_resume_with_another_configuration_is_refused(reference, tmp_path, capsys):
    assert main(["train", "--resume", str(reference), "--width", "32"]) == 2
    err = capsys.readouterr().err
    assert "different training configuration" in err and "train.width: 16 in the checkpoint, 32 now" in err
    assert main(["train", "--resume", str(reference), "--constant-lr"]) == 2
    assert "train.anneal_lr: True in the checkpoint, False now" in capsys.readouterr().err
    with pytest.raises(CheckpointError, match="seed: 3 in the checkpoint, 4 now"):
        train_agent("random-s", reference, **dict(RUN, seed=4), resume=True)
    with pytest.raises(CheckpointError, match="levels: 'random-s"):
        train_agent("random-m", reference, **RUN, resume=True)


def test_a_restored_runner_lowers_to_the_program_of_a_fresh_one():
    """A resume finds the first sitting's compiled chunk in the persistent cache (which keys on the lowered program):
    settled, a fresh runner and one restored from its saved arrays lower the chunk to the same program. Unsettled,
    the fresh one's weakly typed scalars and uncommitted arrays gave another, and every resume compiled afresh."""
    env, params, factory, _ = setup_levels("levels/cartpole.json", None, "entity", "multi_discrete",
                                           CurriculumConfig(), None)
    trainer = make_train(dataclasses.replace(CONFIG, total_timesteps=STEPS), env, params, factory(None))
    fresh = jax2d.jit(trainer.init)(jax.random.key(0))
    restored = resume.restore(fresh, resume.flatten(resume.host_tree(fresh)))
    assert trainer.run.lower(settled(fresh)).as_text() == trainer.run.lower(settled(restored)).as_text()


def test_resume_without_state_is_a_clear_error(tmp_path, capsys):
    assert main(["train", "--resume", str(tmp_path)]) == 2
    assert "has no training state to resume" in capsys.readouterr().err
    assert main(["train", "--steps", "100"]) == 2
    assert "--level is required" in capsys.readouterr().err
    assert main(["train", "--level", "random-s", "--resume", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    assert "differs from --resume" in capsys.readouterr().err


def arrays_at(update: int) -> dict:
    return {".w": np.full((3,), update, np.float32), ".step": np.asarray(update, np.int32)}


def test_state_files_are_atomic_and_the_last_good_one_wins(tmp_path):
    for update in (2, 4, 6):
        resume.save(tmp_path, update, {"run": {}, "history": [update]}, arrays_at(update))
    directory = resume.state_dir(tmp_path)
    assert sorted(p.name for p in directory.iterdir()) == ["state-000000004.msgpack", "state-000000006.msgpack"]
    meta, arrays, path = resume.load_latest(tmp_path)
    assert meta["history"] == [6] and arrays[".step"] == 6 and path.name == "state-000000006.msgpack"
    # a leftover temporary file (a kill before the rename) is never read
    (directory / ".state-000000008.msgpack.1.tmp").write_bytes(b"\x00" * 10)
    assert resume.load_latest(tmp_path)[0]["history"] == [6]
    # one flipped byte in the newest: the checksum catches it, the previous file is used
    newest = directory / "state-000000006.msgpack"
    data = bytearray(newest.read_bytes())
    data[-5] ^= 0xFF
    newest.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match="checksum mismatch"):
        assert resume.load_latest(tmp_path)[0]["history"] == [4]
    (directory / "state-000000004.msgpack").write_bytes(b"")
    with warnings.catch_warnings(), pytest.raises(CheckpointError, match="no intact training state"):
        warnings.simplefilter("ignore")
        resume.load_latest(tmp_path)


def test_restore_checks_paths_and_shapes():
    import jax
    import jax.numpy as jnp

    template = {"w": jnp.zeros((3,), jnp.float32), "key": jax.random.key(1)}
    saved = resume.flatten(resume.host_tree({"w": jnp.arange(3, dtype=jnp.float32), "key": jax.random.key(7)}))
    restored = resume.restore(template, saved)
    np.testing.assert_array_equal(restored["w"], [0, 1, 2])
    assert (jax.random.key_data(restored["key"]) == jax.random.key_data(jax.random.key(7))).all()
    with pytest.raises(CheckpointError, match=r"\['w'\] is float32\[4\], this run needs float32\[3\]"):
        resume.restore(template, dict(saved, **{"['w']": np.zeros((4,), np.float32)}))
    with pytest.raises(CheckpointError, match="does not fit"):
        resume.restore(template, {"['w']": saved["['w']"]})


def test_checkpoint_cadence():
    assert not checkpoint_due(599.0, 3, every_minutes=10, every_updates=None)
    assert checkpoint_due(600.0, 0, every_minutes=10, every_updates=None)
    assert not checkpoint_due(10_000.0, 3, every_minutes=None, every_updates=4)
    assert checkpoint_due(1.0, 4, every_minutes=None, every_updates=4)
    assert checkpoint_due(1.0, 4, every_minutes=10, every_updates=4)  # whichever comes first
    assert not checkpoint_due(10_000.0, 10_000, every_minutes=None, every_updates=None)
    with pytest.raises(ValueError, match="checkpoint-every must be positive"):
        train_agent("random-s", "/nonexistent", checkpoint_every=0)


def test_replan_records_where_the_length_changed():
    old = {"arguments": {"steps": 100}}  # a state written before plans were recorded
    assert replan(old, 4, 100) == [{"update": 0, "steps": 100}]
    extended = replan(old, 4, 200)
    assert extended == [{"update": 0, "steps": 100}, {"update": 4, "steps": 200}]
    assert replan({"plans": extended}, 8, 200) == extended  # resumed with the same length: nothing new
    # changed again before any update ran: the newer plan replaces the one that never took effect
    assert replan({"plans": extended}, 4, 300) == [{"update": 0, "steps": 100}, {"update": 4, "steps": 300}]


def test_replan_records_where_the_batch_cut_changed():
    saved = {"arguments": {"steps": 100, "config": {"update_epochs": 4, "num_minibatches": 4}}}
    cut = {"update_epochs": 4, "num_minibatches": 4}
    assert replan(saved, 4, 100, cut) == [{"update": 0, "steps": 100}]  # the run's own cut: nothing new
    finer = replan(saved, 4, 100, dict(cut, num_minibatches=32))
    assert finer == [{"update": 0, "steps": 100}, {"update": 4, "steps": 100, "update_epochs": 4,
                                                   "num_minibatches": 32}]
    # resumed again with the cut in force, or only extended: the cut is the latest plan's, not the arguments'
    assert replan(dict(saved, plans=finer), 8, 100, dict(cut, num_minibatches=32)) == finer
    assert replan(dict(saved, plans=finer), 8, 200, dict(cut, num_minibatches=32))[-1] == {"update": 8, "steps": 200}
    # back to the first cut later: recorded again
    assert replan(dict(saved, plans=finer), 8, 100, cut)[-1] == {"update": 8, "steps": 100, **cut}
    # extended before any update ran with the new cut: the newer plan replaces the older and keeps its cut
    assert replan(dict(saved, plans=finer), 4, 300, dict(cut, num_minibatches=32))[-1] == {
        "update": 4, "steps": 300, "update_epochs": 4, "num_minibatches": 32}


def test_replan_records_where_the_learning_rate_changed():
    saved = {"arguments": {"steps": 100, "config": {"update_epochs": 4, "num_minibatches": 4, "lr": 3e-4}}}
    same = {"update_epochs": 4, "num_minibatches": 4, "lr": 3e-4}
    assert replan(saved, 4, 100, same) == [{"update": 0, "steps": 100}]
    lower = replan(saved, 4, 100, dict(same, lr=5e-5))
    # the whole planned setting from that update on: the rate and the cut in force with it
    assert lower[-1] == {"update": 4, "steps": 100, "update_epochs": 4, "num_minibatches": 4, "lr": 5e-5}
    assert replan(dict(saved, plans=lower), 8, 100, dict(same, lr=5e-5)) == lower  # resumed at that rate again
    finer = replan(dict(saved, plans=lower), 8, 100, dict(same, lr=5e-5, num_minibatches=8))
    assert finer[-1] == {"update": 8, "steps": 100, "update_epochs": 4, "num_minibatches": 8, "lr": 5e-5}


def test_the_env_steps_where_the_batch_changed_stay_with_a_plan_made_again_before_any_update():
    saved = {"arguments": {"steps": 100, "config": {"update_epochs": 4, "num_minibatches": 4, "lr": 3e-4,
                                                    "num_envs": 4}}}
    wider = replan(saved, 4, 100, {"num_envs": 8})
    wider[-1]["env_steps"] = 60  # (train_agent adds it where num_envs changed)
    again = replan(dict(saved, plans=wider), 4, 200, {"num_envs": 8, "lr": 1e-4})
    assert again[-1] == {"update": 4, "steps": 200, "update_epochs": 4, "num_minibatches": 4, "lr": 1e-4,
                         "num_envs": 8, "env_steps": 60}
    assert batch_offset(again, TrainConfig(num_envs=8, num_steps=4)) == 60 - 4 * 32
    assert batch_offset(again[:1], TrainConfig(num_envs=8, num_steps=4)) == 0


def test_a_learning_rate_that_is_not_positive_and_finite_is_refused():
    for lr in (0.0, -1e-4, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="lr must be a positive finite number"):
            TrainConfig(lr=lr)
    assert TrainConfig(lr=1e-5).lr == 1e-5


def test_an_entropy_weight_that_is_negative_or_not_finite_is_refused():
    for coef in (-0.01, float("nan"), float("inf"), True, "0.01"):
        with pytest.raises(ValueError, match="ent_coef must be a finite number >= 0"):
            TrainConfig(ent_coef=coef)
    assert TrainConfig(ent_coef=0).ent_coef == 0 and TrainConfig(ent_coef=0.0025).ent_coef == 0.0025


def _stopped_after_four_updates(out: Path) -> None:
    """The first job of RUN, stopped gracefully after 4 of its 8 updates."""
    chunks = []
    first = train_agent("random-s", out, **RUN, save_state=True, should_stop=lambda: len(chunks) >= 2,
                        progress=lambda m: chunks.append(m) if m["update"] % 2 == 0 else None)
    assert first["stopped"] and len(first["metrics"]) == 4


@pytest.mark.slow
def test_resume_with_another_entropy_weight_trains_with_it_and_records_it(reference, tmp_path):
    """--resume DIR --ent-coef X: the loss weighs the entropy bonus by X from the resume on. Resumed with the weight
    it had, the run equals the uninterrupted one; with a huge weight its parameters differ and it ends nearer the
    uniform policy (a higher logged entropy) than the uninterrupted run, and the plan records where the weight
    changed."""
    same = tmp_path / "same"
    _stopped_after_four_updates(same)
    assert main(["train", "--resume", str(same), "--ent-coef", str(CONFIG.ent_coef)]) == 0
    assert_same_run(same, reference)
    assert json.loads((same / "metrics.json").read_text())["plans"] == [{"update": 0, "steps": STEPS}]

    bonus = tmp_path / "bonus"
    _stopped_after_four_updates(bonus)
    assert main(["train", "--resume", str(bonus), "--ent-coef", "50"]) == 0
    summary = json.loads((bonus / "metrics.json").read_text())
    assert summary["complete"] and summary["config"]["ent_coef"] == 50.0
    assert summary["plans"][-1] == {"update": 4, "steps": STEPS, "update_epochs": 1, "num_minibatches": 2,
                                    "lr": CONFIG.lr, "ent_coef": 50.0, "num_envs": 4}
    # the tiny policy starts near uniform (at most 4 ln 3 + 2 ln 2); the bonus brings it nearer, where the
    # uninterrupted run moved away
    uniform = 4 * math.log(3) + 2 * math.log(2)
    ref_meta, ref_arrays = final_state(reference)
    assert uniform - summary["metrics"][-1]["entropy"] < 0.8 * (uniform - ref_meta["history"][-1]["entropy"])
    _, arrays = final_state(bonus)
    assert max(float(np.max(np.abs(arrays[k] - ref_arrays[k]))) for k in arrays
               if k.startswith(".train_state.params")) > 1e-5
    assert main(["train", "--resume", str(bonus), "--ent-coef", "-1"]) == 2  # refused, and nothing changed
    assert json.loads((bonus / "metrics.json").read_text()) == summary


def test_rebase_schedule_keeps_the_rate_of_the_plan_at_the_same_update():
    import jax.numpy as jnp
    import optax
    from flax.training.train_state import TrainState

    from kinetix.agents.ppo import rebase_schedule

    config = TrainConfig(total_timesteps=4 * 8 * 10, num_envs=4, num_steps=8, num_minibatches=2, update_epochs=3)
    schedule = optax.linear_schedule(1.0, 0.0, config.num_updates * 3 * 2)
    state = TrainState.create(apply_fn=None, params={"w": jnp.ones(3)},
                              tx=optax.chain(optax.clip_by_global_norm(1.0), optax.adam(schedule)))
    for _ in range(4 * 3 * 2):  # 4 updates of 3 epochs x 2 minibatches
        state = state.apply_gradients(grads={"w": jnp.ones(3)})

    def counts(s):
        found = {}
        for path, leaf in jax.tree_util.tree_leaves_with_path(s.opt_state):
            found[jax.tree_util.keystr(path)] = int(leaf) if jnp.ndim(leaf) == 0 else None
        return {k: v for k, v in found.items() if v is not None}

    assert set(counts(state).values()) == {24}  # Adam's and the schedule's
    assert counts(rebase_schedule(state, config, 4)) == counts(state)  # the same cut: unchanged
    finer = rebase_schedule(state, dataclasses.replace(config, num_minibatches=8), 4)
    assert sorted(counts(finer).values()) == [24, 4 * 3 * 8]  # the schedule's count moves, Adam's does not
    # the rate the next step takes: that of update 4 of 10 under the new cut, 1 - 4/10
    new_schedule = optax.linear_schedule(1.0, 0.0, config.num_updates * 3 * 8)
    assert float(new_schedule(4 * 3 * 8)) == pytest.approx(1 - 4 / 10)
    assert {leaf.dtype for leaf in jax.tree.leaves(finer.opt_state) if leaf.ndim == 0} == {jnp.dtype(jnp.int32)}


@pytest.mark.slow
def test_resume_with_another_batch_cut_trains_on_and_records_it(reference, tmp_path):
    out = tmp_path / "run"
    half = dict(RUN, steps=STEPS // 2)
    train_agent("random-s", out, **half, save_state=True)  # 4 updates of 1 epoch x 2 minibatches
    finer = dataclasses.replace(CONFIG, num_minibatches=4, update_epochs=2)
    summary = train_agent("random-s", out, **dict(RUN, config=finer), resume=True)
    assert summary["complete"] and [m["update"] for m in summary["metrics"]] == list(range(1, 9))
    assert summary["plans"] == [{"update": 0, "steps": STEPS // 2},
                                {"update": 4, "steps": STEPS, "update_epochs": 2, "num_minibatches": 4,
                                 "lr": CONFIG.lr, "ent_coef": CONFIG.ent_coef, "num_envs": 4}]
    _, arrays = final_state(out)
    counts = sorted(int(v) for k, v in arrays.items() if k.startswith(".train_state.opt_state") and k.endswith("count"))
    # Adam took 4 x 2 + 4 x 8 steps; the schedule's count was re-based to 4 updates x 8 at the resume
    assert counts == [4 * 1 * 2 + 4 * 2 * 4, 8 * 2 * 4]


def test_resume_with_more_environments_carries_the_learning_and_counts_the_steps(tmp_path):
    """--resume DIR --num-envs N (a bigger batch where a GPU is lent): parameters, Adam, PLR buffer, key and update
    index carry over and every environment restarts, at the new count; the env steps go on from where they were,
    and a later resume from the command line counts them the same."""
    out = tmp_path / "run"
    train_agent("random-s", out, **dict(RUN, steps=STEPS // 2), save_state=True)  # 4 updates of 4 x 8: 128 steps
    _, saved, _ = resume.load_latest(out)
    wider = dataclasses.replace(CONFIG, num_envs=8)
    with pytest.warns(UserWarning, match=r"from update 4 on with 8 environments \(was 4\)"):
        restored = train_agent("random-s", out, **dict(RUN, config=wider), resume=True,
                               should_stop=lambda: True)  # stops before its first chunk: writes what it restored
    assert len(restored["metrics"]) == 4
    _, arrays, _ = resume.load_latest(out)
    carried = [p for p in saved if p.startswith((".train_state", ".key", ".update_index", ".curriculum"))]
    assert len(carried) > 10 and all(np.array_equal(arrays[p], saved[p]) for p in carried)
    scores = next(v for k, v in arrays.items() if k.startswith(".curriculum") and "scores" in k)
    assert (scores > NEG / 2).any()  # the PLR buffer came along
    assert arrays[".env_state.level.sim.bodies.active"].shape[0] == 8
    assert (arrays[".env_level_ids"] == -2).all()  # fresh levels, no buffer slot's

    summary = train_agent("random-s", out, **dict(RUN, config=wider), resume=True)  # 128 more steps: 2 updates of 64
    assert summary["complete"] and [m["update"] for m in summary["metrics"]] == list(range(1, 7))
    assert [m["env_steps"] for m in summary["metrics"]] == [32, 64, 96, 128, 192, 256]
    assert summary["steps"] == STEPS and summary["metrics"][-1]["total_steps"] == STEPS
    assert summary["plans"][-1] == {"update": 4, "steps": STEPS, "update_epochs": 1, "num_minibatches": 2,
                                    "lr": CONFIG.lr, "ent_coef": CONFIG.ent_coef, "num_envs": 8, "env_steps": 128}
    assert main(["train", "--resume", str(out), "--steps", str(2 * STEPS)]) == 0  # 8 envs from the saved run
    longer = json.loads((out / "metrics.json").read_text())
    assert [m["env_steps"] for m in longer["metrics"][6:]] == [320, 384, 448, 512]
    assert longer["config"]["num_envs"] == 8 and longer["steps"] == 2 * STEPS



@pytest.mark.slow
def test_resume_with_another_learning_rate_trains_at_it_and_records_it(reference, tmp_path):
    out = tmp_path / "run"
    train_agent("random-s", out, **dict(RUN, steps=STEPS // 2), save_state=True)  # 4 updates at 3e-4
    _, half_arrays, _ = resume.load_latest(out)
    params = [k for k in half_arrays if k.startswith(".train_state.params")]
    _, ref_arrays = final_state(reference)  # the same 4 updates, then 4 more at 3e-4

    def moved(arrays):  # the largest change of a parameter over the last 4 updates
        return max(float(np.max(np.abs(arrays[k] - half_arrays[k]))) for k in params)

    assert moved(ref_arrays) > 1e-4
    slow = dataclasses.replace(CONFIG, lr=1e-12)
    summary = train_agent("random-s", out, **dict(RUN, config=slow), resume=True)
    assert summary["complete"] and [m["update"] for m in summary["metrics"]] == list(range(1, 9))
    assert summary["plans"][-1] == {"update": 4, "steps": STEPS, "update_epochs": 1, "num_minibatches": 2,
                                    "lr": 1e-12, "ent_coef": CONFIG.ent_coef, "num_envs": 4}
    _, arrays = final_state(out)
    assert moved(arrays) < 1e-9  # Adam's steps are about the rate in size: 8 of them at 1e-12
    with pytest.raises(CheckpointError, match="anneal_lr: True in the checkpoint, False now"):
        train_agent("random-s", out, **dict(RUN, config=dataclasses.replace(slow, anneal_lr=False)), resume=True)


def test_sfl_settings_from_the_command_line_are_part_of_the_run(monkeypatch):
    """`--sfl-refresh-every N` (like `--sfl-candidates` and `--buffer-size`) sets the run's curriculum config; a
    resumed job (which names nothing but the directory) keeps the saved value, and one given again is kept for
    train_agent to compare."""
    import argparse

    from kinetix.agents.train import settings_from_args
    from kinetix.cli import _train_arguments

    parser = argparse.ArgumentParser()
    _train_arguments(parser)
    fresh = settings_from_args(parser.parse_args(["--level", "random-all", "--curriculum", "sfl",
                                                  "--sfl-refresh-every", "2"]))
    assert fresh["level"] == "random-all" and fresh["curriculum_config"].refresh_every == 2
    saved = {"level": "random-all", "curriculum": "sfl", "config": {},
             "curriculum_config": dataclasses.asdict(CurriculumConfig(refresh_every=2))}
    monkeypatch.setattr(resume, "load_latest", lambda out: ({"arguments": saved}, {}, Path(out)))
    resumed = settings_from_args(parser.parse_args(["--resume", "somewhere"]))
    assert resumed["curriculum_config"].refresh_every == 2 and resumed["curriculum"] == "sfl"
    changed = settings_from_args(parser.parse_args(["--resume", "somewhere", "--sfl-refresh-every", "3"]))
    assert changed["curriculum_config"].refresh_every == 3  # train_agent refuses it: it differs from the run
    sized = settings_from_args(parser.parse_args(["--level", "random-all", "--curriculum", "sfl",
                                                  "--sfl-candidates", "1024", "--buffer-size", "128"]))
    assert (sized["curriculum_config"].candidates, sized["curriculum_config"].buffer_size) == (1024, 128)
    assert sized["curriculum_config"].refresh_every == CurriculumConfig().refresh_every


@pytest.mark.slow
def test_sfl_trains_on_random_all_levels(tmp_path):
    config = dataclasses.replace(CONFIG, width=8, hidden=16)
    curriculum = CurriculumConfig(buffer_size=4, candidates=4, attempts=1, refresh_every=2)
    summary = train_agent("random-all", tmp_path, steps=4 * 8 * 2, config=config, curriculum="sfl",
                          curriculum_config=curriculum, save_state=True)
    assert summary["complete"] and len(summary["metrics"]) == 2
    meta, arrays, _ = resume.load_latest(tmp_path)
    assert meta["arguments"]["level"] == "random-all"
    # each size class in its own group of environments at its own size, with its own sfl buffer
    assert summary["size_groups"] == meta["run"]["size_groups"] == {"s": 1, "m": 1, "l": 2}
    assert {"solve_rate_s", "solve_rate_m", "solve_rate_l"} <= set(summary["metrics"][-1])
    assert arrays[".env_state[0].level.sim.bodies.active"].shape == (1, 7)  # s: 5 polygons + 2 circles
    assert arrays[".env_state[2].level.sim.bodies.active"].shape == (2, 16)  # l
    assert arrays[".curriculum[1]['scores']"].shape == (1,)  # m's third of the buffer
    longer = train_agent("random-all", tmp_path, steps=4 * 8 * 4, config=config, curriculum="sfl",
                         curriculum_config=curriculum, resume=True)  # resumes with its groups
    assert longer["complete"] and len(longer["metrics"]) == 4 and longer["size_groups"] == summary["size_groups"]


@pytest.mark.slow
def test_a_random_all_run_padded_to_l_resumes_padded_or_goes_on_in_size_groups(tmp_path):
    """Runs started before size groups (every level padded to l in one batch) resume as they were saved, or, asked
    to, go on in size groups with everything they learned."""
    config = dataclasses.replace(CONFIG, width=8, hidden=16)
    plr = dict(curriculum="plr", curriculum_config=CURRICULUM)  # a curriculum with a state: PLR's buffer
    summary = train_agent("random-all", tmp_path, steps=64, config=config, save_state=True, size_groups=False, **plr)
    _, arrays, _ = resume.load_latest(tmp_path)
    assert summary["size_groups"] is None and arrays[".env_state.level.sim.bodies.active"].shape == (4, 16)
    longer = train_agent("random-all", tmp_path, steps=128, config=config, **plr, resume=True)
    assert longer["complete"] and len(longer["metrics"]) == 4 and longer["size_groups"] is None
    _, padded, _ = resume.load_latest(tmp_path)
    # asked to, it goes on in size groups: the same parameters, optimiser, key and update count, fresh environments
    with pytest.warns(UserWarning, match="from update 4 on in size groups"):
        grouped = train_agent("random-all", tmp_path, steps=192, config=config, **plr, resume=True, size_groups=True,
                              should_stop=lambda: True)  # stops before its first chunk: writes what it restored
    assert grouped["size_groups"] == {"s": 1, "m": 1, "l": 2} and len(grouped["metrics"]) == 4
    assert grouped["plans"][-1] == {"update": 4, "steps": 192, "size_groups": {"s": 1, "m": 1, "l": 2}}
    meta, arrays, _ = resume.load_latest(tmp_path)
    assert meta["run"]["size_groups"] == grouped["size_groups"]
    carried = [path for path in padded if path.startswith((".train_state", ".key", ".update_index"))]
    assert len(carried) > 10 and all(np.array_equal(arrays[path], padded[path]) for path in carried)
    assert arrays[".env_state[0].level.sim.bodies.active"].shape == (1, 7)
    assert (arrays[".curriculum[2]['scores']"] == NEG).all()  # l's own buffer (2 slots), empty until played
    again = train_agent("random-all", tmp_path, steps=192, config=config, **plr, resume=True)  # now in groups
    assert again["complete"] and len(again["metrics"]) == 6 and again["size_groups"] == grouped["size_groups"]
    with pytest.raises(CheckpointError, match="size_groups: {'s': 1, 'm': 1, 'l': 2} in the checkpoint, None now"):
        train_agent("random-all", tmp_path, steps=256, config=config, **plr, resume=True, size_groups=False)
    with pytest.raises(ValueError, match="size groups are for --level random-all"):
        train_agent("random-s", tmp_path / "s", steps=32, config=config, size_groups=True)


def test_a_compact_state_continues_the_run_with_fresh_environments(reference, tmp_path, capsys):
    """`python -m kinetix.agents.resume compact DIR` keeps the learning (parameters, Adam, PLR buffer, key, update
    index) and drops the environments; the run resumes from it, longer, with every environment on a fresh level."""
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    _, full, _ = resume.load_latest(out)
    assert resume.main(["compact", str(out)]) == 0
    shutil.rmtree(out / "checkpoint")  # what gets committed: the compact state (and metrics), nothing else needed
    (out / "curve.png").unlink()
    meta, arrays, path = resume.load_latest(out)
    assert [p.name for p in resume.state_dir(out).iterdir()] == [path.name] and meta["compact"]
    assert resume.is_compact(arrays) and not resume.is_compact(full)
    assert not any(p.startswith(".env_state") for p in arrays) and len(arrays) < len(full)
    for name, array in arrays.items():  # what is kept is kept exactly
        np.testing.assert_array_equal(array, full[name])
    with pytest.warns(UserWarning, match="compact training state"):
        summary = train_agent("random-s", out, **dict(RUN, steps=2 * STEPS), resume=True)
    assert summary["complete"] and len(summary["metrics"]) == 16 and summary["resumed_at_update"] == 8
    assert (out / "checkpoint" / "params.msgpack").is_file() and (out / "curve.png").is_file()
    assert np.isfinite([m["mean_return"] for m in summary["metrics"][8:]]).all()
    assert resume.main(["compact", str(tmp_path / "nothing")]) == 2
    assert "no training state" in capsys.readouterr().err


@pytest.mark.slow
def test_a_run_in_size_groups_keeps_its_groups_on_other_devices(tmp_path):
    """The groups are part of the run: saved on one device (8 envs: 2, 3, 3), it resumes with them wherever the
    devices would cut 8 envs otherwise (on two: 2, 2, 4), on one device if they do not split over the devices."""
    config = dataclasses.replace(CONFIG, num_envs=8, width=8, hidden=16)
    first = train_agent("random-all", tmp_path, steps=128, config=config, save_state=True, shard=False)
    assert first["size_groups"] == {"s": 2, "m": 3, "l": 3}
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # two CPU devices in the child: --devices 2
    result = subprocess.run([sys.executable, "-m", "kinetix", "train", "--resume", str(tmp_path), "--steps", "256",
                             "--devices", "2"], cwd=Path(__file__).resolve().parents[3], env=env, capture_output=True,
                            text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    longer = json.loads((tmp_path / "metrics.json").read_text())
    assert longer["devices"] == 2 and len(longer["metrics"]) == 4 and longer["size_groups"] == first["size_groups"]
    # with another number of environments (a GPU's batch) the groups are cut afresh; the learning carries over
    _, before, _ = resume.load_latest(tmp_path)
    with pytest.warns(UserWarning, match=r"from update 4 on with 16 environments \(was 8\)"):
        wider = train_agent("random-all", tmp_path, steps=256, config=dataclasses.replace(config, num_envs=16),
                            resume=True, shard=False, should_stop=lambda: True)
    assert wider["size_groups"] == {"s": 5, "m": 5, "l": 6}
    assert wider["plans"][-1]["size_groups"] == wider["size_groups"] and wider["plans"][-1]["env_steps"] == 256
    _, after, _ = resume.load_latest(tmp_path)
    carried = [path for path in before if path.startswith((".train_state", ".key", ".update_index"))]
    assert len(carried) > 10 and all(np.array_equal(after[path], before[path]) for path in carried)
    assert after[".env_state[2].level.sim.bodies.active"].shape[0] == 6


@pytest.mark.slow
def test_a_run_saved_before_the_architecture_fields_resumes_as_the_run_it_was(tmp_path):
    """States written before TrainConfig had `activation` and `pooled_norm` record neither; their networks were
    relu without a pooled LayerNorm, and a resume must go on so (not with today's defaults) and equal the
    uninterrupted run."""
    relu = {**RUN, "config": dataclasses.replace(CONFIG, activation="relu", pooled_norm=False)}
    whole = tmp_path / "whole"
    train_agent("random-s", whole, **relu, save_state=True)
    out = tmp_path / "old"
    chunks = []
    train_agent("random-s", out, **relu, save_state=True, should_stop=lambda: len(chunks) >= 2,
                progress=lambda m: chunks.append(m) if m["update"] % 2 == 0 else None)
    meta, arrays, _ = resume.load_latest(out)
    for record in (meta["arguments"]["config"], meta["run"]["train"]):
        del record["activation"], record["pooled_norm"]
    resume.save(out, 4, {k: v for k, v in meta.items() if k not in ("format", "version")}, arrays)
    assert "activation" not in resume.load_latest(out)[0]["run"]["train"]
    assert main(["train", "--resume", str(out)]) == 0
    assert_same_run(out, whole)
    saved = json.loads((out / "checkpoint" / "config.json").read_text())["train"]
    assert saved["activation"] == "relu" and saved["pooled_norm"] is False
