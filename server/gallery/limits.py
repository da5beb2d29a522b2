"""Rate limits for the gallery API: an in-process token bucket per client and kind of action.

    limits = RateLimits(writes_per_minute=60, identities_per_hour=10)
    limits.take("write", client_key)        # raises RateLimited(retry_after seconds) when the bucket is empty

A bucket holds up to one period's allowance (so a burst of that size passes at once) and refills continuously.
The client key is the peer address: behind a reverse proxy every user shares the proxy's address, so raise the
limits there (X-Forwarded-For is not trusted: any client can set it). Limits are per process; with several
processes on one PostgreSQL gallery each process counts on its own.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time

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
            if bucket.tokens < 1:
                raise RateLimited(what, max(1, math.ceil((1 - bucket.tokens) / rate)))
            bucket.tokens -= 1

    def _forget_idle(self, now: float) -> None:
        for key, bucket in list(self._buckets.items()):
            _, capacity, rate = self._rule(key[0])
            if bucket.tokens + (now - bucket.stamp) * rate >= capacity:
                del self._buckets[key]
