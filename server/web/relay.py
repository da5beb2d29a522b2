"""viser behind the side server: viser's internal port answers only the relay, and the relay itself.

    server, token = start_guarded_viser(viser)       # a ViserServer on 127.0.0.1:<ephemeral> that wants the token
    await relay_to_viser(socket, server.get_port(), token)

viser listens on an ephemeral port of 127.0.0.1 that browsers never see. Without a guard, anything on the machine
(another user's process, a page's DNS-rebound request to 127.0.0.1) could connect to it straight and skip the side
server's Host, Origin and proxy checks (server.web.security). viser has no option for that, so while its server
starts `websockets.asyncio.server.serve` is wrapped to add a `process_request` check in front of viser's own
(which serves its client files): every request, websocket or plain HTTP, must carry the header TOKEN_HEADER with a
random token only this process knows, else it gets 403 before viser sees it. The relay sends it. (A unix socket
would need viser to listen on one, which it cannot.)

The page's query (`?level=<id>&mode=agent`, `?draft=<id>`) travels with viser's websocket (static/frames.js adds it to
the URL viser's client connects to) and the relay passes it on to viser's internal URL, where `page_query` finds it
for the new client: so a tab's session knows what its address names the moment it starts, instead of a second or
more later over /keys, after the browser has built viser's panel (issue 37: the tab showed nothing, then an empty
level, before the level of a Watch agent link).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import http
import io
import logging
import re
import secrets
import threading

import websockets
import websockets.asyncio.server
from fastapi import WebSocket

log = logging.getLogger(__name__)

VISER_HOST = "127.0.0.1"  # viser listens here only; browsers reach it through the relay below
TOKEN_HEADER = "X-Kinetix-Relay"
UNSENDABLE_CLOSE_CODES = (1005, 1006, 1015)  # reported by a websocket library, never sent in a close frame
MAX_QUERY = 2048  # characters of the page's query passed on to viser (an address is far shorter; longer ones go)
# What a query may hold as it is passed on (it is percent-encoded already; anything else is dropped, not repaired).
QUERY_CHARACTERS = re.compile(r"[A-Za-z0-9._~%!$&'()*+,;=:@/?-]*")
_serve_lock = threading.Lock()  # one guarded start at a time (the wrapper is installed process-wide meanwhile)


def start_guarded_viser(viser_module) -> tuple[object, str]:
    """Start a ViserServer on VISER_HOST (an ephemeral port) that refuses whoever lacks the returned token."""
    token = secrets.token_urlsafe(24)
    original = websockets.asyncio.server.serve

    def guarded_serve(handler, *args, process_request=None, **kwargs):
        def check(connection, request):
            sent = request.headers.get(TOKEN_HEADER, "").encode("utf-8", "surrogateescape")
            if not hmac.compare_digest(sent, token.encode()):
                return connection.respond(http.HTTPStatus.FORBIDDEN, "only the kinetix side server may connect\n")
            return process_request(connection, request) if process_request is not None else None

        return original(handler, *args, process_request=check, **kwargs)

    with _serve_lock:
        websockets.asyncio.server.serve = guarded_serve
        try:
            # viser's constructor returns once its port is bound, so serve() has been called by then.
            with contextlib.redirect_stdout(io.StringIO()):  # viser prints its internal URL even when not verbose
                server = viser_module.ViserServer(host=VISER_HOST, port=0, verbose=False)
        finally:
            websockets.asyncio.server.serve = original
    return server, token


async def relay_to_viser(socket: WebSocket, viser_port: int, token: str | None = None) -> None:
    """Relay one browser websocket to viser's internal port, message for message, both ways, until either closes.

    The browser's subprotocol (viser-v<version>) is passed on, and viser's choice and close code come back, so
    viser's own version check still works. No compression on the loopback leg: viser's windows are zstd and JPEG.
    """
    offered = [p.strip() for p in socket.headers.get("sec-websocket-protocol", "").split(",") if p.strip()]
    query = socket.url.query
    if len(query) > MAX_QUERY or not QUERY_CHARACTERS.fullmatch(query):
        query = ""
    try:
        upstream = await websockets.connect(f"ws://{VISER_HOST}:{viser_port}/" + (f"?{query}" if query else ""),
                                            subprotocols=offered or None,
                                            compression=None, max_size=None, ping_interval=None, open_timeout=10,
                                            additional_headers={TOKEN_HEADER: token} if token else None)
    except (OSError, TimeoutError, websockets.InvalidHandshake) as error:
        log.warning("viser's websocket is not reachable: %s", error)
        await socket.close(code=1011, reason="the viewer is not running")
        return
    await socket.accept(subprotocol=upstream.subprotocol)

    async def to_viser() -> None:
        while True:
            message = await socket.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            await upstream.send(data if data is not None else message.get("text") or "")

    async def to_browser() -> None:
        with contextlib.suppress(websockets.ConnectionClosed):
            async for data in upstream:
                if isinstance(data, bytes):
                    await socket.send_bytes(data)
                else:
                    await socket.send_text(data)

    tasks = [asyncio.create_task(to_viser()), asyncio.create_task(to_browser())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:  # a send into a closed socket ends its task with an error; nothing is left to relay
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        await upstream.close()
        code = upstream.close_code
        if code is None or code in UNSENDABLE_CLOSE_CODES:
            code = 1011  # viser went away without a proper close (e.g. a server restart)
        with contextlib.suppress(Exception):  # the browser may have gone already
            await socket.close(code=code, reason=upstream.close_reason or "")


def page_query(server, client_id: int) -> str | None:
    """The query of the page whose websocket became viser client `client_id` ("?level=...&mode=agent"), as the relay
    passed it on; None when it named none (a bare address, an older page, a client that came straight to viser's
    port). viser 1.1.1 keeps each client's websocket connection, and with it the request, in its websocket server;
    it has no public call for it, so if its internals differ this finds nothing (the query then comes over /keys)."""
    try:
        path = server._websock_server._live_connections[client_id].request.path
    except (AttributeError, KeyError, TypeError):
        return None
    _, mark, query = path.partition("?")
    return f"?{query}" if mark and query else None
