"""Recordings in the browser (server.recordings.recorder, server.recordings.replay, server.gallery.runs) at the
protocol level: every play is recorded and replays bitwise, Download recording sends a valid MCAP, replay mode
pushes frames and scrubs, bad uploads get a clear message, a disconnect leaves a finished file or none, the gallery
keeps the best human solve."""

from __future__ import annotations

import io
import json
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from fake_editor import falling_win_spec
from PIL import Image
from viser_client import KeysSocket

from kinetix.formats import build
from kinetix.levels import to_document
from kinetix.recording import read_recording, recorded_level, verify
from server.play.session import Controller
from server.play.steps import action_from_keys
from tests.server.conftest import LEVELS, running_app, session_of, wait_until

CAR = LEVELS / "car_ramp.json"


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with running_app(gallery=True, data=tmp_path_factory.mktemp("data"), warm_sizes=("m",), max_sessions=4,
                     level=str(CAR)) as app:
        yield app


def _wait(predicate, timeout=30.0):
    wait_until(predicate, timeout)


def _session(app, client):
    return session_of(app, client, 30.0)


def _download(client, start: int = 0, timeout: float = 30.0) -> tuple[str, bytes]:
    """The file of the first download the server started after message `start`, assembled from its parts."""
    head = client.wait_for(lambda m: m["type"] == "FileTransferStartDownload", timeout, start)
    uuid, parts = head["transfer_uuid"], head["part_count"]
    def is_part(m: dict) -> bool:
        return m["type"] == "FileTransferPart" and m["transfer_uuid"] == uuid

    _wait(lambda: len(client.matching(is_part)) == parts, timeout)
    chunks = sorted((m["part_index"], m["content"]) for m in client.matching(is_part))
    return head["filename"], b"".join(c for _, c in chunks)


def _upload(client, label: str, name: str, data: bytes) -> None:
    _wait(lambda: any(e.get("label") == label for e in client.gui().values()))
    uuid = client.find_gui(label)["uuid"]
    transfer = f"t{time.monotonic_ns()}"
    size = 1 << 16
    parts = [data[i:i + size] for i in range(0, len(data), size)] or []
    client.send("FileTransferStartUpload", source_component_uuid=uuid, transfer_uuid=transfer, filename=name,
                mime_type="application/octet-stream", part_count=len(parts), size_bytes=len(data))
    for i, part in enumerate(parts):
        client.send("FileTransferPart", source_component_uuid=uuid, transfer_uuid=transfer, part_index=i,
                    content=part)


def _click(client, label: str) -> None:
    """Click a button once the tab has it (GUI messages arrive a moment after the session is registered)."""
    _wait(lambda: any(e.get("label") == label for e in client.gui().values()))
    client.click_button(label)


def _status(client) -> str:
    # viser sends a markdown element's text as its "_markdown" property
    return " ".join(str(e.get("_markdown", "")) for e in client.gui().values() if e["type"] == "GuiMarkdownMessage")


def _play_keys(app, session, keys: KeysSocket, held: str, steps: int) -> None:
    """Play with `held` held for `steps` steps, then release and Esc (a stopped play)."""
    session.toggle_play()
    keys.down(held)
    _wait(lambda: session._steps >= steps)
    keys.up(held)
    _wait(lambda: session._steps >= steps + 5)
    keys.down("Escape")
    _wait(lambda: session.mode == "edit")


def _recorder(app):
    return app.recorder


def test_a_keyboard_play_is_recorded_and_re_simulates_bitwise(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce)
    try:
        _play_keys(app, session, keys, "ArrowRight", 20)
        steps = session._steps
        finished = _recorder(app).last_finished(session)
    finally:
        keys.close()
    assert finished is not None and finished.path is not None and finished.result == "stopped"
    assert finished.path.parent == app.store.recordings_dir / "recent"
    recording = read_recording(finished.path)
    assert recording.num_steps == steps and finished.steps == steps
    assert recording.metadata["player"] == "human" and recording.metadata["seed"] == "0"
    assert recording.metadata["project_version"] and recording.env["frame_skip"] == 2
    right = action_from_keys({"ArrowRight"}, session.clockwise)[0]  # the level's clockwise turn of binding 0
    assert (recording.actions[:, 0] == right).sum() >= 15, "ArrowRight drove motor binding 0"
    assert len(recording.frames) >= 2 and recording.frames[0][:2] == b"\xff\xd8"  # JPEG frames
    assert np.all(np.diff(recording.frame_times) >= 0.1 - 1e-6), "frames at most 10 Hz"
    assert recording.step_times[-1] == pytest.approx(steps * 2 / 60), "simulated time"
    check = verify(recording)
    assert check.ok, check.detail


