"""A standalone gallery app: the API under /api, the page at /gallery and static/ at /static.

The side server (server/web/http.py) does the same with two lines:

    app.include_router(make_router(store, admin_token=os.environ.get("KINETIX_ADMIN_TOKEN")), prefix="/api")
    app.add_api_route("/gallery", gallery_page, include_in_schema=False)

Run it alone (no editor): `python -m server.gallery.app [--db URL] [--data DIR] [--port 8081]`.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterable
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from server.gallery.api import make_router
from server.gallery.limits import RateLimits, SharedRateLimits
from server.gallery.models import problem_handlers
from server.gallery.store import Store, open_store
from server.web.proxies import TrustedProxies
from server.web.security import LOCAL_HOSTS, WebSecurity, allowed_hosts_for

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"


def gallery_page() -> FileResponse:
    """GET /gallery: the gallery page (its data comes from /api)."""
    return FileResponse(STATIC_DIR / "gallery.html", media_type="text/html; charset=utf-8",
                        headers={"Cache-Control": "no-cache"})


def create_gallery_app(store: Store, admin_token: str | None = None, *, limits: RateLimits | None = None,
                       allowed_hosts: Iterable[str] = LOCAL_HOSTS,
                       trusted_proxies: TrustedProxies | None = None) -> FastAPI:
    """The gallery alone; requests must name one of `allowed_hosts` (server.web.security), writes and new
    identities are rate-limited by `limits` (default RateLimits())."""
    app = FastAPI(title="Kinetix gallery", version="1")
    app.add_middleware(WebSecurity, allowed_hosts=allowed_hosts, trusted_proxies=trusted_proxies)
    app.include_router(make_router(store, admin_token=admin_token, limits=limits), prefix="/api")
    problem_handlers(app)  # 422s as {"detail": "..."}, the API's one error shape
    app.add_api_route("/gallery", gallery_page, include_in_schema=False)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    return app


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", default=None, help="postgresql://... or a SQLite file (default: env KINETIX_DB, "
                                                   "else <data>/gallery.sqlite3)")
    parser.add_argument("--data", default=None, help="data directory (default: env KINETIX_DATA, else XDG)")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8081)
    parser.add_argument("--no-seed", action="store_true", help="do not seed an empty gallery from levels/")
    add_web_arguments(parser)
    args = parser.parse_args(argv)
    try:
        trusted = TrustedProxies.parse(args.trusted_proxies)
    except ValueError as error:
        parser.error(str(error))
    import uvicorn

    store = open_store(args.db, data_dir=args.data, **({"seed_dir": None} if args.no_seed else {}))
    app = create_gallery_app(store, os.environ.get("KINETIX_ADMIN_TOKEN"), limits=limits_from(args, store),
                             allowed_hosts=allowed_hosts_for(args.host, args.allowed_hosts),
                             trusted_proxies=trusted)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning")


def add_web_arguments(parser: argparse.ArgumentParser) -> None:
    """--allowed-hosts and the rate limits, shared by `kinetix serve` and this standalone app."""
    defaults = RateLimits()
    parser.add_argument("--allowed-hosts", type=lambda text: [h for h in text.split(",") if h.strip()],
                        default=[], metavar="NAMES",
                        help="comma-separated host names or addresses clients may use in the URL besides the --host "
                             "address, localhost and 127.0.0.1 (any port); '*' allows any (not advised: DNS "
                             "rebinding)")
    parser.add_argument("--trusted-proxies", default="", metavar="ADDRESSES",
                        help="comma-separated addresses or networks of reverse proxies whose X-Forwarded-For, -Host "
                             "and -Proto are believed; '*' any (default: none; docs/deploy.md)")
    parser.add_argument("--write-limit", type=float, default=defaults.writes_per_minute, metavar="N",
                        help="gallery writes (save, change, delete, vote) per minute per client address; 0 = no "
                             f"limit (default: {defaults.writes_per_minute:g})")
    parser.add_argument("--identity-limit", type=float, default=defaults.identities_per_hour, metavar="N",
                        help="new author or voter identities per hour per client address; 0 = no limit "
                             f"(default: {defaults.identities_per_hour:g})")


def limits_from(args: argparse.Namespace, store: Store | None = None) -> RateLimits:
    """The rate limits of the arguments: in the database when it is PostgreSQL (several processes count together),
    else in this process's memory."""
    allowances = {"writes_per_minute": args.write_limit, "identities_per_hour": args.identity_limit}
    if store is not None and store.dialect != "sqlite":
        return SharedRateLimits(store, **allowances)
    return RateLimits(**allowances)


if __name__ == "__main__":
    main()
