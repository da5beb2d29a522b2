"""The gallery's HTTP API: a FastAPI router the side server includes under /api.

    app.include_router(make_router(store, admin_token=os.environ.get("KINETIX_ADMIN_TOKEN")), prefix="/api")

Request bodies are read by hand, not by FastAPI's body parameters, so the 1 MB limit is enforced before
anything is parsed; their schemas are still published in the OpenAPI description. Every error is a 4xx
JSON `{"detail": "what is wrong"}` and stores nothing. Store calls block, so they run in the thread pool.

Cross-site and abuse rules: a body must be `Content-Type: application/json` (415 otherwise), so a page on another
site cannot send one with a "simple" form or text/plain request (server.web.security checks `Origin` too); writes
and new identities are rate-limited per client (429 with Retry-After, server.gallery.limits); play statistics are
not accepted from clients at all: the server records the plays it ran itself (`Store.record_play`, from
server.play.gallery_tab). A vote counts only from an identity that played the level in such a play (its tab's
author token), once per level.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response
from pydantic import BaseModel, ValidationError
from starlette.concurrency import run_in_threadpool

from server.gallery.checks import (
    SIZES,
    SORTS,
    Invalid,
    StoreError,
    check_admin,
    check_description,
    check_name,
    check_tags,
    check_unicode,
)
from server.gallery.limits import RateLimited, RateLimits
from server.gallery.models import (
    CURSOR_PATTERN,
    ID_PATTERN,
    TEXT_PATTERN,
    WRITE,
    CreateBody,
    Created,
    LevelDetail,
    LevelPage,
    Ok,
    Stats,
    UpdateBody,
    VoteBody,
    VoteResult,
    errors,
    problem_text,
)
from server.gallery.runs import BestRuns
from server.gallery.store import Store

MAX_BODY = 1_000_000  # bytes
LevelId = Annotated[str, Path(pattern=ID_PATTERN, max_length=32, description="a level's id")]
VOTER_COOKIE = "kinetix_voter"  # a voter token earlier versions issued (HttpOnly); still read, no longer issued


def _check_level(level: Any) -> None:
    if not isinstance(level, dict):
        raise Invalid(f"level: expected a JSON object in our format or the Kinetix format, got {type(level).__name__}")


def _check_parent(parent: Any) -> None:
    if not isinstance(parent, str):
        raise Invalid("parent: expected a level id string or null")
    check_unicode("parent", parent)


FIELD_CHECKS = {"name": check_name, "description": check_description, "tags": check_tags, "level": _check_level,
                "parent": _check_parent}


def _body_doc(model: type[BaseModel]) -> dict:
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": model.model_json_schema()}}}}


async def read_json(request: Request, model: type[BaseModel]) -> dict[str, Any]:
    """The request body as a JSON object, at most MAX_BODY bytes, valid for `model` (server.gallery.models: its
    fields only, their types and limits); the fields it sent. Raises 415 / 413 / 400 / 422 before anything is
    stored."""
    fields = {name: info.is_required() for name, info in model.model_fields.items()}
    media_type = request.headers.get("content-type", "").partition(";")[0].strip().lower()
    if media_type != "application/json":
        raise HTTPException(415, f"body must be sent as Content-Type: application/json, got {media_type[:80]!r}"
                            if media_type else "body must be sent as Content-Type: application/json")
    declared = request.headers.get("content-length")
    if declared is not None and (not declared.isdigit() or int(declared) > MAX_BODY):
        raise HTTPException(413, f"request body over {MAX_BODY} bytes")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > MAX_BODY:
            raise HTTPException(413, f"request body over {MAX_BODY} bytes")
        chunks.append(chunk)
    try:
        data = json.loads(b"".join(chunks))
    except (ValueError, RecursionError) as error:
        raise HTTPException(400, f"body is not valid JSON: {error}"[:300]) from None
    if not isinstance(data, dict):
        raise HTTPException(422, "body: expected a JSON object")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise HTTPException(422, f"body: unknown fields {', '.join(map(repr, unknown))[:200]}; "
                                 f"allowed: {', '.join(fields)}")
    missing = [name for name, required in fields.items() if required and name not in data]
    if missing:
        raise HTTPException(422, f"body: missing fields {', '.join(missing)}")
    try:
        for name, value in data.items():  # the store's own checks first: their messages say more
            if value is not None and name in FIELD_CHECKS:
                FIELD_CHECKS[name](value)
        model.model_validate(data)
    except StoreError as error:
        raise HTTPException(error.status, error.message) from None
    except ValidationError as error:
        raise HTTPException(422, problem_text(error)) from None
    return data


def bearer(request: Request) -> str | None:
    header = request.headers.get("authorization")
    if header is None:
        return None
    scheme, _, token = header.partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token or len(token) > 200:
        raise HTTPException(401, "malformed Authorization header: expected 'Bearer TOKEN'")
    return token


async def call(function, *args, **kwargs):
    """Run a blocking store call in the thread pool, turning its errors into HTTP errors."""
    try:
        return await run_in_threadpool(function, *args, **kwargs)
    except StoreError as error:
        raise HTTPException(error.status, error.message) from None
    except UnicodeEncodeError:  # a safety net: the store rejects lone surrogates itself, naming the field
        raise HTTPException(422, "text must be valid Unicode (no lone UTF-16 surrogates)") from None


def client_key(request: Request) -> str:
    """Whom a rate limit counts: the peer address (see server.gallery.limits about proxies)."""
    return request.client.host if request.client is not None else "unknown"


def limited(limits: RateLimits, kind: str, request: Request) -> None:
    try:
        limits.take(kind, client_key(request))
    except RateLimited as error:
        raise HTTPException(429, str(error), headers={"Retry-After": str(error.retry_after)}) from None


def _public_vote(result: dict) -> dict:
    """A vote's answer without the voter's token: a browser keeps it only in the HttpOnly cookie."""
    return {key: result[key] for key in ("up", "down", "score", "value")}


def _with_thumbnail(item: dict, request: Request) -> dict:
    """The summary with its thumbnail's URL (under the server's --root-path, server.web.prefix)."""
    root = request.scope.get("root_path", "")
    item["thumbnail"] = f"{root}/api/levels/{item['id']}/thumbnail.png?v={item['updated']}"
    return item


PREPARING_RETRY_S = 2  # a new gallery's seeding takes ~2-13 s (a thumbnail per project level)


def make_router(store: Store, admin_token: str | None = None, limits: RateLimits | None = None,
                ready: Callable[[], bool] | None = None) -> APIRouter:
    """The gallery API on `store`; `admin_token` (e.g. env KINETIX_ADMIN_TOKEN) may update or delete any level;
    `limits` caps writes and new identities per client (default: RateLimits()). Until `ready()` is true (a new
    gallery being seeded by `kinetix serve`'s warm-up) every route answers 503 with Retry-After, never an empty
    gallery."""

    def check_ready() -> None:
        if ready is not None and not ready():
            raise HTTPException(503, f"the gallery is being prepared: try again in {PREPARING_RETRY_S} s",
                                headers={"Retry-After": str(PREPARING_RETRY_S)})

    router = APIRouter(tags=["gallery"], dependencies=[Depends(check_ready)])
    limits = limits if limits is not None else RateLimits()

    def user_token(request: Request) -> str | None:
        token = bearer(request)
        if token is not None and check_admin(token, admin_token):
            raise HTTPException(401, "the admin token can update and delete levels but not author or vote")
        return token

    @router.get("/levels", response_model=LevelPage, summary="List levels, one page at a time", responses=errors())
    async def list_levels(
        request: Request,
        sort: Literal["newest", "top", "played", "hardest"] = Query("newest", description=", ".join(SORTS)),
        size: Literal["s", "m", "l", "xl"] | None = Query(None, description="size class: " + ", ".join(SIZES)),
        tag: str | None = Query(None, max_length=32, pattern=TEXT_PATTERN),
        q: str | None = Query(None, max_length=100, pattern=TEXT_PATTERN,
                              description="search the name (case-insensitive)"),
        author: str | None = Query(None, max_length=16, pattern=TEXT_PATTERN),
        limit: int = Query(24, ge=1, le=100),
        cursor: str | None = Query(None, max_length=60, pattern=CURSOR_PATTERN,
                                   description="the previous page's `next`"),
    ) -> dict:
        items, nxt = await call(store.list_levels, sort=sort, size=size, tag=tag, q=q, author=author, limit=limit,
                                cursor=cursor)
        return {"items": [_with_thumbnail(i, request) for i in items], "next": nxt}

    @router.post("/levels", response_model=Created, status_code=201, openapi_extra=_body_doc(CreateBody),
                 summary="Save a new level (a new author token is returned when none is sent)",
                 responses=errors(401, *WRITE))
    async def create_level(request: Request) -> dict:
        limited(limits, "write", request)
        token = user_token(request)
        data = await read_json(request, CreateBody)
        if token is None:
            limited(limits, "identity", request)  # a new author
        level_id, new_token = await call(store.create_level, data["name"], data["level"],
                                         description=data.get("description", ""), tags=data.get("tags", []),
                                         token=token, parent=data.get("parent"))
        return {"id": level_id, "author_token": new_token}

    @router.get("/levels/{level_id}", response_model=LevelDetail, summary="One level: metadata, stats, level",
                responses=errors(404))
    async def get_level(level_id: LevelId, request: Request) -> dict:
        return _with_thumbnail(await call(store.get_level, level_id), request)

    @router.get("/levels/{level_id}/thumbnail.png", response_class=Response, summary="The level's PNG thumbnail",
                responses={200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}},
                           **errors(404)})
    async def thumbnail(level_id: LevelId) -> Response:
        png = await call(store.thumbnail, level_id)
        # The listing links with ?v=<updated>, so a cached image is never stale.
        return Response(png, media_type="image/png", headers={"Cache-Control": "public, max-age=86400"})

    @router.put("/levels/{level_id}", response_model=Ok, openapi_extra=_body_doc(UpdateBody),
                summary="Change a level (Authorization: Bearer <author or admin token>)",
                responses=errors(401, 404, *WRITE))
    async def update_level(level_id: LevelId, request: Request) -> dict:
        limited(limits, "write", request)
        token = bearer(request)
        admin = check_admin(token, admin_token)
        if token is None:
            raise HTTPException(401, "this needs the author's token: send Authorization: Bearer TOKEN")
        await call(store.thumbnail, level_id)  # 404 before reading a body for an unknown id
        data = await read_json(request, UpdateBody)
        await call(store.update_level, level_id, None if admin else token, admin=admin, **data)
        return {"ok": True}

    @router.delete("/levels/{level_id}", response_model=Ok,
                   summary="Delete a level (Authorization: Bearer <author or admin token>)",
                   responses=errors(401, 403, 404, 429))
    async def delete_level(level_id: LevelId, request: Request) -> dict:
        limited(limits, "write", request)
        token = bearer(request)
        admin = check_admin(token, admin_token)
        await call(store.delete_level, level_id, None if admin else token, admin=admin)
        return {"ok": True}

    @router.post("/levels/{level_id}/vote", response_model=VoteResult, openapi_extra=_body_doc(VoteBody),
                 summary="Vote +1, -1 or 0 (withdraw); one vote per identity per level, and only from an identity "
                         "that played the level in the browser (the Bearer author token the tab keeps, or an "
                         "older kinetix_voter cookie)", responses=errors(401, 404, *WRITE))
    async def vote(level_id: LevelId, request: Request) -> dict:
        limited(limits, "write", request)
        token = user_token(request)
        data = await read_json(request, VoteBody)
        value = data["value"]
        if not isinstance(value, int) or isinstance(value, bool) or value not in (-1, 0, 1):
            raise HTTPException(422, "value: expected 1 (up), -1 (down) or 0 (withdraw)")
        if token is None:
            cookie = request.cookies.get(VOTER_COOKIE)  # issued by earlier versions; now the tab's token votes
            token = cookie if cookie and len(cookie) <= 200 else None
        if token is None:
            await call(store.thumbnail, level_id)  # 404 for an unknown level first
        return _public_vote(await call(store.vote, level_id, token, value))

    @router.get("/levels/{level_id}/stats", response_model=Stats, summary="Plays, solve rates, best time, votes",
                responses=errors(404))
    async def stats(level_id: LevelId) -> dict:
        return await call(store.stats, level_id)

    runs = BestRuns(store) if store.recordings_dir is not None else None

    @router.get("/levels/{level_id}/best-run.mcap", response_class=Response,
                summary="The MCAP recording of the level's best human solve (docs/recording.md)",
                responses={200: {"content": {"application/octet-stream": {"schema": {"type": "string",
                                                                                     "format": "binary"}}}},
                           **errors(404)})
    async def best_run(level_id: LevelId) -> Response:
        await call(store.thumbnail, level_id)  # 404 for an unknown id
        path = await call(runs.best_run_file, level_id) if runs is not None else None
        if path is None:
            raise HTTPException(404, f"level {level_id!r} has no recorded best run yet: solve it in the browser")
        try:
            data = await run_in_threadpool(path.read_bytes)
        except FileNotFoundError:  # superseded between the lookup and the read
            raise HTTPException(404, f"level {level_id!r} has no recorded best run yet") from None
        return Response(data, media_type="application/octet-stream", headers={
            "Content-Disposition": f'attachment; filename="best-run-{level_id}.mcap"', "Cache-Control": "no-store"})

    return router
