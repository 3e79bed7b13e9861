"""What the console knows of the system: the newest of every stream, the force history, the
event log, the engagement reference of the commanded target, and the polled status.

Zenoh's callbacks only store here (latest-wins or append, under a lock, O(1)); the GUI
thread reads snapshots. Nothing here talks to the page.

Nobody watching, no work: what only a page shows (the force, the supervised command, the
passivity figures, the video) is subscribed to only while a browser is connected
(`watch_page`, `watch_video`).
Video frames are stored as they arrive, undecoded; `frame()` decodes the newest one when
the page is about to show it, so frames no browser will see are never decoded.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import zenoh
from numpy.typing import NDArray

from services.bus import codec
from services.bus.errors import ProtocolError
from services.bus.keys import (
    ARM_DESCRIPTION,
    ARM_TARGET,
    EVENTS,
    FORCE,
    MASTER_STATE,
    PASSIVITY_MASTER,
    PASSIVITY_SLAVE,
    STATE,
    STEREO_L,
    STEREO_R,
    VISION_STATS,
    Topic,
)
from services.bus.messages import (
    ArmDescription,
    ArmTarget,
    Event,
    ForceSample,
    MasterState,
    Message,
    PassivityState,
    RobotState,
    StereoFrame,
    VisionStats,
    mat3,
)
from services.bus.node import Node, Subscription
from services.frontends.console.link import LinkMeter
from services.frontends.console.tdpa import PortSeen, TdpaView, newer, plot_row, tdpa_view
from services.geometry import Array3, Mat3
from services.world.workcell.messages import WORKCELL_STATE, WorkcellState

M = TypeVar("M", bound=Message)

TARGET_STALE_S = 1.0
"""The commanded target is drawn while robot/arm/target arrived within this time."""


class History:
    """A ring buffer of rows of `width` values for a plot: time (s), the row, and when the
    newest arrived (s, this process's monotonic clock). `add_row` is O(1) and called from
    Zenoh's thread. A row older than the newest one starts a new series (see ForceHistory).
    """

    def __init__(self, capacity: int, width: int = 6) -> None:
        if capacity < 2:
            raise ValueError("capacity must be ≥ 2")
        self.width = width
        self._t = np.zeros(capacity)
        self._w = np.zeros((capacity, width))
        self._n = 0
        self._i = 0
        self._rx_s = 0.0
        self.restarts = 0
        """How many times a sample from the past started a new series."""
        self._lock = threading.Lock()

    def add_row(self, t_s: float, row: tuple[float, ...], rx_s: float | None = None) -> None:
        """Append a row taken at `t_s` that arrived at `rx_s` (time.monotonic(); now if
        None)."""
        rx = time.monotonic() if rx_s is None else rx_s
        with self._lock:
            if self._n and t_s < self._t[self._i - 1]:
                self._n = self._i = 0
                self.restarts += 1
            self._t[self._i] = t_s
            self._w[self._i] = row
            self._i = (self._i + 1) % len(self._t)
            self._n = min(self._n + 1, len(self._t))
            self._rx_s = rx

    def __len__(self) -> int:
        with self._lock:
            return self._n

    def window(
        self, span_s: float, max_points: int, now_s: float | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The samples of the last `span_s` seconds, oldest first, as (t, w): t (n,) in s
        relative to now (≤ 0), w (n, width); decimated by an integer step to at most
        `max_points`. "Now" is `now_s` (time.monotonic()): the newest sample sits at minus
        its age, so a stalled stream leaves the window; with `now_s` None, at 0."""
        with self._lock:
            n, i, rx = self._n, self._i, self._rx_s
            idx = (np.arange(i - n, i)) % len(self._t)
            t = self._t[idx].copy()
            w = self._w[idx].copy()
        if n == 0:
            return np.zeros(0), np.zeros((0, self.width))
        t -= t[-1] + (max(0.0, now_s - rx) if now_s is not None else 0.0)
        keep = t >= -span_s
        t, w = t[keep], w[keep]
        step = max(1, -(-len(t) // max_points))
        # Decimate from the newest backwards so the newest sample is always shown; the
        # arrays are made contiguous because the page's serializer sends raw buffers.
        return (
            np.ascontiguousarray(t[::-1][::step][::-1]),
            np.ascontiguousarray(w[::-1][::step][::-1]),
        )


class ForceHistory(History):
    """The force samples for the plots: time (s, the sender's clock), w = (f (3, N),
    c (3, N·m)), tool frame.

    The sender's clock spaces the points (Python callbacks run late in bursts under load,
    so arrival times would bunch them up); the receiver's clock places the newest one, so a
    stream that stalls slides out of the window instead of freezing on screen. A sample
    older than the newest one (the sender's wall clock stepped back, the sender restarted,
    or another publisher's clock) starts a new series: mixing two time bases drew one
    cluster of points at the end of an axis minutes long (#23 item 9).
    """

    def __init__(self, capacity: int) -> None:
        super().__init__(capacity, 6)

    def add(
        self, t_s: float, f: tuple[float, ...], c: tuple[float, ...], rx_s: float | None = None
    ) -> None:
        """Append a sample taken at `t_s` (the sender's clock) that arrived at `rx_s`
        (time.monotonic(); now if None)."""
        self.add_row(t_s, (*f, *c), rx_s)


class BusMirror:
    """Subscribes to the streams the console shows; polled status is stored here too.

    Always: robot/state, master/state, robot/events, vision/stats (what the hand link and
    the event log need, at low rates), and robot/arm/description (on change, with history:
    the arm's cached description arrives however late the console starts). While
    `watch_page(True)`: robot/force, robot/arm/target, workcell/state and
    robot/passivity/{master,slave}. While `watch_video(True)`: vision/stereo/l and /r.

    `tdpa` holds the passivity plot's rows (`tdpa.plot_row`), one per figures received,
    timed on this process's monotonic clock (the two sides' clocks may differ).
    """

    def __init__(
        self,
        node: Node,
        events: int,
        force_capacity: int,
        tdpa_capacity: int = 1024,
        receiver: str = "console",
    ) -> None:
        self.node = node
        # the link panel's figures and the video's arrival report (link.py)
        self.link = LinkMeter(receiver)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self.force = ForceHistory(force_capacity)
        self._force_latest: ForceSample | None = None
        self.tdpa = History(tdpa_capacity, width=4)
        self._tdpa: dict[str, PortSeen] = {}
        self._workcell: WorkcellState | None = None
        self._events: deque[Event] = deque(maxlen=events)
        self.events_seen = 0
        self._masters: dict[str, MasterState] = {}
        self._target: ArmTarget | None = None
        self._target_rx_s = -1e18
        self.decision_status: dict[str, Any] | None = None
        self.decision_error: str | None = "no reply yet"
        self.master_status: dict[str, Any] | None = None
        self._page_subs: list[Any] = []
        self._video_subs: list[Any] = []
        # eye → (frames arrived, the newest one's payload, undecoded)
        self._frames: dict[str, tuple[int, bytes | None]] = {"l": (0, None), "r": (0, None)}
        self.state: Subscription[RobotState] = node.subscribe(STATE)
        self.description: Subscription[ArmDescription] = node.subscribe(
            ARM_DESCRIPTION, history=True
        )
        self.vision: Subscription[VisionStats] = node.subscribe(VISION_STATS)
        node.subscribe(EVENTS, self._on_event)
        node.subscribe(MASTER_STATE, self._on_master)

    # --- what only a page shows ---------------------------------------------------------------
    def watch_page(self, on: bool) -> None:
        """Subscribe to the force, the supervised command and the workcell's state (on) or
        drop them (off)."""
        if on and not self._page_subs:
            self._page_subs = [
                self._subscribe(FORCE, self._on_force),
                self._subscribe(ARM_TARGET, self._on_target),
                self._subscribe(WORKCELL_STATE, self._on_workcell),
                self._subscribe(PASSIVITY_MASTER, self._passivity_store("master")),
                self._subscribe(PASSIVITY_SLAVE, self._passivity_store("slave")),
            ]
        elif not on:
            subs, self._page_subs = self._page_subs, []
            for sub in subs:
                sub.undeclare()
            self._force_latest = None
            with self._lock:
                self._tdpa.clear()

    def watch_video(self, on: bool) -> None:
        """Subscribe to both eyes (on) or drop them (off: vision, if nobody else watches,
        then stops rendering and encoding)."""
        if on and not self._video_subs:
            self._video_subs = [
                self.node.session.declare_subscriber(topic.key, self._frame_store(eye))
                for eye, topic in (("l", STEREO_L), ("r", STEREO_R))
            ]
        elif not on:
            subs, self._video_subs = self._video_subs, []
            for sub in subs:
                sub.undeclare()
            with self._lock:
                # Frames from before are stale by the time anyone watches again.
                self._frames = {eye: (n, None) for eye, (n, _) in self._frames.items()}

    @property
    def watching(self) -> tuple[bool, bool]:
        """(page streams subscribed, video subscribed)."""
        return bool(self._page_subs), bool(self._video_subs)

    def _subscribe(self, topic: Topic[M], on_message: Callable[[M], None]) -> Any:
        """A subscription that can be dropped: decode, count a bad payload as the node's
        own subscriptions do (rejected event), hand the message over."""

        def callback(sample: zenoh.Sample) -> None:
            try:
                msg = codec.decode(topic.type, sample.payload.to_bytes())
            except ProtocolError as e:
                self.node.report_rejected(str(sample.key_expr), str(e))
                return
            on_message(msg)

        # On the session, not through the node, so that it can be undeclared and forgotten.
        return self.node.session.declare_subscriber(topic.key, callback)

    def _frame_store(self, eye: str) -> Callable[[zenoh.Sample], None]:
        def store(sample: zenoh.Sample) -> None:
            # Copied now (a memcpy), decoded later: a payload kept by reference may sit in a
            # shared-memory buffer its publisher reuses.
            data = sample.payload.to_bytes()
            rx_ns = time.time_ns()
            with self._lock:
                n = self._frames[eye][0]
                self._frames[eye] = (n + 1, data)
            if eye == "l":  # one eye per pair, for the arrival report (vision/arrival)
                try:
                    frame = codec.decode(StereoFrame, data)
                except ProtocolError:
                    return  # reported when the page decodes it (`frame`)
                self.link.on_frame(frame.seq, frame.t_ns, rx_ns)

        return store

    def frame_counts(self) -> tuple[int, int]:
        """How many frames of each eye (left, right) arrived so far."""
        with self._lock:
            return self._frames["l"][0], self._frames["r"][0]

    def frame(self, eye: str) -> StereoFrame | None:
        """The newest frame of `eye` ("l" | "r"), decoded and validated now; None when none
        arrived or it is bad (counted and reported as a rejected input)."""
        with self._lock:
            payload = self._frames[eye][1]
        if payload is None:
            return None
        try:
            return codec.decode(StereoFrame, payload)
        except ProtocolError as e:
            key = (STEREO_L if eye == "l" else STEREO_R).key
            self.node.report_rejected(key, str(e))
            return None

    # --- Zenoh's thread: store only -------------------------------------------------------
    def _on_force(self, msg: ForceSample) -> None:
        self.force.add(msg.t_ns / 1e9, msg.f, msg.c)
        self.link.on_force(msg.seq, time.monotonic())
        self._force_latest = msg

    def _passivity_store(self, side: str) -> Callable[[PassivityState], None]:
        key = (PASSIVITY_MASTER if side == "master" else PASSIVITY_SLAVE).key

        def store(msg: PassivityState) -> None:
            if msg.side != side:  # the other side's figures on this side's key: refused
                self.node.report_rejected(key, f"side: {msg.side!r} on {key}")
                return
            rx = time.monotonic()
            with self._lock:
                old = self._tdpa.get(side)
                if old is not None and not newer(old.msg, msg):
                    return
                self._tdpa[side] = PortSeen.first(msg, rx) if old is None else old.after(msg, rx)
                row = plot_row(tdpa_view(self._tdpa, rx))
            self.tdpa.add_row(rx, row, rx)

        return store

    def _on_workcell(self, msg: WorkcellState) -> None:
        old = self._workcell
        if old is None or msg.seq > old.seq or msg.t_ns > old.t_ns:
            self._workcell = msg

    def _on_event(self, ev: Event) -> None:
        with self._lock:
            self._events.append(ev)
            self.events_seen += 1

    def _on_master(self, msg: MasterState) -> None:
        with self._cond:
            old = self._masters.get(msg.master)
            if old is None or msg.seq > old.seq or msg.t_ns > old.t_ns:
                self._masters[msg.master] = msg
            self._cond.notify_all()

    def _on_target(self, tgt: ArmTarget) -> None:
        with self._lock:
            old = self._target
            if old is not None and tgt.seq <= old.seq and tgt.t_ns <= old.t_ns:
                return
            self._target = tgt
            self._target_rx_s = time.monotonic()

    # --- readers ----------------------------------------------------------------------------
    def latest_force(self) -> ForceSample | None:
        return self._force_latest

    def passivity(self, now_s: float | None = None) -> TdpaView:
        """The passivity figures as shown at `now_s` (time.monotonic(); now if None)."""
        with self._lock:
            seen = dict(self._tdpa)
        return tdpa_view(seen, time.monotonic() if now_s is None else now_s)

    def workcell(self) -> WorkcellState | None:
        """The newest `workcell/state` (its objects not yet checked: `objects_of`)."""
        return self._workcell

    def events(self) -> list[Event]:
        with self._lock:
            return list(self._events)

    def events_since(self, seen: int) -> tuple[list[Event], int]:
        """The events that arrived after the first `seen` ones (at most the log's length),
        oldest first, and the new count to pass next time."""
        with self._lock:
            n = min(self.events_seen - seen, len(self._events))
            return (list(self._events)[len(self._events) - n :] if n > 0 else []), self.events_seen

    def master(self, master_id: str) -> MasterState | None:
        with self._lock:
            return self._masters.get(master_id)

    def wait_master(
        self, master_id: str, pred: Callable[[MasterState], bool], timeout_s: float
    ) -> MasterState | None:
        """Block until master `master_id`'s newest state satisfies `pred`, or the deadline."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                m = self._masters.get(master_id)
                if m is not None and pred(m):
                    return m
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)

    def target(self) -> tuple[Array3, Mat3, bool] | None:
        """The tool target robot/arm/target asks for (p, R, active: false while the
        supervisor holds), or None when none arrived within TARGET_STALE_S."""
        with self._lock:
            tgt, rx = self._target, self._target_rx_s
        if tgt is None or time.monotonic() - rx > TARGET_STALE_S:
            return None
        return np.asarray(tgt.p, dtype=float), mat3(tgt.R), not tgt.hold

    def set_status(
        self,
        decision: dict[str, Any] | None,
        decision_error: str | None,
        master: dict[str, Any] | None,
    ) -> None:
        """Store the polled status (from the poller thread)."""
        with self._lock:
            self.decision_status = decision
            self.decision_error = decision_error
            self.master_status = master

    def status(self) -> tuple[dict[str, Any] | None, str | None, dict[str, Any] | None]:
        with self._lock:
            return self.decision_status, self.decision_error, self.master_status
