"""Event callbacks of the force service, and a rate limit so bad data cannot flood the bus.

An event is `(kind, message, data)`: `kind` is the Event kind of PROTOCOL.md §3 (`stale`,
`recovered`, `bad_data`, `gap`, `error`, `status`), `message` is for people, `data` a map
of plain values (msgpack-able). The service wiring turns each into a `robot/events` Event.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection
from typing import Any

from services.bus.events import EventLimiter

EventSink = Callable[[str, str, dict[str, Any]], None]

UNTHROTTLED_KINDS = frozenset({"stale", "recovered", "status"})
"""Kinds that are already once-per-change by construction: never held back."""


def ignore_event(kind: str, message: str, data: dict[str, Any]) -> None:
    """An EventSink that drops everything (a sensor used on its own)."""


class EventThrottle:
    """An EventSink that lets through at most one event per kind per `interval_s` (the
    bus's `EventLimiter`); kinds in `exempt` always pass.

    The next event of a kind that gets through carries `data["suppressed"]`, the number of
    events of that kind held back since the last one, so counts are never lost. Safe to call
    from several threads.
    """

    __slots__ = ("_exempt", "_limiter", "_sink")

    def __init__(
        self,
        sink: EventSink,
        interval_s: float = 1.0,
        exempt: Collection[str] = UNTHROTTLED_KINDS,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self._sink = sink
        self._exempt = frozenset(exempt)
        self._limiter = EventLimiter(interval_s, clock_s=clock_s)

    def __call__(self, kind: str, message: str, data: dict[str, Any]) -> None:
        if kind not in self._exempt:
            held = self._limiter.allow(kind)
            if held is None:
                return
            if held:
                data = {**data, "suppressed": held}
        self._sink(kind, message, data)
