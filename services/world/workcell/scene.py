"""The simulated workcell: one description of the scene for physics, rendering and tasks.

Every simulated part of the system reads geometry from here: the workcell's MuJoCo cell
(mujoco_model.py: the contacts are its solver's), the vision service's renderer, the
decision server's guarded moves and the task scenarios. Frames: world (R_w: z up, floor
at z = 0; an arm's model says where its base stands in it). Units: m.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from services.geometry import Array3


@dataclass(frozen=True, slots=True)
class Box:
    """An axis-aligned box: `center` (m, world), full `size` (m), BGR `color` for rendering."""

    name: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    color: tuple[int, int, int] = (160, 160, 160)
    #: an object the gripper may pick up (the MuJoCo cell gives it a free joint); fixtures are not
    movable: bool = False

    @property
    def lo(self) -> Array3:
        return np.asarray(self.center) - 0.5 * np.asarray(self.size)

    @property
    def hi(self) -> Array3:
        return np.asarray(self.center) + 0.5 * np.asarray(self.size)

    @property
    def top_z(self) -> float:
        return float(self.center[2] + 0.5 * self.size[2])

    def corners(self) -> NDArray[np.float64]:
        """The 8 corners, (8, 3), ordered by the bits (x, y, z) of the index."""
        lo, hi = self.lo, self.hi
        return np.array(
            [
                [(hi if i & 1 else lo)[0], (hi if i & 2 else lo)[1], (hi if i & 4 else lo)[2]]
                for i in range(8)
            ]
        )


@dataclass(frozen=True, slots=True)
class Cylinder:
    """An upright cylinder (a bottle): base centre `base` (m, world), `radius`, `height`.

    A movable cylinder is an open-topped bottle holding liquid up to `liquid_height_m`
    (m above its base, upright) at the start; it spills when tilted (docs/tasks.md, W3).
    """

    name: str
    base: tuple[float, float, float]
    radius: float
    height: float
    color: tuple[int, int, int] = (200, 140, 60)
    movable: bool = False
    liquid_height_m: float = 0.0

    @property
    def top_z(self) -> float:
        return float(self.base[2] + self.height)


@dataclass(frozen=True, slots=True)
class Scene:
    """The workcell: the floor plane z = `floor_z`, a table and the objects on it."""

    floor_z: float = 0.0
    boxes: tuple[Box, ...] = field(default_factory=tuple)
    cylinders: tuple[Cylinder, ...] = field(default_factory=tuple)

    def box(self, name: str) -> Box:
        for b in self.boxes:
            if b.name == name:
                return b
        raise KeyError(name)

    def cylinder(self, name: str) -> Cylinder:
        for c in self.cylinders:
            if c.name == name:
                return c
        raise KeyError(name)

    def solid(self, name: str) -> Box | Cylinder:
        """The box or cylinder called `name` (KeyError if none)."""
        for s in self.solids():
            if s.name == name:
                return s
        raise KeyError(name)

    def solids(self) -> tuple[Box | Cylinder, ...]:
        """Every box, then every cylinder, in declaration order."""
        out: list[Box | Cylinder] = [*self.boxes]
        out.extend(self.cylinders)
        return tuple(out)

    def movables(self) -> tuple[Box | Cylinder, ...]:
        """The objects the gripper may pick up, boxes first, in declaration order."""
        return tuple(s for s in self.solids() if s.movable)

    def fixtures(self) -> Scene:
        """The static part: the same scene without its movable objects (what never moves,
        so a renderer can draw it once and the objects over it from `workcell/state`)."""
        return replace(
            self,
            boxes=tuple(b for b in self.boxes if not b.movable),
            cylinders=tuple(c for c in self.cylinders if not c.movable),
        )

    def moved(self, origins: Mapping[str, Sequence[float]]) -> Scene:
        """The same scene with solids moved: `origins[name]` is a box's new `center` or a
        cylinder's new `base` (m, world). Solids stay axis-aligned and upright: a renderer
        of this scene sees a moved object at its new place, not its tilt
        (the dynamic poses are in `workcell/state`, docs/tasks.md)."""
        boxes = tuple(
            replace(b, center=_triple(origins[b.name])) if b.name in origins else b
            for b in self.boxes
        )
        cylinders = tuple(
            replace(c, base=_triple(origins[c.name])) if c.name in origins else c
            for c in self.cylinders
        )
        return replace(self, boxes=boxes, cylinders=cylinders)


def _triple(v: Sequence[float]) -> tuple[float, float, float]:
    if len(v) != 3:
        raise ValueError(f"expected 3 coordinates, got {len(v)}")
    return (float(v[0]), float(v[1]), float(v[2]))


TABLE = Box("table", center=(0.60, 0.0, 0.20), size=(0.50, 0.90, 0.40), color=(60, 90, 140))
"""The table in front of the arm: top at z = 0.40 m, reachable with the tool pointing down."""

BLOCK_SIZE_M = 0.05
BOTTLE_LIQUID_HEIGHT_M = 0.18
"""Liquid in the bottle (m above its base, upright): 18 of its 20 cm, so it spills past a
tilt of atan((0.20 − 0.18) / 0.035) = 29.7° (docs/tasks.md, W3)."""


def default_scene() -> Scene:
    """The standard workcell: floor, table, three blocks and a bottle on the table top."""
    top = TABLE.top_z
    h = BLOCK_SIZE_M
    blocks = tuple(
        Box(f"block{i}", center=(0.50, y, top + h / 2), size=(h, h, h), color=col, movable=True)
        for i, (y, col) in enumerate(
            [(-0.20, (40, 40, 200)), (-0.10, (40, 180, 40)), (0.0, (200, 60, 40))]
        )
    )
    bottle = Cylinder(
        "bottle",
        base=(0.55, 0.25, top),
        radius=0.035,
        height=0.20,
        movable=True,
        liquid_height_m=BOTTLE_LIQUID_HEIGHT_M,
    )
    return Scene(boxes=(TABLE, *blocks), cylinders=(bottle,))
