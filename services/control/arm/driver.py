"""The arm driver role: what the arm service needs from whatever moves the joints.

An `Arm` is the joint-level controller of the arm model in use: the simulated one (`SimArm`,
any model), or a real controller — the retrofitted PUMA 560 controller on a serial line
(`SerialArm`). The service streams one joint setpoint per control cycle and reads the joints
back; the controller interpolates between setpoints, enforces its own software joint limits
and refuses a setpoint that jumps.

Units: joint angles in rad, the model's n joints, joint 1 first. Times in s.

Status, as the controller reports it:

    disconnected → connected → initializing → ready;   error from any state.

`initialize()` starts calibration and returns; the status stays `initializing` until the
controller reports it is done. After an error the arm holds and takes no setpoint until
`connect()` and `initialize()` succeed again; neither of them moves the joints.

This module holds the role and what it publishes (its statuses, its error); `arm_base.py`
what the backends share, `backends.py` `open_arm(config, model)`, which picks a backend and
imports it lazily.
"""

from __future__ import annotations

from typing import Literal, Protocol, get_args, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from services.bus.errors import TelerobotError

ArmStatus = Literal["disconnected", "connected", "initializing", "ready", "error"]
ARM_STATUSES: frozenset[str] = frozenset(get_args(ArmStatus))
DriverName = Literal["sim", "serial", "libfranka"]

Q = NDArray[np.float64]


class ArmError(TelerobotError):
    """The arm cannot do what was asked (not connected, not calibrated, link lost, ...)."""


@runtime_checkable
class Arm(Protocol):
    """The joint-level controller of the arm (the service's only way to move the robot).

    Thread safety: every method may be called from any thread; `command` is called once per
    control cycle by the proxy's loop and never blocks on I/O.

    A driver may also offer `preflight() -> str | None`: what is plainly missing before
    `connect` (a serial device that does not exist, no robot address), said by the service
    at start-up as a warning and an `error` event.
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
        """The latest measured joint angles (n,), rad.

        Raises `ArmError` before the first calibration has completed (the encoders are
        incremental: nothing is known before). After an error: the last value received.
        """
        ...

    def command(self, q_setpoint: Q) -> None:
        """Stream the joint setpoint (n,), rad, for this control cycle.

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


@runtime_checkable
class Gripping(Protocol):
    """An arm driver that also drives a gripper (the Franka Hand): an optional capability,
    checked once with `isinstance`."""

    def grip(self, grip: float) -> None:
        """Close the gripper to `grip` (0 open … 1 closed; the newest wins). Never blocks;
        ignored unless the arm is `ready`."""
        ...


@runtime_checkable
class Clocked(Protocol):
    """An arm driver whose robot keeps its own clock (franky-sim runs slower than real time
    on a loaded machine): the service's control loop advances motions by the robot's time,
    so its setpoints never run ahead of what the robot can follow. Optional, checked once."""

    def robot_elapsed_s(self, wall_dt_s: float) -> float:
        """The robot's time since the last call (s); `wall_dt_s` when it keeps none now."""
        ...
