"""The messages of the wire contract (PROTOCOL.md §1 and §3) as frozen dataclasses.

Vectors travel as tuples of floats: `Vec3` (3), `Joints` (the arm's n, 1 … MAX_JOINTS),
`Rot` (9, a row-major 3×3 rotation). The field annotations are the schema:
`services.bus.codec` reads them to encode, decode and validate, so a field is declared once,
here. Optional fields default to None and
are left out of the encoding when None.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.errors import ProtocolError
from services.geometry import ROTATION_TOL, rotation_defect


@dataclass(frozen=True, slots=True)
class Size:
    """Annotation: a float sequence of exactly `n` finite numbers (of `n` … `hi` when `hi`
    is given)."""

    n: int
    hi: int | None = None


@dataclass(frozen=True, slots=True)
class Rotation:
    """Annotation: the 9 floats are a proper rotation (‖RᵀR − I‖ ≤ tol, det R > 0)."""

    tol: float = ROTATION_TOL


@dataclass(frozen=True, slots=True)
class Range:
    """Annotation: a number within [lo, hi]."""

    lo: float
    hi: float


@dataclass(frozen=True, slots=True)
class MaxLen:
    """Annotation: a str or bytes of at most `n` characters / bytes."""

    n: int


MAX_JOINTS = 32
"""The most joints an arm may have: a joint vector's largest size."""
MAX_URDF_CHARS = 1 << 20

Vec3 = Annotated[tuple[float, ...], Size(3)]
Vec6 = Annotated[tuple[float, ...], Size(6)]
Joints = Annotated[tuple[float, ...], Size(1, MAX_JOINTS)]
Rot = Annotated[tuple[float, ...], Size(9), Rotation()]
Count = Annotated[int, Range(0, 2**63 - 1)]
Name = Annotated[str, MaxLen(128)]
Unit = Annotated[float, Range(0.0, 1.0)]

Frame = Literal["world", "tool"]
Eye = Literal["l", "r"]
ImageEncoding = Literal["jpeg", "bgr8"]
RobotStatus = Literal["disconnected", "connected", "initializing", "ready", "moving", "error"]

MAX_FRAME_BYTES = 64 * 1024 * 1024
MAX_TEXT = 4096


@dataclass(frozen=True, slots=True)
class Message:
    """Base: every message has `seq` (per-sender counter) and `t_ns` (sender's time.time_ns())."""

    name: ClassVar[str] = "Message"


@dataclass(frozen=True, slots=True)
class OperatorCommand(Message):
    """`robot/cmd`: the operator's scaled motion since the engagement (§2)."""

    name: ClassVar[str] = "OperatorCommand"
    seq: Count
    t_ns: Count
    master: Name
    engage: Count
    active: bool
    frame: Frame
    dp: Vec3
    dR: Rot
    grip: Unit | None = None


@dataclass(frozen=True, slots=True)
class ArmTarget(Message):
    """`robot/arm/target`: the supervised tool pose the arm is to reach (§3), absolute, in
    world coordinates, after every supervisory rule. `origin_t_ns` is the `t_ns` of the
    operator command it carries out (the sender's own time for holds and task steps)."""

    name: ClassVar[str] = "ArmTarget"
    seq: Count
    t_ns: Count
    origin_t_ns: Count
    master: Name
    engage: Count
    p: Vec3
    R: Rot
    grip: Unit | None = None
    hold: bool | None = None
    """Extension: true when the supervisor holds (it re-sends the target it last sent and
    follows no operator): what the console and the passivity port tell apart; the arm
    treats it as any target."""


