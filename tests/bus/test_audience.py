"""Audience: who subscribes, from Zenoh's matching status, as one flag that is never left
stale by the order in which the listener and the first status read report."""

from __future__ import annotations

import threading
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from services.bus.audience import Audience
from tests.conftest import Net, wait_until


class _Probe:
    """A publisher's matching side. `race`: while its status is read (False), a subscriber
    arrives and the listener reports True before the read returns its older value."""

    def __init__(self, race: bool) -> None:
        self.race = race
        self.listener: Callable[[Any], None] | None = None

    def declare_matching_listener(self, cb: Callable[[Any], None]) -> SimpleNamespace:
        self.listener = cb
        return SimpleNamespace(undeclare=lambda: None)

    @property
    def matching_status(self) -> SimpleNamespace:
        if self.race:
            assert self.listener is not None
            self.listener(SimpleNamespace(matching=True))
        return SimpleNamespace(matching=False)

    def undeclare(self) -> None:
        pass


class _Session:
    def __init__(self, race: bool) -> None:
        self.probes: list[_Probe] = []
        self.race = race

    def declare_publisher(self, key: str) -> _Probe:
        self.probes.append(_Probe(self.race))
        return self.probes[-1]


def test_a_subscriber_arriving_during_the_first_read_is_not_overwritten_by_it() -> None:
    # The CI failure this pins (2026-11-26): the force service saw nobody subscribing, the
    # listener's True overwritten by the older False its first read returned, and never
    # published to the subscriber that was there.
    seen: list[bool] = []
    aud = Audience(_Session(race=True), ("robot/force",), seen.append)  # type: ignore[arg-type]
    assert aud.watched is True
    assert aud.matched() == {"robot/force": True}
    assert seen == [True]


def test_the_first_read_counts_when_the_listener_has_not_reported() -> None:
    seen: list[bool] = []
    session = _Session(race=False)
    aud = Audience(session, ("a", "b"), seen.append)  # type: ignore[arg-type]
    assert aud.watched is False and seen == [False]  # once at start
    listener_b = session.probes[1].listener
    assert listener_b is not None
    listener_b(SimpleNamespace(matching=True))
    listener_b(SimpleNamespace(matching=True))  # no change, no call
    assert aud.matched() == {"a": False, "b": True}
    listener_b(SimpleNamespace(matching=False))
    assert seen == [False, True, False]


def test_over_zenoh_a_subscriber_declared_at_any_moment_is_seen(net: Net) -> None:
    """Twenty rounds of a subscriber declared on one peer while another declares its
    Audience, in a thread, so the two race as in a service's start-up."""
    pub_node = net.node("pub")
    sub_node = net.node("sub")
    subscribers: list[Any] = []  # kept: a dropped subscriber may be undeclared
    for i in range(20):
        key = f"telerobot/test/audience/{i}"
        flags: list[bool] = []
        subscribed = threading.Thread(
            target=lambda k=key: subscribers.append(
                sub_node.session.declare_subscriber(k, lambda _s: None)
            )
        )
        subscribed.start()
        aud = Audience(pub_node.session, (key,), flags.append)
        subscribed.join()
        assert wait_until(lambda a=aud: a.watched, 10.0, what=f"round {i}: the subscriber seen")
        assert flags[-1] is True
        aud.close()
