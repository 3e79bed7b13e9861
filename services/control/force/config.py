"""`ForceConfig`: the `[force]` table of a deployment, checked at start-up.

Every bad value raises ConfigError("force.<key>", …). Field types are those the bus's
`section()` reader knows (numbers, strings, Literals, tuples), so a TOML table maps onto it
directly; a misspelt key is refused there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from services.bus.errors import ConfigError
from services.control.force.gravity import STANDARD_GRAVITY_MPS2, ToolLoad
from services.control.force.model import (
    RotationMode,
    WristModel,
    as_calibration,
    as_rotation,
    as_vec3,
)
from services.control.force.priority import PRIORITY_LEVELS, PriorityLevel
from services.control.force.sampler import HANDOFFS, PERIOD_MAX_MS, PERIOD_MIN_MS, Handoff
from services.control.force.sensors import SENSOR_KINDS, SensorKind
from services.geometry import V3

IDENTITY_R: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


DEFAULT_HOST = "192.168.1.1"
"""`host`'s default: the Net F/T's factory address."""


@dataclass(frozen=True, slots=True)
class ForceConfig:
    """The force service's settings. Units are in the names; frames:

    - `sensor_p_m`, `sensor_R`: the sensor frame R_s at rest in the flange frame R_e (eMs;
      the paper's R_s ≡ R_e is the identity default);
    - `tool_p_m`, `tool_R`: the tool placement in the flange frame (eMt), PROTOCOL.md's
      default (0, 0, 0.2), identity; updated live from arm's set_tool;
    - `tool_com_m`: the tool's centre of mass in the tool frame, from the tool point.

    `calibration`: "identity" or 36 row-major floats mapping the six sensing signals to
    the plate motion (ΔS m, θ rad) of eq. (4). `K_l_n_per_m`, `K_r_nm_per_rad`: wrist
    stiffness, a number (isotropic) or three (per axis of the tool frame).

    `host`: the Net F/T's address, or with `sensor = "franka"` the robot's (the arm's
    `robot_ip`): the robot's own wrench estimate, no gravity compensation of ours.

    `handoff`: "inline" publishes each sample from the sampling thread (no queue, no extra
    thread per sample); "queue" hands it to a publisher thread through `queue_len`.
    `spin_us`: the final spin before each deadline, used only when `priority = "highest"`
    got a real-time policy. Sim only: `inertia` (default off) adds the tool's inertial
    force from its acceleration while no physics wrench arrives (an arm on its own physics:
    the wrist in free space; with the workcell's physics its solver's wrench is the
    wrist's, docs/sim.md); off because nothing compensates it yet, and with compliance on
    the tool's own acceleration then drives the admittance (sim_sensor.SimSensor).
    """

    sensor: SensorKind = "sim"
    port: str = "/dev/ttyUSB0"
    baudrate: int = 921_600
    host: str = DEFAULT_HOST
    netft_port: int = 49152
    counts_per_force: float = 1_000_000.0
    counts_per_torque: float = 1_000_000.0
    period_ms: float = 1.0
    priority: PriorityLevel = "normal"
    autostart: bool = True
    K_l_n_per_m: float | V3 = 10_000.0
    K_r_nm_per_rad: float | V3 = 50.0
    calibration: Literal["identity"] | tuple[float, ...] = "identity"
    rotation: RotationMode = "exact"
    sensor_p_m: V3 = (0.0, 0.0, 0.0)
    sensor_R: tuple[float, ...] = IDENTITY_R
    tool_p_m: V3 = (0.0, 0.0, 0.2)
    tool_R: tuple[float, ...] = IDENTITY_R
    tool_mass_kg: float = 0.25
    tool_com_m: V3 = (0.0, 0.0, -0.1)
    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    noise_n: float = 0.02
    noise_nm: float = 0.002
    seed: int | None = None
    queue_len: int = 256
    handoff: Handoff = "inline"
    inertia: bool = False
    stale_after_periods: int = 5
    bias_samples: int = 16
    event_interval_s: float = 1.0
    spin_us: float = 100.0

    def __post_init__(self) -> None:
        if self.sensor not in SENSOR_KINDS:
            _bad("sensor", f"one of {list(SENSOR_KINDS)}, got {self.sensor!r}")
        if self.priority not in PRIORITY_LEVELS:
            _bad("priority", f"one of {list(PRIORITY_LEVELS)}, got {self.priority!r}")
        if self.rotation not in ("exact", "small_angle"):
            _bad("rotation", f"exact or small_angle, got {self.rotation!r}")
        if self.sensor == "serial" and not self.port:
            _bad("port", "a serial device or pyserial URL is required")
        if self.sensor == "netft" and not self.host:
            _bad("host", "the Net F/T address is required")
        if self.sensor == "franka" and (not self.host or self.host == DEFAULT_HOST):
            _bad("host", "the Franka's address (the arm's robot_ip) is required")
        _int_in("baudrate", self.baudrate, 300, 20_000_000)
        _int_in("netft_port", self.netft_port, 1, 65535)
        _int_in("queue_len", self.queue_len, 1, 1_000_000)
        _int_in("stale_after_periods", self.stale_after_periods, 1, 10)
        _int_in("bias_samples", self.bias_samples, 1, 100_000)
        _num_in("period_ms", self.period_ms, PERIOD_MIN_MS, PERIOD_MAX_MS)
        _num_in("counts_per_force", self.counts_per_force, 0.0, math.inf, lo_open=True)
        _num_in("counts_per_torque", self.counts_per_torque, 0.0, math.inf, lo_open=True)
        _num_in("tool_mass_kg", self.tool_mass_kg, 0.0, 1000.0)
        _num_in("gravity_mps2", self.gravity_mps2, 0.0, 100.0)
        _num_in("noise_n", self.noise_n, 0.0, 1000.0)
        _num_in("noise_nm", self.noise_nm, 0.0, 1000.0)
        _num_in("event_interval_s", self.event_interval_s, 0.0, 3600.0)
        _num_in("spin_us", self.spin_us, 0.0, 10_000.0)
        if self.handoff not in HANDOFFS:
            _bad("handoff", f"one of {list(HANDOFFS)}, got {self.handoff!r}")
        if not isinstance(self.inertia, bool):
            _bad("inertia", f"true or false, got {self.inertia!r}")
        for key in ("sensor_p_m", "tool_p_m", "tool_com_m"):
            v = getattr(self, key)
            if len(v) != 3 or not all(_finite(x) for x in v):
                _bad(key, f"3 finite numbers (m), got {v!r}")
        for key in ("K_l_n_per_m", "K_r_nm_per_rad"):
            try:
                as_vec3(getattr(self, key), key)
            except (ValueError, TypeError) as e:
                _bad(key, str(e))
        for key in ("sensor_R", "tool_R"):
            try:
                as_rotation(getattr(self, key), key)
            except (ValueError, TypeError) as e:
                _bad(key, f"9 row-major floats of a rotation: {e}")
        try:
            as_calibration(self.calibration)
        except (ValueError, TypeError) as e:
            _bad("calibration", str(e))

    def wrist_model(self) -> WristModel:
        """The eq. (4) model these settings describe."""
        return WristModel(
            calibration=as_calibration(self.calibration),
            K_l=as_vec3(self.K_l_n_per_m, "K_l"),
            K_r=as_vec3(self.K_r_nm_per_rad, "K_r"),
            R_es=np.asarray(self.sensor_R, dtype=float).reshape(3, 3),
            p_es=np.asarray(self.sensor_p_m, dtype=float),
            R_et=np.asarray(self.tool_R, dtype=float).reshape(3, 3),
            p_et=np.asarray(self.tool_p_m, dtype=float),
            mode=self.rotation,
        )

    def tool_load(self) -> ToolLoad:
        # A Franka's wrench estimate has the load the robot was told of taken out already.
        mass = 0.0 if self.sensor == "franka" else self.tool_mass_kg
        return ToolLoad(mass, self.tool_com_m, self.gravity_mps2)


def _bad(key: str, message: str) -> None:
    raise ConfigError(f"force.{key}", message)


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _num_in(key: str, v: Any, lo: float, hi: float, *, lo_open: bool = False) -> None:
    if not _finite(v) or v < lo or v > hi or (lo_open and v == lo):
        _bad(key, f"a number within {lo}…{hi}, got {v!r}")


def _int_in(key: str, v: Any, lo: int, hi: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        _bad(key, f"an integer within {lo}…{hi}, got {v!r}")
