"""A fake retrofitted PUMA controller that speaks docs/serial-arm-protocol.md byte for byte.

It listens on TCP 127.0.0.1 so that `SerialArm("socket://127.0.0.1:PORT")` talks to it as
to a serial port, and moves a simulated arm with the same joint servo as `SimArm`. For
fault tests it can garble or drop bytes (one-shot or at random with a seed), corrupt what
it receives, go silent (a pulled RS-232 cable) or drop the connection (a pulled USB
adapter), and press its own e-stop. It records every setpoint it accepts, and how far each
was from the measured joints, so tests can prove the host never jumped.

Run it alone: `python -m services.control.arm.fake_controller --port 5555`.
"""

from __future__ import annotations

import argparse
import random
import select
import socket
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from services.control.arm.driver import Q
from services.control.arm.model import load_model
from services.control.arm.serial_arm import (
    MAX_LINE_BYTES,
    MODEL,
    LineError,
    clean_text,
    decode_line,
    encode_line,
    format_joints,
    parse_joints,
    parse_uint,
)
from services.control.arm.sim_arm import SERVO_DT_S, JointFollower

FIRMWARE = "FAKE-1.0"
HOST = "127.0.0.1"


@dataclass(frozen=True, slots=True)
class SetpointRecord:
    """One accepted setpoint: its `seq`, the setpoint and the measured joints (rad) on arrival."""

    seq: int
    setpoint: tuple[float, ...]
    measured: tuple[float, ...]

    @property
    def jump_rad(self) -> float:
        """The largest |setpoint − measured| over the joints (rad)."""
        return max(abs(a - b) for a, b in zip(self.setpoint, self.measured, strict=True))


