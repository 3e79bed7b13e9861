"""`open_force_sensor(config)`: the sensor backend a `ForceConfig` names, built, not opened.

`BACKENDS` maps each `force.sensor` name to a constructor that imports its backend only when
called, so the simulation and its tests never load pyserial; `sensor_options` is what the
configuration passes to that constructor. Backends: `SimSensor` (sim_sensor.py, the default:
contact with the simulated workcell), `SerialSensor` (serial_sensor.py, six ADC channels as
checksummed ASCII lines, docs/serial-force-protocol.md), `NetFTSensor` (netft.py, ATI Net
F/T RDT over UDP).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from services.bus.errors import ConfigError
from services.force.config import ForceConfig
from services.force.sensors import SENSOR_KINDS, ForceSensor


def _sim(options: dict[str, Any]) -> ForceSensor:
    from services.force.sim_sensor import SimSensor

    return SimSensor(**options)


def _serial(options: dict[str, Any]) -> ForceSensor:
    from services.force.serial_sensor import SerialSensor

    return SerialSensor(**options)


def _netft(options: dict[str, Any]) -> ForceSensor:
    from services.force.netft import NetFTSensor

    return NetFTSensor(**options)


BACKENDS: Mapping[str, Callable[[dict[str, Any]], ForceSensor]] = {
    "sim": _sim,
    "serial": _serial,
    "netft": _netft,
}
"""Backend name (`force.sensor`) → constructor, called with `sensor_options(config)`."""


def sensor_options(config: ForceConfig) -> dict[str, Any]:
    """The constructor arguments of the backend `config.sensor`."""
    if config.sensor == "serial":
        return {"port": config.port, "baudrate": config.baudrate}
    if config.sensor == "netft":
        return {
            "host": config.host,
            "port": config.netft_port,
            "counts_per_force": config.counts_per_force,
            "counts_per_torque": config.counts_per_torque,
        }
    return {
        "model": config.wrist_model(),
        "load": config.tool_load(),
        "noise_n": config.noise_n,
        "noise_nm": config.noise_nm,
        "probe_radius_m": config.probe_radius_m,
        "seed": config.seed,
        "block_density_kg_m3": config.block_density_kg_m3,
        "bottle_mass_kg": config.bottle_mass_kg,
        "inertia": config.inertia,
        "carried_contact": config.carried_contact,
    }


def build_sensor(kind: str, options: dict[str, Any]) -> ForceSensor:
    """The backend `kind` built from `options`; ConfigError("force.sensor") if there is none."""
    construct = BACKENDS.get(kind)
    if construct is None:
        raise ConfigError(
            "force.sensor", f"unknown sensor kind {kind!r} (known: {', '.join(SENSOR_KINDS)})"
        )
    return construct(options)


def open_force_sensor(config: ForceConfig) -> ForceSensor:
    """The sensor `config.sensor` with its options, not yet opened (`ForceSensor.open`)."""
    return build_sensor(config.sensor, sensor_options(config))
