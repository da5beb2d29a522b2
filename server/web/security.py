"""Web safety for the side server and the standalone gallery: one ASGI middleware in front of every route.

    app.add_middleware(WebSecurity, allowed_hosts=allowed_hosts_for("127.0.0.1", ["kinetix.local"]))

- **Trusted proxies** (server.web.proxies): from a proxy named with --trusted-proxies, X-Forwarded-For, -Host and
  -Proto replace the peer address, Host and scheme before the checks below (from anyone else they are ignored).
- **Host check** (DNS rebinding): a request whose `Host` header names no allowed host gets 400 (a websocket is
  refused before it opens). Without it a page on `evil.example` whose name later resolves to 127.0.0.1 could read
  and write the gallery of a server on the user's laptop.
- **Origin check** (cross-site requests): a state-changing request (POST, PUT, PATCH, DELETE) or a websocket whose
  `Origin` header is present but is not this server's own origin (scheme-less `host:port` equal to `Host`) gets
  403. Browsers always send `Origin` with these; non-browser clients (curl, scripts) send none and pass.
- **Headers** on every HTTP answer (pages, static files, the API): `X-Content-Type-Options: nosniff`, a
  Content-Security-Policy whose `frame-ancestors 'self'` stops other sites framing the app (clickjacking), the same
  as `X-Frame-Options` for old browsers, and `Referrer-Policy: same-origin`. FastAPI's /docs and /redoc pages get a
  policy that also allows the CDNs they load from.

The CSP fits viser's page: its loader is an inline script that decompresses the client with WebAssembly and adds it
as an inline module, and the client uses blob: workers and data:/blob: images. Its websocket and /keys are on the
page's own origin (the side server relays viser's websocket, server/web/http.py), so connect-src is 'self' (which
covers ws:/wss: to the same host and port). tests/e2e checks the page still loads.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

from server.web.proxies import TrustedProxies

UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")
ANY_HOST = "*"

CONTENT_SECURITY_POLICY = "; ".join([
    "default-src 'self'",
    "script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval' blob:",
    "style-src 'self' 'unsafe-inline'",
    "img-src 'self' data: blob:",
    "font-src 'self' data:",
    "connect-src 'self' data: blob:",
    "worker-src 'self' blob:",
    "object-src 'none'",
    "base-uri 'self'",
    "form-action 'self'",
    "frame-ancestors 'self'",
])
# viser's page (the editor at /) only: viser 1.1.1's client holds an Emscripten (embind) module, its splat sorter,
# which builds its class constructors with `new Function(...)` as the client loads. Without 'unsafe-eval' every
# load threw an uncaught EvalError (31 of 31 loads, issue 37); nothing of ours evaluates strings. The gallery page,
# the API and the static files keep the policy above.
VISER_PAGE_CONTENT_SECURITY_POLICY = CONTENT_SECURITY_POLICY.replace(
    "'wasm-unsafe-eval'", "'unsafe-eval' 'wasm-unsafe-eval'")
# FastAPI's /docs (Swagger UI) and /redoc pages load their code, styles, fonts and icon from public CDNs.
DOCS_PATHS = ("/docs", "/docs/oauth2-redirect", "/redoc")
DOCS_CONTENT_SECURITY_POLICY = "; ".join([
    "default-src 'self'",
    "script-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net",
    "style-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net https://fonts.googleapis.com",
    "font-src 'self' data: https://fonts.gstatic.com",
    "img-src 'self' data: https://fastapi.tiangolo.com https://cdn.redoc.ly",
    "worker-src 'self' blob:",
    "object-src 'none'",
    "base-uri 'self'",
    "frame-ancestors 'self'",
])
COMMON_HEADERS = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"SAMEORIGIN"),
    (b"referrer-policy", b"same-origin"),
]
SECURITY_HEADERS = [*COMMON_HEADERS, (b"content-security-policy", CONTENT_SECURITY_POLICY.encode())]
DOCS_HEADERS = [*COMMON_HEADERS, (b"content-security-policy", DOCS_CONTENT_SECURITY_POLICY.encode())]


def allowed_hosts_for(bind: str, extra: Iterable[str] | None = None) -> frozenset[str]:
    """The host names a server bound to `bind` answers to: the bind address, localhost, 127.0.0.1 and ::1 (any port),
    plus `extra` (e.g. `--allowed-hosts kinetix.lan,192.168.1.20`; `*` allows any host)."""
    hosts = {h.lower() for h in LOCAL_HOSTS}
    if bind and bind not in ("0.0.0.0", "::"):  # a wildcard bind is not a name a client sends
        hosts.add(bind.strip("[]").lower())
    for name in extra or ():
        name = name.strip().lower()
        if name:
            hosts.add(name if name == ANY_HOST else split_host(name)[0])
    return frozenset(hosts)


def split_host(value: str) -> tuple[str, str]:
    """`host[:port]` -> (host lowercased, port or ""), for names, IPv4 and bracketed IPv6 (`[::1]:8080`)."""
    value = value.strip().lower()
    if value.startswith("["):
        host, _, rest = value[1:].partition("]")
        return host, rest[1:] if rest.startswith(":") else ""
    if value.count(":") == 1:
        host, _, port = value.partition(":")
        return host, port
    return value, ""  # a bare name, or a bare IPv6 address


def origin_matches(origin: str, host_header: str) -> bool:
    """Whether an `Origin` header (`scheme://host[:port]`) names the server that `Host` reached."""
    scheme, sep, rest = origin.partition("://")
    if not sep or scheme not in ("http", "https") or "/" in rest:
        return False  # e.g. "null" (a sandboxed frame or a file: page)
    default = "443" if scheme == "https" else "80"
    o_host, o_port = split_host(rest)
    h_host, h_port = split_host(host_header)
    return o_host == h_host and (o_port or default) == (h_port or default)


class WebSecurity:
    """ASGI middleware: Host and Origin checks, security headers (see the module docstring)."""

    def __init__(self, app, allowed_hosts: Iterable[str] = LOCAL_HOSTS, trusted_proxies: TrustedProxies | None = None):
        self.app = app
        self.allowed_hosts = frozenset(h.lower() for h in allowed_hosts)
        self.trusted_proxies = trusted_proxies or TrustedProxies()

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        scope = self.trusted_proxies.apply(scope)  # a trusted proxy's X-Forwarded-* first: the checks use them
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        host = headers.get("host", "")
        problem = None
        if ANY_HOST not in self.allowed_hosts and (not host or split_host(host)[0] not in self.allowed_hosts):
            status, problem = 400, (f"host {host[:100]!r} is not served here: start the server with "
                                    "--allowed-hosts NAME to allow it")
        elif "origin" in headers and (scope["type"] == "websocket" or scope.get("method") in UNSAFE_METHODS) \
                and not origin_matches(headers["origin"], host):
            status, problem = 403, f"cross-site request refused: Origin {headers['origin'][:100]!r} is not this server"
        if problem is not None:
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": problem[:120]})
                return
            await _answer(send, status, problem)
            return
        if scope["type"] == "websocket":
            await self.app(scope, receive, send)
            return

        path, root = scope.get("path", ""), scope.get("root_path", "")
        extra = DOCS_HEADERS if (path[len(root):] if root and path.startswith(root) else path) in DOCS_PATHS \
            else SECURITY_HEADERS

        async def send_with_headers(message) -> None:
            if message["type"] == "http.response.start":
                present = {k.lower() for k, _ in message.get("headers", [])}
                message["headers"] = list(message.get("headers", [])) + [
                    (k, v) for k, v in extra if k not in present]
            await send(message)

        await self.app(scope, receive, send_with_headers)


async def _answer(send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *SECURITY_HEADERS]})
    await send({"type": "http.response.body", "body": body})
