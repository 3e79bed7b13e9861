"""`open_master_device(config)`: the master device a `MasterConfig` names, built and opened.

`BACKENDS` names each `master.device` backend's class, imported, and with it its library
(hidapi, pyserial, websockets), only when that backend is built; `device_options` maps the
configuration to the class's constructor arguments. Unlike the other roles the device comes
open: a station without its device is `DeviceNotFound` at start-up, with what was found.
"""

from __future__ import annotations

from typing import Any

from services.bus.registry import BackendRegistry
from services.control.master.config import MasterConfig
from services.control.master.devices import MasterDevice

BACKENDS: BackendRegistry[MasterDevice] = BackendRegistry(
    "master.device",
    "master device",
    {
        "spacemouse": "services.control.master.hid_spacemouse:HidSpaceMouse",
        "serial_arm": "services.control.master.serial_arm:SerialMasterArm",
        "keyboard": "services.control.master.keyboard:KeyboardMaster",
        "scripted": "services.control.master.scripted:ScriptedMaster",
        "virtual": "services.control.master.virtual:VirtualMaster",
        "haply": "services.control.master.haply:HaplyMaster",
        "haptic_sim": "services.control.master.haptic_sim:SimHapticMaster",
    },
)
"""Backend name (`master.device`) → class, constructed with `device_options(config)`."""


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
    device = BACKENDS.build(config.device, device_options(config))
    device.open()
    return device
