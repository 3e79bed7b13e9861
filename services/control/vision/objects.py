"""The workcell's movable objects as the renderer draws them: posed boxes and bottles.

The scene description (`services.world.workcell.scene`) is the one the workcell simulates: its
fixtures (the table) never move and are ray-cast once per eye; its movable objects (blocks,
the bottle) are drawn where `workcell/state` says they are, turned by their rotation (a
tilted bottle, a toppled block), with the bottle's liquid up to its level. Each object is
ray-cast only over the pixels its bounding box covers, and only when its pose changed
(`ObjectLayer` is the cached result), so a frame where nothing moved costs nothing more.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.control.vision.rig import PinholeCamera
from services.world.workcell.messages import M3_PER_ML, ObjectView
from services.world.workcell.scene import Box, Scene

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

NEAR_M = 0.05
MAX_SIZE_M = 2.0
"""An object larger than this along any axis is not drawn (a bad message, not a block)."""
MAX_DIST_M = 10.0
"""Nor one farther than this from the base."""
DEFAULT_BGR = (160, 160, 160)
LIQUID_BGR = (40, 215, 240)
"""The liquid, seen through the bottle's wall: an amber no other object uses."""
SPILL_BGR = (30, 170, 200)
"""Spilled liquid on a surface: the liquid's amber, darker."""
_LIGHT = np.array([0.5, -0.35, 1.0]) / np.linalg.norm([0.5, -0.35, 1.0])


@dataclass(frozen=True, slots=True, eq=False)
class ObjectPose:
    """One movable object to draw: `kind` "box" (p = centre) or "cylinder" (p = base centre,
    axis = R's z), rotation `R` (world←object), full `size` (m; a cylinder's is
    (2r, 2r, height)), BGR `color`, and for a bottle the liquid's height along its axis
    (m above the base, 0 for none)."""

    name: str
    kind: str
    p: F64
    R: F64
    size: F64
    color: tuple[int, int, int]
    liquid_m: float = 0.0

    def key(self) -> tuple[object, ...]:
        """Equal keys draw the same pixels."""
        return (self.p.tobytes(), self.R.tobytes(), *self.look())

    def look(self) -> tuple[object, ...]:
        """What it is, pose aside: its key without `p` and `R`."""
        return (self.kind, self.size.tobytes(), self.color, round(self.liquid_m, 4))

    def corners(self) -> F64:
        """The 8 corners of its bounding box (world, m)."""
        half = 0.5 * self.size
        lo = np.array([-half[0], -half[1], -half[2] if self.kind == "box" else 0.0])
        hi = np.array([half[0], half[1], half[2] if self.kind == "box" else self.size[2]])
        c = np.array(
            [[(hi if i & k else lo)[j] for j, k in enumerate((1, 2, 4))] for i in range(8)]
        )
        return self.p + c @ self.R.T

    def aabb(self) -> Box:
        """Its axis-aligned bounding box (for the tool's shadow)."""
        c = self.corners()
        lo, hi = c.min(axis=0), c.max(axis=0)
        centre = 0.5 * (lo + hi)
        size = hi - lo
        return Box(
            self.name,
            (float(centre[0]), float(centre[1]), float(centre[2])),
            (float(size[0]), float(size[1]), float(size[2])),
        )


def _color_of(scene: Scene, name: str) -> tuple[int, int, int]:
    try:
        return scene.solid(name).color
    except KeyError:
        return DEFAULT_BGR


def objects_of_scene(scene: Scene) -> tuple[ObjectPose, ...]:
    """The movable objects where the scene description puts them (before any state)."""
    out = []
    for s in scene.movables():
        if isinstance(s, Box):
            out.append(
                ObjectPose(
                    s.name,
                    "box",
                    np.array(s.center, float),
                    np.eye(3),
                    np.array(s.size, float),
                    s.color,
                )
            )
        else:
            out.append(
                ObjectPose(
                    s.name,
                    "cylinder",
                    np.array(s.base, float),
                    np.eye(3),
                    np.array([2 * s.radius, 2 * s.radius, s.height]),
                    s.color,
                    s.liquid_height_m,
                )
            )
    return tuple(out)


