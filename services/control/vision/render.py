"""Rendering of the simulated workcell for one stereo eye.

The workcell's fixtures (`services.world.workcell.scene`, `Scene.fixtures()`) do not move, so they
are ray-cast once per eye when the camera opens: shaded colour and a per-pixel depth image
(z along the optical axis, m), supersampled for smooth edges. The movable objects are drawn
over them where `workcell/state` puts them (`services.control.vision.objects`: each re-cast only
when it moved, only its region redone). Each frame then copies that background, darkens the tool's
drop shadow and draws the arm with OpenCV primitives (thick lines for links, discs for
joints and the tool marker) into a colour layer and a depth layer, far to near. Long links
are cut into short pieces so that each piece has nearly one depth; the arm shows wherever
its depth is nearer than the scene's, so the table hides the pedestal behind it while the
tool above the table stays visible. Everything behind the near plane is clipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.control.vision.camera import Image
from services.control.vision.objects import (
    ObjectLayer,
    ObjectPose,
    Region,
    composite,
    object_layer,
    objects_of_scene,
    region_of,
    union,
)
from services.control.vision.rig import PinholeCamera
from services.world.workcell.scene import Box, Cylinder, Scene

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

NEAR_M = 0.05
"""Near clipping distance (m, camera z): nothing closer is drawn."""
ROOM_HALF_M = 3.0
"""The floor is drawn as a square room of ±3 m around the base; beyond it, the wall."""
GRID_STEP_M = 0.25
GRID_HALF_WIDTH_M = 0.004
DEPTH_STEP_M = 0.02
"""Longest depth extent (m) of one drawn piece of a link: bounds the occlusion error."""
MAX_PIECES = 32
_PIECE_IDS = 255
"""Pieces are numbered in a uint8 layer: an arm's links (≤ 0.7 m each) give ~100 at most;
beyond 255 (a pose no arm can take) the farthest pieces are not drawn."""
SHIFT = 4
"""Sub-pixel bits for OpenCV drawing: coordinates are sent as integers × 2**SHIFT."""
_ONE = 1 << SHIFT

TOOL_MARKER_BGR = (255, 0, 255)
"""The tool point's marker: a flat, unshaded magenta no other part of the scene uses."""
TOOL_MARKER_RADIUS_M = 0.015
LINK_RADIUS_BASE_M = 0.09
LINK_RADIUS_TIP_M = 0.035
"""Drawn radius of the segments of `RobotPose.link_points`: from the base's down to the
flange's, in even steps."""
MAX_LINK_POINTS = 34
"""The most skeleton points an arm has (32 joints, its base and its flange)."""
LINK_BGR = ((175, 185, 195), (140, 150, 160))
JOINT_BGR = (70, 72, 80)
SHAFT_BGR = (110, 110, 110)
SHAFT_RADIUS_M = 0.012
FINGER_BGR = (45, 45, 45)
FINGER_RADIUS_M = 0.006
FINGER_MAX_GAP_M = 0.08

_LIGHT = np.array([0.5, -0.35, 1.0]) / np.linalg.norm([0.5, -0.35, 1.0])
_WALL_TOP_BGR = np.array([92.0, 78.0, 66.0])
_WALL_LOW_BGR = np.array([150.0, 140.0, 128.0])
_FLOOR_BGR = (np.array([178.0, 180.0, 176.0]), np.array([160.0, 164.0, 160.0]))
_GRID_BGR = np.array([105.0, 108.0, 108.0])
_CHUNK_RAYS = 1 << 17


