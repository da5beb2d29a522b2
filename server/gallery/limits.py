"""Rate limits for the gallery API: an in-process token bucket per client and kind of action.

    limits = RateLimits(writes_per_minute=60, identities_per_hour=10)
    limits.take("write", client_key)        # raises RateLimited(retry_after seconds) when the bucket is empty

    limits = SharedRateLimits(store, writes_per_minute=60)   # the buckets in the gallery database

A bucket holds up to one period's allowance (so a burst of that size passes at once) and refills continuously.
The client key is the client's address: the TCP peer, or behind a trusted reverse proxy the address it forwards
(server.web.proxies: X-Forwarded-For is believed only from the addresses given with --trusted-proxies).
`RateLimits` counts in this process's memory (one process: no set-up). `SharedRateLimits` keeps the buckets in the
gallery database's `rate_buckets` table, one row per (kind, client) updated under a row lock, so several processes
on one PostgreSQL gallery (docs/deploy.md) count together; its clock is the wall clock, the same on every host
that keeps NTP time.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time

from sqlalchemy import delete, select, text, update

from server.gallery.schema import rate_buckets_t

MAX_TRACKED_CLIENTS = 10_000  # beyond this, full buckets (idle clients) are forgotten


class RateLimited(Exception):
    def __init__(self, what: str, retry_after: int):
        super().__init__(f"too many {what}: try again in {retry_after} s")
        self.retry_after = retry_after


@dataclasses.dataclass
class _Bucket:
    tokens: float
    stamp: float


@dataclasses.dataclass
class RateLimits:
    """Allowances per client; 0 turns a limit off. The defaults are far above what a person clicking does:
    a vote or a save is a click, and a browser keeps one voter identity (a cookie) for a year."""

    writes_per_minute: float = 60.0  # POST, PUT and DELETE on /api
    identities_per_hour: float = 10.0  # new author or voter identities (a request without a token)

    def __post_init__(self) -> None:
        for field in ("writes_per_minute", "identities_per_hour"):
            value = getattr(self, field)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"{field}: expected a number >= 0 (0 = no limit), got {value!r}")
        self._lock = threading.Lock()
        self._buckets: dict[tuple[str, str], _Bucket] = {}

    def _rule(self, kind: str) -> tuple[str, float, float]:
        """(what it counts, capacity, tokens per second) of a kind of action."""
        if kind == "write":
            return "writes", self.writes_per_minute, self.writes_per_minute / 60
        if kind == "identity":
            return "new identities", self.identities_per_hour, self.identities_per_hour / 3600
        raise ValueError(f"unknown rate limit {kind!r}")

    def take(self, kind: str, client: str) -> None:
        """Spend one token of `client`'s `kind` bucket, or raise RateLimited with the seconds until one is back."""
        what, capacity, rate = self._rule(kind)
        if capacity <= 0:
            return
        now = time.monotonic()
        with self._lock:
            bucket = self._buckets.get((kind, client))
            if bucket is None:
                if len(self._buckets) >= MAX_TRACKED_CLIENTS:
                    self._forget_idle(now)
                bucket = self._buckets[(kind, client)] = _Bucket(capacity, now)
            bucket.tokens = min(capacity, bucket.tokens + (now - bucket.stamp) * rate)
            bucket.stamp = now
            bucket.tokens = _spend(what, bucket.tokens, rate)

    def _forget_idle(self, now: float) -> None:
        for key, bucket in list(self._buckets.items()):
            _, capacity, rate = self._rule(key[0])
            if bucket.tokens + (now - bucket.stamp) * rate >= capacity:
                del self._buckets[key]


def _spend(what: str, tokens: float, rate: float) -> float:
    """The tokens left after spending one, or RateLimited with the seconds until one is back."""
    if tokens < 1:
        raise RateLimited(what, max(1, math.ceil((1 - tokens) / rate)))
    return tokens - 1


CLIENT_KEY_CHARS = 64  # the column's width: an IPv6 address is at most 45 characters
SWEEP_EVERY_S = 60.0  # how often one process removes full (idle) buckets from the table


class SharedRateLimits(RateLimits):
    """RateLimits whose buckets live in the gallery database (table rate_buckets), shared by every process on it."""

    def __init__(self, store, **allowances):
        super().__init__(**allowances)
        self.store = store
        self._swept = 0.0

    def take(self, kind: str, client: str) -> None:
        what, capacity, rate = self._rule(kind)
        if capacity <= 0:
            return
        client = client[:CLIENT_KEY_CHARS]
        now = time.time()
        with self.store._write() as conn:
            # Insert a full bucket unless one is there, then lock the row: two processes spending at once queue on
            # the lock (SQLite's BEGIN IMMEDIATE serialises the whole transaction instead).
            conn.execute(text("INSERT INTO rate_buckets (kind, client, tokens, stamp) VALUES (:k, :c, :t, :s) "
                              "ON CONFLICT (kind, client) DO NOTHING"),
                         {"k": kind, "c": client, "t": float(capacity), "s": now})
            row = conn.execute(select(rate_buckets_t.c.tokens, rate_buckets_t.c.stamp)
                               .where(rate_buckets_t.c.kind == kind, rate_buckets_t.c.client == client)
                               .with_for_update()).one()
            stamp = max(now, row.stamp)  # a host whose clock is behind never refills a bucket backwards
            tokens = min(capacity, row.tokens + (stamp - row.stamp) * rate)
            left = _spend(what, tokens, rate)  # refused: the transaction rolls back, the stamp stays (same refill)
            conn.execute(update(rate_buckets_t).where(rate_buckets_t.c.kind == kind,
                                                      rate_buckets_t.c.client == client)
                         .values(tokens=left, stamp=stamp))
        if now - self._swept > SWEEP_EVERY_S:
            self._swept = now
            self._sweep(now)

    def _sweep(self, now: float) -> None:
        """Forget buckets idle long enough to be full again (the table stays as small as the active clients)."""
        with self.store._write() as conn:
            for kind in ("write", "identity"):
                _, capacity, rate = self._rule(kind)
                if capacity > 0:
                    conn.execute(delete(rate_buckets_t).where(rate_buckets_t.c.kind == kind,
                                                              rate_buckets_t.c.stamp < now - capacity / rate))
