"""server.gallery.runs: the gallery keeps one recording per level, the best human solve's (fewest seconds, then
fewest steps), deletes superseded files, serves it at /api/levels/{id}/best-run.mcap and flags it in the stats."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.gallery.runs import BestRuns
from server.gallery.store import Store
from tests.gallery.conftest import level_doc


@pytest.fixture
def runs(db_url: str, tmp_path: Path):
    store = Store(db_url, seed_dir=None, recordings_dir=tmp_path / "recordings")
    yield BestRuns(store)
    store.close()


def _solve(runs: BestRuns, level_id: str, tmp_path: Path, steps: int, seconds: float, kind: str = "human"):
    """Offer a finished solve's recording as tab.GalleryLink.record_play does; returns the kept file name or None."""
    source = tmp_path / f"play-{steps}-{seconds}.mcap"
    source.write_bytes(f"run {steps} {seconds}".encode())
    name = runs.offer(level_id, source, steps, seconds) if kind == "human" else None
    runs.store.record_play(level_id, kind, solved=True, steps=steps, seconds=seconds, recording_path=name)
    if name is not None:
        runs.prune(level_id)
    return name


def test_only_the_best_human_solve_keeps_its_recording(runs, tmp_path):
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


def test_a_faster_unrecorded_solve_hides_the_kept_run_so_best_time_and_best_run_agree(runs, tmp_path):
    level_id, _ = runs.store.create_level("lvl", level_doc())
    kept = _solve(runs, level_id, tmp_path, 48, 1.6)
    assert runs.best_run_file(level_id).name == kept
    # A faster human solve without a recording (a --no-record server, a recording that failed): the kept run did
    # not set the best time any more, so it is not offered as the best run.
    runs.store.record_play(level_id, "human", solved=True, steps=38, seconds=38 / 30)
    stats = runs.store.stats(level_id)
    assert stats["best_human_steps"] == 38
    assert runs.best_run_file(level_id) is None and stats["has_best_run"] is False
    # A recorded solve as fast as the best time is the best run again.
    tie = _solve(runs, level_id, tmp_path, 38, 38 / 30)
    assert tie is not None and runs.best_run_file(level_id).name == tie
    assert runs.store.stats(level_id)["has_best_run"] is True


def test_orphans_and_other_levels(runs, tmp_path):
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


def test_api_serves_the_best_run_or_a_404_with_a_message(runs, tmp_path):
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
        assert client.get(f"/api/levels/{level_id}/best-run.mcap").status_code == 404
        assert "best-run.mcap" in str(client.get("/openapi.json").json()["paths"])