def test_each_tab_keeps_only_its_last_play_in_recent(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce)
    try:
        _play_keys(app, session, keys, "ArrowLeft", 5)
        first = _recorder(app).last_finished(session).path
        _play_keys(app, session, keys, "ArrowLeft", 5)
        second = _recorder(app).last_finished(session).path
    finally:
        keys.close()
    assert second.exists() and second != first
    assert not first.exists(), "the tab's previous play is deleted once the next one is finished"


class _Agent(Controller):
    player = "agent:test"

    def act(self, state, params):
        return np.array([1, 0, 0, 0, 0, 0], np.int32)


def test_an_agent_play_is_recorded_with_the_agent_as_player(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    session.play(controller=_Agent())
    _wait(lambda: session._steps >= 10)
    session.stop()
    recording = read_recording(_recorder(app).last_finished(session).path)
    assert recording.metadata["player"] == "agent:test"
    assert np.all(recording.actions[:, 0] == 1)
    assert verify(recording).ok


def test_plays_stepped_together_in_a_batch_replay_bitwise(app, make_client):
    """With 3 tabs playing, the server steps them in one vmapped call (bitwise different from single steps):
    the recordings say so per step and re-simulate bitwise."""
    from server.play import steps

    steps.warm_batches_in_background(("m",))
    assert steps.wait_for_compiles(timeout=300)
    sessions = [_session(app, make_client(app))[0] for _ in range(3)]
    for i, session in enumerate(sessions):
        agent = _Agent()
        agent.act = lambda state, params, i=i: np.array([1 + i % 2, 0, 0, 0, 0, 0], np.int32)
        session.play(controller=agent)
    _wait(lambda: all(s._steps >= 40 for s in sessions))
    for session in sessions:
        session.stop()
    recordings = [read_recording(_recorder(app).last_finished(s).path) for s in sessions]
    assert any((r.batches > 1).any() for r in recordings), "no step was batched"
    for recording in recordings:
        check = verify(recording)
        assert check.ok, check.detail


def test_download_sends_the_last_play_and_mid_play_the_steps_so_far(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    start = client.count()
    _click(client, "Download recording")
    _wait(lambda: "Nothing recorded yet" in _status(client))
    keys = KeysSocket(app.port, nonce)
    try:
        _play_keys(app, session, keys, "ArrowRight", 8)
        start = client.count()
        _click(client, "Download recording")
        name, data = _download(client, start)
        assert name.endswith(".mcap") and "stopped" in name
        assert data == _recorder(app).last_finished(session).path.read_bytes()
        assert verify(read_recording(data)).ok

        session.toggle_play()  # a play still running: its steps so far, as a complete file
        keys.down("ArrowLeft")
        _wait(lambda: session._steps >= 12)
        start = client.count()
        _click(client, "Download recording")
        name, data = _download(client, start)
        keys.down("Escape")
    finally:
        keys.close()
    assert "so-far" in name
    partial = read_recording(data)
    assert partial.num_steps >= 12 and partial.metadata["extra"]["partial"] is True
    assert len(partial.frames) >= 2 and np.all(np.diff(partial.frame_times) >= 0.1 - 1e-6)
    assert verify(partial).ok


def _frame(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"), np.int16)


def test_replay_pushes_frames_and_scrubbing_shows_that_steps_state(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce)
    try:
        _play_keys(app, session, keys, "ArrowRight", 60)
    finally:
        keys.close()
    recording = read_recording(_recorder(app).last_finished(session).path)
    start = client.count()
    _click(client, "Replay last play")
    _wait(lambda: session.mode == "replay" and session.replay is not None)
    replay = session.replay
    _wait(lambda: replay.frames_pushed >= 10)
    assert len(client.frames(start)) >= 5
    _click(client, "Pause replay")
    _wait(lambda: not replay.playing)
    assert replay.step < recording.num_steps - 1, "paused before the end (the run lasts 2 s at 1x)"
    _wait(lambda: any(e.get("label") == "Play replay" for e in client.gui().values()))
    slider = client.find_gui("Replay step")
    # The slider counts steps done, 0 (the start) to N, like the HUD's "step k/N"; recording step k-1 is shown.
    assert (slider["min"], slider["max"]) == (0, recording.num_steps)
    folders = [e for e in client.gui().values() if e["type"] == "GuiFolderMessage"]
    timeline = next(e for e in folders if e["label"] == "Replay")
    assert timeline["visible"] and timeline["order"] < min(  # at the top of the panel, above the editor's folders
        e["order"] for e in folders if e["uuid"] != timeline["uuid"])
    for step in (3, recording.num_steps - 1, 0):
        before = client.count()
        client.send("GuiUpdateMessage", uuid=slider["uuid"], updates={"value": step + 1})
        _wait(lambda step=step: replay.shown_step == step)
        client.wait_frame(before)
        # What is drawn is the recorded state of that step (no re-simulation).
        level = recorded_level(recording, step)
        assert np.array_equal(replay._scene.position, np.asarray(level.sim.bodies.position))
        assert np.array_equal(replay._scene.angle, np.asarray(level.sim.bodies.angle))
        assert np.array_equal(replay._scene.position[recording.bodies], recording.position[step])
    # ←/→ step the replay one step (Shift: 10), and the slider follows; at the start it stays at 0.
    keys = KeysSocket(app.port, nonce)
    try:
        keys.down("ArrowRight")
        _wait(lambda: replay.shown_step == 1)
        _wait(lambda: client.find_gui("Replay step")["value"] == 2)
        keys.up("ArrowRight")
        keys.down("ArrowLeft", shift=True)
        _wait(lambda: replay.shown_step == -1)
        _wait(lambda: client.find_gui("Replay step")["value"] == 0)
        keys.up("ArrowLeft", shift=True)
    finally:
        keys.close()
    assert session.mode == "replay" and not replay.playing
    first = _frame(client.frames()[-1])
    before = client.count()
    client.send("GuiUpdateMessage", uuid=slider["uuid"], updates={"value": recording.num_steps})
    _wait(lambda: replay.shown_step == recording.num_steps - 1)
    last = _frame(client.wait_frame(before))
    assert np.abs(first - last).mean() > 0.5, "the car moved between the first and the last step"
    before = client.count()
    client.send_camera(300, 500)  # a resized tab gets a frame of its new size, also while paused
    assert _frame(client.wait_frame(before)).shape == (500, 300, 3)
    client.send("GuiUpdateMessage", uuid=client.find_gui("Speed")["uuid"], updates={"value": "4x"})
    _wait(lambda: replay.speed == 4.0)
    _click(client, "Close replay")
    _wait(lambda: session.mode == "edit" and session.replay is None)


def _mcap_of_another_profile() -> bytes:
    from mcap.writer import Writer

    out = io.BytesIO()
    writer = Writer(out)
    writer.start(profile="ros2", library="test")
    writer.finish()
    return out.getvalue()


def test_bad_uploads_get_a_clear_message_and_leave_the_tab_as_it_was(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce)
    try:
        _play_keys(app, session, keys, "ArrowRight", 5)
    finally:
        keys.close()
    good = _recorder(app).last_finished(session).path.read_bytes()
    cases = [("notes.mcap", b"hello, not a recording", "not an MCAP file"),
             ("other.mcap", _mcap_of_another_profile(), "not a kinetix recording"),
             ("cut.mcap", good[: len(good) // 2], "truncated")]
    for name, data, words in cases:
        _upload(client, "Replay a file (.mcap)", name, data)
        _wait(lambda name=name, words=words: f"Cannot replay {name}" in _status(client) and words in _status(client))
        assert session.mode == "edit" and session.replay is None
    _upload(client, "Replay a file (.mcap)", "good.mcap", good)
    _wait(lambda: session.mode == "replay")
    _wait(lambda: "Replaying good.mcap" in _status(client))
    session.stop()


def test_a_disconnect_mid_play_leaves_a_finished_file(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce)
    session.toggle_play()
    keys.down("ArrowRight")
    _wait(lambda: session._steps >= 15)
    live = _recorder(app)._live[session]
    client.close()  # the tab goes away mid-play
    keys.close()
    finished = live.done.result(timeout=30)
    assert finished.result == "stopped" and finished.path is not None
    recording = read_recording(finished.path)
    assert recording.num_steps >= 15 and verify(recording).ok
    leftovers = list((app.store.recordings_dir / "recent").glob(".*.part"))
    assert not leftovers, leftovers


# ---------------------------------------------------------------------- the gallery's best runs


def _gallery_level(app, name: str) -> str:
    level_id, _ = app.store.create_level(name, to_document(build(falling_win_spec())))
    return level_id


def _api(app, path: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(app.url + path.lstrip("/"), timeout=10) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def _solve_by_link(app, make_client, level_id: str):
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce, query=f"?level={level_id}&mode=play")
    try:
        _wait(lambda: session.mode == "ready")  # opened for play: it starts with the player's first key
        keys.down("Space")
        _wait(lambda: session.mode == "ended")
        assert session._result == "solved"
        _wait(lambda: app.store.stats(level_id)["human_plays"] >= 1)
    finally:
        keys.close()
    return client, session


def test_the_gallery_keeps_only_the_best_human_solve_and_serves_it(app, make_client):
    level_id = _gallery_level(app, "falling win")
    status, body = _api(app, f"/api/levels/{level_id}/best-run.mcap")
    assert status == 404 and "no recorded best run" in json.loads(body)["detail"]
    assert app.store.stats(level_id)["has_best_run"] is False
    assert _api(app, "/api/levels/nosuchlevel/best-run.mcap")[0] == 404

    # A slower recorded solve already kept: the browser's faster solve replaces it and its file goes.
    runs_dir = app.store.recordings_dir
    slow = runs_dir / f"best-{level_id}-slow.mcap"
    slow.write_bytes(b"a slower run")
    app.store.record_play(level_id, "human", solved=True, steps=500, seconds=500 / 30,
                          recording_path=slow.name)
    _solve_by_link(app, make_client, level_id)
    _wait(lambda: not slow.exists())
    status, body = _api(app, f"/api/levels/{level_id}/best-run.mcap")
    assert status == 200
    best = read_recording(body)
    assert best.metadata["player"] == "human" and best.metadata["level_id"] == level_id and best.solved
    assert verify(best).ok
    stats = app.store.stats(level_id)
    assert stats["has_best_run"] is True and best.num_steps == stats["best_human_steps"]
    kept = sorted(p.name for p in runs_dir.glob(f"best-{level_id}-*.mcap"))
    assert len(kept) == 1

    # An equal solve (same steps) does not replace it: still one file, the same one.
    _solve_by_link(app, make_client, level_id)
    _wait(lambda: app.store.stats(level_id)["human_plays"] == 3)
    time.sleep(0.5)
    assert sorted(p.name for p in runs_dir.glob(f"best-{level_id}-*.mcap")) == kept
    listing = json.loads(_api(app, "/api/levels?limit=100")[1])
    assert next(i for i in listing["items"] if i["id"] == level_id)["stats"]["has_best_run"] is True


def test_a_replay_link_replays_the_levels_best_run(app, make_client):
    level_id = _gallery_level(app, "replay me")
    _solve_by_link(app, make_client, level_id)
    _wait(lambda: app.store.stats(level_id)["has_best_run"])
    client = make_client(app)
    session, nonce = _session(app, client)
    start = client.count()
    keys = KeysSocket(app.port, nonce, query=f"?level={level_id}&mode=replay")
    try:
        _wait(lambda: session.mode == "replay" and session.replay is not None)
        replay = session.replay
        _wait(lambda: replay.frames_pushed >= 3)
        assert len(client.frames(start)) >= 2
        assert "best run" in _status(client)
    finally:
        keys.close()
    session.stop()

    other = _gallery_level(app, "never solved")
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce, query=f"?level={other}&mode=replay")
    try:
        client.wait_for(lambda m: "No best run yet" in json.dumps(m, default=str), 30.0)
        assert session.mode == "edit"
    finally:
        keys.close()


def test_start_up_removes_partial_leftovers(tmp_path):
    import fcntl
    import os

    from server.recordings.recorder import PlayRecorder

    recorder = PlayRecorder(tmp_path)
    orphan = tmp_path / "recent" / ".play-x.mcap.abc.part"  # its writer is gone: nobody holds its lock
    owned = tmp_path / "recent" / ".play-y.mcap.def.part"  # a live writer's (another server on the same data)
    top = tmp_path / ".play-z.mcap.ghi.part"
    stale = tmp_path / "recent" / "play-old.mcap"
    for path in (orphan, owned, top, stale):
        path.write_bytes(b"x")
        os.utime(path, (time.time() - 60, time.time() - 60))  # a minute old: past the creation-to-lock window
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    holder = os.open(owned, os.O_RDONLY)
    fcntl.flock(holder, fcntl.LOCK_EX)
    try:
        removed = recorder.clean_up()
    finally:
        os.close(holder)
    assert set(removed) == {orphan, top, stale}
    assert owned.exists(), "a live recorder's partial file is kept"
    assert recorder.clean_up() == [owned]  # its writer has gone now
    recorder.close()


def _fill_recent(recorder, sizes: list[int]) -> list:
    """Recordings of these sizes in recent/, one second apart in age, oldest first."""
    import os

    paths = []
    for i, size in enumerate(sizes):
        path = recorder.recent / f"play-{i:03d}.mcap"
        path.write_bytes(b"x" * size)
        age = time.time() - 100 + i
        os.utime(path, (age, age))
        paths.append(path)
    return paths


def test_recent_recordings_are_capped_by_count_oldest_first(tmp_path):
    from server.recordings.recorder import RECENT_MAX_BYTES, RECENT_MAX_FILES, PlayRecorder

    assert RECENT_MAX_FILES >= 8 and RECENT_MAX_BYTES >= 1 << 20  # room for each tab of a default server
    recorder = PlayRecorder(tmp_path, max_files=5)
    paths = _fill_recent(recorder, [10] * 8)
    assert sorted(recorder.clean_up()) == paths[:3]
    assert sorted(recorder.recent.iterdir()) == paths[3:]
    recorder.close()


def test_recent_recordings_are_capped_by_size_oldest_first(tmp_path):
    from server.recordings.recorder import PlayRecorder

    recorder = PlayRecorder(tmp_path, max_bytes=1000)
    paths = _fill_recent(recorder, [400, 300, 300, 300, 200])  # 1500 bytes: the two oldest must go
    assert sorted(recorder.clean_up()) == paths[:2]
    assert sum(p.stat().st_size for p in recorder.recent.iterdir()) <= 1000
    recorder.close()


def test_the_cap_applies_as_plays_finish_and_spares_open_tabs(app, make_client, tmp_path, monkeypatch):
    client = make_client(app)
    session, _ = _session(app, client)
    recorder = _recorder(app)
    monkeypatch.setattr(recorder, "max_files", 3)
    monkeypatch.setattr(recorder, "recent", tmp_path)  # only this test's files
    old = _fill_recent(recorder, [10] * 3)
    session.toggle_play()
    _wait(lambda: session._steps >= 3)
    session.stop()
    finished = recorder.last_finished(session)
    assert finished is not None and finished.path is not None and finished.path.exists()  # the tab's last play
    _wait(lambda: not old[0].exists())  # swept right after the file is finished
    assert sorted(tmp_path.iterdir()) == sorted(old[1:] + [finished.path])  # the oldest went to make room


def test_a_recording_that_cannot_be_written_does_not_stop_the_play(app, make_client, tmp_path, monkeypatch):
    client = make_client(app)
    session, nonce = _session(app, client)
    monkeypatch.setattr(_recorder(app), "recent", tmp_path / "gone")  # e.g. the folder was deleted under us
    session.toggle_play()
    _wait(lambda: session._steps >= 10)
    session.stop()
    finished = _recorder(app).last_finished(session)
    assert finished is not None and finished.path is None and finished.steps >= 10
    assert not (tmp_path / "gone").exists()
    _click(client, "Download recording")
    _wait(lambda: "No download:" in _status(client) and "could not be recorded" in _status(client))


def test_a_reload_gets_the_tabs_last_play_back_from_the_database(app, make_client):
    import secrets

    tab, table = secrets.token_hex(16), _recorder(app).table  # the key keys.js keeps in the tab's sessionStorage
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce, tab=tab)
    try:
        assert session.tab_key == tab
        session.toggle_play()
        _wait(lambda: session._steps >= 5)
        assert table.get(tab) is None, "a play in progress is not in the table"
        session.stop()
        played = _recorder(app).last_finished(session).path.read_bytes()
    finally:
        keys.close()
    _wait(lambda: table.get(tab) is not None)
    assert table.get(tab).data == played, "stored once complete, as written"
    session.play(wait=True)  # as ?mode=play does: a play waiting for its first key...
    client.close()  # ...when the tab reloads: this session goes, a new one comes with the tab's key
    _wait(lambda: session.closed)
    assert _recorder(app).last_finished(session).path.read_bytes() == played, "a play that never stepped is dropped"
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce, tab=tab)
    try:
        finished = _recorder(app).last_finished(session)
        assert finished.path.read_bytes() == played and finished.result == "stopped"
        _click(client, "Replay last play")
        _wait(lambda: session.mode == "replay" and session.replay.frames_pushed >= 1)
    finally:
        keys.close()
    session.stop()
    other = make_client(app)
    session, nonce = _session(app, other)
    KeysSocket(app.port, nonce, tab="../" + tab).close()  # not a tab key: ignored
    assert session.tab_key is None and _recorder(app).last_finished(session) is None


def test_server_start_removes_partial_recordings_and_orphaned_best_runs(tmp_path):
    import os

    recordings = tmp_path / "recordings"
    (recordings / "recent").mkdir(parents=True)
    old = time.time() - 7200
    partials = [recordings / "recent" / ".play-a.mcap.x1.part", recordings / ".best-lvl-1.mcap.copy.part"]
    orphan = recordings / "best-nosuchlevel-abc.mcap"
    for path in [*partials, orphan]:
        path.write_bytes(b"left over by a killed server")
        os.utime(path, (old, old))
    with running_app(gallery=True, data=tmp_path, warm_sizes=()) as app:
        assert app.store.recordings_dir == recordings
        assert not any(p.exists() for p in partials)
        assert not orphan.exists()


def test_a_stuck_writer_does_not_hold_up_the_play(app, make_client, monkeypatch):
    """The play loop only queues: with the recording's writer thread blocked (a stalled disk), the play still
    steps and stops; once the writer goes on, the file is finished with every step."""
    import threading

    from kinetix.recording.writer import Recorder

    gate = threading.Event()
    original = Recorder._write_step

    def stuck_write_step(self, *args):
        gate.wait(timeout=120)
        return original(self, *args)

    monkeypatch.setattr(Recorder, "_write_step", stuck_write_step)
    client = make_client(app)
    session, _ = _session(app, client)
    session.toggle_play()
    try:
        _wait(lambda: session._steps >= 40)
        session.stop()  # returns although the file cannot be finished yet
        assert session.mode == "edit"
        live = _recorder(app)._last[session]
        assert not live.done.done(), "the recording is still being written"
    finally:
        gate.set()
    finished = live.done.result(timeout=60)
    recording = read_recording(finished.path)
    assert recording.num_steps == finished.steps >= 40
