"""XCDR1 ("DDS_CDR", little-endian) primitives, as Fast-CDR writes them for ROS 2.

A serialized message is a 4-byte encapsulation header (`00 01 00 00`: plain CDR, little
endian) and the body. Every primitive is aligned to its own size (8 for float64), counted
from the start of the body; a string is a uint32 length that includes the terminating NUL,
the bytes and the NUL; a sequence is a uint32 count and its elements; a fixed array has no
count. The reader is bounded: every length is checked against what is left and against a
caller's maximum before anything is allocated, so a hostile payload costs nothing.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

ENCAPSULATION_LE = b"\x00\x01\x00\x00"
HEADER_BYTES = len(ENCAPSULATION_LE)

_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")
_F64 = struct.Struct("<d")
_TIME = struct.Struct("<iI")


class CdrError(ValueError):
    """A payload that is not a valid CDR encoding of the expected type (or exceeds a bound)."""


class Writer:
    """Appends aligned little-endian primitives; `bytes()` gives header + body."""

    __slots__ = ("_buf",)

    def __init__(self) -> None:
        self._buf = bytearray(ENCAPSULATION_LE)

    def _align(self, n: int) -> None:
        pad = -(len(self._buf) - HEADER_BYTES) % n
        if pad:
            self._buf += b"\x00" * pad

    def u8(self, v: int) -> None:
        self._buf.append(v & 0xFF)

    def boolean(self, v: bool) -> None:
        self._buf.append(1 if v else 0)

    def u32(self, v: int) -> None:
        self._align(4)
        self._buf += _U32.pack(v)

    def time(self, sec: int, nanosec: int) -> None:
        """builtin_interfaces/Time: int32 sec, uint32 nanosec."""
        self._align(4)
        self._buf += _TIME.pack(sec, nanosec)

    def f64(self, v: float) -> None:
        self._align(8)
        self._buf += _F64.pack(v)

    def f64s(self, values: Sequence[float]) -> None:
        """A fixed-size float64 array (no count)."""
        self._align(8)
        self._buf += struct.pack(f"<{len(values)}d", *values)

    def f64_seq(self, values: Sequence[float]) -> None:
        """A float64 sequence: count, then the values (aligned to 8 only if not empty)."""
        self.u32(len(values))
        if values:
            self.f64s(values)

    def string(self, s: str) -> None:
        """A string: UTF-8, NUL-terminated. A character UTF-8 cannot carry (a lone surrogate,
        as `os.fsdecode` makes of a file name's undecodable bytes) is written as `?`: a ROS
        string must be valid UTF-8, and the bridge must not fail on its own data."""
        data = s.encode("utf-8", "replace")
        self.u32(len(data) + 1)
        self._buf += data
        self._buf.append(0)

    def string_seq(self, items: Sequence[str]) -> None:
        self.u32(len(items))
        for s in items:
            self.string(s)

    def octets(self, data: bytes) -> None:
        """A uint8 sequence (images): count, then the raw bytes."""
        self.u32(len(data))
        self._buf += data

    def bytes(self) -> bytes:
        return bytes(self._buf)


class Reader:
    """Reads what `Writer` writes, refusing anything malformed or larger than allowed."""

    __slots__ = ("_data", "_pos")

    def __init__(self, data: bytes | bytearray | memoryview, max_bytes: int) -> None:
        if len(data) > max_bytes:
            raise CdrError(f"payload of {len(data)} bytes exceeds the {max_bytes}-byte bound")
        if len(data) < HEADER_BYTES:
            raise CdrError("shorter than the encapsulation header")
        if data[:HEADER_BYTES] != ENCAPSULATION_LE:
            head = bytes(data[:HEADER_BYTES]).hex()
            raise CdrError(f"encapsulation {head} is not plain CDR little-endian (00010000)")
        self._data = bytes(data)
        self._pos = HEADER_BYTES

    def _align(self, n: int) -> None:
        self._pos += -(self._pos - HEADER_BYTES) % n

    def _take(self, n: int) -> int:
        start = self._pos
        if n < 0 or start + n > len(self._data):
            raise CdrError(
                f"truncated: need {n} bytes at offset {start}, have {len(self._data) - start}"
            )
        self._pos = start + n
        return start

    def u8(self) -> int:
        return self._data[self._take(1)]

    def boolean(self) -> bool:
        v = self.u8()
        if v > 1:
            raise CdrError(f"boolean byte {v} is neither 0 nor 1")
        return v == 1

    def u32(self) -> int:
        self._align(4)
        return int(_U32.unpack_from(self._data, self._take(4))[0])

    def time(self) -> tuple[int, int]:
        self._align(4)
        sec, nanosec = _TIME.unpack_from(self._data, self._take(8))
        if nanosec >= 1_000_000_000:
            raise CdrError(f"nanosec {nanosec} ≥ 1e9")
        return int(sec), int(nanosec)

    def f64(self) -> float:
        self._align(8)
        return float(_F64.unpack_from(self._data, self._take(8))[0])

    def f64s(self, n: int) -> tuple[float, ...]:
        self._align(8)
        return struct.unpack_from(f"<{n}d", self._data, self._take(8 * n))

    def count(self, max_items: int, what: str) -> int:
        n = self.u32()
        if n > max_items:
            raise CdrError(f"{what}: {n} items exceed the bound of {max_items}")
        return n

    def f64_seq(self, max_items: int, what: str) -> tuple[float, ...]:
        n = self.count(max_items, what)
        return self.f64s(n) if n else ()

    def string(self, max_chars: int, what: str) -> str:
        n = self.u32()
        if n == 0:
            raise CdrError(f"{what}: string length 0 (the NUL is counted)")
        if n - 1 > max_chars:
            raise CdrError(f"{what}: {n - 1} bytes exceed the bound of {max_chars}")
        start = self._take(n)
        if self._data[start + n - 1] != 0:
            raise CdrError(f"{what}: string not NUL-terminated")
        try:
            return self._data[start : start + n - 1].decode("utf-8")
        except UnicodeDecodeError as e:
            raise CdrError(f"{what}: not UTF-8 ({e.reason})") from None

    def string_seq(self, max_items: int, max_chars: int, what: str) -> tuple[str, ...]:
        n = self.count(max_items, what)
        return tuple(self.string(max_chars, what) for _ in range(n))

    def octets(self, max_bytes: int, what: str) -> bytes:
        n = self.count(max_bytes, what)
        start = self._take(n)
        return self._data[start : start + n]

    def end(self) -> None:
        """Refuse trailing bytes beyond the 3 bytes of padding a writer may add."""
        if len(self._data) - self._pos > 3:
            raise CdrError(f"{len(self._data) - self._pos} trailing bytes")


def finite(name: str, *values: float) -> None:
    """Raise CdrError naming `name` unless every value is finite (NaN and inf are refused)."""
    for v in values:
        if not math.isfinite(v):
            raise CdrError(f"{name}: not finite ({v})")