def objects_of_state(scene: Scene, views: Mapping[str, ObjectView]) -> tuple[ObjectPose, ...]:
    """The objects of a decoded `workcell/state` (`objects_of`), coloured by the scene.

    Raises ValueError naming the object when a size or position is out of bounds (not
    positive, larger than MAX_SIZE_M, farther than MAX_DIST_M) or a rotation is not one.
    """
    out = []
    for name, v in views.items():
        size = np.asarray(v.size, float)
        if not (np.all(size > 0.0) and np.all(size <= MAX_SIZE_M)):
            raise ValueError(f"objects.{name}.size must be within 0 … {MAX_SIZE_M} m")
        if not float(np.linalg.norm(v.p)) <= MAX_DIST_M:
            raise ValueError(f"objects.{name}.p is farther than {MAX_DIST_M} m")
        R = np.asarray(v.R, float)
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
            raise ValueError(f"objects.{name}.R is not a rotation")
        liquid = 0.0
        if v.kind == "cylinder" and v.liquid_ml is not None:
            area = math.pi * (0.5 * size[0]) ** 2
            liquid = min(max(v.liquid_ml, 0.0) * M3_PER_ML / area, float(size[2]))
        out.append(
            ObjectPose(
                name, v.kind, np.asarray(v.p, float), R, size, _color_of(scene, name), liquid
            )
        )
    return tuple(out)


STILL_P_M = 1e-4
"""An object drawn once stays drawn where it was until its position has moved more than
this (0.1 mm: a twentieth of a pixel at 1 m at 640×480 and 60°) …"""
STILL_R = 5e-4
"""… or an entry of its rotation more than this (about 0.5 mrad: 0.1 mm at 0.2 m). MuJoCo's
resting objects are never quite still (the bottle rocks by ~7e-5 of a rotation entry, a
block settles by micrometres): drawn at each new bit of their pose, every object was
ray-cast again in both eyes at every pair during teleoperation, a third of vision's CPU."""


def steady(
    drawn: tuple[ObjectPose, ...] | None, objects: tuple[ObjectPose, ...]
) -> tuple[ObjectPose, ...]:
    """`objects`, where each that has not moved beyond STILL_P_M / STILL_R from how it is
    `drawn` (the same name and `look`: kind, size, colour, liquid level) is the drawn one (so
    its key is unchanged and it is not ray-cast again). All of `drawn` when none moved."""
    if not drawn:
        return objects
    before = {o.name: o for o in drawn}
    out = []
    for o in objects:
        d = before.get(o.name)
        still = (
            d is not None
            and d.look() == o.look()
            and float(np.max(np.abs(d.p - o.p))) <= STILL_P_M
            and float(np.max(np.abs(d.R - o.R))) <= STILL_R
        )
        out.append(d if still and d is not None else o)
    kept = tuple(out)
    if len(kept) == len(drawn) and all(a is b for a, b in zip(kept, drawn, strict=True)):
        return drawn
    return kept


SPILL_THICKNESS_M = 0.003
"""A puddle is drawn as a disc this thick would hold the spilled volume …"""
MAX_PUDDLE_RADIUS_M = 0.15
"""… up to this radius."""
PUDDLE_MERGE_M = 0.04
"""A drop landing this close to a puddle's centre joins it."""
MAX_PUDDLES = 8


@dataclass(slots=True)
class Puddle:
    x: float
    y: float
    z: float
    volume_ml: float


class Spills:
    """Where spilled liquid lies, from the growth of each bottle's `spilled_ml`.

    `workcell/state` says how much has spilled, not where it fell: each increase is taken
    to fall from the lowest point of the bottle's rim at that moment straight down onto the
    highest fixture below it (the table, else the floor), and joins the puddle within
    PUDDLE_MERGE_M of it (or starts one). A decrease (the workcell was reset) dries them.
    Not thread-safe: one owner.
    """

    def __init__(self, scene: Scene) -> None:
        self._fixtures = scene.fixtures()
        self._spilled: dict[str, float] = {}
        self.puddles: list[Puddle] = []

    def update(self, views: Mapping[str, ObjectView]) -> None:
        for name, v in views.items():
            if v.kind != "cylinder" or v.spilled_ml is None:
                continue
            before = self._spilled.get(name, 0.0)
            now = max(0.0, float(v.spilled_ml))
            self._spilled[name] = now
            if now < before - 1e-9:
                self.puddles.clear()
            elif now > before:
                self._drop(self._rim_low(v), now - before)

    @staticmethod
    def _rim_low(v: ObjectView) -> F64:
        axis = v.R[:, 2]
        top = v.p + axis * float(v.size[2])
        down = np.array([0.0, 0.0, -1.0]) - axis * float(-axis[2])
        n = float(np.linalg.norm(down))
        return top + (0.5 * float(v.size[0]) * down / n if n > 1e-9 else 0.0)

    def _drop(self, at: F64, volume_ml: float) -> None:
        x, y = float(at[0]), float(at[1])
        z = self._fixtures.floor_z
        for b in self._fixtures.boxes:
            lo, hi = b.lo, b.hi
            if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and z < b.top_z <= at[2] + 1e-6:
                z = b.top_z
        for pd in self.puddles:
            if abs(pd.z - z) < 1e-6 and math.hypot(pd.x - x, pd.y - y) <= PUDDLE_MERGE_M:
                w = volume_ml / (pd.volume_ml + volume_ml)
                pd.x, pd.y = pd.x + w * (x - pd.x), pd.y + w * (y - pd.y)
                pd.volume_ml += volume_ml
                return
        if len(self.puddles) >= MAX_PUDDLES:
            nearest = min(self.puddles, key=lambda pd: math.hypot(pd.x - x, pd.y - y))
            nearest.volume_ml += volume_ml
            return
        self.puddles.append(Puddle(x, y, z, volume_ml))

    def objects(self) -> tuple[ObjectPose, ...]:
        """The puddles as flat discs to draw."""
        out = []
        for i, pd in enumerate(self.puddles):
            r = math.sqrt(pd.volume_ml * M3_PER_ML / (math.pi * SPILL_THICKNESS_M))
            r = min(max(r, 0.005), MAX_PUDDLE_RADIUS_M)
            out.append(
                ObjectPose(
                    f"spill{i}",
                    "cylinder",
                    np.array([pd.x, pd.y, pd.z]),
                    np.eye(3),
                    np.array([2 * r, 2 * r, 0.002]),
                    SPILL_BGR,
                )
            )
        return tuple(out)


