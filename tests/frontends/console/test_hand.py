"""The gizmo → virtual master link against the real master, decision and sim arm over Zenoh
(no browser): parking on the tool moves nothing, the first motion engages there, the tool
follows the gizmo, the master-shift decouples them, and a master that engaged before the
console arrived never jumps."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from services.bus import keys
from services.bus.messages import Event, RobotState, mat3
from services.bus.node import Node
from services.control.arm.config import ArmConfig
from services.control.arm.service import ArmService
from services.control.decision.config import DecisionConfig
from services.control.decision.service import DecisionService
from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from services.frontends.console.hand import HandLink, ToolPose
from services.frontends.console.mirror import BusMirror
from services.geometry import Array3, Mat3

pytestmark = [pytest.mark.system, pytest.mark.timeout(90)]

TOL_M = 0.002


def _d(x: float, y: float, z: float) -> Array3:
    """An offset (m, world)."""
    return np.array([x, y, z])


@dataclass
class Drift:
    """The largest distance of the tool from `origin` seen on robot/state since `reset`."""

    origin: Array3 = field(default_factory=lambda: np.zeros(3))
    worst_m: float = 0.0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def reset(self, origin: Array3) -> None:
        with self.lock:
            self.origin, self.worst_m = origin.copy(), 0.0

    def __call__(self, st: RobotState) -> None:
        with self.lock:
            d = float(np.linalg.norm(np.asarray(st.tool_p) - self.origin))
            self.worst_m = max(self.worst_m, d)


@dataclass
class Rig:
    net: Any
    client: Node
    mirror: BusMirror
    drift: Drift
    placed: list[tuple[Array3, Mat3]]

    def link(self, master_id: str) -> HandLink:
        def place(p: Array3, R: Mat3) -> None:
            self.placed.append((p, R))

        def wait(pred: Any, timeout_s: float) -> Any:
            return self.mirror.wait_master(master_id, pred, timeout_s)

        return HandLink(self.client, master_id, wait, self.tool, place, rpc_timeout_s=5.0)

    def tool(self) -> ToolPose | None:
        st = self.mirror.state.latest
        if st is None:
            return None
        return ToolPose(np.asarray(st.tool_p), mat3(st.tool_R), st.status)

    def tool_p(self) -> Array3:
        st = self.mirror.state.latest
        assert st is not None
        return np.asarray(st.tool_p)

    def wait_tool(self, p: Array3, timeout_s: float = 15.0) -> RobotState | None:
        return self.mirror.state.wait_for(
            lambda s: float(np.linalg.norm(np.asarray(s.tool_p) - p)) < TOL_M, timeout_s
        )

    def settle(self, n_states: int = 50) -> None:
        """Let `n_states` robot states go by (a count, not a time)."""
        st = self.mirror.state.latest
        seq = st.seq if st is not None else 0
        assert self.mirror.state.wait_for(lambda s: s.seq >= seq + n_states, 10.0) is not None


@pytest.fixture
def rig(net: Any) -> Iterator[Rig]:
    closers: list[Any] = []
    try:
        closers.append(ArmService(net.node("arm"), ArmConfig(sim_calibration_s=0.05)))
        # The default watchdogs (100 ms command, 200 ms state), as deployed.
        closers.append(DecisionService(net.node("decision"), DecisionConfig()))
        closers.append(
            MasterService(
                net.node("master", instance="console"),
                MasterConfig(master_id="console", device="virtual", engage_on_start=False),
            )
        )
        client = net.node("console")
        drift = Drift()
        client.subscribe(keys.STATE, drift)
        mirror = BusMirror(client, events=50, force_capacity=10)
        assert mirror.state.wait_for(lambda s: True, 10.0) is not None
        yield Rig(net, client, mirror, drift, [])
    finally:
        for c in reversed(closers):
            c.close()


def _ready_at_home(rig: Rig) -> Array3:
    rig.client.call("decision", "connect", {}, 5.0)
    rig.client.call("decision", "initialize", {}, 5.0)
    assert rig.mirror.state.wait_for(lambda s: s.status == "ready", 10.0) is not None
    rig.client.call("decision", "home", {"wait": True}, 60.0)
    return rig.tool_p()


def _wait_link(link: HandLink, state: str, resyncs: int = 0) -> None:
    """Wait until the link is in `state` after at least `resyncs` resyncs."""
    ok = link.wait(lambda h: h.state == state and h.resyncs >= resyncs, 5.0)
    assert ok, (link.state, link.resyncs, link.error)


def test_park_engage_follow_and_master_shift(rig: Rig) -> None:
    link = rig.link("console")
    try:
        # Not ready: the gizmo is parked on the tool, the master stays clutched.
        link.resync()
        _wait_link(link, "parked")
        assert len(rig.placed) == 1 and np.allclose(rig.placed[0][0], rig.tool_p())
        p_idle = rig.tool_p()
        link.set_gizmo(p_idle + _d(0.0, 0.0, 0.05), np.eye(3))
        assert rig.mirror.wait_master(
            "console", lambda m: not m.active and m.hand_p[2] > p_idle[2] + 0.04, 5.0
        )
        _wait_link(link, "parked")

        home = _ready_at_home(rig)
        R_home = mat3(rig.mirror.state.latest.tool_R)  # type: ignore[union-attr]
        # Parking on the tool moves nothing.
        rig.drift.reset(home)
        link.resync()
        _wait_link(link, "parked", resyncs=2)
        assert np.allclose(rig.placed[-1][0], home) and np.allclose(rig.placed[-1][1], R_home)
        rig.settle()
        assert rig.drift.worst_m < 1e-4

        # The first motion of the gizmo engages at the tool and the tool follows it.
        goal = home + _d(0.0, 0.05, 0.0)
        link.set_gizmo(goal, R_home)
        assert rig.wait_tool(goal) is not None, (rig.tool_p(), link.state, link.error)
        _wait_link(link, "engaged")
        status = rig.client.call("decision", "status", {}, 5.0)
        assert status["lease"] == "console"

        # Master-shift: the gizmo moves alone.
        link.set_shift(True)
        assert rig.mirror.wait_master("console", lambda m: not m.active, 5.0)
        # The arm settles on the last target (the arm ends its motion: ready), then holds.
        assert rig.mirror.state.wait_for(lambda s: s.status == "ready", 10.0) is not None
        rig.settle(10)
        rig.drift.reset(rig.tool_p())
        moved_hand = goal + _d(0.0, 0.0, 0.1)
        link.set_gizmo(moved_hand, R_home)
        assert rig.mirror.wait_master(
            "console", lambda m: abs(m.hand_p[2] - moved_hand[2]) < 1e-9, 5.0
        )
        rig.settle()
        assert rig.drift.worst_m < 1e-3
        _wait_link(link, "master-shift")

        # Released: a new engagement from where the hand is; motion is relative again.
        link.set_shift(False)
        assert rig.mirror.wait_master("console", lambda m: m.active, 5.0)
        link.set_gizmo(moved_hand + _d(0.0, 0.0, -0.03), R_home)
        assert rig.wait_tool(goal + _d(0.0, 0.0, -0.03)) is not None, rig.tool_p()
    finally:
        link.close()


def test_letting_go_of_the_gizmo_disengages_cleanly_and_the_next_drag_engages_afresh(
    rig: Rig,
) -> None:
    link = rig.link("console")
    events: list[Event] = []
    rig.client.subscribe(keys.EVENTS, events.append)
    try:
        home = _ready_at_home(rig)
        R_home = mat3(rig.mirror.state.latest.tool_R)  # type: ignore[union-attr]
        link.resync()
        _wait_link(link, "parked", resyncs=1)
        goal = home + _d(0.0, 0.03, 0.0)
        link.set_gizmo(goal, R_home)
        assert rig.wait_tool(goal) is not None, (rig.tool_p(), link.state, link.error)
        engaged_state = rig.mirror.master("console")
        assert engaged_state is not None
        first = engaged_state.engage
        link.release()  # the mouse button comes up
        assert rig.mirror.wait_master("console", lambda m: not m.active, 5.0)
        _wait_link(link, "parked")
        assert rig.client.call("decision", "status", {}, 5.0)["lease"] is None
        rig.settle(60)  # well past the 100 ms watchdog: a released hand trips nothing
        assert not [e for e in events if e.kind == "watchdog"], [e.message for e in events]
        lease = [
            e for e in events if e.kind == "lease" and (e.data or {}).get("master") == "console"
        ]
        assert lease and (lease[-1].data or {}).get("reason") == "disengaged"
        rig.drift.reset(rig.tool_p())
        again = goal + _d(0.0, 0.0, 0.02)  # the next drag: a new engagement, relative motion
        link.set_gizmo(again, R_home)
        assert rig.wait_tool(again) is not None, rig.tool_p()
        assert rig.mirror.wait_master("console", lambda m: m.active and m.engage > first, 5.0)
    finally:
        link.close()


def test_a_master_engaged_before_the_console_does_not_jump(rig: Rig) -> None:
    home = _ready_at_home(rig)
    # An operator started `telerobot master --device virtual` by hand: it engages at its
    # first tick with the hand at the origin, and takes the lease with the robot ready.
    ext = MasterService(
        rig.net.node("master", instance="ext"),
        MasterConfig(master_id="ext", device="virtual"),
    )
    try:
        assert rig.mirror.wait_master("ext", lambda m: m.active, 5.0) is not None
        rig.drift.reset(home)
        link = rig.link("ext")
        try:
            link.resync()
            _wait_link(link, "parked")
            rig.settle()
            # The hand went from the origin to the tool (0.85 m) with the master-shift held.
            assert rig.drift.worst_m < 1e-4
            R_home = mat3(rig.mirror.state.latest.tool_R)  # type: ignore[union-attr]
            link.set_gizmo(home + _d(0.03, 0.0, 0.0), R_home)
            assert rig.wait_tool(home + _d(0.03, 0.0, 0.0)) is not None, rig.tool_p()
        finally:
            link.close()
    finally:
        ext.close()
