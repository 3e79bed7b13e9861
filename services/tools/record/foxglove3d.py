"""What a 3D viewer draws of a recording: the arm's frames, its model and the workcell.

Derived from the recorded streams by the recorder's writer thread (docs/record.md, "The arm
in 3D"), as Foxglove's well-known JSON schemas. The arm is whatever its description
(`robot/arm/description`, PROTOCOL.md §1) says it is: an `ArmView` is built from one
description, with the arm's URDF, its link poses (`services.control.arm.links.LinkPoses`)
and the tool placement eMt in use.

- `/tf` (`foxglove.FrameTransforms`), one message per `robot/state`: every URDF joint's
  parent → child transform at the recorded q (world → … → flange, and the links off the
  chain such as fingers), then flange → tool: the recorded tool pose seen from the flange
  pose of that q, so world → tool reproduces `robot/state`'s `tool_p`/`tool_R`. With no
  description yet, only world → flange → tool, from the state's own poses.
- `/robot_model` (`foxglove.SceneUpdate`), once per description and file: the URDF's visuals
  (cylinders, boxes, spheres, and meshes embedded in the message) and the tool shaft, each
  entity locked to its link frame, so the arm is drawn with no URDF layer to set up.
- `/robot_description` (`std_msgs/String`, JSON `{data}`), with `/robot_model`: the URDF
  itself with a `tool` link at eMt, which Foxglove's URDF layer reads from a topic; the same
  text is attached to the file (`<model>.urdf`).
- `/workcell` (`foxglove.SceneUpdate`), one message per `workcell/state`: the fixtures
  and every movable object at its pose, coloured as the scene description
  (`services.world.workcell.scene.default_scene`) colours them; a bottle shows its liquid, and
  spilled liquid lies in puddles where the video draws them
  (`services.control.vision.objects.Spills`).
"""

from __future__ import annotations

import base64
import math
from collections import deque
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from services.bus.errors import ConfigError
from services.bus.messages import ArmDescription
from services.control.arm.links import TOOL_LINK, LinkPoses, UrdfJoint, urdf_with_tool
from services.control.arm.model import ArmModel, model_from_description
from services.control.vision.objects import Spills
from services.geometry import R_from_wxyz, quat_of_rotation
from services.tools.record.schemas import TIME_SCHEMA
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState, objects_of
from services.world.workcell.scene import Box, Scene, default_scene

F64 = NDArray[np.float64]

FRAME_TRANSFORMS = "foxglove.FrameTransforms"
SCENE_UPDATE = "foxglove.SceneUpdate"
STRING = "std_msgs/String"
"""The schema name Foxglove's URDF layer takes a URDF topic by (its `data` is the XML)."""
TF_TOPIC = "/tf"
MODEL_TOPIC = "/robot_model"
DESCRIPTION_TOPIC = "/robot_description"
WORKCELL_TOPIC = "/workcell"
URDF_MEDIA_TYPE = "application/xml"
ROLE_DERIVED = "derived"
WORKCELL_KEY = WORKCELL_STATE.key
WORLD_FRAME = "world"
"""The world frame R_w (the arm's base frame) and the workcell's."""
FLANGE_FRAME = "flange"
"""The flange's frame name when no description says it (the frames of `robot/state` only)."""
TOOL_RADIUS_M = 0.012
"""The tool shaft drawn from the flange to the tool point."""
LIQUID_RGBA = (0.94, 0.84, 0.16, 0.9)
"""The liquid's colour (the amber the video shows)."""
MESH_MEDIA_TYPES = {
    ".stl": "model/stl",
    ".dae": "model/vnd.collada+xml",
    ".glb": "model/gltf-binary",
    ".obj": "model/obj",
}
"""The mesh files a `foxglove.ModelPrimitive` embeds, by suffix (others are left out)."""

# --- Foxglove's JSON Schemas (foxglove/schemas, schemas/jsonschema), the fields we write --
_TIME = TIME_SCHEMA
_DURATION = {
    "type": "object",
    "title": "duration",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}


