"""`kinetix bench server`: what a player feels, measured against a real server in this process.

- draw_ms: server.play.draw frame time at 512x512 (mean over a project level, static layer cached as in play);
- key-to-frame latency in headless Chromium (the apt chromium via playwright): from the keydown handler in the
  page to the moment the frame stepped with that key is drawn on the page's canvas (static/frames.js; the server
  puts the key's sequence number in a hidden element in the same batch as the frame), p50 and p90;
- frames per second the Chromium page drew (not just received) while playing one level;
- key-to-wire latency: the same, ending when a headless protocol client receives that batch (server side only),
  through the user's port and, to show what the websocket relay costs, straight to viser's internal port;
- fps delivered to one tab and to each of 8 concurrent playing sessions (through the user's port), counted at the
  websocket by headless protocol clients in a child process (browser tabs with software WebGL would measure the
  2-core machine's CPU, not the server);
- peak RSS of this process (the server) while 8 sessions play;
- capacity: tabs playing at >= 25 fps per CPU core, with 1 and with 2 server processes (server.bench.capacity;
  `--capacity-only` runs just this, `--no-capacity` skips it), docs/deploy.md's sizing rule.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

LEVEL = Path(__file__).resolve().parents[2] / "levels" / "car_right.json"


def _print(name: str, value: float, unit: str, as_json: bool, **extra) -> None:
    if as_json:
        print(json.dumps({"bench": "server", "metric": name, "value": round(value, 3), "unit": unit, **extra}))
    else:
        print(f"{name:<34} {value:>10.2f} {unit}")


def _draw_ms(level_file) -> float:
    from server.play.draw import View, draw_frame, scene_of

    scene, view = scene_of(level_file.level), View(512, 512)
    for _ in range(5):
        draw_frame(scene, view, hud="PLAY")
    t0 = time.perf_counter()
    for _ in range(200):
        draw_frame(scene, view, hud="PLAY  step 12  0.40 s")
    return (time.perf_counter() - t0) / 200 * 1000


# static/frames.js draws each frame on the page's frame canvas and tells its listeners which key acknowledgements
# (the key's sequence number, sent in the same batch as the frame it produced) that frame carried.
DRAWN_SCRIPT = """() => { window.__drawn = []; window.__kinetixFrames.listeners.push((seq, acks) => {
  const now = performance.now(); for (const a of acks) window.__drawn.push([a, now]); }); }"""


def _latency(app, chromium: str, samples: int) -> tuple[list[float], float]:
    """Key-to-frame latencies (ms) and the frames per second the page drew while playing."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--use-gl=swiftshader"])
        # The control panel (about 390 px) is docked beside the canvas: this leaves a canvas of about 640x480.
        # bypass_csp: wait_for_function evaluates its predicate with eval in the page, which the server's
        # Content-Security-Policy refuses (server/web/security.py); the page and its frames are the same.
        page = browser.new_page(viewport={"width": 1030, "height": 480}, bypass_csp=True)
        page.goto(app.url)
        page.wait_for_function("window.__kinetixKeys && window.__kinetixKeys.ready()", timeout=60_000)
        page.evaluate(DRAWN_SCRIPT)
        box = page.evaluate("() => { const r = [...document.querySelectorAll('canvas')].map(c => "
                            "c.getBoundingClientRect()).sort((a, b) => b.width * b.height - a.width * a.height)[0];"
                            " return [r.x + r.width / 2, r.y + r.height / 2]; }")
        page.mouse.click(*box)  # focus the canvas (a click on an empty canvas edits nothing with select)
        page.keyboard.press("Space")
        page.wait_for_timeout(500)
        latencies = []
        for i in range(samples):
            key = "ArrowRight" if i % 2 == 0 else "ArrowLeft"
            page.keyboard.down(key)
            seq, t = page.evaluate("() => { const s = window.__kinetixKeys.sent; return [s[s.length-1].seq, "
                                   "s[s.length-1].t]; }")
            page.wait_for_function(f"window.__drawn.some(a => a[0] >= {seq})", timeout=5000)
            ack = page.evaluate(f"() => window.__drawn.find(a => a[0] >= {seq})[1]")
            latencies.append(ack - t)
            page.keyboard.up(key)
            page.wait_for_timeout(60)
        # Frames the page drew in 3 s of play with no key held.
        drawn0, t0 = page.evaluate("() => [window.__kinetixFrames.drawn, performance.now()]")
        page.wait_for_timeout(3000)
        drawn1, t1 = page.evaluate("() => [window.__kinetixFrames.drawn, performance.now()]")
        page.keyboard.press("Space")
        browser.close()
    return latencies, (drawn1 - drawn0) / (t1 - t0) * 1000


