"""Telerobot messages → ROS 2 messages, pure functions on plain floats (they run per sample).

The arm is whatever the arm service describes (robot/arm/description, PROTOCOL §1): an
`ArmView` is built from one ArmDescription and knows nothing of any particular model. Its
URDF is the description's with the tool link added at the described eMt (what
/robot_description carries); /joint_states names the described joints; /tf carries every
URDF joint's parent→child transform (services/control/arm/links.py, `LinkPoses`), so RViz's
robot model follows /tf with nothing else running, and then the flange→tool transform
from each RobotState (eMt = oMe⁻¹·oMt, the placement the arm really uses). The root of /tf
is the URDF's root link, the description's `base_frame` (the world frame R_w).
Quaternions are ROS's (x, y, z, w).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from services.bus.errors import ConfigError
from services.bus.messages import ArmDescription, ForceSample, RobotState, StereoFrame
from services.control.arm.links import TOOL_LINK, LinkPoses, urdf_tree, urdf_with_tool
from services.control.arm.model import model_from_description
from services.frontends.rosmsg import msgs
from services.frontends.rosmsg.msgs import Header, QuatXyzw
from services.geometry import V3, quat_of_rotation, rotation_of_quat

JPEG_FORMAT = "bgr8; jpeg compressed bgr8"
"""What compressed_image_transport writes for a colour JPEG (RViz, rqt and Foxglove read it)."""


def quat_of(R: Sequence[float]) -> QuatXyzw:
    """The unit quaternion in ROS's order (x, y, z, w), w ≥ 0, of a row-major rotation."""
    w, x, y, z = quat_of_rotation(R)
    return (x, y, z, w)


def rotation_of(q: QuatXyzw) -> tuple[float, ...]:
    """The row-major rotation of a quaternion in ROS's order (x, y, z, w)."""
    x, y, z, w = q
    return rotation_of_quat(w, x, y, z)


def relative_pose(
    pa: Sequence[float], Ra: Sequence[float], pb: Sequence[float], Rb: Sequence[float]
) -> tuple[V3, tuple[float, ...]]:
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


def transform_of(M: pin.SE3) -> tuple[V3, QuatXyzw]:
    """(translation, quaternion) of a rigid transform, as TransformStamped carries them."""
    t = M.translation
    R: list[float] = np.asarray(M.rotation).reshape(9).tolist()
    return (float(t[0]), float(t[1]), float(t[2])), quat_of(R)


class ArmView:
    """One ArmDescription as ROS sees it: `urdf` (/robot_description) and RobotState →
    /joint_states and /tf. ConfigError when the description cannot be drawn: its URDF
    does not build (key `arm.model`), or already has a link named `tool_frame`
    (`ros2.tool_frame`). `joint_state` and `tf` are thread-safe; a state whose `q` has not
    the described n joints raises ValueError (see `fits`)."""

    def __init__(self, desc: ArmDescription, tool_frame: str = TOOL_LINK) -> None:
        model = model_from_description(desc)
        links = {link for j in urdf_tree(desc.urdf) for link in (j.parent, j.child)}
        if tool_frame in links:
            raise ConfigError(
                "ros2.tool_frame",
                f"the URDF of {desc.model!r} already has a link {tool_frame!r}: set another "
                "[ros2] tool_frame for the tool",
            )
        self.model = desc.model
        self.n = model.n
        self.joint_names = model.joint_names
        self.world_frame = desc.base_frame
        self.flange_frame = desc.flange_frame
        self.tool_frame = tool_frame
        self.tool_p = tuple(float(x) for x in desc.eMt["p"])
        self.tool_R = tuple(float(x) for x in desc.eMt["R"])
        self.urdf = urdf_with_tool(
            desc.urdf, desc.flange_frame, self.tool_p, self.tool_R, name=tool_frame
        )
        self._poses = LinkPoses(model)
        self._lock = threading.Lock()
        # The joints off the arm's chain (fixed ones, locked fingers) do not move: their
        # transforms are computed once; the chain's at each state.
        moving = set(self.joint_names)
        self._fixed: tuple[tuple[V3, QuatXyzw] | None, ...] = tuple(
            None if j.name in moving else transform_of(M)
            for j, M in self._poses.transforms(model.home)
        )

    def fits(self, st: RobotState) -> bool:
        """Whether `st` has the described number of joints."""
        return len(st.q) == self.n

    def joint_state(self, st: RobotState) -> msgs.JointState:
        if not self.fits(st):
            raise ValueError(f"robot/state has {len(st.q)} joints, {self.model} has {self.n}")
        return msgs.JointState(Header.at(st.t_ns, ""), self.joint_names, st.q)

    def tool_placement(self, st: RobotState) -> tuple[V3, tuple[float, ...]]:
        """eMt: the tool in the flange, from the state's flange and tool poses."""
        return relative_pose(st.flange_p, st.flange_R, st.tool_p, st.tool_R)

    def tf(self, st: RobotState) -> msgs.TFMessage:
        """Every URDF joint's parent→child transform at the state's joints, in the URDF's
        order, then flange→tool."""
        with self._lock:  # LinkPoses has one pin.Data
            joints = self._poses.transforms(st.q)  # ValueError on a wrong n
        out: list[msgs.TransformStamped] = []
        for (j, M), fixed in zip(joints, self._fixed, strict=True):
            p, quat = fixed if fixed is not None else transform_of(M)
            out.append(msgs.TransformStamped(Header.at(st.t_ns, j.parent), j.child, p, quat))
        p_et, R_et = self.tool_placement(st)
        out.append(
            msgs.TransformStamped(
                Header.at(st.t_ns, self.flange_frame), self.tool_frame, p_et, quat_of(R_et)
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
