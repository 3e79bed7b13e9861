"""`open_arm(config)`: the arm backend a `ArmConfig` names, built and not yet connected.

`BACKENDS` names each `arm.driver` backend's class, imported only when that backend is built,
so the simulation and its tests never load pyserial; `arm_options` maps the configuration
to the class's constructor arguments.
"""

from __future__ import annotations

from typing import Any

from services.bus.registry import BackendRegistry
from services.control.arm.config import ArmConfig
from services.control.arm.driver import Arm

BACKENDS: BackendRegistry[Arm] = BackendRegistry(
    "arm.driver",
    "arm driver",
    {
        "sim": "services.control.arm.sim_arm:SimArm",
        "serial": "services.control.arm.serial_arm:SerialArm",
    },
)
"""Backend name (`arm.driver`) → class, constructed with `arm_options(config)`."""


def arm_options(config: ArmConfig) -> dict[str, Any]:
    """The constructor arguments of the backend `config.driver`."""
    if config.driver == "serial":
        return {
            "port": config.port,
            "baudrate": config.baudrate,
            "cycle_ms": config.serial_cycle_ms,
            "timeout_s": config.serial_timeout_s,
        }
    # The simulated arm powers on at home: the tool above the table, ready to work.
    return {"calibration_s": config.sim_calibration_s, "q_init": config.home_q}


def open_arm(config: ArmConfig) -> Arm:
    """The arm `config.driver` with its options, not yet connected (`Arm.connect` does that).

    Raises `ConfigError("arm.driver", …)` for a name without a backend (an `ArmConfig` built
    the ordinary way has already refused it).
    """
    return BACKENDS.build(config.driver, arm_options(config))
