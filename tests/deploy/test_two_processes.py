"""Two `kinetix serve` processes on one PostgreSQL database behind nginx, run with docs/deploy.md's own nginx
config (issue 34): saved on A, listed on B; a draft made on A reopens on B; a best run made on A replays on B;
`kill -9` A under open tabs: they come back through nginx on B, one with its draft; votes and rate limits count
across both; a tab's last play, recorded on A, is in its Recordings folder after a reload on B.

A is a real `python -m kinetix serve` process (so it can be killed); B runs in this process, so the test can look
at B's sessions. Tabs go through nginx only. B starts after the tabs did their work on A (nginx sends a client
address to one process while it is up; B not being up yet puts the tabs on A), and A is killed after B is up.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.e2e.conftest import browser, wait_js  # noqa: F401  (the browser fixture)
from tests.gallery.conftest import pg_schema_url  # noqa: F401  (a fresh PostgreSQL schema)
from tests.server.conftest import wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
READY = "window.__kinetixKeys && window.__kinetixKeys.ready()"
WRITE_LIMIT = 30  # per minute per client, on both processes


def nginx_config_from_docs() -> str:
    """The ```nginx block of docs/deploy.md, as written there."""
    text = (ROOT / "docs" / "deploy.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```nginx\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1, "docs/deploy.md must hold exactly one nginx config"
    return blocks[0]


