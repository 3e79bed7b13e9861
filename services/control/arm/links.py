"""Where every link of the arm is, for those who draw it or publish its frames.

The arm's kinematics already gives the tool and flange poses of a joint vector, and it
publishes them in `robot/state`; a viewer needs more: the pose of every URDF link (to place
its visuals) and every URDF joint's parent→child transform (ROS's /tf, Foxglove's frame
transforms). `LinkPoses` computes them for any model from its Pinocchio model and the URDF's
joint tree, in one forward-kinematics pass per joint vector. `urdf_with_tool` adds the tool
frame (eMt, which is not part of the arm's URDF) as a `tool` link, for a viewer that draws
the URDF.

Frames: world R_w (the model's base frame). Units: m, rad. Not thread-safe (one pin.Data).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from services.control.arm.model import ArmModel

TOOL_LINK = "tool"


@dataclass(frozen=True, slots=True)
class UrdfJoint:
    """One joint of the URDF tree: its name, type, parent and child links."""

    name: str
    kind: str
    parent: str
    child: str


def urdf_tree(urdf: str) -> tuple[UrdfJoint, ...]:
    """Every `<joint>` of a URDF, in file order."""
    root = ET.fromstring(urdf)
    out = []
    for j in root.iter("joint"):
        parent, child = j.find("parent"), j.find("child")
        if parent is None or child is None:
            continue
        out.append(
            UrdfJoint(
                str(j.get("name")),
                str(j.get("type")),
                str(parent.get("link")),
                str(child.get("link")),
            )
        )
    return tuple(out)


def urdf_with_tool(
    urdf: str,
    flange: str,
    tool_p: Sequence[float],
    tool_R: Sequence[float],
    name: str = TOOL_LINK,
) -> str:
    """The URDF with a link `name` fixed to `flange` at eMt = (tool_R row-major, tool_p):
    the tool frame, for a viewer that draws the URDF (RViz, Foxglove)."""
    root = ET.fromstring(urdf)
    if any(e.get("name") == name for e in root.iter("link")):
        return urdf
    R = np.asarray(tool_R, dtype=np.float64).reshape(3, 3)
    rpy = pin.rpy.matrixToRpy(R)
    ET.SubElement(root, "link", {"name": name})
    joint = ET.SubElement(root, "joint", {"name": f"{name}_joint", "type": "fixed"})
    ET.SubElement(joint, "parent", {"link": flange})
    ET.SubElement(joint, "child", {"link": name})
    ET.SubElement(
        joint,
        "origin",
        {
            "xyz": " ".join(repr(float(x) + 0.0) for x in tool_p),
            "rpy": " ".join(repr(float(x) + 0.0) for x in rpy),
        },
    )
    return ET.tostring(root, encoding="unicode")


class LinkPoses:
    """The world pose of every link of a model, and the transform of every URDF joint."""

    def __init__(self, model: ArmModel) -> None:
        self.model_name = model.name
        self.tree = urdf_tree(model.urdf)
        self._pin = model.pin_model()
        self._data = self._pin.createData()
        self._frames: dict[str, int] = {}
        for j in self.tree:
            for link in (j.parent, j.child):
                if link not in self._frames and self._pin.existFrame(link):
                    self._frames[link] = self._pin.getFrameId(link)
        self.links: tuple[str, ...] = tuple(self._frames)
        """The links whose pose is known (every link of the URDF tree Pinocchio kept)."""
        self.n = self._pin.nq

    def poses(self, q: Sequence[float]) -> dict[str, pin.SE3]:
        """link → its pose in the world at joints q (n floats, rad)."""
        qv = np.asarray(q, dtype=np.float64)
        if qv.shape != (self.n,) or not np.all(np.isfinite(qv)):
            raise ValueError(f"expected {self.n} finite joint angles")
        pin.framesForwardKinematics(self._pin, self._data, qv)
        return {name: pin.SE3(self._data.oMf[fid]) for name, fid in self._frames.items()}

    def transforms(self, q: Sequence[float]) -> list[tuple[UrdfJoint, pin.SE3]]:
        """Each URDF joint with its parent→child transform at joints q (what /tf carries)."""
        poses = self.poses(q)
        out = []
        for j in self.tree:
            a, b = poses.get(j.parent), poses.get(j.child)
            if a is not None and b is not None:
                out.append((j, a.actInv(b)))
        return out
