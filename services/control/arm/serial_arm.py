"""A retrofitted PUMA 560 controller on a serial line (implements `Arm`).

The line protocol is documented in docs/serial-arm-protocol.md: ASCII sentences
`$BODY*HH\\r\\n`, HH the XOR of the BODY bytes, one reply per request. This module holds
the codec (pure functions, shared with the fake controller) and `SerialArm`.

`SerialArm` owns the port through one I/O thread that runs a fixed cycle (28 ms, the
classic PUMA setpoint period, or faster): each cycle it sends the newest setpoint given to
`command()` (`SP`) or, with none, reads the joints (`RJ`), and checks the reply. Any link
fault — a reply that does not come within `timeout_s`, a bad checksum, a malformed or
unexpected reply, a controller error, the port vanishing — puts the arm in `error`: the
thread sends a best-effort `HOLD` and stops streaming, so no setpoint is sent until
`connect()` and `initialize()` succeed again. The controller also holds by itself when
setpoints stop arriving (its watchdog).

pyserial is imported only by `connect()`: the codec and the fake controller do not need it.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.bus.serialport import close_port
from services.control.arm.arm_base import ArmBase
from services.control.arm.driver import ArmError, ArmStatus, Q

MAX_LINE_BYTES = 128
MODEL = "PUMA560"
N_JOINTS = 6
"""The protocol's joint count (docs/serial-arm-protocol.md): this driver is the PUMA 560's."""
CONTROLLER_STATES = ("IDLE", "CAL", "READY", "ESTOP", "FAULT")
ERROR_CODES = ("CHK", "SYNTAX", "UNKNOWN", "STATE", "LIMIT", "STEP", "ESTOP", "FAULT")


class LineError(ValueError):
    """A line that is not a valid sentence: `code` is `CHK` (checksum) or `SYNTAX`."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code


class ControllerError(ArmError):
    """The controller answered `ERR,<code>,<text>`."""

    def __init__(self, code: str, text: str) -> None:
        super().__init__(f"controller error {code}: {text}")
        self.code = code
        self.text = text


class LinkError(ArmError):
    """The link failed: timeout, garbage, unexpected reply, port gone."""


# --- codec ------------------------------------------------------------------------------


def checksum(body: bytes) -> int:
    """XOR of the body bytes (the NMEA 0183 checksum)."""
    c = 0
    for b in body:
        c ^= b
    return c


def encode_line(fields: Sequence[str]) -> bytes:
    """`["SP", "7", ...]` → `b"$SP,7,...*HH\\r\\n"`. Fields must be printable ASCII without
    `$`, `*` or `,`."""
    for f in fields:
        if not f.isascii() or not f.isprintable() or any(c in f for c in "$*,"):
            raise ValueError(f"field {f!r} cannot go into a sentence")
    body = ",".join(fields).encode("ascii")
    line = b"$" + body + b"*" + f"{checksum(body):02X}".encode("ascii") + b"\r\n"
    if len(line) > MAX_LINE_BYTES:
        raise ValueError(f"sentence of {len(line)} bytes is longer than {MAX_LINE_BYTES}")
    return line


def decode_line(raw: bytes) -> list[str]:
    """One received line (with or without its line end) → its fields.

    Raises `LineError("SYNTAX", …)` for a line that is not `$BODY*HH`, `LineError("CHK", …)`
    when HH is not the XOR of BODY.
    """
    line = raw.rstrip(b"\r\n")
    if len(line) > MAX_LINE_BYTES:
        raise LineError("SYNTAX", "line too long")
    if len(line) < 4 or line[:1] != b"$" or line[-3:-2] != b"*":
        raise LineError("SYNTAX", f"not a sentence: {line[:40]!r}")
    body, hh = line[1:-3], line[-2:]
    if any(c not in b"0123456789ABCDEF" for c in hh):
        raise LineError("SYNTAX", f"bad checksum digits {hh!r} (two uppercase hex digits)")
    sent = int(hh.decode("ascii"), 16)
    if sent != checksum(body):
        raise LineError("CHK", f"checksum {hh.decode('ascii')} != {checksum(body):02X}")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise LineError("SYNTAX", "non-ASCII bytes") from None
    if not text.isprintable() or "$" in text or "*" in text:
        raise LineError("SYNTAX", "forbidden characters in the body")
    fields = text.split(",")
    if not fields[0]:
        raise LineError("SYNTAX", "empty sentence type")
    return fields


