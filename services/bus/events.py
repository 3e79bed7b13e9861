"""The event rate limiter: at most one event per key per interval, the rest counted.

Every service that could flood `robot/events` (bad data at 1 kHz, a rejected input per
message) asks an `EventLimiter` before sending. The one it lets through says how many of
its key were held back since the last one, so counts are never lost, only batched.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class EventLimiter:
    """At most one event per key every `interval_s`, and, with `per_s`, at most `per_s`
    events a second over all keys (a fixed one-second window). Thread-safe.

    `allow(key)` is None for an event to hold back; otherwise the number of events of that
    key held back since the last one let through (0 when none). Times are seconds of
    `clock_s` (monotonic by default) unless the caller passes its own `now_s`.
    """

    __slots__ = ("_clock_s", "_held", "_last", "_lock", "_window", "interval_s", "per_s")

    def __init__(
        self,
        interval_s: float,
        per_s: int | None = None,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        if not interval_s >= 0:
            raise ValueError("interval_s must be ≥ 0")
        if per_s is not None and per_s < 1:
            raise ValueError("per_s must be ≥ 1")
        self.interval_s = interval_s
        self.per_s = per_s
        self._clock_s = clock_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._window = (0.0, 0)
        self._lock = threading.Lock()

    def allow(self, key: str, now_s: float | None = None) -> int | None:
        """None to hold this event back; else how many of `key` were held back before it."""
        now = self._clock_s() if now_s is None else now_s
        with self._lock:
            last = self._last.get(key)
            start, sent = self._window
            if now - start >= 1.0:
                start, sent = now, 0
            if (last is not None and now - last < self.interval_s) or (
                self.per_s is not None and sent >= self.per_s
            ):
                self._held[key] = self._held.get(key, 0) + 1
                self._window = (start, sent)
                return None
            self._last[key] = now
            self._window = (start, sent + 1)
            return self._held.pop(key, 0)

    def held(self, key: str) -> int:
        """Events of `key` held back since the last one let through."""
        with self._lock:
            return self._held.get(key, 0)
