"""The server at the protocol level: a headless viser client and the /keys socket, one server for the module."""

from __future__ import annotations

import io
import json
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from fake_editor import FakeEditor, falling_win_spec
from PIL import Image
from viser_client import KeysSocket, is_frame, session_nonce

from server.play.session import Controller, PlayListener
from tests.server.conftest import running_app

EDITORS: list[FakeEditor] = []


def _editor(level=None, size="m"):
    editor = FakeEditor(falling_win_spec(), size=size)
    EDITORS.append(editor)
    return editor


@pytest.fixture(scope="module")
def app():
    with running_app(warm_sizes=("m",), max_sessions=3, editor_factory=_editor) as app:
        yield app


def _image(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"))


def _session(app, client):
    nonce = session_nonce(client)
    _wait(lambda: app.manager.session_by_nonce(nonce) is not None)  # registered right after its GUI is built
    return app.manager.session_by_nonce(nonce), nonce


def _wait(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not reached")
        time.sleep(0.01)


def _has_label(client, label: str) -> bool:
    try:
        client.find_gui(label)
        return True
    except KeyError:
        return False


def test_page_has_the_key_script_and_no_internal_port(app):
    page = urllib.request.urlopen(app.url, timeout=10).read().decode()
    # Our scripts open <head>, so frames.js wraps window.Worker before viser's own code creates its worker; relative
    # paths, so the page also works under a reverse proxy's path.
    ours = '<script src="static/frames.js"></script><script src="static/keys.js"></script>'
    after_ours = page.index(ours) + len(ours)
    assert page.index("<head>") < page.index(ours) < page.index("<script", after_ours)
    assert "BackgroundImageMessage" in urllib.request.urlopen(app.url + "static/frames.js", timeout=10).read().decode()
    assert "viserPort" not in page and "__KINETIX__" not in page  # the page names no internal port
    script = urllib.request.urlopen(app.url + "static/keys.js", timeout=10).read().decode()
    assert "kinetix-session" in script and "/keys" in script
    with pytest.raises(urllib.error.HTTPError) as error:
        urllib.request.urlopen(app.url + "gallery", timeout=10)
    assert error.value.code == 404


def test_frames_are_rendered_at_the_canvas_size(app, make_client):
    client = make_client(app, 640, 480)
    frame = _image(client.wait_frame())
    assert frame.shape == (480, 640, 3)
    start = client.count()
    client.send_camera(300, 500)
    # a frame drawn before the resize reached the session may still arrive first (under load): the first frame of
    # another size must be the new canvas's
    resized = client.wait_for(lambda m: is_frame(m) and _image(m["rgb_data"]).shape != (480, 640, 3), 10.0, start)
    assert _image(resized["rgb_data"]).shape == (500, 300, 3)
    # Letterboxed: the square world fills the width of a tall canvas; bands above and below keep its aspect.
    tall = _image(client.frames()[-1])
    assert tall[5, 150].tolist() != tall[250, 150].tolist()


def test_click_and_drag_reach_the_editor_in_world_coordinates(app, make_client):
    client = make_client(app, 800, 600)
    session, _ = _session(app, client)
    client.click(0.5, 0.5)
    _wait(lambda: session.editor.clicks)
    assert session.editor.clicks[0] == pytest.approx((2.5, 2.5), abs=1e-6)
    # Top-left corner of the world: x = 0 at pixel 100 of 800 (letterbox), y = 5 at the top.
    client.click(100 / 800, 0.0)
    _wait(lambda: len(session.editor.clicks) == 2)
    assert session.editor.clicks[1] == pytest.approx((0.0, 5.0), abs=1e-6)
    client.drag("/kinetix/catcher", [(0.5, 0.5), (0.6, 0.5), (0.7, 0.4)], owner=str(session.client.client_id))
    _wait(lambda: any(c[0] == "pointer_up" for c in session.editor.calls))
    names = [c[0] for c in session.editor.calls]
    assert names[0] == "pointer_down" and names[-1] == "pointer_up"
    assert session.editor.calls[-1][1] == pytest.approx((2.5 + 0.2 * 800 / 120, 2.5 + 0.1 * 600 / 120), abs=1e-6)
    client.rect_select(0.25, 0.25, 0.5, 0.5)
    _wait(lambda: any(c[0] == "box_select" for c in session.editor.calls))
    box = [c for c in session.editor.calls if c[0] == "box_select"][0][1]
    assert box == pytest.approx((2.5 - 0.25 * 800 / 120, 2.5, 2.5, 2.5 + 0.25 * 600 / 120), abs=1e-6)


def test_keys_socket_rejects_unknown_nonces(app):
    import websockets.sync.client

    ws = websockets.sync.client.connect(f"ws://127.0.0.1:{app.port}/keys", open_timeout=10)
    ws.send(json.dumps({"type": "down", "code": "Space"}))
    with pytest.raises(websockets.exceptions.ConnectionClosed) as closed:
        ws.recv(timeout=10)
    assert closed.value.rcvd.code == 1008


def test_editor_keys_go_to_the_editor_in_edit_mode(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce)
    try:
        assert keys.reply == {"type": "ready"}
        keys.down("KeyZ", "z", ctrl=True)
        _wait(lambda: session.editor.keys)
        assert session.editor.keys[0] == ("z", {"ctrl": True, "shift": False, "alt": False, "meta": False})
    finally:
        keys.close()


def test_space_plays_arrows_drive_and_stopping_restores(app, make_client):
    client = make_client(app)
    session, nonce = _session(app, client)
    edit_frame = client.wait_frame()
    keys = KeysSocket(app.port, nonce)
    try:
        start = client.count()
        keys.down("Space", " ")
        _wait(lambda: len(client.frames(start)) >= 5)
        assert session.mode in ("play", "ended")
        frames = client.frames(start)
        assert len(set(frames)) > 1  # the ball falls: frames change while playing
        keys.down("ArrowRight")
        _wait(lambda: "ArrowRight" in session.held or session.mode == "ended")
        keys.up("ArrowRight")
        _wait(lambda: "ArrowRight" not in session.held)
        keys.down("Space", " ")
        _wait(lambda: session.mode == "edit")
        _wait(lambda: client.frames()[-1] == edit_frame)  # the edited level is shown again, unchanged
    finally:
        keys.close()


def test_win_shows_the_result_with_play_again_and_edit(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    client.click_button("Play (Space)")
    _wait(lambda: session.mode == "ended", timeout=20)
    assert session._result == "solved" and session._steps > 0
    _wait(lambda: client.find_gui("Play again").get("visible") is True)
    assert client.find_gui("Edit").get("visible") is True
    _wait(lambda: client.find_gui("Stop (Space)").get("visible") is False)  # nothing left to stop
    client.click_button("Play again")
    _wait(lambda: session.mode == "ready")  # it waits for the player: nothing moves until Space or a key
    assert session._steps == 0
    _wait(lambda: _has_label(client, "Start (Space)"))
    client.click_button("Start (Space)")
    _wait(lambda: session.mode in ("play", "ended") and session._steps > 0)
    _wait(lambda: _has_label(client, "Stop (Space)"))
    client.click_button("Stop (Space)")
    _wait(lambda: session.mode == "edit")


def test_a_waiting_play_shows_its_start_and_the_first_control_key_starts_and_acts(app, make_client):
    from server.play.session import START_HINT

    class FirstAction(PlayListener):
        actions: list = []

        def play_stepped(self, session, action, state, result) -> None:
            self.actions.append(np.array(action))

    listener = FirstAction()
    client = make_client(app)
    session, nonce = _session(app, client)
    keys = KeysSocket(app.port, nonce)
    app.manager.add_listener(listener)
    try:
        start = client.count()
        session.play(wait=True)  # as the gallery's Play link and Play again open a play
        assert session.mode == "ready" and session.hud().startswith("READY")
        ready_frame = _image(client.wait_frame(start))  # its start is drawn, with the hint on the canvas
        with session.lock:
            session.mode = "play"  # the same frame without the hint, for comparison
            playing = session.render()
            session.mode = "ready"
        assert START_HINT and np.abs(ready_frame.astype(int) - playing.astype(int)).sum() > 50_000
        time.sleep(0.5)
        assert session._steps == 0 and session.mode == "ready", "nothing moves before the player's first key"
        keys.down("ArrowRight")
        _wait(lambda: session._steps > 0)
        assert session.mode in ("play", "ended")
        assert listener.actions[0][0] != 0, "the key that started the play drove its first step"
        keys.up("ArrowRight")
    finally:
        app.manager.listeners.remove(listener)
        session.stop()
        keys.close()


def test_pause_and_single_step(app, make_client):
    client = make_client(app)
    session, _ = _session(app, client)
    client.click_button("Play (Space)")
    _wait(lambda: session.mode == "play")
    _wait(lambda: client.find_gui("Pause").get("disabled") is False)
    client.click_button("Pause")
    _wait(lambda: session.mode == "paused")
    steps = session._steps
    time.sleep(0.2)
    assert session._steps == steps
    client.click_button("Step")
    _wait(lambda: session._steps == steps + 1)
    session.stop()


def test_sessions_past_the_cap_get_a_clear_message(app, make_client):
    # Earlier tests' tabs are closed by their fixture, but the server may not have dropped their sessions yet;
    # counting them would leave a free slot for the extra tab once they go.
    _wait(lambda: not app.manager.sessions)
    clients = [make_client(app) for _ in range(app.manager.max_sessions)]
    for client in clients:
        session_nonce(client)
    extra = make_client(app)
    message = extra.wait_for(lambda m: m["type"] == "GuiMarkdownMessage")
    assert "server is full" in message["props"]["_markdown"].lower()
    _wait(lambda: len(app.manager.sessions) == app.manager.max_sessions)
    assert len(app.manager.rejected) == 1
    # The tab past the cap also sees it on the canvas, and gets no session (no nonce for /keys).
    assert extra.wait_frame()[:2] == b"\xff\xd8"
    assert not extra.matching(lambda m: m["type"] == "GuiHtmlMessage" and "kinetix-session" in m["props"]["content"])
    clients[0].close()
    _wait(lambda: len(app.manager.sessions) == app.manager.max_sessions - 1)


class _Log(PlayListener):
    def __init__(self):
        self.events = []

    def play_started(self, session, level_file, params):
        self.events.append(("started", session.player))

    def play_stepped(self, session, action, state, result):
        self.events.append(("stepped", tuple(int(a) for a in action)))

    def frame_pushed(self, session, jpeg, frame):
        self.events.append(("frame", jpeg[:2], frame.shape))

    def play_ended(self, session, result, steps, seconds):
        self.events.append(("ended", result, steps))


class _Always(Controller):
    player = "agent:test"

    def __init__(self, action):
        self.action, self.calls = action, 0

    def act(self, state, params):
        self.calls += 1
        return self.action

    def hud(self):
        return "motor0 +1"


def test_listeners_see_each_play_and_a_controller_drives_it(app, make_client):
    log = _Log()
    app.manager.add_listener(log)
    try:
        client = make_client(app)
        session, nonce = _session(app, client)
        keys = KeysSocket(app.port, nonce)
        try:
            controller = _Always(np.array([2, 0, 0, 0, 0, 0], np.int32))
            session.play(controller=controller)
            keys.down("ArrowLeft")  # ignored while a controller plays: every step uses its action
            _wait(lambda: session.mode == "ended", timeout=20)
            assert session.player == "agent:test" and "agent:test" in session.hud() and "motor0 +1" in session.hud()
            keys.up("ArrowLeft")
        finally:
            keys.close()
        events = [e for e in log.events if e[0] != "frame"]  # the result banner's frame follows the end
        assert events[0] == ("started", "agent:test") and events[-1][0] == "ended"
        steps = [e for e in events if e[0] == "stepped"]
        assert len(steps) == controller.calls == events[-1][2] and all(e[1] == (2, 0, 0, 0, 0, 0) for e in steps)
        assert events[-1][1] == "solved"
        frames = [e for e in log.events if e[0] == "frame"]
        assert frames and all(e[1] == b"\xff\xd8" and e[2][2] == 3 for e in frames)
        # A human play stopped early ends as "stopped", and the controller is gone.
        log.events.clear()
        session.play()
        _wait(lambda: any(e[0] == "stepped" for e in log.events))
        session.stop()
        assert session.controller is None and session.player == "human"
        events = [e for e in log.events if e[0] != "frame"]
        assert events[0] == ("started", "human") and events[-1][:2] == ("ended", "stopped")
    finally:
        app.manager.listeners.remove(log)


def test_a_failing_controller_stops_its_play_with_a_message(app, make_client):
    class Broken(Controller):
        def act(self, state, params):
            raise RuntimeError("boom")

    client = make_client(app)
    session, _ = _session(app, client)
    session.play(controller=Broken())
    _wait(lambda: session.mode == "edit")
    assert "agent failed" in session._message and session.controller is None