@dataclass(frozen=True, slots=True)
class RobotState(Message):
    """`robot/state`: joints, tool and flange poses (world), last command applied."""

    name: ClassVar[str] = "RobotState"
    seq: Count
    t_ns: Count
    status: RobotStatus
    q: Joints
    tool_p: Vec3
    tool_R: Rot
    flange_p: Vec3
    flange_R: Rot
    engage: Count
    cmd_seq: Count
    grip: Unit | None = None
    manipulability: float | None = None
    cmd_rx_ns: Count | None = None
    """Extension: time.time_ns() when the arm received command `cmd_seq`."""
    setpoint_ns: Count | None = None
    """Extension: time.time_ns() when the first arm setpoint computed from target `cmd_seq`
    went to the arm (absent until one has)."""
    cmd_origin_t_ns: Count | None = None
    """Extension: the `origin_t_ns` that command `cmd_seq` carried (the operator's send
    time), so master→arm and master→setpoint are timed on one clock."""
    tool_p_cmd: Vec3 | None = None
    """Extension: the tool position (world) of the setpoint the arm is following; the pose
    the arm takes as a new engagement's start (`tool_p` is measured, and trails it by the
    servo's error). Left out when the two agree (at rest)."""


@dataclass(frozen=True, slots=True)
class ArmDescription(Message):
    """`robot/arm/description` (and `describe`'s reply, PROTOCOL §1): the arm the arm
    service runs. `joints`: n maps {name, lo, hi, max_speed, max_accel} (rad, rad/s,
    rad/s²); `eMt`: {p, R}, the tool in use. Optional fields are extensions
    (docs/protocol-extensions.md)."""

    name: ClassVar[str] = "ArmDescription"
    seq: Count
    t_ns: Count
    model: Name
    n: Annotated[int, Range(1, MAX_JOINTS)]
    joints: Annotated[tuple[dict[str, Any], ...], MaxLen(MAX_JOINTS)]
    base_frame: Name
    flange_frame: Name
    urdf: Annotated[str, MaxLen(MAX_URDF_CHARS)] = field(repr=False)
    eMt: dict[str, Any]
    analytic_ik: bool
    grip: bool | None = None
    named: dict[str, Any] | None = None
    """Extension: named configurations, name → n joints (rad); `home` among them."""
    reach_m: Annotated[float, Range(0.0, 100.0)] | None = None
    """Extension: how far from the world origin the tool point can be (m)."""
    max_target_step_m: Annotated[float, Range(0.0, 10.0)] | None = None
    max_target_step_rad: Annotated[float, Range(0.0, 10.0)] | None = None
    """Extension: the step bound of robot/arm/target (§3)."""
    workspace: dict[str, Any] | None = None
    """Extension: {min, max} (m, world): the box the decision supervises the tool point in
    unless configured otherwise."""
    max_tool_speed_m_s: Annotated[float, Range(0.0, 100.0)] | None = None
    max_tool_rot_speed_rad_s: Annotated[float, Range(0.0, 100.0)] | None = None
    """Extension: the tool speeds the arm holds every setpoint to (its `limits`)."""
    packages: dict[str, str] | None = None
    """Extension: the URDF's `package://` roots on the arm's host (name → absolute folder),
    for a consumer on that host that loads its meshes (the simulated cell's physics)."""

    def __post_init__(self) -> None:
        try:
            check_description(self)
        except ProtocolError:
            raise
        except (TypeError, AttributeError, KeyError, ValueError) as e:
            # fields of the wrong kind altogether: the codec names which when it decodes
            raise ProtocolError("joints", f"malformed description ({type(e).__name__})") from None


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def check_description(d: ArmDescription) -> None:
    """The cross-field rules of an ArmDescription (ProtocolError naming the field): n joint
    maps, each with a name and finite limits lo < hi, max_speed and max_accel > 0; eMt a p
    and a proper rotation R; named configurations of n finite joints; a workspace box of
    finite min < max."""
    if len(d.joints) != d.n:
        raise ProtocolError("joints", f"{len(d.joints)} joints, not the n said")
    for i, j in enumerate(d.joints):
        name = j.get("name")
        if not isinstance(name, str) or not 0 < len(name) <= 128:
            raise ProtocolError(f"joints[{i}].name", "must be a name of 1 … 128 characters")
        for key in ("lo", "hi", "max_speed", "max_accel"):
            if not _finite(j.get(key)):
                raise ProtocolError(f"joints[{i}].{key}", "must be a finite number")
        if not j["lo"] < j["hi"] or j["max_speed"] <= 0 or j["max_accel"] <= 0:
            raise ProtocolError(f"joints[{i}]", "needs lo < hi, max_speed > 0, max_accel > 0")
    p, R = d.eMt.get("p"), d.eMt.get("R")
    if not (isinstance(p, list | tuple) and len(p) == 3 and all(map(_finite, p))):
        raise ProtocolError("eMt.p", "must be 3 finite numbers")
    if not (isinstance(R, list | tuple) and len(R) == 9 and all(map(_finite, R))):
        raise ProtocolError("eMt.R", "must be 9 finite numbers")
    err, det = rotation_defect([float(x) for x in R])
    if not err <= ROTATION_TOL or det < 0.0:
        raise ProtocolError("eMt.R", "not a rotation")
    for k, q in (d.named or {}).items():
        if not (isinstance(q, list | tuple) and len(q) == d.n and all(map(_finite, q))):
            raise ProtocolError(f"named.{k}", f"must be {d.n} finite numbers")
    if d.workspace is not None:
        box = [d.workspace.get(k) for k in ("min", "max")]
        for k, v in zip(("min", "max"), box, strict=True):
            if not (isinstance(v, list | tuple) and len(v) == 3 and all(map(_finite, v))):
                raise ProtocolError(f"workspace.{k}", "must be 3 finite numbers (m)")
            if max(abs(float(x)) for x in v) > 100.0:
                raise ProtocolError(f"workspace.{k}", "more than 100 m from the origin")
        if not all(a < b for a, b in zip(box[0], box[1], strict=True)):  # type: ignore[arg-type]
            raise ProtocolError("workspace", "needs min < max on every axis")


