"""The baselines the bench measures beside the system, on the same machine in the same run.

- The floor: the very bytes of a ForceSample (msgpack, as on `robot/force`) sent at 1 kHz
  from another process over one raw TCP connection on 127.0.0.1 with TCP_NODELAY, each
  framed by a 4-byte length. Nothing is cheaper between two processes on one host.
- A remoting baseline: a method call over XML-RPC from the standard library (HTTP + XML,
  the SOAP-like remoting the paper's .NET Remoting used), served by another process with
  keep-alive and TCP_NODELAY so that neither connection set-up nor Nagle's delay is counted.

The other side of each runs as a child process (`python -m services.tools.bench.baselines
tcp-send|xmlrpc-serve`), started with subprocess like the services.
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import subprocess
import sys
import time
import xmlrpc.client
from dataclasses import dataclass
from typing import Any
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

import msgpack
import numpy as np

from services.bus import codec
from services.bus.messages import ForceSample
from services.bus.rate import RateLoop
from services.tools.cell.procs import Child

HEADER = struct.Struct(">I")
XMLRPC_INT_MAX = 2**31 - 1
STARTUP_TIMEOUT_S = 20.0


FORCE_F_N = (0.12, -0.05, -2.45)
FORCE_C_NM = (0.011, 0.024, -0.002)
FORCE_RAW = (0.0012, -0.0004, 0.0251, 0.0011, 0.0024, -0.0002)


def force_payload(seq: int, t_ns: int) -> bytes:
    """The msgpack bytes of a ForceSample with every field, exactly as `codec.encode` gives
    them (a test holds them equal), packed directly: a floor sender does no validation."""
    return msgpack.packb(
        {"seq": seq, "t_ns": t_ns, "f": list(FORCE_F_N), "c": list(FORCE_C_NM),
         "raw": list(FORCE_RAW)},
        use_bin_type=True,
    )  # fmt: skip


# --- the TCP floor ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TcpRun:
    """What the receiving end of the TCP floor recorded.

    rx_ns[i] is when the recv() that completed message i returned; t_ns[i] and seq[i] are
    decoded from it. `sent` is the sender's own count (its exit report).
    """

    rx_ns: np.ndarray
    t_ns: np.ndarray
    seq: list[int]
    sent: int
    duration_s: float
    payload_bytes: int


def tcp_floor(rate_hz: float, duration_s: float, timeout_s: float = 30.0) -> TcpRun:
    """Receive ForceSamples from a sender process at `rate_hz` for `duration_s` (loopback)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as srv:
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        srv.settimeout(STARTUP_TIMEOUT_S)
        port = srv.getsockname()[1]
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.tools.bench.baselines",
                "tcp-send",
                "--port",
                str(port),
                "--rate-hz",
                str(rate_hz),
                "--duration-s",
                str(duration_s),
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
        try:
            conn, _ = srv.accept()
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.settimeout(timeout_s)
                rx, tx, seqs, size = _receive_frames(conn)
            out, err = proc.communicate(timeout=timeout_s)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    if proc.returncode != 0:
        raise RuntimeError(f"tcp sender failed ({proc.returncode}): {err.decode(errors='replace')}")
    sent = int(out.decode().split()[-1])
    return TcpRun(
        rx_ns=np.asarray(rx, dtype=np.int64),
        t_ns=np.asarray(tx, dtype=np.int64),
        seq=seqs,
        sent=sent,
        duration_s=duration_s,
        payload_bytes=size,
    )


def _receive_frames(conn: socket.socket) -> tuple[list[int], list[int], list[int], int]:
    rx: list[int] = []
    tx: list[int] = []
    seqs: list[int] = []
    size = 0
    buf = bytearray()
    while True:
        chunk = conn.recv(65536)
        now = time.time_ns()
        if not chunk:
            return rx, tx, seqs, size
        buf += chunk
        while len(buf) >= HEADER.size:
            (n,) = HEADER.unpack_from(buf)
            if len(buf) < HEADER.size + n:
                break
            payload = bytes(buf[HEADER.size : HEADER.size + n])
            del buf[: HEADER.size + n]
            # Decoded and validated like the bus probe does, so both sides pay the same.
            msg = codec.decode(ForceSample, payload)
            rx.append(now)
            tx.append(msg.t_ns)
            seqs.append(msg.seq)
            size = n


