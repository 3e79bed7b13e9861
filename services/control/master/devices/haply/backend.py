"""The Haply Inverse3 (3-DoF force display) with its wireless VerseGrip, as a `MasterDevice`.

It talks to the Haply Inverse Service (the Haply Hub runs it on the operator's machine) over
the service's simulation channel, a WebSocket carrying JSON (`protocol`). The service
answers every client message with exactly one state frame, so the master's loop sets the
rate: each `read` sends one `set_cursor_force` (the force `display_force` asked for during
the previous tick, else zero: the keepalive) and waits briefly for a state frame; a second
message may go before the first is answered, never a third (`MAX_IN_FLIGHT`).

Hand pose: the Inverse3 cursor is the hand position, the VerseGrip quaternion its
orientation, both in Haply's frame (+x right, +y away from the operator, +z up), which is
the desk master frame of docs/master.md. VerseGrip button `a` (by default) is a dead-man:
held = engaged, released = master-shift. Button `b` toggles the grip.

Only the master service's loop thread calls the methods (franka-node's rule). The
`websockets` package is imported when the device opens, as the other backends import
theirs, so simulation and the tests of pure logic never load it.
"""

from __future__ import annotations

import collections
import contextlib
import importlib
import logging
import math
import time
import urllib.parse
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.errors import ProtocolError
from services.control.master.config import check_buttons, option_error, positive, string
from services.control.master.device import (
    DeviceLost,
    DeviceNotFound,
    DeviceOptions,
    HandReading,
    MasterDevice,
)
from services.control.master.devices.haply.protocol import (
    BUTTONS,
    DEFAULT_URL,
    MAX_MESSAGE_BYTES,
    ServiceFrame,
    force_message,
    parse_frame,
)
from services.control.master.feedback import saturate
from services.geometry import R_from_wxyz, rotation_angle

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig

log = logging.getLogger("telerobot.master.haply")

SESSION_PROFILE = "org.telerobot.master"
"""How our session is named in the Haply Hub (session.configure.profile.name)."""

_REJECT_NOTES = 64
"""Rejection reasons kept for the service to report; older ones are dropped (still counted)."""

MAX_IN_FLIGHT = 2
"""Messages sent and not yet answered, at most: one late state frame does not cost a tick's
force; a service further behind is not flooded (those ticks are counted `skipped`)."""

_MAX_DRAIN = 8
"""Frames taken per read at most: a service that floods frames cannot hold the loop."""

_ZERO3: NDArray[np.float64] = np.zeros(3)


@dataclass(frozen=True, slots=True)
class HaplyStats:
    """Counters since open(): state frames accepted, frames rejected (malformed, missing
    our device, non-finite, absurd), jumps (a cursor or grip step faster than a hand can
    move: read as a master-shift for one tick), late (reads that got no state frame within
    `reply_timeout_s`), skipped (reads that sent nothing because two messages were still
    unanswered), forces sent, and the largest force magnitude sent (N)."""

    frames: int = 0
    rejected: int = 0
    jumps: int = 0
    late: int = 0
    skipped: int = 0
    forces_sent: int = 0
    max_force_sent_n: float = 0.0


@dataclass(frozen=True, slots=True)
class HaplyOptions(DeviceOptions):
    """`device = "haply"`: its `[master]` keys.

    haply_url: the Inverse Service's WebSocket, `ws://HOST:PORT`.
    haply_max_force_n: the largest force ever sent to the Inverse3 (N).
    clutch_button, grip_button: VerseGrip button bits, 0, 1, 2 = a, b, c. The clutch button
        is a dead-man: held = engaged, released = master-shift; the grip button toggles.
    """

    haply_url: str = DEFAULT_URL
    haply_max_force_n: float = 3.0
    clutch_button: int = 0
    grip_button: int = 1

    def __post_init__(self) -> None:
        string(self, "haply_url")
        positive(self, "haply_max_force_n")
        check_buttons(self.clutch_button, self.grip_button)
        for key in ("clutch_button", "grip_button"):
            if getattr(self, key) >= len(BUTTONS):
                raise option_error(key, "must be 0, 1 or 2 for haply (VerseGrip a, b, c)")
        try:
            url = urllib.parse.urlsplit(self.haply_url)
            port = url.port
        except ValueError as e:
            raise option_error("haply_url", f"not a URL: {e}") from None
        if url.scheme not in ("ws", "wss") or not url.hostname or port is None:
            raise option_error("haply_url", "must be ws://HOST:PORT (or wss://)")

    def build(self, config: MasterConfig) -> MasterDevice:
        return HaplyMaster(
            self.haply_url,
            deadman_button=self.clutch_button,
            grip_button=self.grip_button,
            max_force_n=self.haply_max_force_n,
        )