@dataclass(frozen=True, slots=True)
class ForceSample(Message):
    """`robot/force`: force `f` (N) and moment `c` (N·m) at the tool point, tool frame."""

    name: ClassVar[str] = "ForceSample"
    seq: Count
    t_ns: Count
    f: Vec3
    c: Vec3
    raw: Vec6 | None = None
    estimate: bool | None = None
    """Extension: true when `f` and `c` are an estimate, not a wrist sensor's measurement
    (a Franka's external wrench estimate from its joint torques, docs/franka.md)."""


@dataclass(frozen=True, slots=True)
class Event(Message):
    """`robot/events`: something a person or a supervisor should know about."""

    name: ClassVar[str] = "Event"
    seq: Count
    t_ns: Count
    source: Name
    kind: Name
    message: Annotated[str, MaxLen(MAX_TEXT)]
    data: dict[str, Any] | None = None


@dataclass(frozen=True, slots=True)
class StereoFrame(Message):
    """`vision/stereo/l|r`: one eye of a stereo pair; both eyes share `seq` and `t_ns`."""

    name: ClassVar[str] = "StereoFrame"
    seq: Count
    t_ns: Count
    eye: Eye
    width: Annotated[int, Range(1, 16384)]
    height: Annotated[int, Range(1, 16384)]
    encoding: ImageEncoding
    data: Annotated[bytes, MaxLen(MAX_FRAME_BYTES)] = field(repr=False)
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    baseline: float | None = None


@dataclass(frozen=True, slots=True)
class MasterState(Message):
    """`master/state`: what the operator's station is doing."""

    name: ClassVar[str] = "MasterState"
    seq: Count
    t_ns: Count
    master: Name
    engage: Count
    active: bool
    frame: Frame
    scale_t: float
    scale_r: float
    hand_p: Vec3
    hand_R: Rot
    device: Name


@dataclass(frozen=True, slots=True)
class VisionStats(Message):
    """`vision/stats` (extension, docs/protocol-extensions.md): the stereo pipeline's figures."""

    name: ClassVar[str] = "VisionStats"
    seq: Count
    t_ns: Count
    fps: float
    encode_ms: float
    dropped: Count
    skew_ms: float
    width: Count
    height: Count
    encoding: ImageEncoding
    data: dict[str, Any] | None = None


