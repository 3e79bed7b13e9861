"""`open_master_device(config)`: the master device a `MasterConfig` names, built and opened.

The one place that knows the devices. `DEVICES` names each `master.device` backend's options
class (`DeviceOptions`: its own `[master]` keys, and how it builds the backend), imported
only when that device is chosen or a `[master]` table holds keys the chosen one has not (to
find whose they are); its backend's library (hidapi, pyserial, websockets) only when the
device is opened. Unlike the other roles the
device comes open: a station without its device is `DeviceNotFound` at start-up, with what
was found.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, cast

from services.bus.registry import BackendRegistry
from services.control.master.device import DeviceOptions, MasterDevice

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig

DEVICES: BackendRegistry[DeviceOptions] = BackendRegistry(
    "master.device",
    "master device",
    {
        "spacemouse": "services.control.master.devices.spacemouse:SpaceMouseOptions",
        "serial_arm": "services.control.master.devices.master_arm.backend:MasterArmOptions",
        "keyboard": "services.control.master.devices.keyboard:KeyboardOptions",
        "scripted": "services.control.master.devices.scripted:ScriptedOptions",
        "virtual": "services.control.master.devices.virtual:VirtualOptions",
        "haply": "services.control.master.devices.haply.backend:HaplyOptions",
        "haptic_sim": "services.control.master.backends:HapticSimOptions",
    },
)
"""Device name (`master.device`) → its options class, in the order `from_mapping` checks
another device's keys in."""


def options_class(device: str) -> type[DeviceOptions]:
    """The options class of `device` (ConfigError("master.device") for an unknown name)."""
    return cast(type[DeviceOptions], DEVICES.load(device))


@dataclass(frozen=True, slots=True)
class HapticSimOptions(DeviceOptions):
    """`haptic_sim`, the simulated haptic device of the passivity lab (docs/passivity.md):
    no keys of its own; its module belongs with the passivity work, so its options are
    here."""

    engages_on_start: ClassVar[bool] = True

    def build(self, config: MasterConfig) -> MasterDevice:
        from services.control.master.haptic_sim import SimHapticMaster

        return SimHapticMaster()


def open_master_device(config: MasterConfig) -> MasterDevice:
    """The device `config.device` with its options, opened.

    Raises DeviceNotFound when the device is absent.
    """
    device = config.options.build(config)
    device.open()
    return device
