"""The workcell as the console draws it: scene-node poses from `workcell/state`.

Pure functions of the scene description (`services.world.workcell.scene`, the one the workcell,
force and vision simulations use) and of a decoded `workcell/state` (`objects_of`), so the
3D scene is tested without a browser. Spilled liquid lies where the video and the
recordings put it (`services.control.vision.objects.Spills`). Frames: world (z up), m. Node names
are the page's (`/workcell/<object>`, `/workcell/<object>/liquid`, `/workcell/spill<i>`,
`/arm/tool_frame/finger_l|r`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from services.bus.bounds import each_out_of_bounds
from services.bus.errors import ProtocolError
from services.control.vision.objects import Spills
from services.geometry import V3, Quat, wxyz_from_R
from services.world.workcell.messages import M3_PER_ML, ObjectView
from services.world.workcell.scene import Box, Cylinder, Scene

LIQUID_INSET = 0.85
"""The liquid's radius as a fraction of its bottle's (drawn inside the bottle's wall)."""
FINGER_SIZE_M: V3 = (0.012, 0.02, 0.06)
"""A gripper finger (x, y, z in the tool frame): it hangs below the palm (the tool point)."""
GRIPPER_OPEN_M = 0.09
"""The gap between the fingers of the open gripper (grip 0); closed (grip 1) it is 0."""
PUDDLE_THICKNESS_M = 0.002


@dataclass(frozen=True, slots=True)
class ObjectNode:
    """One movable object as drawn: the solid's node at its centre `position` (world) with
    orientation `wxyz`; for a bottle the liquid column (`liquid_height_m` inside the bottle,
    its centre `liquid_z_m` in the bottle's frame)."""

    name: str
    position: V3
    wxyz: Quat
    phase: str
    liquid_height_m: float = 0.0
    liquid_z_m: float = 0.0


@dataclass(frozen=True, slots=True)
class PuddleNode:
    """A puddle of spilled liquid: a flat disc of `radius_m` centred at `position` (world)."""

    position: V3
    radius_m: float


def _t3(v: np.ndarray) -> V3:
    return (float(v[0]), float(v[1]), float(v[2]))


def _volume_m3(ml: float | None) -> float:
    """A volume off the wire (ml) in m³: none, negative or not finite draws nothing."""
    if ml is None or not math.isfinite(ml) or ml <= 0.0:
        return 0.0
    return ml * M3_PER_ML


def object_node(scene: Scene, view: ObjectView) -> ObjectNode:
    """How `view` (one object of `workcell/state`) is drawn; ProtocolError if it does not
    match the scene (unknown name or kind) or lies outside the world's bounds."""
    try:
        solid = scene.solid(view.name)
    except KeyError:
        raise ProtocolError(f"objects.{view.name}", "not an object of the scene") from None
    if (view.kind == "box") != isinstance(solid, Box):
        raise ProtocolError(f"objects.{view.name}.kind", "does not match the scene")
    why = each_out_of_bounds(f"objects.{view.name}.p", view.p.tolist(), "position_m")
    if why is not None:
        raise ProtocolError(f"objects.{view.name}.p", why)
    centre = view.centre
    q = wxyz_from_R(view.R)
    wxyz = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    node = ObjectNode(view.name, _t3(centre), wxyz, view.phase)
    if not isinstance(solid, Cylinder) or solid.liquid_height_m <= 0.0:
        return node
    area = math.pi * solid.radius**2
    liquid_m3 = _volume_m3(view.liquid_ml)
    h = min(solid.height, liquid_m3 / area)
    return ObjectNode(
        view.name,
        _t3(centre),
        wxyz,
        view.phase,
        liquid_height_m=h,
        liquid_z_m=-0.5 * solid.height + 0.5 * h,
    )


def object_nodes(scene: Scene, views: Mapping[str, ObjectView]) -> dict[str, ObjectNode]:
    """Every object of the state, drawn (see `object_node`), by name."""
    return {name: object_node(scene, v) for name, v in views.items()}


def puddle_nodes(spills: Spills) -> tuple[PuddleNode, ...]:
    """The puddles `spills` holds (updated from every state drawn), as the video draws
    them: a disc at each puddle's place on its surface, of the video's radius."""
    out = []
    for pose in spills.objects():
        p = pose.p
        out.append(
            PuddleNode(
                (float(p[0]), float(p[1]), float(p[2]) + 0.5 * PUDDLE_THICKNESS_M),
                0.5 * float(pose.size[0]),
            )
        )
    return tuple(out)


def finger_offsets(grip: float | None) -> tuple[V3, V3] | None:
    """The centres (tool frame, m) of the left and right fingers for `grip` (0 open … 1
    closed), or None when the robot reports no gripper."""
    if grip is None or not math.isfinite(grip):
        return None
    g = min(1.0, max(0.0, grip))
    half_gap = 0.5 * GRIPPER_OPEN_M * (1.0 - g) + 0.5 * FINGER_SIZE_M[1]
    z = 0.5 * FINGER_SIZE_M[2]
    return (0.0, half_gap, z), (0.0, -half_gap, z)


__all__ = [
    "FINGER_SIZE_M",
    "ObjectNode",
    "PuddleNode",
    "finger_offsets",
    "object_node",
    "object_nodes",
    "puddle_nodes",
]
