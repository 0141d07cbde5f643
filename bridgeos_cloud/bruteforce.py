"""Count failed logins per (identity, address) and per address, in Redis, and block past a limit."""

from __future__ import annotations

import ipaddress
import threading
import time
from functools import cache, lru_cache

from django.conf import settings
from django.dispatch import Signal

# Sent with scope=, identity=, address= when a login identity just reached its limit (monitoring logs it).
login_blocked = Signal()


class FailureLimit:
    """Allow ``limit`` failures per key within ``window`` seconds; past that, the key is blocked until it expires."""

    def __init__(self, redis_url: str | None, *, prefix: str = "bridgeos:failures:") -> None:
        self.prefix = prefix
        self._redis = None
        if redis_url:
            import redis

            self._redis = redis.Redis.from_url(redis_url, socket_timeout=5)
        self._local: dict[str, tuple[int, float]] = {}
        self._lock = threading.Lock()

    def blocked_for(self, keys: list[tuple[str, int]], window: float) -> float:
        """Return how many seconds the first blocked key stays blocked (0: none is)."""
        for key, limit in keys:
            count, expires = self._get(key, window)
            if count >= limit:
                return max(1.0, expires)
        return 0.0

    def blocked_for_many(self, logins: list[list[tuple[str, int]]], window: float) -> list[float]:
        """Return ``blocked_for`` of many logins at once: one Redis round trip for all of them."""
        if self._redis is None:
            return [self.blocked_for(keys, window) for keys in logins]
        # One MGET of the distinct counters (a fleet behind one address shares its address counter),
        # and TTLs only for those at their limit: a connect storm's batch asked four commands a robot.
        names = list(dict.fromkeys(self.prefix + key for keys in logins for key, _ in keys))
        counts = dict(zip(names, self._redis.mget(names), strict=True)) if names else {}
        over = list(
            dict.fromkeys(
                self.prefix + key
                for keys in logins
                for key, limit in keys
                if int(counts[self.prefix + key] or 0) >= limit
            )
        )
        ttls: dict[str, int] = {}
        if over:
            pipe = self._redis.pipeline()
            for name in over:
                pipe.ttl(name)
            ttls = dict(zip(over, pipe.execute(), strict=True))
        retries = []
        for keys in logins:
            retry = 0.0
            for key, limit in keys:
                name = self.prefix + key
                if int(counts[name] or 0) >= limit:
                    ttl = ttls.get(name)
                    retry = max(1.0, float(ttl if ttl and ttl > 0 else window))
                    break
            retries.append(retry)
        return retries

    def succeeded_many(self, keys: list[str]) -> None:
        """Forget the failures of identities that just proved themselves, in one round trip."""
        if self._redis is not None:
            if keys:
                self._redis.delete(*(self.prefix + key for key in keys))
        else:
            for key in keys:
                self.succeeded(key)

    def failed(self, keys: list[tuple[str, int]], window: float) -> bool:
        """Count a failure against every key; return True when one of them just reached its limit."""
        tripped = False
        for key, limit in keys:
            tripped |= self._incr(key, window) == limit
        return tripped

    def succeeded(self, key: str) -> None:
        """Forget the failures of an identity that just proved itself."""
        if self._redis is not None:
            self._redis.delete(self.prefix + key)
        else:
            with self._lock:
                self._local.pop(key, None)

    def _get(self, key: str, window: float) -> tuple[int, float]:
        if self._redis is not None:
            pipe = self._redis.pipeline()
            pipe.get(self.prefix + key)
            pipe.ttl(self.prefix + key)
            count, ttl = pipe.execute()
            return int(count or 0), float(ttl if ttl and ttl > 0 else window)
        with self._lock:
            count, until = self._local.get(key, (0, 0.0))
            now = time.monotonic()
            return (count, until - now) if until > now else (0, 0.0)

    def _incr(self, key: str, window: float) -> int:
        if self._redis is not None:
            pipe = self._redis.pipeline()
            pipe.incr(self.prefix + key)
            pipe.expire(self.prefix + key, int(window), nx=True)
            return int(pipe.execute()[0])
        with self._lock:
            now = time.monotonic()
            count, until = self._local.get(key, (0, 0.0))
            if until <= now:
                count, until = 0, now + window
            self._local[key] = (count + 1, until)
            return count + 1


@cache
def failures() -> FailureLimit:
    """Return this process's failure counter (shared through Redis between processes)."""
    return FailureLimit(settings.REDIS_URL)


def login_keys(scope: str, identity: str, address: str) -> list[tuple[str, int]]:
    """Return the counters a login attempt counts against: the identity from this address, and the address."""
    conf = settings.BRIDGEOS
    keys = [(f"{scope}:{identity[:200]}:{address}", conf["AUTH_FAILURES"])]
    if not _loopback(address):
        # This machine's own processes (a local proxy, tests) are never blocked as a whole.
        keys.append((f"address:{address}", conf["AUTH_FAILURES_PER_ADDRESS"]))
    return keys


@lru_cache(maxsize=4096)  # asked for every login; a fleet comes from few addresses
def _loopback(address: str) -> bool:
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False


def window() -> float:
    """Return how long failures are counted (and a blocked key stays blocked)."""
    return settings.BRIDGEOS["AUTH_WINDOW_S"]


def blocked(scope: str, identity: str, address: str) -> float:
    """Return for how many seconds more logins of this identity from this address are refused (0: not)."""
    return failures().blocked_for(login_keys(scope, identity, address), window())


def blocked_many(scope: str, logins: list[tuple[str, str]]) -> list[float]:
    """Return ``blocked`` for many (identity, address) logins at once."""
    return failures().blocked_for_many([login_keys(scope, identity, address) for identity, address in logins], window())


def attempted_many(scope: str, logins: list[tuple[str, str, bool]]) -> None:
    """Count many login attempts at once: successes clear in one round trip, failures count one by one."""
    failures().succeeded_many([login_keys(scope, identity, address)[0][0] for identity, address, ok in logins if ok])
    for identity, address, ok in logins:
        if not ok:
            attempted(scope, identity, address, ok)


def attempted(scope: str, identity: str, address: str, ok: bool) -> None:
    """Count a login attempt: a success clears the identity's failures, a failure counts (and may block)."""
    keys = login_keys(scope, identity, address)
    if ok:
        failures().succeeded(keys[0][0])
    elif failures().failed(keys, window()):
        login_blocked.send(sender=FailureLimit, scope=scope, identity=identity, address=address)
