"""server.gallery.runs: the gallery keeps one recording per level, the best human solve's (fewest seconds, then
fewest steps), deletes superseded files, serves it at /api/levels/{id}/best-run.mcap and flags it in the stats;
a play sets the best time only if its recording re-simulates to a solve of the gallery level (server.gallery.proof)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from kinetix.levels import load_level, to_document
from server.gallery import runs as runs_module
from server.gallery.runs import BestRuns
from server.gallery.schema import recording_files_t
from server.gallery.store import Store
from tests.gallery.conftest import level_doc


@pytest.fixture
def runs(db_url: str, tmp_path: Path):
    store = Store(db_url, seed_dir=None, recordings_dir=tmp_path / "recordings")
    yield BestRuns(store)
    store.close()


@pytest.fixture
def unverified(monkeypatch):
    """For the ordering and retention tests: their stand-in files pass as proven records."""
    monkeypatch.setattr(runs_module, "why_not_a_record", lambda *args, **kwargs: None)


def _solve(runs: BestRuns, level_id: str, tmp_path: Path, steps: int, seconds: float, kind: str = "human"):
    """Offer a finished solve's recording as tab.GalleryLink.record_play does; returns the kept file name or None."""
    source = tmp_path / f"play-{steps}-{seconds}.mcap"
    source.write_bytes(f"run {steps} {seconds}".encode())
    name = runs.offer(level_id, source, steps, seconds) if kind == "human" else None
    runs.store.record_play(level_id, kind, solved=True, steps=steps, seconds=seconds, recording_path=name)
    if name is not None:
        runs.prune(level_id)
    return name


def test_only_the_best_human_solve_keeps_its_recording(runs, tmp_path, unverified):
    level_id, _ = runs.store.create_level("lvl", level_doc())
    assert runs.best_run_file(level_id) is None and runs.store.stats(level_id)["has_best_run"] is False
    first = _solve(runs, level_id, tmp_path, 100, 3.3)
    assert runs.best_run_file(level_id).read_bytes() == b"run 100 3.3"
    assert runs.store.stats(level_id)["has_best_run"] is True

    assert _solve(runs, level_id, tmp_path, 120, 4.0) is None, "slower: not copied"
    assert _solve(runs, level_id, tmp_path, 100, 3.3) is None, "a tie on seconds and steps keeps the earlier run"
    faster = _solve(runs, level_id, tmp_path, 90, 3.0)
    assert faster is not None
    assert not (runs.directory / first).exists(), "the superseded best run's file is deleted"
    assert runs.best_run_file(level_id).name == faster

    # Same seconds, fewer steps wins the tie (levels can change their time step between plays).
    fewer = _solve(runs, level_id, tmp_path, 80, 3.0)
    assert fewer is not None and not (runs.directory / faster).exists()
    assert sorted(p.name for p in runs.directory.glob("best-*.mcap")) == [fewer]
    _solve(runs, level_id, tmp_path, 10, 0.3, kind="agent")  # agents never become the human best run
    assert runs.best_run_file(level_id).name == fewer


def test_a_solve_without_a_recording_counts_as_a_play_but_sets_no_best_time(runs, tmp_path, caplog):
    level_id, _ = runs.store.create_level("lvl", level_doc())
    runs.store.record_play(level_id, "human", solved=True, steps=38, seconds=38 / 30)  # e.g. --no-record
    tab = SimpleNamespace(gallery_id=level_id)
    with caplog.at_level(logging.WARNING, "server.gallery.runs"):
        assert runs.offer(level_id, None, 38, 38 / 30) is None
        assert runs.candidate(None, tab, "solved", 38, 38 / 30) is None  # a server without a PlayRecorder
        assert runs.candidate(None, tab, "solved", 38, 38 / 30) is None
    assert "sets no best time: the play has no recording" in caplog.text
    assert caplog.text.count("plays are not recorded (--no-record)") == 1, "said once"
    stats = runs.store.stats(level_id)
    assert stats["human_solved"] == 1 and stats["best_human_seconds"] is None and stats["has_best_run"] is False
    assert runs.best_run_file(level_id) is None


# ---------------------------------------------------------------------- verification by replay (real recordings)


def _falling_level(runs: BestRuns) -> tuple[str, object]:
    from kinetix.formats import build
    from tests.server.fake_editor import falling_win_spec

    document = to_document(build(falling_win_spec()))  # a ball that falls onto the goal: solved with no key held
    level_id, _ = runs.store.create_level("falling", document)
    return level_id, load_level(document)


