"""The operator console: a viser page that mirrors the arm and drives the system.

Threads (franka-node's rule, applied to a page): Zenoh's callbacks only store into the
`BusMirror`; the page's callbacks only store, queue an action or notify the `HandLink`;
ONE GUI thread pushes to viser at `gui_rate_hz` (arm, frames, force arrow, panels, plots,
video at `video_fps`); one action thread runs the buttons' calls in order (the e-stop does
not queue: it is called at once); one poller thread asks the decision server and the master
for their status every `status_period_s`; the hand link's thread feeds the virtual master.

The console talks to the robot only through the decision server (`robot/decision/rpc/…`)
and to the operator's station through the master's methods (`robot/master/<id>/rpc/…`).

Nobody watching, no work: the GUI thread and the poller run only while a browser is
connected (viser's connect/disconnect callbacks); without one they sleep, and the force,
the supervised command and the video are not even subscribed to (so vision, seeing nobody
subscribe, renders nothing). An engaged virtual master is clutched when the last browser
leaves and parked on the tool when one comes back.
"""

from __future__ import annotations

import contextlib
import io
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from typing import Any, cast

import numpy as np
import viser

from services.bus.errors import ProtocolError, RpcError, Unavailable
from services.bus.messages import Event, RobotState, mat3
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.control.puma.kinematics import Puma560
from services.control.vision.objects import LIQUID_BGR, SPILL_BGR, Spills
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.geometry import (
    Mat,
    Vec,
    box_edges,
    cylinder_pose,
    force_arrow,
    hand_pose,
    link_segments,
)
from services.frontends.console.hand import HandLink, ToolPose
from services.frontends.console.mirror import BusMirror
from services.frontends.console.tdpa import TdpaView
from services.frontends.console.video import VIEW_MODES, FrameGate, Image, ViewMode, compose, decode
from services.frontends.console.view import (
    MasterView,
    alive_html,
    estop_latched,
    events_html,
    loading_html,
    loading_items,
    passivity_html,
    status_html,
)
from services.frontends.console.world import (
    FINGER_SIZE_M,
    PUDDLE_THICKNESS_M,
    ObjectNode,
    finger_offsets,
    object_nodes,
    puddle_nodes,
)
from services.geometry import wxyz_from_R
from services.world.workcell.messages import WORKCELL_STATE, objects_of
from services.world.workcell.scene import default_scene

log = logging.getLogger("telerobot.console")

DECISION = "decision"
LINK_RADIUS_M = 0.045
JOINT_RADIUS_M = 0.06
TOOL_RADIUS_M = 0.012
FORCE_ARROW_MAX_M = 0.4
FORCE_MIN_N = 0.5
"""Below this the force arrow is hidden (sensor noise, not a contact)."""
PANEL_EVERY_S = 0.2
PLOT_EVERY_S = 0.1
SAME_Q_RAD = 1e-5
REDRAW_TOL = 5e-4
"""A drawn pose or arrow is sent again only when it moved more than this (m, or unit-free
for rotation entries): sub-millimetre noise does not keep the browser re-rendering."""
GIZMO_LINE_WIDTH = 4.0
"""The gizmo's handles are drawn this thick (screen px; viser's default is 2.5): a first
drag grabs them rather than the camera."""
HOME_BUSY_RETRY_S = 1.0
HOME_BUSY_STEP_S = 0.05

REFUSALS = frozenset({"lease", "busy", "rejected"})
"""Decision events that, naming our master, mean its engagement was refused or held."""
ROBOT_ACTIONS = ("Connect", "Initialize", "Home", "Stop")
ROBOT_HINT = (
    "Connect: puma connect. Initialize: connect if needed, then calibrate (ready follows). "
    "Home: clutch the master, move home. Stop: hold teleoperation, cancel a task."
)

_ARM_COLOR = (235, 140, 52)
_PEDESTAL_COLOR = (90, 90, 100)
_JOINT_COLOR = (60, 60, 70)
_TOOL_COLOR = (200, 200, 210)
_FORCE_COLOR = (220, 30, 200)
_WORKSPACE_COLOR = (30, 160, 90)
_TARGET_COLOR = (255, 140, 0)
_FINGER_COLOR = (70, 70, 80)
FINGER_HOLDING_COLOR = (30, 160, 90)
BOTTLE_OPACITY = 0.45
"""A bottle is drawn translucent, so that its liquid shows."""

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


