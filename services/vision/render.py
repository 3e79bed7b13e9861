"""Rendering of the simulated workcell for one stereo eye.

The workcell (`services.workcell.scene`) does not move, so it is ray-cast once per eye when
the camera opens: shaded colour and a per-pixel depth image (z along the optical axis, m),
supersampled for smooth edges. Each frame then copies that background, darkens the tool's
drop shadow and draws the arm with OpenCV primitives (thick lines for links, discs for
joints and the tool marker) into a colour layer and a depth layer, far to near. Long links
are cut into short pieces so that each piece has nearly one depth; the arm shows wherever
its depth is nearer than the scene's, so the table hides the pedestal behind it while the
tool above the table stays visible. Everything behind the near plane is clipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.vision.camera import Image
from services.vision.rig import PinholeCamera
from services.workcell.scene import Box, Cylinder, Scene

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
SHIFT = 4
"""Sub-pixel bits for OpenCV drawing: coordinates are sent as integers × 2**SHIFT."""
_ONE = 1 << SHIFT

TOOL_MARKER_BGR = (255, 0, 255)
"""The tool point's marker: a flat, unshaded magenta no other part of the scene uses."""
TOOL_MARKER_RADIUS_M = 0.015
LINK_RADII_M = (0.09, 0.075, 0.06, 0.05, 0.04, 0.035)
"""Drawn radius of the segment from point i to point i+1 of `RobotPose.link_points`."""
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

    `link_points` (7, 3): the base, then the origins of DH frames 1…6 (the last one is the
    flange / wrist centre). `tool_p` (3): the tool point. `tool_R` (3, 3): the tool frame's
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
        if pts.shape != (7, 3) or p.shape != (3,) or R.shape != (3, 3):
            raise ValueError(
                f"expected link_points (7, 3), tool_p (3,), tool_R (3, 3); got "
                f"{pts.shape}, {p.shape}, {R.shape}"
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
class _Piece:
    """One drawable: a thick segment (p, q) or a disc (p, radius). Pixel coords, float."""

    depth_m: float
    p: tuple[float, float]
    q: tuple[float, float] | None
    size_px: float
    bgr: tuple[int, int, int]


class EyeRenderer:
    """Renders one eye. Not thread-safe: one capture thread owns it."""

    def __init__(self, scene: Scene, camera: PinholeCamera, supersample: int = 2) -> None:
        self.camera = camera
        self.scene = scene
        self.background, self.depth = raycast_scene(scene, camera, supersample)
        h, w = camera.height, camera.width
        self._layer = np.zeros((h, w, 3), np.uint8)
        self._layer_depth = np.full((h, w), np.inf, np.float32)
        self._mask = np.zeros((h, w), np.uint8)

    def render(self, robot: RobotPose | None) -> Image:
        """The eye's image (H, W, 3) BGR uint8 of the scene with `robot` (None: no arm)."""
        out = self.background.copy()
        if robot is None:
            return out
        self._shadow(out, robot)
        pieces = self._pieces(robot)
        roi = self._bbox(pieces)
        if roi is None:
            return out
        y0, y1, x0, x1 = roi
        layer, layer_depth = self._layer, self._layer_depth
        layer[y0:y1, x0:x1] = 0
        layer_depth[y0:y1, x0:x1] = np.inf
        for pc in pieces:
            _draw(layer, pc, pc.bgr)
            _draw(layer_depth, pc, (pc.depth_m,))
        shown = layer_depth[y0:y1, x0:x1] < self.depth[y0:y1, x0:x1]
        out[y0:y1, x0:x1][shown] = layer[y0:y1, x0:x1][shown]
        return out

    def _pieces(self, robot: RobotPose) -> list[_Piece]:
        cam = self.camera
        fx = cam.intrinsics.fx
        pts_c = cam.to_camera(robot.link_points)
        pieces: list[_Piece] = []
        for i, r in enumerate(LINK_RADII_M):
            self._segment(pieces, pts_c[i], pts_c[i + 1], r, LINK_BGR[i % 2])
        for i in range(1, 7):
            self._disc(pieces, pts_c[i], 1.15 * LINK_RADII_M[min(i, 5)], JOINT_BGR)
        tool_c = cam.to_camera(robot.tool_p)
        self._segment(pieces, pts_c[6], tool_c, SHAFT_RADIUS_M, SHAFT_BGR)
        if robot.grip is not None:
            x_t = robot.tool_R[:, 0] @ cam.wRc
            z_t = robot.tool_R[:, 2] @ cam.wRc
            gap = 0.5 * FINGER_MAX_GAP_M * (1.0 - robot.grip) + FINGER_RADIUS_M
            tops = []
            for side in (-1.0, 1.0):
                base = tool_c + side * gap * x_t
                tops.append(base - 0.05 * z_t)
                self._segment(pieces, tops[-1], base + 0.012 * z_t, FINGER_RADIUS_M, FINGER_BGR)
            self._segment(pieces, tops[0], tops[1], FINGER_RADIUS_M, FINGER_BGR)
        pieces.sort(key=lambda pc: -pc.depth_m)
        # The tool marker is a cursor the operator must always find: drawn over the arm's
        # own parts, yet still hidden by the scene in front of it (depth test at composite).
        z = float(tool_c[2])
        if z - TOOL_MARKER_RADIUS_M > NEAR_M:
            uv = cam.project_camera(tool_c)[0]
            rad = fx * TOOL_MARKER_RADIUS_M / z
            if self._on_screen(float(uv[0]), float(uv[1]), rad):
                pieces.append(
                    _Piece(z - TOOL_MARKER_RADIUS_M, (uv[0], uv[1]), None, rad, TOOL_MARKER_BGR)
                )
        return pieces

    def _segment(
        self, out: list[_Piece], a: F64, b: F64, radius_m: float, bgr: tuple[int, int, int]
    ) -> None:
        za, zb = float(a[2]), float(b[2])
        if za < NEAR_M and zb < NEAR_M:
            return
        if za < NEAR_M:
            a = a + (NEAR_M - za) / (zb - za) * (b - a)
        elif zb < NEAR_M:
            b = b + (NEAR_M - zb) / (za - zb) * (a - b)
        n = int(min(MAX_PIECES, max(1, math.ceil(abs(float(b[2] - a[2])) / DEPTH_STEP_M))))
        pts = a + np.linspace(0.0, 1.0, n + 1)[:, None] * (b - a)
        uv = self.camera.project_camera(pts)
        fx = self.camera.intrinsics.fx
        for k in range(n):
            z_mid = 0.5 * float(pts[k, 2] + pts[k + 1, 2])
            width = 2.0 * fx * radius_m / z_mid
            clipped = self._clip(uv[k], uv[k + 1], width)
            if clipped is not None:
                out.append(_Piece(z_mid - radius_m, clipped[0], clipped[1], width, bgr))

    def _disc(self, out: list[_Piece], c: F64, radius_m: float, bgr: tuple[int, int, int]) -> None:
        z = float(c[2])
        if z - radius_m <= NEAR_M:
            return
        uv = self.camera.project_camera(c)[0]
        rad = self.camera.intrinsics.fx * radius_m / z
        if self._on_screen(float(uv[0]), float(uv[1]), rad):
            out.append(_Piece(z - radius_m, (float(uv[0]), float(uv[1])), None, rad, bgr))

    def _on_screen(self, u: float, v: float, rad: float) -> bool:
        w, h = self.camera.width, self.camera.height
        return -rad <= u <= w - 1 + rad and -rad <= v <= h - 1 + rad and rad < 4 * max(w, h)

    def _clip(
        self, p: F64, q: F64, width_px: float
    ) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """Liang–Barsky clip of the segment to the image grown by the line's half width, so
        that OpenCV only ever sees bounded coordinates."""
        m = 0.5 * width_px + 1.0
        lo = (-m, -m)
        hi = (self.camera.width - 1 + m, self.camera.height - 1 + m)
        t0, t1 = 0.0, 1.0
        d = (float(q[0] - p[0]), float(q[1] - p[1]))
        for axis in (0, 1):
            for num, den in ((float(p[axis]) - lo[axis], -d[axis]), (hi[axis] - p[axis], d[axis])):
                if den == 0.0:
                    if num < 0.0:
                        return None
                    continue
                t = num / den
                if den < 0.0:
                    t0 = max(t0, t)
                else:
                    t1 = min(t1, t)
                if t0 > t1:
                    return None
        pu, pv = float(p[0]), float(p[1])
        return (pu + t0 * d[0], pv + t0 * d[1]), (pu + t1 * d[0], pv + t1 * d[1])

    def _bbox(self, pieces: list[_Piece]) -> tuple[int, int, int, int] | None:
        if not pieces:
            return None
        us: list[float] = []
        vs: list[float] = []
        for pc in pieces:
            r = pc.size_px / 2.0 if pc.q is not None else pc.size_px
            for pt in (pc.p, pc.q) if pc.q is not None else (pc.p,):
                us += (pt[0] - r, pt[0] + r)
                vs += (pt[1] - r, pt[1] + r)
        w, h = self.camera.width, self.camera.height
        x0, x1 = max(0, int(min(us)) - 2), min(w, int(max(us)) + 3)
        y0, y1 = max(0, int(min(vs)) - 2), min(h, int(max(vs)) + 3)
        if x0 >= x1 or y0 >= y1:
            return None
        return y0, y1, x0, x1

    def _shadow(self, out: Image, robot: RobotPose) -> None:
        """Darken the tool point's drop shadow on the surface right below it: a depth cue
        that tells the operator how high above the table the tool is."""
        x, y, z = (float(v) for v in robot.tool_p)
        ground = _support_z(self.scene, x, y, z)
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


def _draw(img: Image | F32, pc: _Piece, color: tuple[float, ...]) -> None:
    p = (round(pc.p[0] * _ONE), round(pc.p[1] * _ONE))
    if pc.q is None:
        r = max(1, round(pc.size_px * _ONE))
        cv2.circle(img, p, r, color, -1, cv2.LINE_8, SHIFT)
    else:
        q = (round(pc.q[0] * _ONE), round(pc.q[1] * _ONE))
        thickness = int(min(32000, max(1, round(pc.size_px))))
        cv2.line(img, p, q, color, thickness, cv2.LINE_8, SHIFT)


class StereoRenderer:
    """Both eyes of a rig, over one scene."""

    def __init__(
        self, scene: Scene, left: PinholeCamera, right: PinholeCamera, ss: int = 2
    ) -> None:
        self.left = EyeRenderer(scene, left, ss)
        self.right = EyeRenderer(scene, right, ss)

    def render(self, robot: RobotPose | None) -> tuple[Image, Image]:
        return self.left.render(robot), self.right.render(robot)
