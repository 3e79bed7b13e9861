"""What a 3D viewer draws of a recording: the arm's frames, its model and the workcell.

Derived from the recorded streams by the recorder's writer thread (docs/record.md, "The arm
in 3D"), as Foxglove's well-known JSON schemas:

- `/tf` (`foxglove.FrameTransforms`), one message per `robot/state`: the frame tree of the
  URDF `services.control.arm.urdf.puma_urdf` generates from the contract's DH table, world →
  link1 … link6 → flange → tool. Joint i's transform is the URDF's fixed origin F_{i−1}
  followed by Rz(q_i), so world → flange is the DH forward kinematics of the recorded q;
  flange → tool is the recorded tool pose seen from the recorded flange pose, so world →
  tool reproduces `robot/state`'s `tool_p`/`tool_R`.
- `/robot_model` (`foxglove.SceneUpdate`), once per file: the URDF's visuals (pedestal,
  joint housings, links, tool shaft) as cylinders locked to those frames, so the arm is
  drawn with no URDF layer to set up. The URDF itself is attached to the file
  (`puma560.urdf`) for viewers that load one.
- `/workcell` (`foxglove.SceneUpdate`), one message per `workcell/state`: the fixtures
  and every movable object at its pose, coloured as the scene description
  (`services.world.workcell.scene.default_scene`) colours them; a bottle shows its liquid, and
  spilled liquid lies in puddles where the video draws them
  (`services.control.vision.objects.Spills`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.control.arm.kinematics import PUMA560_DH, DHLink
from services.control.arm.urdf import (
    JOINT_LENGTH_M,
    JOINT_RADIUS_M,
    LINK_RADIUS_M,
    TOOL_RADIUS_M,
    UrdfFrames,
)
from services.control.vision.objects import Spills
from services.geometry import R_from_wxyz, quat_of_rotation, quat_of_rx_rz
from services.tools.record.schemas import TIME_SCHEMA
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState, objects_of
from services.world.workcell.scene import Box, Scene, default_scene

F64 = NDArray[np.float64]

FRAME_TRANSFORMS = "foxglove.FrameTransforms"
SCENE_UPDATE = "foxglove.SceneUpdate"
TF_TOPIC = "/tf"
MODEL_TOPIC = "/robot_model"
WORKCELL_TOPIC = "/workcell"
URDF_NAME = "puma560.urdf"
URDF_MEDIA_TYPE = "application/xml"
ROLE_DERIVED = "derived"
WORKCELL_KEY = WORKCELL_STATE.key
FRAMES = UrdfFrames()
LIQUID_RGBA = (0.94, 0.84, 0.16, 0.9)
"""The liquid's colour (the amber the video shows)."""

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
                    "cylinders": {"type": "array", "items": _CYLINDER},
                },
            },
        },
    },
}

