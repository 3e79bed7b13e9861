"""The `MasterDevice` role: whatever the operator's hand holds, reduced to a hand pose.

A device reports the hand pose in its own base frame (the *master frame*: for the desk
devices x to the operator's right, y away from the operator, z up), the state of the
master-shift (clutch) and of the grip. Devices that can push back display a wrench given in
that same frame. `open_device` picks a backend by name and imports its library lazily, so
simulation and the tests of pure logic never load hidapi, pyserial or websockets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.errors import TelerobotError
from services.geometry import is_rotation
from services.master.config import DEVICE_KINDS, MasterConfig


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


def open_device(kind: str, **opts: Any) -> MasterDevice:
    """Build the backend `kind` with `opts`, open it and return it.

    kind: `spacemouse` (HidSpaceMouse), `serial_arm` (SerialMasterArm), `keyboard`
    (KeyboardMaster), `scripted` (ScriptedMaster), `virtual` (VirtualMaster), `haply`
    (HaplyMaster), `haptic_sim` (SimHapticMaster: a simulated device and operator); `opts`
    are the backend's constructor arguments. Raises DeviceNotFound when the device is absent
    and ValueError for an unknown kind.
    """
    device: MasterDevice
    if kind == "spacemouse":
        from services.master.hid_spacemouse import HidSpaceMouse

        device = HidSpaceMouse(**opts)
    elif kind == "serial_arm":
        from services.master.serial_arm import SerialMasterArm

        device = SerialMasterArm(**opts)
    elif kind == "keyboard":
        from services.master.keyboard import KeyboardMaster

        device = KeyboardMaster(**opts)
    elif kind == "scripted":
        from services.master.scripted import ScriptedMaster

        device = ScriptedMaster(**opts)
    elif kind == "virtual":
        from services.master.virtual import VirtualMaster

        device = VirtualMaster(**opts)
    elif kind == "haply":
        from services.master.haply import HaplyMaster

        device = HaplyMaster(**opts)
    elif kind == "haptic_sim":
        from services.master.haptic_sim import SimHapticMaster

        device = SimHapticMaster(**opts)
    else:
        raise ValueError(f"unknown master device {kind!r}; one of {', '.join(DEVICE_KINDS)}")
    device.open()
    return device


def device_options(config: MasterConfig) -> dict[str, Any]:
    """The `open_device` options a MasterConfig implies for its `device`."""
    rate = {
        "deadband": config.deadband,
        "sensitivity": config.sensitivity,
        "full_speed_m_s": config.full_speed_m_s,
        "full_rate_rad_s": config.full_rate_rad_s,
    }
    if config.device == "spacemouse":
        return {
            "path": config.port or None,
            "clutch_button": config.clutch_button,
            "grip_button": config.grip_button,
            **rate,
        }
    if config.device == "serial_arm":
        return {
            "url": config.port,
            "dh": config.arm_dh,
            "baudrate": config.baudrate,
            "stream_rate_hz": config.rate_hz,
            "max_joint_torque_nm": config.max_joint_torque_nm,
        }
    if config.device == "keyboard":
        return {"tty_path": config.port or None, "sensitivity": config.sensitivity}
    if config.device == "scripted":
        return {"script": config.script}
    if config.device == "haply":
        return {
            "url": config.haply_url,
            "deadman_button": config.clutch_button,
            "grip_button": config.grip_button,
            "max_force_n": config.haply_max_force_n,
        }
    return {}


def open_master(config: MasterConfig) -> MasterDevice:
    """Open the device a MasterConfig names (see `open_device`)."""
    return open_device(config.device, **device_options(config))
