"""The serial master arm's ASCII line protocol (docs/serial-master-protocol.md): framing,
CRC and the fields of each line. Pure bytes ↔ values, shared by `SerialMasterArm` and the
fake arm, so both ends speak exactly the documented format.

A line is `$<TYPE>[,<field>…]*<CRC>\\r\\n`; CRC is CRC-16/CCITT-FALSE (poly 0x1021, init
0xFFFF) over the bytes between `$` and `*`, as 4 upper-case hex digits.
"""

from __future__ import annotations

from dataclasses import dataclass

N_JOINTS = 6
JOINT_LSB_RAD = 1e-4
"""Joint angles travel as integers of 0.1 mrad."""
TORQUE_LSB_NM = 1e-3
"""Joint torques travel as integers of 1 mN·m."""
GRIP_FULL = 1000
"""Grip travels as an integer 0 (open) … 1000 (closed); an empty field means no grip."""
MAX_LINE_BYTES = 128
SEQ_MODULO = 65536

NAK_REASONS = ("crc", "syntax", "range", "unknown")


class LineError(ValueError):
    """A line that breaks the protocol; `reason` is one of NAK_REASONS."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason


def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor.
    Check value: crc16_ccitt(b"123456789") == 0x29B1."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def encode_line(kind: str, fields: list[str] | tuple[str, ...] = ()) -> bytes:
    """Frame one line: `$kind,f1,f2…*CRC\\r\\n`."""
    if not kind.isalpha() or not kind.isupper():
        raise ValueError(f"line type must be upper-case letters, got {kind!r}")
    body = ",".join([kind, *fields]).encode("ascii")
    if any(ch in body for ch in b"$*\r\n"):
        raise ValueError("fields must not contain '$', '*', CR or LF")
    line = b"$" + body + b"*" + f"{crc16_ccitt(body):04X}".encode("ascii") + b"\r\n"
    if len(line) > MAX_LINE_BYTES:
        raise ValueError(f"line longer than {MAX_LINE_BYTES} bytes")
    return line


def parse_line(line: bytes) -> tuple[str, list[str]]:
    """Check framing and CRC of one line (with or without its CR/LF); (type, fields)."""
    raw = line.rstrip(b"\r\n")
    if len(raw) > MAX_LINE_BYTES:
        raise LineError("syntax", "line too long")
    if not raw.startswith(b"$"):
        raise LineError("syntax", "line does not start with '$'")
    star = raw.rfind(b"*")
    if star < 0 or len(raw) - star - 1 != 4:
        raise LineError("syntax", "missing '*' and 4-digit CRC")
    body = raw[1:star]
    try:
        crc_sent = int(raw[star + 1 :].decode("ascii"), 16)
        text = body.decode("ascii")
    except (UnicodeDecodeError, ValueError) as exc:
        raise LineError("syntax", "not ASCII / bad CRC digits") from exc
    if crc16_ccitt(body) != crc_sent:
        raise LineError("crc", f"CRC {crc_sent:04X} != {crc16_ccitt(body):04X}")
    parts = text.split(",")
    if not parts[0].isalpha() or not parts[0].isupper():
        raise LineError("syntax", f"bad line type {parts[0]!r}")
    return parts[0], parts[1:]


def _int(field: str, what: str) -> int:
    try:
        return int(field, 10)
    except ValueError as exc:
        raise LineError("syntax", f"{what} is not an integer: {field!r}") from exc


@dataclass(frozen=True, slots=True)
class JointFrame:
    """`$J`, arm → host: seq (0 … 65535, wraps), q_rad (6 joint angles), buttons (bitmask,
    bit 0 = master-shift pressed, bit 1 = grip button), grip (0 … 1, None if absent)."""

    seq: int
    q_rad: tuple[float, ...]
    buttons: int
    grip: float | None

    def encode(self) -> bytes:
        if len(self.q_rad) != N_JOINTS:
            raise ValueError("q_rad must have 6 joints")
        q = [str(round(v / JOINT_LSB_RAD)) for v in self.q_rad]
        grip = "" if self.grip is None else str(round(self.grip * GRIP_FULL))
        fields = [str(self.seq % SEQ_MODULO), *q, f"{self.buttons:X}", grip]
        return encode_line("J", fields)

    @classmethod
    def decode(cls, fields: list[str]) -> JointFrame:
        if len(fields) != N_JOINTS + 3:
            raise LineError("syntax", f"J needs {N_JOINTS + 3} fields, got {len(fields)}")
        seq = _int(fields[0], "seq")
        if not 0 <= seq < SEQ_MODULO:
            raise LineError("range", "seq out of 0 … 65535")
        q = tuple(_int(f, "joint angle") * JOINT_LSB_RAD for f in fields[1 : N_JOINTS + 1])
        try:
            buttons = int(fields[N_JOINTS + 1], 16)
        except ValueError as exc:
            raise LineError("syntax", "buttons is not hex") from exc
        grip_field = fields[N_JOINTS + 2]
        grip: float | None = None
        if grip_field:
            grip_counts = _int(grip_field, "grip")
            if not 0 <= grip_counts <= GRIP_FULL:
                raise LineError("range", "grip out of 0 … 1000")
            grip = grip_counts / GRIP_FULL
        return cls(seq, q, buttons, grip)


@dataclass(frozen=True, slots=True)
class TorqueFrame:
    """`$T`, host → arm: seq (0 … 65535, wraps) and 6 joint torques (N·m)."""

    seq: int
    tau_nm: tuple[float, ...]

    def encode(self) -> bytes:
        if len(self.tau_nm) != N_JOINTS:
            raise ValueError("tau_nm must have 6 joints")
        fields = [str(self.seq % SEQ_MODULO), *(str(round(t / TORQUE_LSB_NM)) for t in self.tau_nm)]
        return encode_line("T", fields)

    @classmethod
    def decode(cls, fields: list[str]) -> TorqueFrame:
        if len(fields) != N_JOINTS + 1:
            raise LineError("syntax", f"T needs {N_JOINTS + 1} fields, got {len(fields)}")
        seq = _int(fields[0], "seq")
        if not 0 <= seq < SEQ_MODULO:
            raise LineError("range", "seq out of 0 … 65535")
        tau = tuple(_int(f, "torque") * TORQUE_LSB_NM for f in fields[1:])
        return cls(seq, tau)


@dataclass(frozen=True, slots=True)
class Identity:
    """`$I` reply, arm → host: model, firmware version, number of joints."""

    model: str
    firmware: str
    n_joints: int

    def encode(self) -> bytes:
        return encode_line("I", [self.model, self.firmware, str(self.n_joints)])

    @classmethod
    def decode(cls, fields: list[str]) -> Identity:
        if len(fields) != 3:
            raise LineError("syntax", "I reply needs model, firmware, n_joints")
        return cls(fields[0], fields[1], _int(fields[2], "n_joints"))


class LineSplitter:
    """Splits a byte stream into lines; drops runaway garbage longer than a line."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.overflows = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Append bytes; return the complete lines (without CR/LF), empty lines skipped."""
        self._buf.extend(data)
        lines: list[bytes] = []
        while True:
            nl = self._buf.find(b"\n")
            if nl < 0:
                break
            line = bytes(self._buf[:nl]).rstrip(b"\r")
            del self._buf[: nl + 1]
            if line:
                lines.append(line)
        if len(self._buf) > MAX_LINE_BYTES:
            # No newline in sight: noise on the line. Resynchronise on the next '$'.
            self.overflows += 1
            dollar = self._buf.rfind(b"$")
            self._buf = self._buf[dollar:] if dollar > 0 else bytearray()
        return lines
