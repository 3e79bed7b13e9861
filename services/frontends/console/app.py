"""The operator console: a viser page that mirrors the arm and drives the system.

Threads (franka-node's rule, applied to a page): Zenoh's callbacks only store into the
`BusMirror`; the page's callbacks only store, queue an action or notify the `HandLink`;
ONE GUI thread pushes to viser at `gui_rate_hz` (the arm when its joints moved, frames,
force arrow, panels, plots, video at `video_fps`); one action thread runs the buttons'
calls in order (the e-stop does not queue: it is called at once); one poller thread asks
the decision server and the master for their status every `status_period_s`; the hand
link's thread feeds the virtual master.

The console talks to the robot only through the decision server (`robot/decision/rpc/…`)
and to the operator's station through the master's methods (`robot/master/<id>/rpc/…`).

Nobody watching, no work: the GUI thread and the poller run only while a browser is
connected (viser's connect/disconnect callbacks); without one they sleep, and the force,
the supervised command and the video are not even subscribed to (so vision, seeing nobody
subscribe, renders nothing). An engaged virtual master is clutched when the last browser
leaves and parked on the tool when one comes back.

The page's parts are mixins of `Console`, one module each: the 3D view (`view3d.py`), the
controls and panels (`panels.py`), the actions and the poller (`actions.py`).
"""

from __future__ import annotations

import contextlib
import io
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import viser

from services.bus.messages import Event, RobotState, mat3
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.control.vision.adapt import VIDEO_ARRIVAL
from services.frontends.console.actions import DECISION, Actions
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.hand import HandLink, ToolPose
from services.frontends.console.mirror import BusMirror
from services.frontends.console.panels import Panels
from services.frontends.console.video import FrameGate, ViewMode
from services.frontends.console.view3d import View3D
from services.geometry import Array3, Mat3, wxyz_from_R
from services.world.workcell.scene import Scene

log = logging.getLogger("telerobot.console")


PANEL_EVERY_S = 0.2
PLOT_EVERY_S = 0.1
SAME_Q_RAD = 1e-5
"""The arm is redrawn when a joint (rad) or the tool's or flange's pose (m, unit-free R)
moved more than this since it was last drawn."""
REFUSALS = frozenset({"lease", "busy", "rejected"})
"""Decision events that, naming our master, mean its engagement was refused or held."""


@contextlib.contextmanager
def _quiet(what: str) -> Iterator[None]:
    """Send what a third-party call prints on stdout to the debug log instead."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        yield
    if buf.getvalue().strip():
        log.debug("%s: %s", what, buf.getvalue().strip())


class Console(View3D, Panels, Actions):
    """The console page on `config.host:config.port` for the system on `node`'s network.

    `url` is where it is served. `close()` stops the threads and the web server; it does
    not close the node (its owner does).
    """

    def __init__(self, node: Node, config: ConsoleConfig, scene: Scene | None = None) -> None:
        self.node = node
        self.config = config
        self.scene = scene
        # The passivity figures reach the console at twice the GUI rate per side (its
        # session's downsampling): room for the plot's window of both.
        self.mirror = BusMirror(
            node,
            config.events,
            force_capacity=int(1000 * config.plot_window_s * 1.5) + 64,
            tdpa_capacity=int(4 * config.gui_rate_hz * config.plot_window_s * 1.5) + 64,
            receiver=f"console/{config.master_id}",
        )
        # what this console gets of the video, for the vision service's level (adapt.py)
        self._arrival_pub = node.publisher(VIDEO_ARRIVAL)
        self._arrival_sent_s = 0.0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._place: tuple[Array3, Mat3] | None = None
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
        self._last_drawn: tuple[float, ...] | None = None
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
        rebuilt = self._sync_arm()
        if st is not None:
            self._watch_status(st)
            # Drawn only when it moved: the joints, or the tool alone (set_tool).
            drawn = (*st.q, *st.tool_p, *st.tool_R, *st.flange_p)
            last = self._last_drawn
            if (
                rebuilt
                or last is None
                or len(last) != len(drawn)
                or max(abs(a - b) for a, b in zip(drawn, last, strict=True)) > SAME_Q_RAD
            ):
                self._draw_arm(st)
                self._last_drawn = drawn
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
