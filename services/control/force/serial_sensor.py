"""`SerialSensor`: six ADC channels of a compliant wrist as checksummed ASCII lines.

The line format is docs/serial-force-protocol.md; this module is its one implementation
(`encode_sample`, `encode_command`, `decode_line` are pure functions of bytes). The port is
opened with `serial.serial_for_url`, so the same backend reads `/dev/ttyUSB0` in the lab
and `socket://127.0.0.1:PORT` (fake_serial_sensor.py) in tests.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from services.bus.serialport import close_port
from services.control.force.accounting import StreamAccounting
from services.control.force.events import EventSink, ignore_event
from services.control.force.sensors import Reading, SensorError, Six

if TYPE_CHECKING:
    import serial

SAMPLE_TAG = b"FS"
SEQ_MODULO = 65536
MAX_LINE_BYTES = 128
MAX_NUMBER_CHARS = 16
DEFAULT_BAUDRATE = 921_600

LineFault = Literal["garbage", "checksum", "short", "nan", "number", "overlong", "duplicate"]

_NUMBER = re.compile(rb"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_NON_FINITE = re.compile(rb"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
_SEQ = re.compile(rb"\d{1,5}")
_TAG = re.compile(rb"[A-Z][A-Z0-9]{0,7}")


class LineError(ValueError):
    """A line that is not a valid sample. `fault` classifies it; `seq` is the sample number
    when the line's checksum was good (the sample arrived, its data is bad)."""

    def __init__(self, fault: LineFault, message: str, seq: int | None = None) -> None:
        super().__init__(f"{fault}: {message}")
        self.fault: LineFault = fault
        self.seq = seq


@dataclass(frozen=True, slots=True)
class SerialFrame:
    """One sample line: the device's sample number and its six channels (device units)."""

    seq: int
    channels: Six


def checksum(body: bytes) -> int:
    """XOR of the bytes between '$' and '*' (NMEA 0183 style)."""
    x = 0
    for b in body:
        x ^= b
    return x


def sentence(body: bytes) -> bytes:
    """`$<body>*<CK>\\r\\n`: a body framed with its checksum."""
    return b"$" + body + b"*" + f"{checksum(body):02X}".encode() + b"\r\n"


def _number(v: float) -> bytes:
    if float(v).is_integer() and abs(v) < 1e15:
        return str(int(v)).encode()
    return f"{v:.9g}".encode()


def encode_sample(seq: int, channels: Sequence[float]) -> bytes:
    """`$FS,<seq>,<c1>,…,<c6>*<CK>\\r\\n`; integral channels are written as integers."""
    if len(channels) != 6:
        raise ValueError("six channels")
    body = b",".join([SAMPLE_TAG, str(seq % SEQ_MODULO).encode(), *(_number(c) for c in channels)])
    return sentence(body)


def encode_command(name: Literal["START", "STOP"]) -> bytes:
    """A host→device command line: `$START*CK\\r\\n` or `$STOP*CK\\r\\n`."""
    return sentence(name.encode())


def decode_line(line: bytes) -> SerialFrame | None:
    """One line (CR/LF optional) → a sample, None for another well-formed sentence, or LineError."""
    line = line.rstrip(b"\r\n")
    if len(line) > MAX_LINE_BYTES:
        raise LineError("overlong", f"{len(line)} bytes")
    if not line.startswith(b"$"):
        raise LineError("garbage", "no '$' at the start")
    star = line.rfind(b"*")
    if star < 0 or len(line) - star != 3:
        if line.startswith(b"$" + SAMPLE_TAG + b","):
            raise LineError("short", "truncated line (no *CK at the end)")
        raise LineError("garbage", "no '*CK' at the end")
    body = line[1:star]
    try:
        ck = int(line[star + 1 :], 16)
    except ValueError:
        raise LineError("garbage", "checksum is not hex") from None
    if checksum(body) != ck:
        raise LineError("checksum", f"computed {checksum(body):02X}, line says {ck:02X}")
    fields = body.split(b",")
    if not _TAG.fullmatch(fields[0]):
        raise LineError("garbage", "bad sentence tag")
    if fields[0] != SAMPLE_TAG:
        return None
    if len(fields) < 2 or not _SEQ.fullmatch(fields[1]) or int(fields[1]) >= SEQ_MODULO:
        raise LineError("garbage", "bad sample number")
    seq = int(fields[1])
    if len(fields) != 8:
        raise LineError("short", f"{len(fields) - 2} channels, expected 6", seq)
    values: list[float] = []
    for i, tok in enumerate(fields[2:], start=1):
        if len(tok) > MAX_NUMBER_CHARS:
            raise LineError("number", f"channel {i} too long", seq)
        if _NON_FINITE.fullmatch(tok):
            raise LineError("nan", f"channel {i} is {tok.decode()}", seq)
        if not _NUMBER.fullmatch(tok):
            raise LineError("number", f"channel {i} is not a number", seq)
        v = float(tok)
        if not math.isfinite(v):
            raise LineError("nan", f"channel {i} overflows", seq)
        values.append(v)
    return SerialFrame(seq, (values[0], values[1], values[2], values[3], values[4], values[5]))


