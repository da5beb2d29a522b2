"""Drafts on the server (server/drafts/store.py, server/drafts/tab.py): the store, the document, and a tab reopening its
draft with the undo history, at the protocol level (the browser tests are in tests/e2e/test_reload_in_browser.py)."""

from __future__ import annotations

import json
import os
import time

import pytest
from viser_client import KeysSocket, ViserTestClient, session_nonce

from server.drafts.store import DraftError, DraftStore, draft_document, read_draft, snapshot_json
from server.editor import Editor
from tests.server.conftest import running_app, wait_until


def _edited_editor() -> Editor:
    editor = Editor()
    editor.set_tool("circle")
    editor.click(1.0, 1.0)
    editor.click(3.0, 2.0)
    editor.set_gravity(0.0, -5.0)
    editor.undo()  # one step to redo
    return editor


def _document(editor: Editor, gallery_id=None) -> dict:
    history = editor.history
    return draft_document(snapshot_json(editor.spec, editor.size),
                          [snapshot_json(s.spec, s.size) for s in history.undo_stack],
                          [snapshot_json(s.spec, s.size) for s in history.redo_stack], gallery_id)


def test_a_draft_brings_back_the_level_and_its_undo_history(tmp_path):
    editor = _edited_editor()
    store = DraftStore(tmp_path)
    try:
        draft_id = store.new_id()
        store.save_later(draft_id, _document(editor, "abc"))
        draft = store.load(draft_id)  # waits for the queued write
    finally:
        store.close()
    assert draft.gallery_id == "abc"
    again = Editor()
    again.load_draft(draft.spec, draft.size, draft.undo, draft.redo)
    assert again.spec == editor.spec and again.size == editor.size
    assert len(again.history.undo_stack) == 2 and len(again.history.redo_stack) == 1
    assert again.redo() and again.spec.gravity == (0.0, -5.0)
    assert again.undo() and again.undo() and again.undo()
    assert len(again.spec.bodies) == len(Editor().spec.bodies)  # back to the walls only
    assert not again.undo()


def test_the_newest_queued_document_wins_and_unknown_drafts_are_none(tmp_path):
    store = DraftStore(tmp_path)
    try:
        editor = Editor()
        for gallery_id in ("one", "two", "three"):
            store.save_later("tab-0001", _document(editor, gallery_id))
        assert store.load("tab-0001").gallery_id == "three"
        assert store.load("nothing-here") is None
    finally:
        store.close()


def test_a_failed_write_leaves_the_previous_draft_whole(tmp_path, monkeypatch):
    store = DraftStore(tmp_path)
    try:
        editor = Editor()
        store.save("tab-0001", _document(editor, "first"))
        with pytest.raises(ValueError):  # NaN is not JSON: nothing is written
            store.save("tab-0001", {**_document(editor), "gallery_id": float("nan")})
        monkeypatch.setattr(os, "replace", lambda *a: (_ for _ in ()).throw(OSError(28, "No space left on device")))
        with pytest.raises(OSError):
            store.save("tab-0001", _document(editor, "second"))
        monkeypatch.undo()
        assert store.load("tab-0001").gallery_id == "first"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["tab-0001.json"]  # no temporary file left
    finally:
        store.close()


@pytest.mark.parametrize("content, message", [
    (b'{"format": "kinetix-draft", "version": 1, "level": {"si', "not valid JSON"),
    (b"\xff\xfe", "not valid JSON"),
    (b'{"levels": []}', "not a kinetix draft"),
    (b'{"format": "kinetix-draft", "version": 7}', "version 7 is not supported"),
])
def test_malformed_drafts_give_a_clear_error(tmp_path, content, message):
    store = DraftStore(tmp_path)
    try:
        (tmp_path / "tab-0001.json").write_bytes(content)
        with pytest.raises(DraftError, match=message) as error:
            store.load("tab-0001")
        assert "tab-0001" in str(error.value)
    finally:
        store.close()


def test_a_wrong_field_is_named_with_its_path():
    document = _document(_edited_editor())
    document["undo"][1]["spec"]["bodies"][4]["position"] = "left"
    with pytest.raises(DraftError, match=r"undo\[1\]\.spec\.bodies\[4\]\.position: expected two numbers"):
        read_draft(document)
    document = _document(_edited_editor())
    document["level"]["spec"]["joints"] = [{"path": "joints[0]", "a": 0, "b": 1, "colour": "red"}]
    with pytest.raises(DraftError, match=r"level\.spec\.joints\[0\]: unknown field 'colour'"):
        read_draft(document)
    document = _document(_edited_editor())
    document["level"]["size"]["polygons"] = -1
    with pytest.raises(DraftError, match=r"level\.size: .*non-negative"):
        read_draft(document)


def test_ids_that_could_name_other_files_are_refused(tmp_path):
    store = DraftStore(tmp_path)
    try:
        for bad in ("../gallery", "a/b/c/d/e", "short", "x" * 65, ""):
            with pytest.raises(DraftError, match="not a draft id"):
                store.load(bad)
    finally:
        store.close()


