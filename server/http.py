"""The side server on the user's port: viser's page with our key script, static files, /keys, and the gallery API.

viser serves only its own client build and has no hooks for routes, so this FastAPI app (run by uvicorn in
a background thread, see server.app) is the one URL the user opens:

    GET /            viser's client/build/index.html with `window.__KINETIX__ = {viserPort}`, frames.js and keys.js
                     injected
    GET /static/...  files of static/
    WS  /keys        key events from keys.js, paired to the tab's session by the nonce the session put in the page
    GET /gallery     static/gallery.html, the gallery page; only with the gallery router (it calls /api)
    /api/...         the gallery router, when given (create_app(..., gallery_router=router))
"""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path

from fastapi import APIRouter, FastAPI, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, HTMLResponse, PlainTextResponse
from fastapi.staticfiles import StaticFiles

from server.web_security import LOCAL_HOSTS, WebSecurity

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
KEY_FIELDS = ("ctrl", "shift", "alt", "meta")
MAX_KEY_MESSAGE = 1024  # bytes; anything longer is not a key event


def viser_index_html() -> str:
    import viser

    return (Path(viser.__file__).parent / "client" / "build" / "index.html").read_text(encoding="utf-8")


def inject(page: str, viser_port: int) -> str:
    """The viser page with our configuration, frame display and key script right after <head>."""
    snippet = (f"<script>window.__KINETIX__ = {json.dumps({'viserPort': viser_port})};</script>"
               '<script src="/static/frames.js"></script><script src="/static/keys.js"></script>'
               '<script src="/static/labels.js"></script>')  # ties viser's labels to their inputs
    head = page.find("<head>")
    if head < 0:
        raise ValueError("viser's index.html has no <head>; cannot inject the key script")
    return page[: head + 6] + snippet + page[head + 6:]


def create_app(manager, viser_port: int, *, static_dir: Path = STATIC_DIR,
               gallery_router: APIRouter | None = None, allowed_hosts=LOCAL_HOSTS) -> FastAPI:
    """The side server's app. `manager` is a server.session.SessionManager (it maps nonces to sessions).
    Requests must name one of `allowed_hosts` (server.web_security: Host/Origin checks, security headers)."""
    app = FastAPI(title="Kinetix playground", docs_url="/docs", openapi_url="/openapi.json")
    app.add_middleware(WebSecurity, allowed_hosts=allowed_hosts)
    page = inject(viser_index_html(), viser_port)

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def index() -> HTMLResponse:
        return HTMLResponse(page, headers={"Cache-Control": "no-store"})

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
            await socket.send_text(json.dumps({"type": "ready"}))
            query = hello.get("query")
            if isinstance(query, str) and query and manager.on_query is not None:
                # e.g. /?level=<gallery id>&mode=play: the page's query reaches Python only through this socket.
                await asyncio.get_running_loop().run_in_executor(None, manager.on_query, session, query)
            while True:
                event = await _receive(socket)
                kind, code = event.get("type"), event.get("code")
                if kind == "blur":
                    session.release_all_keys()
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