def _numbers(title: str, names: str) -> dict[str, Any]:
    return {
        "title": title,
        "type": "object",
        "properties": {n: {"type": "number"} for n in names},
    }


_VECTOR3 = _numbers("foxglove.Vector3", "xyz")
_QUATERNION = _numbers("foxglove.Quaternion", "xyzw")
_COLOR = _numbers("foxglove.Color", "rgba")
_POSE = {
    "title": "foxglove.Pose",
    "type": "object",
    "properties": {"position": _VECTOR3, "orientation": _QUATERNION},
}

FRAME_TRANSFORMS_SCHEMA: dict[str, Any] = {
    "title": FRAME_TRANSFORMS,
    "description": "An array of FrameTransform messages",
    "type": "object",
    "properties": {
        "transforms": {
            "type": "array",
            "items": {
                "title": "foxglove.FrameTransform",
                "type": "object",
                "properties": {
                    "timestamp": _TIME,
                    "parent_frame_id": {"type": "string"},
                    "child_frame_id": {"type": "string"},
                    "translation": _VECTOR3,
                    "rotation": _QUATERNION,
                },
            },
        }
    },
}

_CUBE = {
    "title": "foxglove.CubePrimitive",
    "type": "object",
    "properties": {"pose": _POSE, "size": _VECTOR3, "color": _COLOR},
}
_SPHERE = {
    "title": "foxglove.SpherePrimitive",
    "type": "object",
    "properties": {"pose": _POSE, "size": _VECTOR3, "color": _COLOR},
}
_CYLINDER = {
    "title": "foxglove.CylinderPrimitive",
    "type": "object",
    "properties": {
        "pose": _POSE,
        "size": _VECTOR3,
        "bottom_scale": {"type": "number"},
        "top_scale": {"type": "number"},
        "color": _COLOR,
    },
}
_MODEL = {
    "title": "foxglove.ModelPrimitive",
    "type": "object",
    "properties": {
        "pose": _POSE,
        "scale": _VECTOR3,
        "color": _COLOR,
        "override_color": {"type": "boolean"},
        "url": {"type": "string"},
        "media_type": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}
SCENE_UPDATE_SCHEMA: dict[str, Any] = {
    "title": SCENE_UPDATE,
    "description": "An update to the entities displayed in a 3D scene",
    "type": "object",
    "properties": {
        "deletions": {
            "type": "array",
            "items": {
                "title": "foxglove.SceneEntityDeletion",
                "type": "object",
                "properties": {
                    "timestamp": _TIME,
                    "type": {
                        "oneOf": [
                            {"title": "MATCHING_ID", "const": 0},
                            {"title": "ALL", "const": 1},
                        ]
                    },
                    "id": {"type": "string"},
                },
            },
        },
        "entities": {
            "type": "array",
            "items": {
                "title": "foxglove.SceneEntity",
                "type": "object",
                "properties": {
                    "timestamp": _TIME,
                    "frame_id": {"type": "string"},
                    "id": {"type": "string"},
                    "lifetime": _DURATION,
                    "frame_locked": {"type": "boolean"},
                    "metadata": {
                        "type": "array",
                        "items": {
                            "title": "foxglove.KeyValuePair",
                            "type": "object",
                            "properties": {"key": {"type": "string"}, "value": {"type": "string"}},
                        },
                    },
                    "cubes": {"type": "array", "items": _CUBE},
                    "spheres": {"type": "array", "items": _SPHERE},
                    "cylinders": {"type": "array", "items": _CYLINDER},
                    "models": {"type": "array", "items": _MODEL},
                },
            },
        },
    },
}
STRING_SCHEMA: dict[str, Any] = {
    "title": STRING,
    "description": "A string (here: a URDF, for Foxglove's URDF layer)",
    "type": "object",
    "properties": {"data": {"type": "string"}},
}

SCHEMAS: dict[str, dict[str, Any]] = {
    FRAME_TRANSFORMS: FRAME_TRANSFORMS_SCHEMA,
    SCENE_UPDATE: SCENE_UPDATE_SCHEMA,
    STRING: STRING_SCHEMA,
}


# --- geometry ------------------------------------------------------------------------------
def quaternion(R: Sequence[float] | F64) -> dict[str, float]:
    """The unit quaternion {x, y, z, w} (w ≥ 0) of a rotation (3×3 or 9 row-major)."""
    w, x, y, z = quat_of_rotation(np.asarray(R, dtype=np.float64).reshape(9).tolist())
    return {"x": x, "y": y, "z": z, "w": w}


def rotation(q: Mapping[str, float]) -> F64:
    """The 3×3 rotation of a unit quaternion {x, y, z, w}."""
    return R_from_wxyz([q["w"], q["x"], q["y"], q["z"]])


def _time(t_ns: int) -> dict[str, int]:
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def _vec(v: Sequence[float] | F64) -> dict[str, float]:
    x, y, z = (float(a) for a in v)
    return {"x": x, "y": y, "z": z}


def _xyz(v: F64) -> dict[str, float]:
    """`_vec` of a float64 3-vector, faster (per-state work)."""
    x, y, z = v.tolist()
    return {"x": x, "y": y, "z": z}


def _pose(M: pin.SE3) -> dict[str, Any]:
    return {"position": _vec(M.translation), "orientation": quaternion(M.rotation)}


Transform = tuple[str, str, dict[str, float], dict[str, float]]
"""(parent frame, child frame, translation, rotation quaternion)."""


def _tool_transform(
    flange: str, tool: str, pf: F64, Rf: F64, state: Mapping[str, Any]
) -> Transform:
    """flange → tool: the state's tool pose seen from the flange pose (pf, Rf)."""
    Rt = np.asarray(state["tool_R"], dtype=np.float64).reshape(3, 3)
    pt = np.asarray(state["tool_p"], dtype=np.float64)
    return (flange, tool, _xyz(Rf.T @ (pt - pf)), quaternion(Rf.T @ Rt))


def _document(t_ns: int, tfs: list[Transform]) -> dict[str, Any]:
    t = _time(t_ns)
    return {
        "transforms": [
            {
                "timestamp": t,
                "parent_frame_id": parent,
                "child_frame_id": child,
                "translation": p,
                "rotation": R,
            }
            for parent, child, p, R in tfs
        ]
    }


def _parent_first(tree: Sequence[UrdfJoint], roots: Sequence[str]) -> list[UrdfJoint]:
    """The joints of a URDF tree ordered so that each parent link comes before its children
    (breadth first from `roots`); joints not reached from them are left out."""
    children: dict[str, list[UrdfJoint]] = {}
    for j in tree:
        children.setdefault(j.parent, []).append(j)
    out: list[UrdfJoint] = []
    todo = deque(roots)
    seen = set(roots)
    while todo:
        for j in children.get(todo.popleft(), []):
            if j.child not in seen:
                seen.add(j.child)
                out.append(j)
                todo.append(j.child)
    return out


class ArmView:
    """The 3D views of one arm, from its ArmDescription (PROTOCOL.md §1): its frame tree at
    a recorded q, its visuals, its URDF with the tool link. ConfigError (arm.model) when the
    description's URDF does not build. Not thread-safe (one LinkPoses)."""

    def __init__(self, desc: ArmDescription) -> None:
        self.description = desc
        self.model: ArmModel = model_from_description(desc)
        self.links = LinkPoses(self.model)
        self.base = desc.base_frame
        self.flange = desc.flange_frame
        names = {link for j in self.links.tree for link in (j.parent, j.child)}
        self.tool = TOOL_LINK if TOOL_LINK not in names else f"{TOOL_LINK}_eMt"
        """The tool frame's name: `tool`, unless the arm's URDF has a link of that name."""
        p, R = desc.eMt["p"], desc.eMt["R"]
        self.tool_p = np.asarray(p, dtype=np.float64).reshape(3)
        self.tool_R = np.asarray(R, dtype=np.float64).reshape(3, 3)
        self.urdf = urdf_with_tool(desc.urdf, self.flange, p, R, self.tool)
        """The URDF with the tool link at eMt: what `/robot_description` and the attachment
        hold."""
        self.urdf_name = f"{desc.model}.urdf"
        known = set(self.links.links)
        self._joints = [
            j
            for j in _parent_first(self.links.tree, [self.base])
            if j.parent in known and j.child in known
        ]
        # Only the chain's joints move (the others are fixed, or held like the fingers):
        # the transforms of the rest are computed once.
        moving = set(self.model.joint_names)
        poses = self.links.poses(self.model.home)
        self._fixed: dict[str, Transform] = {}
        for j in self._joints:
            if j.name not in moving:
                M = poses[j.parent].actInv(poses[j.child])
                self._fixed[j.name] = (
                    j.parent,
                    j.child,
                    _xyz(M.translation),
                    quaternion(M.rotation),
                )
        self._head: list[Transform] = []
        if self.base != WORLD_FRAME:  # the world frame R_w is the arm's base frame
            self._head.append((WORLD_FRAME, self.base, _vec((0, 0, 0)), quaternion(np.eye(3))))
        self._visuals: list[tuple[str, dict[str, list[dict[str, Any]]]]] | None = None
        self.visuals_error = ""
        """Why the URDF's visuals are not drawn (meshes not found), or empty."""

    def transforms(self, state: Mapping[str, Any]) -> list[Transform]:
        """The frame tree at one `robot/state` (its wire fields), parents first: every URDF
        joint at the state's q, then flange → tool from the state's tool pose. ValueError
        when q is not the arm's n joints."""
        poses = self.links.poses(state["q"])
        out = list(self._head)
        for j in self._joints:
            fixed = self._fixed.get(j.name)
            if fixed is None:
                M = poses[j.parent].actInv(poses[j.child])
                fixed = (j.parent, j.child, _xyz(M.translation), quaternion(M.rotation))
            out.append(fixed)
        oMf = poses[self.flange]
        out.append(_tool_transform(self.flange, self.tool, oMf.translation, oMf.rotation, state))
        return out

    def visuals(self) -> list[tuple[str, dict[str, list[dict[str, Any]]]]]:
        """(link, {"cubes"|"spheres"|"cylinders"|"models": primitives}) of the URDF's
        visuals, each in its link's frame, and the tool shaft in the flange frame. Built
        once; a model whose meshes are not found here (not a shipped model) is drawn with
        its tool shaft only (`visuals_error` says why)."""
        if self._visuals is None:
            by_link: dict[str, dict[str, list[dict[str, Any]]]] = {}
            try:
                geom = self.model.geometry()
            except (ConfigError, RuntimeError, ValueError, OSError) as e:
                self.visuals_error = str(e)
                geom = None
            if geom is not None:
                frames = self.model.pin_model().frames
                for go in geom.geometryObjects:
                    frame = frames[go.parentFrame]
                    kind, prim = _primitive(go, frame.placement.actInv(go.placement))
                    if prim is not None:
                        by_link.setdefault(frame.name, {}).setdefault(kind, []).append(prim)
            shaft = _cylinder_between((0, 0, 0), self.tool_p, TOOL_RADIUS_M, _TOOL_RGBA)
            if shaft is not None:
                by_link.setdefault(self.flange, {}).setdefault("cylinders", []).append(shaft)
            self._visuals = list(by_link.items())
        return self._visuals


def _rgba_of(c: Sequence[float]) -> dict[str, float]:
    r, g, b, a = (float(x) for x in c)
    return {"r": r, "g": g, "b": b, "a": a}


def _primitive(go: Any, M: pin.SE3) -> tuple[str, dict[str, Any] | None]:
    """One visual of a Pinocchio GeometryObject, placed by `M` in its link frame: the kind
    of primitive and its `foxglove.*Primitive` (None: a shape Foxglove cannot draw)."""
    g = go.geometry
    color = _rgba_of(go.meshColor)
    # coal's (formerly hppfcl's) shapes, told apart by name: their module depends on pin's
    # version.
    shape = type(g).__name__
    if shape == "Cylinder":
        d = 2.0 * float(g.radius)
        size = {"x": d, "y": d, "z": 2.0 * float(g.halfLength)}
        body = {"pose": _pose(M), "size": size, "bottom_scale": 1.0, "top_scale": 1.0}
        return "cylinders", {**body, "color": color}
    if shape == "Box":
        size = _vec(2.0 * np.asarray(g.halfSide, dtype=np.float64))
        return "cubes", {"pose": _pose(M), "size": size, "color": color}
    if shape == "Sphere":
        d = 2.0 * float(g.radius)
        return "spheres", {"pose": _pose(M), "size": {"x": d, "y": d, "z": d}, "color": color}
    path = Path(str(go.meshPath))
    media = MESH_MEDIA_TYPES.get(path.suffix.lower())
    if media is None or not path.is_file():
        return "models", None
    return "models", {
        "pose": _pose(M),
        "scale": _vec(go.meshScale),
        "color": color,
        # An STL has no colour of its own; another format keeps its own unless the URDF
        # gave the visual a material.
        "override_color": media == "model/stl" or bool(go.overrideMaterial),
        "url": "",
        "media_type": media,
        "data": base64.b64encode(path.read_bytes()).decode("ascii"),
    }


def frame_transforms(state: Mapping[str, Any], arm: ArmView | None = None) -> dict[str, Any]:
    """The `foxglove.FrameTransforms` of one `robot/state` (its wire fields): the arm's
    frame tree (`ArmView.transforms`), or with no arm described, world → flange → tool from
    the state's poses. ValueError when q does not fit the arm."""
    if arm is not None:
        tfs = arm.transforms(state)
    else:
        Rf = np.asarray(state["flange_R"], dtype=np.float64).reshape(3, 3)
        pf = np.asarray(state["flange_p"], dtype=np.float64)
        tfs = [
            (WORLD_FRAME, FLANGE_FRAME, _vec(pf), quaternion(Rf)),
            _tool_transform(FLANGE_FRAME, TOOL_LINK, pf, Rf, state),
        ]
    return _document(int(state["t_ns"]), tfs)


def robot_model(t_ns: int, arm: ArmView) -> dict[str, Any]:
    """A `foxglove.SceneUpdate` drawing the arm (`ArmView.visuals`), each entity locked to
    its link frame (so `/tf` moves it); it first deletes what an earlier one drew."""
    t = _time(t_ns)
    entities = [
        {
            "timestamp": t,
            "frame_id": link,
            "id": f"arm/{link}",
            "lifetime": {"sec": 0, "nsec": 0},
            "frame_locked": True,
            "metadata": [{"key": "model", "value": arm.description.model}],
            "cubes": prims.get("cubes", []),
            "spheres": prims.get("spheres", []),
            "cylinders": prims.get("cylinders", []),
            "models": prims.get("models", []),
        }
        for link, prims in arm.visuals()
    ]
    return {"deletions": [{"timestamp": t, "type": 1, "id": ""}], "entities": entities}


def robot_description(arm: ArmView) -> dict[str, Any]:
    """The `std_msgs/String` of `/robot_description`: the URDF with the tool link."""
    return {"data": arm.urdf}


def _rgba(bgr: tuple[int, int, int], a: float = 1.0) -> dict[str, float]:
    b, g, r = bgr
    return {"r": r / 255.0, "g": g / 255.0, "b": b / 255.0, "a": a}


def _cylinder_between(
    start: Sequence[float] | F64,
    end: Sequence[float] | F64,
    radius_m: float,
    color: dict[str, float],
) -> dict[str, Any] | None:
    a, b = np.asarray(start, float), np.asarray(end, float)
    d = b - a
    length = float(np.linalg.norm(d))
    if length < 1e-9:
        return None
    u = d / length
    # The rotation taking z onto u: axis z × u, angle acos(u_z).
    w, x, y = 1.0 + u[2], -u[1], u[0]
    n = math.sqrt(w * w + x * x + y * y)
    orient = {"x": x / n, "y": y / n, "z": 0.0, "w": w / n} if n > 1e-9 else {
        "x": 1.0, "y": 0.0, "z": 0.0, "w": 0.0
    }  # fmt: skip
    return {
        "pose": {"position": _vec(0.5 * (a + b)), "orientation": orient},
        "size": {"x": 2 * radius_m, "y": 2 * radius_m, "z": length},
        "bottom_scale": 1.0,
        "top_scale": 1.0,
        "color": color,
    }


_TOOL_RGBA = {"r": 0.9, "g": 0.45, "b": 0.1, "a": 1.0}


def _entity(
    t: dict[str, int], name: str, cubes: list[Any], cyls: list[Any], meta: dict[str, str]
) -> dict[str, Any]:
    return {
        "timestamp": t,
        "frame_id": WORLD_FRAME,
        "id": f"workcell/{name}",
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [{"key": k, "value": v} for k, v in meta.items()],
        "cubes": cubes,
        "cylinders": cyls,
    }


def _fixture(t: dict[str, int], b: Box) -> dict[str, Any]:
    cube = {
        "pose": {
            "position": _vec(b.center),
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        },
        "size": _vec(b.size),
        "color": _rgba(b.color),
    }
    return _entity(t, b.name, [cube], [], {"fixture": "true"})


def workcell_update(
    state: Mapping[str, Any], scene: Scene | None = None, spills: Spills | None = None
) -> dict[str, Any]:
    """The `foxglove.SceneUpdate` of one `workcell/state` (its wire fields, objects checked
    by `services.world.workcell.messages.objects_of`): fixtures and objects, world frame; with
    `spills` (updated from this state), the puddles as one entity `workcell/spills`."""
    scene = scene if scene is not None else SCENE
    msg = WorkcellState(
        seq=int(state["seq"]),
        t_ns=int(state["t_ns"]),
        tool_p=tuple(state["tool_p"]),
        grip=float(state["grip"]),
        held=str(state["held"]),
        objects=dict(state["objects"]),
    )
    t = _time(msg.t_ns)
    entities = [_fixture(t, b) for b in scene.fixtures().boxes]
    views = objects_of(msg)
    if spills is not None:
        spills.update(views)
        puddles = [
            {
                "pose": {
                    "position": _vec(o.p + np.array([0.0, 0.0, 0.5 * o.size[2]])),
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                },
                "size": _vec(o.size),
                "bottom_scale": 1.0,
                "top_scale": 1.0,
                "color": _rgba(o.color, 0.9),
            }
            for o in spills.objects()
        ]
        entities.append(_entity(t, "spills", [], puddles, {}))
    for name, v in views.items():
        try:
            bgr = scene.solid(name).color
        except KeyError:
            bgr = (160, 160, 160)
        meta = {"phase": v.phase, "on": v.on, "held": str(name == msg.held).lower()}
        orient = quaternion(v.R)
        centre = v.centre
        if v.kind == "box":
            cube = {
                "pose": {"position": _vec(centre), "orientation": orient},
                "size": _vec(v.size),
                "color": _rgba(bgr),
            }
            entities.append(_entity(t, name, [cube], [], meta))
            continue
        cyls = [
            {
                "pose": {"position": _vec(centre), "orientation": orient},
                "size": _vec(v.size),
                "bottom_scale": 1.0,
                "top_scale": 1.0,
                "color": _rgba(bgr, 0.45),
            }
        ]
        if v.liquid_ml is not None:
            meta["liquid_ml"] = f"{v.liquid_ml:.1f}"
            meta["spilled_ml"] = f"{v.spilled_ml or 0.0:.1f}"
            r = 0.5 * float(v.size[0])
            h = min(max(v.liquid_ml, 0.0) * 1e-6 / (math.pi * r * r), float(v.size[2]))
            if h > 1e-4:
                mid = v.p + v.R @ np.array([0.0, 0.0, 0.5 * h])
                cyls.append(
                    {
                        "pose": {"position": _vec(mid), "orientation": orient},
                        "size": {"x": 1.9 * r, "y": 1.9 * r, "z": h},
                        "bottom_scale": 1.0,
                        "top_scale": 1.0,
                        "color": dict(zip("rgba", LIQUID_RGBA, strict=True)),
                    }
                )
        entities.append(_entity(t, name, [], cyls, meta))
    return {"deletions": [], "entities": entities}


SCENE = default_scene()