def tcp_send(port: int, rate_hz: float, duration_s: float) -> int:
    """The sending end: stamp, encode and send one ForceSample per tick; the count sent."""
    sent = 0
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        loop = RateLoop(rate_hz)
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            sent += 1
            payload = force_payload(sent, time.time_ns())
            sock.sendall(HEADER.pack(len(payload)) + payload)
            loop.sleep()
        sock.shutdown(socket.SHUT_WR)
    return sent


# --- XML-RPC -----------------------------------------------------------------------------


class _KeepAliveHandler(SimpleXMLRPCRequestHandler):
    # HTTP/1.1 keeps the connection open between calls, as a remoting channel does; without
    # TCP_NODELAY the reply's headers and body would wait on Nagle's algorithm.
    protocol_version = "HTTP/1.1"
    disable_nagle_algorithm = True
    rpc_paths = ("/RPC2",)


def xmlrpc_safe(obj: Any) -> Any:
    """`obj` as XML-RPC can carry it: integers beyond 32 bits become floats, keys strings."""
    if isinstance(obj, bool) or obj is None or isinstance(obj, str | float):
        return obj
    if isinstance(obj, int):
        return obj if -XMLRPC_INT_MAX - 1 <= obj <= XMLRPC_INT_MAX else float(obj)
    if isinstance(obj, dict):
        return {str(k): xmlrpc_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [xmlrpc_safe(v) for v in obj]
    return str(obj)


def xmlrpc_serve(reply: dict[str, Any]) -> None:
    """Serve `status()` → `reply` on a free port of 127.0.0.1; print "port N"; run forever."""
    server = SimpleXMLRPCServer(
        ("127.0.0.1", 0), requestHandler=_KeepAliveHandler, logRequests=False, allow_none=True
    )
    server.register_function(lambda: reply, "status")
    print(f"port {server.server_address[1]}", flush=True)
    with server:
        server.serve_forever()


def xmlrpc_round_trips(reply: dict[str, Any], n: int, timeout_s: float = 30.0) -> list[float]:
    """Round trips (ms) of `n` sequential `status()` calls to a server process replying
    `reply` (made XML-RPC-safe). Each reply is checked against `reply`."""
    safe = xmlrpc_safe(reply)
    server = Child(
        "xmlrpc-serve",
        [sys.executable, "-m", "services.tools.bench.baselines", "xmlrpc-serve"],
        lines=True,
        errors_apart=True,
        stdin=subprocess.PIPE,
    ).start()
    try:
        assert server.proc is not None and server.proc.stdin is not None
        server.proc.stdin.write(json.dumps(safe).encode())
        server.proc.stdin.close()
        try:
            line = server.expect(lambda _: True, timeout_s).strip()
        except AssertionError as e:
            if server.wait(1.0) is None:
                raise TimeoutError(
                    f"no reply from the baseline server within {timeout_s:g} s"
                ) from e
            line = ""  # it ended without a word
        if not line.startswith("port "):
            raise RuntimeError(f"xmlrpc server did not start: {line!r}")
        port = int(line.split()[1])
        out: list[float] = []
        with xmlrpc.client.ServerProxy(f"http://127.0.0.1:{port}/RPC2", allow_none=True) as sp:
            for _ in range(n):
                t0 = time.perf_counter()
                got = sp.status()
                out.append((time.perf_counter() - t0) * 1e3)
                if got != safe:
                    raise RuntimeError("xmlrpc status() replied something else")
        return out
    finally:
        server.stop()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m services.tools.bench.baselines", description=__doc__
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("tcp-send", help="the sending end of the TCP floor")
    s.add_argument("--port", type=int, required=True)
    s.add_argument("--rate-hz", type=float, default=1000.0)
    s.add_argument("--duration-s", type=float, default=5.0)
    sub.add_parser("xmlrpc-serve", help="serve status() with the JSON map read from stdin")
    args = p.parse_args(argv)
    if args.cmd == "tcp-send":
        print(f"sent {tcp_send(args.port, args.rate_hz, args.duration_s)}", flush=True)
        return 0
    reply = json.loads(sys.stdin.read() or "{}")
    try:
        xmlrpc_serve(reply)
    except KeyboardInterrupt:
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
