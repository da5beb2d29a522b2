"""The side server on the user's port: viser's page with our scripts, viser's websocket, static files, /keys, the API.

viser serves only its own client build and has no hooks for routes, so this FastAPI app (run by uvicorn in
a background thread, see server.app) is the one URL the user opens, and the only port the app listens on for
the outside world (viser itself listens on an ephemeral port of 127.0.0.1):

    GET /            viser's client/build/index.html with frames.js and keys.js injected (relative paths, so the
                     page also works under a reverse proxy or TLS); for an address that names a level
                     (?level=<id>, ?draft=<id>) also that level's picture, which frames.js shows at once
    WS  /            viser's websocket, relayed to viser's internal port (viser's client connects to the page's own
                     URL when the page has no ?websocket= parameter; keys.js removes a stale one)
    GET /static/...  files of static/
    WS  /keys        key events from keys.js, paired to the tab's session by the nonce the session put in the page
    GET /gallery     static/gallery.html, the gallery page; only with the gallery router (it calls /api)
    /api/...         the gallery router, when given (create_app(..., gallery_router=router))
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import re
from collections.abc import Callable
from pathlib import Path

from fastapi import APIRouter, FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, HTMLResponse, PlainTextResponse
from fastapi.staticfiles import StaticFiles

from kinetix.draw import LETTERBOX
from server.web.prefix import UnderPath, normalise
from server.web.proxies import TrustedProxies
from server.web.relay import relay_to_viser
from server.web.security import LOCAL_HOSTS, VISER_PAGE_CONTENT_SECURITY_POLICY, WebSecurity

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
KEY_FIELDS = ("ctrl", "shift", "alt", "meta")
MAX_KEY_MESSAGE = 1024  # bytes; anything longer is not a key event
TAB_KEY = re.compile(r"[A-Za-z0-9_-]{16,64}")  # a tab's key as keys.js makes it (32 hex digits); others are ignored
# The largest message a browser may send on any websocket of the side server (uvicorn's ws_max_size): viser's
# client uploads files in 512 KiB parts, msgpack-framed. Key events are cut at MAX_KEY_MESSAGE anyway.
MAX_BROWSER_MESSAGE = 1 << 20


def viser_index_html() -> str:
    import viser

    return (Path(viser.__file__).parent / "client" / "build" / "index.html").read_text(encoding="utf-8")


def inject(page: str) -> str:
    """The viser page with our frame display, key script and labels right after <head> (before viser's code).

    The paths are relative to the page, so a reverse proxy may serve the app under a path of its own."""
    snippet = ('<script src="static/passive.js"></script>'  # first: before any listener is added
               '<script src="static/frames.js"></script><script src="static/keys.js"></script>'
               '<script src="static/labels.js"></script>')  # labels.js ties viser's labels to their inputs
    head = page.find("<head>")
    if head < 0:
        raise ValueError("viser's index.html has no <head>; cannot inject the key script")
    return page[: head + 6] + snippet + page[head + 6:]


def with_preview(page: str, jpeg: bytes, letterbox: tuple[int, int, int]) -> str:
    """The page with a level's picture as its body's first element, filling the window as viser's canvas will at
    first (letterboxed in `letterbox`, as the server's frames are), so the page's very first paint shows the level;
    static/frames.js draws it on the canvas once viser's canvas exists and hides this. Inline, so it is there before
    anything is painted, without a request of its own."""
    body = page.find("<body>")
    if body < 0:
        return page  # the page still works without it
    colour = "#" + "".join(f"{channel:02x}" for channel in letterbox)
    # Under everything viser draws (z-index -1): it shows only until viser's canvas covers it.
    style = f"position:fixed;inset:0;z-index:-1;width:100%;height:100%;object-fit:contain;background:{colour}"
    image = (f'<img id="kinetix-preview" alt="" decoding="sync" data-letterbox="{colour}" style="{style}" '
             f'src="data:image/jpeg;base64,{base64.b64encode(jpeg).decode()}">')
    return page[: body + 6] + image + page[body + 6:]


def create_app(manager, viser_port: int, *, static_dir: Path = STATIC_DIR,
               gallery_router: APIRouter | None = None,
               gallery_handlers: Callable[[FastAPI], None] | None = None, allowed_hosts=LOCAL_HOSTS,
               trusted_proxies: TrustedProxies | None = None, root_path: str = "",
               relay_token: str | None = None) -> FastAPI:
    """The side server's app. `manager` is a server.play.session.SessionManager (it maps nonces to sessions).
    Requests must name one of `allowed_hosts` (server.web.security: Host/Origin checks, security headers), and
    X-Forwarded-* headers count only from `trusted_proxies` (server.web.proxies). With `root_path` ("/kinetix/")
    every route is served under that path instead of the root (server.web.prefix). `relay_token`: what viser's
    internal port asks of the relay (server.web.relay)."""
    app = FastAPI(title="Kinetix playground", docs_url="/docs", openapi_url="/openapi.json")
    page = inject(viser_index_html())

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def index(request: Request) -> HTMLResponse:
        # The level the address names, drawn into the page: shown before viser's client has started (issue 37).
        preview = getattr(manager, "preview", None)
        jpeg = preview(request.url.query) if preview is not None else None
        shown = page if jpeg is None else with_preview(page, jpeg, LETTERBOX)
        # viser's client needs a policy of its own (server.web.security); the middleware keeps a header already set.
        return HTMLResponse(shown, headers={"Cache-Control": "no-store",
                                           "Content-Security-Policy": VISER_PAGE_CONTENT_SECURITY_POLICY})

    @app.websocket("/")
    async def viser_socket(socket: WebSocket) -> None:
        await relay_to_viser(socket, viser_port, relay_token)

    @app.get("/health", response_class=PlainTextResponse, include_in_schema=False)
    def health() -> str:
        return f"ok {len(manager.sessions)} sessions"

    @app.get("/gallery", include_in_schema=False)
    def gallery():
        # The page is nothing without its API: a server started without the gallery says so instead.
        if gallery_router is None:
            return PlainTextResponse("this server runs without the gallery", status_code=404)
        return FileResponse(static_dir / "gallery.html")

    if gallery_router is not None:
        app.include_router(gallery_router, prefix="/api")
        if gallery_handlers is not None:  # the gallery's own error shape (server.gallery.models.problem_handlers):
            gallery_handlers(app)  # passed in, so server.web never imports server.gallery

    @app.websocket("/keys")
    async def keys(socket: WebSocket) -> None:
        await socket.accept()
        session = None
        try:
            hello = await _receive(socket)
            if hello.get("type") != "hello" or not isinstance(hello.get("nonce"), str):
                await socket.close(code=1008, reason="expected hello with a nonce")
                return
            # The session can be a moment behind the page (viser connects it after its first camera message).
            for _ in range(50):
                session = manager.session_by_nonce(hello["nonce"])
                if session is not None:
                    break
                await asyncio.sleep(0.1)
            if session is None:
                await socket.close(code=1008, reason="unknown session")
                return
            if isinstance(hello.get("token"), str) and hello["token"]:
                session.author_token = hello["token"]  # the gallery author token the browser keeps
            if isinstance(hello.get("tab"), str) and TAB_KEY.fullmatch(hello["tab"]):
                session.tab_key = hello["tab"]  # the tab's key in sessionStorage (its last play is kept under it)
            query = hello.get("query")
            if isinstance(query, str):
                # e.g. /?level=<gallery id>&mode=play, ?draft=<id>, or "" (a new tab gets a draft id), unless the
                # session opened it at connect already (the relay passed the query on; the manager opens it once).
                # Before "ready", so keys pressed meanwhile (keys.js queues them) act on the opened level, not on
                # the placeholder.
                await asyncio.get_running_loop().run_in_executor(None, manager.open_query, session, query)
            await socket.send_text(json.dumps({"type": "ready"}))
            while True:
                event = await _receive(socket)
                kind, code = event.get("type"), event.get("code")
                if kind == "blur":
                    session.release_all_keys()
                    continue
                if kind == "fields":  # a dialog's text fields, sent before its button's click (keys.js)
                    await asyncio.get_running_loop().run_in_executor(None, session.set_fields, event.get("values"))
                    await socket.send_text(json.dumps({"type": "fields_ack", "id": event.get("id")}))
                    continue
                if kind not in ("down", "up") or not isinstance(code, str):
                    continue
                seq = event.get("seq")
                session.key_event(kind, code, str(event.get("key") or ""),
                                  **{f: bool(event.get(f)) for f in KEY_FIELDS},
                                  seq=seq if isinstance(seq, int) else -1)
        except WebSocketDisconnect:
            pass
        finally:
            if session is not None:
                session.release_all_keys()  # a closed key socket must not leave a thruster firing

    app.mount("/static", StaticFiles(directory=static_dir), name="static")
    # The last added is the outermost: the path prefix, then the security checks (which also guard the relay of
    # viser's websocket).
    app.add_middleware(WebSecurity, allowed_hosts=allowed_hosts, trusted_proxies=trusted_proxies)
    if normalise(root_path):
        app.add_middleware(UnderPath, root_path=root_path)
    return app


async def _receive(socket: WebSocket) -> dict:
    text = await socket.receive_text()
    if len(text) > MAX_KEY_MESSAGE:
        return {}
    try:
        event = json.loads(text)
    except json.JSONDecodeError:
        return {}
    return event if isinstance(event, dict) else {}
