"""A fake ATI Net F/T speaking RDT byte for byte on UDP 127.0.0.1 (any port, 0 = free).

It answers the 8-byte requests of netft.py's docstring: start streaming (to the requester,
`sample_count` records or for ever), stop, software bias; and streams 36-byte records at
`rate_hz`, sending the records it owes after a late wake-up as the real sensor's clock
would. Faults on demand: lost datagrams (rdt_sequence gaps), short datagrams, records with
error status bits, stalls.
"""

from __future__ import annotations

import select
import threading
import time
from collections.abc import Sequence

from services.bus.loopback import LoopbackServer
from services.control.force.netft import (
    CMD_SET_SOFTWARE_BIAS,
    CMD_START_STREAMING,
    CMD_STOP_STREAMING,
    DEFAULT_COUNTS_PER_FORCE,
    DEFAULT_COUNTS_PER_TORQUE,
    SEQ_MODULO,
    RdtRecord,
    pack_record,
    unpack_request,
)

MAX_CATCH_UP = 50
INTERNAL_RATE_HZ = 7000.0
"""The rate of the Net F/T's internal sampling, which ft_sequence counts."""


class FakeNetFT(LoopbackServer):
    """A Net F/T on 127.0.0.1:`port` measuring the wrench set by `set_wrench`."""

    def __init__(
        self,
        *,
        port: int = 0,
        rate_hz: float = 1000.0,
        counts_per_force: float = DEFAULT_COUNTS_PER_FORCE,
        counts_per_torque: float = DEFAULT_COUNTS_PER_TORQUE,
    ) -> None:
        self._period_s = 1.0 / rate_hz
        self._cpf = counts_per_force
        self._cpt = counts_per_torque
        super().__init__("udp", port, "fake-netft")
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._counts = (0, 0, 0, 0, 0, 0)
        self._bias = (0, 0, 0, 0, 0, 0)
        self._seq = 1
        self._client: tuple[str, int] | None = None
        self._remaining = 0
        self._gap = 0
        self._short = 0
        self._status: list[int] = []
        self._stall_until = 0.0
        self.sent = 0
        """Records sent, or lost on purpose (each consumes an rdt_sequence)."""
        self.requests: list[tuple[int, int]] = []
        self.bad_requests = 0

    @property
    def streaming(self) -> bool:
        return self._client is not None

    # --- what it measures, and faults ----------------------------------------------------

    def set_wrench(self, f_n: Sequence[float], c_nm: Sequence[float]) -> None:
        """The wrench at the sensor origin, sensor frame (N, N·m), before the bias."""
        counts = [round(v * self._cpf) for v in f_n] + [round(v * self._cpt) for v in c_nm]
        if len(counts) != 6:
            raise ValueError("3 forces and 3 torques")
        with self._lock:
            self._counts = (counts[0], counts[1], counts[2], counts[3], counts[4], counts[5])

    def inject_gap(self, n: int = 1) -> None:
        """Lose the next `n` records (their rdt_sequence numbers are skipped)."""
        with self._lock:
            self._gap += n

    def inject_short(self, n: int = 1) -> None:
        """Send `n` truncated datagrams (20 bytes) besides the records."""
        with self._lock:
            self._short += n

    def inject_status(self, n: int = 1, status: int = 0x8000_0000) -> None:
        """The next `n` records carry `status` (error bits)."""
        with self._lock:
            self._status.extend([status] * n)

    def stall(self, seconds: float) -> None:
        """Send nothing for `seconds` (the records are not sent, not lost: no gap)."""
        with self._lock:
            self._stall_until = time.monotonic() + seconds

    # --- server thread -------------------------------------------------------------------

    def _serve(self) -> None:
        next_t = time.monotonic()
        while not self._closed.is_set():
            timeout = max(0.0, next_t - time.monotonic()) if self.streaming else 0.05
            readable, _, _ = select.select([self._sock], [], [], timeout)
            if readable:
                try:
                    data, addr = self._sock.recvfrom(2048)
                except OSError:
                    return
                if self._request(data, addr):
                    next_t = time.monotonic()
            client = self._client
            if client is None:
                continue
            now = time.monotonic()
            if now < self._stall_until:
                next_t = self._stall_until
                continue
            n = 0
            while next_t <= now and n < MAX_CATCH_UP and self._client is not None:
                payload = self._next_datagrams()
                for p in payload:
                    try:
                        self._sock.sendto(p, client)
                    except OSError:
                        return
                next_t += self._period_s
                n += 1
            if next_t <= now:
                next_t = now + self._period_s

    def _request(self, data: bytes, addr: tuple[str, int]) -> bool:
        """Handle one request; True when streaming (re)starts."""
        try:
            command, count = unpack_request(data)
        except ValueError:
            self.bad_requests += 1
            return False
        self.requests.append((command, count))
        with self._lock:
            if command == CMD_START_STREAMING:
                self._client = addr
                self._remaining = count
                return True
            if command == CMD_STOP_STREAMING:
                self._client = None
            elif command == CMD_SET_SOFTWARE_BIAS:
                self._bias = self._counts
            else:
                self.bad_requests += 1
        return False

    def _next_datagrams(self) -> list[bytes]:
        with self._lock:
            out: list[bytes] = []
            if self._short:
                self._short -= 1
                out.append(b"\x00" * 20)
            while self._gap:
                self._gap -= 1
                self._seq = (self._seq + 1) % SEQ_MODULO
                self.sent += 1
            status = self._status.pop(0) if self._status else 0
            ft_seq = int((time.monotonic() - self._t0) * INTERNAL_RATE_HZ) % SEQ_MODULO
            counts = tuple(c - b for c, b in zip(self._counts, self._bias, strict=True))
            rec = RdtRecord(
                self._seq,
                ft_seq,
                status,
                (counts[0], counts[1], counts[2], counts[3], counts[4], counts[5]),
            )
            out.append(pack_record(rec))
            self._seq = (self._seq + 1) % SEQ_MODULO
            self.sent += 1
            if self._remaining:
                self._remaining -= 1
                if self._remaining == 0:
                    self._client = None
            return out