@dataclass(frozen=True, slots=True, eq=False)
class RobotPose:
    """What is drawn of the arm, in world coordinates (m).

    `link_points` (k, 3): the arm's skeleton from its base to its flange
    (`Kinematics.link_origins`: the base link, each joint's frame origin, the flange).
    `tool_p` (3): the tool point. `tool_R` (3, 3): the tool frame's
    axes as columns in world. `grip`: 0 open … 1 closed, None when there is no gripper.
    """

    link_points: F64
    tool_p: F64
    tool_R: F64
    grip: float | None = None

    @classmethod
    def make(
        cls,
        link_points: ArrayLike,
        tool_p: ArrayLike,
        tool_R: ArrayLike,
        grip: float | None = None,
    ) -> RobotPose:
        """Validate and copy; raises ValueError on a wrong shape or a non-finite value."""
        pts = np.array(link_points, dtype=np.float64)
        p = np.array(tool_p, dtype=np.float64).reshape(-1)
        R = np.array(tool_R, dtype=np.float64)
        if R.shape == (9,):
            R = R.reshape(3, 3)
        if (
            pts.ndim != 2
            or pts.shape[1] != 3
            or not 2 <= pts.shape[0] <= MAX_LINK_POINTS
            or p.shape != (3,)
            or R.shape != (3, 3)
        ):
            raise ValueError(
                f"expected link_points (k, 3) with 2 ≤ k ≤ {MAX_LINK_POINTS}, tool_p (3,), "
                f"tool_R (3, 3); got {pts.shape}, {p.shape}, {R.shape}"
            )
        if not (np.isfinite(pts).all() and np.isfinite(p).all() and np.isfinite(R).all()):
            raise ValueError("robot pose has a non-finite value")
        if grip is not None and not (math.isfinite(grip) and 0.0 <= grip <= 1.0):
            raise ValueError(f"grip {grip!r} must be in 0…1")
        for a in (pts, p, R):
            a.setflags(write=False)
        return cls(pts, p, R, None if grip is None else float(grip))


