"""Shared fixtures: Zenoh peers in-process on free loopback ports, multicast scouting off."""

from __future__ import annotations

import os
import random
import socket
import time
from collections.abc import Callable, Iterator

import pytest
from hypothesis import HealthCheck, settings

from services.bus.config import NodeConfig
from services.bus.peers import Peers

# Hypothesis's timing checks (a 200 ms deadline per example, "input generation is slow")
# measure the machine, not the property: on two shared cores, with a second pytest worker,
# they fail at random. Off by default for the whole suite; example counts stay per test.
settings.register_profile("suite", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("suite")


PORTS_FROM = 20_000
"""Test ports are taken below Linux's ephemeral range (32768–60999 by default), in a slice
of 1 000 per pytest-xdist worker. A port the kernel handed out by `bind(0)` comes from the
range it also gives every outgoing connection its local port from: between the test taking
it and a router binding it, a Zenoh client of a parallel test could connect from it, and
the router's listener failed (fresh-clone CI 2026-11-27: the operator profile never reached
the robot's router over TLS, its three services missing after 45 s)."""
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


class Waited:
    """What `wait_until` saw: truthy iff the condition held before the deadline.

    Its repr names the condition and the deadline, so a bare `assert wait_until(...)`
    fails with a message that says what never happened (and `assert not wait_until(...)`
    says what happened when it should not have).
    """

    __slots__ = ("elapsed_s", "held", "timeout_s", "what")

    def __init__(self, held: bool, what: str, timeout_s: float, elapsed_s: float) -> None:
        self.held, self.what = held, what
        self.timeout_s, self.elapsed_s = timeout_s, elapsed_s

    def __bool__(self) -> bool:
        return self.held

    def __repr__(self) -> str:
        if self.held:
            return f"<{self.what} held after {self.elapsed_s:.2f} s>"
        return f"<timed out: {self.what} still false after {self.timeout_s:g} s>"


def _describe(pred: Callable[[], object]) -> str:
    """A name for a condition: its function name, or where a lambda was written."""
    code = getattr(pred, "__code__", None)
    name = getattr(pred, "__qualname__", None) or repr(pred)
    if code is None or name.rpartition(".")[2] != "<lambda>":
        return name
    return f"lambda at {code.co_filename.rpartition('/')[2]}:{code.co_firstlineno}"


def wait_until(
    pred: Callable[[], object],
    timeout_s: float = 10.0,
    poll_s: float = 0.005,
    *,
    what: str | None = None,
) -> Waited:
    """Poll `pred` until it holds or `timeout_s` passes (for state with no condition to wait
    on); the one waiting helper of the suite, never a bare sleep as synchronisation.

    Use as `assert wait_until(cond, 5.0, what="the arm at rest")`: the answer is truthy iff
    `pred` held, and a failure names `what` (or the condition) and the deadline. The
    deadline is generous on purpose (two shared, loaded cores); it bounds a failure, it never
    measures speed.
    """
    start = time.monotonic()
    deadline = start + timeout_s
    while not pred():
        if time.monotonic() >= deadline:
            # One last look: a poll that slept past the deadline must not miss a late truth.
            held = bool(pred())
            return Waited(held, what or _describe(pred), timeout_s, time.monotonic() - start)
        time.sleep(poll_s)
    return Waited(True, what or _describe(pred), timeout_s, time.monotonic() - start)


class Net(Peers):
    """A private Zenoh network for one test: the first node listens on a free loopback port,
    the rest connect to it; `ns` prefixes every key."""

    def __init__(self, ns: str = "") -> None:
        self.port = free_port()
        self.ns = ns
        super().__init__(f"tcp/127.0.0.1:{self.port}", NodeConfig(ns=ns))


@pytest.fixture
def net() -> Iterator[Net]:
    n = Net()
    try:
        yield n
    finally:
        n.close()


@pytest.fixture
def make_net() -> Iterator[Callable[..., Net]]:
    nets: list[Net] = []

    def make(ns: str = "") -> Net:
        n = Net(ns)
        nets.append(n)
        return n

    try:
        yield make
    finally:
        for n in nets:
            n.close()