class FakeController:
    """The fake controller on `127.0.0.1:port` (0 picks a free port; see `.port`, `.url`).

    `calibration_s`: duration of CAL. `min_cycle_us`: the shortest setpoint period it
    accepts, announced in HELLO. `watchdog_s`: after that long without a setpoint while
    streaming, it holds. `max_setpoint_step_rad`: a setpoint further than that from the
    measured joints is refused (`ERR,STEP`) and latches a fault.
    """

    def __init__(
        self,
        port: int = 0,
        *,
        q_init: Sequence[float] | None = None,
        calibration_s: float = 0.5,
        min_cycle_us: int = 1000,
        watchdog_s: float = 0.25,
        max_setpoint_step_rad: float = 0.5,
        max_joint_speed_rad_s: Sequence[float] | None = None,
        max_joint_accel_rad_s2: Sequence[float] | None = None,
        seed: int = 0,
    ) -> None:
        # The controller's servo limits are the PUMA 560's (its model: URDF and arm.toml).
        puma = load_model("puma560")
        self._lock = threading.RLock()
        self._servo = JointFollower.of(
            puma,
            puma.named["qn"] if q_init is None else q_init,
            max_joint_speed_rad_s,
            max_joint_accel_rad_s2,
        )
        self.q_lo = np.asarray(puma.q_lo)
        self.q_hi = np.asarray(puma.q_hi)
        self.calibration_s = float(calibration_s)
        self.min_cycle_us = int(min_cycle_us)
        self.watchdog_s = float(watchdog_s)
        self.max_setpoint_step_rad = float(max_setpoint_step_rad)
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((HOST, port))
        self._listener.listen(2)
        self.port: int = self._listener.getsockname()[1]
        self._client: socket.socket | None = None
        self._rx = bytearray()
        self._running = threading.Event()
        self._thread: threading.Thread | None = None
        self._rng = random.Random(seed)
        # Controller state.
        self.state = "IDLE"
        self.calibrated = False
        self.fault_text = "-"
        self._cal_left_s = 0.0
        self._streaming = False
        self._last_sp_t = 0.0
        self._last_seq = 0
        # Faults.
        self._garble_replies = 0
        self._drop_reply_bytes = 0
        self._garble_rx_lines = 0
        self._garble_rx_kind: bytes | None = None
        self._pulled: str | None = None
        self.drop_per_byte = 0.0
        self.garble_per_byte = 0.0
        # Observations.
        self.setpoints: list[SetpointRecord] = []
        self.lines_rx = 0
        self.replies: Counter[str] = Counter()
        self.errors_sent: Counter[str] = Counter()
        self.watchdog_trips = 0
        self.connections = 0

    @property
    def url(self) -> str:
        return f"socket://{HOST}:{self.port}"

    # --- lifecycle -------------------------------------------------------------------

    def start(self) -> FakeController:
        self._running.set()
        self._thread = threading.Thread(target=self._run, name="fake-arm", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._drop_client()
        self._listener.close()

    def __enter__(self) -> FakeController:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- observation -----------------------------------------------------------------

    @property
    def q(self) -> Q:
        """The joint angles of the simulated arm (rad)."""
        with self._lock:
            return self._servo.q

    @property
    def max_setpoint_jump_rad(self) -> float:
        """The largest |setpoint − measured| of any accepted setpoint (rad); 0 with none."""
        with self._lock:
            return max((r.jump_rad for r in self.setpoints), default=0.0)

    # --- fault injection ----------------------------------------------------------------

    def garble_next_reply(self, n: int = 1) -> None:
        """Flip one body byte in each of the next `n` replies (the checksum then fails)."""
        with self._lock:
            self._garble_replies += n

    def drop_next_reply_bytes(self, n: int = 1) -> None:
        """Leave `n` bytes out of the middle of the next reply."""
        with self._lock:
            self._drop_reply_bytes += n

    def garble_next_rx(self, n: int = 1, kind: str | None = None) -> None:
        """Corrupt one body byte in each of the next `n` received lines (noise on the host's
        transmit wire; the checksum then fails), or only in lines of `kind` ("SP") when given:
        the host's link also sends joint reads, and a test of a corrupted setpoint must hit one."""
        with self._lock:
            self._garble_rx_lines += n
            self._garble_rx_kind = None if kind is None else b"$" + kind.encode("ascii") + b","

    def clear_faults(self) -> None:
        """The line is clean again: no noise, and one-shot faults not yet fired are dropped
        (a fault meant for a stream that ended for another reason must not hit the next
        session's handshake)."""
        with self._lock:
            self._garble_replies = 0
            self._drop_reply_bytes = 0
            self._garble_rx_lines = 0
            self._garble_rx_kind = None
            self.drop_per_byte = 0.0
            self.garble_per_byte = 0.0

    def set_noise(self, drop_per_byte: float = 0.0, garble_per_byte: float = 0.0) -> None:
        """Random line noise on every reply byte from now on (seeded: reproducible)."""
        with self._lock:
            self.drop_per_byte = drop_per_byte
            self.garble_per_byte = garble_per_byte

    def pull_cable(self, hard: bool = False) -> None:
        """Pull the cable: silence (RS-232: nothing in or out), or with `hard` the port
        vanishes (USB adapter: the connection drops and new ones are refused)."""
        with self._lock:
            self._pulled = "hard" if hard else "soft"
            if hard:
                self._drop_client()

    def plug_cable(self) -> None:
        with self._lock:
            self._pulled = None

    def press_estop(self) -> None:
        """The e-stop button on the controller's pendant."""
        with self._lock:
            self._estop("pendant e-stop")

    # --- the loop ----------------------------------------------------------------------

    def _run(self) -> None:
        last = time.monotonic()
        acc_s = 0.0
        while self._running.is_set():
            socks = [self._listener] + ([self._client] if self._client is not None else [])
            try:
                readable, _, _ = select.select(socks, [], [], SERVO_DT_S)
            except (OSError, ValueError):
                self._drop_client()
                continue
            for s in readable:
                if s is self._listener:
                    self._accept()
                else:
                    self._receive()
            now = time.monotonic()
            acc_s += now - last
            last = now
            # Catch up in servo steps, but never simulate more than 50 ms at once.
            acc_s = min(acc_s, 0.05)
            with self._lock:
                while acc_s >= SERVO_DT_S:
                    self._physics(SERVO_DT_S, now)
                    acc_s -= SERVO_DT_S

    def _accept(self) -> None:
        try:
            conn, _ = self._listener.accept()
        except OSError:
            return
        with self._lock:
            if self._pulled == "hard":
                conn.close()
                return
            # A serial line has one end: a new connection replaces the old one.
            self._drop_client()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._client = conn
            self._rx.clear()
            self.connections += 1

    def _drop_client(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            try:
                client.close()
            except OSError:
                return  # already gone

    def _receive(self) -> None:
        client = self._client
        if client is None:
            return
        try:
            data = client.recv(4096)
        except OSError:
            data = b""
        with self._lock:
            if not data:
                self._drop_client()
                return
            if self._pulled is not None:
                return  # the wire is cut: the bytes never arrive
            self._rx.extend(data)
            while True:
                nl = self._rx.find(b"\n")
                if nl < 0:
                    break
                line = bytes(self._rx[: nl + 1])
                del self._rx[: nl + 1]
                self._handle(line)
            if len(self._rx) > MAX_LINE_BYTES:
                self._rx.clear()
                self._reply(["ERR", "SYNTAX", "line too long"])

    def _physics(self, dt_s: float, now: float) -> None:
        if self.state == "CAL":
            self._cal_left_s -= dt_s
            if self._cal_left_s <= 0.0:
                self.state = "READY"
                self.calibrated = True
        if self._streaming and now - self._last_sp_t > self.watchdog_s:
            self._streaming = False
            self.watchdog_trips += 1
            self._servo.hold()
        self._servo.step(dt_s)

    # --- the protocol ----------------------------------------------------------------

    def _handle(self, raw: bytes) -> None:
        self.lines_rx += 1
        if (
            self._garble_rx_lines > 0
            and len(raw) > 4
            and (self._garble_rx_kind is None or raw.startswith(self._garble_rx_kind))
        ):
            self._garble_rx_lines -= 1
            raw = _flip_body(raw)
        try:
            fields = decode_line(raw)
        except LineError as e:
            self._reply(["ERR", e.code, clean_text(str(e))])
            return
        kind, args = fields[0], fields[1:]
        handler = {
            "HELLO": self._on_hello,
            "STAT": self._on_stat,
            "CAL": self._on_cal,
            "SP": self._on_sp,
            "RJ": self._on_rj,
            "HOLD": self._on_hold,
            "ESTOP": self._on_estop,
            "RESET": self._on_reset,
        }.get(kind)
        if handler is None:
            self._reply(["ERR", "UNKNOWN", clean_text(kind)])
            return
        handler(args)

    def _on_hello(self, args: list[str]) -> None:
        self._reply(["HELLO", MODEL, FIRMWARE, str(self.min_cycle_us)])

    def _on_stat(self, args: list[str]) -> None:
        self._reply(["STAT", self.state, "1" if self.calibrated else "0", self.fault_text])

    def _on_cal(self, args: list[str]) -> None:
        if self._refuse_if_halted():
            return
        if self.state != "CAL":
            self.state = "CAL"
            self._cal_left_s = self.calibration_s
            self._streaming = False
            self._servo.hold()
        self._reply(["ACK", "CAL"])

    def _on_sp(self, args: list[str]) -> None:
        try:
            if len(args) != 7:
                raise LineError("SYNTAX", "SP needs a seq and 6 joint values")
            seq = parse_uint(args[0], "seq")
            sp = parse_joints(args[1:])
        except LineError as e:
            self._reply(["ERR", e.code, clean_text(str(e))])
            return
        if self._refuse_if_halted():
            return
        if self.state != "READY":
            self._reply(["ERR", "STATE", f"{self.state} not READY"])
            return
        outside = np.flatnonzero((sp < self.q_lo) | (sp > self.q_hi))
        if outside.size:
            self._fault(f"q{int(outside[0]) + 1} setpoint outside limits")
            self._reply(["ERR", "LIMIT", self.fault_text])
            return
        measured = self._servo.q
        jump = float(np.max(np.abs(sp - measured)))
        if jump > self.max_setpoint_step_rad:
            self._fault(f"setpoint jump {jump:.3f} rad")
            self._reply(["ERR", "STEP", self.fault_text])
            return
        self._servo.setpoint = sp
        self._streaming = True
        self._last_sp_t = time.monotonic()
        self._last_seq = seq
        self.setpoints.append(SetpointRecord(seq, tuple(sp.tolist()), tuple(measured.tolist())))
        self._reply(["JS", str(seq), *format_joints(self._servo.q_rad)])

    def _on_rj(self, args: list[str]) -> None:
        if not self.calibrated:
            self._reply(["ERR", "STATE", "not calibrated"])
            return
        self._reply(["JS", str(self._last_seq), *format_joints(self._servo.q_rad)])

    def _on_hold(self, args: list[str]) -> None:
        self._streaming = False
        self._servo.hold()
        self._reply(["ACK", "HOLD"])

    def _on_estop(self, args: list[str]) -> None:
        self._estop("host e-stop")
        self._reply(["ACK", "ESTOP"])

    def _on_reset(self, args: list[str]) -> None:
        # Clears a latched e-stop or fault; arm power stays off until the next CAL.
        self.state = "IDLE"
        self.fault_text = "-"
        self._streaming = False
        self._servo.hold()
        self._reply(["ACK", "RESET"])

    def _refuse_if_halted(self) -> bool:
        if self.state in ("ESTOP", "FAULT"):
            self._reply(["ERR", self.state, self.fault_text])
            return True
        return False

    def _estop(self, why: str) -> None:
        self._servo.halt()
        self._streaming = False
        self.state = "ESTOP"
        self.fault_text = clean_text(why)

    def _fault(self, why: str) -> None:
        self._servo.hold()
        self._streaming = False
        self.state = "FAULT"
        self.fault_text = clean_text(why)

    def _reply(self, fields: list[str]) -> None:
        self.replies[fields[0]] += 1
        if fields[0] == "ERR":
            self.errors_sent[fields[1]] += 1
        data = bytearray(encode_line(fields))
        if self._garble_replies > 0:
            self._garble_replies -= 1
            data = bytearray(_flip_body(bytes(data)))
        if self._drop_reply_bytes > 0:
            mid = len(data) // 2
            del data[mid : mid + self._drop_reply_bytes]
            self._drop_reply_bytes = 0
        if self.drop_per_byte > 0.0 or self.garble_per_byte > 0.0:
            data = self._noisy(data)
        if self._pulled is not None or self._client is None:
            return
        try:
            self._client.sendall(bytes(data))
        except OSError:
            self._drop_client()

    def _noisy(self, data: bytearray) -> bytearray:
        out = bytearray()
        for b in data:
            r = self._rng.random()
            if r < self.drop_per_byte:
                continue
            if r < self.drop_per_byte + self.garble_per_byte:
                b ^= 1 << self._rng.randrange(7)
            out.append(b)
        return out


def _flip_body(raw: bytes) -> bytes:
    """`raw` with the middle byte of its body (between `$` and `*`) changed to another
    printable character, so the line keeps its frame and only its checksum fails."""
    star = raw.rfind(b"*")
    end = star if star > 1 else len(raw)
    i = (1 + end) // 2
    b = raw[i]
    new = ord("#") if b != ord("#") else ord("%")
    return raw[:i] + bytes([new]) + raw[i + 1 :]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Fake PUMA 560 serial controller on 127.0.0.1")
    parser.add_argument("--port", type=int, default=0, help="TCP port (0: a free one)")
    parser.add_argument("--calibration-s", type=float, default=0.5)
    parser.add_argument("--watchdog-s", type=float, default=0.25)
    args = parser.parse_args(argv)
    fake = FakeController(args.port, calibration_s=args.calibration_s, watchdog_s=args.watchdog_s)
    with fake:
        print(f"fake PUMA controller on {fake.url}", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            return


if __name__ == "__main__":
    main()
