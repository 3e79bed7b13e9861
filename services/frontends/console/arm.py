"""The arm as the console draws it: the URDF visuals of whatever model the arm service
describes (`robot/arm/description`), placed by the joints of `robot/state`.

`arm_layout(desc)` turns a description into what is drawn (pure, tested without a page):
one `Group` per joint of the chain (0: the base, fixed in the world) placed at the world
pose of a URDF link that joint carries (`LinkPoses`), and the `Part`s fixed in it — each
visual of the URDF (`ArmModel.geometry`: meshes, boxes, spheres, cylinders) at its
placement in that link. When the visuals cannot be drawn here (a user's own model whose
meshes this checkout does not have, a shape we cannot draw, a URDF without visuals), the
parts are the arm's skeleton instead: thin cylinders between the joints' origins
(`Kinematics.link_origins`), each fixed in the link of the joint it starts from.
`ArmView` puts a layout on the page and moves it.

Why nested nodes per joint, with the visuals as their children, and not Pinocchio's
`ViserVisualizer`: every pose sent to the page is a viser setter (a numpy comparison, a
message, a wake-up of its event loop), measured at ≈ 130 µs on the 2-core test machine,
so an update costs what its number of setters says. The visuals on one joint move as one
rigid body, and a revolute joint turns its link about an origin fixed in its parent's: so
each visual's pose in its joint's link is sent once, when the arm is built, each joint's
node is a child of its parent joint's, and an update sends one orientation per joint that
turned (by more than REDRAW_ROT), from one `LinkPoses` pass. `ViserVisualizer.display`
sends a position and an orientation for every visual on every call (the FR3: 34 setters,
and hidden frame nodes for its 30 Pinocchio frames). Measured per update of a moving arm
(tests/frontends/console/measure_arm.py, load ≈ 5 on 2 cores): FR3 1.6 ms (7 setters)
against 4.9 ms, PUMA 560 1.7 against 4.2 ms, UR5e 1.2 against 2.0 ms; of which
`LinkPoses` ≈ 0.15 ms. The console draws only when q changes (app.py): an arm at rest
costs nothing.

Frames: world R_w (the description's base frame, z up), m. Not thread-safe: the GUI thread
only (one pin.Data).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal

import coal
import numpy as np
import pinocchio as pin
import viser
from numpy.typing import NDArray

from services.bus.errors import ConfigError
from services.bus.messages import ArmDescription
from services.control.arm.links import LinkPoses
from services.control.arm.model import ArmModel, model_from_description
from services.frontends.console.poses import MIN_SEGMENT_M, cylinder_pose
from services.geometry import V3, Quat, wxyz_from_R

Rgb = tuple[int, int, int]
LayoutKind = Literal["visuals", "skeleton"]

REDRAW_TOL = 5e-4
"""A joint's node is sent again only when its origin moved more than this (m) in its parent
link, or its rotation there by more than REDRAW_ROT (unit-free entries, ≈ rad): encoder
noise does not keep the browser re-rendering. The rotation's bound is the tighter because
the errors of the nested joints add up along the arm (7 × 1e-4 rad is 0.7 mm at 1 m)."""
REDRAW_ROT = 1e-4
SKELETON_RADIUS_M = 0.02
SKELETON_JOINT_RADIUS_M = 0.03
VISUAL_COLOR: Rgb = (214, 216, 222)
"""A visual whose URDF gives no material (the FR3's, the UR5e's) is drawn in this pale grey."""
SKELETON_COLOR: Rgb = (235, 140, 52)
SKELETON_JOINT_COLOR: Rgb = (60, 60, 70)
_NAME_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


class VisualsUnavailable(Exception):
    """The description's visuals cannot be drawn here (the reason is the message)."""


@dataclass(frozen=True, slots=True)
class Mesh:
    """A triangle mesh in its part's frame: vertices (V, 3) m (scaled), faces (F, 3)."""

    vertices: NDArray[np.float32]
    faces: NDArray[np.uint32]


@dataclass(frozen=True, slots=True)
class Box:
    size: V3
    """Edge lengths along the part's x, y, z (m), centred on its origin."""


@dataclass(frozen=True, slots=True)
class Sphere:
    radius: float


@dataclass(frozen=True, slots=True)
class Cylinder:
    """Along the part's z axis, centred on its origin (URDF's and viser's convention)."""

    radius: float
    length: float


Shape = Mesh | Box | Sphere | Cylinder


@dataclass(frozen=True, slots=True)
class Group:
    """What moves with joint `joint` of the chain (0: the base, fixed in the world): one node
    at the world pose of `link`, a URDF link that joint carries, drawn as a child of the
    node of joint `parent` (-1: of the arm's root)."""

    joint: int
    link: str
    parent: int


@dataclass(frozen=True, slots=True)
class Part:
    """One shape of the drawn arm: node `name` (unique within the arm) in the group of joint
    `group` (`ArmLayout.groups[group]`), at pose (`p`, `wxyz`) in that group's link frame.
    `visual`: the URDF geometry object it draws ("" for the skeleton's cylinders)."""

    name: str
    group: int
    shape: Shape
    p: V3
    wxyz: Quat
    rgb: Rgb
    opacity: float | None = None
    visual: str = ""