SCHEMAS: dict[str, dict[str, Any]] = {
    FRAME_TRANSFORMS: FRAME_TRANSFORMS_SCHEMA,
    SCENE_UPDATE: SCENE_UPDATE_SCHEMA,
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


def _joint_quaternion(alpha_rad: float, q_rad: float) -> dict[str, float]:
    """The quaternion of Rx(α)·Rz(q) (w ≥ 0)."""
    w, x, y, z = quat_of_rx_rz(alpha_rad, q_rad)
    return {"x": x, "y": y, "z": z, "w": w}


def joint_transforms(
    q: Sequence[float], dh: Sequence[DHLink] = PUMA560_DH
) -> list[tuple[str, str, dict[str, float], dict[str, float]]]:
    """(parent, child, translation, rotation quaternion) of the URDF's joints at joint
    angles `q` (rad): world → link1 … link6 → flange. Joint i is the fixed part of DH row
    i − 1, Tz(d)·Tx(a)·Rx(α), then Rz(q_i)."""
    out = []
    for i in range(1, len(dh) + 1):
        prev = dh[i - 2] if i > 1 else DHLink(0.0, 0.0, 0.0, 0.0, 0.0)
        out.append(
            (
                FRAMES.link(i - 1),
                FRAMES.link(i),
                {"x": prev.a_m, "y": 0.0, "z": prev.d_m},
                _joint_quaternion(prev.alpha_rad, float(q[i - 1])),
            )
        )
    last = dh[-1]
    out.append(
        (
            FRAMES.link(len(dh)),
            FRAMES.flange,
            {"x": last.a_m, "y": 0.0, "z": last.d_m},
            _joint_quaternion(last.alpha_rad, 0.0),
        )
    )
    return out


def frame_transforms(state: Mapping[str, Any]) -> dict[str, Any]:
    """The `foxglove.FrameTransforms` of one `robot/state` (its wire fields)."""
    t = _time(int(state["t_ns"]))
    Rf = np.asarray(state["flange_R"], dtype=np.float64).reshape(3, 3)
    pf = np.asarray(state["flange_p"], dtype=np.float64)
    Rt = np.asarray(state["tool_R"], dtype=np.float64).reshape(3, 3)
    pt = np.asarray(state["tool_p"], dtype=np.float64)
    tfs = joint_transforms(state["q"])
    tfs.append((FRAMES.flange, FRAMES.tool, _vec(Rf.T @ (pt - pf)), quaternion(Rf.T @ Rt)))
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


def _rgba(bgr: tuple[int, int, int], a: float = 1.0) -> dict[str, float]:
    b, g, r = bgr
    return {"r": r / 255.0, "g": g / 255.0, "b": b / 255.0, "a": a}


def _cylinder_between(
    start: Sequence[float], end: Sequence[float], radius_m: float, color: dict[str, float]
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


_LINK_RGBA = {"r": 0.85, "g": 0.85, "b": 0.8, "a": 1.0}
_JOINT_RGBA = {"r": 0.3, "g": 0.3, "b": 0.35, "a": 1.0}
_TOOL_RGBA = {"r": 0.9, "g": 0.45, "b": 0.1, "a": 1.0}


def robot_model(
    t_ns: int, tool_p: Sequence[float], dh: Sequence[DHLink] = PUMA560_DH
) -> dict[str, Any]:
    """A `foxglove.SceneUpdate` drawing the URDF's visuals, each entity locked to its link
    frame (so `/tf` moves it). `tool_p`: the tool point in the flange frame."""
    t = _time(t_ns)
    entities = []

    def entity(frame: str, cyls: list[dict[str, Any] | None]) -> None:
        entities.append(
            {
                "timestamp": t,
                "frame_id": frame,
                "id": f"arm/{frame}",
                "lifetime": {"sec": 0, "nsec": 0},
                "frame_locked": True,
                "metadata": [],
                "cubes": [],
                "cylinders": [c for c in cyls if c is not None],
            }
        )

    entity(FRAMES.world, [_cylinder_between((0, 0, 0), (0, 0, dh[0].d_m), 0.08, _JOINT_RGBA)])
    half = JOINT_LENGTH_M / 2
    for i, link in enumerate(dh, start=1):
        cyls = [_cylinder_between((0, 0, -half), (0, 0, half), JOINT_RADIUS_M, _JOINT_RGBA)]
        if i > 1:
            cyls.append(_cylinder_between((0, 0, 0), (0, 0, link.d_m), LINK_RADIUS_M, _LINK_RGBA))
        cyls.append(
            _cylinder_between((0, 0, link.d_m), (link.a_m, 0, link.d_m), LINK_RADIUS_M, _LINK_RGBA)
        )
        entity(FRAMES.link(i), cyls)
    entity(FRAMES.flange, [_cylinder_between((0, 0, 0), tool_p, TOOL_RADIUS_M, _TOOL_RGBA)])
    return {"deletions": [], "entities": entities}


def _entity(
    t: dict[str, int], name: str, cubes: list[Any], cyls: list[Any], meta: dict[str, str]
) -> dict[str, Any]:
    return {
        "timestamp": t,
        "frame_id": FRAMES.world,
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
