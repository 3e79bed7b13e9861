"""A 6-joint master arm on a serial line (docs/serial-master-protocol.md).

The arm streams its joint angles; forward kinematics over a configurable standard DH table
gives the hand pose in the arm's base frame (the master frame). Force display sends joint
torques τ = Jᵀ·[f; c] back over the same line (J: geometric Jacobian at the hand point,
base-frame aligned). `serial.serial_for_url` opens `/dev/ttyUSB0` in the lab and
`socket://127.0.0.1:PORT` against `fake.FakeMasterArm` in tests.
"""

from __future__ import annotations

import importlib
import socket
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.serialport import close_port
from services.control.master.config import number, option_error, positive, string
from services.control.master.device import (
    DeviceLost,
    DeviceNotFound,
    DeviceOptions,
    HandReading,
    MasterDevice,
)
from services.control.master.devices.master_arm.kinematics import (
    DEFAULT_MASTER_DH,
    DhRow,
    forward_kinematics,
    joint_torques_for_wrench,
)
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

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig

_READ_CHUNK = 4096


@dataclass(frozen=True, slots=True)
class MasterArmOptions(DeviceOptions):
    """`device = "serial_arm"`: its `[master]` keys. It streams at the station's `rate_hz`.

    port: the serial URL (`/dev/ttyUSB0`, `socket://127.0.0.1:PORT`).
    arm_dh: the master arm's standard DH table, 6 rows (d_m, a_m, alpha_rad).
    baudrate: the line speed.
    max_joint_torque_nm: clamp of each displayed joint torque.
    """

    port: str = ""
    arm_dh: tuple[DhRow, ...] = field(default=DEFAULT_MASTER_DH)
    baudrate: int = 115200
    max_joint_torque_nm: float = 1.0

    def __post_init__(self) -> None:
        string(self, "port")
        positive(self, "max_joint_torque_nm")
        rows = self.arm_dh
        if not isinstance(rows, tuple | list) or len(rows) != 6:
            raise option_error("arm_dh", "must be 6 rows of (d_m, a_m, alpha_rad)")
        checked: list[DhRow] = []
        for row in rows:
            if not isinstance(row, tuple | list) or len(row) != 3:
                raise option_error("arm_dh", "each row must be (d_m, a_m, alpha_rad)")
            d, a, alpha = (number("arm_dh", v) for v in row)
            checked.append((d, a, alpha))
        object.__setattr__(self, "arm_dh", tuple(checked))
        if isinstance(self.baudrate, bool) or not isinstance(self.baudrate, int):
            raise option_error("baudrate", "must be an integer")
        if self.baudrate <= 0:
            raise option_error("baudrate", "must be > 0")

    def build(self, config: MasterConfig) -> MasterDevice:
        return SerialMasterArm(
            self.port,
            dh=self.arm_dh,
            baudrate=self.baudrate,
            stream_rate_hz=config.rate_hz,
            max_joint_torque_nm=self.max_joint_torque_nm,
        )


@dataclass(frozen=True, slots=True)
class LinkStats:
    """Counters of the serial link since open(): joint frames received, frames lost (seq
    gaps), lines rejected for CRC or syntax, NAKs and torque-watchdog notices from the arm,
    torque frames sent."""

    frames: int = 0
    lost: int = 0
    crc_errors: int = 0
    syntax_errors: int = 0
    naks: int = 0
    watchdogs: int = 0
    torques_sent: int = 0


