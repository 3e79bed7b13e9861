"""The console's store of the bus: the force history, the event log, the commanded target."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus import keys
from services.bus.messages import IDENTITY_R, OperatorCommand
from services.console.mirror import BusMirror, ForceHistory

from .support import ready_state, wait_until


def test_force_history_window_and_wrap_around() -> None:
    h = ForceHistory(100)
    for i in range(250):  # wraps twice and a half
        h.add(i * 0.01, (float(i), 0.0, 0.0), (0.0, 0.0, -float(i)))
    assert len(h) == 100
    t, w = h.window(span_s=0.505, max_points=1000)
    assert t[-1] == 0.0 and t[0] == pytest.approx(-0.5)
    assert len(t) == 51
    assert w[-1, 0] == 249.0 and w[-1, 5] == -249.0 and w[0, 0] == 199.0
    assert t.flags.c_contiguous and w.flags.c_contiguous


@given(st.integers(2, 500), st.integers(2, 60))
def test_force_history_decimation_keeps_the_newest_and_the_order(n: int, max_points: int) -> None:
    h = ForceHistory(1000)
    for i in range(n):
        h.add(i * 0.001, (float(i), 0.0, 0.0), (0.0, 0.0, 0.0))
    t, w = h.window(span_s=10.0, max_points=max_points)
    assert 1 <= len(t) <= max_points
    assert w[-1, 0] == n - 1 and t[-1] == 0.0
    assert np.all(np.diff(t) > 0)


def test_empty_history() -> None:
    t, w = ForceHistory(10).window(5.0, 100)
    assert t.shape == (0,) and w.shape == (0, 6)


def _cmd(seq: int, engage: int, dp: tuple[float, float, float]) -> OperatorCommand:
    return OperatorCommand(
        seq=seq,
        t_ns=time.time_ns(),
        master="decision",
        engage=engage,
        active=True,
        frame="world",
        dp=dp,
        dR=IDENTITY_R,
    )


def test_mirror_over_the_bus(net: Any) -> None:
    pub_node = net.node("puma")
    mirror_node = net.node("console")
    mirror = BusMirror(mirror_node, events=3, force_capacity=100)
    mirror.watch_page(True)  # robot/puma/cmd is subscribed to while a page is shown
    state_pub = pub_node.publisher(keys.STATE)
    cmd_pub = pub_node.publisher(keys.PUMA_CMD)
    assert mirror.target() is None

    state_pub.put(ready_state(1, (0.5, 0.0, 0.6)))
    assert mirror.state.wait_for(lambda s: s.seq == 1, 5.0) is not None
    cmd_pub.put(_cmd(10, 7, (0.0, 0.1, 0.0)))
    assert wait_until(lambda: mirror.target() is not None)
    target = mirror.target()
    assert target is not None
    p, R, active = target
    # The engagement's reference is the tool pose when its first command arrived.
    assert np.allclose(p, [0.5, 0.1, 0.6]) and np.allclose(R, np.eye(3)) and active

    for i in range(5):
        pub_node.event("status", f"e{i}")
    assert wait_until(lambda: mirror.events_seen == 5)
    assert [e.message for e in mirror.events()] == ["e2", "e3", "e4"]
    new, seen = mirror.events_since(3)
    assert [e.message for e in new] == ["e3", "e4"] and seen == 5
    assert mirror.events_since(5) == ([], 5)
    # More new events than the log holds: only those kept come back.
    assert [e.message for e in mirror.events_since(0)[0]] == ["e2", "e3", "e4"]
