"""`open_arm(config)`: the arm backend a `PumaConfig` names, built and not yet connected.

`BACKENDS` names each `puma.arm` backend's class, imported only when that backend is built,
so the simulation and its tests never load pyserial; `arm_options` maps the configuration
to the class's constructor arguments.
"""

from __future__ import annotations

from typing import Any

from services.bus.registry import BackendRegistry
from services.control.puma.arm import Arm
from services.control.puma.config import PumaConfig

BACKENDS: BackendRegistry[Arm] = BackendRegistry(
    "puma.arm",
    "arm",
    {
        "sim": "services.control.puma.sim_arm:SimArm",
        "serial": "services.control.puma.serial_arm:SerialArm",
    },
)
"""Backend name (`puma.arm`) → class, constructed with `arm_options(config)`."""


def arm_options(config: PumaConfig) -> dict[str, Any]:
    """The constructor arguments of the backend `config.arm`."""
    if config.arm == "serial":
        return {
            "port": config.port,
            "baudrate": config.baudrate,
            "cycle_ms": config.serial_cycle_ms,
            "timeout_s": config.serial_timeout_s,
        }
    # The simulated arm powers on at home: the tool above the table, ready to work.
    return {"calibration_s": config.sim_calibration_s, "q_init": config.home_q}


def open_arm(config: PumaConfig) -> Arm:
    """The arm `config.arm` with its options, not yet connected (`Arm.connect` does that).

    Raises `ConfigError("puma.arm", …)` for a name without a backend (a `PumaConfig` built
    the ordinary way has already refused it).
    """
    return BACKENDS.build(config.arm, arm_options(config))
