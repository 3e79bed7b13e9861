"""`open_arm(config, model)`: the arm driver an `ArmConfig` names, built and not yet connected.

`BACKENDS` names each `arm.driver` backend's class, imported only when that backend is built,
so the simulation and its tests never load pyserial; `arm_options` maps the configuration
to the class's constructor arguments.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from services.bus.errors import ConfigError
from services.bus.registry import BackendRegistry
from services.control.arm.config import ArmConfig
from services.control.arm.driver import Arm
from services.control.arm.model import ArmModel, load_model

if TYPE_CHECKING:
    from services.world.workcell.channel import ArmChannel

BACKENDS: BackendRegistry[Arm] = BackendRegistry(
    "arm.driver",
    "arm driver",
    {
        "sim": "services.control.arm.sim_arm:SimArm",
        "serial": "services.control.arm.serial_arm:SerialArm",
        "libfranka": "services.control.arm.franka.driver:FrankaArm",
    },
)
"""Backend name (`arm.driver`) → class, constructed with `arm_options(config)`."""


def arm_options(
    config: ArmConfig,
    model: ArmModel | None = None,
    node: Any = None,
    channel: ArmChannel | None = None,
) -> dict[str, Any]:
    """The constructor arguments of the backend `config.driver`, for `model` (default: the
    configuration's); `node`: the service's, for a simulated arm on the workcell's physics;
    `channel`: the `ArmChannel` of a workcell in this process (`sim_physics = "embedded"`)."""
    arm = model if model is not None else load_model(config.model)
    config = config.bind(arm)
    if config.driver == "serial":
        return {
            "port": config.port,
            "baudrate": config.baudrate,
            "cycle_ms": config.serial_cycle_ms,
            "timeout_s": config.serial_timeout_s,
        }
    if config.driver == "libfranka":
        from services.control.arm.franka.params import load_params

        return {
            "robot_ip": config.robot_ip,
            "model": arm,
            "params": load_params(arm),
            "realtime": config.franka_realtime,
            "watchdog_s": config.franka_watchdog_s,
            "gripper": config.franka_gripper,
        }
    # The simulated arm powers on at home: the tool above the table, ready to work.
    options = {"calibration_s": config.sim_calibration_s, "q_init": config.home_q, "model": arm}
    if config.sim_physics == "workcell":
        if node is None:
            raise ConfigError("arm.sim_physics", "the workcell's physics needs the bus")
        options["node"] = node
    elif config.sim_physics == "embedded":
        if channel is None:
            raise ConfigError(
                "arm.sim_physics", "embedded needs the workcell in this process (telerobot arm)"
            )
        options["channel"] = channel
    return options


def open_arm(
    config: ArmConfig,
    model: ArmModel | None = None,
    node: Any = None,
    channel: ArmChannel | None = None,
) -> Arm:
    """The arm `config.driver` with its options, not yet connected (`Arm.connect` does that).

    Raises `ConfigError("arm.driver", …)` for a name without a backend (an `ArmConfig` built
    the ordinary way has already refused it).
    """
    return BACKENDS.build(config.driver, arm_options(config, model, node, channel))