@dataclass(frozen=True, slots=True, eq=False)
class ObjectLayer:
    """An object ray-cast over its pixel box `y0:y1, x0:x1`: colour, depth (camera z, m)
    and `mask` (True where the object covers the pixel)."""

    key: tuple[object, ...]
    y0: int
    y1: int
    x0: int
    x1: int
    bgr: NDArray[np.uint8]
    depth: F32
    mask: NDArray[np.bool_]


def object_layer(
    obj: ObjectPose, camera: PinholeCamera, supersample: int = 2
) -> ObjectLayer | None:
    """Ray-cast `obj` over the pixels its bounding box projects to (None: off screen)."""
    corners_c = camera.to_camera(obj.corners())
    w, h = camera.width, camera.height
    if (corners_c[:, 2] < NEAR_M).all():
        return None
    if (corners_c[:, 2] < NEAR_M).any():
        x0, y0, x1, y1 = 0, 0, w, h
    else:
        uv = camera.project_camera(corners_c)
        x0, y0 = (
            max(0, (math.floor(uv[:, 0].min())) - 1),
            max(0, (math.floor(uv[:, 1].min())) - 1),
        )
        x1, y1 = (
            min(w, (math.ceil(uv[:, 0].max())) + 2),
            min(h, (math.ceil(uv[:, 1].max())) + 2),
        )
    if x0 >= x1 or y0 >= y1:
        return None
    s = int(supersample)
    k = camera.intrinsics
    u = (np.arange(x0 * s, x1 * s) + 0.5) / s - 0.5
    v = (np.arange(y0 * s, y1 * s) + 0.5) / s - 0.5
    # Each ray's camera-frame direction is (x, y, 1); in the world, x·c0 + y·c1 + c2 with
    # c_i the columns of wRc (no 3-D matmul: several times cheaper on a few thousand rays).
    xs = np.tile((u - k.cx) / k.fx, v.size)
    ys = np.repeat((v - k.cy) / k.fy, u.size)
    c0, c1, c2 = camera.wRc[:, 0], camera.wRc[:, 1], camera.wRc[:, 2]
    d = xs[:, None] * c0 + ys[:, None] * c1 + c2
    t, normal, liquid = _hit(obj, camera.position_m, d)
    hit = np.isfinite(t)
    if not hit.any():
        return None
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    lambert = np.clip(normal @ _LIGHT, 0.0, 1.0)
    facing = np.clip(-np.einsum("ij,ij->i", normal, dn), 0.0, 1.0)
    shade = (0.38 + 0.42 * lambert + 0.2 * facing)[:, None]
    albedo = np.where(liquid[:, None], np.array(LIQUID_BGR, float), np.array(obj.color, float))
    col = np.clip(albedo * shade, 0.0, 255.0)
    hs, ws = (y1 - y0), (x1 - x0)
    col = col.reshape(hs, s, ws, s, 3)
    hit4 = hit.reshape(hs, s, ws, s)
    n_hit = hit4.sum(axis=(1, 3))
    summed = np.where(hit4[..., None], col, 0.0).sum(axis=(1, 3))
    bgr = (summed / np.maximum(n_hit, 1)[..., None]).astype(np.uint8)
    depth = t.reshape(hs, s, ws, s).min(axis=(1, 3)).astype(np.float32)
    mask = n_hit * 2 >= s * s
    return ObjectLayer(obj.key(), y0, y1, x0, x1, bgr, depth, mask)


