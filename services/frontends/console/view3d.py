"""The console's 3D scene: the arm (whatever robot/arm/description says it is), its tool
frame, tool and fingers, the target, the force arrow and the workcell's objects, liquids
and puddles, redrawn only when they move."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np
import viser

from services.bus.errors import ConfigError, ProtocolError
from services.bus.keys import ARM_DESCRIPTION
from services.bus.messages import ArmDescription, RobotState, mat3
from services.bus.node import Node
from services.control.vision.objects import LIQUID_BGR, SPILL_BGR, Spills
from services.frontends.console.arm import ArmView, arm_layout
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.mirror import BusMirror
from services.frontends.console.poses import MIN_SEGMENT_M, cylinder_pose, force_arrow
from services.frontends.console.view import NO_ARM, ArmShown
from services.frontends.console.workcell import (
    FINGER_SIZE_M,
    PUDDLE_THICKNESS_M,
    ObjectNode,
    finger_offsets,
    object_nodes,
    puddle_nodes,
)
from services.geometry import wxyz_from_R
from services.world.workcell.messages import WORKCELL_STATE, objects_of
from services.world.workcell.scene import Scene, default_scene

log = logging.getLogger("telerobot.console")


TOOL_RADIUS_M = 0.008
"""The tool (flange → tool point, eMt) is drawn as a thin cylinder of this radius."""
FORCE_ARROW_MAX_M = 0.4
FORCE_MIN_N = 0.5
"""Below this the force arrow is hidden (sensor noise, not a contact)."""
REDRAW_TOL = 5e-4
"""A drawn pose or arrow is sent again only when it moved more than this (m, or unit-free
for rotation entries): sub-millimetre noise does not keep the browser re-rendering."""
GIZMO_LINE_WIDTH = 4.0
"""The gizmo's handles are drawn this thick (screen px; viser's default is 2.5): a first
drag grabs them rather than the camera."""
_TOOL_COLOR = (235, 140, 52)
_FORCE_COLOR = (220, 30, 200)
_TARGET_COLOR = (255, 140, 0)
_FINGER_COLOR = (70, 70, 80)
FINGER_HOLDING_COLOR = (30, 160, 90)
BOTTLE_OPACITY = 0.45
"""A bottle is drawn translucent, so that its liquid shows."""


def _rgb(bgr: tuple[int, int, int]) -> tuple[int, int, int]:
    return (bgr[2], bgr[1], bgr[0])


class View3D:
    """Builds and draws the 3D view (a mixin of `Console`; GUI thread only)."""

    # What the scene uses of the rest of `Console` (set in `Console.__init__`).
    node: Node
    config: ConsoleConfig
    mirror: BusMirror
    server: viser.ViserServer
    scene: Scene | None
    """The workcell's scene ([scene] file), None for the standard one."""
    _drawn: dict[str, np.ndarray]

    if TYPE_CHECKING:

        def _on_gizmo(self, ev: Any) -> None: ...

    # --- the page: scene ----------------------------------------------------------------
    def _build_scene(self) -> None:
        sc = self.server.scene
        sc.add_grid("/floor", width=3.0, height=3.0, cell_size=0.25, section_size=1.0)
        # The same description the workcell, force and vision simulations use; the movable
        # objects are moved to their `workcell/state` poses while a browser watches.
        self.workcell = self.scene if self.scene is not None else default_scene()
        self._objects: dict[str, Any] = {}
        self._liquids: dict[str, Any] = {}
        self._spills = Spills(self.workcell)  # where the video puts spilled liquid
        self._puddles: list[Any] = []
        self._workcell_seq = -1
        self.workcell_drawn = 0
        for b in self.workcell.boxes:
            self._objects[b.name] = sc.add_box(
                f"/workcell/{b.name}",
                color=_rgb(b.color),
                dimensions=b.size,
                position=b.center,
            )
        for c in self.workcell.cylinders:
            liquid = c.liquid_height_m > 0.0
            self._objects[c.name] = sc.add_cylinder(
                f"/workcell/{c.name}",
                radius=c.radius,
                height=c.height,
                color=_rgb(c.color),
                opacity=BOTTLE_OPACITY if liquid else None,
                position=(c.base[0], c.base[1], c.base[2] + 0.5 * c.height),
            )
            if liquid:
                self._liquids[c.name] = sc.add_cylinder(
                    f"/workcell/{c.name}/liquid",
                    radius=0.85 * c.radius,
                    height=c.liquid_height_m,
                    color=_rgb(LIQUID_BGR),
                    position=(0.0, 0.0, -0.5 * c.height + 0.5 * c.liquid_height_m),
                )
        # The arm is built when its description arrives (`_sync_arm`), not before.
        self.arm: ArmView | None = None
        self.arm_shown: ArmShown = NO_ARM
        self.arm_description: ArmDescription | None = None
        """The newest robot/arm/description the scene has followed."""
        self._arm_source: tuple[str, str] | None = None
        self._arm_warned: set[tuple[str, str]] = set()
        self.arm_builds = 0
        self._tool_frame = sc.add_frame(
            "/arm/tool_frame", axes_length=0.1, axes_radius=0.006, visible=False
        )
        # The tool, from the flange to the tool point: a child of the tool frame, so it
        # moves with it and is re-sent only when eMt changes (set_tool).
        self._tool = sc.add_cylinder(
            "/arm/tool_frame/tool",
            radius=TOOL_RADIUS_M,
            height=1.0,
            color=_TOOL_COLOR,
            visible=False,
        )
        self._fingers = [
            sc.add_box(
                f"/arm/tool_frame/finger_{side}",
                color=_FINGER_COLOR,
                dimensions=FINGER_SIZE_M,
                visible=False,
            )
            for side in ("l", "r")
        ]
        self._finger_color = _FINGER_COLOR
        self._target = sc.add_frame(
            "/target",
            axes_length=0.07,
            axes_radius=0.004,
            origin_radius=0.015,
            origin_color=_TARGET_COLOR,
            visible=False,
        )
        self._force = sc.add_arrows(
            "/force",
            points=np.zeros((1, 2, 3), dtype=np.float32),
            colors=_FORCE_COLOR,
            shaft_radius=0.008,
            head_radius=0.02,
            head_length=0.04,
            visible=False,
        )
        self._workspace_box: Any = None
        self.gizmo = sc.add_transform_controls(
            "/master/hand",
            scale=self.config.gizmo_scale_m,
            line_width=GIZMO_LINE_WIDTH,
            depth_test=False,
            visible=False,
        )
        self.gizmo.on_update(self._on_gizmo)

    def _sync_arm(self) -> bool:
        """Follow robot/arm/description: build the arm anew when its model or URDF changed
        (a restarted arm with another model), keep it when only the tool did (set_tool).
        True when the arm was rebuilt (or taken off the page)."""
        desc = self.mirror.description.latest
        if desc is None or desc is self.arm_description:
            return False
        self.arm_description = desc
        source = (desc.model, desc.urdf)
        if source == self._arm_source:
            return False
        self._arm_source = source
        if self.arm is not None:
            self.arm.remove()
            self.arm = None
        self.arm_builds += 1
        self.arm_shown = ArmShown("none", desc.model, f"{desc.model}: being built")
        try:
            layout = arm_layout(desc)
        except ConfigError as e:
            self.node.report_rejected(ARM_DESCRIPTION.key, e.reason)
            self.arm_shown = ArmShown(
                "invalid", desc.model, f"{desc.model}: not drawn ({e.reason})"
            )
            log.error("the description of arm %r cannot be drawn: %s", desc.model, e.reason)
            return True
        self.arm = ArmView(self.server.scene, layout)
        if layout.kind == "visuals":
            text = f"{desc.model}, {layout.n} joints: {len(layout.parts)} URDF visuals"
        else:
            text = f"{desc.model}, {layout.n} joints: skeleton (its visuals: {layout.why})"
            if source not in self._arm_warned:
                self._arm_warned.add(source)
                log.warning(
                    "arm %r: its visuals cannot be drawn here (%s): drawing its skeleton",
                    desc.model,
                    layout.why,
                )
        self.arm_shown = ArmShown(layout.kind, desc.model, text)
        log.info("drawing arm %r: %s", desc.model, text)
        return True

    def _draw_arm(self, st: RobotState) -> None:
        """The arm at st.q (when it is the described arm's: a state of another, from a
        restart under way, is not drawn), the tool frame at the state's tool pose, and the
        tool from the flange to the tool point (both as the arm computed them: never
        recomputed from q)."""
        if self.arm is not None and len(st.q) == self.arm.n:
            self.arm.draw(st.q)
        tool_R = mat3(st.tool_R)
        self._tool_frame.position = np.asarray(st.tool_p)
        self._tool_frame.wxyz = wxyz_from_R(tool_R)
        if not self._tool_frame.visible:
            self._tool_frame.visible = True
        # The flange in the tool frame, −R_etᵀ·p_et: constant until the tool changes.
        flange_t = tool_R.T @ (np.asarray(st.flange_p) - np.asarray(st.tool_p))
        if self._changed("tool", flange_t, REDRAW_TOL):
            length = float(np.linalg.norm(flange_t))
            if length >= MIN_SEGMENT_M:
                centre, wxyz, _ = cylinder_pose(np.zeros(3), flange_t)
                self._tool.position, self._tool.wxyz, self._tool.height = centre, wxyz, length
            self._tool.visible = length >= MIN_SEGMENT_M

    def _draw_workcell(self, st: RobotState | None) -> None:
        """Move the objects to the newest `workcell/state` (once per new message), and
        open or close the gripper's fingers as robot/state's `grip` says."""
        fingers = finger_offsets(st.grip if st is not None else None)
        wc = self.mirror.workcell()
        holding = wc is not None and bool(wc.held)
        for k, h in enumerate(self._fingers):
            if fingers is None:
                if h.visible:
                    h.visible = False
                continue
            if self._changed(f"finger{k}", np.asarray(fingers[k]), REDRAW_TOL):
                h.position = fingers[k]
            if not h.visible:
                h.visible = True
        color = FINGER_HOLDING_COLOR if holding else _FINGER_COLOR
        if fingers is not None and color != self._finger_color:
            self._finger_color = color
            for h in self._fingers:
                h.color = color
        if wc is None or wc.seq == self._workcell_seq:
            return
        self._workcell_seq = wc.seq
        try:
            views = objects_of(wc)
            nodes = object_nodes(self.workcell, views)
        except ProtocolError as e:
            self.node.report_rejected(WORKCELL_STATE.key, str(e))
            return
        for node in nodes.values():
            self._draw_object(node)
        self._spills.update(views)
        self._draw_puddles()
        self.workcell_drawn += 1

    def _draw_puddles(self) -> None:
        puddles = puddle_nodes(self._spills)
        sc = self.server.scene
        for i, pd in enumerate(puddles):
            if i == len(self._puddles):
                self._puddles.append(
                    sc.add_cylinder(
                        f"/workcell/spill{i}",
                        radius=pd.radius_m,
                        height=PUDDLE_THICKNESS_M,
                        color=_rgb(SPILL_BGR),
                        position=pd.position,
                    )
                )
                self._changed(f"puddle{i}", np.array([pd.radius_m, *pd.position]), 0.0)
                continue
            h = self._puddles[i]
            if self._changed(f"puddle{i}", np.array([pd.radius_m, *pd.position]), REDRAW_TOL):
                h.radius = pd.radius_m
                h.position = pd.position
            if not h.visible:
                h.visible = True
        for h in self._puddles[len(puddles) :]:
            if h.visible:
                h.visible = False  # dried: the workcell was reset

    def _draw_object(self, node: ObjectNode) -> None:
        h = self._objects[node.name]
        pose = np.array([*node.position, *node.wxyz])
        if self._changed(f"object/{node.name}", pose, REDRAW_TOL):
            h.position = node.position
            h.wxyz = node.wxyz
        liquid = self._liquids.get(node.name)
        if liquid is None:
            return
        level = np.array([node.liquid_height_m])
        if self._changed(f"liquid/{node.name}", level, REDRAW_TOL):
            if node.liquid_height_m > 0.0:
                liquid.height = node.liquid_height_m
                liquid.position = (0.0, 0.0, node.liquid_z_m)
            liquid.visible = node.liquid_height_m > 0.0

    def _draw_target(self) -> None:
        target = self.mirror.target()
        if target is None:
            if self._target.visible:
                self._target.visible = False
            return
        p, R, _active = target
        pose = np.concatenate([p, R.ravel()])
        if self._changed("target", pose, REDRAW_TOL):
            self._target.position = p
            self._target.wxyz = wxyz_from_R(R)
        if not self._target.visible:
            self._target.visible = True

    def _draw_force(self, st: RobotState | None) -> None:
        sample = self.mirror.latest_force()
        if st is None or sample is None or float(np.linalg.norm(sample.f)) < FORCE_MIN_N:
            if self._force.visible:
                self._force.visible = False
            return
        pts = force_arrow(
            st.tool_p, mat3(st.tool_R), sample.f, self.config.force_arrow_m_per_n, FORCE_ARROW_MAX_M
        )
        if self._changed("force", pts.ravel(), REDRAW_TOL):
            self._force.points = pts.astype(np.float32)[None]
        if not self._force.visible:
            self._force.visible = True

    def _changed(self, key: str, value: np.ndarray, tol: float) -> bool:
        """True (and remembered) if `value` differs from what was last drawn by more than
        `tol`: the page renders on demand, so an unchanged scene costs the browser nothing."""
        last = self._drawn.get(key)
        if last is not None and last.shape == value.shape and np.max(np.abs(last - value)) <= tol:
            return False
        self._drawn[key] = value.copy()
        return True
