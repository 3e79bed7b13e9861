"""The console's actions: the page's callbacks, the calls to the decision server and
the master that the buttons queue (run in order on the action thread), and the poller
of their status."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any, cast

from services.bus.errors import RpcError, Unavailable
from services.bus.node import Node
from services.bus.streams import Publisher
from services.control.vision.adapt import VideoArrival
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.hand import HandLink
from services.frontends.console.mirror import BusMirror
from services.frontends.console.poses import hand_pose
from services.frontends.console.video import VIEW_MODES, FrameGate, ViewMode
from services.geometry import Array3, Mat3

log = logging.getLogger("telerobot.console")


DECISION = "decision"
HOME_BUSY_RETRY_S = 1.0
HOME_BUSY_STEP_S = 0.05


class Actions:
    """The page's callbacks, actions and poller (a mixin of `Console`)."""

    # What the actions use of the rest of `Console` (set in `Console.__init__` and
    # `Panels._build_gui`).
    node: Node
    config: ConsoleConfig
    mirror: BusMirror
    hand: HandLink
    _stop: threading.Event
    _arrival_pub: Publisher[VideoArrival]
    _arrival_sent_s: float
    _lock: threading.Lock
    _place: tuple[Array3, Mat3] | None
    _view_mode: ViewMode
    _gate: FrameGate
    _actions: queue.Queue[tuple[str, Callable[[], str]] | None]
    _scale_t: Any
    _scale_r: Any

    if TYPE_CHECKING:

        def _wait_viewers(self) -> bool: ...

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

    def _request_place(self, p: Array3, R: Mat3) -> None:
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
            self._poll_link()
            self._stop.wait(self.config.status_period_s)

    def _poll_link(self) -> None:
        """The link panel's round trip (a call to the vision service, through the robot
        host's router and back) and, once a second while video is watched, the report of
        what arrived of it (`vision/arrival`), from which the vision service adapts."""
        if self.node.alive.is_alive("vision"):
            t0 = time.perf_counter()
            try:
                self.node.call("vision", "status", {}, min(1.0, self.config.rpc_timeout_s))
            except (RpcError, Unavailable):
                pass
            else:
                self.mirror.link.on_rtt((time.perf_counter() - t0) * 1e3)
        now = time.monotonic()
        if self.mirror.watching[1] and now - self._arrival_sent_s >= 1.0:
            self._arrival_sent_s = now
            report = self.mirror.link.report()
            if report is not None:
                self._arrival_pub.put(report)
