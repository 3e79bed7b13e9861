"""`open_force_sensor(config)`: the sensor backend a `ForceConfig` names, built, not opened.

`BACKENDS` names each `force.sensor` backend's class, imported only when that backend is
built, so the simulation and its tests never load pyserial; `sensor_options` maps the
configuration to the class's constructor arguments.

Backends: `SimSensor` (sim_sensor.py, the default: contact with the simulated workcell),
`SerialSensor` (serial_sensor.py, six ADC channels as checksummed ASCII lines,
docs/serial-force-protocol.md), `NetFTSensor` (netft.py, ATI Net F/T RDT over UDP),
`FrankaWrenchSource` (franka_source.py, a Franka's own wrench estimate, docs/franka.md).
"""

from __future__ import annotations

from typing import Any

from services.bus.registry import BackendRegistry
from services.control.force.config import ForceConfig
from services.control.force.sensors import ForceSensor

BACKENDS: BackendRegistry[ForceSensor] = BackendRegistry(
    "force.sensor",
    "sensor kind",
    {
        "sim": "services.control.force.sim_sensor:SimSensor",
        "serial": "services.control.force.serial_sensor:SerialSensor",
        "netft": "services.control.force.netft:NetFTSensor",
        "franka": "services.control.force.franka_source:FrankaWrenchSource",
    },
)
"""Backend name (`force.sensor`) → class, constructed with `sensor_options(config)`."""


def sensor_options(config: ForceConfig) -> dict[str, Any]:
    """The constructor arguments of the backend `config.sensor`."""
    if config.sensor == "serial":
        return {"port": config.port, "baudrate": config.baudrate}
    if config.sensor == "franka":
        return {"robot_ip": config.host}
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
        "seed": config.seed,
        "inertia": config.inertia,
    }


def open_force_sensor(config: ForceConfig) -> ForceSensor:
    """The sensor `config.sensor` with its options, not yet opened (`ForceSensor.open`)."""
    return BACKENDS.build(config.sensor, sensor_options(config))
