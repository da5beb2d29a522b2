"""Startup: viser on an internal port of 127.0.0.1, the side server on the user's port, sessions, warm-up, Ctrl+C.

Browsers reach everything through the user's port: the side server relays viser's websocket (server.web.http).

    app = App(Config(port=0)).start()     # port 0: any free port (tests)
    print(app.url)                        # the one URL to open
    app.stop()
"""

from __future__ import annotations

import contextlib
import dataclasses
import faulthandler
import io
import logging
import os
import signal
import socket
import sys
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)


def default_data_dir() -> Path:
    if os.environ.get("KINETIX_DATA"):
        return Path(os.environ["KINETIX_DATA"])
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "kinetix"


@dataclasses.dataclass
class Config:
    host: str = "127.0.0.1"
    port: int = 8080
    data: Path | None = None
    db: str | None = None
    max_sessions: int = 8
    warm_sizes: tuple[str, ...] = ("s", "m", "l")  # compile the play step for these before serving
    warm_batches: bool = True  # then compile their batched steps (several tabs playing at once) in the background
    gallery: bool = True  # include the gallery router when server.gallery is installed
    level: str | None = None  # a level file every new tab opens with (default: the editor's new level)
    editor_factory: object = None  # tests may swap the editor model; default server.editor.Editor
    record: bool = True  # record every play to MCAP (server.recordings.recorder); the tab's Recordings folder needs it
    drafts: bool = True  # keep every tab's work as a draft in <data>/drafts (server.drafts.tab): reloads lose nothing
    recent_max_files: int | None = None  # cap on recordings/recent (None: server.recordings.recorder.RECENT_MAX_FILES)
    recent_max_bytes: int | None = None  # its cap in bytes (None: server.recordings.recorder.RECENT_MAX_BYTES)
    agents: bool = True  # the Agent folder (Watch agent, Race, Train on this level) in every tab
    warm_agent: bool = True  # compile the general agent for warm_sizes in the background after start
    max_training_runs: int = 1  # training worker processes at once; more runs queue
    max_training_queue: int = 8  # training runs waiting in all; beyond it "Train" is refused (queue full)
    max_training_per_client: int = 1  # runs of one client (author identity, else tab) running at once
    train_steps: int = 100_000  # the default of a tab's "Training steps"
    train_options: dict = dataclasses.field(default_factory=dict)  # e.g. {"config": {"num_envs": 8}} (tests)
    train_worker: object = None  # the training worker function (tests swap in a cheap one); default train_worker
    allowed_hosts: tuple[str, ...] = ()  # host names besides `host`, localhost and 127.0.0.1 (server.web.security)
    trusted_proxies: str = ""  # proxies whose X-Forwarded-* headers are believed (server.web.proxies)
    root_path: str = ""  # serve everything under this path, e.g. "/kinetix/" (server.web.http.mount_under)
    write_limit: float | None = None  # gallery writes per minute per client; None: RateLimits' default, 0: off
    identity_limit: float | None = None  # new gallery identities per hour per client; None: default, 0: off


