"""A Zenoh network of one process's nodes: the first node listens, the others connect to it
(`Peers`), or all are clients of one router (`Clients`).

For in-process systems (the headless tasks, the link bench's robot side) that want their
services on separate nodes, as in deployment, without a router: `Peers().node("arm")`.
Multicast scouting stays off (`NodeConfig`'s default); by default the endpoint is a free
port on loopback.
"""

from __future__ import annotations

import socket
from dataclasses import replace

from services.bus.config import NodeConfig
from services.bus.node import Node


def free_loopback_endpoint() -> str:
    """`tcp/127.0.0.1:<a port free just now>`."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{int(sock.getsockname()[1])}"


class Peers:
    """`endpoint`: where the first node listens (and the others and other processes
    connect); `config`: the rest of every node's settings (mode, listen and connect are set
    here)."""

    def __init__(self, endpoint: str | None = None, config: NodeConfig | None = None) -> None:
        self.endpoint = endpoint or free_loopback_endpoint()
        self._base = config or NodeConfig()
        self.nodes: list[Node] = []

    def config(self, listen: bool = False) -> NodeConfig:
        """A node's settings: listening on the endpoint, or connecting to it."""
        return replace(
            self._base,
            mode="peer",
            listen=(self.endpoint,) if listen else (),
            connect=() if listen else (self.endpoint,),
        )

    def node(self, name: str, instance: str | None = None) -> Node:
        n = Node(name, self.config(listen=not self.nodes), instance=instance)
        self.nodes.append(n)
        return n

    def close(self) -> None:
        for n in reversed(self.nodes):
            n.close()
        self.nodes.clear()


class Clients(Peers):
    """Every node a client of the router at `endpoint` (none listens)."""

    def config(self, listen: bool = False) -> NodeConfig:
        return replace(self._base, mode="client", listen=(), connect=(self.endpoint,))
