"""Holds a master hears (issue 42 item 5): a scripted master kept reporting `engaged` after
the decision's 100 ms watchdog held it, and never moved the arm again. Now every master
logs the hold, counts it in `status`, and re-engages (a new engagement where the hand is:
no jump) after a hold for a gap in its stream while its device still asks to move; after a
hold the operator must act on (a stop), it waits for the operator."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from services.bus import keys
from services.bus.messages import Event, OperatorCommand
from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from tests.conftest import Net, wait_until


def station(net: Net, **cfg: object) -> tuple[MasterService, list[OperatorCommand]]:
    cmds: list[OperatorCommand] = []
    lock = threading.Lock()

    def on_cmd(c: OperatorCommand) -> None:
        with lock:
            cmds.append(c)

    net.node("robot").subscribe(keys.CMD, on_cmd)
    config = MasterConfig(master_id="s1", device="scripted", rate_hz=100.0, **cfg)  # type: ignore[arg-type]
    return MasterService(net.node("master", instance="s1"), config), cmds


def test_a_hold_heard_late_is_not_reengaged_after(net: Net) -> None:
    """A master that was frozen or cut off (the hold's event reaches it late) waits for its
    operator: the frozen-master fault test's arm stays where it held."""
    decision = net.node("decision")
    svc, cmds = station(net)
    try:
        assert wait_until(lambda: svc.teleop.engaged and len(cmds) > 5, 5.0)
        engage = svc.teleop.engage
        data = {"master": "s1", "engage": engage, "reason": "command_timeout"}
        stale = Event(
            seq=1,
            t_ns=time.time_ns() - 2_000_000_000,
            source="decision",
            kind="watchdog",
            message="held 2 s ago",
            data=data,
        )
        decision.publisher(keys.EVENTS).put(stale)
        assert wait_until(lambda: svc._status()["holds"] == 1, 5.0)
        n = len(cmds)
        assert wait_until(lambda: len(cmds) > n + 10, 5.0)
        assert svc.teleop.engage == engage and svc._status()["reengages"] == 0
    finally:
        svc.close()


@pytest.mark.parametrize(
    ("kind", "data", "reengages"),
    [
        ("watchdog", {"reason": "command_timeout"}, True),
        # said and counted, but not re-engaged after: the live watchdog event is the cue
        ("lease", {"reason": "engagement_held", "held_by": "command_timeout"}, False),
        ("lease", {"reason": "engagement_held", "held_by": "stop"}, False),
        ("watchdog", {"reason": "state_stale"}, False),
    ],
    ids=["watchdog", "held-after-timeout", "held-after-stop", "state-stale"],
)
def test_a_held_master_says_so_and_reengages_only_after_a_stream_gap(
    net: Net, caplog: pytest.LogCaptureFixture, kind: str, data: dict[str, object], reengages: bool
) -> None:
    decision = net.node("decision")
    with caplog.at_level(logging.WARNING, logger="telerobot.master"):
        svc, cmds = station(net)
        try:
            assert wait_until(lambda: svc.teleop.engaged and len(cmds) > 5, 5.0)
            engage = svc.teleop.engage
            decision.event(kind, "held for the test", {"master": "s1", "engage": engage, **data})
            assert wait_until(lambda: svc._status()["holds"] == 1, 5.0)
            st = svc._status()
            assert st["last_hold"] == (data.get("held_by") or data["reason"])
            if reengages:
                assert wait_until(lambda: svc.teleop.engage == engage + 1, 5.0)
                n = len(cmds)
                assert wait_until(lambda: len(cmds) > n + 3, 5.0)
                after = [c for c in list(cmds) if c.engage == engage + 1]
                assert after and all(c.active for c in after)
                # a new engagement starts at the hand: its first command is no motion
                assert after[0].dp == (0.0, 0.0, 0.0)
                assert svc._status()["reengages"] == 1
            else:
                n = len(cmds)
                assert wait_until(lambda: len(cmds) > n + 10, 5.0)
                assert svc.teleop.engage == engage and svc._status()["reengages"] == 0
            # said once per engagement, whatever repeats
            decision.event(kind, "held for the test", {"master": "s1", "engage": engage, **data})
            decision.event("watchdog", "other master", {"master": "s2", "engage": 9, **data})
            n = len(cmds)
            assert wait_until(lambda: len(cmds) > n + 10, 5.0)
            assert svc._status()["holds"] == 1
        finally:
            svc.close()
    assert sum("held engagement" in r.getMessage() for r in caplog.records) == 1