def _record_solve(path: Path, level_id: str, level_file, forge_win_at: int | None = None) -> tuple[int, float]:
    """Play the level with no key held and record it as the server does; returns (steps, seconds).
    `forge_win_at`: a tampered file that says the play was solved at that step (it was not)."""
    from kinetix.actions import noop_action
    from kinetix.env import EnvConfig, EnvParams, make_env
    from kinetix.recording import Recorder, step_function

    env = make_env(EnvConfig(size=level_file.size, frame_skip=level_file.params.frame_skip), level_file)
    params = EnvParams.from_level_params(level_file.params)
    step, state = step_function(env.config), env.initial_state(None, params)
    action = np.asarray(noop_action(env.config.action))
    with Recorder(path, level_file, metadata={"player": "human", "level_id": level_id, "seed": 0},
                  env_config=env.config, env_params=params) as recorder:
        for steps in range(1, 300):
            state, reward, terminated, truncated, _ = step(state, action, params)
            if steps == forge_win_at:
                reward, terminated = np.float32(1.0), True
            recorder.add_step(action, reward, terminated, truncated, state)
            if terminated or truncated:
                break
    assert terminated and float(reward) > 0.5, "the falling ball solves its level"
    return steps, steps * level_file.params.frame_skip * level_file.params.dt


def test_a_genuine_solve_sets_the_record_after_replay(runs, tmp_path):
    level_id, level_file = _falling_level(runs)
    steps, seconds = _record_solve(tmp_path / "play.mcap", level_id, level_file)
    name = runs.offer(level_id, tmp_path / "play.mcap", steps, seconds)
    assert name is not None
    runs.store.record_play(level_id, "human", solved=True, steps=steps, seconds=seconds, recording_path=name)
    stats = runs.store.stats(level_id)
    assert stats["best_human_steps"] == steps and stats["has_best_run"] is True
    assert runs.best_run_file(level_id).read_bytes() == (tmp_path / "play.mcap").read_bytes()


def test_tampered_or_mismatched_recordings_are_refused_and_the_record_stays(runs, tmp_path, caplog):
    level_id, level_file = _falling_level(runs)
    kept = runs.directory / f"best-{level_id}-kept.mcap"  # a slower record, kept from before
    kept.write_bytes(b"kept")
    runs.store.record_play(level_id, "human", solved=True, steps=100, seconds=5.0, recording_path=kept.name)
    genuine, forged, moved = tmp_path / "genuine.mcap", tmp_path / "forged.mcap", tmp_path / "moved.mcap"
    steps, seconds = _record_solve(genuine, level_id, level_file)
    forged_steps, forged_seconds = _record_solve(forged, level_id, level_file, forge_win_at=3)
    # The recording's level is not the gallery's: the ball starts lower.
    sim = level_file.level.sim
    lower = dataclasses.replace(sim.bodies, position=sim.bodies.position.at[:, 1].add(-0.3))
    moved_file = dataclasses.replace(level_file, level=dataclasses.replace(
        level_file.level, sim=dataclasses.replace(sim, bodies=lower)))
    moved_steps, moved_seconds = _record_solve(moved, level_id, moved_file)
    (tmp_path / "garbage.mcap").write_bytes(b"not a recording")
    claims = {"does not re-simulate": (forged, forged_steps, forged_seconds),
              f"has {steps} steps, the play claims {steps - 2}": (genuine, steps - 2, seconds),
              "the play claims": (genuine, steps, seconds - 0.1),
              "another level than the gallery's": (moved, moved_steps, moved_seconds),
              "unreadable": (tmp_path / "garbage.mcap", 1, 0.05),
              "no recording": (None, 1, 0.05)}
    for reason, (path, claim_steps, claim_seconds) in claims.items():
        caplog.clear()
        with caplog.at_level(logging.WARNING, "server.gallery.runs"):
            assert runs.offer(level_id, path, claim_steps, claim_seconds) is None, reason
        assert reason in caplog.text
    stats = runs.store.stats(level_id)
    assert (stats["best_human_steps"], stats["best_human_seconds"]) == (100, 5.0)
    assert runs.best_run_file(level_id) == kept
    assert sorted(p.name for p in runs.directory.iterdir()) == [kept.name], "refused copies leave nothing"