def format_joints(q: Sequence[float] | Q) -> list[str]:
    """Joint angles (rad) as fixed-point fields, 1 µrad resolution."""
    return [f"{float(x):.6f}" for x in q]


def parse_joints(fields: Sequence[str]) -> Q:
    """N_JOINTS fields → joint angles (rad); `LineError("SYNTAX")` unless N_JOINTS finite
    numbers."""
    if len(fields) != N_JOINTS:
        raise LineError("SYNTAX", f"expected {N_JOINTS} joint values, got {len(fields)}")
    try:
        q = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise LineError("SYNTAX", "joint value is not a number") from None
    if not np.all(np.isfinite(q)):
        raise LineError("SYNTAX", "joint value is not finite")
    return q


def parse_uint(text: str, name: str) -> int:
    if not text.isdigit():
        raise LineError("SYNTAX", f"{name} must be an unsigned integer, got {text!r}")
    return int(text)


def clean_text(text: str) -> str:
    """Free text made safe for a field (no separators), at most 48 characters."""
    out = "".join(c if c.isascii() and c.isprintable() and c not in "$*," else " " for c in text)
    return out.strip()[:48] or "-"


# --- host side ----------------------------------------------------------------------------


@dataclass(slots=True)
class _Request:
    """A one-off exchange the I/O thread performs between two cycles (CAL, HOLD, ESTOP)."""

    fields: list[str]
    expect: str
    done: threading.Event = field(default_factory=threading.Event)
    error: ArmError | None = None


class SerialArm(ArmBase):
    """The PUMA controller at `port` (a device or any pyserial URL, e.g. `socket://…`).

    `cycle_ms` is the setpoint period (≤ 28 ms, ≥ the controller's minimum announced in its
    HELLO); `timeout_s` bounds the wait for each reply. A setpoint given to `command()` is
    streamed until `setpoint_stale_s` has passed without a newer one: then the arm only
    reads the joints and the controller's watchdog holds it.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115_200,
        cycle_ms: float = 28.0,
        timeout_s: float = 0.1,
        setpoint_stale_s: float = 0.25,
    ) -> None:
        if not 0.5 <= cycle_ms <= 28.0:
            raise ValueError("cycle_ms must be within 0.5 … 28 ms")
        if timeout_s <= 0.0 or setpoint_stale_s <= 0.0:
            raise ValueError("timeout_s and setpoint_stale_s must be > 0")
        self.port = port
        self.baudrate = int(baudrate)
        self.cycle_s = cycle_ms / 1000.0
        self.timeout_s = float(timeout_s)
        self.setpoint_stale_s = float(setpoint_stale_s)
        self.n = N_JOINTS
        self._lock = threading.RLock()
        # Whole sentences only: a HOLD written on failure must not split a SP in two.
        self._wlock = threading.Lock()
        self._ser: Any = None
        self._rx = bytearray()
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._wake = threading.Event()
        self._requests: deque[_Request] = deque()
        self._status: ArmStatus = "disconnected"
        self._last_error: str | None = None
        self._q: Q | None = None
        self._setpoint: Q | None = None
        self._setpoint_t = 0.0
        self._seq = 0
        self.controller_id: str | None = None
        self.cycles = 0
        self.setpoints_sent = 0
        self.setpoints_ignored = 0
        self.max_transaction_s = 0.0

    # --- Arm ---------------------------------------------------------------------------

    def preflight(self) -> str | None:
        """What is plainly missing before any byte is sent (a device path that does not
        exist), in words an operator can act on; None when nothing is (URLs are not checked:
        only `connect` can tell whether something answers there)."""
        if "://" in self.port or os.path.exists(self.port):
            return None
        return (
            f"no serial port {self.port}: is the arm controller's cable plugged in and "
            "powered? (set [arm] port or --port; `ls /dev/serial/by-id/` lists what is there)"
        )

    def connect(self) -> None:
        import serial  # lazy: sim and tests of pure logic never load pyserial

        self._stop_thread()
        self._close_port()
        with self._lock:
            self._setpoint = None
            self._requests.clear()
        try:
            try:
                ser = serial.serial_for_url(
                    self.port, baudrate=self.baudrate, timeout=self.timeout_s
                )
            except ValueError as e:
                raise LinkError(f"cannot open {self.port}: {e}") from None
            self._ser = ser
            self._rx.clear()
            ser.reset_input_buffer()
            hello = self._handshake()
            self._transact(["RESET"], "ACK")
        except ArmError as e:
            self._fail(str(e))
            self._close_port()
            raise
        except LineError as e:
            self._fail(f"bad HELLO: {e}")
            self._close_port()
            raise LinkError(f"bad HELLO: {e}") from None
        except OSError as e:  # pyserial's SerialException is an OSError
            self._fail(f"link: {e}")
            self._close_port()
            raise LinkError(f"link: {e}") from None
        with self._lock:
            self.controller_id = ",".join(hello[1:3])
            self._status = "connected"
            self._running.set()
            self._thread = threading.Thread(target=self._run, name="serial-arm", daemon=True)
            self._thread.start()

    def initialize(self) -> None:
        with self._lock:
            self._check_can_initialize()
            self._setpoint = None
        self._request(["CAL"], "ACK")
        with self._lock:
            if self._status in ("connected", "ready"):
                self._status = "initializing"

    def read_joints(self) -> Q:
        with self._lock:
            if self._q is None:
                raise ArmError("joint angles unknown: the arm was never calibrated")
            return self._q.copy()

    def command(self, q_setpoint: Q) -> None:
        with self._lock:
            sp = self._accept_setpoint(q_setpoint)
            if sp is None:
                return
            self._setpoint = sp.copy()
            self._setpoint_t = time.monotonic()

    def stop(self) -> None:
        with self._lock:
            self._setpoint = None
            running = self._thread is not None and self._status in ("ready", "initializing")
        if running:
            # A failure is already the arm's status; holding is all that was wanted here.
            with contextlib.suppress(ArmError):
                self._request(["HOLD"], "ACK")

    def estop(self) -> None:
        with self._lock:
            self._setpoint = None
            running = self._thread is not None and self._running.is_set()
        if running:
            # On failure the status already says error, and the controller's watchdog holds.
            with contextlib.suppress(ArmError):
                self._request(["ESTOP"], "ACK")
        else:
            self._write_best_effort(["ESTOP"])
        with self._lock:
            self._status = "error"
            self._last_error = "emergency stop"

    def close(self) -> None:
        self.stop()
        self._stop_thread()
        self._close_port()
        with self._lock:
            self._status = "disconnected"

    # --- I/O thread --------------------------------------------------------------------

    def _run(self) -> None:
        next_t = time.monotonic()
        while self._running.is_set():
            try:
                self._serve_requests()
                self._cycle()
            except ArmError as e:
                self._fail(str(e))
            except LineError as e:
                self._fail(f"bad reply: {e}")
            except OSError as e:  # pyserial's SerialException is an OSError
                self._fail(f"link: {e}")
            if not self._running.is_set():
                break
            next_t += self.cycle_s
            now = time.monotonic()
            if next_t < now - self.cycle_s:
                next_t = now  # late by more than a cycle: do not burst to catch up
            self._wake.wait(max(0.0, next_t - now))
            self._wake.clear()
        self._abort_requests()

    def _serve_requests(self) -> None:
        while True:
            with self._lock:
                if not self._requests:
                    return
                req = self._requests.popleft()
            try:
                self._transact(req.fields, req.expect)
            except ArmError as e:
                req.error = e
                req.done.set()
                raise
            req.done.set()

    def _cycle(self) -> None:
        with self._lock:
            status = self._status
            sp = self._setpoint
            if sp is not None and time.monotonic() - self._setpoint_t > self.setpoint_stale_s:
                sp = self._setpoint = None
        if status == "initializing":
            reply = self._transact(["STAT"], "STAT")
            state = reply[1] if len(reply) > 1 else ""
            if state == "READY":
                q = self._read_joints_now()
                with self._lock:
                    if self._status == "initializing":
                        self._q = q
                        self._status = "ready"
            elif state in ("ESTOP", "FAULT"):
                raise ControllerError(state, reply[3] if len(reply) > 3 else "-")
        elif status == "ready":
            if sp is None:
                q = self._read_joints_now()
            else:
                self._seq += 1
                t0 = time.monotonic()
                reply = self._transact(["SP", str(self._seq), *format_joints(sp)], "JS")
                self.max_transaction_s = max(self.max_transaction_s, time.monotonic() - t0)
                if len(reply) != 8 or parse_uint(reply[1], "seq") != self._seq:
                    raise LinkError(f"reply to setpoint {self._seq} is {','.join(reply[:2])}")
                q = parse_joints(reply[2:])
                self.setpoints_sent += 1
            with self._lock:
                self._q = q
        elif status == "connected":
            # Keep polling so a dead link is noticed before anyone tries to move.
            self._transact(["STAT"], "STAT")
        self.cycles += 1

    def _read_joints_now(self) -> Q:
        reply = self._transact(["RJ"], "JS")
        if len(reply) != 8:
            raise LineError("SYNTAX", "JS needs a seq and 6 joint values")
        return parse_joints(reply[2:])

    # --- link --------------------------------------------------------------------------

    def _handshake(self) -> list[str]:
        """Send HELLO and wait for the controller's HELLO, skipping stale lines."""
        self._write(["HELLO"])
        deadline = time.monotonic() + max(self.timeout_s, 0.5)
        while True:
            try:
                fields = decode_line(self._read_line(deadline))
            except LineError:
                continue  # leftovers of an earlier session on the same wire
            if fields[0] == "HELLO":
                break
        if len(fields) != 4 or fields[1] != MODEL:
            raise LinkError(f"not a {MODEL} controller: {','.join(fields)}")
        min_cycle_us = parse_uint(fields[3], "cycle_us")
        if self.cycle_s * 1e6 < min_cycle_us:
            raise LinkError(f"cycle {self.cycle_s * 1e3:.1f} ms is below the controller's minimum")
        return fields

    def _transact(self, fields: list[str], expect: str) -> list[str]:
        self._write(fields)
        try:
            reply = decode_line(self._read_line(time.monotonic() + self.timeout_s))
        except LineError as e:
            raise LinkError(f"garbled reply to {fields[0]}: {e}") from None
        if reply[0] == "ERR":
            code = reply[1] if len(reply) > 1 else "?"
            raise ControllerError(code, reply[2] if len(reply) > 2 else "-")
        if reply[0] != expect:
            raise LinkError(f"expected {expect} in reply to {fields[0]}, got {reply[0]}")
        return reply

    def _write(self, fields: list[str]) -> None:
        line = encode_line(fields)
        with self._wlock:
            ser = self._ser
            if ser is None:
                raise LinkError("port closed")
            ser.write(line)

    def _read_line(self, deadline: float) -> bytes:
        ser = self._ser
        if ser is None:
            raise LinkError("port closed")
        while True:
            nl = self._rx.find(b"\n")
            if nl >= 0:
                line = bytes(self._rx[: nl + 1])
                del self._rx[: nl + 1]
                return line
            if len(self._rx) > MAX_LINE_BYTES:
                self._rx.clear()
                raise LinkError("garbage on the line (no line end)")
            left = deadline - time.monotonic()
            if left <= 0.0:
                raise LinkError(f"no reply within {self.timeout_s * 1e3:.0f} ms")
            ser.timeout = left
            chunk = ser.read(max(1, ser.in_waiting))
            self._rx.extend(chunk)

    def _write_best_effort(self, fields: list[str]) -> None:
        try:
            self._write(fields)
        except (ArmError, OSError):
            return  # a dead port cannot pass HOLD on; the controller's watchdog holds the arm

    def _request(self, fields: list[str], expect: str) -> None:
        req = _Request(fields, expect)
        with self._lock:
            if self._thread is None or not self._running.is_set():
                raise ArmError(f"cannot send {fields[0]}: arm is {self._status}")
            self._requests.append(req)
        self._wake.set()
        if not req.done.wait(self.timeout_s + 2 * self.cycle_s + 0.5):
            raise LinkError(f"{fields[0]} was not acknowledged")
        if req.error is not None:
            raise req.error

    def _abort_requests(self) -> None:
        with self._lock:
            pending = list(self._requests)
            self._requests.clear()
            why = self._last_error or "link closed"
        for req in pending:
            req.error = ArmError(why)
            req.done.set()

    def _fail(self, why: str) -> None:
        with self._lock:
            self._fail_locked(why)

    def _fail_locked(self, why: str) -> None:
        """Error: stop streaming, ask the controller to hold, stop the I/O thread."""
        self._setpoint = None
        if self._status != "error":
            self._last_error = why
        self._status = "error"
        if self._running.is_set():
            self._running.clear()
            self._wake.set()
            self._write_best_effort(["HOLD"])

    def _stop_thread(self) -> None:
        thread = self._thread
        self._running.clear()
        self._wake.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        self._thread = None

    def _close_port(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            close_port(ser)
