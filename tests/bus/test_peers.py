"""`services.bus.peers.Peers`: one process's nodes as a private Zenoh network."""

from __future__ import annotations

from services.bus.config import NodeConfig
from services.bus.peers import Clients, Peers, free_loopback_endpoint


def test_nodes_find_each_other_and_keep_the_given_settings() -> None:
    peers = Peers(config=NodeConfig(lease_ms=2000))
    try:
        assert peers.endpoint.startswith("tcp/127.0.0.1:")
        a, b = peers.node("a"), peers.node("b", instance="x")
        b.announce()
        assert a.alive.wait("b/x", 10.0), a.alive.names()
        cfg_a, cfg_b = a.config, b.config
        assert cfg_a.listen == (peers.endpoint,) and cfg_a.connect == ()
        assert cfg_b.connect == (peers.endpoint,) and cfg_b.listen == ()
        assert cfg_a.lease_ms == cfg_b.lease_ms == 2000
        assert cfg_a.mode == cfg_b.mode == "peer"
    finally:
        peers.close()
    assert peers.nodes == []
    assert a.closed and b.closed


def test_free_endpoints_are_loopback() -> None:
    assert free_loopback_endpoint().startswith("tcp/127.0.0.1:")


def test_clients_all_connect_to_the_router_and_never_listen() -> None:
    from services.bus.router import open_router

    peers = Peers()
    router = open_router(NodeConfig(mode="router", listen=(peers.endpoint,)))
    clients = Clients(peers.endpoint, NodeConfig(lease_ms=1500))
    try:
        a, b = clients.node("a"), clients.node("b")
        b.announce()
        assert a.alive.wait("b", 10.0), a.alive.names()
        for n in (a, b):
            assert n.config.mode == "client" and n.config.listen == ()
            assert n.config.connect == (peers.endpoint,) and n.config.lease_ms == 1500
    finally:
        clients.close()
        router.close()
    assert clients.nodes == []
