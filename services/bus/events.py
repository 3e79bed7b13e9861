"""The event rate limiter: at most one event per key per interval, the rest counted.

Every service that could flood `robot/events` (bad data at 1 kHz, a rejected input per
message) asks an `EventLimiter` before sending. The one it lets through says how many of
its key were held back since the last one, so counts are never lost, only batched.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable


class EventLimiter:
    """At most one event per key every `interval_s`, and, with `per_s`, at most `per_s`
    events a second over all keys (a fixed one-second window). Thread-safe.

    `allow(key)` is None for an event to hold back; otherwise the number of events of that
    key held back since the last one let through (0 when none). Times are seconds of
    `clock_s` (monotonic by default) unless the caller passes its own `now_s`.

    With `max_keys`, only that many keys are remembered (the least recently let through is
    forgotten with its held count), so keys taken from the network cannot grow it; a key
    the limiter does not remember has no held count kept.
    """

    __slots__ = (
        "_clock_s",
        "_held",
        "_last",
        "_lock",
        "_window",
        "interval_s",
        "max_keys",
        "per_s",
    )

    def __init__(
        self,
        interval_s: float,
        per_s: int | None = None,
        clock_s: Callable[[], float] = time.monotonic,
        max_keys: int | None = None,
    ) -> None:
        if not interval_s >= 0:
            raise ValueError("interval_s must be ≥ 0")
        if per_s is not None and per_s < 1:
            raise ValueError("per_s must be ≥ 1")
        if max_keys is not None and max_keys < 1:
            raise ValueError("max_keys must be ≥ 1")
        self.interval_s = interval_s
        self.per_s = per_s
        self.max_keys = max_keys
        self._clock_s = clock_s
        self._last: OrderedDict[str, float] = OrderedDict()
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
                if self.max_keys is None or last is not None:
                    self._held[key] = self._held.get(key, 0) + 1
                self._window = (start, sent)
                return None
            self._last[key] = now
            self._window = (start, sent + 1)
            held = self._held.pop(key, 0)
            if self.max_keys is not None:
                self._last.move_to_end(key)
                while len(self._last) > self.max_keys:
                    old, _ = self._last.popitem(last=False)
                    self._held.pop(old, None)
            return held

    def held(self, key: str) -> int:
        """Events of `key` held back since the last one let through."""
        with self._lock:
            return self._held.get(key, 0)
