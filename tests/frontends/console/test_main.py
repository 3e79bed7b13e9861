"""`telerobot console` as a process: it prints its URL, serves the page, starts its virtual
master, and leaves cleanly on SIGTERM (the master's close holds the arm)."""

from __future__ import annotations

import re
import signal
import sys
import urllib.request
from typing import Any

import pytest

from tests.bus.test_router import spawned
from tests.conftest import wait_until

pytestmark = [pytest.mark.system, pytest.mark.timeout(90)]


def test_console_process_serves_and_stops(net: Any) -> None:
    peer = net.node("test")  # the first node listens: the console connects to it
    alive = peer.alive
    argv = [sys.executable, "-m", "services.frontends.console", "--port", "0"]
    with spawned([*argv, "--connect", net.endpoint], merge_stderr=False) as console:
        line = console.expect(lambda _: True)
        m = re.fullmatch(r"console: (http://127\.0\.0\.1:(\d+))", line)
        assert m is not None, f"unexpected first line {line!r}"
        with urllib.request.urlopen(m.group(1) + "/", timeout=10) as reply:
            assert reply.status == 200
            assert b"<html" in reply.read(4096).lower()
        assert alive.wait("console", 10.0)
        assert alive.wait("master/console", 10.0)
        console.proc.send_signal(signal.SIGTERM)
        assert console.wait(20.0) == 0
        assert console.rest() == [line], console.lines
    # Both liveliness tokens go with the process.
    assert wait_until(lambda: not alive.is_alive("console"), 5.0, what="console token gone")
    assert wait_until(lambda: not alive.is_alive("master/console"), 5.0, what="master gone")


def test_the_in_process_master_does_not_listen_twice() -> None:
    from services.bus.config import NodeConfig
    from services.frontends.console.__main__ import master_node_config

    cfg = NodeConfig(listen=("tcp/0.0.0.0:7448",))
    assert master_node_config(cfg) == NodeConfig(connect=("tcp/127.0.0.1:7448",))
    cfg = NodeConfig(connect=("tcp/127.0.0.1:7447",), listen=("tcp/0.0.0.0:7448",))
    assert master_node_config(cfg) == NodeConfig(connect=("tcp/127.0.0.1:7447",))
