"""`open_master_device(config)`: the master device a `MasterConfig` names, built and opened.

`BACKENDS` maps each `master.device` name to a constructor that imports its backend, and
with it its library (hidapi, pyserial, websockets), only when called; `device_options` is
what the configuration passes to that constructor. Unlike the other roles the device comes
open: a station without its device is `DeviceNotFound` at start-up, with what was found.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from services.bus.errors import ConfigError
from services.master.config import DEVICE_KINDS, MasterConfig
from services.master.devices import MasterDevice


def _spacemouse(options: dict[str, Any]) -> MasterDevice:
    from services.master.hid_spacemouse import HidSpaceMouse

    return HidSpaceMouse(**options)


def _serial_arm(options: dict[str, Any]) -> MasterDevice:
    from services.master.serial_arm import SerialMasterArm

    return SerialMasterArm(**options)


def _keyboard(options: dict[str, Any]) -> MasterDevice:
    from services.master.keyboard import KeyboardMaster

    return KeyboardMaster(**options)


def _scripted(options: dict[str, Any]) -> MasterDevice:
    from services.master.scripted import ScriptedMaster

    return ScriptedMaster(**options)


def _virtual(options: dict[str, Any]) -> MasterDevice:
    from services.master.virtual import VirtualMaster

    return VirtualMaster(**options)


def _haply(options: dict[str, Any]) -> MasterDevice:
    from services.master.haply import HaplyMaster

    return HaplyMaster(**options)


def _haptic_sim(options: dict[str, Any]) -> MasterDevice:
    from services.master.haptic_sim import SimHapticMaster

    return SimHapticMaster(**options)


BACKENDS: Mapping[str, Callable[[dict[str, Any]], MasterDevice]] = {
    "spacemouse": _spacemouse,
    "serial_arm": _serial_arm,
    "keyboard": _keyboard,
    "scripted": _scripted,
    "virtual": _virtual,
    "haply": _haply,
    "haptic_sim": _haptic_sim,
}
"""Backend name (`master.device`) → constructor, called with `device_options(config)`."""


def device_options(config: MasterConfig) -> dict[str, Any]:
    """The constructor arguments of the backend `config.device`."""
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


def open_master_device(config: MasterConfig) -> MasterDevice:
    """The device `config.device` with its options, opened.

    Raises DeviceNotFound when the device is absent, ConfigError("master.device") for a
    name without a backend (a `MasterConfig` built the ordinary way has refused it already).
    """
    construct = BACKENDS.get(config.device)
    if construct is None:
        raise ConfigError(
            "master.device",
            f"unknown master device {config.device!r}; one of {', '.join(DEVICE_KINDS)}",
        )
    device = construct(device_options(config))
    device.open()
    return device