@dataclass(frozen=True, slots=True)
class MasterFeedback(Message):
    """`master/feedback` (extension): the wrench a master displayed to the operator's hand,
    in the operator's frame, after scaling and saturation."""

    name: ClassVar[str] = "MasterFeedback"
    seq: Count
    t_ns: Count
    master: Name
    f: Vec3
    c: Vec3
    saturated: bool
    stale: bool


Joules = Annotated[float, Range(0.0, 1e6)]
Newtons = Annotated[float, Range(0.0, 1e6)]
PortSide = Literal["master", "slave"]


@dataclass(frozen=True, slots=True)
class PassivityState(Message):
    """`robot/passivity/master` and `robot/passivity/slave` (extension, docs/passivity.md):
    one side's time-domain passivity figures for engagement `engage` of `master`.

    e_in / e_out: energy (J) that entered / left the channel at this port since the
    engagement began (cumulative, never decreasing within it); the other side bounds its
    output by this side's `e_in`. dissipated_j: energy the controller removed; gain: its
    last action (N·s/m damping at the master, m/N correction at the slave); active_steps:
    how many steps it acted; enabled: false when the side only observes. asked_n / shown_n
    (optional, master side): the force the master was asked to display on its last step
    and the force its controller let the hand feel, both as newtons at the tool (the
    display's magnitudes ÷ its force scale); the slave yields what is withheld.
    repaid_j / forgiven_j (optional, slave side): of what the slave overdrew at impacts, the
    energy the workcell gave back to repay it, and the rest, forgiven once the tool was out
    of contact (energy the channel created: one tick's impact, sampled late). rot_e_in /
    rot_e_out / rot_dissipated_j (optional, both sides): the same for the side's rotational
    port (moment × rotation), when it runs one; the slave runs its own only while the
    master's figures carry `rot_e_in`. echo_t_ns / echo_age_ns (optional, both sides): the
    `t_ns` of the other side's newest PassivityState this side had received, and how long
    it had held it (ns, on this side's own clock) when it sent this one; the other side
    takes its round trip from them, on its own clock alone. rtt_ms (optional, both sides):
    the sender's round trip so measured, the median over its last 2 s."""

    name: ClassVar[str] = "PassivityState"
    seq: Count
    t_ns: Count
    master: Name
    engage: Count
    side: PortSide
    enabled: bool
    e_in: Joules
    e_out: Joules
    dissipated_j: Joules
    gain: Annotated[float, Range(0.0, 1e12)]
    active_steps: Count
    asked_n: Newtons | None = None
    shown_n: Newtons | None = None
    repaid_j: Joules | None = None
    forgiven_j: Joules | None = None
    rot_e_in: Joules | None = None
    rot_e_out: Joules | None = None
    rot_dissipated_j: Joules | None = None
    echo_t_ns: Count | None = None
    echo_age_ns: Annotated[int, Range(0, 60_000_000_000)] | None = None
    rtt_ms: Annotated[float, Range(0.0, 60_000.0)] | None = None


ALL_MESSAGES: tuple[type[Message], ...] = (
    OperatorCommand,
    ArmTarget,
    RobotState,
    ArmDescription,
    ForceSample,
    Event,
    StereoFrame,
    MasterState,
    VisionStats,
    MasterFeedback,
    PassivityState,
)

IDENTITY_R: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def vec(a: ArrayLike) -> tuple[float, ...]:
    """A float tuple from any array-like (flattened, row-major) for a message field."""
    return tuple(float(x) for x in np.asarray(a, dtype=float).ravel())


def mat3(r: tuple[float, ...] | list[float]) -> NDArray[np.float64]:
    """The 3×3 matrix of a row-major `R` field."""
    return np.asarray(r, dtype=float).reshape(3, 3)
