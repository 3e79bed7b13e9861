"""The `MasterDevice` role: whatever the operator's hand holds, reduced to a hand pose.

A device reports the hand pose in its own base frame (the *master frame*: for the desk
devices x to the operator's right, y away from the operator, z up), the state of the
master-shift (clutch) and of the grip. Devices that can push back display a wrench given in
that same frame. `backends.py` holds `open_master_device(config)`, which picks a backend
and imports its library lazily, so simulation and the tests of pure logic never load hidapi,
pyserial or websockets.

Each backend declares its own `[master]` keys as a `DeviceOptions` (how it is built), and
what it can do beyond the role as the capability Protocols below (`ShowsStatus`,
`MayIdle`, `ReportsRejected`, `VirtualHand`, `KeepsStats`), which the station checks once,
with `isinstance`, when it gets its device.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.errors import TelerobotError
from services.control.master.status_line import StatusInfo
from services.geometry import is_rotation

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig


class DeviceNotFound(TelerobotError):
    """The requested master device is not there. `found` lists what was found instead."""

    def __init__(self, message: str, found: list[str] | None = None) -> None:
        self.found = list(found or [])
        listing = "; ".join(self.found) if self.found else "nothing"
        super().__init__(f"{message} (found: {listing})")


class DeviceLost(TelerobotError):
    """An open master device stopped answering (unplugged, line cut, stream stalled)."""


@dataclass(frozen=True, slots=True)
class HandReading:
    """One sample of the operator's hand, in the master frame.

    hand_p: position (3,) in m. hand_R: orientation (3, 3), a rotation.
    clutch: True while the master-shift is pressed (master and slave disconnected).
    grip: 0 open … 1 closed, or None when the device has no grip input.
    buttons: raw button bitmask (bit i = button i pressed).
    The arrays are copied and made read-only.
    """

    hand_p: NDArray[np.float64]
    hand_R: NDArray[np.float64]
    clutch: bool
    grip: float | None = None
    buttons: int = 0

    def __post_init__(self) -> None:
        p = np.array(self.hand_p, dtype=float).reshape(-1)
        R = np.array(self.hand_R, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError("hand_p must be 3 finite numbers")
        if R.shape == (9,):
            R = R.reshape(3, 3)
        if not is_rotation(R):
            raise ValueError("hand_R must be a rotation")
        if self.grip is not None and not 0.0 <= float(self.grip) <= 1.0:
            raise ValueError("grip must be within 0 … 1")
        p.setflags(write=False)
        R.setflags(write=False)
        object.__setattr__(self, "hand_p", p)
        object.__setattr__(self, "hand_R", R)
        object.__setattr__(self, "clutch", bool(self.clutch))
        object.__setattr__(self, "grip", None if self.grip is None else float(self.grip))
        object.__setattr__(self, "buttons", int(self.buttons))


@runtime_checkable
class MasterDevice(Protocol):
    """A master device. Only the master service's loop thread calls these methods.

    name: a human-readable device name (goes into MasterState.device).
    can_display_force: True when `display_force` actually pushes on the operator's hand.
    open(): connect; raises DeviceNotFound when the device is absent.
    read(dt_s): the current hand; dt_s (s) is the time since the previous read, over which
        rate devices (SpaceMouse, keyboard) integrate and scripted ones advance.
    display_force(f, c): push on the hand with force f (3, N) and moment c (3, N·m), in the
        master frame; a no-op on devices that cannot.
    close(): release the device and leave it passive (no force).
    """

    @property
    def name(self) -> str: ...

    @property
    def can_display_force(self) -> bool: ...

    def open(self) -> None: ...

    def read(self, dt_s: float) -> HandReading: ...

    def display_force(self, f: ArrayLike, c: ArrayLike) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True, slots=True)
class DeviceOptions(ABC):
    """A device backend's own keys of the `[master]` table, and how the backend is built.

    Each backend declares a frozen dataclass of this kind beside itself, its fields named
    as users write the keys (`haply_url`, `arm_dh`, …) and checked in `__post_init__`
    (`ConfigError("master.<key>", …)`), registered under its `device` name in
    `backends.py`. `MasterConfig.from_mapping` hands it the keys that are not common.

    engages_on_start: the default of `MasterConfig.engage_on_start`: True for a device
    nobody holds (scripted, virtual), False for one an operator holds.
    """

    engages_on_start: ClassVar[bool] = False

    @abstractmethod
    def build(self, config: MasterConfig) -> MasterDevice:
        """The device for the station `config` (its common keys, e.g. `rate_hz`), not
        yet opened."""


# --- optional capabilities, checked once with isinstance when the device is built -----


@runtime_checkable
class ShowsStatus(Protocol):
    """A device with a place to show the station's state to its operator (the keyboard's
    terminal line); called on the loop thread with each master/state."""

    def show_status(self, info: StatusInfo) -> None: ...


@runtime_checkable
class MayIdle(Protocol):
    """A device whose station may tick slowly while clutched and not engaged (the virtual
    master, fed from outside): `may_idle` says it may, `wake` is set on any input."""

    may_idle: bool
    wake: threading.Event


@runtime_checkable
class ReportsRejected(Protocol):
    """A device that refuses bad input on its own link (the Haply's frames):
    `take_rejected()` returns the reasons since the last call, for the station to count
    and report."""

    def take_rejected(self) -> list[str]: ...


@runtime_checkable
class VirtualHand(Protocol):
    """A device whose hand is set by program (the web console, the tasks), from any thread:
    the station's `set_hand` method."""

    def set_hand(
        self,
        p: ArrayLike,
        R: ArrayLike | None = None,
        clutch: bool = False,
        grip: float | None = None,
        buttons: int = 0,
    ) -> None: ...


@runtime_checkable
class KeepsStats(Protocol):
    """A device that counts what happens on its link: `stats`, a dataclass snapshot, goes
    into the station's `status` as `device_stats`."""

    @property
    def stats(self) -> Any: ...
