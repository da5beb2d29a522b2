"""Trusted reverse proxies: whose X-Forwarded-For, -Host and -Proto headers are believed (like uvicorn's
--forwarded-allow-ips).

    trusted = TrustedProxies.parse("127.0.0.1,10.0.0.0/8")   # `kinetix serve --trusted-proxies ...`
    scope = trusted.apply(scope)                               # an ASGI scope as the client sent it to the proxy

Anyone can send X-Forwarded-For, so by default nothing is believed and the client is the TCP peer. A request
whose peer is a trusted proxy is rewritten before any check sees it (server.web.security):
- the client address is the right-most X-Forwarded-For entry that is not itself a trusted proxy (a client that
  sends its own X-Forwarded-For only adds entries to the left of what the proxy appended);
- `Host` becomes X-Forwarded-Host (the name and port the browser used), so the Host and Origin checks compare
  what the browser saw even when the proxy sends `Host: $host` without the port;
- the scheme becomes X-Forwarded-Proto (http/https; ws/wss for websockets), for cookies' Secure flag and links.
The rate limits (server.gallery.limits) count the client address this gives.
"""

from __future__ import annotations

import dataclasses
import ipaddress
from collections.abc import Iterable

ANY = "*"


@dataclasses.dataclass(frozen=True)
class TrustedProxies:
    networks: tuple = ()
    any: bool = False

    @classmethod
    def parse(cls, names: str | Iterable[str] | None) -> TrustedProxies:
        """From `--trusted-proxies` (comma-separated addresses or networks, `*` for any); ValueError naming a bad
        entry."""
        if names is None:
            return cls()
        items = names.split(",") if isinstance(names, str) else list(names)
        networks, any_ = [], False
        for item in (i.strip() for i in items):
            if not item:
                continue
            if item == ANY:
                any_ = True
                continue
            try:
                networks.append(ipaddress.ip_network(item, strict=False))
            except ValueError:
                raise ValueError(f"--trusted-proxies: {item!r} is not an IP address or network "
                                 "(e.g. 127.0.0.1, 10.0.0.0/8, ::1)") from None
        return cls(tuple(networks), any_)

    def __bool__(self) -> bool:
        return self.any or bool(self.networks)

    def trusts(self, address: str | None) -> bool:
        if self.any:
            return True
        if not address:
            return False
        try:
            ip = ipaddress.ip_address(address.strip("[]"))
        except ValueError:
            return False  # e.g. a unix socket peer has no address
        return any(ip in network for network in self.networks)

    def apply(self, scope: dict) -> dict:
        """The scope as the proxy's client sent it, when the peer is a trusted proxy; else `scope` unchanged."""
        peer = scope.get("client")
        if not self or not self.trusts(peer[0] if peer else None):
            return scope
        headers = scope.get("headers", [])
        values: dict[bytes, str] = {}
        for key, value in headers:
            key = key.lower()
            if key in (b"x-forwarded-for", b"x-forwarded-host", b"x-forwarded-proto"):
                text = value.decode("latin-1")
                values[key] = f"{values[key]},{text}" if key in values else text  # repeated headers join
        scope = dict(scope)
        forwarded = [part.strip() for part in values.get(b"x-forwarded-for", "").split(",") if part.strip()]
        if forwarded:
            client = forwarded[0]
            for address in reversed(forwarded):
                client = address
                if not self.trusts(address):
                    break
            scope["client"] = (client, 0)
        host = values.get(b"x-forwarded-host", "").split(",")[0].strip()
        if host:
            scope["headers"] = [(k, v) for k, v in headers if k.lower() != b"host"] + [(b"host", host.encode())]
        proto = values.get(b"x-forwarded-proto", "").split(",")[0].strip().lower()
        if proto in ("http", "https"):
            secure = proto == "https"
            scope["scheme"] = ("wss" if secure else "ws") if scope["type"] == "websocket" else proto
        return scope
