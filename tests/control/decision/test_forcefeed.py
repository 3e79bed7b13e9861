"""ForceFeed: robot/force subscribed only while the arm moves or may start to."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

from services.bus.messages import IDENTITY_R, ForceSample, OperatorCommand
from services.bus.node import Node
from services.control.decision.forcefeed import FORCE_WAIT_S, WARM_KEEP_S, ForceFeed
from services.control.decision.supervisor import Mode, Supervisor

S = 1_000_000_000


class FakeLatest:
    def __init__(self) -> None:
        self.watching = False
        self.sample: tuple[ForceSample, int] | None = None
        self.switches = 0

    def watch(self, on: bool) -> None:
        if on != self.watching:
            self.switches += 1
        self.watching = on

    def read(self) -> tuple[ForceSample, int] | None:
        return self.sample


class FakeNode:
    def __init__(self) -> None:
        self.handle = FakeLatest()

    def latest(self, topic: Any, watch: bool = True) -> FakeLatest:
        assert not watch
        return self.handle


@dataclass
class FakeSup:
    mode: Mode = Mode.HOLD
    watch: object = None


def cmd(active: bool = True) -> OperatorCommand:
    return OperatorCommand(
        seq=1, t_ns=0, master="m1", engage=2, active=active, frame="world",
        dp=(0.0, 0.0, 0.0), dR=IDENTITY_R,
    )  # fmt: skip


def sample(rx_ns: int) -> tuple[ForceSample, int]:
    return ForceSample(seq=1, t_ns=0, f=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0)), rx_ns


def feed() -> tuple[ForceFeed, FakeLatest, FakeSup]:
    node = FakeNode()
    f = ForceFeed(cast(Node, node))
    return f, node.handle, FakeSup()


def sup_(s: FakeSup) -> Supervisor:
    return cast(Supervisor, s)


def test_idle_and_inactive_commands_subscribe_nothing() -> None:
    f, latest, sup = feed()
    for t in range(5):
        assert f.warm((cmd(active=False),), t * S) is False
        f.update(sup_(sup), t * S)
    assert not latest.watching and latest.switches == 0


def test_an_engagement_from_a_hold_keeps_the_stream_whichever_tick_sees_it_first() -> None:
    """The livelock this guards against: a timer tick (the hold's re-send) sees the first
    sample and drops the subscription, the next command subscribes again and waits, …"""
    f, latest, sup = feed()
    t0 = 10 * S
    assert f.warm((cmd(),), t0) is True  # subscribed, the engagement deferred
    f.update(sup_(sup), t0)
    assert latest.watching
    latest.sample = sample(t0 + 3_000_000)  # the stream is back
    assert f.warm((), t0 + 5_000_000) is False  # a timer tick sees it first
    f.update(sup_(sup), t0 + 5_000_000)
    assert latest.watching  # kept for the engagement
    assert f.warm((cmd(),), t0 + 10_000_000) is False  # the command: it may start now
    sup.mode = Mode.FOLLOW
    f.update(sup_(sup), t0 + 10_000_000)
    assert latest.watching and latest.switches == 1
    sup.mode = Mode.HOLD  # disengaged: dropped
    f.update(sup_(sup), t0 + S)
    assert not latest.watching


def test_no_stream_waits_at_most_force_wait_and_gives_up_after_warm_keep() -> None:
    f, latest, sup = feed()
    t0 = 10 * S
    assert f.warm((cmd(),), t0) is True
    assert f.warm((cmd(),), t0 + int(FORCE_WAIT_S * S) - 1) is True
    assert f.warm((cmd(),), t0 + int(FORCE_WAIT_S * S) + 1) is False  # stale rules now
    f.update(sup_(sup), t0 + int(FORCE_WAIT_S * S) + 1)
    assert latest.watching  # still asked for, not re-subscribed in a loop
    f.update(sup_(sup), t0 + int(WARM_KEEP_S * S) + 1)
    assert not latest.watching and latest.switches == 2


def test_pins_and_watched_motions_subscribe() -> None:
    f, latest, sup = feed()
    f.pins = 1
    f.update(sup_(sup), 0)
    assert latest.watching
    f.pins = 0
    sup.watch = object()
    f.update(sup_(sup), 0)
    assert latest.watching
    sup.watch = None
    f.update(sup_(sup), 0)
    assert not latest.watching
