"""`NetFTSensor`: an ATI Net F/T over its Raw Data Transfer (RDT) UDP protocol.

RDT (ATI Net F/T manual, "UDP interface using RDT"): the host sends an 8-byte request to
UDP port 49152, big-endian

    uint16 header = 0x1234 | uint16 command | uint32 sample_count

with command 0x0002 = start high-speed real-time streaming (sample_count records, 0 = for
ever), 0x0000 = stop streaming, 0x0042 = set software bias. The sensor answers with 36-byte
records, big-endian

    uint32 rdt_sequence | uint32 ft_sequence | uint32 status | int32 Fx Fy Fz Tx Ty Tz

rdt_sequence counts records sent (a jump is a lost datagram), ft_sequence counts internal
samples, status is a bit map (0 = healthy), and the six values are counts: divide by
counts-per-force (N) and counts-per-torque (N·m), which the sensor's calibration sets
(many Net F/Ts: 1 000 000 each). The wrench is at the sensor origin, sensor frame.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time
from dataclasses import dataclass

from services.control.force.accounting import StreamAccounting
from services.control.force.events import EventSink, ignore_event
from services.control.force.sensors import Reading, SensorError, Six

RDT_PORT = 49152
RDT_HEADER = 0x1234
CMD_STOP_STREAMING = 0x0000
CMD_START_STREAMING = 0x0002
CMD_SET_SOFTWARE_BIAS = 0x0042
REQUEST = struct.Struct(">HHI")
RECORD = struct.Struct(">IIIiiiiii")
SEQ_MODULO = 2**32
DEFAULT_COUNTS_PER_FORCE = 1_000_000.0
DEFAULT_COUNTS_PER_TORQUE = 1_000_000.0
RESTART_AFTER_S = 0.5
"""Without a record for this long, the start request is sent again: UDP may have lost it,
or the sensor rebooted and forgot it."""


@dataclass(frozen=True, slots=True)
class RdtRecord:
    """One RDT record: sequence numbers, status bits and the six raw counts."""

    rdt_sequence: int
    ft_sequence: int
    status: int
    counts: tuple[int, int, int, int, int, int]


def pack_request(command: int, sample_count: int = 0) -> bytes:
    """The 8-byte RDT request."""
    return REQUEST.pack(RDT_HEADER, command, sample_count)


def unpack_request(data: bytes) -> tuple[int, int]:
    """(command, sample_count) of an RDT request; ValueError when it is not one."""
    if len(data) != REQUEST.size:
        raise ValueError(f"RDT request is {REQUEST.size} bytes, got {len(data)}")
    header, command, count = REQUEST.unpack(data)
    if header != RDT_HEADER:
        raise ValueError(f"RDT header 0x{header:04x}, expected 0x{RDT_HEADER:04x}")
    return command, count


def pack_record(rec: RdtRecord) -> bytes:
    """The 36-byte RDT record."""
    return RECORD.pack(rec.rdt_sequence, rec.ft_sequence, rec.status, *rec.counts)


def unpack_record(data: bytes) -> RdtRecord:
    """An RDT record from exactly 36 bytes; ValueError otherwise."""
    if len(data) != RECORD.size:
        raise ValueError(f"RDT record is {RECORD.size} bytes, got {len(data)}")
    rdt, ft, status, fx, fy, fz, tx, ty, tz = RECORD.unpack(data)
    return RdtRecord(rdt, ft, status, (fx, fy, fz, tx, ty, tz))


class NetFTSensor(StreamAccounting):
    """An ATI Net F/T at `host`:`port`, streaming RDT records at its configured rate.

    `open()` binds a UDP socket and requests infinite streaming; `read()` drains every
    datagram received (non-blocking) and returns the newest valid record as a wrench
    `Reading("wrench", (Fx, Fy, Fz, Tx, Ty, Tz))` in N and N·m, sensor frame. The socket is
    connected to the sensor, so datagrams from anyone else never arrive; a datagram that is
    not 36 bytes, or whose status has a bit of `status_mask` set, is dropped as bad;
    rdt_sequence jumps are counted as gaps.
    `close()` asks the sensor to stop streaming.
    """

    seq_modulo = SEQ_MODULO
    unit = "records"

    def __init__(
        self,
        host: str,
        port: int = RDT_PORT,
        *,
        counts_per_force: float = DEFAULT_COUNTS_PER_FORCE,
        counts_per_torque: float = DEFAULT_COUNTS_PER_TORQUE,
        status_mask: int = 0xFFFF_FFFF,
        on_event: EventSink = ignore_event,
    ) -> None:
        if not (counts_per_force > 0 and counts_per_torque > 0):
            raise ValueError("counts_per_force and counts_per_torque must be > 0")
        self.on_event = on_event
        self._host = host
        self._port = port
        self._cpf = float(counts_per_force)
        self._cpt = float(counts_per_torque)
        self._status_mask = status_mask
        self._sock: socket.socket | None = None
        self._init_accounting()
        self._records = 0
        self._requests = 0
        self._last_rx_s = 0.0

    @property
    def name(self) -> str:
        return f"netft {self._host}:{self._port}"

    @property
    def records(self) -> int:
        """Valid records received since construction."""
        return self._records

    def open(self) -> None:
        if self._sock is not None:
            return
        try:
            info = socket.getaddrinfo(self._host, self._port, socket.AF_INET, socket.SOCK_DGRAM)
            peer = info[0][4]
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            # A connected UDP socket takes the route's source address and lets the kernel
            # drop datagrams from anyone but the sensor.
            sock.connect(peer)
            sock.setblocking(False)
            sock.send(pack_request(CMD_START_STREAMING, 0))
        except OSError as e:
            raise SensorError(f"{self.name}: cannot open: {e}") from None
        self._sock = sock
        self._last_seq = None
        self._requests += 1
        self._last_rx_s = time.monotonic()

    @property
    def requests(self) -> int:
        """Start-streaming requests sent (more than one: the sensor went silent)."""
        return self._requests

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is None:
            return
        # An unreachable sensor needs no stop: it streams to nobody anyway.
        with contextlib.suppress(OSError):
            sock.send(pack_request(CMD_STOP_STREAMING, 0))
        sock.close()

    def set_hardware_bias(self) -> None:
        """Ask the Net F/T to zero itself (RDT 0x0042). The service biases in software."""
        if self._sock is None:
            raise SensorError(f"{self.name} is not open")
        self._sock.send(pack_request(CMD_SET_SOFTWARE_BIAS, 0))

    def read(self) -> Reading | None:
        sock = self._sock
        if sock is None:
            raise SensorError(f"{self.name} is not open")
        newest: RdtRecord | None = None
        while True:
            try:
                data = sock.recv(2048)
            except BlockingIOError:
                break
            except ConnectionRefusedError:
                continue  # an ICMP "port unreachable" for an earlier request: no sensor yet
            rec = self._take(data)
            if rec is not None:
                newest = rec
        now = time.monotonic()
        if newest is None:
            if now - self._last_rx_s > RESTART_AFTER_S:
                self._last_rx_s = now
                self._requests += 1
                # Unreachable now: the next attempt follows in RESTART_AFTER_S.
                with contextlib.suppress(OSError):
                    sock.send(pack_request(CMD_START_STREAMING, 0))
            return None
        self._last_rx_s = now
        c = newest.counts
        f, t = self._cpf, self._cpt
        values: Six = (c[0] / f, c[1] / f, c[2] / f, c[3] / t, c[4] / t, c[5] / t)
        return Reading("wrench", values, newest.rdt_sequence)

    def _take(self, data: bytes) -> RdtRecord | None:
        try:
            rec = unpack_record(data)
        except ValueError as e:
            self._reject("short", str(e))
            return None
        last = self._last_seq
        if not self._step(rec.rdt_sequence, refuse_late=True):
            self._reject("order", f"rdt_sequence {rec.rdt_sequence} after {last}")
            return None
        if rec.status & self._status_mask:
            self._reject("status", f"status 0x{rec.status:08x}")
            return None
        self._records += 1
        return rec

    def _reject(self, reason: str, message: str) -> None:
        self._bad_data(message, reason)
