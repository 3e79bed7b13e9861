"""What the arm backends (`SimArm`, `SerialArm`) share: status and last error under one lock,
the precondition of `initialize`, and the checks `command` makes before it takes a setpoint.
"""

from __future__ import annotations

import math
import threading
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from services.control.arm.driver import ArmError, ArmStatus, Q


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
    n: int
    """The number of joints."""

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
            return as_joint_vector(q_setpoint, "setpoint", self.n)
        except ValueError as e:
            self._fail_locked(f"bad setpoint: {e}")
            return None


def as_joint_vector(q: Any, name: str, n: int) -> Q:
    """`q` as a finite float vector (n,), or ValueError naming `name`."""
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have {n} joint values, got shape {arr.shape}")
    # On plain floats: a numpy reduction costs more than n checks (once per setpoint).
    if not all(map(math.isfinite, arr.tolist())):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr
