"""A fake serial master arm that speaks docs/serial-master-protocol.md byte for byte.

It listens on TCP 127.0.0.1 (a free port), so `SerialMasterArm("socket://127.0.0.1:PORT")`
talks to it through pyserial exactly as to the real arm on a UART. Joint motion is
scriptable (fixed angles or a function of time), buttons and grip can be set, received
torques are recorded, and faults (corrupted CRCs, silence) can be injected. It also runs the
arm-side torque watchdog the protocol requires.
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence

from services.bus.loopback import LoopbackServer
from services.control.master.devices.master_arm.protocol import (
    N_JOINTS,
    SEQ_MODULO,
    Identity,
    JointFrame,
    LineError,
    LineSplitter,
    TorqueFrame,
    encode_line,
    parse_line,
)

Motion = Callable[[float], Sequence[float]]
_HISTORY = 100_000
"""Joint frames remembered (about 17 min at 100 Hz)."""


class FakeMasterArm(LoopbackServer):
    """Serve one master arm on `url`; use as a context manager or start()/stop()."""

    def __init__(
        self,
        *,
        q_rad: Sequence[float] = (0.0, math.pi / 2, 0.0, 0.0, 0.0, 0.0),
        model: str = "fake-arm",
        firmware: str = "1.0",
        n_joints: int = N_JOINTS,
        torque_watchdog_s: float = 0.25,
    ) -> None:
        self._lock = threading.Lock()
        self._motion: Motion = _constant(q_rad)
        self._buttons = 0
        self._grip: float | None = None
        self._identity = Identity(model, firmware, n_joints)
        self._watchdog_s = torque_watchdog_s
        self._corrupt = 0
        self._silent = False
        self._torques: list[TorqueFrame] = []
        self._tau = (0.0,) * N_JOINTS
        self._tau_t = 0.0
        self._sent: deque[JointFrame] = deque(maxlen=_HISTORY)
        self._commands: list[str] = []
        self._naks_sent = 0
        super().__init__("tcp", 0, "fake-master-arm")

    def stop(self) -> None:
        """The same as `close()`."""
        self.close()

    def set_joints(self, q_rad: Sequence[float]) -> None:
        """Hold the joints at q_rad (6 angles, rad)."""
        with self._lock:
            self._motion = _constant(q_rad)

    def set_motion(self, motion: Motion) -> None:
        """Joint angles as a function of the time (s) since streaming started."""
        with self._lock:
            self._motion = motion

    def set_buttons(self, buttons: int) -> None:
        with self._lock:
            self._buttons = buttons

    def set_grip(self, grip: float | None) -> None:
        with self._lock:
            self._grip = grip

    def corrupt_next(self, n_frames: int) -> None:
        """Send the next n joint frames with a wrong CRC."""
        with self._lock:
            self._corrupt = n_frames

    def set_silent(self, silent: bool) -> None:
        """Stop (True) or resume (False) sending joint frames, as a cut line would."""
        with self._lock:
            self._silent = silent

    @property
    def torques(self) -> list[TorqueFrame]:
        """Every torque frame received, in order."""
        with self._lock:
            return list(self._torques)

    @property
    def applied_torque_nm(self) -> tuple[float, ...]:
        """The torques the motors would apply now (zero after the watchdog fired)."""
        with self._lock:
            return self._tau

    @property
    def sent(self) -> list[JointFrame]:
        """The joint frames sent (as decoded by the host, i.e. quantised), oldest first."""
        with self._lock:
            return list(self._sent)

    @property
    def commands(self) -> list[str]:
        """Types of every valid host line received, in order (e.g. ['X', 'I', 'S', 'T'])."""
        with self._lock:
            return list(self._commands)

    @property
    def naks_sent(self) -> int:
        with self._lock:
            return self._naks_sent

    def _session(self, conn: socket.socket) -> None:
        splitter = LineSplitter()
        rate_hz = 0.0
        t0 = next_t = 0.0
        seq = 0
        while not self._closed.is_set():
            now = time.monotonic()
            wait = 0.05 if rate_hz <= 0.0 else max(0.0, min(0.05, next_t - now))
            readable, _, _ = select.select([conn], [], [], wait)
            if readable:
                try:
                    data = conn.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                for line in splitter.feed(data):
                    reply, new_rate = self._handle(line, rate_hz)
                    if new_rate != rate_hz:
                        rate_hz = new_rate
                        t0 = next_t = time.monotonic()
                    if reply and not self._send(conn, reply):
                        return
            now = time.monotonic()
            self._run_watchdog(conn, now)
            if rate_hz > 0.0 and now >= next_t:
                next_t += 1.0 / rate_hz
                if next_t < now:
                    next_t = now + 1.0 / rate_hz
                frame_line = self._joint_line(seq, now - t0)
                if frame_line is not None:
                    seq = (seq + 1) % SEQ_MODULO
                    if not self._send(conn, frame_line):
                        return

    @staticmethod
    def _send(conn: socket.socket, data: bytes) -> bool:
        try:
            conn.sendall(data)
        except OSError:
            return False
        return True

    def _handle(self, line: bytes, rate_hz: float) -> tuple[bytes | None, float]:
        """One host line → (reply or None, new stream rate)."""
        try:
            kind, fields = parse_line(line)
            if kind == "I" and not fields:
                reply: bytes | None = self._identity.encode()
            elif kind == "S" and len(fields) == 1:
                rate = int(fields[0])
                if not 1 <= rate <= 1000:
                    raise LineError("range", "rate out of 1 … 1000")
                reply, rate_hz = encode_line("A", ["S"]), float(rate)
            elif kind == "X" and not fields:
                reply, rate_hz = encode_line("A", ["X"]), 0.0
                self._zero_torque()
            elif kind == "Z" and not fields:
                reply = encode_line("A", ["Z"])
                self._zero_torque()
            elif kind == "T":
                frame = TorqueFrame.decode(fields)
                with self._lock:
                    self._torques.append(frame)
                    self._tau = frame.tau_nm
                    self._tau_t = time.monotonic()
                reply = None
            else:
                raise LineError("unknown", f"unknown command {kind}")
        except LineError as exc:
            with self._lock:
                self._naks_sent += 1
            return encode_line("N", [exc.reason]), rate_hz
        except ValueError:
            with self._lock:
                self._naks_sent += 1
            return encode_line("N", ["syntax"]), rate_hz
        with self._lock:
            self._commands.append(kind)
        return reply, rate_hz

    def _zero_torque(self) -> None:
        with self._lock:
            self._tau = (0.0,) * N_JOINTS

    def _run_watchdog(self, conn: socket.socket, now: float) -> None:
        with self._lock:
            fire = any(self._tau) and now - self._tau_t > self._watchdog_s
            if fire:
                self._tau = (0.0,) * N_JOINTS
        if fire:
            self._send(conn, encode_line("W"))

    def _joint_line(self, seq: int, t_s: float) -> bytes | None:
        with self._lock:
            if self._silent:
                return None
            q = tuple(float(v) for v in self._motion(t_s))
            frame = JointFrame(seq, q, self._buttons, self._grip)
            line = frame.encode()
            # Keep what the host will decode (angles quantised to the wire's 0.1 mrad).
            self._sent.append(JointFrame.decode(parse_line(line)[1]))
            if self._corrupt > 0:
                self._corrupt -= 1
                star = line.rfind(b"*")
                bad_crc = (int(line[star + 1 : star + 5], 16) ^ 0x5A5A) & 0xFFFF
                line = line[: star + 1] + f"{bad_crc:04X}".encode() + b"\r\n"
        return line


def _constant(q_rad: Sequence[float]) -> Motion:
    q = tuple(float(v) for v in q_rad)
    if len(q) != N_JOINTS:
        raise ValueError("q_rad must have 6 joints")
    return lambda _t: q