def test_orphans_and_other_levels(runs, tmp_path, unverified):
    a, _ = runs.store.create_level("a", level_doc())
    b, _ = runs.store.create_level("b", level_doc())
    kept_a = _solve(runs, a, tmp_path, 50, 2.0)
    kept_b = _solve(runs, b, tmp_path, 70, 2.5)
    assert runs.best_run_file(a).name == kept_a and runs.best_run_file(b).name == kept_b
    orphan = runs.directory / f"best-{a}-deadbeef.mcap"  # e.g. copied, then the server died before the insert
    orphan.write_bytes(b"x")
    assert runs.remove_orphans() == [orphan]
    assert (runs.directory / kept_a).exists() and (runs.directory / kept_b).exists()
    runs.store.delete_level(b, None, admin=True)
    assert runs.remove_orphans() == [runs.directory / kept_b], "a deleted level's best run goes at start-up"


def test_api_serves_the_best_run_or_a_404_with_a_message(runs, tmp_path, unverified):
    from fastapi.testclient import TestClient

    from server.gallery.app import create_gallery_app

    level_id, _ = runs.store.create_level("lvl", level_doc())
    with TestClient(create_gallery_app(runs.store), base_url="http://localhost") as client:
        missing = client.get(f"/api/levels/{level_id}/best-run.mcap")
        assert missing.status_code == 404 and "no recorded best run" in missing.json()["detail"]
        assert client.get("/api/levels/nope/best-run.mcap").status_code == 404
        name = _solve(runs, level_id, tmp_path, 100, 3.3)
        response = client.get(f"/api/levels/{level_id}/best-run.mcap")
        assert response.status_code == 200 and response.content == (runs.directory / name).read_bytes()
        assert f'filename="best-run-{level_id}.mcap"' in response.headers["content-disposition"]
        summary = client.get(f"/api/levels/{level_id}").json()
        assert summary["stats"]["has_best_run"] is True
        (runs.directory / name).unlink()  # a file lost behind the database's back: 404, not a 500
        if runs.shared:  # PostgreSQL: the local file is a cache of the shared copy, fetched again
            assert client.get(f"/api/levels/{level_id}/best-run.mcap").content == response.content
            with runs.store._write() as conn:
                conn.execute(recording_files_t.delete())
            (runs.directory / name).unlink()
        assert client.get(f"/api/levels/{level_id}/best-run.mcap").status_code == 404
        assert "best-run.mcap" in str(client.get("/openapi.json").json()["paths"])


def test_a_level_opened_in_a_tab_plays_bitwise_the_gallerys_stored_level():
    """The proof compares the recording's level with load_level(stored document): a genuine play must pass."""
    import json

    from kinetix.formats import build
    from kinetix.levels import read_json
    from server.editor import levelio
    from server.gallery.proof import _same_level
    from server.gallery.store import REPO_LEVELS

    files = sorted(Path(REPO_LEVELS).glob("*.json"))
    assert files
    for path in files:
        document = to_document(load_level(read_json(path)))  # what the gallery stores and serves
        spec, size = levelio.parse(json.dumps(document).encode(), path.name)  # what Session.open_level plays
        assert _same_level(build(spec, size), load_level(document)), path.name


def test_a_best_run_kept_by_one_process_is_served_by_another(pg_schema_url, tmp_path, unverified):
    """Two processes on one PostgreSQL gallery, each with its own data directory: A keeps the run, B serves it;
    when A's run is beaten on B, A no longer finds the superseded one."""
    a_store = Store(pg_schema_url, seed_dir=None, recordings_dir=tmp_path / "a")
    b_store = Store(pg_schema_url, seed_dir=None, recordings_dir=tmp_path / "b")
    try:
        a, b = BestRuns(a_store), BestRuns(b_store)
        level_id, _ = a_store.create_level("lvl", level_doc())
        kept = _solve(a, level_id, tmp_path, 100, 3.3)
        assert not (tmp_path / "b" / kept).exists()
        assert b.best_run_file(level_id).read_bytes() == b"run 100 3.3", "fetched from the shared table"
        faster = _solve(b, level_id, tmp_path, 90, 3.0)
        assert a.best_run_file(level_id).name == faster and a.best_run_file(level_id).read_bytes() == b"run 90 3.0"
        with a_store._read() as conn:
            assert [r.name for r in conn.execute(recording_files_t.select())] == [faster], "superseded row gone"
    finally:
        a_store.close()
        b_store.close()
