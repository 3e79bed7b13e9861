"""Configuration of the PUMA proxy service: rates, motion limits, home pose, arm backend.

Read once at start-up (from the deployment TOML's `[arm]` table via `ArmConfig.from_mapping`)
into a frozen dataclass; a bad or misspelt key raises `ConfigError("arm.<key>", …)`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, get_args

from services.bus.bounds import check_config
from services.bus.config import section
from services.bus.errors import ConfigError
from services.control.arm.driver import (
    ARM_MAX_JOINT_ACCEL_RAD_S2,
    ARM_MAX_JOINT_SPEED_RAD_S,
    Q_HI_RAD,
    Q_LO_RAD,
    DriverName,
)

Joint6 = tuple[float, float, float, float, float, float]

HOME_Q_RAD: Joint6 = (0.276321, 1.193707, -3.260341, 0.0, -1.074959, 0.276321)
"""Home: tool point at (0.55, 0, 0.65) m in the world, 0.25 m above the table top (z = 0.40),
tool z axis pointing down (R_wt = diag(−1, 1, −1)) with the default tool eMt; branch `rum`,
no joint within 25° of a limit, away from every singularity (manipulability 0.086 vs 0.079 at
qn). Computed with `Puma560.ik` and rounded to 1 µrad; tests/control/arm/test_proxy.py
checks it."""


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
    "max_reach_m": "displacement_m",
    "max_target_step_m": "displacement_m",
    "max_target_step_rad": "joint_rad",
    "teleop_settle_s": "duration_s",
    "event_interval_s": "duration_s",
}


@dataclass(frozen=True, slots=True)
class ArmConfig:
    """The arm service's settings. Units are in the names; joint tuples are joint 1 first.

    The proxy plans every motion within `max_joint_speed_rad_s`, `max_joint_accel_rad_s2`,
    `max_tool_speed_m_s` (tool point) and `max_tool_rot_speed_rad_s` (tool frame), and its
    safety filter enforces them on every setpoint whatever the source. They must not exceed
    what the arm's servo can do (`ARM_MAX_JOINT_*` in arm.py).
    """

    state_rate_hz: float = 250.0
    control_rate_hz: float = 500.0
    max_joint_speed_rad_s: Joint6 = (2.0, 2.0, 2.0, 4.0, 4.0, 4.0)
    max_joint_accel_rad_s2: Joint6 = (5.0, 5.0, 5.0, 10.0, 10.0, 10.0)
    max_tool_speed_m_s: float = 0.5
    max_tool_rot_speed_rad_s: float = 1.5
    home_q: Joint6 = HOME_Q_RAD
    driver: DriverName = "sim"
    port: str | None = None
    baudrate: int = 115_200
    serial_cycle_ms: float = 28.0
    serial_timeout_s: float = 0.1
    sim_calibration_s: float = 0.5
    max_following_error_rad: float = 0.35
    max_dp_m: float = 2.0
    max_reach_m: float = 1.6
    max_target_step_m: float = 0.05
    max_target_step_rad: float = 0.35
    teleop_settle_s: float = 0.2
    event_interval_s: float = 1.0

    def __post_init__(self) -> None:
        _positive(self, "state_rate_hz")
        if self.state_rate_hz < 100.0:
            raise ConfigError("arm.state_rate_hz", "must be ≥ 100 Hz (PROTOCOL §3)")
        _positive(self, "control_rate_hz")
        if self.control_rate_hz < self.state_rate_hz:
            raise ConfigError("arm.control_rate_hz", "must be ≥ state_rate_hz")
        _joint6(self, "max_joint_speed_rad_s", positive=True, at_most=ARM_MAX_JOINT_SPEED_RAD_S)
        _joint6(self, "max_joint_accel_rad_s2", positive=True, at_most=ARM_MAX_JOINT_ACCEL_RAD_S2)
        for key in (
            "max_tool_speed_m_s",
            "max_tool_rot_speed_rad_s",
            "serial_timeout_s",
            "max_following_error_rad",
            "max_dp_m",
            "max_reach_m",
            "max_target_step_m",
            "max_target_step_rad",
            "teleop_settle_s",
            "event_interval_s",
        ):
            _positive(self, key)
        _joint6(self, "home_q")
        for j, (q, lo, hi) in enumerate(zip(self.home_q, Q_LO_RAD, Q_HI_RAD, strict=True)):
            if not lo <= q <= hi:
                raise ConfigError("arm.home_q", f"q{j + 1} = {q} rad is outside [{lo}, {hi}]")
        if self.driver not in get_args(DriverName):
            raise ConfigError("arm.driver", f"must be 'sim' or 'serial', got {self.driver!r}")
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
        check_config("arm", self, _KINDS)

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any]) -> ArmConfig:
        """From a TOML `[arm]` table (the bus's one section reader: an unknown key or a
        value of the wrong type is an error naming `arm.<key>`)."""
        return section(cls, table, "arm")


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


def _joint6(
    cfg: ArmConfig,
    key: str,
    positive: bool = False,
    at_most: tuple[float, ...] | None = None,
) -> None:
    value = getattr(cfg, key)
    if not isinstance(value, tuple | list) or len(value) != 6:
        raise ConfigError(f"arm.{key}", f"must be 6 numbers, joint 1 first, got {value!r}")
    for j, x in enumerate(value):
        v = _number(key, x)
        if positive and v <= 0.0:
            raise ConfigError(f"arm.{key}", f"joint {j + 1} must be > 0")
        if at_most is not None and v > at_most[j]:
            raise ConfigError(f"arm.{key}", f"joint {j + 1} exceeds the arm's {at_most[j]}")
