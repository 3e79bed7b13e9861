"""The master displays the wrist force however old its robot-host stamp is: over a link of
hundreds of ms round trip (or with the robot host's clock behind or ahead of the operator's)
every sample is "old" by `t_ns`, and it is still the newest contact there is. What blanks the
display is a stream that stops arriving."""

from __future__ import annotations

import threading
import time

import pytest

from services.bus import keys
from services.bus.messages import IDENTITY_R, ForceSample, RobotState
from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from tests.conftest import Net, wait_until

pytestmark = [pytest.mark.system, pytest.mark.timeout(60)]


@pytest.mark.parametrize("stamp_offset_s", [-0.35, -5.0, 3.0])
def test_the_force_is_shown_whatever_its_stamp_and_blanked_when_the_stream_stops(
    net: Net, stamp_offset_s: float
) -> None:
    """-0.35 s: the one-way delay of a 700 ms link; -5 s and +3 s: robot clocks off by that."""
    cfg = MasterConfig(
        master_id="p1", device="haptic_sim", rate_hz=200.0, force_ramp_s=0.0, max_force_n=10.0
    )
    station = MasterService(net.node("master", instance="p1"), cfg)
    robot = net.node("robot")
    force_pub = robot.publisher(keys.FORCE)
    state_pub = robot.publisher(keys.STATE)
    stop = threading.Event()

    def robot_side() -> None:  # 200 Hz, every stamp shifted by stamp_offset_s
        k = 0
        while not stop.is_set():
            k += 1
            t_ns = time.time_ns() + int(stamp_offset_s * 1e9)
            state_pub.put(
                RobotState(
                    seq=k,
                    t_ns=t_ns,
                    status="moving",
                    q=(0.0,) * 6,
                    tool_p=(0.5, 0.0, 0.5),
                    tool_R=IDENTITY_R,
                    flange_p=(0.5, 0.0, 0.7),
                    flange_R=IDENTITY_R,
                    engage=1,
                    cmd_seq=k,
                )
            )
            force_pub.put(ForceSample(seq=k, t_ns=t_ns, f=(0.0, 0.0, 4.0), c=(0.0, 0.0, 0.0)))
            stop.wait(0.005)

    worker = threading.Thread(target=robot_side, daemon=True)
    worker.start()
    try:
        assert wait_until(lambda: station.ticks > 20 and not station._stale), "never fresh"
        assert wait_until(lambda: float(station.displayed.f[2]) == pytest.approx(4.0))
        # The stream stops: force_stale_ms later (20 ticks at 200 Hz) the display is blank,
        # not first when the stamps say so (+3 s: three seconds later).
        stop.set()
        worker.join(timeout=2.0)
        stopped, ticks = time.monotonic(), station.ticks
        assert wait_until(lambda: station._stale and not station.displayed.f.any())
        assert station.ticks - ticks <= 100
        assert time.monotonic() - stopped >= cfg.force_stale_ms / 1e3 * 0.9  # not blanked at once
    finally:
        stop.set()
        worker.join(timeout=2.0)
        station.close()