def _hit(obj: ObjectPose, origin: F64, d: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Nearest hit (t = camera z, +inf for a miss), world normal, and whether the hit point
    shows the liquid, for rays `origin + t·d` (world)."""
    o = (origin - obj.p) @ obj.R  # object frame
    dl = d @ obj.R
    n = d.shape[0]
    t_best = np.full(n, np.inf)
    nrm = np.zeros((n, 3))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if obj.kind == "box":
            half = 0.5 * obj.size
            t_in = np.full(n, -np.inf)
            t_out = np.full(n, np.inf)
            axis = np.zeros(n, np.int64)
            for k in range(3):
                t1 = (-half[k] - o[k]) / dl[:, k]
                t2 = (half[k] - o[k]) / dl[:, k]
                near = np.minimum(t1, t2)
                axis[near > t_in] = k
                t_in = np.maximum(t_in, near)
                t_out = np.minimum(t_out, np.maximum(t1, t2))
            hit = (t_in <= t_out) & (t_in > NEAR_M) & np.isfinite(t_in)
            idx = np.nonzero(hit)[0]
            t_best[idx] = t_in[idx]
            nrm[idx, axis[idx]] = -np.sign(dl[idx, axis[idx]])
        else:
            r, height = 0.5 * obj.size[0], obj.size[2]
            a = dl[:, 0] ** 2 + dl[:, 1] ** 2
            b = 2.0 * (o[0] * dl[:, 0] + o[1] * dl[:, 1])
            c = o[0] ** 2 + o[1] ** 2 - r * r
            disc = b * b - 4.0 * a * c
            ts = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
            zs = o[2] + ts * dl[:, 2]
            side = (disc >= 0) & (a > 0) & (ts > NEAR_M) & (zs >= 0.0) & (zs <= height)
            idx = np.nonzero(side)[0]
            t_best[idx] = ts[idx]
            px = o[0] + ts[idx] * dl[idx, 0]
            py = o[1] + ts[idx] * dl[idx, 1]
            nrm[idx] = np.stack([px, py, np.zeros_like(px)], axis=1) / r
            for z_cap, nz in ((height, 1.0), (0.0, -1.0)):
                t = (z_cap - o[2]) / dl[:, 2]
                qx = o[0] + t * dl[:, 0]
                qy = o[1] + t * dl[:, 1]
                cap = (t > NEAR_M) & (qx * qx + qy * qy <= r * r) & (t < t_best)
                idx = np.nonzero(cap)[0]
                t_best[idx] = t[idx]
                nrm[idx] = (0.0, 0.0, nz)
    world_n = nrm @ obj.R.T
    liquid = np.zeros(n, bool)
    if obj.kind == "cylinder" and obj.liquid_m > 0.0:
        # The surface is level in the world: through the axis at the liquid's height.
        level_z = float((obj.p + obj.R @ np.array([0.0, 0.0, obj.liquid_m]))[2])
        seen = np.isfinite(t_best)
        z_hit = origin[2] + np.where(seen, t_best, 0.0) * d[:, 2]
        liquid = seen & (z_hit <= level_z)
    return t_best, world_n, liquid


Region = tuple[int, int, int, int]
"""y0, y1, x0, x1 (pixels, half-open)."""


def region_of(ly: ObjectLayer) -> Region:
    return (ly.y0, ly.y1, ly.x0, ly.x1)


def union(regions: list[Region]) -> Region | None:
    if not regions:
        return None
    return (
        min(r[0] for r in regions),
        max(r[1] for r in regions),
        min(r[2] for r in regions),
        max(r[3] for r in regions),
    )


def composite(
    background: NDArray[np.uint8],
    depth: F32,
    layers: list[ObjectLayer],
    out: tuple[NDArray[np.uint8], F32] | None = None,
    region: Region | None = None,
) -> tuple[NDArray[np.uint8], F32]:
    """(background, depth) with every layer drawn where it is nearer. With `out` (images
    of the same size) and `region`, only that region of `out` is redone, in place: the
    static background restored there, then the layers that overlap it drawn over it."""
    if out is None or region is None:
        img, dep = background.copy(), depth.copy()
        region = (0, background.shape[0], 0, background.shape[1])
    else:
        img, dep = out
        y0, y1, x0, x1 = region
        img[y0:y1, x0:x1] = background[y0:y1, x0:x1]
        dep[y0:y1, x0:x1] = depth[y0:y1, x0:x1]
    ry0, ry1, rx0, rx1 = region
    for ly in layers:
        y0, y1 = max(ly.y0, ry0), min(ly.y1, ry1)
        x0, x1 = max(ly.x0, rx0), min(ly.x1, rx1)
        if y0 >= y1 or x0 >= x1:
            continue
        sl = (slice(y0 - ly.y0, y1 - ly.y0), slice(x0 - ly.x0, x1 - ly.x0))
        roi_d = dep[y0:y1, x0:x1]
        shown = ly.mask[sl] & (ly.depth[sl] < roi_d)
        img[y0:y1, x0:x1][shown] = ly.bgr[sl][shown]
        roi_d[shown] = ly.depth[sl][shown]
    return img, dep
