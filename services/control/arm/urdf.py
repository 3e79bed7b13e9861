"""A URDF of the PUMA 560 generated from the contract's DH table and a tool placement.

A pure function of its arguments (no Pinocchio, no bus), so the ROS 2 bridge publishes it as
/robot_description and a recorder can embed it in a file. Numbers are written with `repr`,
so a parser reads back exactly the floats of the table.

Frames (PROTOCOL.md §1): the root link `world` is the DH base frame. Standard DH gives
A_i = Rz(q_i)·F_i with the fixed part F_i = Tz(d_i)·Tx(a_i)·Rx(α_i); a URDF joint is a fixed
origin followed by a rotation about its axis, so joint i has origin F_{i−1} (identity for
joint 1) and axis z, and link `link<i>` is DH frame i−1 turned by q_i. A fixed joint F_6
gives `flange` (DH frame 6, the wrist centre) and a fixed joint eMt = (R_et, p_et) gives
`tool`. Hence world→flange is exactly the DH forward kinematics, and world→tool its
composition with the tool placement (eq. 1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from services.control.arm.driver import ARM_MAX_JOINT_SPEED_RAD_S
from services.control.arm.kinematics import PUMA560_DH, DHLink

Mat3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]

IDENTITY_R: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
DEFAULT_TOOL_P: tuple[float, float, float] = (0.0, 0.0, 0.2)
LINK_RADIUS_M = 0.035
JOINT_RADIUS_M = 0.05
JOINT_LENGTH_M = 0.1
TOOL_RADIUS_M = 0.012
_EPS = 1e-12


@dataclass(frozen=True, slots=True)
class UrdfFrames:
    """Names of the root, the links (`<link_prefix><i>`, i = 1…6), the flange and the tool."""

    world: str = "world"
    link_prefix: str = "link"
    flange: str = "flange"
    tool: str = "tool"
    joint_prefix: str = "joint"

    def link(self, i: int) -> str:
        return self.world if i == 0 else f"{self.link_prefix}{i}"


def rpy_of(R: Sequence[float]) -> tuple[float, float, float]:
    """URDF roll, pitch, yaw of a row-major rotation: R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    r = [float(x) for x in R]
    pitch = math.atan2(-r[6], math.hypot(r[7], r[8]))
    if math.hypot(r[7], r[8]) < _EPS:  # pitch = ±90°: only roll ∓ yaw is defined; take yaw = 0
        return (math.atan2(r[1] if pitch > 0 else -r[1], r[4]), pitch, 0.0)
    return (math.atan2(r[7], r[8]), pitch, math.atan2(r[3], r[0]))


def _f(x: float) -> str:
    return repr(float(x) + 0.0)  # + 0.0 turns -0.0 into 0.0


def _xyz(v: Sequence[float]) -> str:
    return " ".join(_f(x) for x in v)


def _origin(xyz: Sequence[float], rpy: Sequence[float] = (0.0, 0.0, 0.0)) -> str:
    return f'<origin xyz="{_xyz(xyz)}" rpy="{_xyz(rpy)}"/>'


def _z_to(u: Sequence[float]) -> tuple[float, float, float]:
    """rpy of a rotation taking the z axis onto the unit vector u (a cylinder's axis)."""
    ux, uy, uz = u
    c = uz
    ax, ay = -uy, ux  # z × u
    s = math.hypot(ax, ay)
    if s < _EPS:
        return (0.0, 0.0, 0.0) if c > 0 else (math.pi, 0.0, 0.0)
    kx, ky = ax / s, ay / s
    v = 1.0 - c
    R = (
        c + kx * kx * v, kx * ky * v, ky * s,
        kx * ky * v, c + ky * ky * v, -kx * s,
        -ky * s, kx * s, c,
    )  # fmt: skip
    return rpy_of(R)


def _cylinder(start: Sequence[float], end: Sequence[float], radius_m: float, material: str) -> str:
    d = [e - s for s, e in zip(start, end, strict=True)]
    length = math.sqrt(sum(x * x for x in d))
    if length < 1e-9:
        return ""
    mid = [(s + e) / 2.0 for s, e in zip(start, end, strict=True)]
    rpy = _z_to([x / length for x in d])
    return (
        f"<visual>{_origin(mid, rpy)}<geometry>"
        f'<cylinder radius="{_f(radius_m)}" length="{_f(length)}"/></geometry>'
        f'<material name="{material}"/></visual>'
    )


