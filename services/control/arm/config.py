"""Configuration of the arm service: its model, driver, rates and motion limits.

Read once at start-up (from the deployment TOML's `[arm]` table via `ArmConfig.from_mapping`)
into a frozen dataclass; a bad or misspelt key raises `ConfigError("arm.<key>", …)`. What
depends on the arm model (the joint limits and home pose, n values each, the step bound) is
left empty here and filled from the model by `bind(model)`, which checks what was given
against it: a home pose outside the joint limits, a speed above what the model says its
joints can do, or a vector of the wrong length is an error naming the key.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal, get_args

from services.bus.bounds import check_config, short
from services.bus.config import section
from services.bus.errors import ConfigError
from services.control.arm.driver import DriverName
from services.control.arm.model import DEFAULT_MODEL, ArmModel

SIM_PHYSICS = ("own", "workcell", "embedded")
"""Whose physics a `sim` arm's joints are (ArmConfig.sim_physics)."""

#: the physical bound (services/bus/bounds.py) each numeric setting must respect
_KINDS: dict[str, str] = {
    "state_rate_hz": "rate_hz",
    "control_rate_hz": "rate_hz",
    "max_tool_speed_m_s": "speed_m_s",
    "max_tool_rot_speed_rad_s": "rot_speed_rad_s",
    "serial_timeout_s": "timeout_s",
    "sim_calibration_s": "duration_s",
    "max_following_error_rad": "joint_rad",
    "max_dp_m": "displacement_m",
    "teleop_settle_s": "duration_s",
    "event_interval_s": "duration_s",
    "franka_watchdog_s": "timeout_s",
}


