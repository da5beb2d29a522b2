"""How the gallery's listings are read: one SELECT of the levels with their play and vote statistics, the sort keys,
a level's listing entry, and the cursors of "next" pages. server.gallery.store runs these."""

from __future__ import annotations

import re

from sqlalchemy import Connection, and_, case, func, select

from server.gallery.checks import StoreError
from server.gallery.schema import levels_t, plays_t, tags_t, votes_t

# `<sort key>.<last id>`: every string of this shape is a cursor (the API's schema publishes the pattern, so a
# client that builds one gets a page, never an error); sort keys are counts or milliseconds, far below 10**18.
CURSOR_RE = re.compile(r"(-?[0-9]{1,18})\.([A-Za-z0-9_-]{1,32})")


def encode_cursor(key: int, level_id: str) -> str:
    return f"{key}.{level_id}"


def decode_cursor(cursor: str) -> tuple[int, str]:
    match = CURSOR_RE.fullmatch(cursor) if isinstance(cursor, str) else None
    if match is None:
        raise StoreError("cursor: not a cursor from a previous page's \"next\"")
    return int(match.group(1)), match.group(2)


def stats_subqueries(level_id: str | None = None):
    """Per-level play counts, solve counts and best record times (p), and vote counts (v); for one level if given."""
    human = plays_t.c.kind == "human"
    agent = plays_t.c.kind == "agent"
    record = and_(human, plays_t.c.solved, plays_t.c.recording_path.is_not(None))
    plays = (select(
        plays_t.c.level_id,
        func.count().label("plays"),
        func.count().filter(human).label("human_plays"),
        func.count().filter(and_(human, plays_t.c.solved)).label("human_solved"),
        func.count().filter(agent).label("agent_plays"),
        func.count().filter(and_(agent, plays_t.c.solved)).label("agent_solved"),
        # Best times come only from records: human solves whose recording server.gallery.runs verified by
        # replay and kept (recording_path set; it keeps the best one's only, the best time's play).
        func.min(case((record, plays_t.c.seconds))).label("best_human_seconds"),
        func.min(case((record, plays_t.c.steps))).label("best_human_steps"),
        func.count().filter(record).label("best_runs"),
    ).where(plays_t.c.level_id == level_id if level_id else True).group_by(plays_t.c.level_id).subquery("p"))
    votes = (select(
        votes_t.c.level_id,
        func.count().filter(votes_t.c.value > 0).label("up"),
        func.count().filter(votes_t.c.value < 0).label("down"),
    ).where(votes_t.c.level_id == level_id if level_id else True).group_by(votes_t.c.level_id).subquery("v"))
    return plays, votes

def listing(level_id: str | None = None):
    """(the SELECT of every level, or of one, with its play and vote statistics, {sort name: sort key})."""
    # For one level the aggregates are filtered inside the subqueries: SQLite does not push the outer
    # WHERE into a GROUP BY subquery, and would otherwise aggregate every play in the gallery.
    p, v = stats_subqueries(level_id)
    n = lambda col: func.coalesce(col, 0)
    human_plays, human_solved = n(p.c.human_plays), n(p.c.human_solved)
    keys = {
        "newest": levels_t.c.created,
        "top": n(v.c.up) - n(v.c.down),
        "played": n(p.c.plays),
        # Parts per million of human plays solved (an integer, so cursors compare exactly); unplayed last.
        "hardest": case((human_plays == 0, 1_000_001), else_=human_solved * 1_000_000 / human_plays),
    }
    columns = [levels_t.c.id, levels_t.c.name, levels_t.c.description, levels_t.c.author_id,
               levels_t.c.created, levels_t.c.updated, levels_t.c.parent_id, levels_t.c.size,
               n(p.c.plays).label("plays"), human_plays.label("human_plays"), human_solved.label("human_solved"),
               n(p.c.agent_plays).label("agent_plays"), n(p.c.agent_solved).label("agent_solved"),
               p.c.best_human_seconds, p.c.best_human_steps, n(v.c.up).label("up"), n(v.c.down).label("down"),
               n(p.c.best_runs).label("best_runs")]
    base = (select(*columns).select_from(levels_t.outerjoin(p, p.c.level_id == levels_t.c.id)
                                         .outerjoin(v, v.c.level_id == levels_t.c.id)))
    return base, keys

def tags_of(conn: Connection, ids: list[str]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {i: [] for i in ids}
    if ids:
        for row in conn.execute(select(tags_t.c.level_id, tags_t.c.tag).where(tags_t.c.level_id.in_(ids))
                                .order_by(tags_t.c.tag)):
            out[row.level_id].append(row.tag)
    return out

def summary(row, tags: list[str]) -> dict:
    """A level's listing entry (the API's JSON) from a row of `listing`."""
    rate = lambda solved, plays: (solved / plays) if plays else None
    return {
        "id": row.id, "name": row.name, "description": row.description,
        "author": row.author_id, "created": row.created, "updated": row.updated, "parent": row.parent_id,
        "size": row.size, "tags": tags,
        "stats": {
            "plays": int(row.plays), "human_plays": int(row.human_plays), "human_solved": int(row.human_solved),
            "human_solve_rate": rate(row.human_solved, row.human_plays),
            "agent_plays": int(row.agent_plays), "agent_solved": int(row.agent_solved),
            "agent_solve_rate": rate(row.agent_solved, row.agent_plays),
            "best_human_seconds": row.best_human_seconds,
            "best_human_steps": None if row.best_human_steps is None else int(row.best_human_steps),
            "has_best_run": int(row.best_runs) > 0,
            "votes_up": int(row.up), "votes_down": int(row.down), "score": int(row.up) - int(row.down),
        },
    }