class SerialSensor(StreamAccounting):
    """A compliant wrist whose six sensing signals arrive as ASCII lines on a serial port.

    `port` is anything `serial.serial_for_url` opens (`/dev/ttyUSB0`, `socket://host:port`,
    `loop://`). `open()` sends `$START`, `close()` `$STOP`. `read()` is non-blocking: it
    parses every complete line received and returns the newest valid sample as
    `Reading("signals", …)`. The fragment before the first line end after `open()` is a
    partial line of a device already streaming, and is dropped without being counted.
    """

    seq_modulo = SEQ_MODULO
    unit = "samples"

    def __init__(
        self,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        *,
        on_event: EventSink = ignore_event,
    ) -> None:
        self.on_event = on_event
        self._port = port
        self._baudrate = baudrate
        self._ser: serial.Serial | None = None
        self._buf = bytearray()
        self._synced = False
        self._init_accounting()
        self._frames = 0

    @property
    def name(self) -> str:
        return f"serial {self._port}"

    @property
    def frames(self) -> int:
        """Valid sample lines received since construction."""
        return self._frames

    def open(self) -> None:
        if self._ser is not None:
            return
        import serial

        try:
            ser = serial.serial_for_url(
                self._port, baudrate=self._baudrate, timeout=0, write_timeout=1.0
            )
        except (serial.SerialException, ValueError) as e:
            raise SensorError(f"{self.name}: cannot open: {e}") from None
        ser.reset_input_buffer()
        ser.write(encode_command("START"))
        self._ser = ser
        self._buf.clear()
        self._synced = False
        self._last_seq = None

    def close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is None:
            return
        # A device already gone needs no stop: closing is all that is left.
        with contextlib.suppress(OSError):
            ser.write(encode_command("STOP"))
        close_port(ser)

    def read(self) -> Reading | None:
        ser = self._ser
        if ser is None:
            raise SensorError(f"{self.name} is not open")
        while True:
            chunk = ser.read(4096)
            self._buf += chunk
            if len(chunk) < 4096:
                break
        newest: SerialFrame | None = None
        while (end := self._buf.find(b"\n")) >= 0:
            line = bytes(self._buf[: end + 1])
            del self._buf[: end + 1]
            frame = self._take(line)
            if frame is not None:
                newest = frame
        if len(self._buf) > MAX_LINE_BYTES:
            self._reject(LineError("overlong", f"{len(self._buf)} bytes without a line end"), b"")
            self._buf.clear()
        if newest is None:
            return None
        return Reading("signals", newest.channels, newest.seq)

    def _take(self, line: bytes) -> SerialFrame | None:
        first = not self._synced
        self._synced = True
        if not line.strip():
            return None
        try:
            frame = decode_line(line)
        except LineError as e:
            if first:
                return None
            if e.seq is not None:
                self._step(e.seq)
            self._reject(e, line)
            return None
        if frame is None:
            return None
        if not self._step(frame.seq):
            self._reject(LineError("duplicate", f"sample {frame.seq} again", frame.seq), line)
            return None
        self._frames += 1
        return frame

    def _reject(self, e: LineError, line: bytes) -> None:
        self._bad_data(str(e), e.fault, line=line[:48].decode("ascii", "replace"))
