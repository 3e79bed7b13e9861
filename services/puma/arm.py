"""The arm controller role: what the PUMA proxy needs from whatever moves the joints.

An `Arm` is the joint-level controller of the PUMA 560: the simulated one (`SimArm`) or a
retrofitted real controller on a serial line (`SerialArm`). The proxy streams one joint
setpoint per control cycle and reads the joints back; the controller interpolates between
setpoints, enforces its own software joint limits and refuses a setpoint that jumps.

Units: joint angles in rad, joint 1 first, DH convention of PROTOCOL.md §1. Times in s.

Status, as the controller reports it:

    disconnected → connected → initializing → ready;   error from any state.

`initialize()` starts calibration and returns; the status stays `initializing` until the
controller reports it is done. After an error the arm holds and takes no setpoint until
`connect()` and `initialize()` succeed again; neither of them moves the joints.
"""

from __future__ import annotations

import math
import threading
from abc import ABC, abstractmethod
from typing import Any, Literal, Protocol, get_args, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from services.bus.errors import TelerobotError

ArmStatus = Literal["disconnected", "connected", "initializing", "ready", "error"]
ARM_STATUSES: frozenset[str] = frozenset(get_args(ArmStatus))
ArmKind = Literal["sim", "serial"]

Q = NDArray[np.float64]

# The controller's software joint limits (rad): the PUMA 560 table of PROTOCOL.md §1. They
# belong to the controller as much as to the kinematic model, and the fake controller runs
# as its own process without Pinocchio, so the table is kept here as plain numbers (the DH
# table of kinematics.py takes its limits from here).
JOINT_LIMITS_DEG: tuple[tuple[float, float], ...] = (
    (-160.0, 160.0),
    (-45.0, 225.0),
    (-225.0, 45.0),
    (-110.0, 170.0),
    (-100.0, 100.0),
    (-266.0, 266.0),
)
Q_LO_RAD: tuple[float, ...] = tuple(math.radians(lo) for lo, _ in JOINT_LIMITS_DEG)
Q_HI_RAD: tuple[float, ...] = tuple(math.radians(hi) for _, hi in JOINT_LIMITS_DEG)

# PUMA-like capabilities of the arm itself (rad/s, rad/s²): what the controller's servo can do.
# The proxy plans with lower limits (`PumaConfig`), so the servo always has headroom.
ARM_MAX_JOINT_SPEED_RAD_S: tuple[float, ...] = (2.5, 2.5, 2.5, 5.0, 5.0, 5.0)
ARM_MAX_JOINT_ACCEL_RAD_S2: tuple[float, ...] = (8.0, 8.0, 8.0, 20.0, 20.0, 20.0)

# The nominal "ready" pose qn of PROTOCOL.md §1 (`kinematics.qn`): where a simulated arm starts.
QN_RAD: tuple[float, ...] = (0.0, math.pi / 4, -math.pi, 0.0, math.pi / 4, 0.0)


class ArmError(TelerobotError):
    """The arm cannot do what was asked (not connected, not calibrated, link lost, ...)."""


@runtime_checkable
class Arm(Protocol):
    """The joint-level controller of a PUMA 560 (the proxy's only way to move the robot).

    Thread safety: every method may be called from any thread; `command` is called once per
    control cycle by the proxy's loop and never blocks on I/O.
    """

    @property
    def status(self) -> ArmStatus:
        """The controller status (see the module docstring)."""
        ...

    @property
    def last_error(self) -> str | None:
        """Why the arm is in `error`, for people; None when it never failed."""
        ...

    def connect(self) -> None:
        """Open the link (or re-open it after an error) and clear a latched fault.

        Status becomes `connected`; raises `ArmError` (status `error`) if the controller does
        not answer. Never moves the joints.
        """
        ...

    def initialize(self) -> None:
        """Start calibration; status `initializing` until the controller reports `ready`.

        Raises `ArmError` unless connected (or ready). Never moves the joints.
        """
        ...

    def read_joints(self) -> Q:
        """The latest measured joint angles (6,), rad.

        Raises `ArmError` before the first calibration has completed (the encoders are
        incremental: nothing is known before). After an error: the last value received.
        """
        ...

    def command(self, q_setpoint: Q) -> None:
        """Stream the joint setpoint (6,), rad, for this control cycle.

        Only in `ready`; ignored in any other status (so nothing queued before an error is
        ever executed after it). A setpoint outside the joint limits or too far from the
        measured joints puts the arm in `error`: the controller refuses jumps.
        """
        ...

    def stop(self) -> None:
        """Stop streaming and hold where the arm is now (decelerating within its limits)."""
        ...

    def estop(self) -> None:
        """Emergency stop: halt at once, arm power off; status `error` until re-connected."""
        ...

    def close(self) -> None:
        """Hold and release the link; status `disconnected`. Idempotent."""
        ...


class ArmBase(ABC):
    """What the backends share: status and last error under one lock, the precondition of
    `initialize`, and the checks `command` makes before it takes a setpoint.

    A backend sets `_lock`, `_status`, `_last_error` and `setpoints_ignored` in its
    constructor and defines `_fail_locked` (the lock held: `error`, hold, no more setpoints).
    """

    _lock: threading.RLock
    _status: ArmStatus
    _last_error: str | None
    setpoints_ignored: int

    @property
    def status(self) -> ArmStatus:
        with self._lock:
            return self._status

    @property
    def last_error(self) -> str | None:
        with self._lock:
            return self._last_error

    @abstractmethod
    def _fail_locked(self, why: str) -> None:
        """Go to `error` for `why` (kept if already in error); the caller holds the lock."""

    def _check_can_initialize(self) -> None:
        """ArmError unless connected or ready; the caller holds the lock."""
        if self._status not in ("connected", "ready"):
            raise ArmError(f"cannot initialize: arm is {self._status}")

    def _accept_setpoint(self, q_setpoint: Q) -> Q | None:
        """`command`'s setpoint as a joint vector, or None to drop it: counted in
        `setpoints_ignored` outside `ready`, an error when malformed. The caller holds the lock."""
        if self._status != "ready":
            self.setpoints_ignored += 1
            return None
        try:
            return as_joint_vector(q_setpoint, "setpoint")
        except ValueError as e:
            self._fail_locked(f"bad setpoint: {e}")
            return None


def as_joint_vector(q: Any, name: str = "q") -> Q:
    """`q` as a finite float vector (6,), or ValueError naming `name`."""
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (6,):
        raise ValueError(f"{name} must have 6 joint values, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr


def open_arm(kind: ArmKind, port: str | None = None, **opts: Any) -> Arm:
    """Open the arm backend `kind` (not yet connected).

    `sim`: a `SimArm` (`port` ignored); `serial`: a `SerialArm` on `port`, any pyserial URL
    (`/dev/ttyUSB0`, `socket://127.0.0.1:PORT`). `opts` go to the backend's constructor.
    pyserial is imported only for `serial`.
    """
    if kind == "sim":
        from services.puma.sim_arm import SimArm

        return SimArm(**opts)
    if kind == "serial":
        if not port:
            raise ValueError("a serial arm needs a port (a device path or pyserial URL)")
        from services.puma.serial_arm import SerialArm

        return SerialArm(port, **opts)
    raise ValueError(f"unknown arm kind {kind!r}: expected 'sim' or 'serial'")