def _wire_latency(app, samples: int) -> tuple[list[float], list[float]]:
    """ms from sending a key on /keys to the frame batch carrying its ack arriving at a protocol client: through the
    user's port (viser's websocket relayed by the side server, as browsers get it) and, for the relay's cost, straight
    to viser's internal port. The two tabs take turns (in alternating order), so the machine's load hits both alike."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "server"))
    from viser_client import KeysSocket, ViserTestClient, session_nonce

    tabs = []
    try:
        for port in (app.port, app.viser.get_port()):
            client = ViserTestClient(port, 640, 480, token=app.relay_token if port != app.port else None)
            tabs.append((client, None))
            client.wait_frame(timeout=30)
            tabs[-1] = (client, KeysSocket(app.port, session_nonce(client)))
        for _, keys in tabs:
            keys.down("Space")
        time.sleep(0.5)
        latencies: tuple[list[float], list[float]] = ([], [])
        for i in range(samples):
            code = "ArrowRight" if i % 2 == 0 else "ArrowLeft"
            for k in (0, 1) if i % 2 == 0 else (1, 0):  # who goes first alternates: no order bias
                (client, keys), out = tabs[k], latencies[k]
                start = client.count()
                t0 = time.perf_counter()
                seq = keys.down(code)
                client.wait_for(lambda m, seq=seq: m["type"] == "GuiUpdateMessage"
                                and f'data-seq="{seq}"' in str(m.get("updates")), timeout=5, start=start)
                out.append((time.perf_counter() - t0) * 1000)
                keys.up(code)
                time.sleep(0.05)
        for _, keys in tabs:
            keys.down("Space")
        return latencies
    finally:
        for client, keys in tabs:
            if keys is not None:
                keys.close()
            client.close()
        deadline = time.monotonic() + 10
        while app.manager.sessions and time.monotonic() < deadline:
            time.sleep(0.05)


def _fps(app, sessions: int, seconds: float) -> list[float]:
    """Frames per second received by each of `sessions` protocol clients while all play.

    The clients run in a child process: tabs are not part of the server, and decoding 8 streams in the server's
    own process would charge their work to the server's interpreter lock.
    """
    import subprocess

    child = subprocess.Popen([sys.executable, "-c", "from server.bench.server import client_process; client_process()",
                              str(app.port), str(sessions), str(seconds)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                             cwd=Path(__file__).resolve().parents[2])
    try:
        if child.stdout.readline().strip() != "connected":
            raise RuntimeError("the benchmark's client process did not connect")
        deadline = time.monotonic() + 30
        while len(app.manager.sessions) < sessions and time.monotonic() < deadline:
            time.sleep(0.05)
        for session in list(app.manager.sessions.values()):
            session.play()
        time.sleep(0.5)
        child.stdin.write("go\n")
        child.stdin.flush()
        rates = json.loads(child.stdout.readline())
        child.wait(timeout=30)
        return rates
    finally:
        if child.poll() is None:
            child.kill()
        deadline = time.monotonic() + 10
        while app.manager.sessions and time.monotonic() < deadline:
            time.sleep(0.05)


def client_process() -> None:
    """Child of _fps: argv = the server's port (it relays viser's websocket), number of tabs, seconds; prints
    "connected", waits for "go", then the frames per second each tab received as a JSON list."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "server"))
    from viser_client import ViserTestClient  # the headless client of the protocol tests

    port, sessions, seconds = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
    clients = [ViserTestClient(port, 640, 480) for _ in range(sessions)]
    for client in clients:
        client.wait_frame(timeout=30)
    print("connected", flush=True)
    from server.bench.capacity import print_rates_when_asked

    print_rates_when_asked(clients, seconds)
    for client in clients:
        client.close()


def _capacity(args: argparse.Namespace) -> None:
    """Tabs playing at >= 25 fps per core, with 1 and with 2 server processes (server.bench.capacity)."""
    from server.bench.capacity import MIN_FPS, capacity, cores

    quiet = (lambda line: None) if args.json else print
    for processes in (1, 2):
        tabs, _ = capacity(processes, seconds=args.seconds, report=quiet)
        _print(f"tabs_at_{MIN_FPS:g}fps_{processes}_process", tabs, "tabs", args.json, cores=cores())
        _print(f"tabs_per_core_{processes}_process", tabs / cores(), "tabs/core", args.json, cores=cores())


def run(args: argparse.Namespace) -> int:
    if getattr(args, "capacity_only", False):
        _capacity(args)
        return 0
    from kinetix.levels import load_level
    from server.app import App, Config
    from server.play import steps

    level_file = load_level(LEVEL)
    # Started as `kinetix serve` starts (all size classes warm, batched steps compiled in the background, then the
    # malloc thresholds for frame buffers), so draw time and peak RSS are the server's.
    app = App(Config(port=0, max_sessions=args.sessions + 2, level=str(LEVEL), gallery=False)).start()
    steps.wait_for_compiles()  # measure after the background compiles
    try:
        _print("draw_ms_512", _draw_ms(level_file), "ms", args.json)
        if Path(args.chromium).exists():
            lat, drawn_fps = _latency(app, args.chromium, args.samples)
            lat = sorted(lat)
            _print("key_to_frame_p50", statistics.median(lat), "ms", args.json, samples=len(lat))
            _print("key_to_frame_p90", lat[int(0.9 * (len(lat) - 1))], "ms", args.json, samples=len(lat))
            _print("fps_drawn_in_chromium", drawn_fps, "fps", args.json)
        else:
            print(f"no chromium at {args.chromium}: latency not measured (run .ci/setup-chromium.sh)", file=sys.stderr)
        wire, direct = (sorted(x) for x in _wire_latency(app, args.samples))
        _print("key_to_wire_p50", statistics.median(wire), "ms", args.json, samples=len(wire))
        _print("key_to_wire_p90", wire[int(0.9 * (len(wire) - 1))], "ms", args.json, samples=len(wire))
        _print("key_to_wire_direct_p50", statistics.median(direct), "ms", args.json, samples=len(direct))
        _print("key_to_wire_direct_p90", direct[int(0.9 * (len(direct) - 1))], "ms", args.json, samples=len(direct))
        one = _fps(app, 1, args.seconds)
        _print("fps_one_session", one[0], "fps", args.json)
        many = _fps(app, args.sessions, args.seconds)
        _print(f"fps_{args.sessions}_sessions_min", min(many), "fps", args.json)
        _print(f"fps_{args.sessions}_sessions_mean", statistics.mean(many), "fps", args.json)
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        _print(f"peak_rss_{args.sessions}_sessions", peak_mb, "MB", args.json)
    finally:
        app.stop()
    if not getattr(args, "no_capacity", False):
        _capacity(args)  # after this process's server stopped: the capacity servers get the machine
    return 0