def _joint_housing() -> str:
    return _cylinder(
        (0.0, 0.0, -JOINT_LENGTH_M / 2), (0.0, 0.0, JOINT_LENGTH_M / 2), JOINT_RADIUS_M, "joint"
    )


def _fixed_part_rpy(link: DHLink) -> tuple[float, float, float]:
    return (link.alpha_rad, 0.0, 0.0)


def puma_urdf(
    dh: Sequence[DHLink] = PUMA560_DH,
    tool_p: Sequence[float] = DEFAULT_TOOL_P,
    tool_R: Sequence[float] = IDENTITY_R,
    *,
    name: str = "puma560",
    frames: UrdfFrames = UrdfFrames(),
    max_speed_rad_s: Sequence[float] = ARM_MAX_JOINT_SPEED_RAD_S,
) -> str:
    """The URDF (XML text) of a standard-DH arm with the tool at (tool_R, tool_p) in the flange.

    `dh`: the links, joint 1 first (lengths in m, angles and limits in rad); `tool_p` (3, m)
    and `tool_R` (9, row-major) place the tool frame in the flange frame (PROTOCOL §1, eMt);
    `max_speed_rad_s` per joint goes to each joint's velocity limit.
    """
    if len(tool_p) != 3 or len(tool_R) != 9 or len(max_speed_rad_s) != len(dh):
        raise ValueError("tool_p needs 3 numbers, tool_R 9, max_speed_rad_s one per joint")
    if not all(math.isfinite(float(x)) for x in (*tool_p, *tool_R)):
        raise ValueError("tool placement must be finite")
    parts = [f"<robot name={quoteattr(name)}>"]
    parts += [
        '<material name="link"><color rgba="0.85 0.85 0.8 1"/></material>',
        '<material name="joint"><color rgba="0.3 0.3 0.35 1"/></material>',
        '<material name="tool"><color rgba="0.9 0.45 0.1 1"/></material>',
    ]
    pedestal = _cylinder((0.0, 0.0, 0.0), (0.0, 0.0, dh[0].d_m), 0.08, "joint")
    parts.append(f"<link name={quoteattr(frames.world)}>{pedestal}</link>")
    for i, link in enumerate(dh, start=1):
        # visuals of link i: its joint, then the fixed part F_i (d along z, then a along x)
        visuals = _joint_housing()
        if i > 1:  # link 1's d is the pedestal, drawn in the world link
            visuals += _cylinder((0.0, 0.0, 0.0), (0.0, 0.0, link.d_m), LINK_RADIUS_M, "link")
        visuals += _cylinder((0.0, 0.0, link.d_m), (link.a_m, 0.0, link.d_m), LINK_RADIUS_M, "link")
        parts.append(f"<link name={quoteattr(frames.link(i))}>{visuals}</link>")
        prev = dh[i - 2] if i > 1 else None
        origin = (
            _origin((prev.a_m, 0.0, prev.d_m), _fixed_part_rpy(prev))
            if prev is not None
            else _origin((0.0, 0.0, 0.0))
        )
        parts.append(
            f'<joint name={quoteattr(f"{frames.joint_prefix}{i}")} type="revolute">'
            f"<parent link={quoteattr(frames.link(i - 1))}/>"
            f"<child link={quoteattr(frames.link(i))}/>{origin}"
            '<axis xyz="0 0 1"/>'
            f'<limit lower="{_f(link.lo_rad)}" upper="{_f(link.hi_rad)}" effort="0" '
            f'velocity="{_f(max_speed_rad_s[i - 1])}"/></joint>'
        )
    last = dh[-1]
    tool_visual = _cylinder((0.0, 0.0, 0.0), tool_p, TOOL_RADIUS_M, "tool")
    parts.append(f"<link name={quoteattr(frames.flange)}>{tool_visual}</link>")
    parts.append(
        f'<joint name={quoteattr(f"{frames.flange}_joint")} type="fixed">'
        f"<parent link={quoteattr(frames.link(len(dh)))}/>"
        f"<child link={quoteattr(frames.flange)}/>"
        f"{_origin((last.a_m, 0.0, last.d_m), _fixed_part_rpy(last))}</joint>"
    )
    parts.append(f"<link name={quoteattr(frames.tool)}/>")
    parts.append(
        f'<joint name={quoteattr(f"{frames.tool}_joint")} type="fixed">'
        f"<parent link={quoteattr(frames.flange)}/><child link={quoteattr(frames.tool)}/>"
        f"{_origin(tool_p, rpy_of(tool_R))}</joint>"
    )
    parts.append("</robot>")
    return '<?xml version="1.0"?>\n' + "\n".join(parts) + "\n"