def test_old_drafts_and_drafts_over_the_cap_are_removed(tmp_path):
    store = DraftStore(tmp_path, max_age_s=30 * 86400, cap=2)
    try:
        now = time.time()
        for i, age_days in enumerate([40, 3, 2, 1]):
            path = tmp_path / f"tab-000{i}.json"
            path.write_text("{}")
            os.utime(path, (now - age_days * 86400, now - age_days * 86400))
        crash = tmp_path / ".tab-0009.json.ab12.tmp"
        crash.write_text("{")
        os.utime(crash, (now - 3600, now - 3600))
        removed = {p.name for p in store.clean_up(now)}
        assert removed == {"tab-0000.json", "tab-0001.json", crash.name}  # 40 days old; the oldest over 2; the crash
        assert sorted(p.name for p in tmp_path.iterdir()) == ["tab-0002.json", "tab-0003.json"]
    finally:
        store.close()


# ---------------------------------------------------------------- a tab and its draft, at the protocol level

@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with running_app(warm_sizes=(), data=tmp_path_factory.mktemp("drafts"), agents=False) as app:
        yield app


def _open_tab(app, query: str = ""):
    client = ViserTestClient(app.port)
    nonce = session_nonce(client)
    wait_until(lambda: app.manager.session_by_nonce(nonce) is not None)
    keys = KeysSocket(app.port, nonce, query=query)
    return client, keys, app.manager.session_by_nonce(nonce)


def _address(client) -> str:
    import re

    try:
        content = client.html_containing("kinetix-address")
    except KeyError:  # not in the page yet
        return ""
    return re.search(r'data-query="([^"]*)"', content).group(1)


def test_a_tab_reopens_its_draft_with_undo_after_the_tab_goes(app):
    client, keys, session = _open_tab(app)
    try:
        wait_until(lambda: _address(client).startswith("?draft="))
        draft_id = _address(client).split("=", 1)[1]
        session.editor.set_tool("circle")
        session.edit_call("click", 1.0, 1.0)
        session.edit_call("click", 3.0, 1.0)
        spec = session.editor.spec
    finally:
        keys.close()
        client.close()
    assert app.drafts.flush()
    client, keys, session = _open_tab(app, f"?draft={draft_id}")
    try:
        wait_until(lambda: session.editor.spec == spec)
        wait_until(lambda: _address(client) == f"?draft={draft_id}")
        with session.lock:
            assert session.editor.undo()
        assert len(session.editor.spec.bodies) == len(spec.bodies) - 1
    finally:
        keys.close()
        client.close()


def test_a_malformed_draft_is_reported_and_the_tab_goes_on_with_a_new_one(app):
    (app.drafts.directory / "broken-draft1.json").write_text('{"format": "kinetix-draft", "version": 1, "lev')
    client, keys, session = _open_tab(app, "?draft=broken-draft1")
    try:
        note = client.wait_for(lambda m: m["type"] == "NotificationShowMessage", timeout=10)
        assert "Could not reopen the draft" in json.dumps(note)
        assert "not valid JSON" in json.dumps(note)
        wait_until(lambda: _address(client).startswith("?draft=") and "broken-draft1" not in _address(client))
        session.edit_call("click", 2.0, 2.0)  # the tab still edits
        assert (app.drafts.directory / "broken-draft1.json").exists()  # left for a look, removed when old
    finally:
        keys.close()
        client.close()


def test_a_second_key_socket_of_the_same_tab_does_not_reopen_the_level(app):
    # keys.js opens /keys again after a network blip, with the same nonce and address: the play must go on.
    client, keys, session = _open_tab(app)
    again = None
    try:
        wait_until(lambda: _address(client).startswith("?draft="))
        session.edit_call("click", 2.0, 2.0)
        wait_until(lambda: app.drafts.flush() and (app.drafts.directory / f"{_address(client)[7:]}.json").exists())
        spec = session.editor.spec
        session.play()
        keys.close()
        again = KeysSocket(app.port, session.nonce, query=_address(client))
        time.sleep(0.5)
        assert session.mode != "edit" and session.editor.spec is spec
    finally:
        if again is not None:
            again.close()
        client.close()


def test_discard_this_draft_removes_the_file_and_starts_a_new_level(app):
    client, keys, session = _open_tab(app)
    try:
        wait_until(lambda: _address(client).startswith("?draft="))
        old = _address(client)[len("?draft="):]
        walls = len(session.editor.spec.bodies)
        session.editor.set_tool("circle")
        session.edit_call("click", 2.0, 2.0)
        wait_until(lambda: app.drafts.flush() and (app.drafts.directory / f"{old}.json").exists())
        client.click_button("Discard this draft")
        wait_until(lambda: _address(client).startswith("?draft=") and old not in _address(client))
        assert not (app.drafts.directory / f"{old}.json").exists()
        assert len(session.editor.spec.bodies) == walls and not session.editor.can_undo
    finally:
        keys.close()
        client.close()