def _nginx() -> str:
    found = shutil.which("nginx") or ("/usr/sbin/nginx" if Path("/usr/sbin/nginx").exists() else None)
    if found is None:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but nginx is not installed (.ci/setup-nginx.sh)")
        pytest.skip("nginx is not installed (source .ci/setup-nginx.sh)")
    return found


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_nginx(nginx: str, folder: Path, port: int, a: int, b: int) -> subprocess.Popen:
    site = nginx_config_from_docs()
    site = site.replace("listen 8080;", f"listen 127.0.0.1:{port};")
    site = site.replace("127.0.0.1:8081", f"127.0.0.1:{a}").replace("127.0.0.1:8082", f"127.0.0.1:{b}")
    (folder / "kinetix.conf").write_text(site)
    for sub in ("body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (folder / "temp" / sub).mkdir(parents=True, exist_ok=True)
    temp = " ".join(f"{sub}_temp_path {folder / 'temp' / sub};" for sub in ("fastcgi", "uwsgi", "scgi")) + \
        f" client_body_temp_path {folder / 'temp' / 'body'}; proxy_temp_path {folder / 'temp' / 'proxy'};"
    user = "user root;" if os.geteuid() == 0 else ""  # workers must read this test's private folder
    (folder / "nginx.conf").write_text(
        f"{user}\nworker_processes 1;\npid {folder / 'nginx.pid'};\nerror_log {folder / 'error.log'};\n"
        f"events {{ worker_connections 256; }}\n"
        f"http {{ access_log off; {temp} include {folder / 'kinetix.conf'}; }}\n")
    checked = subprocess.run([nginx, "-t", "-p", str(folder), "-c", str(folder / "nginx.conf")],
                             capture_output=True, text=True)
    assert checked.returncode == 0, checked.stderr
    process = subprocess.Popen([nginx, "-p", str(folder), "-c", str(folder / "nginx.conf"), "-g", "daemon off;"])
    wait_until(lambda: _port_open(port), timeout=20)
    return process


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _start_a(url: str, port: int, data: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen(
        [sys.executable, "-m", "kinetix", "serve", "--port", str(port), "--data", str(data), "--db", url,
         "--trusted-proxies", "127.0.0.1", "--root-path", "/kinetix/", "--warm", "m",
         "--write-limit", str(WRITE_LIMIT)], env=env, cwd=ROOT)
    wait_until(lambda: process.poll() is not None or _answers(port, "/kinetix/api/levels"), timeout=180)
    assert process.poll() is None, "process A did not start"
    return process


def _answers(port: int, path: str) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5):
            return True
    except (OSError, urllib.error.HTTPError):
        return False


def _call(port: int, method: str, path: str, body: dict | None = None, headers: dict | None = None):
    """(status, parsed JSON body) of one request straight to a process."""
    request = urllib.request.Request(f"http://127.0.0.1:{port}{path}", method=method,
                                     data=None if body is None else json.dumps(body).encode(),
                                     headers={"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(request, timeout=30) as answer:
            return answer.status, json.loads(answer.read() or b"null")
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read() or b"null")


def _session(app, page):
    nonce = page.get_attribute("#kinetix-session", "data-nonce")
    wait_until(lambda: app.manager.session_by_nonce(nonce) is not None, timeout=30)
    return app.manager.session_by_nonce(nonce)


def test_two_processes_behind_nginx_share_everything_and_survive_a_kill(browser, pg_schema_url, tmp_path):  # noqa: F811
    from kinetix.formats import build
    from kinetix.levels import to_document
    from kinetix.recording import read_recording
    from server.agents.queue import TrainingQueue
    from server.app import App, Config
    from server.drafts.table import TableDraftStore
    from server.gallery.store import Store
    from tests.e2e.conftest import Tab
    from tests.server.fake_editor import falling_win_spec

    nginx = _nginx()
    a_port, b_port, proxy_port = _free_port(), _free_port(), _free_port()
    (tmp_path / "nginx").mkdir()
    store = Store(pg_schema_url, seed_dir=None)  # the test's own view of the shared database
    a = b = proxy = None
    context = None
    try:
        a = _start_a(pg_schema_url, a_port, tmp_path / "a")
        proxy = _start_nginx(nginx, tmp_path / "nginx", proxy_port, a_port, b_port)
        public = f"http://127.0.0.1:{proxy_port}/kinetix/"

        # Saved on A (straight to its port).
        status, made = _call(a_port, "POST", "/kinetix/api/levels",
                             {"name": "falls and wins", "level": to_document(build(falling_win_spec()))})
        assert status == 201, made
        level_id = made["id"]

        # Two tabs through nginx, both on A (B is not up yet): one draws (its draft), one plays the saved level.
        context = browser.new_context(viewport={"width": 1280, "height": 800})
        # Page loads, not 30 s: in CI (both cores busy with the other test worker) A once took over 30 s to answer
        # a play page through nginx; nginx logged nothing but B's refusals. The tab's readiness is checked after.
        context.set_default_navigation_timeout(90_000)
        drawing, player = context.new_page(), context.new_page()
        drawing.goto(public)
        wait_js(drawing, READY)
        drawing.get_by_role("button", name="Rect", exact=True).click()
        box = Tab.__new__(Tab)  # only its geometry helpers: the world-to-page mapping of the canvas
        box.page = drawing
        box.drag((1.0, 1.0), (2.0, 1.4))
        drawing.wait_for_url(re.compile(r"\?draft=[A-Za-z0-9_-]+$"), timeout=30_000)
        draft_id = drawing.url.rsplit("=", 1)[1]
        drafts = TableDraftStore(store)
        wait_until(lambda: (d := drafts.load(draft_id)) is not None and len(d.undo) >= 1, timeout=30)
        drawn = drafts.load(draft_id).spec  # written by A into the shared table

        player.goto(f"{public}?level={level_id}&mode=play")
        wait_js(player, READY)
        player.mouse.click(300, 300)
        player.keyboard.press("Space")  # the ball falls onto the goal: solved; A verifies and keeps the run
        wait_until(lambda: store.stats(level_id)["has_best_run"], timeout=120)
        wait_js(player, "localStorage.getItem('kinetix.author_token')")  # its identity, from its first play
        token = player.evaluate("localStorage.getItem('kinetix.author_token')")

        # B starts (in this process) on the same database.
        b = App(Config(port=b_port, db=pg_schema_url, data=tmp_path / "b", gallery=True, agents=False,
                       warm_sizes=("m",), warm_batches=False, warm_agent=False, trusted_proxies="127.0.0.1",
                       root_path="/kinetix/", write_limit=WRITE_LIMIT)).start()
        assert b.wait_until_warm(timeout=600)
        assert b.shared and type(b.drafts).__name__ == "TableDraftStore"
        # A's `kinetix serve` takes training runs from the shared queue: its worker slot is registered there (B runs
        # no agents here; tests/server/test_training_shared.py runs a tab's job across two servers).
        assert TrainingQueue(store).slots() == 1

        # Listed on B; the best run made on A is served by B.
        status, page = _call(b_port, "GET", "/kinetix/api/levels?q=falls")
        assert status == 200 and [item["id"] for item in page["items"]] == [level_id]
        with urllib.request.urlopen(f"http://127.0.0.1:{b_port}/kinetix/api/levels/{level_id}/best-run.mcap") as r:
            assert r.status == 200 and len(r.read()) > 100

        # Votes: ten fresh cookie-less votes, alternately to A and B, count nothing; the identity that played
        # votes once, whichever process it asks.
        for i in range(10):
            status, answer = _call((a_port, b_port)[i % 2], "POST", f"/kinetix/api/levels/{level_id}/vote",
                                   {"value": 1})
            assert status == 403, answer
        for port in (a_port, b_port, a_port):
            status, answer = _call(port, "POST", f"/kinetix/api/levels/{level_id}/vote", {"value": 1},
                                   {"Authorization": f"Bearer {token}"})
            assert status == 200 and answer["up"] == 1, answer
        # Rate limits: one client (as nginx forwards it) gets WRITE_LIMIT writes a minute across both processes
        # (these votes are refused, 403, but each is a write that counts).
        client = {"X-Forwarded-For": "203.0.113.77"}
        answers = [_call((a_port, b_port)[i % 2], "POST", f"/kinetix/api/levels/{level_id}/vote", {"value": 1},
                         client)[0] for i in range(WRITE_LIMIT + 1)]
        assert answers[:WRITE_LIMIT] == [403] * WRITE_LIMIT and answers[-1] == 429, answers

        # kill -9 A under both open tabs: they reconnect through nginx, to B.
        nonce = drawing.get_attribute("#kinetix-session", "data-nonce")
        a.send_signal(signal.SIGKILL)
        a.wait(timeout=30)
        wait_js(drawing, f"document.getElementById('kinetix-session') && document.getElementById("
                         f"'kinetix-session').getAttribute('data-nonce') !== '{nonce}' && {READY}", timeout=120)
        session = _session(b, drawing)
        wait_until(lambda: session.editor.spec == drawn, timeout=30)  # the draft, from the shared table
        assert session.editor.can_undo, "with its undo history"
        assert drawing.url.endswith(f"?draft={draft_id}")

        # The best run made on A replays on B, in a tab.
        player.goto(f"{public}?level={level_id}&mode=replay")
        wait_js(player, READY, timeout=120)
        replaying = _session(b, player)
        wait_until(lambda: replaying.mode == "replay" and replaying.replay is not None, timeout=60)
        wait_until(lambda: replaying.replay.frames_pushed >= 2, timeout=60)

        # The player's last play, recorded on A, is in its Recordings folder on B after the reload.
        last = b.recorder.last_finished(replaying)
        assert last is not None and (last.result, last.level_id, last.player) == ("solved", level_id, "human")
        assert read_recording(last.path).metadata["level_id"] == level_id
    finally:
        if context is not None:
            context.close()
        if b is not None:
            b.stop()
        if a is not None and a.poll() is None:
            a.kill()
            a.wait(timeout=30)
        if proxy is not None:
            proxy.terminate()
            proxy.wait(timeout=30)
        store.close()
