"""Event callbacks of the force service, and a rate limit so bad data cannot flood the bus.

An event is `(kind, message, data)`: `kind` is the Event kind of PROTOCOL.md §3 (`stale`,
`recovered`, `bad_data`, `gap`, `error`, `status`), `message` is for people, `data` a map
of plain values (msgpack-able). The service wiring turns each into a `robot/events` Event.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Collection
from typing import Any

EventSink = Callable[[str, str, dict[str, Any]], None]

UNTHROTTLED_KINDS = frozenset({"stale", "recovered", "status"})
"""Kinds that are already once-per-change by construction: never held back."""


def ignore_event(kind: str, message: str, data: dict[str, Any]) -> None:
    """An EventSink that drops everything (a sensor used on its own)."""


class EventThrottle:
    """At most one event per kind per `interval_s`; the ones held back are counted.

    The next event of a kind that gets through carries `data["suppressed"]`, the number of
    events of that kind held back since the last one, so counts are never lost. Safe to call
    from several threads.
    """

    def __init__(
        self,
        sink: EventSink,
        interval_s: float = 1.0,
        exempt: Collection[str] = UNTHROTTLED_KINDS,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self._sink = sink
        self._interval_s = interval_s
        self._exempt = frozenset(exempt)
        self._clock_s = clock_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def __call__(self, kind: str, message: str, data: dict[str, Any]) -> None:
        if kind not in self._exempt:
            now = self._clock_s()
            with self._lock:
                last = self._last.get(kind)
                if last is not None and now - last < self._interval_s:
                    self._held[kind] = self._held.get(kind, 0) + 1
                    return
                self._last[kind] = now
                held = self._held.pop(kind, 0)
            if held:
                data = {**data, "suppressed": held}
        self._sink(kind, message, data)