@contextlib.contextmanager
def _quiet(what: str) -> Iterator[None]:
    """Send what a third-party call prints on stdout to the debug log instead."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        yield
    if buf.getvalue().strip():
        log.debug("%s: %s", what, buf.getvalue().strip())


def _rgb(bgr: tuple[int, int, int]) -> tuple[int, int, int]:
    return (bgr[2], bgr[1], bgr[0])


class Console:
    """The console page on `config.host:config.port` for the system on `node`'s network.

    `url` is where it is served. `close()` stops the threads and the web server; it does
    not close the node (its owner does).
    """

    def __init__(self, node: Node, config: ConsoleConfig) -> None:
        self.node = node
        self.config = config
        self._kin = Puma560()  # GUI thread only: Pinocchio's data is not thread-safe
        # The passivity figures reach the console at twice the GUI rate per side (its
        # session's downsampling): room for the plot's window of both.
        self.mirror = BusMirror(
            node,
            config.events,
            force_capacity=int(1000 * config.plot_window_s * 1.5) + 64,
            tdpa_capacity=int(4 * config.gui_rate_hz * config.plot_window_s * 1.5) + 64,
        )
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._place: tuple[Vec, Mat] | None = None
        self._view_mode: ViewMode = "side-by-side"
        self._gate = FrameGate(config.video_fps)
        self._actions: queue.Queue[tuple[str, Callable[[], str]] | None] = queue.Queue()
        self.last_action = ""
        self.gui_errors = 0
        self.video_errors = 0
        self.ticks = 0
        self.frames_shown = 0
        # Browsers connected now (viser's callbacks), and whether the hand was clutched
        # because the last one left (then it is parked again when one comes back).
        self._viewers = 0
        self._viewers_cond = threading.Condition()
        self._held_while_away = False
        self._last_q: tuple[float, ...] | None = None
        self._last_status: str | None = None
        self._events_seen = 0
        self._panels: dict[str, str] = {}
        self._drawn: dict[str, np.ndarray] = {}
        self._workspace: tuple[tuple[float, ...], tuple[float, ...]] | None = None
        self._estop_shown: bool | None = None
        self._plot_empty = True
        self._tdpa_empty = True
        self._tdpa_state = ""
        self.loaded = False
        self._scales_loaded = False

        # viser prints a banner on stdout whatever `verbose` says; our one line
        # `console: URL` (which `make demo` reads) must be the only one there.
        with _quiet("viser start"):
            self.server = viser.ViserServer(
                host=config.host, port=config.port, label="Telerobot console", verbose=False
            )
        if config.port and self.port != config.port:
            log.warning("port %d is taken: serving on %d", config.port, self.port)
        self.server.gui.configure_theme(
            control_width="large", show_share_button=False, show_logo=False
        )
        self.server.scene.set_up_direction("+z")
        self.server.scene.configure_default_lights(cast_shadow=config.shadows)
        self.server.initial_camera.position = config.camera_position_m
        self.server.initial_camera.look_at = config.camera_look_at_m
        self.hand = HandLink(
            node,
            config.master_id,
            lambda pred, timeout_s: self.mirror.wait_master(config.master_id, pred, timeout_s),
            self._tool_pose,
            self._request_place,
            config.rpc_timeout_s,
        )
        self._build_scene()
        self._build_gui()
        self.server.on_client_connect(self._on_clients_changed)
        self.server.on_client_disconnect(self._on_clients_changed)
        self._threads = [
            threading.Thread(target=self._gui_loop, name="console-gui", daemon=True),
            threading.Thread(target=self._action_loop, name="console-actions", daemon=True),
            threading.Thread(target=self._poll_loop, name="console-poll", daemon=True),
        ]
        for t in self._threads:
            t.start()
        node.announce()

    @property
    def port(self) -> int:
        """The port actually served (differs from the configured one if that was taken)."""
        return self.server.get_port()

    @property
    def url(self) -> str:
        return f"http://{self.config.host}:{self.port}"

    @property
    def viewers(self) -> int:
        """How many browsers are connected."""
        with self._viewers_cond:
            return self._viewers

    # --- browsers come and go -------------------------------------------------------------
    def _on_clients_changed(self, _client: Any) -> None:
        # viser's thread pool may run these out of order: count the clients it has now,
        # under the lock, so the last one to run leaves the true count.
        with self._viewers_cond:
            self._viewers = len(self.server.get_clients())
            self._viewers_cond.notify_all()

    def _wait_viewers(self) -> bool:
        """Block while no browser is connected; False once the console is closing."""
        with self._viewers_cond:
            while self._viewers == 0 and not self._stop.is_set():
                self._viewers_cond.wait()
            return not self._stop.is_set()

    def _go_live(self) -> None:
        """A browser came: subscribe to what the page shows, park a hand clutched while
        nobody was there, and show the state from now on, not a backlog."""
        self.mirror.watch_page(True)
        self._events_seen = self.mirror.events_seen
        self._gate.reset()
        # Each new page shows what it still waits for until everything has arrived.
        self.loaded = False
        self._loading_html.visible = True
        if self._held_while_away:
            self._held_while_away = False
            self.hand.resync()
        log.info("a browser is connected: the page is live")

    def _go_idle(self) -> None:
        """The last browser left: nobody sees or drives anything any more."""
        self.mirror.watch_video(False)
        self.mirror.watch_page(False)
        if self.hand.state == "engaged":
            # The operator is gone: clutch, so no engagement outlives its operator.
            self.hand.hold()
            self._held_while_away = True
        log.info("no browser: the page sleeps")

    # --- the page: scene ----------------------------------------------------------------
    def _build_scene(self) -> None:
        sc = self.server.scene
        sc.add_grid("/floor", width=3.0, height=3.0, cell_size=0.25, section_size=1.0)
        # The same description the workcell, force and vision simulations use; the movable
        # objects are moved to their `workcell/state` poses while a browser watches.
        self.workcell = default_scene()
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
        self._links: list[Any] = []
        self._joints: list[Any] = []
        self._tool_frame = sc.add_frame(
            "/arm/tool_frame", axes_length=0.1, axes_radius=0.006, visible=False
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

    # --- page callbacks (viser's threads): store, queue or notify only --------------------
    # A value set by the console itself (client None) is not the operator's: not sent on.
    def _on_robot(self, action: str) -> None:
        if action == "Connect":
            self._submit("connect", self._do_connect)
        elif action == "Initialize":
            self._submit("initialize", self._do_initialize)
        elif action == "Home":
            self._submit("home", self._do_home)
        elif action == "Stop":
            # Like the e-stop, not queued behind a running `home`.
            self._now("stop", self._do_stop)

    def _on_frame(self, ev: Any) -> None:
        if ev.client is not None:
            self._submit("frame", partial(self._do_frame, str(ev.target.value)))

    def _on_scale(self, ev: Any) -> None:
        if ev.client is not None:
            self._submit("scale", self._do_scale)

    def _on_gizmo(self, ev: Any) -> None:
        p, R = hand_pose(ev.target.position, ev.target.wxyz)
        self.hand.set_gizmo(p, R)
        if getattr(ev, "phase", None) == "end":
            self.hand.release()  # let go: disengage cleanly, engage afresh at the next drag

    def _set_view(self, mode: str) -> None:
        if mode in VIEW_MODES:
            self._view_mode = cast(ViewMode, mode)
            self._gate.reset()

    def _request_place(self, p: Vec, R: Mat) -> None:
        with self._lock:
            self._place = (p, R)

    def _submit(self, name: str, fn: Callable[[], str]) -> None:
        self._actions.put((name, fn))

    def _now(self, name: str, fn: Callable[[], str]) -> None:
        """Run an urgent action on the calling thread, ahead of anything queued."""
        self._run_action(name, fn)

    # --- actions ------------------------------------------------------------------------
    def _call(self, method: str, args: dict[str, Any] | None = None, timeout_s: float = 0.0) -> Any:
        return self.node.call(DECISION, method, args or {}, timeout_s or self.config.rpc_timeout_s)

    def _call_master(self, method: str, args: dict[str, Any]) -> dict[str, Any]:
        return self.node.call(
            f"master/{self.config.master_id}", method, args, self.config.rpc_timeout_s
        )

    def _do_connect(self) -> str:
        return str(self._call("connect").get("status", "ok"))

    def _do_initialize(self) -> str:
        st = self.mirror.state.latest
        if st is None or st.status in ("disconnected", "error"):
            self._call("connect")
        return str(self._call("initialize").get("status", "ok"))

    def _do_home(self) -> str:
        # The decision refuses `home` while a master teleoperates: clutch ours first. It
        # stays clutched if `home` fails (Snap or Reset releases it), parked if it succeeds.
        self.hand.hold()
        self.mirror.wait_master(
            self.config.master_id, lambda m: not m.active, self.config.rpc_timeout_s
        )
        deadline = time.monotonic() + HOME_BUSY_RETRY_S
        while True:
            try:
                self._call("home", {"wait": True}, self.config.wait_timeout_s)
                break
            except RpcError as e:
                if e.code != "busy" or time.monotonic() > deadline:
                    raise
                # The decision sees the master's disengagement within a tick or two.
                self._stop.wait(HOME_BUSY_STEP_S)
        self.hand.resync()
        return "done"

    def _do_stop(self) -> str:
        self._call("stop")
        return "holding"

    def _do_estop(self) -> str:
        self.hand.hold()
        reply = self._call("estop", {"reason": "e-stop button of the web console"})
        return "latched" if reply.get("estop") else str(reply)

    def _do_reset(self) -> str:
        reply = self._call("reset")
        self.hand.resync()
        return "cleared" if reply.get("was_latched") else "was not latched"

    def _do_frame(self, frame: str) -> str:
        return str(self._call_master("set_frame", {"frame": frame}).get("frame"))

    def _do_scale(self) -> str:
        reply = self._call_master(
            "set_scale",
            {"scale_t": float(self._scale_t.value), "scale_r": float(self._scale_r.value)},
        )
        return f"s_t {reply.get('scale_t')}, s_r {reply.get('scale_r')}"

    def _run_action(self, name: str, fn: Callable[[], str]) -> None:
        self.last_action = f"{name}: …"
        try:
            result = fn()
        except RpcError as e:
            result = f"{e.code}: {e.message}"
        except Unavailable as e:
            result = f"unavailable: {e}"
        self.last_action = f"{name}: {result}"
        log.info("action %s", self.last_action)

    def _action_loop(self) -> None:
        while True:
            item = self._actions.get()
            if item is None:
                return
            self._run_action(*item)

    # --- the poller -----------------------------------------------------------------------
    def _poll_loop(self) -> None:
        master_service = f"master/{self.config.master_id}"
        # The status is for the page only: nobody connected, nothing asked.
        while self._wait_viewers():
            decision: dict[str, Any] | None = None
            error: str | None = None
            master: dict[str, Any] | None = None
            # A service that is down is reported at once, not after a call's timeout.
            if not self.node.alive.is_alive(DECISION):
                error = "decision: not running"
            else:
                try:
                    decision = self._call("status", {}, min(1.0, self.config.rpc_timeout_s))
                except (RpcError, Unavailable) as e:
                    error = f"decision: {e}"
            if self.node.alive.is_alive(master_service):
                try:
                    master = self._call_master("status", {})
                except (RpcError, Unavailable):
                    master = None
            self.mirror.set_status(decision, error, master)
            self._stop.wait(self.config.status_period_s)

    # --- the GUI thread -------------------------------------------------------------------
    def _tool_pose(self) -> ToolPose | None:
        st = self.mirror.state.latest
        if st is None:
            return None
        return ToolPose(np.asarray(st.tool_p, dtype=float), mat3(st.tool_R), st.status)

    def _gui_loop(self) -> None:
        while self._wait_viewers():
            self._go_live()
            rate = RateLoop(self.config.gui_rate_hz)
            next_panel = next_plot = 0.0
            while not self._stop.is_set() and self.viewers > 0:
                now = time.monotonic()
                try:
                    with self.server.atomic():
                        self._gui_tick()
                        if now >= next_panel:
                            next_panel = now + PANEL_EVERY_S
                            self._update_panels()
                        if now >= next_plot:
                            next_plot = now + PLOT_EVERY_S
                            self._update_plots()
                            self._update_tdpa_plot()
                    self._update_video(now)
                except Exception:  # a drawing bug must not stop the mirror: count, log, go on
                    self.gui_errors += 1
                    log.exception("console GUI tick failed")
                self.ticks += 1
                rate.sleep()
            self._go_idle()

    def _gui_tick(self) -> None:
        with self._lock:
            place, self._place = self._place, None
        if place is not None:
            self.gizmo.position = place[0]
            self.gizmo.wxyz = wxyz_from_R(place[1])
            self.gizmo.visible = True
        events, self._events_seen = self.mirror.events_since(self._events_seen)
        for ev in events:
            self._watch_event(ev)
        st = self.mirror.state.latest
        if st is not None:
            self._watch_status(st)
            if (
                self._last_q is None
                or max(abs(a - b) for a, b in zip(st.q, self._last_q, strict=True)) > SAME_Q_RAD
            ):
                self._draw_arm(st)
                self._last_q = st.q
        self._draw_target()
        self._draw_force(st)
        self._draw_workcell(st)

    def _watch_status(self, st: RobotState) -> None:
        """Snap the virtual master to the tool when the arm first shows up and whenever it
        becomes ready (initialized, recovered): engagements start from the tool pose."""
        prev, self._last_status = self._last_status, st.status
        if prev is None or (st.status == "ready" and prev not in ("ready", "moving")):
            self.hand.resync()

    def _watch_event(self, ev: Event) -> None:
        """Follow the decision server's view of our master. When it ends or refuses our
        engagement for a reason other than our own master-shift (watchdog, stop, another
        master's lease, a task), park the hand on the tool so that the next motion of the
        gizmo engages anew; under an e-stop, hold it until Reset."""
        data = ev.data or {}
        # Only an engaged hand is concerned: a late event must not undo a later resync.
        if (
            ev.source != DECISION
            or data.get("master") != self.config.master_id
            or self.hand.state != "engaged"
        ):
            return
        action, reason = data.get("action"), data.get("reason")
        if ev.kind == "estop" or reason == "estop":
            self.hand.hold()
        elif (action == "released" and reason != "disengaged") or (
            action is None and ev.kind in REFUSALS
        ):
            self.hand.resync()

    def _draw_arm(self, st: RobotState) -> None:
        origins = self._kin.link_origins(st.q)
        segments = link_segments(origins, st.tool_p)
        sc = self.server.scene
        for i, (a, b) in enumerate(segments):
            centre, wxyz, length = cylinder_pose(a, b)
            tool = i == len(segments) - 1
            if i >= len(self._links):
                self._links.append(
                    sc.add_cylinder(
                        f"/arm/link{i}",
                        radius=TOOL_RADIUS_M if tool else LINK_RADIUS_M,
                        height=length,
                        color=_TOOL_COLOR if tool else _PEDESTAL_COLOR if i == 0 else _ARM_COLOR,
                        position=centre,
                        wxyz=wxyz,
                    )
                )
            else:
                h = self._links[i]
                h.position, h.wxyz, h.height = centre, wxyz, length
        for j, p in enumerate(origins[1:]):
            if j >= len(self._joints):
                self._joints.append(
                    sc.add_icosphere(
                        f"/arm/joint{j + 1}", radius=JOINT_RADIUS_M, color=_JOINT_COLOR, position=p
                    )
                )
            else:
                self._joints[j].position = p
        self._tool_frame.position = np.asarray(st.tool_p)
        self._tool_frame.wxyz = wxyz_from_R(mat3(st.tool_R))
        self._tool_frame.visible = True

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
        return status_html(self.mirror.state.latest, decision, error, mview, self.last_action)

    def _update_panels(self) -> None:
        self._set_html("status", self._status_html, self._html_status())
        self._set_html("alive", self._alive_html, alive_html(self.node.alive.names()))
        self._set_html("events", self._events_html, events_html(self.mirror.events()))
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

    def _update_plots(self) -> None:
        t, w = self.mirror.force.window(
            self.config.plot_window_s, self.config.plot_points, now_s=time.monotonic()
        )
        if len(t) < 2:
            # Nothing (left) in the window: a stalled stream empties the plot rather than
            # leaving its last picture up as if the force were still streaming.
            if self._plot_empty:
                return
            t, w = np.zeros(0), np.zeros((0, 6))
        self._plot_empty = len(t) == 0
        cols = [np.ascontiguousarray(w[:, k]) for k in range(6)]
        self._f_plot.data = (t, cols[0], cols[1], cols[2])
        self._c_plot.data = (t, cols[3], cols[4], cols[5])

    def _update_tdpa_plot(self) -> None:
        """The passivity plot: reservoirs and dissipated energy per port over the window
        (empty, like the force plots, once the figures stop)."""
        t, w = self.mirror.tdpa.window(
            self.config.plot_window_s, self.config.plot_points, now_s=time.monotonic()
        )
        if len(t) < 2:
            if self._tdpa_empty:
                return
            t, w = np.zeros(0), np.zeros((0, 4))
        self._tdpa_empty = len(t) == 0
        self._tdpa_plot.data = (t, *(np.ascontiguousarray(w[:, k]) for k in range(4)))

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

    # --- shutdown -------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the threads and the web server (idempotent). The node stays open."""
        if self._stop.is_set():
            return
        self._stop.set()
        with self._viewers_cond:
            self._viewers_cond.notify_all()
        self._actions.put(None)
        self.hand.close()
        for t in self._threads:
            t.join(timeout=2.0)
        with _quiet("viser stop"):
            self.server.stop()
