"""The master displays the wrist force however old its robot-host stamp is: over a link of
hundreds of ms round trip (or with the robot host's clock behind or ahead of the operator's)
every sample is "old" by `t_ns`, and it is still the newest contact there is. What blanks the
display is a stream that stops arriving for `force_stale_ms`; until then the last is held."""

from __future__ import annotations

import pytest

from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from tests.conftest import Net, wait_until
from tests.control.master.robot_side import RobotSide

pytestmark = [pytest.mark.system, pytest.mark.timeout(60)]


def station(net: Net, force_stale_ms: float = 100.0) -> MasterService:
    cfg = MasterConfig(
        master_id="p1",
        device="haptic_sim",
        rate_hz=200.0,
        force_ramp_s=0.0,
        max_force_n=10.0,
        force_stale_ms=force_stale_ms,
    )
    return MasterService(net.node("master", instance="p1"), cfg)


def shown_z(s: MasterService) -> float:
    return float(s.displayed.f[2])


@pytest.mark.parametrize("stamp_offset_s", [-0.35, -5.0, 3.0])
def test_the_force_is_shown_whatever_its_stamp_and_blanked_when_the_stream_stops(
    net: Net, stamp_offset_s: float
) -> None:
    """-0.35 s: the one-way delay of a 700 ms link; -5 s and +3 s: robot clocks off by that."""
    s = station(net)
    robot = RobotSide(net.node("robot"), (0.0, 0.0, 4.0), stamp_offset_s)
    try:
        assert wait_until(lambda: s.ticks > 20 and not s._stale), "never fresh"
        assert wait_until(lambda: shown_z(s) == pytest.approx(4.0))
        # The stream stops: force_stale_ms (100 ms, 20 ticks at 200 Hz) later the display is
        # blank, not first when the stamps say so (+3 s: three seconds later).
        robot.stop()
        ticks = s.ticks
        assert wait_until(lambda: s._stale and not s.displayed.f.any())
        assert s.ticks - ticks <= 100
    finally:
        robot.stop()
        s.close()


def test_a_gap_shorter_than_force_stale_ms_holds_the_last_force(net: Net) -> None:
    """force_stale_ms 5 s: 40 ticks (some 0.2 s) after the last sample the 4 N are still
    shown, and the station does not call the force stale."""
    s = station(net, force_stale_ms=5000.0)
    robot = RobotSide(net.node("robot"), (0.0, 0.0, 4.0))
    try:
        assert wait_until(lambda: shown_z(s) == pytest.approx(4.0))
        robot.stop()
        ticks = s.ticks
        assert wait_until(lambda: s.ticks >= ticks + 40)
        assert not s._stale and shown_z(s) == pytest.approx(4.0)
    finally:
        robot.stop()
        s.close()