@dataclass(frozen=True, slots=True)
class ArmConfig:
    """The arm service's settings. Units are in the names; joint tuples are joint 1 first.

    `model`: a shipped model's name (`puma560`, `fr3`, `ur5e`) or the path of an arm's TOML
    (services/control/arm/model.py). `driver`: what moves the joints (`sim` for any model;
    `serial` for the retrofitted PUMA 560 controller).

    The arm plans every motion within `max_joint_speed_rad_s`, `max_joint_accel_rad_s2`
    (default: the model's planning limits), `max_tool_speed_m_s` (tool point) and
    `max_tool_rot_speed_rad_s` (tool frame), and its safety filter enforces them on every
    setpoint whatever the source. They must not exceed what the model's joints can do.
    `home_q` (default: the model's `home`) is where `home` goes and the simulated arm powers
    on. `max_target_step_m` / `max_target_step_rad` (default: the model's): a streamed
    target further than this from the previous one is refused.

    `sim_physics` (driver `sim`): whose physics the simulated arm's joints are: `own` (the
    arm alone, in this process), `workcell` (the cell's, owned by the `workcell` service:
    the arm then touches the objects; docs/sim.md) or `embedded` (the same cell, the
    workcell service run inside the arm's process: setpoints and joints pass in memory,
    no bus hop; the sim profile's).
    `libfranka` (a Franka FR3 or Panda, docs/franka.md) needs `robot_ip`; `franka_realtime`
    is libfranka's real-time check (`auto`: on where the kernel has a real-time policy, else
    off and said at start-up), `franka_watchdog_s` how long without the robot's state is a
    lost link, `franka_gripper` whether to drive the Franka Hand.
    """

    model: str = DEFAULT_MODEL
    driver: DriverName = "sim"
    state_rate_hz: float = 250.0
    control_rate_hz: float = 500.0
    max_joint_speed_rad_s: tuple[float, ...] = ()
    max_joint_accel_rad_s2: tuple[float, ...] = ()
    max_tool_speed_m_s: float = 0.5
    max_tool_rot_speed_rad_s: float = 1.5
    home_q: tuple[float, ...] = ()
    port: str | None = None
    baudrate: int = 115_200
    serial_cycle_ms: float = 28.0
    serial_timeout_s: float = 0.1
    sim_calibration_s: float = 0.5
    sim_physics: str = "own"
    max_following_error_rad: float = 0.35
    max_dp_m: float = 2.0
    max_target_step_m: float = 0.0
    max_target_step_rad: float = 0.0
    teleop_settle_s: float = 0.2
    event_interval_s: float = 1.0
    robot_ip: str | None = None
    franka_realtime: Literal["auto", "enforce", "ignore"] = "auto"
    franka_watchdog_s: float = 0.5
    franka_gripper: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.model, str) or not self.model:
            raise ConfigError("arm.model", "must be a model name or the path of an arm's TOML")
        _positive(self, "state_rate_hz")
        if self.state_rate_hz < 100.0:
            raise ConfigError("arm.state_rate_hz", "must be ≥ 100 Hz (PROTOCOL §3)")
        _positive(self, "control_rate_hz")
        if self.control_rate_hz < self.state_rate_hz:
            raise ConfigError("arm.control_rate_hz", "must be ≥ state_rate_hz")
        for key in (
            "max_tool_speed_m_s",
            "max_tool_rot_speed_rad_s",
            "serial_timeout_s",
            "max_following_error_rad",
            "max_dp_m",
            "teleop_settle_s",
            "event_interval_s",
        ):
            _positive(self, key)
        for key in ("max_target_step_m", "max_target_step_rad"):
            if _number(key, getattr(self, key)) < 0.0:
                raise ConfigError(f"arm.{key}", "must be ≥ 0 (0: the model's)")
        if self.max_target_step_m > 1.0:
            raise ConfigError("arm.max_target_step_m", "must be ≤ 1 m")
        if self.max_target_step_rad > math.pi:
            raise ConfigError("arm.max_target_step_rad", "must be ≤ π")
        if self.driver not in get_args(DriverName):
            names = ", ".join(get_args(DriverName))
            raise ConfigError("arm.driver", f"must be one of {names}, got {self.driver!r}")
        if self.driver == "serial" and not (isinstance(self.port, str) and self.port):
            raise ConfigError("arm.port", "a serial arm needs a port (device or pyserial URL)")
        if self.port is not None and not isinstance(self.port, str):
            raise ConfigError("arm.port", "must be a string")
        if isinstance(self.baudrate, bool) or not isinstance(self.baudrate, int):
            raise ConfigError("arm.baudrate", "must be an integer")
        if self.baudrate <= 0:
            raise ConfigError("arm.baudrate", "must be > 0")
        _positive(self, "serial_cycle_ms")
        if self.serial_cycle_ms > 28.0:
            raise ConfigError("arm.serial_cycle_ms", "must be ≤ 28 ms (the PUMA setpoint cycle)")
        _non_negative(self, "sim_calibration_s")
        if self.sim_physics not in SIM_PHYSICS:
            raise ConfigError(
                "arm.sim_physics",
                f"must be one of {', '.join(SIM_PHYSICS)}, got {short(repr(self.sim_physics))}",
            )
        _positive(self, "franka_watchdog_s")
        if self.robot_ip is not None and not _host(self.robot_ip):
            raise ConfigError("arm.robot_ip", "must be an IP address or a host name")
        if self.driver == "libfranka" and self.robot_ip is None:
            raise ConfigError("arm.robot_ip", "the libfranka driver needs the robot's address")
        check_config("arm", self, _KINDS)

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any]) -> ArmConfig:
        """From a TOML `[arm]` table (the bus's one section reader: an unknown key or a
        value of the wrong type is an error naming `arm.<key>`)."""
        return section(cls, table, "arm")

    def bind(self, model: ArmModel) -> ArmConfig:
        """This configuration with everything the model decides filled in and checked
        against it (n values each, within its limits): ConfigError naming the key."""
        if self.driver == "libfranka" and model.n != 7:
            raise ConfigError(
                "arm.driver", f"libfranka drives Franka's 7-joint arms, not {model.name}"
            )
        if self.driver == "serial" and model.name != "puma560":
            raise ConfigError(
                "arm.driver", f"the serial driver is the PUMA 560 controller's, not {model.name}"
            )
        speed = self.max_joint_speed_rad_s or model.plan_speed_rad_s
        accel = self.max_joint_accel_rad_s2 or model.plan_accel_rad_s2
        _n_positive("max_joint_speed_rad_s", speed, [j.max_speed for j in model.joints])
        _n_positive("max_joint_accel_rad_s2", accel, [j.max_accel for j in model.joints])
        home = model.check_joints("arm.home_q", list(self.home_q or model.home))
        return replace(
            self,
            max_joint_speed_rad_s=tuple(float(x) for x in speed),
            max_joint_accel_rad_s2=tuple(float(x) for x in accel),
            home_q=home,
            max_target_step_m=self.max_target_step_m or model.max_target_step_m,
            max_target_step_rad=self.max_target_step_rad or model.max_target_step_rad,
        )


def _host(value: Any) -> bool:
    """An address libfranka can dial: a host name or IP, no spaces, ≤ 253 characters."""
    return (
        isinstance(value, str)
        and 0 < len(value) <= 253
        and all(c.isalnum() or c in ".-_:" for c in value)
    )


def _number(key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"arm.{key}", f"must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(f"arm.{key}", "must be finite")
    return float(value)


def _positive(cfg: ArmConfig, key: str) -> None:
    if _number(key, getattr(cfg, key)) <= 0.0:
        raise ConfigError(f"arm.{key}", "must be > 0")


def _non_negative(cfg: ArmConfig, key: str) -> None:
    if _number(key, getattr(cfg, key)) < 0.0:
        raise ConfigError(f"arm.{key}", "must be ≥ 0")


def _n_positive(key: str, values: tuple[float, ...], at_most: list[float]) -> None:
    if len(values) != len(at_most):
        raise ConfigError(
            f"arm.{key}", f"must be {len(at_most)} numbers, joint 1 first, got {len(values)}"
        )
    for j, (x, top) in enumerate(zip(values, at_most, strict=True)):
        v = _number(key, x)
        if v <= 0.0:
            raise ConfigError(f"arm.{key}", f"joint {j + 1} must be > 0")
        if v > top * (1 + 1e-12):
            raise ConfigError(f"arm.{key}", f"joint {j + 1} exceeds what the arm can do ({top})")
