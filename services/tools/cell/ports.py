"""Loopback ports: a free TCP or UDP port to listen on, and whether one accepts connections.

`free_port` takes its ports below Linux's ephemeral range (32768–60999 by default), in a
slice of 1 000 per pytest-xdist worker (`PYTEST_XDIST_WORKER`; any other process, the bench
included, is worker 0). A port the kernel handed out by `bind(0)` comes from the range it
also gives every outgoing connection its local port from: between the caller taking it and
a router binding it, a Zenoh client of a parallel test could connect from it, and the
router's listener failed (fresh-clone CI 2026-11-27: the operator profile never reached the
robot's router over TLS, its three services missing after 45 s).
"""

from __future__ import annotations

import os
import random
import socket

PORTS_FROM = 20_000
"""The first port of worker 0's slice (see the module docstring)."""
_given: set[int] = set()
_rng = random.Random(os.getpid())


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now, not handed out before by
    this process, and outside the kernel's ephemeral range (`PORTS_FROM`)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    lo = PORTS_FROM + (int(worker) % 12 if worker.isdigit() else 0) * 1_000
    for _ in range(200):
        port = _rng.randrange(lo, lo + 1_000)
        if port in _given:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _given.add(port)
        return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # the slice is full
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_udp_port() -> int:
    """A UDP port nobody holds on loopback now (QUIC listens on UDP)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def port_open(port: int) -> bool:
    """Whether something accepts TCP connections on 127.0.0.1:port."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0