class SerialMasterArm:
    """The serial master arm as a `MasterDevice`.

    Button bit `clutch_button` of the arm is the master-shift. The grip is the arm's grip
    field when it sends one, else `grip_button` toggles it. When no joint frame has arrived
    for `stale_s` the reading reports the master-shift pressed, so the slave holds while the
    line is silent.
    """

    def __init__(
        self,
        url: str,
        *,
        dh: tuple[DhRow, ...] = DEFAULT_MASTER_DH,
        baudrate: int = 115200,
        stream_rate_hz: float = 100.0,
        max_joint_torque_nm: float = 1.0,
        clutch_button: int = 0,
        grip_button: int = 1,
        stale_s: float = 0.2,
        open_timeout_s: float = 2.0,
    ) -> None:
        if len(dh) != N_JOINTS:
            raise ValueError("the master arm needs 6 DH rows")
        if not 1.0 <= stream_rate_hz <= 1000.0:
            raise ValueError("stream_rate_hz must be within 1 … 1000")
        self._url = url
        self._dh = tuple(dh)
        self._baudrate = baudrate
        self._stream_rate_hz = stream_rate_hz
        self._max_tau = float(max_joint_torque_nm)
        self._clutch_mask = 1 << clutch_button
        self._grip_mask = 1 << grip_button
        self._stale_s = stale_s
        self._open_timeout_s = open_timeout_s
        self._port: Any = None
        self._serial: Any = None
        self._splitter = LineSplitter()
        self._identity: Identity | None = None
        self._frame: JointFrame | None = None
        self._frame_t = 0.0
        self._tx_seq = 0
        self._grip_toggle = 0.0
        self._prev_buttons = 0
        self._stats: dict[str, int] = dict.fromkeys(LinkStats.__slots__, 0)

    @property
    def name(self) -> str:
        model = self._identity.model if self._identity else "?"
        return f"serial_arm:{model}"

    @property
    def can_display_force(self) -> bool:
        return True

    @property
    def stats(self) -> LinkStats:
        """A snapshot of the link counters."""
        return LinkStats(**self._stats)

    @property
    def q_rad(self) -> NDArray[np.float64] | None:
        """The latest joint angles received (rad), None before the first frame."""
        return None if self._frame is None else np.array(self._frame.q_rad)

    def open(self) -> None:
        if not self._url:
            raise DeviceNotFound(
                "a serial master arm needs its port: --port /dev/ttyUSB0 (or a pyserial URL "
                "such as socket://127.0.0.1:5555 for the fake arm)",
                _ports(),
            )
        self._serial = importlib.import_module("serial")
        self._splitter = LineSplitter()
        self._frame = None
        self._stats = dict.fromkeys(LinkStats.__slots__, 0)
        try:
            self._port = self._serial.serial_for_url(
                self._url, baudrate=self._baudrate, timeout=0, write_timeout=1.0
            )
        except (self._serial.SerialException, ValueError, OSError) as exc:
            raise DeviceNotFound(f"cannot open master arm at {self._url}: {exc}", _ports()) from exc
        sock = getattr(self._port, "_socket", None)
        if isinstance(sock, socket.socket):
            # Serial over TCP (a device server, or the fake arm): without TCP_NODELAY, Nagle
            # holds each short torque line until the peer's next ACK, about one stream period.
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            self._send(encode_line("X"))
            self._send(encode_line("I"))
            fields = self._await("I", self._open_timeout_s)
            if fields is None:
                raise DeviceNotFound(f"no master arm answered on {self._url}", _ports())
            self._identity = Identity.decode(fields)
            if self._identity.n_joints != N_JOINTS:
                raise DeviceNotFound(
                    f"{self._identity.model} has {self._identity.n_joints} joints, need 6"
                )
            self._send(encode_line("S", [str(round(self._stream_rate_hz))]))
            if self._await("A", self._open_timeout_s) is None:
                raise DeviceNotFound(f"{self.name} did not acknowledge streaming")
            deadline = time.monotonic() + self._open_timeout_s
            while self._frame is None and time.monotonic() < deadline:
                self._poll(wait_s=0.01)
            if self._frame is None:
                raise DeviceNotFound(f"{self.name} sends no joint frames")
        except BaseException:
            close_port(self._port)
            self._port = None
            raise

    def _send(self, line: bytes) -> None:
        try:
            self._port.write(line)
        except (self._serial.SerialException, OSError) as exc:
            raise DeviceLost(f"master arm at {self._url}: {exc}") from exc

    def _poll(self, wait_s: float = 0.0) -> list[tuple[str, list[str]]]:
        """Read what has arrived; handle J/N/W lines, return the others."""
        try:
            data = self._port.read(_READ_CHUNK)
            if not data and wait_s > 0.0:
                time.sleep(wait_s)
                data = self._port.read(_READ_CHUNK)
        except (self._serial.SerialException, OSError) as exc:
            raise DeviceLost(f"master arm at {self._url}: {exc}") from exc
        others: list[tuple[str, list[str]]] = []
        for line in self._splitter.feed(data):
            try:
                kind, fields = parse_line(line)
                if kind == "J":
                    self._on_joints(JointFrame.decode(fields))
                elif kind == "N":
                    self._stats["naks"] += 1
                elif kind == "W":
                    self._stats["watchdogs"] += 1
                else:
                    others.append((kind, fields))
            except LineError as exc:
                key = "crc_errors" if exc.reason == "crc" else "syntax_errors"
                self._stats[key] += 1
        return others

    def _await(self, kind: str, timeout_s: float) -> list[str] | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for got, fields in self._poll(wait_s=0.005):
                if got == kind:
                    return fields
        return None

    def _on_joints(self, frame: JointFrame) -> None:
        if self._frame is not None:
            gap = (frame.seq - self._frame.seq) % SEQ_MODULO
            self._stats["lost"] += max(gap - 1, 0)
        self._stats["frames"] += 1
        self._frame = frame
        self._frame_t = time.monotonic()

    def read(self, dt_s: float) -> HandReading:
        if self._port is None or self._frame is None:
            raise DeviceLost("master arm is not open")
        self._poll()
        frame = self._frame
        stale = time.monotonic() - self._frame_t > self._stale_s
        if frame.buttons & self._grip_mask and not self._prev_buttons & self._grip_mask:
            self._grip_toggle = 1.0 - self._grip_toggle
        self._prev_buttons = frame.buttons
        p, R = forward_kinematics(frame.q_rad, self._dh)
        clutch = stale or bool(frame.buttons & self._clutch_mask)
        grip = frame.grip if frame.grip is not None else self._grip_toggle
        return HandReading(p, R, clutch, grip, frame.buttons)

    def joint_torques(self, f: ArrayLike, c: ArrayLike) -> NDArray[np.float64]:
        """τ = Jᵀ·[f; c] at the latest joint angles, each clamped to ±max_joint_torque_nm."""
        if self._frame is None:
            raise DeviceLost("no joint angles yet")
        tau = joint_torques_for_wrench(self._frame.q_rad, f, c, self._dh)
        return np.clip(tau, -self._max_tau, self._max_tau)

    def display_force(self, f: ArrayLike, c: ArrayLike) -> None:
        """Send τ = Jᵀ·[f; c] (force f in N, moment c in N·m at the hand point, master
        frame). The arm zeroes its torques by itself if they stop coming (its watchdog)."""
        tau = self.joint_torques(f, c)
        self._tx_seq = (self._tx_seq + 1) % SEQ_MODULO
        self._send(TorqueFrame(self._tx_seq, tuple(float(t) for t in tau)).encode())
        self._stats["torques_sent"] += 1

    def close(self) -> None:
        if self._port is None:
            return
        try:
            self._send(encode_line("X"))
        except DeviceLost:
            pass  # The line is already gone; the arm's torque watchdog makes it passive.
        finally:
            close_port(self._port)
            self._port = None


def _ports() -> list[str]:
    """Serial ports present on this machine, for DeviceNotFound messages."""
    try:
        list_ports = importlib.import_module("serial.tools.list_ports")
        return [f"{p.device} {p.description}" for p in list_ports.comports()]
    except (ImportError, OSError):
        return []
