"""A standalone gallery app: the API under /api, the page at /gallery and static/ at /static.

The side server (server/http.py) does the same with two lines:

    app.include_router(make_router(store, admin_token=os.environ.get("KINETIX_ADMIN_TOKEN")), prefix="/api")
    app.add_api_route("/gallery", gallery_page, include_in_schema=False)

Run it alone (no editor): `python -m server.gallery.app [--db URL] [--data DIR] [--port 8081]`.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from server.gallery.api import make_router
from server.gallery.store import Store, open_store

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"


def gallery_page() -> FileResponse:
    """GET /gallery: the gallery page (its data comes from /api)."""
    return FileResponse(STATIC_DIR / "gallery.html", media_type="text/html; charset=utf-8",
                        headers={"Cache-Control": "no-cache"})


def create_gallery_app(store: Store, admin_token: str | None = None) -> FastAPI:
    app = FastAPI(title="Kinetix gallery", version="1")
    app.include_router(make_router(store, admin_token=admin_token), prefix="/api")
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
    args = parser.parse_args(argv)
    import uvicorn

    store = open_store(args.db, data_dir=args.data, **({"seed_dir": None} if args.no_seed else {}))
    uvicorn.run(create_gallery_app(store, os.environ.get("KINETIX_ADMIN_TOKEN")), host=args.host, port=args.port,
                log_level="warning")


if __name__ == "__main__":
    main()
