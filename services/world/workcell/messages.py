"""`workcell/state` (extension, docs/tasks.md): the simulated workcell's dynamic scene.

The message is a `services.bus.messages.Message`, so the bus codec encodes, decodes and
validates its declared fields; the per-object maps inside `objects` are checked here by
`objects_of`, with the same validators, so a malformed object is a `ProtocolError` naming
its field.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from services.bus import codec
from services.bus.errors import ProtocolError
from services.bus.keys import QoS, Topic
from services.bus.messages import Count, Joints, MaxLen, Message, Rot, Unit, Vec3, vec
from services.world.workcell.bodies import BodyState

Phase = Literal["resting", "held", "falling", "toppled"]
ObjectKind = Literal["box", "cylinder"]
M3_PER_ML = 1e-6


@dataclass(frozen=True, slots=True)
class WorkcellState(Message):
    """`workcell/state`: where every movable object is, and the gripper.

    `tool_p` (m, world) and `grip` (0 … 1): the robot state the step used. `held`: the
    object in the gripper ("" if none). `objects`: name → map with `kind` ("box" |
    "cylinder"), `p` (3, m: a box's centre, a cylinder's base centre), `R` (9, world←object),
    `size` (3, m: the bounding box), `phase` ("resting" | "held" | "falling" | "toppled"),
    `on` (what it rests on), `tilt_deg`, `max_tilt_deg`, and for a bottle `liquid_ml`,
    `spilled_ml`. `data`: the simulation's counters (grasps, missed, releases, collisions,
    toppled, max_penetration_mm).
    """

    name: ClassVar[str] = "WorkcellState"
    seq: Count
    t_ns: Count
    tool_p: Vec3
    grip: Unit
    held: Annotated[str, MaxLen(128)]
    objects: dict[str, Any]
    data: dict[str, Any] | None = None


WORKCELL_STATE = Topic("workcell/state", WorkcellState, QoS.STATE, latest_wins=True)
"""Published by the workcell service at `publish_rate_hz` (INTERACTIVE_HIGH, drop)."""


@dataclass(frozen=True, slots=True)
class SimArmCmd(Message):
    """`sim/arm/cmd` (extension, docs/sim.md): the simulated arm's joint setpoint (rad, the
    model's n joints), from the arm's `sim` driver to the physics. `halt`: brake the joints
    where they are (an emergency stop) before taking `q`."""

    name: ClassVar[str] = "SimArmCmd"
    seq: Count
    t_ns: Count
    q: Joints
    halt: bool = False


@dataclass(frozen=True, slots=True)
class SimArmState(Message):
    """`sim/arm/state` (extension, docs/sim.md): the simulated arm as the physics has it.

    `q` (rad), `qd` (rad/s): the joints; `f_t` (N), `c_t` (N·m about the tool point): the
    wrench of the world on the tool, tool frame, as the wrist's F/T sensor measures it;
    `tool_p` (m, world), `tool_R` (world←tool): the tool the physics holds; `sim_ns`: the
    physics' clock (ns); `cmd_seq`: the last `sim/arm/cmd` it took."""

    name: ClassVar[str] = "SimArmState"
    seq: Count
    t_ns: Count
    sim_ns: Count
    q: Joints
    qd: Joints
    f_t: Vec3
    c_t: Vec3
    tool_p: Vec3
    tool_R: Rot
    cmd_seq: Count = 0


SIM_ARM_CMD = Topic("sim/arm/cmd", SimArmCmd, QoS.CONTROL, latest_wins=True)
"""The `sim` arm driver → the physics (workcell service), once per control cycle."""
SIM_ARM_STATE = Topic("sim/arm/state", SimArmState, QoS.CONTROL, latest_wins=True)
"""The physics → the `sim` arm driver and the force service's `sim` sensor."""


@dataclass(frozen=True, slots=True)
class ObjectView:
    """One object of a `WorkcellState`, decoded and checked (units as in WorkcellState)."""

    name: str
    kind: ObjectKind
    p: NDArray[np.float64]
    R: NDArray[np.float64]
    size: NDArray[np.float64]
    phase: Phase
    on: str
    tilt_deg: float
    max_tilt_deg: float
    liquid_ml: float | None
    spilled_ml: float | None

    @property
    def centre(self) -> NDArray[np.float64]:
        """The object's centre (m, world)."""
        if self.kind == "box":
            return self.p
        return self.p + self.R @ np.array([0.0, 0.0, 0.5 * self.size[2]])

    @property
    def top(self) -> NDArray[np.float64]:
        """The centre of its top face (m, world)."""
        return self.centre + self.R @ np.array([0.0, 0.0, 0.5 * self.size[2]])

    @property
    def bottom(self) -> NDArray[np.float64]:
        """The centre of its base (m, world)."""
        return self.centre - self.R @ np.array([0.0, 0.0, 0.5 * self.size[2]])


def object_map(b: BodyState) -> dict[str, Any]:
    """The wire map of one object (see WorkcellState)."""
    out: dict[str, Any] = {
        "kind": b.kind,
        "p": list(vec(b.p)),
        "R": list(vec(b.R)),
        "size": list(vec(b.size)),
        "phase": b.phase,
        "on": b.on,
        "tilt_deg": math.degrees(b.tilt_rad),
        "max_tilt_deg": math.degrees(b.max_tilt_rad),
    }
    if b.kind == "cylinder" and (b.liquid_m3 > 0.0 or b.spilled_m3 > 0.0):
        out["liquid_ml"] = b.liquid_m3 / M3_PER_ML
        out["spilled_ml"] = b.spilled_m3 / M3_PER_ML
    return out


_PHASES: tuple[str, ...] = ("resting", "held", "falling", "toppled")
_KINDS: tuple[str, ...] = ("box", "cylinder")


def objects_of(state: WorkcellState) -> dict[str, ObjectView]:
    """The objects of `state`, validated; ProtocolError names the first bad field."""
    out: dict[str, ObjectView] = {}
    for name, m in state.objects.items():
        where = f"objects.{name}"
        if not isinstance(m, Mapping):
            raise ProtocolError(where, "expected a map")
        try:
            kind = codec.arg(m, "kind", str)
            phase = codec.arg(m, "phase", str)
            if kind not in _KINDS:
                raise ProtocolError("kind", f"expected one of {list(_KINDS)}")
            if phase not in _PHASES:
                raise ProtocolError("phase", f"expected one of {list(_PHASES)}")
            out[name] = ObjectView(
                name=name,
                kind=kind,
                p=np.asarray(codec.arg(m, "p", Vec3)),
                R=np.asarray(codec.arg(m, "R", Rot)).reshape(3, 3),
                size=np.asarray(codec.arg(m, "size", Vec3)),
                phase=phase,
                on=codec.arg(m, "on", str),
                tilt_deg=codec.arg(m, "tilt_deg", float),
                max_tilt_deg=codec.arg(m, "max_tilt_deg", float),
                liquid_ml=codec.arg(m, "liquid_ml", float, None),
                spilled_ml=codec.arg(m, "spilled_ml", float, None),
            )
        except ProtocolError as e:
            raise ProtocolError(f"{where}.{e.field}", e.reason) from None
    return out


def grip_of(value: float | None) -> float:
    """The grip to report: the robot's, or open (0) when it never sent one."""
    return 0.0 if value is None else float(value)


__all__ = [
    "SIM_ARM_CMD",
    "SIM_ARM_STATE",
    "WORKCELL_STATE",
    "ObjectView",
    "SimArmCmd",
    "SimArmState",
    "WorkcellState",
    "grip_of",
    "object_map",
    "objects_of",
]
