"""The `master` service on the bus: device → eq. 5 → `robot/cmd`, force → operator's hand.

One loop thread owns the device (franka-node's rule): it reads the hand at `rate_hz`,
publishes the command, and displays the newest force (`ForceDisplay`: zero unless engaged,
ramped in after each engagement). Subscriptions only store. The master talks to the robot
only through the decision server (commands on `robot/cmd`, calls to
`robot/decision/rpc/…`). Every exit path publishes a disengaged command, so the slave holds.
A device that is lost is reopened with a growing back-off while the process stays up; the
operator then engages afresh.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict, is_dataclass
from typing import Any

from services.bus import codec, keys
from services.bus.errors import RpcError, TelerobotError
from services.bus.messages import (
    Event,
    MasterFeedback,
    Rot,
    Unit,
    Vec3,
    vec,
)
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.control.master.backends import open_master_device
from services.control.master.config import MasterConfig
from services.control.master.device import (
    DeviceLost,
    HandReading,
    KeepsStats,
    MasterDevice,
    MayIdle,
    ReportsRejected,
    ShowsStatus,
    VirtualHand,
)
from services.control.master.feedback import ForceDisplay, ForceFeedback, WrenchHook
from services.control.master.passivity import MasterTdpa
from services.control.master.status_line import ADVICE, StatusInfo
from services.control.master.teleop import Teleop

log = logging.getLogger("telerobot.master")

STATE_RATE_HZ = 50.0
REOPEN_FIRST_S = 0.25
REOPEN_MAX_S = 2.0
"""A lost device is reopened after 0.25 s, then 0.5, 1, 2, 2 … s until it answers."""
HOLD_REPEATS = 3
REENGAGE_FRESH_NS = 500_000_000
"""A hold is re-engaged after only when the master hears of it this soon (the event's stamp
against this host's clock): a master that was itself frozen or cut off for longer (a
suspended laptop, SIGSTOP past its lease) waits for its operator."""
REENGAGE_AFTER = frozenset({"command_timeout"})
"""Holds a master re-engages after by itself while its device still asks to move: a gap in
the command stream (a loaded host), not something the operator must act on (a stop, an
e-stop, a robot error, a lost sensor: those wait for the operator's own re-engagement)."""
IDLE_RATE_HZ = 50.0
"""A station whose device may idle (the virtual master), clutched and not engaged, ticks this
often until the device wakes it: the contract's floor for robot/cmd (≥ 50 Hz) and, as
master/state goes out each idle tick, above its floor (≥ 30 Hz)."""


class MasterService:
    """Runs one master station; `close()` leaves the slave holding.

    force_hook: a master-side stage on the displayed wrench (see `ForceDisplay`), e.g. a
    passivity controller.
    """

    def __init__(
        self,
        node: Node,
        config: MasterConfig,
        device: MasterDevice | None = None,
        force_hook: WrenchHook | None = None,
    ) -> None:
        self.node = node
        self.config = config
        self.device = device if device is not None else open_master_device(config)
        # What the device can do beyond the role, decided once (device.py's Protocols).
        dev = self.device
        self._status_view = dev if isinstance(dev, ShowsStatus) else None
        self._wake = dev.wake if isinstance(dev, MayIdle) and dev.may_idle else None
        self._rejects = dev if isinstance(dev, ReportsRejected) else None
        self._hand = dev if isinstance(dev, VirtualHand) else None
        self._link_stats = dev if isinstance(dev, KeepsStats) else None
        self.teleop = Teleop(config, self.device.name)
        self.passivity: MasterTdpa | None = None
        if force_hook is None and config.passivity:
            self.passivity = MasterTdpa(
                node,
                config.master_id,
                lambda: self.teleop.engage,
                device_mass_kg=config.passivity_device_mass_kg,
                force_scale=config.force_scale,
                show_moments=config.passivity_moments,
                device_inertia_kg_m2=config.passivity_device_inertia_kg_m2,
            )
            force_hook = self.passivity.hook
        self.force_display = ForceDisplay(config, force_hook)
        self._cmd = node.publisher(keys.CMD)
        self._state = node.publisher(keys.MASTER_STATE)
        self._fb = node.publisher(keys.MASTER_FEEDBACK)
        # Read when the loop displays force (its rate, not the sensor's 1 kHz): no Python
        # work per sample (`Node.latest`); subscribed only while the station is not idle.
        self._force = node.latest(keys.FORCE, watch=False)
        self._robot = node.latest(keys.STATE)
        self._notice: tuple[str, str] | None = None
        self._notice_engage = 0
        self._grip: float | None = None
        self._clutched = False
        self.holds = 0
        self.reengages = 0
        self.last_hold: str | None = None
        self._held_engage = -1
        self._hold_lock = threading.Lock()
        # the decision's holds of this master, and its advice for a terminal's status line
        node.subscribe(keys.EVENTS, self._on_event)
        self._stop = threading.Event()
        self._device_ok = True
        self._reopen_at = 0.0
        self._reopen_wait_s = REOPEN_FIRST_S
        self.reopens = 0
        self._stale = True
        self._fb_seq = 0
        self.ticks = 0
        self.displayed = ForceFeedback.zero()
        self.service_name = f"master/{config.master_id}"
        node.serve(
            self.service_name,
            {
                "status": self._rpc_status,
                "set_scale": self._rpc_set_scale,
                "set_frame": self._rpc_set_frame,
                "set_hand": self._rpc_set_hand,
            },
        )
        self._rate = RateLoop(self.config.rate_hz, on_late=self._on_late)
        self._thread = threading.Thread(target=self._loop, name="master-loop", daemon=True)
        self._thread.start()
        node.announce()

    # --- the loop (owns the device) -------------------------------------------------
    def _loop(self) -> None:
        rate = self._rate
        state_every = max(1, round(self.config.rate_hz / STATE_RATE_HZ))
        last = time.perf_counter()
        try:
            while not self._stop.is_set():
                now = time.perf_counter()
                dt, last = now - last, now
                # robot/force only while the station may engage: an idle virtual master
                # (nobody at the console) asks for none, so none is sent for it.
                self._force.watch(not self._idle())
                self._tick(dt)
                if self.ticks % state_every == 0:
                    self._publish_state()
                self.ticks += 1
                if self._idle():
                    wake = self._wake
                    (wake or self._stop).wait(1.0 / IDLE_RATE_HZ)
                    if wake is not None:
                        wake.clear()
                    rate.set_rate(self.config.rate_hz)  # a fresh schedule, not a late one
                    if self.ticks % state_every:
                        self._publish_state()  # master/state with every slow tick
                    continue
                rate.sleep()
        finally:
            self._hold()

    def _idle(self) -> bool:
        """Not engaged, on a device that may idle (it wakes the loop on any input), and
        clutched or not to engage by itself: nothing to stream but the contract's 50 Hz."""
        return (
            self._wake is not None
            and (self._clutched or not self.config.engage_on_start)
            and (not self.teleop.engaged)
        )

    def _tick(self, dt_s: float) -> None:
        t_ns = time.time_ns()
        try:
            if not self._device_ok:
                self._reopen()
            reading = self.device.read(dt_s)
        except (DeviceLost, TelerobotError, OSError) as e:
            self._report_rejected()
            if self._device_ok:
                self._device_ok = False
                self._reopen_wait_s = REOPEN_FIRST_S
                self._reopen_at = time.monotonic() + self._reopen_wait_s
                self.node.event(
                    "error",
                    f"master device {self.device.name} lost: {e}",
                    {"device": self.device.name},
                )
            self._cmd.put(self.teleop.hold(t_ns, rearm=False))
            self.displayed = ForceFeedback.zero()
            return
        self._report_rejected()
        self._grip = reading.grip
        self._clutched = bool(reading.clutch)
        self._cmd.put(self.teleop.tick(reading, t_ns))
        self._display_force(reading, dt_s)

    def _reopen(self) -> None:
        now = time.monotonic()
        if now < self._reopen_at:
            raise DeviceLost("waiting to reopen")
        self._reopen_wait_s = min(2.0 * self._reopen_wait_s, REOPEN_MAX_S)
        self._reopen_at = now + self._reopen_wait_s
        self.device.close()
        self.device.open()
        self._device_ok = True
        self.reopens += 1
        self.node.event(
            "status",
            f"master device {self.device.name} back; press and release the master-shift to engage",
            {"device": self.device.name},
        )

    def _report_rejected(self) -> None:
        """Count and report (rate-limited) what the device refused from its own link."""
        if self._rejects is not None:
            for reason in self._rejects.take_rejected():
                self.node.report_rejected(f"master/{self.config.master_id}/device", reason)

    def _display_force(self, reading: HandReading, dt_s: float) -> None:
        f_read, s_read = self._force.read(), self._robot.read()
        sample = f_read[0] if f_read is not None else None
        state = s_read[0] if s_read is not None else None
        # Stale by *arrival* on this host's monotonic clock, not by the sample's `t_ns`: that
        # is the robot host's clock, and over a link of 200 ms round trip every sample is
        # 100 ms old on arrival (the display stayed zero: no force feedback at all beyond
        # ~150 ms). The link's delay is TDPA's business; a stream that stops is this one's.
        stale = (
            f_read is None
            or state is None
            or time.monotonic_ns() - f_read[1] > self.config.force_stale_ms * 1e6
        )
        measured = (
            None
            if stale or sample is None or state is None
            else (
                sample.f,
                sample.c,
                state.tool_R,
            )
        )
        shown = self.force_display.update(
            measured, self.teleop.frame, self.teleop.engaged, reading, dt_s, time.monotonic()
        )
        if self.device.can_display_force:
            self.device.display_force(shown.f, shown.c)
        self.displayed = shown
        self._stale = stale

    def _on_event(self, ev: Event) -> None:
        """The decision's word about this master: a hold of its engagement (logged, counted
        in `status`, and re-engaged after when REENGAGE_AFTER says so), and its last advice
        (a hold, a refusal, a limit) for a terminal's status line; a new engagement clears
        that."""
        if ev.source != "decision":
            return
        data = ev.data or {}
        about = data.get("master")
        if about == self.config.master_id:
            self._on_hold(ev, data)
        if (
            self._status_view is not None
            and ev.kind in ADVICE
            and about in (None, self.config.master_id)
        ):
            self._notice = (ev.kind, ev.message)
            self._notice_engage = self.teleop.state(0).engage

    def _on_hold(self, ev: Event, data: dict[str, Any]) -> None:
        """A watchdog hold of this master's engagement, or the decision saying the
        engagement it still streams was held (the hold's own event may have been
        rate-limited away): said once per engagement. Re-engaged after only on the live
        watchdog event (REENGAGE_FRESH_NS) for a gap in the stream (REENGAGE_AFTER)."""
        engage, reason = data.get("engage"), data.get("reason")
        if ev.kind == "watchdog":
            why = reason
        elif ev.kind == "lease" and reason == "engagement_held":
            why = data.get("held_by")
        else:
            return
        if not isinstance(engage, int) or isinstance(engage, bool):
            return
        with self._hold_lock:
            if engage <= self._held_engage:
                return
            self._held_engage = engage
            self.holds += 1
            self.last_hold = str(why)[:64] if why is not None else "held"
        log.warning("the decision held engagement %d: %s", engage, ev.message[:200])
        live = ev.kind == "watchdog" and abs(time.time_ns() - ev.t_ns) < REENGAGE_FRESH_NS
        if live and why in REENGAGE_AFTER and self.config.reengage and self.teleop.reengage(engage):
            with self._hold_lock:
                self.reengages += 1
            log.info("re-engaging after the hold: the device still asks to move")

    def _show_status(self) -> None:
        show = self._status_view
        if show is None:
            return
        engaged = self.teleop.engaged
        state = self.teleop.state(0)
        if engaged and self._notice is not None and state.engage > self._notice_engage:
            self._notice = None  # a new engagement since: the news is history
        show.show_status(
            StatusInfo(
                device=self.device.name,
                engaged=engaged,
                scale_t=state.scale_t,
                scale_r=state.scale_r,
                frame=state.frame,
                grip=self._grip,
                notice=self._notice,
            )
        )

    def _publish_state(self) -> None:
        self._show_status()
        t_ns = time.time_ns()
        self._state.put(self.teleop.state(t_ns))
        self._fb_seq += 1
        shown = self.displayed
        self._fb.put(
            MasterFeedback(
                seq=self._fb_seq,
                t_ns=t_ns,
                master=self.config.master_id,
                f=vec(shown.f),
                c=vec(shown.c),
                saturated=bool(shown.force_saturated or shown.torque_saturated),
                stale=self._stale,
            )
        )

    def _hold(self) -> None:
        """Disengage on the way out: the slave holds (sent a few times: one may be lost)."""
        for _ in range(HOLD_REPEATS):
            try:
                self._cmd.put(self.teleop.hold(time.time_ns()))
            except Exception:  # closing: a failed put must not hide the others
                log.warning("could not send the hold command", exc_info=True)

    def _on_late(self, late_s: float, n_late: int) -> None:
        log.warning("master loop late by up to %.1f ms (%d late ticks)", late_s * 1e3, n_late)

    # --- methods --------------------------------------------------------------------
    def _status(self) -> dict[str, Any]:
        return {
            "master": self.config.master_id,
            "device": self.device.name,
            "device_ok": self._device_ok,
            "engaged": self.teleop.engaged,
            "engage": self.teleop.engage,
            "frame": self.teleop.frame,
            "scale_t": self.teleop.scale_t,
            "scale_r": self.teleop.scale_r,
            "rate_hz": self.config.rate_hz,
            "can_display_force": self.device.can_display_force,
            "ticks": self.ticks,
            "reopens": self.reopens,
            "holds": self.holds,
            "reengages": self.reengages,
            "last_hold": self.last_hold,
            "loop": self._rate.stats(),
            **self._device_stats(),
        }

    def _rpc_status(self, args: dict[str, Any]) -> dict[str, Any]:
        return self._status()

    def _rpc_set_scale(self, args: dict[str, Any]) -> dict[str, Any]:
        st = codec.arg(args, "scale_t", float, None)
        sr = codec.arg(args, "scale_r", float, None)
        try:
            self.teleop.set_scale(scale_t=st, scale_r=sr)
        except ValueError as e:
            raise RpcError("bad_request", str(e)) from None
        return self._status()

    def _rpc_set_frame(self, args: dict[str, Any]) -> dict[str, Any]:
        frame = codec.arg(args, "frame", str)
        try:
            self.teleop.set_frame(frame)
        except ValueError as e:
            raise RpcError("bad_request", str(e)) from None
        return self._status()

    def _rpc_set_hand(self, args: dict[str, Any]) -> dict[str, Any]:
        if self._hand is None:
            raise RpcError("bad_request", f"device {self.device.name} is not a virtual master")
        p = codec.arg(args, "p", Vec3)
        R = codec.arg(args, "R", Rot, None)
        clutch = codec.arg(args, "clutch", bool, False)
        grip = codec.arg(args, "grip", Unit, None)
        self._hand.set_hand(
            p, None if R is None else [R[0:3], R[3:6], R[6:9]], clutch=clutch, grip=grip
        )
        return {}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if self._thread.is_alive():
            self._hold()
        self.device.close()

    def _device_stats(self) -> dict[str, Any]:
        """A backend's link counters (`stats`, a dataclass), when it keeps some."""
        stats = self._link_stats.stats if self._link_stats is not None else None
        if stats is None or not is_dataclass(stats) or isinstance(stats, type):
            return {}
        return {"device_stats": asdict(stats)}
