"""Loopback ports: free ones outside the ephemeral range, each handed out once."""

from __future__ import annotations

import socket

from services.tools.cell.ports import PORTS_FROM, free_port, free_udp_port, port_open


def test_free_ports_are_distinct_bindable_and_below_the_ephemeral_range() -> None:
    ports = [free_port() for _ in range(20)]
    assert len(set(ports)) == len(ports)
    assert all(PORTS_FROM <= p < 32_768 for p in ports)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", ports[0]))


def test_port_open_sees_a_listener_and_its_absence() -> None:
    port = free_port()
    assert not port_open(port)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", port))
        s.listen()
        assert port_open(port)


def test_a_free_udp_port_binds() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", free_udp_port()))
