"""Editing with the real editor at the protocol level: panel buttons, drags on the catcher, /keys shortcuts, frames."""

from __future__ import annotations

import time

import pytest
from viser_client import KeysSocket, session_nonce

from server.play.draw import View
from tests.server.conftest import running_app


@pytest.fixture(scope="module")
def app():
    with running_app(warm_sizes=()) as app:
        yield app


def _wait(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.01)


def _session(app, client):
    nonce = session_nonce(client)
    _wait(lambda: app.manager.session_by_nonce(nonce) is not None)
    return app.manager.session_by_nonce(nonce), nonce


def test_draw_a_rectangle_by_dragging_then_undo_and_redo_by_keys(app, make_client):
    client = make_client(app, 800, 600)
    session, nonce = _session(app, client)
    editor = session.editor
    bodies = len(editor.spec.bodies)
    client.send("GuiUpdateMessage", uuid=client.find_gui("Tool")["uuid"], updates={"value": "Rect"})
    _wait(lambda: editor.tool == "rectangle")
    view = View(800, 600)
    before = client.count()
    client.drag("/kinetix/catcher", [view.to_screen(1.0, 1.0), view.to_screen(1.5, 1.2), view.to_screen(2.0, 1.5)],
                owner=str(session.client.client_id))
    _wait(lambda: len(editor.spec.bodies) == bodies + 1)
    rect = editor.spec.bodies[-1]
    assert rect.shape == "polygon" and rect.position == pytest.approx((1.5, 1.25), abs=0.06)  # snapping allowed
    assert client.wait_frame(before)[:2] == b"\xff\xd8"  # the edit was pushed as a new frame

    keys = KeysSocket(app.port, nonce)
    try:
        keys.down("KeyZ", "z", ctrl=True)
        _wait(lambda: len(editor.spec.bodies) == bodies)
        keys.up("KeyZ", "z", ctrl=True)
        keys.down("KeyZ", "Z", ctrl=True, shift=True)
        _wait(lambda: len(editor.spec.bodies) == bodies + 1)
    finally:
        keys.close()


def test_click_with_the_circle_tool_adds_a_circle_where_clicked(app, make_client):
    client = make_client(app, 640, 480)
    session, _ = _session(app, client)
    editor = session.editor
    client.send("GuiUpdateMessage", uuid=client.find_gui("Tool")["uuid"], updates={"value": "Circle"})
    _wait(lambda: editor.tool == "circle")
    circles = sum(b.shape == "circle" for b in editor.spec.bodies)
    client.click(*View(640, 480).to_screen(3.0, 2.0))
    _wait(lambda: sum(b.shape == "circle" for b in editor.spec.bodies) == circles + 1)
    assert editor.spec.bodies[-1].position == pytest.approx((3.0, 2.0), abs=0.06)
