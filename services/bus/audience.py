"""Who listens: Zenoh's matching status for a set of keys, as one flag with a callback.

A publisher that works for nobody (renders, encodes, sends) asks this first: vision stops
rendering while nobody subscribes to its eyes, the force service stops publishing while
nobody subscribes to `robot/force` (its sensor keeps sampling). A new subscriber is seen
within one round trip to the router, so the first sample after it reaches it at once.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Sequence
from typing import Any

import zenoh


class Audience:
    """Whether anyone subscribes to any of `keys`, from Zenoh's matching status.

    One publisher per key is declared for its matching status only (it never puts; the
    data goes out through the node's own publishers, with their QoS). `on_change(watched)`
    is called from Zenoh's thread at every change of the union, and once at start.
    """

    def __init__(
        self, session: zenoh.Session, keys_: Sequence[str], on_change: Callable[[bool], None]
    ) -> None:
        self._lock = threading.Lock()
        self._on_change = on_change
        self._matched: dict[str, bool] = {}
        self._watched: bool | None = None
        self._probes = [session.declare_publisher(k) for k in keys_]
        self._listeners = []
        for key, probe in zip(keys_, self._probes, strict=True):
            # The listener first, then the status: a subscriber arriving in between is
            # seen by one or the other, never missed. The status read is kept only if the
            # listener has not reported yet: a report newer than the read (a subscriber
            # that arrived just after it) must not be overwritten by the older read.
            self._listeners.append(probe.declare_matching_listener(self._updater(key)))
            self._update(key, _matching(probe.matching_status), initial=True)

    def _updater(self, key: str) -> Callable[[zenoh.MatchingStatus], None]:
        return lambda status: self._update(key, status.matching)

    def _update(self, key: str, matched: bool, *, initial: bool = False) -> None:
        with self._lock:
            if initial and key in self._matched:
                matched = self._matched[key]  # the listener spoke first: its report is newer
            self._matched[key] = matched
            watched = any(self._matched.values())
            if watched == self._watched:
                return
            self._watched = watched
            # Under the lock, so two changes racing on Zenoh's threads arrive in order.
            self._on_change(watched)

    @property
    def watched(self) -> bool:
        with self._lock:
            return bool(self._watched)

    def matched(self) -> dict[str, bool]:
        """Each key's own matching status."""
        with self._lock:
            return dict(self._matched)

    def close(self) -> None:
        """Undeclare; after the session closed (which already did) a no-op."""
        decls: list[Any] = [*self._listeners, *self._probes]
        for decl in decls:
            with contextlib.suppress(zenoh.ZError):
                decl.undeclare()


def _matching(status: object) -> bool:
    # zenoh 1.10's stubs type `Publisher.matching_status` as bool; it is a MatchingStatus.
    return bool(getattr(status, "matching", status))
