"""Log volume (issue 23, item 7): a late loop is summarized, not reported once per tick, and
a router listening beyond loopback says so loudly (item 4).

RateLoop runs on a fake clock (time advances only when the loop sleeps or the test "works"),
so counts and reports are exact whatever the machine's load.
"""

from __future__ import annotations

import itertools
import logging

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.bus.config import NodeConfig
from services.bus.rate import REPORT_INTERVAL_S, RateLoop
from services.bus.router import exposure_note, is_loopback
from tests.bus.test_node import FakeClock


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    c = FakeClock()
    monkeypatch.setattr("services.bus.rate.time.perf_counter", c.perf_counter)
    monkeypatch.setattr("services.bus.rate.time.sleep", c.sleep)
    return c


def test_a_late_loop_is_summarized_every_ten_seconds_at_most(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    """A 100 Hz loop whose every tick overruns for 60 s: 6 000 late ticks, 6 log lines,
    each with the count since the previous one and the worst lateness."""
    caplog.set_level(logging.WARNING, logger="telerobot.rate")
    loop = RateLoop(100.0, name="master")
    n = 0
    while clock.now < 160.0:
        n += 1
        clock.now += 0.035 if n % 100 == 50 else 0.025  # one worse tick a second
        loop.sleep()
    lines = [r.getMessage() for r in caplog.records]
    assert loop.late == loop.ticks == n
    assert REPORT_INTERVAL_S == 10.0
    assert len(lines) == 6 == loop.reports
    # the first late tick is told at once, later ones gathered: every late tick is counted
    assert lines[0] == "master loop late: 1 tick, worst 15.0 ms (1 of 1 ticks late since start)"
    counts = [int(line.split(": ")[1].split()[0]) for line in lines]
    assert counts[0] == 1 and all(c > 300 for c in counts[1:])
    assert all(" in the last 10 s, worst 25.0 ms " in line for line in lines[1:])
    assert sum(counts) <= loop.late
    assert loop.stats() == {
        "rate_hz": 100.0,
        "ticks": n,
        "late": n,
        "worst_late_ms": pytest.approx(25.0, abs=1e-6),
    }


def test_gathered_lateness_is_reported_once_the_interval_passes(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    """Late ticks after a report are not lost when the loop is on time again: the summary
    comes on the first tick after the interval."""
    caplog.set_level(logging.WARNING, logger="telerobot.rate")
    reports: list[tuple[float, int]] = []
    loop = RateLoop(100.0, on_late=lambda s, n: reports.append((s, n)))
    for work in (0.03, 0.04, 0.05):  # 3 late ticks within a second
        clock.now += work
        loop.sleep()
    assert [n for _, n in reports] == [1]
    while clock.now < 112.0:  # on time for ~11 s
        clock.now += 0.001
        loop.sleep()
    assert len(reports) == 2
    assert reports[1] == (pytest.approx(0.04, abs=1e-9), 3)  # worst of the two, total 3
    assert caplog.records == []  # an on_late loop does not log by itself


def test_an_unnamed_loop_only_counts(clock: FakeClock, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    loop = RateLoop(100.0)
    for _ in range(50):
        clock.now += 0.05
        loop.sleep()
    assert loop.late == 50 and loop.stats()["late"] == 50
    assert caplog.records == []


@settings(max_examples=60, deadline=None)
@given(works=st.lists(st.floats(0.0, 0.2), min_size=1, max_size=400))
def test_reports_never_come_faster_than_the_interval(works: list[float]) -> None:
    clock = FakeClock()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("services.bus.rate.time.perf_counter", clock.perf_counter)
        mp.setattr("services.bus.rate.time.sleep", clock.sleep)
        at: list[float] = []
        totals: list[int] = []

        def on_late(worst_s: float, n: int) -> None:
            at.append(clock.now)
            totals.append(n)

        loop = RateLoop(100.0, on_late=on_late, report_interval_s=1.0)
        for w in works:
            clock.now += w
            loop.sleep()
    assert all(b - a >= 1.0 - 1e-9 for a, b in itertools.pairwise(at))
    assert totals == sorted(totals) and (not totals or totals[-1] <= loop.late)
    assert (loop.late > 0) == (len(at) > 0)


@pytest.mark.parametrize(
    ("endpoint", "loopback"),
    [
        ("tcp/127.0.0.1:7447", True),
        ("tcp/127.0.0.5:0", True),
        ("tcp/[::1]:7447", True),
        ("tcp/localhost:7447", True),
        ("tcp/0.0.0.0:7447", False),
        ("tls/[::]:7448", False),
        ("tcp/192.168.1.10:7447", False),
        ("tcp/robot.lab.example:7447", False),
    ],
)
def test_loopback_endpoints(endpoint: str, loopback: bool) -> None:
    assert is_loopback(endpoint) is loopback


def test_a_router_beyond_loopback_says_who_can_join() -> None:
    assert exposure_note(NodeConfig(mode="router", listen=("tcp/127.0.0.1:7447",))) is None
    open_note = exposure_note(
        NodeConfig(mode="router", listen=("tcp/0.0.0.0:7447",), admin_space=True)
    )
    assert open_note is not None
    assert "beyond loopback on tcp/0.0.0.0:7447" in open_note
    assert "ANYONE who reaches the port can join and publish robot/arm/target" in open_note
    assert "admin space @/**" in open_note and "readable by all" in open_note
    # Zenoh's own default listener ([::]:7447) counts as beyond loopback too
    assert "tcp/[::]:7447" in (exposure_note(NodeConfig(mode="router")) or "")
    # the deployment router: login and ACL, the ACL decides who reads the admin space
    acl = exposure_note(NodeConfig(mode="router", zenoh_config="deploy/router/robot-router.json5"))
    assert acl is not None and "tls/0.0.0.0:7448" in acl
    assert "only sessions that log in" in acl and "ANYONE" not in acl
    assert "the access-control list decides who reads it" in acl


def test_the_sim_profile_listens_on_loopback_only() -> None:
    import tomllib

    from services.tools.cli.launcher import DEPLOY_DIR

    sim = tomllib.loads((DEPLOY_DIR / "sim.toml").read_text())
    assert sim["router"]["listen"] and all(is_loopback(e) for e in sim["router"]["listen"])
    assert sim["zenoh"]["listen"] and all(is_loopback(e) for e in sim["zenoh"]["listen"])
    assert all(is_loopback(e) for e in sim["zenoh"]["connect"])
    router_cfg = NodeConfig(mode="router", listen=tuple(sim["router"]["listen"]), admin_space=True)
    assert exposure_note(router_cfg) is None