class App:
    """The running server: a ViserServer, a SessionManager and the uvicorn side server in a thread."""

    def __init__(self, config: Config):
        self.config = config
        self.viser = None
        self.manager = None
        self._uvicorn = None
        self._thread: threading.Thread | None = None
        self._socket: socket.socket | None = None
        self.store = None  # the gallery Store, once started with the gallery on
        self.recorder = None  # the PlayRecorder (server.recordings.recorder), once started
        self.training = None  # the TrainingPool, with agents on
        self.agents = None  # the AgentLink, with agents on
        self.drafts = None  # the DraftStore, with drafts on
        self.warmup = None  # the background compiles (server.play.warmup.WarmUp), once started
        self.relay_token = None  # what viser's internal port asks of every connection (server.web.relay)

    @property
    def shared(self) -> bool:
        """Whether the gallery is a database several processes share (PostgreSQL): then drafts, best runs, rate
        limits and the training queue live there too (docs/deploy.md); with SQLite they stay in this process and its
        data directory."""
        return self.store is not None and self.store.dialect != "sqlite"

    @property
    def port(self) -> int:
        return self._socket.getsockname()[1]

    @property
    def url(self) -> str:
        host = self.config.host
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else f"[{host}]" if ":" in host else host
        from server.web.prefix import normalise

        return f"http://{shown}:{self.port}{normalise(self.config.root_path)}/"

    def start(self) -> App:
        import uvicorn
        import viser

        from server.gallery.models import problem_handlers
        from server.play.manager import SessionManager
        from server.play.memory import keep_frame_buffers_resident
        from server.play.warmup import WarmUp
        from server.web.http import MAX_BROWSER_MESSAGE, create_app
        from server.web.prefix import normalise
        from server.web.proxies import TrustedProxies
        from server.web.relay import page_query, start_guarded_viser
        from server.web.security import allowed_hosts_for

        if self.config.max_sessions < 1:
            raise ValueError(f"--max-sessions must be at least 1, got {self.config.max_sessions}")
        if self.config.max_training_runs < 1:
            raise ValueError(f"--max-training-runs must be at least 1, got {self.config.max_training_runs}")
        if self.config.max_training_per_client < 1:
            raise ValueError("--max-training-per-client must be at least 1, got "
                             f"{self.config.max_training_per_client}")
        TrustedProxies.parse(self.config.trusted_proxies)  # a bad address or path fails before anything starts
        normalise(self.config.root_path)
        if self.config.max_training_queue < 0:
            raise ValueError(f"--max-training-queue cannot be negative, got {self.config.max_training_queue}")
        # Bind the user's port first so a busy port fails loudly (viser would silently take the next one).
        sock = socket.socket(socket.AF_INET6 if ":" in self.config.host else socket.AF_INET)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.config.host, self.config.port))
        except OSError as error:
            sock.close()
            raise RuntimeError(f"cannot listen on {self.config.host}:{self.config.port}: {error.strerror}") from None
        sock.listen(128)
        self._socket = sock
        # Every compile runs after the server answers (server.play.warmup): the play steps of warm_sizes first, then
        # their batched steps, then the general agent, one at a time on one background thread.
        agent = None
        if self.config.agents and self.config.warm_agent:
            from server.agents.play import warm_agent as agent
        self.warmup = WarmUp(self.config.warm_sizes, batches=self.config.warm_batches, agent=agent)
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its internal URL even when not verbose
            # Loopback only, whatever --host says, and only for the relay, which sends the token viser's port now
            # asks for (server.web.relay): the one port the user gave is the only way in, checks included.
            self.viser, self.relay_token = start_guarded_viser(viser)
        self.viser.gui.configure_theme(show_share_button=False, control_width="large", dark_mode=False)
        # Docked, the panel sits beside the canvas instead of floating over its right third, so no part of the level
        # hides behind it, and the browser renders a smaller canvas (headless Chromium at a 1280x800 window:
        # key-to-frame p50 62 ms docked, 79 ms floating).
        self.viser.gui.main_panel.dock_right()
        # The scene is one flat background image: viser's default lights, shadows and environment map change
        # nothing visible but cost the browser a full 3D render per frame. Measured in headless Chromium
        # (software WebGL): 140 ms per render with them and 30 frames/s without, key-to-frame p50 114 -> 30 ms.
        self.viser.scene.configure_default_lights(enabled=False, cast_shadow=False)
        self.viser.scene.configure_environment_map(hdri=None)
        forget_background_clear(self.viser)
        viser_server = self.viser
        self.manager = SessionManager(self.viser, max_sessions=self.config.max_sessions,
                                      editor_factory=self.config.editor_factory,
                                      initial_level=self._initial_level(), warmup=self.warmup,
                                      page_query=lambda client: page_query(viser_server, client.client_id))
        router = self._gallery_router()
        if self.recorder is None:
            self._start_recordings()
        app = create_app(self.manager, self.viser.get_port(), gallery_router=router,
                         gallery_handlers=problem_handlers if router is not None else None,
                         allowed_hosts=allowed_hosts_for(self.config.host, self.config.allowed_hosts),
                         trusted_proxies=TrustedProxies.parse(self.config.trusted_proxies),
                         root_path=self.config.root_path, relay_token=self.relay_token)
        self._attach_agents()
        self._attach_drafts()
        # No per-message deflate: viser's frames are zstd and JPEG already, and deflating them per tab costs CPU.
        config = uvicorn.Config(app, log_level="warning", lifespan="off", ws_max_size=MAX_BROWSER_MESSAGE,
                                ws_per_message_deflate=False)
        self._uvicorn = uvicorn.Server(config)
        self._uvicorn.install_signal_handlers = lambda: None  # the main thread handles Ctrl+C
        self._thread = threading.Thread(target=self._uvicorn.run, kwargs={"sockets": [sock]},
                                        name="kinetix-http", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 10
        while not self._uvicorn.started and time.monotonic() < deadline:
            time.sleep(0.01)
        if not self._uvicorn.started:
            self.stop()
            raise RuntimeError("the side server did not start")
        # The malloc thresholds that keep frame buffers resident also keep XLA's compile-time memory: set them
        # after the compiles (measured peak RSS, sizes s/m/l, 8 tabs: 1433 MB before, 1209 MB after).
        self.warmup.start(then=keep_frame_buffers_resident)
        return self

    def wait_until_warm(self, timeout: float | None = 600, everything: bool = False) -> bool:
        """Block until the play steps of warm_sizes (with `everything`, also the batched steps and the agent) are
        compiled; False on timeout. Tests and benchmarks that play at once call it; the server itself never waits."""
        return self.warmup is None or self.warmup.wait(timeout, sizes_only=not everything)

    def _initial_level(self):
        if not self.config.level:
            return None
        from kinetix.levels import load_level

        level_file = load_level(self.config.level)  # a bad file fails at startup with a LevelError message
        return lambda client: level_file

    def _gallery_router(self):
        """The gallery's API router, with the gallery linked into every editor tab; None with the gallery off."""
        if not self.config.gallery:
            return None
        from server.gallery.api import make_router
        from server.gallery.limits import RateLimits, SharedRateLimits
        from server.gallery.store import REPO_LEVELS, open_store
        from server.play.gallery_tab import GalleryLink

        # A new gallery gets the project's levels after the server answers (a thumbnail each: ~13 s from an empty
        # JAX cache), as the first warm-up task; a tab opened meanwhile shows the progress.
        self.store = open_store(self.config.db, data_dir=self.config.data or default_data_dir(), seed_dir=None)
        # Until then the API answers 503 with Retry-After rather than an empty gallery (server.gallery.api).
        ready = threading.Event()

        def seed() -> None:
            try:
                self.store.seed(REPO_LEVELS)  # returns at once when the gallery was seeded (another process)
            finally:
                ready.set()  # a failed seed is logged by the warm-up; the gallery then serves what it has

        self.warmup.prepend("the gallery's levels", seed)
        self._start_recordings()
        from server.recordings.replay import open_best_run

        link = GalleryLink(self.store, self.recorder if self.config.record else None,  # None: keeps no new runs
                           open_replay=open_best_run)
        link.attach(self.manager)
        if link.runs is not None:
            link.runs.remove_orphans()
        given = {"writes_per_minute": self.config.write_limit, "identities_per_hour": self.config.identity_limit}
        given = {name: value for name, value in given.items() if value is not None}
        # One process counts in memory; several on one PostgreSQL gallery count together in its rate_buckets table.
        limits = SharedRateLimits(self.store, **given) if self.shared else RateLimits(**given)
        return make_router(self.store, admin_token=os.environ.get("KINETIX_ADMIN_TOKEN"), limits=limits,
                           ready=ready.is_set)

    def _start_recordings(self) -> None:
        """Record every play (server.recordings.recorder) into the gallery's recordings folder, else
        <data>/recordings, and give each tab its Recordings folder (server.recordings.replay); leftovers of a killed
        server are removed first."""
        from server.recordings.recorder import PlayRecorder
        from server.recordings.replay import RecordingPanel

        if self.store is not None and self.store.recordings_dir is not None:
            directory = self.store.recordings_dir
        else:
            directory = Path(self.config.data or default_data_dir()) / "recordings"
        caps = {k: v for k, v in (("max_files", self.config.recent_max_files),
                                  ("max_bytes", self.config.recent_max_bytes)) if v is not None}
        self.recorder = PlayRecorder(directory, enabled=self.config.record, table=self._recent_table(), **caps)
        if self.config.record:
            removed = self.recorder.clean_up()
            if removed:
                log.info("removed %d partial or old recordings from %s", len(removed), directory)
        self.manager.add_listener(self.recorder)
        self.manager.add_listener(RecordingPanel(self.recorder))

    def _recent_table(self):
        """Each tab's last play in the gallery's database (server.recordings.recent), so a reload, through any
        process, finds it; None without the gallery or recordings. Its caps are the ones given (--recent-recordings,
        --recent-recordings-mb), else the folder's with SQLite (one process) and larger ones with PostgreSQL (the
        table holds every process's tabs)."""
        if self.store is None or not self.config.record:
            return None
        from server.recordings import recent
        from server.recordings.recorder import RECENT_KEEP_S, RECENT_MAX_BYTES, RECENT_MAX_FILES

        files, size = (recent.SHARED_RECENT_MAX_FILES, recent.SHARED_RECENT_MAX_BYTES) if self.shared else \
            (RECENT_MAX_FILES, RECENT_MAX_BYTES)
        return recent.RecentTable(self.store, max_files=self.config.recent_max_files or files,
                                  max_bytes=self.config.recent_max_bytes or size, keep_s=RECENT_KEEP_S)

    def _attach_agents(self) -> None:
        """The Agent folder in every tab (after the gallery's hooks, so `?level=..&mode=agent` opens first)."""
        if not self.config.agents:
            return
        from server.agents.shared_pool import SharedTrainingPool
        from server.agents.tab import AgentLink
        from server.agents.training import TrainingPool, train_worker

        data_dir = Path(self.config.data) if self.config.data else default_data_dir()
        limits = {"worker": self.config.train_worker or train_worker, "max_queued": self.config.max_training_queue,
                  "per_client": self.config.max_training_per_client}
        # Several processes on one PostgreSQL gallery share one queue: any process's worker takes the next run, the
        # limits count over all of them (server.agents.shared_pool); one process queues in memory, as ever.
        self.training = SharedTrainingPool(self.store, self.config.max_training_runs,
                                           work_dir=data_dir / "agents" / ".work", **limits) if self.shared else \
            TrainingPool(self.config.max_training_runs, **limits)
        self.agents = AgentLink(store=self.store, agents_dir=data_dir / "agents", pool=self.training,
                                train_steps=self.config.train_steps, train_options=self.config.train_options,
                                recorder=self.recorder if self.config.record else None)
        self.agents.attach(self.manager)
        if self.agents.level_agents is not None and self.agents.level_agents.remove_orphans():
            log.info("removed stored checkpoints of deleted levels' specialists")

    def _attach_drafts(self) -> None:
        """Drafts and the address bar (last, so `?draft=` is looked at before the gallery's and agents' links)."""
        if not self.config.drafts:
            return
        from server.drafts.store import DraftStore
        from server.drafts.tab import DraftLink
        from server.drafts.table import TableDraftStore

        # Several processes on one PostgreSQL gallery share the drafts (a reload may reach another process).
        self.drafts = TableDraftStore(self.store) if self.shared else \
            DraftStore(Path(self.config.data or default_data_dir()) / "drafts")
        removed = self.drafts.clean_up()
        if removed:
            log.info("removed %d old drafts", len(removed))
        DraftLink(self.drafts).attach(self.manager)

    def stop(self, compile_timeout: float = 120.0) -> bool:
        """Shut down: sessions, drafts, recordings, training, then (after waiting up to `compile_timeout` s for a
        background compile under way) the side server and viser. Returns False if a compile still runs: XLA cannot
        stop one midway, and the caller then ends the process itself (serve)."""
        from server.play import steps

        if self.warmup is not None:
            self.warmup.cancel()  # a stop during the first start's compiles waits for one compile, not all of them
        if self.manager is not None:
            self.manager.close_all()
        if self.drafts is not None:
            self.drafts.close()  # write the drafts still queued
        if self.recorder is not None:
            self.recorder.close()  # finish recordings of plays cut short by the shutdown
        if self.training is not None:
            self.training.close()
        compiled = steps.wait_for_compiles(timeout=compile_timeout)
        if not compiled and compile_timeout > 0:  # a compile cut off by interpreter exit aborts the process
            log.warning("background compiles still running at shutdown")
        if self._uvicorn is not None:
            self._uvicorn.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self.store is not None:
            self.store.close()
            self.store = None
        if self.viser is not None:
            with contextlib.redirect_stdout(io.StringIO()):
                self.viser.stop()
        if self._socket is not None:
            self._socket.close()
        return compiled


def forget_background_clear(server) -> None:
    """Drop the "no background image" that viser's start-up (scene.reset) leaves in the state every new client is sent.

    A new tab gets that state from viser's shared buffer while its own messages, the session's first frames among
    them, come from its own buffer at the same time: the clear often came last and hid them, so the canvas stayed
    blank until the next frame, about a second later on a loaded machine (issue 37: Watch agent showed a blank
    canvas for ~1.2 s). Every tab draws its own background, so the shared one has nothing to clear. viser 1.1.1 has
    no public call for this; if its internals differ, nothing is removed (the old behaviour)."""
    try:
        from viser._messages import BackgroundImageMessage

        buffer = server._websock_server.get_message_buffer()
        buffer.remove_from_buffer(lambda message: isinstance(message, BackgroundImageMessage))
    except (ImportError, AttributeError):
        log.debug("viser's start-up background clear stays", exc_info=True)


def _megabytes(value: int | None) -> int | None:
    return None if value is None else value << 20


def serve(args) -> int:
    """`kinetix serve`: start, print the URL, run until Ctrl+C (or SIGTERM), then shut down cleanly."""
    # Python answers Ctrl+C only where SIGINT was not inherited as ignored; a job started with `&` from a script (a
    # test run launched in the background, two CI failures) inherits it ignored, and the server then never stopped
    signal.signal(signal.SIGINT, signal.default_int_handler)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    # viser's websocket server logs its internal port at INFO; users must open only the URL printed below.
    logging.getLogger("websockets").setLevel(logging.WARNING)
    config = Config(host=args.host, port=args.port, data=Path(args.data) if args.data else None,
                    db=getattr(args, "db", None), max_sessions=getattr(args, "max_sessions", 8),
                    warm_sizes=tuple(size for size in getattr(args, "warm", ["s", "m", "l"]) if size != "none"),
                    record=getattr(args, "record", True), max_training_runs=getattr(args, "max_training_runs", 1),
                    max_training_queue=getattr(args, "max_training_queue", 8),
                    max_training_per_client=getattr(args, "max_training_per_client", 1),
                    allowed_hosts=tuple(getattr(args, "allowed_hosts", ())),
                    trusted_proxies=getattr(args, "trusted_proxies", ""),
                    root_path=getattr(args, "root_path", ""),
                    write_limit=getattr(args, "write_limit", None),
                    identity_limit=getattr(args, "identity_limit", None),
                    recent_max_files=getattr(args, "recent_recordings", None),
                    recent_max_bytes=_megabytes(getattr(args, "recent_recordings_mb", None)))
    try:
        app = App(config).start()
    except (RuntimeError, ValueError) as error:
        print(f"kinetix serve: {error}", flush=True)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:  # from here on a Ctrl+C shuts down cleanly, even one that lands in these prints (CI saw it there once)
        print(f"Open {app.url}", flush=True)
        print("Compiling the physics for play in the background (a first start takes longer; later starts use the "
              "cache)...", flush=True)
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    print("Shutting down...", flush=True)
    # A shutdown that hangs says where: every thread's stack on stderr after 20 s (kinetix serve twice did not
    # exit within 30 s of a Ctrl+C in loaded test runs, and never when run alone).
    faulthandler.dump_traceback_later(20)
    stopped = app.stop(compile_timeout=0.0)
    faulthandler.cancel_dump_traceback_later()
    if not stopped:
        # A Ctrl+C during the warm-up: everything is closed and written, but XLA cannot stop the compile under way
        # (waiting for it took ~10 s), and an interpreter exit under a running compile aborts the process. So the
        # process ends here, at once and cleanly; the compile is simply not finished (nothing of it is kept).
        print("(the compile under way is abandoned)", flush=True)
        logging.shutdown()
        sys.stderr.flush()
        os._exit(0)
    return 0
