"""Serving the app under a path (`kinetix serve --root-path /kinetix/`) behind a proxy that forwards that path.

    app = UnderPath(app, "/kinetix/")

The proxy forwards `/kinetix/...` as it is (nginx: `proxy_pass http://kinetix;` without a URI, docs/deploy.md).
Requests under the prefix reach the app with ASGI's `root_path` set to it (Starlette routes on the rest and builds
URLs with it); a GET of the bare prefix (`/kinetix`) is redirected to `/kinetix/`, except viser's websocket, which
the client opens at the page's path without its trailing slash, so it is routed to `/`. Anything else is 404: one
server answers for one prefix. The page's scripts, links and API calls are relative to the page, so they follow.
"""

from __future__ import annotations

import json

from server.web.security import SECURITY_HEADERS


def normalise(root_path: str) -> str:
    """'/kinetix/' or 'kinetix' -> '/kinetix'; '' or '/' -> ''. ValueError for a path with odd characters."""
    parts = [part for part in root_path.strip().split("/") if part]
    for part in parts:
        if part in (".", "..") or not all(c.isalnum() or c in "-_.~" for c in part):
            raise ValueError(f"--root-path: {root_path!r} must be a plain path such as /kinetix/")
    return "/" + "/".join(parts) if parts else ""


class UnderPath:
    """ASGI wrapper: the app answers under `root_path` only (see the module docstring)."""

    def __init__(self, app, root_path: str):
        self.app = app
        self.prefix = normalise(root_path)

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] not in ("http", "websocket") or not self.prefix:
            await self.app(scope, receive, send)
            return
        path = scope["path"]
        if path == self.prefix and scope["type"] == "websocket":
            path = self.prefix + "/"
        elif path == self.prefix:
            query = scope.get("query_string", b"").decode("latin-1")
            target = self.prefix + "/" + (f"?{query}" if query else "")
            await _answer(send, 308, {"detail": f"moved to {target}"}, [(b"location", target.encode("latin-1"))])
            return
        if not path.startswith(self.prefix + "/"):
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": "not served here"})
                return
            await _answer(send, 404, {"detail": f"not found: this server answers under {self.prefix}/"})
            return
        scope = dict(scope, path=path, root_path=scope.get("root_path", "") + self.prefix)
        await self.app(scope, receive, send)


async def _answer(send, status: int, body: dict, headers: list | None = None) -> None:
    data = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode()),
                            *SECURITY_HEADERS, *(headers or [])]})
    await send({"type": "http.response.body", "body": data})
