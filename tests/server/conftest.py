"""One server per test module (compiled once), driven by the headless viser client in viser_client.py."""

from __future__ import annotations

import contextlib
import sys
import tempfile
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # viser_client, fake_editor

LEVELS = Path(__file__).resolve().parents[2] / "levels"


def wait_until(predicate, timeout: float = 20.0) -> None:
    """Poll `predicate` every 20 ms; TimeoutError after `timeout` seconds (sessions run on other threads)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not reached")
        time.sleep(0.02)


def session_of(app, client, timeout: float = 20.0):
    """(the Session, its nonce) of a headless client's tab, once the server has registered it."""
    from viser_client import session_nonce

    nonce = session_nonce(client)
    wait_until(lambda: app.manager.session_by_nonce(nonce) is not None, timeout)
    return app.manager.session_by_nonce(nonce), nonce


@contextlib.contextmanager
def running_app(wait_warm: bool = True, **config):
    from server.app import App, Config

    # No background compiles of batched steps: tests that need them ask for them (test_play_batch.py).
    # Recordings (on by default) go to a temporary data dir unless the test gives one. Nor is the general agent
    # compiled at start: tests that watch it compile it on first use.
    with tempfile.TemporaryDirectory(prefix="kinetix-test-data-") as data:
        app = App(Config(**{"port": 0, "gallery": False, "warm_batches": False, "warm_agent": False,
                            "data": Path(data), **config}))
        app.start()
        try:
            # The server compiles after it answers (server.play.warmup); tests that play at once wait for the play
            # steps, as a user would by the time they press a key. test_warm_start.py does not.
            if wait_warm:
                assert app.wait_until_warm(timeout=600), "the play steps did not compile"
            yield app
        finally:
            app.stop()


@pytest.fixture
def make_client():
    """Clients opened through this fixture are closed before the server stops (viser waits for open sockets)."""
    from viser_client import ViserTestClient

    clients = []

    def make(app, width=640, height=480):
        client = ViserTestClient(app.viser.get_port(), width, height, token=app.relay_token)
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.close()
