"""server.recordings.recent: each tab's last play in the gallery's database, shared by every process on it (two
Store objects on one database stand for two processes), with its limits enforced across them. Runs on SQLite and
PostgreSQL (skipped with a message without KINETIX_TEST_POSTGRES_URL)."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import pytest

from server.recordings.recent import RecentTable, StoredPlay
from server.recordings.recorder import Finished, PlayRecorder

TAB, OTHER = "a" * 32, "b" * 32


def _table(store, **limits) -> RecentTable:
    return RecentTable(store, **{"max_files": 10, "max_bytes": 10_000, "keep_s": 3600, **limits})


def _play(name: str, ended: int, data: bytes = b"mcap bytes", result: str = "solved") -> StoredPlay:
    return StoredPlay(f"play-{name}.mcap", "human", "lvl1", result, 38, 1.27, ended, data)


def test_a_tabs_last_play_put_by_one_process_is_found_by_another_and_only_a_newer_play_replaces_it(two):
    a, b = _table(two[0]), _table(two[1])
    assert b.get(TAB) is None
    assert a.put(TAB, _play("first", ended=1000, data=b"first"))
    assert b.get(TAB) == _play("first", ended=1000, data=b"first")
    assert b.put(TAB, _play("second", ended=2000, data=b"second", result="stopped"))
    # The play a reload cut short, finished late on the old process, does not replace the newer one.
    assert not a.put(TAB, _play("late", ended=1500, data=b"late"))
    assert a.get(TAB).data == b"second" and a.get(TAB).result == "stopped"
    assert a.get(OTHER) is None, "keyed by tab"


def test_a_recording_over_the_bytes_cap_is_not_shared(two, caplog):
    table = _table(two[0], max_bytes=100)
    with caplog.at_level(logging.INFO, "server.recordings.recent"):
        assert not table.put(TAB, _play("big", 1000, data=b"x" * 101))
    assert table.get(TAB) is None and "larger than the recent recordings' cap" in caplog.text


def test_the_sweep_keeps_open_tabs_and_removes_closed_ones_after_the_keep_time_or_over_the_caps(two):
    a, b = (_table(store, max_files=3, keep_s=3600, live_s=30) for store in two)
    start = time.time()
    tabs = [f"{i:032d}" for i in range(5)]
    for i, tab in enumerate(tabs):  # stored a minute apart; none seen since
        a.put(tab, _play(str(i), ended=i), now=start + 60 * i)
    # 4 minutes later tabs 0 and 1 are open on B (its heartbeat marks them); the others closed.
    later = start + 300
    b.touch([tabs[0], tabs[1]], now=later)
    assert b.sweep(now=later) == [tabs[2], tabs[3]], "over the cap the oldest closed tabs go; open ones stay"
    assert a.get(tabs[0]) is not None and a.get(tabs[4]) is not None
    # An hour after their last sign of life (closed, or their process died) the rest go too.
    assert sorted(a.sweep(now=later + 3601)) == [tabs[0], tabs[1], tabs[4]]


def test_the_sweep_never_removes_a_row_seen_after_it_looked(two, monkeypatch):
    if two[0].dialect == "sqlite":
        pytest.skip("SQLite serialises writers (BEGIN IMMEDIATE): no write can land inside a sweep")
    a, b = (_table(store, keep_s=10, live_s=5) for store in two)
    a.put(TAB, _play("old", ended=1), now=time.time() - 60)
    look, looked = a._doomed, []

    def look_then_reload(conn, stamp):
        looked.extend(look(conn, stamp))
        b.touch([TAB])  # meanwhile the tab reloads on B, which marks its row (its own transaction)
        return looked

    monkeypatch.setattr(a, "_doomed", look_then_reload)
    assert a.sweep() == [] and [tab for tab, _ in looked] == [TAB], "it meant to remove the row, but spared it"
    assert b.get(TAB) is not None


class _Tab:
    """What PlayRecorder reads of a Session: the tab's key and whether it is closed."""

    def __init__(self, tab_key: str | None):
        self.tab_key, self.closed = tab_key, False


def _recorder(store, folder: Path, heartbeat_s: float = 3600) -> PlayRecorder:
    return PlayRecorder(folder, table=_table(store, heartbeat_s=heartbeat_s))


def test_a_play_recorded_on_one_process_is_the_tabs_last_play_on_another(two, tmp_path):
    a, b = _recorder(two[0], tmp_path / "a"), _recorder(two[1], tmp_path / "b")
    try:
        made = a.recent / "play-20261126-120000-abcd1234.mcap"
        made.write_bytes(b"a complete recording")
        a._share(TAB, Finished(made, "human", "lvl1", "solved", 38, 1.27), ended=time.time())
        reloaded = _Tab(TAB)  # the same tab after a reload through B: a new session with the tab's key
        b.session_opened(reloaded)
        finished = b.last_finished(reloaded)
        assert finished == Finished(b.recent / made.name, "human", "lvl1", "solved", 38, 1.27)
        assert finished.path.read_bytes() == b"a complete recording"
        assert b.last_finished(_Tab(OTHER)) is None and b.last_finished(_Tab(None)) is None
        assert b.clean_up() == [], "the fetched file is the open tab's last play: kept"
    finally:
        a.close()
        b.close()


def test_the_heartbeat_keeps_an_open_tabs_row_and_a_closed_tab_starts_its_keep_time(two, tmp_path):
    recorder = _recorder(two[0], tmp_path, heartbeat_s=0.05)
    table = recorder.table
    try:
        table.put(TAB, _play("x", 1), now=time.time() - 7200)  # stored two hours ago, by a session now gone
        table.put(OTHER, _play("y", 1), now=time.time() - 7200)
        tab = _Tab(TAB)
        recorder.session_opened(tab)  # the tab reloaded here: its row is seen again
        deadline = time.time() + 20
        while table.get(OTHER) is not None and time.time() < deadline:
            time.sleep(0.05)
        assert table.get(OTHER) is None, "the heartbeat's sweep removed the closed tab's old row"
        assert table.get(TAB) is not None, "and kept the open one's"
        recorder.session_closed(tab)
        recorder.close()  # the finisher has marked it at its close
        with table.store._read() as conn:
            seen = conn.exec_driver_sql("SELECT seen FROM recent_recordings").scalar_one()
        assert time.time() * 1000 - seen < 10_000
    finally:
        recorder.close()


def test_a_table_that_fails_loses_nothing_but_the_sharing(two, tmp_path, caplog):
    recorder = _recorder(two[0], tmp_path)
    try:
        def refuse(*args, **kwargs):
            raise OSError("database gone")

        recorder.table.put = refuse
        made = recorder.recent / "play-x.mcap"
        made.write_bytes(b"data")
        with caplog.at_level(logging.WARNING, "server.recordings.recorder"):
            recorder._share(TAB, Finished(made, "human", None, "stopped", 3, 0.1), ended=time.time())
        assert "not shared" in caplog.text and made.read_bytes() == b"data"
    finally:
        recorder.close()


def test_stored_plays_round_trip_every_field(two):
    table = _table(two[0])
    play = dataclasses.replace(_play("fields", 123456789012), level_id=None, player="agent:general", steps=0,
                               seconds=0.0, data=bytes(range(256)))
    table.put(TAB, play)
    assert _table(two[1]).get(TAB) == play
