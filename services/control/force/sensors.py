"""The `ForceSensor` role, its `Reading` and its error: what the force service needs from a
wrist force sensor. `backends.py` holds `open_force_sensor(config)`, which picks a backend and
imports it lazily; `accounting.py` what the streaming backends share.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

from numpy.typing import ArrayLike

from services.bus.errors import TelerobotError
from services.control.force.events import EventSink

SensorKind = Literal["sim", "serial", "netft", "franka"]
SENSOR_KINDS: tuple[SensorKind, ...] = ("sim", "serial", "netft", "franka")

Six = tuple[float, float, float, float, float, float]


class SensorError(TelerobotError):
    """A sensor could not be used: not open, disconnected, refused."""


@dataclass(frozen=True, slots=True)
class Reading:
    """One new measurement from a sensor.

    `kind == "signals"`: the six raw sensing signals of the compliant wrist (device units;
    the calibration of eq. 4 turns them into plate motion). `kind == "wrench"`: a
    calibrated wrench (Fx, Fy, Fz in N, Tx, Ty, Tz in N·m) at the sensor origin, in the
    sensor frame R_s. Values are always finite. `device_seq` is the device's own sample
    counter when it has one.
    """

    kind: Literal["signals", "wrench"]
    values: Six
    device_seq: int | None = None
    estimate: bool = False
    """The wrench is estimated (a robot's, from its joint torques), not measured."""


@runtime_checkable
class ForceSensor(Protocol):
    """A wrist force sensor.

    Lifecycle: `open()` (may raise SensorError or OSError when the device is unreachable),
    then `read()` from one thread at a time, `close()` (idempotent). `read()` never blocks:
    it returns the newest valid measurement received since the last call, or None when
    there is none. Bad data (garbage, NaN, short packets) is dropped, counted in `bad`,
    and reported through `on_event("bad_data", …)`; missing device samples (sequence
    jumps) are counted in `gaps` and reported as `gap`. `read()` before `open()` or after
    `close()` raises SensorError.
    """

    on_event: EventSink

    @property
    def name(self) -> str:
        """Which sensor, for people and status (e.g. "netft 192.168.1.1:49152")."""
        ...

    @property
    def bad(self) -> int:
        """Measurements dropped as invalid since construction."""
        ...

    @property
    def gaps(self) -> int:
        """Device samples missed (sequence jumps) since construction."""
        ...

    def open(self) -> None: ...

    def read(self) -> Reading | None: ...

    def close(self) -> None: ...


@runtime_checkable
class PoseAwareSensor(Protocol):
    """A sensor that needs the arm's pose: the simulated one senses the simulated world."""

    def update_pose(self, tool_p: ArrayLike, tool_R: ArrayLike) -> None:
        """The tool frame in the world: `tool_p` (3, m), `tool_R` (R world←tool)."""
        ...

    def set_tool(self, p_et: ArrayLike, R_et: ArrayLike) -> None:
        """The tool placement in the flange frame (eMt), as arm's `set_tool`."""
        ...


@runtime_checkable
class IdlingSensor(Protocol):
    """A sensor whose data is computed, not streamed by a device (the simulated one):
    `may_idle` says it may be sampled slower while nobody uses the samples."""

    may_idle: bool


@runtime_checkable
class WorldAwareSensor(Protocol):
    """A sensor of the simulated cell: it follows the tool's pose (validated) and takes
    the wrench the cell's physics computes at the wrist, counting those it took in
    `physics_updates`."""

    physics_updates: int

    def update_pose_checked(
        self,
        p: tuple[float, float, float],
        R: tuple[float, float, float, float, float, float, float, float, float],
        t_ns: int | None = None,
    ) -> None:
        """The tool frame in the world, already validated (plain floats; R row-major
        world←tool), from robot/state stamped `t_ns` (ns)."""
        ...

    def update_physics(
        self, f_t: tuple[float, float, float], c_t: tuple[float, float, float]
    ) -> None:
        """The world's wrench on the tool (N, N·m about the tool point, tool frame) as the
        cell's physics computes it now."""
        ...