def raycast_scene(scene: Scene, camera: PinholeCamera, supersample: int = 2) -> tuple[Image, F32]:
    """Ray-cast the static scene: (BGR image (H, W, 3) uint8, depth (H, W) float32 in m).

    Depth is z along the optical axis of the nearest surface, +inf where a pixel sees only
    the wall. With `supersample` s, s×s rays per pixel are averaged for colour and the
    nearest of them is kept for depth (so the arm is never shown through an object's edge).
    """
    s = int(supersample)
    rays = camera.pixel_rays(s).reshape(-1, 3)
    bgr = np.empty((rays.shape[0], 3))
    depth = np.empty(rays.shape[0])
    for i in range(0, rays.shape[0], _CHUNK_RAYS):
        bgr[i : i + _CHUNK_RAYS], depth[i : i + _CHUNK_RAYS] = _shade_rays(
            scene, camera.position_m, rays[i : i + _CHUNK_RAYS]
        )
    hs, ws = camera.height * s, camera.width * s
    hi = np.clip(bgr.reshape(hs, ws, 3), 0.0, 255.0).astype(np.uint8)
    img = hi
    if s > 1:
        small = cv2.resize(hi, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        img = np.asarray(small, dtype=np.uint8)
    d = depth.reshape(camera.height, s, camera.width, s).min(axis=(1, 3)).astype(np.float32)
    return np.ascontiguousarray(img), d


def _shade_rays(scene: Scene, origin: F64, d: F64) -> tuple[F64, F64]:
    n = d.shape[0]
    t_best = np.full(n, np.inf)
    normal = np.zeros((n, 3))
    albedo = np.zeros((n, 3))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = (scene.floor_z - origin[2]) / d[:, 2]
        p = origin + t[:, None] * d
        hit = (
            (t > NEAR_M)
            & np.isfinite(t)
            & (np.abs(p[:, 0]) <= ROOM_HALF_M)
            & (np.abs(p[:, 1]) <= ROOM_HALF_M)
        )
        t_best[hit] = t[hit]
        normal[hit] = (0.0, 0.0, 1.0)
        albedo[hit] = _floor_albedo(p[hit], t[hit])
        for box in scene.boxes:
            _hit_box(box, origin, d, t_best, normal, albedo)
        for cyl in scene.cylinders:
            _hit_cylinder(cyl, origin, d, t_best, normal, albedo)
    seen = np.isfinite(t_best)
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    lambert = np.clip(normal @ _LIGHT, 0.0, 1.0)
    facing = np.clip(-np.einsum("ij,ij->i", normal, dn), 0.0, 1.0)
    shade = 0.38 + 0.42 * lambert + 0.2 * facing
    out = albedo * shade[:, None]
    # The wall: darker towards the top of the view.
    up = np.clip(dn[:, 2] * 3.0 + 0.3, 0.0, 1.0)[:, None]
    wall = (1.0 - up) * _WALL_LOW_BGR + up * _WALL_TOP_BGR
    out[~seen] = wall[~seen]
    return out, t_best


def _floor_albedo(p: F64, t: F64) -> F64:
    tile = (np.floor(p[:, 0] / (2 * GRID_STEP_M)) + np.floor(p[:, 1] / (2 * GRID_STEP_M))) % 2
    col = np.where(tile[:, None] > 0, _FLOOR_BGR[0], _FLOOR_BGR[1])
    off = np.abs(p[:, :2] / GRID_STEP_M - np.round(p[:, :2] / GRID_STEP_M)) * GRID_STEP_M
    line = (off < GRID_HALF_WIDTH_M).any(axis=1)
    col[line] = _GRID_BGR
    # Fade the far floor into the wall so the grid does not alias into moiré.
    fog = np.clip((t - 3.0) / 3.0, 0.0, 1.0)[:, None]
    return (1.0 - fog) * col + fog * _WALL_LOW_BGR


def _hit_box(box: Box, o: F64, d: F64, t_best: F64, normal: F64, albedo: F64) -> None:
    # Slab test, one axis at a time on contiguous columns (reductions over the short axis
    # of an (N, 3) array are several times slower).
    lo, hi = box.lo, box.hi
    t_in = np.full(d.shape[0], -np.inf)
    t_out = np.full(d.shape[0], np.inf)
    axis = np.zeros(d.shape[0], np.int64)
    for k in range(3):
        dk = np.ascontiguousarray(d[:, k])
        t1 = (lo[k] - o[k]) / dk
        t2 = (hi[k] - o[k]) / dk
        near = np.minimum(t1, t2)
        axis[near > t_in] = k
        t_in = np.maximum(t_in, near)
        t_out = np.minimum(t_out, np.maximum(t1, t2))
    hit = (t_in <= t_out) & (t_in > NEAR_M) & (t_in < t_best)
    idx = np.nonzero(hit)[0]
    t_best[idx] = t_in[idx]
    nrm = np.zeros((idx.size, 3))
    nrm[np.arange(idx.size), axis[idx]] = -np.sign(d[idx, axis[idx]])
    normal[idx] = nrm
    albedo[idx] = box.color


def _hit_cylinder(c: Cylinder, o: F64, d: F64, t_best: F64, normal: F64, albedo: F64) -> None:
    bx, by, bz = c.base
    rx, ry = o[0] - bx, o[1] - by
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2.0 * (rx * d[:, 0] + ry * d[:, 1])
    cc = rx * rx + ry * ry - c.radius**2
    disc = b * b - 4.0 * a * cc
    t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
    z_side = o[2] + t_side * d[:, 2]
    side = (disc >= 0) & (a > 0) & (t_side > NEAR_M) & (z_side >= bz) & (z_side <= bz + c.height)
    side &= t_side < t_best
    idx = np.nonzero(side)[0]
    t_best[idx] = t_side[idx]
    px = o[0] + t_side[idx] * d[idx, 0] - bx
    py = o[1] + t_side[idx] * d[idx, 1] - by
    normal[idx] = np.stack([px, py, np.zeros_like(px)], axis=1) / c.radius
    albedo[idx] = c.color
    for z_cap, nz in ((bz + c.height, 1.0), (bz, -1.0)):
        t = (z_cap - o[2]) / d[:, 2]
        qx = o[0] + t * d[:, 0] - bx
        qy = o[1] + t * d[:, 1] - by
        cap = (t > NEAR_M) & (qx * qx + qy * qy <= c.radius**2) & (t < t_best)
        idx = np.nonzero(cap)[0]
        t_best[idx] = t[idx]
        normal[idx] = (0.0, 0.0, nz)
        albedo[idx] = np.asarray(c.color, dtype=float) * 1.08


@dataclass(frozen=True, slots=True)
class _Pieces:
    """What is drawn of the arm, far to near: thick segments from `p` to `q` (width
    `size_px`) and discs at `p` (`disc`; radius `size_px`, `q` = `p`), in pixels (float),
    each with its nearest depth (m) and colour. Arrays of N rows."""

    p: F64
    q: F64
    size_px: F64
    depth_m: F64
    bgr: NDArray[np.uint8]
    disc: NDArray[np.bool_]

    def __len__(self) -> int:
        return len(self.depth_m)

    @staticmethod
    def join(parts: list[_Pieces]) -> _Pieces:
        return _Pieces(
            *(np.concatenate([getattr(pc, f) for pc in parts]) for f in _Pieces.__slots__)
        )

    def take(self, idx: NDArray[np.intp] | slice) -> _Pieces:
        return _Pieces(*(getattr(self, f)[idx] for f in _Pieces.__slots__))


class EyeRenderer:
    """Renders one eye. Not thread-safe: one capture thread owns it."""

    def __init__(self, scene: Scene, camera: PinholeCamera, supersample: int = 2) -> None:
        self.camera = camera
        self.scene = scene
        self._ss = supersample
        # The fixtures never move: ray-cast once. The movable objects are layers over them,
        # each re-cast only when its pose changes (`set_objects`).
        self.static_background, self.static_depth = raycast_scene(
            scene.fixtures(), camera, supersample
        )
        self.background = self.static_background.copy()
        self.depth = self.static_depth.copy()
        self._layers: dict[str, ObjectLayer | None] = {}
        self._keys: dict[str, tuple[object, ...]] = {}
        self._objects: tuple[ObjectPose, ...] | None = None
        self._support = scene
        self.recasts = 0
        """Object layers ray-cast so far (a frame where nothing moved adds none)."""
        self.set_objects(objects_of_scene(scene))
        h, w = camera.height, camera.width
        self._ids = np.zeros((h, w), np.uint8)
        self._mask = np.zeros((h, w), np.uint8)
        self._depth_lut = np.full((1, 256), np.inf, np.float32)
        self._bgr_lut = np.zeros((1, 256, 3), np.uint8)

    def set_objects(self, objects: tuple[ObjectPose, ...]) -> None:
        """Draw the movable objects at these poses from now on. Only an object whose pose
        changed is ray-cast again; the composite is rebuilt only when one did."""
        if objects is self._objects:
            return
        self._objects = objects
        layers: dict[str, ObjectLayer | None] = {}
        keys: dict[str, tuple[object, ...]] = {}
        dirty: list[Region] = []
        for name in set(self._layers) - {o.name for o in objects}:
            gone = self._layers[name]
            if gone is not None:
                dirty.append(region_of(gone))
        for obj in objects:
            key = keys[obj.name] = obj.key()
            if self._keys.get(obj.name) == key:
                layers[obj.name] = self._layers[obj.name]
                continue
            old = self._layers.get(obj.name)
            new = layers[obj.name] = object_layer(obj, self.camera, self._ss)
            self.recasts += 1
            dirty += [region_of(ly) for ly in (old, new) if ly is not None]
        self._keys = keys
        self._layers = layers
        region = union(dirty)
        if region is None:
            return
        drawn = [ly for ly in layers.values() if ly is not None]
        # Only the region where something moved is redone (in place: `render` copies it).
        composite(
            self.static_background,
            self.static_depth,
            drawn,
            (self.background, self.depth),
            region,
        )
        fixtures = self.scene.fixtures()
        self._support = replace(fixtures, boxes=(*fixtures.boxes, *(o.aabb() for o in objects)))

    def render(
        self, robot: RobotPose | None, objects: tuple[ObjectPose, ...] | None = None
    ) -> Image:
        """The eye's image (H, W, 3) BGR uint8 of the scene with `robot` (None: no arm)
        and the movable objects at `objects` (None: where they were last drawn)."""
        if objects is not None:
            self.set_objects(objects)
        out = self.background.copy()
        if robot is None:
            return out
        self._shadow(out, robot)
        pieces = self._pieces(robot)
        roi = self._bbox(pieces)
        if roi is None:
            return out
        y0, y1, x0, x1 = roi
        # Painted far to near into one layer of piece numbers (0: no piece), each piece
        # drawn once; a pixel's colour and depth are its piece's, looked up by OpenCV.
        pieces = pieces.take(slice(-_PIECE_IDS, None))
        n = len(pieces)
        ids = self._ids
        ids[y0:y1, x0:x1] = 0
        self._depth_lut[0, 1 : n + 1] = pieces.depth_m
        self._bgr_lut[0, 1 : n + 1] = pieces.bgr
        p = np.rint(pieces.p * _ONE).astype(np.int64).tolist()
        q = np.rint(pieces.q * _ONE).astype(np.int64).tolist()
        width = np.clip(np.rint(pieces.size_px), 1, 32000).astype(np.int64).tolist()
        radius = np.maximum(1, np.rint(pieces.size_px * _ONE)).astype(np.int64).tolist()
        for i, disc in enumerate(pieces.disc.tolist()):
            if disc:
                cv2.circle(ids, p[i], radius[i], (i + 1,), -1, cv2.LINE_8, SHIFT)
            else:
                cv2.line(ids, p[i], q[i], (i + 1,), width[i], cv2.LINE_8, SHIFT)
        roi_ids = ids[y0:y1, x0:x1]
        arm_depth = cv2.LUT(roi_ids, self._depth_lut)
        shown = cv2.compare(arm_depth, self.depth[y0:y1, x0:x1], cv2.CMP_LT)
        colour = cv2.LUT(cv2.merge((roi_ids, roi_ids, roi_ids)), self._bgr_lut)
        cv2.copyTo(colour, shown, out[y0:y1, x0:x1])
        return out

    def _pieces(self, robot: RobotPose) -> _Pieces:
        cam = self.camera
        pts_c = cam.to_camera(robot.link_points)
        tool_c = cam.to_camera(robot.tool_p)
        k = len(pts_c)
        radii = np.linspace(LINK_RADIUS_BASE_M, LINK_RADIUS_TIP_M, k - 1).tolist()
        links = [(pts_c[i], pts_c[i + 1], r, LINK_BGR[i % 2]) for i, r in enumerate(radii)]
        tail = [(pts_c[-1], tool_c, SHAFT_RADIUS_M, SHAFT_BGR)]
        if robot.grip is not None:
            x_t = robot.tool_R[:, 0] @ cam.wRc
            z_t = robot.tool_R[:, 2] @ cam.wRc
            gap = 0.5 * FINGER_MAX_GAP_M * (1.0 - robot.grip) + FINGER_RADIUS_M
            tops = []
            for side in (-1.0, 1.0):
                base = tool_c + side * gap * x_t
                tops.append(base - 0.05 * z_t)
                tail.append((tops[-1], base + 0.012 * z_t, FINGER_RADIUS_M, FINGER_BGR))
            tail.append((tops[0], tops[1], FINGER_RADIUS_M, FINGER_BGR))
        joint_radii = 1.15 * np.array([radii[min(i, k - 2)] for i in range(1, k)])
        pieces = _Pieces.join(
            [
                self._segments(links),
                self._discs(pts_c[1:], joint_radii, JOINT_BGR),
                self._segments(tail),
            ]
        )
        pieces = pieces.take(np.argsort(-pieces.depth_m, kind="stable"))
        # The tool marker is a cursor the operator must always find: drawn over the arm's
        # own parts, yet still hidden by the scene in front of it (depth test at composite).
        marker = self._discs(tool_c[None], np.array([TOOL_MARKER_RADIUS_M]), TOOL_MARKER_BGR)
        return _Pieces.join([pieces, marker])

    def _segments(self, segments: list[tuple[F64, F64, float, tuple[int, int, int]]]) -> _Pieces:
        """Thick segments (camera frame, m) cut into pieces of at most DEPTH_STEP_M of depth
        (MAX_PIECES per segment), clipped at the near plane and to the image."""
        a = np.array([sg[0] for sg in segments], dtype=np.float64)
        b = np.array([sg[1] for sg in segments], dtype=np.float64)
        radius = np.array([sg[2] for sg in segments])
        bgr = np.array([sg[3] for sg in segments], dtype=np.uint8)
        keep = (a[:, 2] >= NEAR_M) | (b[:, 2] >= NEAR_M)
        a, b, radius, bgr = a[keep], b[keep], radius[keep], bgr[keep]
        za, zb = a[:, 2], b[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            clip_a = za < NEAR_M
            clip_b = (zb < NEAR_M) & ~clip_a
            a_near = a + ((NEAR_M - za) / (zb - za))[:, None] * (b - a)
            b_near = b + ((NEAR_M - zb) / (za - zb))[:, None] * (a - b)
        a = np.where(clip_a[:, None], a_near, a)
        b = np.where(clip_b[:, None], b_near, b)
        n = np.clip(np.ceil(np.abs(b[:, 2] - a[:, 2]) / DEPTH_STEP_M), 1, MAX_PIECES)
        n = n.astype(np.int64)
        # The n + 1 points of each segment, as np.linspace(0, 1, n + 1) places them.
        seg = np.repeat(np.arange(len(n)), n + 1)
        first = np.cumsum(n + 1) - (n + 1)
        k = np.arange(len(seg)) - first[seg]
        t = k * (1.0 / n[seg])
        t[first + n] = 1.0
        pts = a[seg] + t[:, None] * (b - a)[seg]
        uv = self.camera.project_camera(pts)
        # Piece j of a segment joins its points j and j + 1.
        start = np.ones(len(seg), bool)
        start[first + n] = False
        i0 = np.nonzero(start)[0]
        owner = seg[i0]
        z_mid = 0.5 * (pts[i0, 2] + pts[i0 + 1, 2])
        width = 2.0 * self.camera.intrinsics.fx * radius[owner] / z_mid
        p, q, ok = self._clip(uv[i0], uv[i0 + 1], width)
        return _Pieces(
            p[ok],
            q[ok],
            width[ok],
            (z_mid - radius[owner])[ok],
            bgr[owner][ok],
            np.zeros(int(ok.sum()), bool),
        )

    def _discs(self, centres: F64, radii_m: F64, bgr: tuple[int, int, int]) -> _Pieces:
        """Flat discs facing the camera at `centres` (camera frame, m), those in front of
        the near plane and on screen."""
        z = centres[:, 2]
        front = z - radii_m > NEAR_M
        centres, radii_m, z = centres[front], radii_m[front], z[front]
        uv = self.camera.project_camera(centres)
        rad = self.camera.intrinsics.fx * radii_m / z
        w, h = self.camera.width, self.camera.height
        u, v = uv[:, 0], uv[:, 1]
        on = (
            (-rad <= u)
            & (u <= w - 1 + rad)
            & (-rad <= v)
            & (v <= h - 1 + rad)
            & (rad < 4 * max(w, h))
        )
        n = int(on.sum())
        return _Pieces(
            uv[on],
            uv[on],
            rad[on],
            (z - radii_m)[on],
            np.tile(np.array(bgr, np.uint8), (n, 1)),
            np.ones(n, bool),
        )

    def _clip(self, p: F64, q: F64, width_px: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Liang–Barsky clip of each segment p → q (N, 2) to the image grown by its line's
        half width, so that OpenCV only ever sees bounded coordinates: the clipped ends and
        which segments are left."""
        m = 0.5 * width_px + 1.0
        lo = -m
        hi = (self.camera.width - 1 + m, self.camera.height - 1 + m)
        t0 = np.zeros(len(p))
        t1 = np.ones(len(p))
        ok = np.ones(len(p), bool)
        d = q - p
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis in (0, 1):
                for num, den in (
                    (p[:, axis] - lo, -d[:, axis]),
                    (hi[axis] - p[:, axis], d[:, axis]),
                ):
                    ok &= ~((den == 0.0) & (num < 0.0))
                    t = num / den
                    t0 = np.where(den < 0.0, np.maximum(t0, t), t0)
                    t1 = np.where(den > 0.0, np.minimum(t1, t), t1)
                    ok &= ~(t0 > t1)
        return p + t0[:, None] * d, p + t1[:, None] * d, ok

    def _bbox(self, pieces: _Pieces) -> tuple[int, int, int, int] | None:
        if not len(pieces):
            return None
        r = np.where(pieces.disc, pieces.size_px, pieces.size_px / 2.0)[:, None]
        ends = np.concatenate([pieces.p - r, pieces.p + r, pieces.q - r, pieces.q + r])
        w, h = self.camera.width, self.camera.height
        x0, x1 = max(0, int(ends[:, 0].min()) - 2), min(w, int(ends[:, 0].max()) + 3)
        y0, y1 = max(0, int(ends[:, 1].min()) - 2), min(h, int(ends[:, 1].max()) + 3)
        if x0 >= x1 or y0 >= y1:
            return None
        return y0, y1, x0, x1

    def _shadow(self, out: Image, robot: RobotPose) -> None:
        """Darken the tool point's drop shadow on the surface right below it: a depth cue
        that tells the operator how high above the table the tool is."""
        x, y, z = (float(v) for v in robot.tool_p)
        ground = _support_z(self._support, x, y, z)
        if ground is None or z <= ground:
            return
        height = z - ground
        radius = 0.02 + 0.05 * min(height, 0.5)
        ang = np.linspace(0.0, 2.0 * np.pi, 20, endpoint=False)
        ring = np.stack(
            [x + radius * np.cos(ang), y + radius * np.sin(ang), np.full_like(ang, ground)], 1
        )
        ring_c = self.camera.to_camera(ring)
        if (ring_c[:, 2] < NEAR_M).any():
            return
        uv = self.camera.project_camera(ring_c)
        w, h = self.camera.width, self.camera.height
        x0, y0 = max(0, int(uv[:, 0].min())), max(0, int(uv[:, 1].min()))
        x1, y1 = min(w, int(uv[:, 0].max()) + 2), min(h, int(uv[:, 1].max()) + 2)
        if x0 >= x1 or y0 >= y1:
            return
        mask = self._mask
        mask[y0:y1, x0:x1] = 0
        poly = np.round(uv * _ONE).astype(np.int32)
        cv2.fillConvexPoly(mask, poly, (1,), cv2.LINE_8, SHIFT)
        # Only where the visible surface is the one the shadow lies on, not something nearer.
        z_near = float(ring_c[:, 2].min()) - 0.03
        hit = (mask[y0:y1, x0:x1] > 0) & (self.depth[y0:y1, x0:x1] >= z_near)
        dark = 1.0 - float(np.clip(0.5 - 0.6 * height, 0.15, 0.5))
        region = out[y0:y1, x0:x1]
        region[hit] = (region[hit] * dark).astype(np.uint8)


def _support_z(scene: Scene, x: float, y: float, z: float) -> float | None:
    """The height (m) of the highest scene surface below the point (x, y, z), or None
    when it is outside the room."""
    if abs(x) > ROOM_HALF_M or abs(y) > ROOM_HALF_M:
        return None
    best = scene.floor_z
    for b in scene.boxes:
        lo, hi = b.lo, b.hi
        if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and best < b.top_z <= z:
            best = b.top_z
    for c in scene.cylinders:
        top = c.base[2] + c.height
        if math.hypot(x - c.base[0], y - c.base[1]) <= c.radius and best < top <= z:
            best = top
    return best


class StereoRenderer:
    """Both eyes of a rig, over one scene."""

    def __init__(
        self, scene: Scene, left: PinholeCamera, right: PinholeCamera, ss: int = 2
    ) -> None:
        self.left = EyeRenderer(scene, left, ss)
        self.right = EyeRenderer(scene, right, ss)

    def render(
        self, robot: RobotPose | None, objects: tuple[ObjectPose, ...] | None = None
    ) -> tuple[Image, Image]:
        return self.left.render(robot, objects), self.right.render(robot, objects)
