"""A stand-in robot host for master-station tests: robot/state and robot/force at 200 Hz."""

from __future__ import annotations

import threading
import time

from services.bus import keys
from services.bus.messages import IDENTITY_R, ForceSample, RobotState
from services.bus.node import Node


def moving_state(seq: int, t_ns: int) -> RobotState:
    """The arm moving, tool at (0.5, 0, 0.5) m in world axes, engagement 1."""
    return RobotState(
        seq=seq,
        t_ns=t_ns,
        status="moving",
        q=(0.0,) * 6,
        tool_p=(0.5, 0.0, 0.5),
        tool_R=IDENTITY_R,
        flange_p=(0.5, 0.0, 0.7),
        flange_R=IDENTITY_R,
        engage=1,
        cmd_seq=seq,
    )


class RobotSide:
    """Publishes a state and the wrist force `f_n` every 5 ms until `stop()`, every stamp
    shifted by `stamp_offset_s` (a late link, or a robot clock off the operator's)."""

    def __init__(
        self, node: Node, f_n: tuple[float, float, float], stamp_offset_s: float = 0.0
    ) -> None:
        self._state = node.publisher(keys.STATE)
        self._force = node.publisher(keys.FORCE)
        self._f = f_n
        self._offset_ns = int(stamp_offset_s * 1e9)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            k += 1
            t_ns = time.time_ns() + self._offset_ns
            self._state.put(moving_state(k, t_ns))
            self._force.put(ForceSample(seq=k, t_ns=t_ns, f=self._f, c=(0.0, 0.0, 0.0)))
            self._stop.wait(0.005)

    def stop(self) -> None:
        """No more samples once this returns."""
        self._stop.set()
        self._thread.join(timeout=2.0)
