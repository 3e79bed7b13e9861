"""A fake serial force sensor on TCP 127.0.0.1, for `socket://127.0.0.1:PORT`.

It speaks docs/serial-force-protocol.md byte for byte: waits for `$START`, then streams one
`$FS` line per sample at `rate_hz` (sending the samples it owes when it was late, as a
device with a hardware clock would), stops on `$STOP`. Faults are injected on demand:
garbage lines, NaN channels, truncated lines, bad checksums, skipped sample numbers,
stalls. Used by the tests and by anyone wiring the service without the hardware.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Sequence

from services.bus.loopback import LoopbackServer
from services.control.force.serial_sensor import SEQ_MODULO, encode_command, encode_sample, sentence

GARBAGE_LINE = b"\x00\xff\xfe#garbage!\r\n"
MAX_CATCH_UP = 50
"""Samples sent at most in one go after a late wake-up."""


class FakeSerialSensor(LoopbackServer):
    """A serial force sensor served on 127.0.0.1:`port` (0 = a free port)."""

    def __init__(
        self,
        rate_hz: float = 1000.0,
        *,
        port: int = 0,
        signals: Sequence[float] = (0, 0, 0, 0, 0, 0),
        streaming: bool = False,
    ) -> None:
        self._period_s = 1.0 / rate_hz
        self._signals = tuple(float(v) for v in signals)
        self._stream_at_connect = streaming
        super().__init__("tcp", port, "fake-serial-force")
        self._lock = threading.Lock()
        self._seq = 0
        self._garbage = 0
        self._nan = 0
        self._short = 0
        self._bad_ck = 0
        self._skip = 0
        self._stall_until = 0.0
        self.streaming = False
        self.sent = 0
        """Sample lines sent (including the faulty ones that consume a sample number)."""
        self.commands: list[bytes] = []

    # --- what it measures, and faults ----------------------------------------------------

    def set_signals(self, signals: Sequence[float]) -> None:
        """The six channel values sent from now on (device units, e.g. ADC counts)."""
        if len(signals) != 6:
            raise ValueError("six channels")
        with self._lock:
            self._signals = tuple(float(v) for v in signals)

    def inject_garbage(self, n: int = 1) -> None:
        """`n` extra lines of binary garbage between samples (no sample number consumed)."""
        with self._lock:
            self._garbage += n

    def inject_nan(self, n: int = 1) -> None:
        """`n` samples with a NaN channel and a good checksum (number consumed, data bad)."""
        with self._lock:
            self._nan += n

    def inject_short(self, n: int = 1) -> None:
        """`n` samples cut short mid-line (number consumed, the sample lost)."""
        with self._lock:
            self._short += n

    def inject_bad_checksum(self, n: int = 1) -> None:
        """`n` samples whose checksum is wrong (number consumed, the sample lost)."""
        with self._lock:
            self._bad_ck += n

    def skip(self, n: int = 1) -> None:
        """Skip `n` sample numbers, as a device that dropped samples (a gap of `n`)."""
        with self._lock:
            self._skip += n

    def stall(self, seconds: float) -> None:
        """Send nothing for `seconds`; the device does not sample meanwhile (no gap)."""
        with self._lock:
            self._stall_until = time.monotonic() + seconds

    # --- server thread -------------------------------------------------------------------

    def _session(self, conn: socket.socket) -> None:
        self.streaming = self._stream_at_connect
        rx = bytearray()
        next_t = time.monotonic()
        while not self._closed.is_set():
            timeout = max(0.0, next_t - time.monotonic()) if self.streaming else 0.05
            readable, _, _ = select.select([conn], [], [], timeout)
            if readable:
                try:
                    data = conn.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                rx += data
                while (end := rx.find(b"\n")) >= 0:
                    line = bytes(rx[: end + 1])
                    del rx[: end + 1]
                    self.commands.append(line)
                    if line == encode_command("START"):
                        self.streaming = True
                        next_t = time.monotonic()
                    elif line == encode_command("STOP"):
                        self.streaming = False
            if not self.streaming:
                continue
            now = time.monotonic()
            if now < self._stall_until:
                next_t = self._stall_until
                continue
            out = bytearray()
            n = 0
            while next_t <= now and n < MAX_CATCH_UP:
                out += self._next_lines()
                next_t += self._period_s
                n += 1
            if next_t <= now:  # hopelessly late: a device would not burst forever
                next_t = now + self._period_s
            if out:
                try:
                    conn.sendall(out)
                except OSError:
                    return

    def _next_lines(self) -> bytes:
        with self._lock:
            out = b""
            if self._garbage:
                self._garbage -= 1
                out += GARBAGE_LINE
            if self._skip:
                self._seq = (self._seq + self._skip) % SEQ_MODULO
                self._skip = 0
            seq = self._seq
            self._seq = (self._seq + 1) % SEQ_MODULO
            line = encode_sample(seq, self._signals)
            if self._nan:
                self._nan -= 1
                parts = line.split(b"*")[0][1:].split(b",")
                parts[4] = b"NaN"
                line = sentence(b",".join(parts))
            elif self._short:
                self._short -= 1
                line = line[: len(line) // 2] + b"\r\n"
            elif self._bad_ck:
                self._bad_ck -= 1
                ck = line[-4:-2]
                line = line[:-4] + (b"00" if ck != b"00" else b"FF") + b"\r\n"
            self.sent += 1
            return out + line
