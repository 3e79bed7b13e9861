"""The supervisor's events for robot/events: queued per tick, counted, rate-limited.

An intervention (the supervisor changed or refused what was asked) is counted under its kind
in `counters` and reported; a continuous one (a contact, a limit) only when it starts (an
edge). A flood (a hostile master's ids, a contact chattering at 500 Hz) is one trickle:
at most one event per `interval_s` per limit key and NOTICES_PER_S per kind, the next one
sent saying how many of its kind were suppressed. Memory stays bounded. Pure: the caller
passes the monotonic time (ns).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

EDGE_RELEASE_NS = 250_000_000
"""A continuous intervention (contact, limit) counts once until it has been off this long."""
NOTICES_PER_S = 5
"""Rate-limited events of one kind sent per second, over all their keys."""
MAX_NOTICE_KEYS = 1024
"""Rate-limit keys remembered (oldest forgotten first): memory stays bounded."""

#: the kinds of intervention events, each with a counter in `status`
INTERVENTIONS: tuple[str, ...] = (
    "watchdog",
    "lease",
    "limit",
    "contact",
    "estop",
    "rejected",
    "busy",
)


@dataclass(frozen=True, slots=True)
class Notice:
    """An event for robot/events: `kind`, a message for people, and data."""

    kind: str
    message: str
    data: Mapping[str, Any] = field(default_factory=dict)


def floats(v: NDArray[np.float64]) -> list[float]:
    """A vector as plain floats, for an event's data or a reply."""
    return [float(x) for x in v]


class Notices:
    """The events of the ticks so far (`drain` takes them), the intervention counters, and
    the rate limiter's and edges' memory. `interval_s` is the per-key rate limit
    (`event_interval_s`); the supervisor updates it with its settings."""

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self.counters: dict[str, int] = dict.fromkeys(INTERVENTIONS, 0)
        self.suppressed: dict[str, int] = {}
        self._queue: list[Notice] = []
        self._last_sent_ns: OrderedDict[str, int] = OrderedDict()
        self._kind_window: dict[str, tuple[int, int]] = {}
        self._edges: dict[str, int] = {}

    @property
    def keys_remembered(self) -> int:
        """How many rate-limit keys are remembered (≤ MAX_NOTICE_KEYS)."""
        return len(self._last_sent_ns)

    def post(
        self,
        now_ns: int,
        kind: str,
        message: str,
        data: Mapping[str, Any] | None = None,
        limit_key: str | None = None,
    ) -> None:
        """Queue an event; with `limit_key`, at most one per interval_s for that key and
        NOTICES_PER_S per kind over all keys (a flood of master ids is one trickle); the
        next one sent says how many of its kind were suppressed."""
        if limit_key is not None:
            now = now_ns
            last = self._last_sent_ns.get(limit_key)
            start, sent = self._kind_window.get(kind, (now, 0))
            if now - start >= 1_000_000_000:
                start, sent = now, 0
            if (last is not None and now - last < self.interval_s * 1e9) or sent >= NOTICES_PER_S:
                self.suppressed[kind] = self.suppressed.get(kind, 0) + 1
                self._kind_window[kind] = (start, sent)
                return
            self._kind_window[kind] = (start, sent + 1)
            self._last_sent_ns[limit_key] = now
            self._last_sent_ns.move_to_end(limit_key)
            while len(self._last_sent_ns) > MAX_NOTICE_KEYS:
                self._last_sent_ns.popitem(last=False)
            n = self.suppressed.pop(kind, 0)
            if n:
                data = {**(data or {}), "suppressed": n}
        self._queue.append(Notice(kind, message, dict(data or {})))

    def intervene(
        self, now_ns: int, kind: str, message: str, data: Mapping[str, Any], limit_key: str
    ) -> None:
        """Count an intervention of `kind` and report it (rate-limited per `limit_key`)."""
        self.counters[kind] = self.counters.get(kind, 0) + 1
        self.post(now_ns, kind, message, data, limit_key)

    def edge(
        self,
        now_ns: int,
        name: str,
        active: bool,
        kind: str,
        message: str,
        data: Mapping[str, Any],
    ) -> None:
        """A continuous condition counts (and is reported) once when it starts, and starts
        again only after it has been off for EDGE_RELEASE_NS."""
        if not active:
            return
        last = self._edges.get(name)
        self._edges[name] = now_ns
        if last is None or now_ns - last > EDGE_RELEASE_NS:
            self.intervene(now_ns, kind, message, data, limit_key=f"edge:{name}")

    def clear_edges(self) -> None:
        """A new engagement: every continuous condition counts again when it starts."""
        self._edges.clear()

    def drain(self) -> tuple[Notice, ...]:
        """The events queued since the last drain, in order."""
        out, self._queue = tuple(self._queue), []
        return out
