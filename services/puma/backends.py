"""`open_arm(config)`: the arm backend a `PumaConfig` names, built and not yet connected.

`BACKENDS` maps each `puma.arm` name to a constructor that imports its backend only when
called, so the simulation and its tests never load pyserial; `arm_options` is what the
configuration passes to that constructor.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from services.bus.errors import ConfigError
from services.puma.arm import Arm, ArmKind
from services.puma.config import PumaConfig


def _sim(options: dict[str, Any]) -> Arm:
    from services.puma.sim_arm import SimArm

    return SimArm(**options)


def _serial(options: dict[str, Any]) -> Arm:
    from services.puma.serial_arm import SerialArm

    return SerialArm(**options)


BACKENDS: Mapping[ArmKind, Callable[[dict[str, Any]], Arm]] = {"sim": _sim, "serial": _serial}
"""Backend name (`puma.arm`) → constructor, called with `arm_options(config)`."""


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
    construct = BACKENDS.get(config.arm)
    if construct is None:
        raise ConfigError(
            "puma.arm", f"unknown arm {config.arm!r}, expected one of {sorted(BACKENDS)}"
        )
    return construct(arm_options(config))