@dataclass(frozen=True, slots=True, eq=False)
class ArmLayout:
    """The arm of one description as drawn. `kind`: "visuals" (the URDF's) or "skeleton"
    (`why` says why the visuals are not drawn). `poses` computes the groups' link poses."""

    model: str
    n: int
    kind: LayoutKind
    groups: tuple[Group, ...]
    parts: tuple[Part, ...]
    poses: LinkPoses
    why: str = ""


def _vec3(v: Any) -> V3:
    a = np.asarray(v, dtype=float).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


def _quat(R: Any) -> Quat:
    q = wxyz_from_R(R)
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def _groups(pm: pin.Model, links: tuple[str, ...]) -> tuple[Group, ...]:
    """One group per joint of `pm` (the universe first), each at a link on that joint: the
    one Pinocchio places at the joint's own frame (the URDF joint's child) where there is
    one."""
    on: dict[int, list[tuple[bool, str]]] = {}
    known = set(links)
    for f in pm.frames:
        if f.type == pin.FrameType.BODY and f.name in known:
            on.setdefault(int(f.parentJoint), []).append((not f.placement.isIdentity(), f.name))
    out = []
    for j in range(pm.njoints):
        if j not in on:
            raise VisualsUnavailable(f"no link on joint {pm.names[j]!r}")
        out.append(Group(j, min(on[j])[1], int(pm.parents[j]) if j > 0 else -1))
    return tuple(out)


def _shape(geom: Any, name: str) -> Shape:
    if isinstance(geom, coal.BVHModelBase):
        faces = [list(geom.tri_indices(i)[k] for k in range(3)) for i in range(geom.num_tris)]
        return Mesh(
            np.asarray(geom.vertices(), dtype=np.float32),
            np.asarray(faces, dtype=np.uint32).reshape(-1, 3),
        )
    if isinstance(geom, coal.Box):
        return Box(_vec3(2.0 * np.asarray(geom.halfSide)))
    if isinstance(geom, coal.Sphere):
        return Sphere(float(geom.radius))
    if isinstance(geom, coal.Cylinder):
        return Cylinder(float(geom.radius), 2.0 * float(geom.halfLength))
    raise VisualsUnavailable(f"visual {name!r}: a {type(geom).__name__} is not drawn")


def _unique(name: str, taken: set[str]) -> str:
    base = _NAME_UNSAFE.sub("_", name) or "part"
    out, k = base, 1
    while out in taken:
        k += 1
        out = f"{base}_{k}"
    taken.add(out)
    return out


def visual_parts(model: ArmModel, pm: pin.Model, groups: tuple[Group, ...]) -> tuple[Part, ...]:
    """Every visual of the model's URDF as a part of its joint's group. Raises
    VisualsUnavailable when they cannot be drawn (a mesh not found, an unknown shape, none)."""
    try:
        geometry = model.geometry(pin.GeometryType.VISUAL)
    except ConfigError as e:
        raise VisualsUnavailable(e.reason) from None
    if not geometry.geometryObjects:
        raise VisualsUnavailable("the URDF has no visuals")
    group_frame = {g.joint: pm.frames[pm.getFrameId(g.link)] for g in groups}
    taken: set[str] = set()
    parts = []
    for obj in geometry.geometryObjects:
        j = int(obj.parentJoint)
        if j not in group_frame:
            raise VisualsUnavailable(f"visual {obj.name!r} on an unknown joint")
        # obj.placement is in its joint's frame; the group's node is at its link's.
        gMo = group_frame[j].placement.actInv(obj.placement)
        rgb, alpha = VISUAL_COLOR, 1.0
        if obj.overrideMaterial:  # the URDF gave it a material: its colour
            r, g, b, alpha = (min(1.0, max(0.0, float(c))) for c in obj.meshColor)
            rgb = (round(255 * r), round(255 * g), round(255 * b))
        parts.append(
            Part(
                name=_unique(obj.name, taken),
                group=j,
                shape=_shape(obj.geometry, obj.name),
                p=_vec3(gMo.translation),
                wxyz=_quat(gMo.rotation),
                rgb=rgb,
                opacity=alpha if alpha < 1.0 else None,
                visual=obj.name,
            )
        )
    return tuple(parts)


def skeleton_parts(
    model: ArmModel, poses: LinkPoses, groups: tuple[Group, ...]
) -> tuple[Part, ...]:
    """The arm's skeleton: a thin cylinder from each point of `link_origins` to the next
    (base, joint 1 … joint n, flange), fixed in the link of the joint it starts from, and a
    sphere at each joint's origin."""
    q0 = model.home
    origins = model.kinematics().link_origins(q0)
    at = poses.poses(q0)
    parts = []
    for k in range(len(origins) - 1):
        # Segment k ends at joint k + 1's origin (or the flange), fixed in joint k's body.
        M = at[groups[k].link]
        a, b = M.actInv(origins[k]), M.actInv(origins[k + 1])
        if k > 0:
            parts.append(
                Part(
                    f"joint{k}",
                    k,
                    Sphere(SKELETON_JOINT_RADIUS_M),
                    _vec3(a),
                    (1.0, 0.0, 0.0, 0.0),
                    SKELETON_JOINT_COLOR,
                )
            )
        if float(np.linalg.norm(b - a)) < MIN_SEGMENT_M:
            continue  # coincident origins (a spherical wrist's)
        centre, wxyz, length = cylinder_pose(a, b)
        parts.append(
            Part(
                f"link{k}",
                k,
                Cylinder(SKELETON_RADIUS_M, length),
                _vec3(centre),
                (float(wxyz[0]), float(wxyz[1]), float(wxyz[2]), float(wxyz[3])),
                SKELETON_COLOR,
            )
        )
    return tuple(parts)


