"""The gallery API's contract: the request and answer models, and every error each route can answer
(server.gallery.api uses them; /openapi.json publishes them).

The request models are what the server enforces, not a description beside it: a body is read by hand (size limit
first, server.gallery.api.read_json) and then validated with its model, strict (JSON types, no coercion) and
with no other fields (additionalProperties false), before the store's own checks. Every error is
`{"detail": "what is wrong"}` (`Problem`), 422 included: FastAPI's own list-shaped validation errors are turned
into that one string (`problem_handlers`).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.routing import Match

from server.gallery.checks import MAX_DESCRIPTION, MAX_NAME, MAX_TAGS

NAME_PATTERN = r"^[^\x00]*[^\s\x00][^\x00]*$"  # something besides whitespace (Python's, as str.strip), no NUL
TEXT_PATTERN = r"^[^\x00]*$"
TAG_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$"
ID_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"
CURSOR_PATTERN = r"^-?[0-9]{1,18}\.[A-Za-z0-9_-]{1,32}$"  # server.gallery.queries.encode_cursor


class Problem(BaseModel):
    detail: str = Field(description="what is wrong, for a person to read")


ERRORS = {
    400: "invalid JSON, or a Host the server does not answer to (start it with --allowed-hosts)",
    401: "missing, malformed or unknown token",
    403: "a token that does not own the level, a vote from an identity that has not played the level, or a "
         "write whose Origin is another site",
    404: "no level with this id",
    413: "body over 1 MB",
    415: "body not sent as Content-Type: application/json",
    422: "a parameter or body field that breaks its schema, or a level that does not load",
    429: "over a rate limit (Retry-After says when to try again)",
    503: "the gallery is being prepared at start-up (Retry-After says when to try again)",
}
ALWAYS = (400, 422, 503)  # any route: the Host check, parameter validation, the start-up seeding
WRITE = (403, 413, 415, 429)  # routes with a JSON body (the Origin check, the body's limits, the rate limits)


def errors(*codes: int) -> dict:
    """The `responses=` of a route that can answer these codes (plus ALWAYS), each a Problem."""
    return {code: {"model": Problem, "description": ERRORS[code]} for code in sorted({*ALWAYS, *codes})}


def problem_text(error: ValidationError | RequestValidationError, prefix: tuple = ()) -> str:
    """Pydantic's errors as one line: `name: String should have at least 1 character; tags.0: ...`."""
    parts = []
    for item in error.errors():
        where = ".".join(str(part) for part in (*prefix, *item.get("loc", ()))
                         if part not in ("body", "query", "path"))
        parts.append(f"{where}: {item.get('msg', 'invalid')}" if where else str(item.get("msg", "invalid")))
    return "; ".join(parts)[:1000] or "invalid request"


async def _validation_problem(request: Request, error: RequestValidationError) -> JSONResponse:
    return JSONResponse({"detail": problem_text(error)}, status_code=422)


async def _method_problem(request: Request, error) -> JSONResponse:
    """405 with `Allow` naming every method of the path: Starlette names only those of the first route matching the
    path (GET /api/levels and POST /api/levels are two routes), and a client reads Allow to know what it may do."""
    allowed = set()
    for route in request.app.routes:
        match, _ = route.matches(request.scope) if hasattr(route, "methods") else (Match.NONE, None)
        if match != Match.NONE:
            allowed |= set(route.methods or ())
    if "GET" in allowed:
        allowed.add("HEAD")
    methods = ", ".join(sorted(allowed))
    return JSONResponse({"detail": f"method {request.method} is not allowed here: use {methods}"},
                        status_code=405, headers={"Allow": methods})


def problem_handlers(app) -> None:
    """Make FastAPI's own 422s (query and path parameters) `{"detail": "..."}` like every other error, and 405s
    name every allowed method."""
    app.add_exception_handler(RequestValidationError, _validation_problem)
    app.add_exception_handler(405, _method_problem)


class Stats(BaseModel):
    plays: int
    human_plays: int
    human_solved: int
    human_solve_rate: float | None
    agent_plays: int
    agent_solved: int
    agent_solve_rate: float | None
    best_human_seconds: float | None
    best_human_steps: int | None
    has_best_run: bool = Field(description="a recording of the best human solve can be downloaded from "
                                           "/api/levels/{id}/best-run.mcap")
    votes_up: int
    votes_down: int
    score: int


class LevelSummary(BaseModel):
    id: str
    name: str
    description: str
    author: str | None = Field(description="public author id (derived from the token; never the token)")
    created: int = Field(description="milliseconds since the Unix epoch")
    updated: int
    parent: str | None = Field(description="the level this one remixes")
    size: Literal["s", "m", "l", "xl"]
    tags: list[str]
    stats: Stats
    thumbnail: str = Field(description="URL of the PNG thumbnail")


class LevelDetail(LevelSummary):
    level: dict[str, Any] = Field(description="the level in our format (docs/level-format.md)")


class LevelPage(BaseModel):
    items: list[LevelSummary]
    next: str | None = Field(description="cursor of the next page, null on the last page")


Name = Annotated[str, Field(min_length=1, max_length=MAX_NAME, pattern=NAME_PATTERN,
                            description="1-100 characters, not only spaces, no NUL")]
Description = Annotated[str, Field(max_length=MAX_DESCRIPTION, pattern=TEXT_PATTERN,
                                   description="at most 2000 characters, no NUL")]
Tags = Annotated[list[Annotated[str, Field(pattern=TAG_PATTERN)]],
                 Field(max_length=MAX_TAGS, description="at most 10 tags of 1-32 letters, digits, '-' or '_' "
                                                        "(stored lowercase)")]
LevelDocument = Annotated[dict[str, Any], Field(description="a level in our format or the public Kinetix format "
                                                            "(docs/level-format.md); one that does not load, has a "
                                                            "number out of its range or is over its size class is "
                                                            "refused with 422 and the loader's message")]


class Body(BaseModel):
    """A request body: exactly these fields (additionalProperties false), JSON types only (no coercion)."""

    model_config = ConfigDict(extra="forbid", strict=True)


class CreateBody(Body):
    name: Name
    description: Description = ""
    tags: Tags = []
    level: LevelDocument
    parent: Annotated[str, Field(pattern=ID_PATTERN, description="id of the level this remixes")] | None = None


class UpdateBody(Body):
    name: Name | None = None
    description: Description | None = None
    tags: Tags | None = None
    level: LevelDocument | None = None


class Created(BaseModel):
    id: str
    author_token: str | None = Field(description="a new secret author token, only when the request sent none")


class VoteBody(Body):
    value: Literal[-1, 0, 1] = Field(description="1 up, -1 down, 0 withdraws the vote")


class VoteResult(BaseModel):
    up: int
    down: int
    score: int
    value: int


class Ok(BaseModel):
    ok: bool


def _body_doc(model: type[BaseModel]) -> dict:
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": model.model_json_schema()}}}}


