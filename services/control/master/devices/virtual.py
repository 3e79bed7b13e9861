"""A master whose hand pose is set by program: the web console's virtual master, tests and
scripts drive the same `MasterDevice` protocol as a physical device."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.control.master.device import DeviceOptions, HandReading, MasterDevice

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig


@dataclass(frozen=True, slots=True)
class VirtualOptions(DeviceOptions):
    """`device = "virtual"`: no keys of its own; nobody holds it, so it engages at once."""

    engages_on_start: ClassVar[bool] = True

    def build(self, config: MasterConfig) -> MasterDevice:
        return VirtualMaster()


class VirtualMaster:
    """`MasterDevice` fed by `set_hand`, thread-safe.

    `set_hand` may be called from any thread (e.g. a bus callback of the web console) while
    the service's loop thread calls `read`; `read` returns the latest hand set. Forces sent
    to `display_force` are kept for whoever draws them (`displayed_force`).
    """

    may_idle = True
    """While clutched and not engaged the station may tick slowly: `wake` brings it back."""

    def __init__(self, name: str = "virtual") -> None:
        self._name = name
        self.wake = threading.Event()
        self._lock = threading.Lock()
        self._reading = HandReading(np.zeros(3), np.eye(3), False, None, 0)
        self._force = (np.zeros(3), np.zeros(3))

    @property
    def name(self) -> str:
        return self._name

    @property
    def can_display_force(self) -> bool:
        return True

    def open(self) -> None:
        """Nothing to connect."""

    def set_hand(
        self,
        p: ArrayLike,
        R: ArrayLike | None = None,
        clutch: bool = False,
        grip: float | None = None,
        buttons: int = 0,
    ) -> None:
        """Set the hand: p (3,) m, R (3, 3) or 9 floats row-major (None: identity), clutch
        True = master-shift pressed, grip 0 … 1 or None. Raises ValueError on a bad pose."""
        hand_R = np.eye(3) if R is None else np.asarray(R, dtype=float)
        reading = HandReading(np.asarray(p, dtype=float), hand_R, clutch, grip, buttons)
        with self._lock:
            self._reading = reading
        self.wake.set()

    def read(self, dt_s: float) -> HandReading:
        with self._lock:
            return self._reading

    def display_force(self, f: ArrayLike, c: ArrayLike) -> None:
        """Keep the wrench (master frame) for display."""
        force = (np.array(f, dtype=float).reshape(3), np.array(c, dtype=float).reshape(3))
        with self._lock:
            self._force = force

    def displayed_force(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The latest (f (3,) N, c (3,) N·m) given to display_force."""
        with self._lock:
            return self._force[0].copy(), self._force[1].copy()

    def close(self) -> None:
        """Nothing to release."""