def arm_layout(desc: ArmDescription) -> ArmLayout:
    """The arm `desc` describes, as drawn: its URDF's visuals, else its skeleton (see the
    module docstring). Raises ConfigError when the description's URDF does not build."""
    model = model_from_description(desc)
    pm = model.pin_model()
    poses = LinkPoses(model)
    try:
        groups = _groups(pm, poses.links)
    except VisualsUnavailable as e:
        raise ConfigError("arm.model", f"{desc.model}: {e}") from None
    try:
        return ArmLayout(
            desc.model, model.n, "visuals", groups, visual_parts(model, pm, groups), poses
        )
    except VisualsUnavailable as e:
        why = str(e)
    return ArmLayout(
        desc.model, model.n, "skeleton", groups, skeleton_parts(model, poses, groups), poses, why
    )


def _add_part(scene: viser.SceneApi, name: str, part: Part) -> Any:
    s = part.shape
    common: dict[str, Any] = {"position": part.p, "wxyz": part.wxyz}
    if part.opacity is not None:
        common["opacity"] = part.opacity
    if isinstance(s, Mesh):
        return scene.add_mesh_simple(name, s.vertices, s.faces, color=part.rgb, **common)
    if isinstance(s, Box):
        return scene.add_box(name, color=part.rgb, dimensions=s.size, **common)
    if isinstance(s, Sphere):
        return scene.add_icosphere(name, radius=s.radius, color=part.rgb, **common)
    return scene.add_cylinder(name, radius=s.radius, height=s.length, color=part.rgb, **common)


class ArmView:
    """A layout on the page under node `root`: the joints' nodes nested as the chain is
    (`{root}/j0/j1/…/j<k>`), each part a child of its joint's node. `draw(q)` moves them;
    `remove()` takes it all off the page.

    Each joint's node is placed in its parent's, so a revolute joint changes only its
    node's orientation (its origin is fixed in its parent link): an update sends one
    setter per joint that turned, where world poses would need two per joint downstream."""

    def __init__(self, scene: viser.SceneApi, layout: ArmLayout, root: str = "/arm/model") -> None:
        self.layout = layout
        self.root = root
        self._root = scene.add_frame(root, show_axes=False)
        paths: list[str] = []
        for g in layout.groups:
            paths.append(f"{paths[g.parent] if g.parent >= 0 else root}/j{g.joint}")
        self.paths = tuple(paths)
        """Each group's node name."""
        self.groups = [scene.add_frame(path, show_axes=False) for path in paths]
        self.parts = {
            p.name: _add_part(scene, f"{paths[p.group]}/{p.name}", p) for p in layout.parts
        }
        # What was last sent per group: its position (3) and rotation (9) in its parent's
        # frame; NaN: never sent.
        self._p = np.full((len(paths), 3), np.nan)
        self._R = np.full((len(paths), 9), np.nan)
        self.sent = 0
        """How many setters (a position or an orientation) were sent so far."""

    @property
    def n(self) -> int:
        return self.layout.n

    def draw(self, q: tuple[float, ...]) -> int:
        """Put the arm at joints q (n floats, rad): each joint's node whose pose in its
        parent's changed (position by more than REDRAW_TOL m, rotation entries by more than
        REDRAW_ROT) is sent the new one. Returns how many setters were sent."""
        at = self.layout.poses.poses(q)
        world = [at[g.link] for g in self.layout.groups]
        sent = 0
        for i, g in enumerate(self.layout.groups):
            local = world[i] if g.parent < 0 else world[g.parent].actInv(world[i])
            p, R = local.translation, local.rotation.reshape(9)
            h = self.groups[i]
            if not float(np.max(np.abs(p - self._p[i]))) <= REDRAW_TOL:  # NaN: never sent
                self._p[i] = p
                h.position = p
                sent += 1
            if not float(np.max(np.abs(R - self._R[i]))) <= REDRAW_ROT:
                self._R[i] = R
                h.wxyz = wxyz_from_R(R)
                sent += 1
        self.sent += sent
        return sent

    def remove(self) -> None:
        """Take the arm off the page (its nodes and every child)."""
        self._root.remove()


__all__ = [
    "ArmLayout",
    "ArmView",
    "Box",
    "Cylinder",
    "Group",
    "Mesh",
    "Part",
    "Sphere",
    "VisualsUnavailable",
    "arm_layout",
    "skeleton_parts",
    "visual_parts",
]
