"""A fake Haply Inverse Service: the simulation channel, message for message, on loopback.

It speaks what `protocol` reads (docs/master.md lists each message's source): on
connect one inventory (`session_id`, an `inverse3` list and a `wireless_verse_grip` list,
each device with `device_id`, `config`, `state`, `status`), then exactly one state update
(the same lists without `config`) per message received, whatever the message. It applies
`set_cursor_force` to its Inverse3 and records every force it receives, and records the
session profile names.

Tests script it: the cursor position, the grip's quaternion and buttons (or a motion, a
function of time), raw frames to send instead of the next state updates (hostile input),
an abrupt drop of every connection, a mute mode (messages received, none answered) and a
"down" mode that hangs up on new connections.
`telerobot haply-fake` (or `python -m services.control.master.devices.haply.fake`) runs
it by hand, with a scripted hand, so the backend can be tried without the device.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import importlib
import json
import math
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from services.control.master.devices.haply.protocol import (
    GRIP_LIST,
    INVERSE3_LIST,
    MAX_MESSAGE_BYTES,
)
from services.geometry import V3, Quat

_HISTORY = 100_000
"""Forces remembered (about 17 min at 100 Hz); `forces_received` counts them all."""


@dataclass(frozen=True, slots=True)
class HandPose:
    """What the operator does at one instant: cursor (m, Haply frame), grip quaternion
    (w, x, y, z) and buttons a, b, c."""

    cursor_m: V3 = (0.0, -0.12, 0.15)
    orientation_wxyz: Quat = (1.0, 0.0, 0.0, 0.0)
    a: bool = False
    b: bool = False
    c: bool = False


Motion = Callable[[float], HandPose]


@dataclass(frozen=True, slots=True)
class ReceivedForce:
    """One `set_cursor_force` received: its number n (1, 2, … since start), when
    (time.monotonic()), for which device, the force in N."""

    n: int
    t_s: float
    device_id: str
    force_n: V3


def _dig(value: Any, *keys: str) -> Any:
    """value[k1][k2]…, or None where a level is missing or not an object."""
    for key in keys:
        if not isinstance(value, dict):
            return None
        value = value.get(key)
    return value


def _xyz(v: Sequence[float]) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


class FakeInverseService:
    """Serve the simulation channel on ws://127.0.0.1:PORT; a context manager, or
    start()/stop(). All setters and readers are thread-safe."""

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        session_id: int = 7,
        inverse3_id: str = "049D",
        grip_id: str = "A1B2",
        with_grip: bool = True,
        pose: HandPose | None = None,
    ) -> None:
        self._host = host
        self._port = port
        self._lock = threading.Lock()
        self._first_session = session_id
        self._inverse3_id = inverse3_id
        self._grip_id = grip_id
        self._with_grip = with_grip
        self._pose = pose or HandPose()
        self._motion: Motion | None = None
        self._t0 = time.monotonic()
        self._force: V3 = (0.0, 0.0, 0.0)
        self._forces: collections.deque[ReceivedForce] = collections.deque(maxlen=_HISTORY)
        self._n_forces = 0
        self._profiles: list[str] = []
        self._bases: list[str] = []
        self._messages = 0
        self._bad_messages = 0
        self._connections = 0
        self._inject: collections.deque[str] = collections.deque()
        self._down = False
        self._refused = 0
        self._mute = False
        self._live: set[Any] = set()
        self._server: Any = None
        self._closed_errors: tuple[type[BaseException], ...] = (OSError,)
        self._thread: threading.Thread | None = None

    # --- life cycle -------------------------------------------------------------------
    def start(self) -> FakeInverseService:
        server = importlib.import_module("websockets.sync.server")
        errors = importlib.import_module("websockets.exceptions")
        self._closed_errors = (errors.ConnectionClosed, OSError)
        self._server = server.serve(
            self._handle,
            self._host,
            self._port,
            max_size=MAX_MESSAGE_BYTES,
            compression=None,
            ping_interval=None,
        )
        self._port = int(self._server.socket.getsockname()[1])
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="fake-inverse-service", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._server is None:
            return
        self._server.shutdown()
        self.drop()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._server = None

    def __enter__(self) -> FakeInverseService:
        return self.start()

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    @property
    def port(self) -> int:
        return self._port

    @property
    def url(self) -> str:
        return f"ws://{self._host}:{self._port}"

    # --- scripting --------------------------------------------------------------------
    def set_pose(self, **changes: Any) -> None:
        """Change fields of the hand pose: cursor_m, orientation_wxyz, a, b, c."""
        with self._lock:
            fields = {k: getattr(self._pose, k) for k in HandPose.__slots__}
            fields.update(changes)
            self._pose = HandPose(**fields)

    def set_motion(self, motion: Motion | None) -> None:
        """Drive the hand by motion(t_s) (t_s since now) instead of set_pose; None to stop."""
        with self._lock:
            self._motion = motion
            self._t0 = time.monotonic()

    def inject(self, *frames: str) -> None:
        """Send these raw texts instead of the next state updates, one per client message."""
        with self._lock:
            self._inject.extend(frames)

    def drop(self) -> None:
        """Cut every open connection at once, without a WebSocket close (a service crash)."""
        with self._lock:
            live = list(self._live)
        for conn in live:
            with contextlib.suppress(OSError):  # already gone
                conn.socket.shutdown(socket.SHUT_RDWR)

    def set_mute(self, mute: bool) -> None:
        """While mute, client messages are received (and applied) but not answered."""
        with self._lock:
            self._mute = mute

    def set_down(self, down: bool) -> None:
        """While down, every connection is cut as soon as it opens (no inventory)."""
        with self._lock:
            self._down = down
        if down:
            self.drop()

    # --- what it received -------------------------------------------------------------
    def set_grip_present(self, present: bool) -> None:
        """Whether the VerseGrip is in the frames (a flat battery takes it out)."""
        with self._lock:
            self._with_grip = present

    @property
    def forces(self) -> list[ReceivedForce]:
        """The latest forces received, oldest first."""
        with self._lock:
            return list(self._forces)

    @property
    def forces_received(self) -> int:
        with self._lock:
            return self._n_forces

    @property
    def profiles(self) -> list[str]:
        """Session profile names received (session.configure.profile.name)."""
        with self._lock:
            return list(self._profiles)

    @property
    def bases(self) -> list[str]:
        """Basis permutations received (session.configure.basis.permutation)."""
        with self._lock:
            return list(self._bases)

    @property
    def messages(self) -> int:
        """Client messages received (each answered by one state update)."""
        with self._lock:
            return self._messages

    @property
    def bad_messages(self) -> int:
        """Client messages that were not JSON objects or named an unknown device."""
        with self._lock:
            return self._bad_messages

    @property
    def connections(self) -> int:
        """Connections accepted so far."""
        with self._lock:
            return self._connections

    @property
    def refused(self) -> int:
        """Connections hung up on while down."""
        with self._lock:
            return self._refused

    def forces_since(self, n: int) -> list[ReceivedForce]:
        """The forces received after the n-th (those still remembered)."""
        with self._lock:
            return [r for r in self._forces if r.n > n]

    @property
    def connected(self) -> int:
        """Connections open now."""
        with self._lock:
            return len(self._live)

    # --- the protocol -----------------------------------------------------------------
    def _handle(self, conn: Any) -> None:
        with self._lock:
            if self._down:
                self._refused += 1
                conn.socket.shutdown(socket.SHUT_RDWR)
                return
            self._live.add(conn)
            self._connections += 1
            session_id = self._first_session + self._connections - 1
        try:
            conn.send(json.dumps(self._frame(session_id, inventory=True)))
            for raw in conn:
                reply = self._answer(raw, session_id)
                if reply is not None:
                    conn.send(reply)
        except self._closed_errors:
            pass  # the peer went away or was cut: this session ends
        finally:
            with self._lock:
                self._live.discard(conn)

    def _answer(self, raw: str | bytes, session_id: int) -> str | None:
        try:
            message = json.loads(raw)
        except ValueError:
            message = None
        with self._lock:
            self._messages += 1
            if not isinstance(message, dict):
                self._bad_messages += 1
            else:
                self._apply(message)
            if self._mute:
                return None
            if self._inject:
                return self._inject.popleft()
        return json.dumps(self._frame(session_id, inventory=False))

    def _apply(self, message: dict[str, Any]) -> None:
        """Apply one client message (the lock is held)."""
        name = _dig(message, "session", "configure", "profile", "name")
        if isinstance(name, str):
            self._profiles.append(name)
        permutation = _dig(message, "session", "configure", "basis", "permutation")
        if isinstance(permutation, str):
            self._bases.append(permutation)
        entries = message.get(INVERSE3_LIST)
        for entry in entries if isinstance(entries, list) else []:
            values = _dig(entry, "commands", "set_cursor_force", "values")
            try:
                if _dig(entry, "device_id") != self._inverse3_id:
                    raise ValueError("unknown device")
                force = (float(values["x"]), float(values["y"]), float(values["z"]))
            except (TypeError, KeyError, ValueError):
                self._bad_messages += 1
                continue
            self._force = force
            self._n_forces += 1
            self._forces.append(
                ReceivedForce(self._n_forces, time.monotonic(), self._inverse3_id, force)
            )

    def _hand(self) -> HandPose:
        with self._lock:
            motion, pose, t0 = self._motion, self._pose, self._t0
        return pose if motion is None else motion(time.monotonic() - t0)

    def _frame(self, session_id: int, inventory: bool) -> dict[str, Any]:
        hand = self._hand()
        with self._lock:
            force, with_grip = self._force, self._with_grip
        inverse3: dict[str, Any] = {
            "device_id": self._inverse3_id,
            "state": {
                "cursor_position": _xyz(hand.cursor_m),
                "cursor_velocity": _xyz((0.0, 0.0, 0.0)),
                "current_cursor_force": _xyz(force),
                "control_domain": "cartesian",
                "control_mode": "force" if any(force) else "idle",
            },
            "status": {"calibrated": True, "in_use": True, "ready": True, "started": True},
        }
        frame: dict[str, Any] = {"session_id": session_id, INVERSE3_LIST: [inverse3]}
        grips = []
        if with_grip:
            w, x, y, z = hand.orientation_wxyz
            grips.append(
                {
                    "device_id": self._grip_id,
                    "state": {
                        "orientation": {"w": w, "x": x, "y": y, "z": z},
                        "buttons": {"a": hand.a, "b": hand.b, "c": hand.c},
                    },
                    "status": {},
                }
            )
        frame[GRIP_LIST] = grips
        if inventory:
            inverse3["config"] = {
                "type": "inverse3",
                "device_info": {"id": self._inverse3_id, "device_type": 4},
                "handedness": "right",
                "basis": {"permutation": "XYZ"},
                "mount": {
                    "position": _xyz((0.0, 0.0, 0.0)),
                    "rotation": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
                    "scale": _xyz((1.0, 1.0, 1.0)),
                },
            }
            for grip in grips:
                grip["config"] = {"type": GRIP_LIST}
        return frame


def demo_motion(period_s: float = 8.0, radius_m: float = 0.03) -> Motion:
    """A hand for trying the backend by hand: `a` held while the cursor goes round a circle
    of `radius_m` (x-y) with the grip turning about z, then released for a quarter period
    while the cursor comes back (a master-shift: the slave holds)."""

    def motion(t_s: float) -> HandPose:
        phase = (t_s % period_s) / period_s
        held = phase < 0.75
        angle = 2.0 * math.pi * phase / 0.75 if held else 0.0
        twist = 0.3 * math.sin(angle)
        cursor = (radius_m * math.sin(angle), -0.12 + radius_m * (1.0 - math.cos(angle)), 0.15)
        return HandPose(cursor, (math.cos(twist / 2), 0.0, 0.0, math.sin(twist / 2)), a=held)

    return motion


def main(argv: list[str] | None = None) -> int:
    """`telerobot haply-fake`: serve a fake Inverse Service until Ctrl-C."""
    p = argparse.ArgumentParser(prog="telerobot haply-fake", description=__doc__)
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=10001, help="the Inverse Service's port")
    p.add_argument(
        "--motion",
        choices=["still", "circle"],
        default="circle",
        help="still: cursor at rest, nothing pressed; circle: a scripted operator (a held)",
    )
    args = p.parse_args(argv)
    fake = FakeInverseService(host=args.host, port=args.port)
    if args.motion == "circle":
        fake.set_motion(demo_motion())
    from services.bus.lifecycle import Shutdown

    stop = Shutdown()
    with fake:
        print(f"fake Haply Inverse Service on {fake.url} (Ctrl-C to stop)", flush=True)
        seen = 0
        while not stop.wait(1.0):
            recent = fake.forces_since(seen)
            if recent:
                peak = max(math.hypot(*r.force_n) for r in recent)
                print(
                    f"{fake.connected} client(s), {len(recent)} forces/s, peak {peak:.2f} N",
                    flush=True,
                )
                seen = recent[-1].n
    return 0


if __name__ == "__main__":
    sys.exit(main())