class HaplyMaster:
    """The Inverse3 + VerseGrip behind an Inverse Service at `url`.

    deadman_button, grip_button: VerseGrip button bits (0 = a, 1 = b, 2 = c).
    max_force_n: the largest force ever sent to the Inverse3 (direction kept), N.
    inverse3_id, grip_id: which devices to use; "" = the first of each in the inventory.
    open_timeout_s: connecting and waiting for the inventory.
    reply_timeout_s: how long `read` waits for the state frame of its message.
    stale_s: no valid state frame for this long reads as master-shift (the slave holds).
    lost_s: no valid state frame for this long raises DeviceLost (the service reconnects).
    max_speed_m_s, max_rate_rad_s: faster cursor or grip motion between two frames (plus a
        small slack) is not a hand: the reading reports master-shift for that tick, so the
        next engagement starts from the new pose and the slave never jumps.
    """

    def __init__(
        self,
        url: str = DEFAULT_URL,
        *,
        deadman_button: int = 0,
        grip_button: int = 1,
        max_force_n: float = 3.0,
        inverse3_id: str = "",
        grip_id: str = "",
        open_timeout_s: float = 2.0,
        reply_timeout_s: float = 0.005,
        stale_s: float = 0.25,
        lost_s: float = 1.0,
        max_speed_m_s: float = 2.0,
        max_rate_rad_s: float = 20.0,
    ) -> None:
        for bit, key in ((deadman_button, "deadman_button"), (grip_button, "grip_button")):
            if not 0 <= bit < len(BUTTONS):
                raise ValueError(f"{key} must be 0 … {len(BUTTONS) - 1} (VerseGrip a, b, c)")
        if deadman_button == grip_button:
            raise ValueError("grip_button must differ from deadman_button")
        if not max_force_n > 0.0 or not math.isfinite(max_force_n):
            raise ValueError("max_force_n must be > 0")
        if not 0.0 < stale_s < lost_s:
            raise ValueError("need 0 < stale_s < lost_s")
        self._url = url
        self._deadman_mask = 1 << deadman_button
        self._grip_mask = 1 << grip_button
        self._max_force_n = float(max_force_n)
        self._wanted_inverse3 = inverse3_id
        self._wanted_grip = grip_id
        self._open_timeout_s = open_timeout_s
        self._reply_timeout_s = reply_timeout_s
        self._stale_s = stale_s
        self._lost_s = lost_s
        self._max_speed_m_s = max_speed_m_s
        self._max_rate_rad_s = max_rate_rad_s
        self._ws: Any = None
        self._closed_errors: tuple[type[BaseException], ...] = (OSError,)
        self._inverse3_id = ""
        self._grip_id = ""
        self._session_id: int | None = None
        self._reset()

    def _reset(self) -> None:
        self._p = np.zeros(3)
        self._R = np.eye(3)
        self._buttons = 0
        self._has_grip = False
        self._valid_t = time.monotonic()
        self._in_flight = 0
        # When each unanswered message was sent: its reply shows the hand as it was then,
        # however late our loop reads it (a late tick leaves old replies queued).
        self._sent_t: collections.deque[float] = collections.deque(maxlen=64)
        self._pending_f = _ZERO3
        self._jumped = False
        self._engaged_hand = False
        self._grip_toggle = 0.0
        self._prev_buttons = 0
        self._rejected: collections.deque[str] = collections.deque(maxlen=_REJECT_NOTES)
        self._stats: dict[str, Any] = {k: 0 for k in HaplyStats.__slots__}
        self._stats["max_force_sent_n"] = 0.0

    # --- the MasterDevice protocol ----------------------------------------------------
    @property
    def name(self) -> str:
        return f"haply:{self._inverse3_id or '?'}"

    @property
    def can_display_force(self) -> bool:
        return True

    @property
    def stats(self) -> HaplyStats:
        """A snapshot of the link counters."""
        return HaplyStats(**self._stats)

    @property
    def in_flight(self) -> int:
        """Messages sent whose state frame has not been read yet (0 … MAX_IN_FLIGHT)."""
        return self._in_flight

    @property
    def session_id(self) -> int | None:
        """The Inverse Service's session id from the inventory (None if it sent none)."""
        return self._session_id

    def open(self) -> None:
        """Connect, read the inventory, pick the devices and send the first message (session
        profile, Haply's own axes, zero force). DeviceNotFound if any of it fails."""
        client = importlib.import_module("websockets.sync.client")
        errors = importlib.import_module("websockets.exceptions")
        self._closed_errors = (errors.WebSocketException, OSError)
        self._drop()
        self._reset()
        try:
            self._ws = client.connect(
                self._url,
                open_timeout=self._open_timeout_s,
                close_timeout=0.2,
                max_size=MAX_MESSAGE_BYTES,
                # Our own liveness check is one state frame per message; JSON frames of a
                # few hundred bytes on localhost gain nothing from deflate; never a proxy.
                ping_interval=None,
                compression=None,
                proxy=None,
            )
        except (*self._closed_errors, ValueError) as e:
            raise DeviceNotFound(f"no Haply Inverse Service at {self._url}: {e}") from e
        try:
            self._open_session()
        except BaseException:
            self._drop()
            raise

    def _open_session(self) -> None:
        try:
            raw = self._ws.recv(timeout=self._open_timeout_s)
        except TimeoutError:
            raise DeviceNotFound(f"the Inverse Service at {self._url} sent no inventory") from None
        except self._closed_errors as e:
            raise DeviceNotFound(f"the Inverse Service at {self._url} hung up: {e}") from e
        try:
            inventory = parse_frame(raw)
        except ProtocolError as e:
            raise DeviceNotFound(f"bad inventory from {self._url}: {e}") from e
        found = _listing(inventory)
        # The same Inverse3 across reconnects; the grip is picked afresh (a swapped one works).
        wanted = self._wanted_inverse3 or self._inverse3_id
        picked = _pick([c.device_id for c in inventory.inverse3], wanted)
        if not picked:
            raise DeviceNotFound(f"no Inverse3 ({wanted or 'any'}) at {self._url}", found)
        self._inverse3_id, self._grip_id = picked, ""
        self._session_id = inventory.session_id
        self._accept(inventory, time.monotonic(), self._since())
        if not self._has_grip:
            log.warning("no wireless VerseGrip at %s yet: the dead-man cannot engage", self._url)
        configure = {"profile": {"name": SESSION_PROFILE}, "basis": {"permutation": "XYZ"}}
        self._send(_ZERO3, configure)

    def read(self, dt_s: float) -> HandReading:
        """Exchange one message for one state frame; the hand from the newest valid frame.

        Master-shift is reported while the dead-man is released, while no valid frame came
        for `stale_s`, for one tick after a jump, and while no VerseGrip is there.
        """
        if self._ws is None:
            raise DeviceLost("the Haply device is not open")
        try:
            if self._in_flight < MAX_IN_FLIGHT:
                force, self._pending_f = self._pending_f, _ZERO3
                self._send(force)
            else:
                self._stats["skipped"] += 1
            self._receive()
        except self._closed_errors as e:
            self._drop()
            raise DeviceLost(f"Inverse Service at {self._url}: {e}") from e
        age_s = time.monotonic() - self._valid_t
        if age_s > self._lost_s:
            self._drop()
            raise DeviceLost(f"no valid state from the Inverse Service for {age_s:.1f} s")
        buttons = self._buttons if self._has_grip else 0
        if buttons & self._grip_mask and not self._prev_buttons & self._grip_mask:
            self._grip_toggle = 1.0 - self._grip_toggle
        self._prev_buttons = buttons
        clutch = age_s > self._stale_s or self._jumped or not buttons & self._deadman_mask
        self._jumped = False
        self._engaged_hand = not clutch
        return HandReading(self._p, self._R, clutch, self._grip_toggle, buttons)

    def display_force(self, f: ArrayLike, c: ArrayLike) -> None:
        """Push the hand with force f (3, N, master frame = Haply frame) from the next message
        on, cut to `max_force_n` (direction kept). The Inverse3 has no torque on the hand, so
        c is not shown. Zero while the dead-man is released or for a non-finite f."""
        force = np.asarray(f, dtype=float).reshape(3)
        if not np.all(np.isfinite(force)):
            self._reject("display_force: non-finite force, zero shown")
            force = _ZERO3
        elif not self._engaged_hand:
            force = _ZERO3
        else:
            force, _ = saturate(force, self._max_force_n)
        self._pending_f = force

    def close(self) -> None:
        """Send a zero force and close the session (idempotent)."""
        if self._ws is None:
            return
        try:
            self._ws.send(force_message(self._inverse3_id, _ZERO3))
        except self._closed_errors:
            pass  # Already gone: the service stops our session's forces with the socket.
        finally:
            self._drop()

    # --- rejections, for the service to report ------------------------------------------
    def take_rejected(self) -> list[str]:
        """The reasons of the rejections since the last call (at most the last 64)."""
        out = list(self._rejected)
        self._rejected.clear()
        return out

    # --- internals --------------------------------------------------------------------
    def _send(self, force_n: NDArray[np.float64], configure: dict[str, Any] | None = None) -> None:
        self._ws.send(force_message(self._inverse3_id, force_n, configure))
        self._in_flight += 1
        self._sent_t.append(time.monotonic())
        self._stats["forces_sent"] += 1
        norm = float(np.linalg.norm(force_n))
        if norm > self._stats["max_force_sent_n"]:
            self._stats["max_force_sent_n"] = norm

    def _receive(self) -> None:
        """Take the state frame of our oldest unanswered message (waiting up to
        reply_timeout_s), then whatever else has already arrived (at most _MAX_DRAIN).

        Every frame of one drain is checked for jumps against the hand as it was before it
        (`_since`): frames that arrive together after a late tick were answered over that
        whole time, so their steps between each other, timed by their arrival, would read as
        jumps (a master-shift, then a rebase that loses the motion) though the hand moved at
        a hand's speed (fresh-clone CI, 2026-11-26: a 108 ms late tick). A frame that jumped
        is where the hand is now: the frames after it in the drain are judged against it (a
        teleport answered twice is one jump)."""
        timeout = self._reply_timeout_s if self._in_flight else 0.0
        since = self._since()
        for _ in range(_MAX_DRAIN):
            try:
                raw = self._ws.recv(timeout=timeout)
            except TimeoutError:
                if timeout > 0.0:
                    self._stats["late"] += 1
                return
            self._in_flight = max(self._in_flight - 1, 0)
            # the hand as of the request this frame answers (a backlog after a late tick is
            # old hands, then a current one: timed by their reading, the step between them
            # read as a jump; fresh-clone-like parallel pass, 2026-12-02: 3 runs in 5)
            asked = self._sent_t.popleft() if self._sent_t else time.monotonic()
            try:
                frame = parse_frame(raw)
            except ProtocolError as e:
                self._reject(str(e))
            else:
                if self._accept(frame, asked, since):
                    since = self._since()
            timeout = 0.0

    def _since(self) -> tuple[NDArray[np.float64], NDArray[np.float64], float] | None:
        """The hand as the last valid frame gave it, and that frame's time (None before one)."""
        return (self._p, self._R, self._valid_t) if self._stats["frames"] > 0 else None

    def _accept(
        self,
        frame: ServiceFrame,
        now: float,
        since: tuple[NDArray[np.float64], NDArray[np.float64], float] | None,
    ) -> bool:
        """Take a valid frame; a step from `since` (the hand's position, orientation and the
        time of its frame; None for the first) faster than a hand can move is a jump.
        Returns whether it jumped."""
        cursor = frame.cursor(self._inverse3_id)
        if cursor is None:
            self._reject(f"inverse3 {self._inverse3_id} missing from the state frame")
            return False
        if not self._grip_id:
            self._grip_id = _pick([g.device_id for g in frame.grips], self._wanted_grip)
        grip = frame.grip(self._grip_id) if self._grip_id else None
        p = np.array(cursor.position_m)
        R = self._R if grip is None else R_from_wxyz(grip.orientation_wxyz)
        jumped = False
        if since is not None:
            p0, R0, t0 = since
            dt = now - t0
            step_m = float(np.linalg.norm(p - p0))
            turn_rad = rotation_angle(R0.T @ R)
            if step_m > self._max_speed_m_s * dt + 0.005 or (
                turn_rad > self._max_rate_rad_s * dt + 0.05
            ):
                self._stats["jumps"] += 1
                self._jumped = jumped = True
        self._p, self._R = p, R
        self._has_grip = grip is not None
        self._buttons = 0 if grip is None else grip.buttons
        self._valid_t = now
        self._stats["frames"] += 1
        return jumped

    def _reject(self, reason: str) -> None:
        self._stats["rejected"] += 1
        self._rejected.append(reason)

    def _drop(self) -> None:
        ws, self._ws = self._ws, None
        self._in_flight = 0
        self._sent_t.clear()
        if ws is not None:
            with contextlib.suppress(*self._closed_errors):  # a dead socket: nothing to release
                ws.close()


def _listing(frame: ServiceFrame) -> list[str]:
    return [f"inverse3 {c.device_id}" for c in frame.inverse3] + [
        f"wireless_verse_grip {g.device_id}" for g in frame.grips
    ]


def _pick(ids: list[str], wanted: str) -> str:
    """`wanted` if it is among `ids`, the first id when nothing is wanted, else ""."""
    if wanted:
        return wanted if wanted in ids else ""
    return ids[0] if ids else ""
