"""Shared state of several server processes on one database (docs/deploy.md): drafts in a table, rate limits
counted together, and the client address taken from trusted proxies only. Runs on SQLite and PostgreSQL (two
Store objects on one database stand for two processes)."""

from __future__ import annotations

import pytest

from server.drafts.store import DraftError, draft_document, read_draft
from server.drafts.table import TableDraftStore
from server.gallery.limits import RateLimited, SharedRateLimits
from server.web.proxies import TrustedProxies


def _document(name: str) -> dict:
    """A draft whose level is named `name`, with one undo step (a level named "old")."""
    import dataclasses

    from server.drafts.store import snapshot_json
    from server.editor import Editor

    editor = Editor()
    old = dataclasses.replace(editor.spec, name="old")
    return draft_document(snapshot_json(dataclasses.replace(editor.spec, name=name), editor.size),
                          [snapshot_json(old, editor.size)], [], None)


def test_a_draft_written_by_one_process_is_read_by_another_with_its_undo(two):
    a, b = TableDraftStore(two[0]), TableDraftStore(two[1])
    try:
        draft_id = a.new_id()
        a.save_later(draft_id, _document("first"))
        a.save_later(draft_id, _document("second"))  # the newest queued document wins
        assert a.flush(draft_id)
        draft = b.load(draft_id)
        assert draft.spec.name == "second" and [spec.name for spec, _ in draft.undo] == ["old"]
        assert read_draft(_document("second")).spec == draft.spec
        b.save(draft_id, _document("third"))  # B edits it: an update of the same row
        assert a.load(draft_id).spec.name == "third"
        assert b.load("missingmissing") is None
        with pytest.raises(DraftError, match="not a draft id"):
            b.load("../etc")
        b.discard(draft_id)
        assert a.load(draft_id) is None
    finally:
        a.close()
        b.close()


def test_the_table_keeps_the_newest_drafts_under_its_cap_and_age(two):
    drafts = TableDraftStore(two[0], cap=2, max_age_s=3600)
    try:
        ids = [drafts.new_id() for _ in range(3)]
        for draft_id in ids:
            drafts.save(draft_id, _document(draft_id))
        assert drafts.clean_up() == [ids[0]], "beyond the cap the oldest goes"
        assert sorted(drafts.clean_up(now=__import__("time").time() + 7200)) == sorted(ids[1:]), "too old"
        assert drafts.load(ids[2]) is None
    finally:
        drafts.close()


def test_rate_limits_count_across_processes(two):
    a = SharedRateLimits(two[0], writes_per_minute=4, identities_per_hour=1)
    b = SharedRateLimits(two[1], writes_per_minute=4, identities_per_hour=1)
    for limits in (a, b, a, b):
        limits.take("write", "203.0.113.9")
    with pytest.raises(RateLimited) as refused:
        b.take("write", "203.0.113.9")
    assert refused.value.retry_after == 15, "one write per 15 s comes back"
    a.take("write", "198.51.100.1")  # another client has its own bucket
    a.take("identity", "203.0.113.9")
    with pytest.raises(RateLimited, match="too many new identities"):
        b.take("identity", "203.0.113.9")
    off = SharedRateLimits(two[0], writes_per_minute=0)
    for _ in range(10):
        off.take("write", "203.0.113.9")  # 0 turns it off


def _scope(peer: str, headers: dict[str, str], kind: str = "http") -> dict:
    return {"type": kind, "client": (peer, 5000), "scheme": "http",
            "headers": [(k.encode(), v.encode()) for k, v in headers.items()]}


def test_forwarded_headers_count_only_from_trusted_proxies():
    trusted = TrustedProxies.parse("127.0.0.1,10.0.0.0/8")
    sent = {"host": "127.0.0.1:9000", "x-forwarded-for": "1.2.3.4, 203.0.113.7, 10.1.2.3",
            "x-forwarded-host": "kinetix.example:8443", "x-forwarded-proto": "https"}
    scope = trusted.apply(_scope("127.0.0.1", sent))
    # 1.2.3.4 is whatever the client wrote; 10.1.2.3 is a trusted hop; 203.0.113.7 is who reached our proxies.
    assert scope["client"][0] == "203.0.113.7" and scope["scheme"] == "https"
    assert dict(scope["headers"])[b"host"] == b"kinetix.example:8443"
    assert trusted.apply(_scope("127.0.0.1", sent, "websocket"))["scheme"] == "wss"
    untouched = _scope("192.0.2.5", sent)  # not a trusted proxy: the headers are anyone's words
    assert trusted.apply(untouched) is untouched
    assert TrustedProxies.parse("").apply(_scope("127.0.0.1", sent))["client"][0] == "127.0.0.1"
    assert TrustedProxies.parse("*").apply(_scope("192.0.2.5", sent))["client"][0] == "1.2.3.4", "all trusted"
    with pytest.raises(ValueError, match="--trusted-proxies: 'proxy.lan' is not an IP address"):
        TrustedProxies.parse("proxy.lan")
