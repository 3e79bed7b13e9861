"""Shared fixtures: Zenoh peers in-process on free loopback ports, multicast scouting off."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator

import pytest

from services.bus.config import NodeConfig
from services.bus.node import Node


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(pred: Callable[[], bool], timeout_s: float = 10.0, poll_s: float = 0.005) -> bool:
    """Poll `pred` until it holds or the deadline passes (for state with no condition to
    wait on); whether it held."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)
    return True


class Net:
    """A private Zenoh network for one test: the first node listens, the rest connect to it."""

    def __init__(self, ns: str = "") -> None:
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.ns = ns
        self.nodes: list[Node] = []

    def config(self, listen: bool = False) -> NodeConfig:
        if listen:
            return NodeConfig(mode="peer", listen=(self.endpoint,), ns=self.ns)
        return NodeConfig(mode="peer", connect=(self.endpoint,), ns=self.ns)

    def node(self, name: str, instance: str | None = None) -> Node:
        n = Node(name, self.config(listen=not self.nodes), instance=instance)
        self.nodes.append(n)
        return n

    def close(self) -> None:
        for n in reversed(self.nodes):
            n.close()
        self.nodes.clear()


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
