"""Telerobot messages → ROS 2 messages, pure functions on plain floats (they run per sample).

Frames: the world is the DH base frame; `link<i>` is DH frame i−1 turned by q_i and `flange`
DH frame 6, exactly as in the URDF of services/control/arm/urdf.py, so /tf drives RViz's robot
model with nothing else running; `tool` is placed in the flange by the live tool placement
(eMt = oMe⁻¹·oMt from each RobotState). Quaternions are ROS's (x, y, z, w).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from services.bus.messages import ForceSample, RobotState, StereoFrame
from services.control.arm.kinematics import PUMA560_DH, DHLink
from services.control.arm.urdf import UrdfFrames
from services.frontends.rosmsg import msgs
from services.frontends.rosmsg.msgs import Header, Quat, Vec3
from services.geometry import quat_of_rotation, quat_of_rx_rz, rotation_of_quat

JOINT_NAMES: tuple[str, ...] = tuple(f"joint{i}" for i in range(1, 7))
JPEG_FORMAT = "bgr8; jpeg compressed bgr8"
"""What compressed_image_transport writes for a colour JPEG (RViz, rqt and Foxglove read it)."""


def quat_of(R: Sequence[float]) -> Quat:
    """The unit quaternion in ROS's order (x, y, z, w), w ≥ 0, of a row-major rotation."""
    w, x, y, z = quat_of_rotation(R)
    return (x, y, z, w)


def rotation_of(q: Quat) -> tuple[float, ...]:
    """The row-major rotation of a quaternion in ROS's order (x, y, z, w)."""
    x, y, z, w = q
    return rotation_of_quat(w, x, y, z)


def relative_pose(
    pa: Sequence[float], Ra: Sequence[float], pb: Sequence[float], Rb: Sequence[float]
) -> tuple[Vec3, tuple[float, ...]]:
    """(p, R) of frame b in frame a, from both in the world: R = Raᵀ·Rb, p = Raᵀ·(pb − pa)."""
    d = (pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2])
    p = (
        Ra[0] * d[0] + Ra[3] * d[1] + Ra[6] * d[2],
        Ra[1] * d[0] + Ra[4] * d[1] + Ra[7] * d[2],
        Ra[2] * d[0] + Ra[5] * d[1] + Ra[8] * d[2],
    )
    R = tuple(
        Ra[i] * Rb[j] + Ra[3 + i] * Rb[3 + j] + Ra[6 + i] * Rb[6 + j]
        for i in range(3)
        for j in range(3)
    )
    return p, R


def _joint_transform(prev: DHLink | None, q_rad: float) -> tuple[Vec3, Quat]:
    """link<i−1> → link<i>: the fixed part of DH link i−1, then Rz(q_i) (see urdf.py)."""
    if prev is None:
        w, x, y, z = quat_of_rx_rz(0.0, q_rad)
        return (0.0, 0.0, 0.0), (x, y, z, w)
    w, x, y, z = quat_of_rx_rz(prev.alpha_rad, q_rad)
    return (prev.a_m, 0.0, prev.d_m), (x, y, z, w)


@dataclass(frozen=True, slots=True)
class StateConverter:
    """RobotState → /joint_states and /tf, with the frame names of the URDF."""

    frames: UrdfFrames = field(default_factory=UrdfFrames)
    dh: tuple[DHLink, ...] = PUMA560_DH

    def joint_state(self, st: RobotState) -> msgs.JointState:
        return msgs.JointState(Header.at(st.t_ns, ""), JOINT_NAMES, st.q)

    def tool_placement(self, st: RobotState) -> tuple[Vec3, tuple[float, ...]]:
        """eMt: the tool in the flange, from the state's flange and tool poses."""
        return relative_pose(st.flange_p, st.flange_R, st.tool_p, st.tool_R)

    def tf(self, st: RobotState) -> msgs.TFMessage:
        out: list[msgs.TransformStamped] = []
        for i, q in enumerate(st.q, start=1):
            prev = self.dh[i - 2] if i > 1 else None
            p, quat = _joint_transform(prev, q)
            out.append(
                msgs.TransformStamped(
                    Header.at(st.t_ns, self.frames.link(i - 1)), self.frames.link(i), p, quat
                )
            )
        last = self.dh[-1]
        ha = 0.5 * last.alpha_rad
        out.append(
            msgs.TransformStamped(
                Header.at(st.t_ns, self.frames.link(len(self.dh))),
                self.frames.flange,
                (last.a_m, 0.0, last.d_m),
                (math.sin(ha), 0.0, 0.0, math.cos(ha)),
            )
        )
        p_et, R_et = self.tool_placement(st)
        out.append(
            msgs.TransformStamped(
                Header.at(st.t_ns, self.frames.flange), self.frames.tool, p_et, quat_of(R_et)
            )
        )
        return msgs.TFMessage(tuple(out))


def wrench(f: ForceSample, tool_frame: str) -> msgs.WrenchStamped:
    """robot/force (tool frame, at the tool point) → WrenchStamped in the tool frame."""
    return msgs.WrenchStamped(Header.at(f.t_ns, tool_frame), f.f, f.c)  # type: ignore[arg-type]


def compressed_image(fr: StereoFrame, frame_id: str) -> msgs.CompressedImage:
    """A JPEG StereoFrame → CompressedImage (the bytes are passed through, not re-encoded)."""
    return msgs.CompressedImage(Header.at(fr.t_ns, frame_id), JPEG_FORMAT, fr.data)


def camera_info(fr: StereoFrame, frame_id: str) -> msgs.CameraInfo:
    """The pinhole model of a rectified eye (no distortion). K is zero when the frame carries
    no intrinsics (ROS's "uncalibrated"); the right eye's P carries Tx = −fx·baseline."""
    fx, fy, cx, cy = (fr.fx or 0.0), (fr.fy or 0.0), (fr.cx or 0.0), (fr.cy or 0.0)
    if fr.fx is None or fr.fy is None or fr.cx is None or fr.cy is None:
        fx = fy = cx = cy = 0.0
    tx = -fx * (fr.baseline or 0.0) if fr.eye == "r" else 0.0
    return msgs.CameraInfo(
        Header.at(fr.t_ns, frame_id),
        fr.height,
        fr.width,
        "plumb_bob",
        (0.0, 0.0, 0.0, 0.0, 0.0),
        (fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0 if fx else 0.0),
        (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
        (fx, 0.0, cx, tx, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0 if fx else 0.0, 0.0),
    )
