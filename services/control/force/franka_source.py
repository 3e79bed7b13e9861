"""`FrankaWrenchSource`: the Franka's own estimate of the external wrench as the force sensor,
for an FR3 (or Panda) with no F/T sensor at its wrist — `[force] sensor = "franka"`.

libfranka estimates the wrench on the end effector from its joint torque sensors
(`O_F_ext_hat_K`: force N and moment N·m at the stiffness frame K, in the robot's base frame
O). The arm's libfranka driver publishes each state the robot sends in its shared block
(services/control/arm/franka/shm.py, one per robot address on this host): this source
reads it there — libfranka allows one client per robot, and that is the arm — and gives
the wrench at the flange origin in the flange frame, which the force service turns into the
tool frame at the tool point like any wrist sensor's (the sensor frame R_s is the flange:
`sensor_p_m`, `sensor_R` at their identity defaults).

It is an estimate, not a measurement: from joint torques through the robot's dynamic model,
with the load the robot was told of (Desk's end-effector settings), so the force service
does no gravity compensation of its own for it (the load is the robot's), and its name in
`sensor_status` says `estimate`. Its quality is the robot's (a few N on a real FR3 at rest);
franky-sim reports zero.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from services.control.arm.franka.shm import Shared, state_path
from services.control.force.accounting import StreamAccounting
from services.control.force.events import EventSink, ignore_event
from services.control.force.sensors import Reading, SensorError


class FrankaWrenchSource(StreamAccounting):
    """The external wrench estimate of the Franka at `robot_ip`, read from the arm's block.

    `open()` attaches the block (SensorError when no libfranka arm of that address runs on
    this host); `read()` returns the wrench of each state the robot sent since the last call
    (the newest), None when there is none: the robot's state stops while the arm is not
    connected. `device_seq` is the robot's cycle count.
    """

    seq_modulo = 1 << 53
    unit = "states"

    def __init__(
        self, robot_ip: str, *, path: Path | None = None, on_event: EventSink = ignore_event
    ) -> None:
        self.on_event = on_event
        self.robot_ip = robot_ip
        self._path = path if path is not None else state_path(robot_ip)
        self._shm: Shared | None = None
        self._last_wall = 0
        self._count = 0
        self._ino = 0
        self._checked_s = 0.0
        self._init_accounting()

    @property
    def name(self) -> str:
        return f"franka estimate (O_F_ext_hat_K) {self.robot_ip}"

    def open(self) -> None:
        if self._shm is not None:
            return
        if not self._path.exists():
            raise SensorError(
                f"no libfranka arm for {self.robot_ip} on this host ({self._path}): the franka "
                "force source reads the arm's state; start the arm with driver = libfranka"
            )
        self._shm = Shared.attach(self._path)
        self._ino = self._path.stat().st_ino

    def read(self) -> Reading | None:
        shm = self._shm
        if shm is None:
            raise SensorError("franka force source: read before open")
        s = shm.snapshot()
        if s.wall_ns == self._last_wall:
            self._reattach_if_replaced()
            return None
        self._last_wall = s.wall_ns
        self._count += 1
        O_T_EE = s.O_T_EE.reshape((4, 4), order="F")
        EE_T_K = s.EE_T_K.reshape((4, 4), order="F")
        F_T_EE = _identity_if_zero(s.F_T_EE.reshape((4, 4), order="F"))
        O_T_K = O_T_EE @ _identity_if_zero(EE_T_K)
        O_T_F = O_T_EE @ np.linalg.inv(F_T_EE)
        f_O = s.O_F_ext_hat_K[:3]
        m_O = s.O_F_ext_hat_K[3:]
        if not (np.all(np.isfinite(f_O)) and np.all(np.isfinite(m_O))):
            self._bad_data("a non-finite wrench estimate", "not_finite")
            return None
        # the moment about the flange origin: m_F = m_K + (p_K − p_F) × f
        m_at_F = m_O + np.cross(O_T_K[:3, 3] - O_T_F[:3, 3], f_O)
        R_OF = O_T_F[:3, :3]
        f = R_OF.T @ f_O
        m = R_OF.T @ m_at_F
        return Reading(
            "wrench",
            (float(f[0]), float(f[1]), float(f[2]), float(m[0]), float(m[1]), float(m[2])),
            device_seq=s.cycles,
            estimate=True,
        )

    def _reattach_if_replaced(self) -> None:
        """The arm restarted (a new block at the path): follow it, once a second at most."""
        now = time.monotonic()
        if now - self._checked_s < 1.0:
            return
        self._checked_s = now
        try:
            ino = self._path.stat().st_ino
        except OSError:
            return
        if self._shm is not None and ino != self._ino:
            self._shm.close()
            self._shm = Shared.attach(self._path)
            self._ino = ino

    def close(self) -> None:
        shm, self._shm = self._shm, None
        if shm is not None:
            shm.close()


def _identity_if_zero(T: np.ndarray) -> np.ndarray:
    """A transform from a block not yet written (all zeros) as the identity."""
    return np.eye(4) if T[3, 3] == 0.0 else T
