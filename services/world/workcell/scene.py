"""The simulated workcell: one description of the scene for contact, rendering and tasks.

Every simulated part of the system reads geometry from here: the force service's contact
model, the vision service's renderer, the decision server's guarded moves and the task
scenarios. Frames: world (R_w: z up, floor at z = 0; an arm's model says where its base
stands in it). Units: m.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

Vec3 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Box:
    """An axis-aligned box: `center` (m, world), full `size` (m), BGR `color` for rendering."""

    name: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    color: tuple[int, int, int] = (160, 160, 160)
    stiffness_n_per_m: float = 20_000.0
    #: an object the gripper may pick up (services.world.workcell.physics); fixtures are not
    movable: bool = False

    @property
    def lo(self) -> Vec3:
        return np.asarray(self.center) - 0.5 * np.asarray(self.size)

    @property
    def hi(self) -> Vec3:
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
    stiffness_n_per_m: float = 20_000.0
    movable: bool = False
    liquid_height_m: float = 0.0

    @property
    def top_z(self) -> float:
        return float(self.base[2] + self.height)


@dataclass(frozen=True, slots=True)
class Contact:
    """A penetration of the probe sphere into a solid.

    `depth` (m, > 0 when penetrating), `normal` (unit, world, pointing out of the solid,
    i.e. the direction the solid pushes the probe), `force` = stiffness · depth · normal (N).
    """

    solid: str
    depth: float
    normal: Vec3
    force: Vec3


@dataclass(frozen=True, slots=True)
class Scene:
    """The workcell: the floor plane z = `floor_z`, a table and the objects on it."""

    floor_z: float = 0.0
    floor_stiffness_n_per_m: float = 50_000.0
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
        or contact model of this scene sees a moved object at its new place, not its tilt
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

    def contacts(self, point: Vec3, radius: float = 0.0) -> list[Contact]:
        """Every contact of a sphere of `radius` (m) centred at `point` (world) with the scene."""
        p = np.asarray(point, dtype=float)
        out: list[Contact] = []
        depth = self.floor_z - (p[2] - radius)
        if depth > 0:
            n = np.array([0.0, 0.0, 1.0])
            out.append(Contact("floor", depth, n, self.floor_stiffness_n_per_m * depth * n))
        for b in self.boxes:
            c = _box_contact(b, p, radius)
            if c is not None:
                out.append(c)
        for cyl in self.cylinders:
            c = _cylinder_contact(cyl, p, radius)
            if c is not None:
                out.append(c)
        return out

    def contact_force(self, point: Vec3, radius: float = 0.0) -> Vec3:
        """The summed contact force (N, world) on a probe sphere at `point`."""
        total = np.zeros(3)
        for c in self.contacts(point, radius):
            total += c.force
        return total


def _box_contact(b: Box, p: Vec3, radius: float) -> Contact | None:
    lo, hi = b.lo, b.hi
    closest = np.clip(p, lo, hi)
    delta = p - closest
    dist = float(np.linalg.norm(delta))
    if dist > 0.0:
        if dist >= radius:
            return None
        n = delta / dist
        depth = radius - dist
    else:
        # Centre inside the box: push out through the nearest face.
        to_lo, to_hi = p - lo, hi - p
        faces = np.concatenate([to_lo, to_hi])
        k = int(np.argmin(faces))
        n = np.zeros(3)
        n[k % 3] = -1.0 if k < 3 else 1.0
        depth = float(faces[k]) + radius
    return Contact(b.name, depth, n, b.stiffness_n_per_m * depth * n)


def _cylinder_contact(c: Cylinder, p: Vec3, radius: float) -> Contact | None:
    base = np.asarray(c.base, dtype=float)
    rel = p - base
    r_xy = float(np.hypot(rel[0], rel[1]))
    z = float(rel[2])
    # Distance outside along the radial and axial directions.
    out_r = r_xy - c.radius
    out_z = max(-z, z - c.height)
    if out_r > 0 and out_z > 0:
        dist = float(np.hypot(out_r, out_z))
        if dist >= radius:
            return None
        radial = np.array([rel[0], rel[1], 0.0]) / r_xy
        axial = np.array([0.0, 0.0, 1.0 if z > c.height else -1.0])
        n = (out_r * radial + out_z * axial) / dist
        depth = radius - dist
    elif out_r > 0 or out_z > 0:
        dist = out_r if out_r > 0 else out_z
        if dist >= radius:
            return None
        if out_r > 0:
            n = np.array([rel[0], rel[1], 0.0]) / r_xy
        else:
            n = np.array([0.0, 0.0, 1.0 if z > c.height else -1.0])
        depth = radius - dist
    else:
        # Inside: leave through the nearer of the side and the top/bottom.
        if -out_r < -out_z:
            n = (
                np.array([rel[0], rel[1], 0.0]) / r_xy
                if r_xy > 1e-12
                else np.array([1.0, 0.0, 0.0])
            )
            depth = -out_r + radius
        else:
            n = np.array([0.0, 0.0, 1.0 if z > 0.5 * c.height else -1.0])
            depth = -out_z + radius
    return Contact(c.name, depth, n, c.stiffness_n_per_m * depth * n)


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
