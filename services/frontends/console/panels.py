"""The console's controls and panels: the buttons, the status, events and services
panels, the force and passivity plots and the video window."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import viser

from services.bus.node import Node
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.hand import HandLink
from services.frontends.console.link import link_html
from services.frontends.console.mirror import BusMirror, History
from services.frontends.console.poses import box_edges
from services.frontends.console.tdpa import TdpaView
from services.frontends.console.video import VIEW_MODES, FrameGate, Image, ViewMode, compose, decode
from services.frontends.console.view import (
    VIDEO_STYLE,
    ArmShown,
    MasterView,
    alive_html,
    estop_latched,
    events_html,
    loading_html,
    loading_items,
    passivity_html,
    status_html,
)

log = logging.getLogger("telerobot.console")


ROBOT_ACTIONS = ("Connect", "Initialize", "Home", "Stop")
ROBOT_HINT = (
    "Connect: arm connect. Initialize: connect if needed, then calibrate (ready follows). "
    "Home: clutch the master, move home. Stop: hold teleoperation, cancel a task."
)
_WORKSPACE_COLOR = (30, 160, 90)

_FORCE_SERIES = (
    viser.uplot.Series(label="t (s)"),
    viser.uplot.Series(label="Fx", stroke="#d62728", width=1.5),
    viser.uplot.Series(label="Fy", stroke="#2ca02c", width=1.5),
    viser.uplot.Series(label="Fz", stroke="#1f77b4", width=1.5),
)
_TDPA_SERIES = (
    viser.uplot.Series(label="t (s)"),
    viser.uplot.Series(label="reservoir master", stroke="#1f77b4", width=1.5),
    viser.uplot.Series(label="reservoir slave", stroke="#ff7f0e", width=1.5),
    viser.uplot.Series(label="dissipated master", stroke="#1f77b4", width=1.0, dash=(4, 3)),
    viser.uplot.Series(label="dissipated slave", stroke="#ff7f0e", width=1.0, dash=(4, 3)),
)
_MOMENT_SERIES = (
    viser.uplot.Series(label="t (s)"),
    viser.uplot.Series(label="Cx", stroke="#d62728", width=1.5),
    viser.uplot.Series(label="Cy", stroke="#2ca02c", width=1.5),
    viser.uplot.Series(label="Cz", stroke="#1f77b4", width=1.5),
)


class Panels:
    """Builds the controls and refreshes the panels (a mixin of `Console`)."""

    # What the panels use of the rest of `Console` (set in `Console.__init__`).
    node: Node
    config: ConsoleConfig
    mirror: BusMirror
    hand: HandLink
    server: viser.ViserServer
    last_action: str
    video_errors: int
    frames_shown: int
    loaded: bool
    arm_shown: ArmShown
    _gate: FrameGate
    _view_mode: ViewMode
    _panels: dict[str, str]
    _workspace: tuple[tuple[float, ...], tuple[float, ...]] | None
    _workspace_box: Any
    _estop_shown: bool | None
    _plot_empty: bool
    _tdpa_empty: bool
    _tdpa_state: str
    _scales_loaded: bool

    if TYPE_CHECKING:

        def _on_robot(self, action: str) -> None: ...
        def _on_frame(self, ev: Any) -> None: ...
        def _on_scale(self, ev: Any) -> None: ...
        def _set_view(self, mode: str) -> None: ...
        def _submit(self, name: str, fn: Callable[[], str]) -> None: ...
        def _now(self, name: str, fn: Callable[[], str]) -> None: ...
        def _do_estop(self) -> str: ...
        def _do_reset(self) -> str: ...

    # --- the page: controls -------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        self._loading_html = gui.add_html(loading_html(("robot state", "supervisor")))
        with gui.add_folder("Robot"):
            b_estop = gui.add_button("E-STOP", color="red", hint="latch the emergency stop")
            self._status_html = gui.add_html(
                status_html(
                    None, None, None, MasterView(self.config.master_id, "waiting", None, None), ""
                )
            )
            robot = gui.add_button_group("Arm", options=ROBOT_ACTIONS, hint=ROBOT_HINT)
            b_reset = gui.add_button(
                "Reset e-stop",
                color="orange",
                hint="clear the latch (the decision server's reset)",
            )
        self._b_estop, self._b_reset = b_estop, b_reset
        with gui.add_folder("Teleoperation"):
            # Any: viser's `value` setter is invisible to mypy (an asymmetric property).
            self._frame: Any = gui.add_dropdown(
                "Frame", options=("world", "tool"), initial_value="world"
            )
            self._scale_t: Any = gui.add_slider(
                "Scale transl.", min=0.05, max=1.0, step=0.05, initial_value=1.0
            )
            self._scale_r: Any = gui.add_slider(
                "Scale rotation", min=0.05, max=1.0, step=0.05, initial_value=1.0
            )
            self._shift = gui.add_checkbox(
                "Master-shift",
                initial_value=False,
                hint="the clutch: while ticked the gizmo moves alone; untick to engage from there",
            )
            b_snap = gui.add_button(
                "Snap master to tool",
                hint="clutch and put the gizmo on the tool; moving it engages from there",
            )
        # The video has a window of its own over the 3D view (bottom left), not the
        # control panel's 300 px: the image fills the window's width, keeping its aspect,
        # and the window can be resized, moved, docked or minimized.
        self._video_panel = gui.add_panel()
        with self._video_panel.add_tab("Video"):
            self._view = gui.add_dropdown("View", options=VIEW_MODES, initial_value=self._view_mode)
            gui.add_html(VIDEO_STYLE)
            self._image = gui.add_image(
                np.full((120, 320, 3), 40, dtype=np.uint8), label=None, format="jpeg"
            )
        self._video_panel.float(x=15, y=-15, width=self.config.video_panel_width_px)
        with gui.add_folder("Force at the tool (tool frame)"):
            t0 = np.array([-self.config.plot_window_s, 0.0])
            z = np.zeros(2)
            # The x axis is the window itself, whatever the data: one stray time cannot
            # stretch it to minutes and squeeze the live data into a point.
            window = (-self.config.plot_window_s, 0.0)
            scales = {"x": viser.uplot.Scale(time=False, auto=False, range=window)}
            axes = (viser.uplot.Axis(), viser.uplot.Axis(size=56))
            self._f_plot = gui.add_uplot(
                (t0, z, z, z),
                _FORCE_SERIES,
                title="force (N)",
                scales=scales,
                axes=axes,
                aspect=2.2,
            )
            self._c_plot = gui.add_uplot(
                (t0, z, z, z),
                _MOMENT_SERIES,
                title="moment (N·m)",
                scales=scales,
                axes=axes,
                aspect=2.2,
            )
        with gui.add_folder("Passivity (TDPA)"):
            self._tdpa_html = gui.add_html(passivity_html(TdpaView(())))
            self._tdpa_plot = gui.add_uplot(
                (t0, z, z, z, z),
                _TDPA_SERIES,
                title="energy (J)",
                scales=scales,
                axes=axes,
                aspect=2.2,
                visible=False,
            )
        with gui.add_folder("Link"):
            self._link_html = gui.add_html(link_html(self.mirror.link.view(None)))
        with gui.add_folder("Events"):
            self._events_html = gui.add_html(events_html(()))
        with gui.add_folder("Services"):
            self._alive_html = gui.add_html(alive_html(()))

        b_estop.on_click(lambda _: self._now("estop", self._do_estop))
        robot.on_click(lambda ev: self._on_robot(str(ev.target.value)))
        b_reset.on_click(lambda _: self._submit("reset", self._do_reset))
        b_snap.on_click(lambda _: self.hand.resync())
        self._frame.on_update(self._on_frame)
        self._scale_t.on_update(self._on_scale)
        self._scale_r.on_update(self._on_scale)
        self._shift.on_update(lambda ev: self.hand.set_shift(bool(ev.target.value)))
        self._view.on_update(lambda ev: self._set_view(str(ev.target.value)))

    def _set_html(self, key: str, handle: Any, content: str) -> None:
        if self._panels.get(key) != content:
            self._panels[key] = content
            handle.content = content

    def _html_status(self) -> str:
        decision, error, _master = self.mirror.status()
        mview = MasterView(
            self.config.master_id,
            self.hand.state,
            self.mirror.master(self.config.master_id),
            self.hand.error,
        )
        return status_html(
            self.mirror.state.latest, decision, error, mview, self.last_action, self.arm_shown
        )

    def _update_panels(self) -> None:
        self._set_html("status", self._status_html, self._html_status())
        self._set_html("alive", self._alive_html, alive_html(self.node.alive.names()))
        self._set_html("events", self._events_html, events_html(self.mirror.events()))
        link = self.mirror.link.view(self.mirror.vision.latest)
        self._set_html("link", self._link_html, link_html(link))
        tdpa = self.mirror.passivity()
        self._set_html("tdpa", self._tdpa_html, passivity_html(tdpa))
        if tdpa.state != self._tdpa_state:
            self._tdpa_state = tdpa.state
            self._tdpa_plot.visible = tdpa.state != "none"
        decision, error, master = self.mirror.status()
        self._show_estop(estop_latched(decision) if decision is not None else None)
        self._show_loading(decision is not None or error not in (None, "no reply yet"))
        if decision is not None:
            settings = decision.get("settings") or {}
            lo, hi = settings.get("workspace_min"), settings.get("workspace_max")
            if lo is not None and hi is not None and (tuple(lo), tuple(hi)) != self._workspace:
                self._workspace = (tuple(lo), tuple(hi))
                if self._workspace_box is not None:
                    self._workspace_box.remove()
                self._workspace_box = self.server.scene.add_line_segments(
                    "/workspace",
                    points=box_edges(lo, hi),
                    colors=_WORKSPACE_COLOR,
                    thickness=2.0,
                    thickness_units="screen",
                )
        if master is not None and not self._scales_loaded:
            # Show the master's own settings once; from then on the sliders drive it.
            self._scales_loaded = True
            self._scale_t.value = float(master.get("scale_t", 1.0))
            self._scale_r.value = float(master.get("scale_r", 1.0))
            if master.get("frame") in ("world", "tool"):
                self._frame.value = master["frame"]

    def _show_estop(self, latched: bool | None) -> None:
        """The E-STOP button says when the latch is set, and Reset is offered (enabled) while
        it is, or while the decision server's state is unknown."""
        if latched == self._estop_shown:
            return
        self._estop_shown = latched
        self._b_estop.label = "E-STOP — LATCHED" if latched else "E-STOP"
        self._b_estop.hint = (
            "the e-stop is latched: Reset clears it" if latched else "latch the emergency stop"
        )
        self._b_reset.disabled = latched is False
        self._b_reset.color = "red" if latched else "orange"

    def _show_loading(self, decision_replied: bool) -> None:
        """The loading indicator: shown from a browser's arrival until the robot state, the
        supervisor's reply, the force and the video (those whose services are alive) have
        all arrived; then hidden until the next browser."""
        if self.loaded:
            return
        alive = self.node.alive
        waiting = loading_items(
            state=self.mirror.state.latest is not None,
            decision=decision_replied,
            force=self.mirror.latest_force() is not None if alive.is_alive("force") else None,
            video=(
                self.frames_shown > 0
                if self._view_mode != "off" and alive.is_alive("vision")
                else None
            ),
        )
        self._set_html("loading", self._loading_html, loading_html(waiting))
        if not waiting:
            self.loaded = True
            self._loading_html.visible = False

    def _plot_columns(self, history: History, was_empty: bool) -> list[np.ndarray] | None:
        """The time column and one column per value of `history` over the plot window.
        Nothing (left) in the window: empty columns, so that a stalled stream empties its
        plot rather than leaving its last picture up; None when the plot is empty already
        (nothing to redraw)."""
        t, w = history.window(
            self.config.plot_window_s, self.config.plot_points, now_s=time.monotonic()
        )
        if len(t) < 2:
            if was_empty:
                return None
            t, w = np.zeros(0), np.zeros((0, history.width))
        return [t, *(np.ascontiguousarray(w[:, k]) for k in range(history.width))]

    def _update_plots(self) -> None:
        cols = self._plot_columns(self.mirror.force, self._plot_empty)
        if cols is None:
            return
        self._plot_empty = len(cols[0]) == 0
        self._f_plot.data = (cols[0], cols[1], cols[2], cols[3])
        self._c_plot.data = (cols[0], cols[4], cols[5], cols[6])

    def _update_tdpa_plot(self) -> None:
        """The passivity plot: reservoirs and dissipated energy per port over the window."""
        cols = self._plot_columns(self.mirror.tdpa, self._tdpa_empty)
        if cols is None:
            return
        self._tdpa_empty = len(cols[0]) == 0
        self._tdpa_plot.data = tuple(cols)

    def _update_video(self, now: float) -> None:
        mode = self._view_mode
        self.mirror.watch_video(mode != "off")
        key = self.mirror.frame_counts()
        if mode == "off" or key == (0, 0) or not self._gate.due(now, key):
            return
        # Only the eyes this view shows are decoded, and only the frames it shows.
        left = self.mirror.frame("l") if mode != "right" else None
        right = self.mirror.frame("r") if mode != "left" else None
        try:
            li: Image | None = decode(left) if left is not None else None
            ri: Image | None = decode(right) if right is not None else None
        except ValueError:
            self.video_errors += 1
            return
        img = compose(li, ri, mode, self.config.video_max_width_px)
        if img is not None:
            self._image.image = img
            self.frames_shown += 1
