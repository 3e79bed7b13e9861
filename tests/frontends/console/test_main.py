"""`telerobot console` as a process: it prints its URL, serves the page, starts its virtual
master, and leaves cleanly on SIGTERM (the master's close holds the arm)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import wait_until

pytestmark = [pytest.mark.system, pytest.mark.timeout(90)]

ROOT = Path(__file__).resolve().parents[3]


def test_console_process_serves_and_stops(net: Any) -> None:
    peer = net.node("test")  # the first node listens: the console connects to it
    alive = peer.alive
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.frontends.console",
            "--port",
            "0",
            "--connect",
            net.endpoint,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        m = re.fullmatch(r"console: (http://127\.0\.0\.1:(\d+))\n", line)
        assert m is not None, f"unexpected first line {line!r}"
        with urllib.request.urlopen(m.group(1) + "/", timeout=10) as reply:
            assert reply.status == 200
            assert b"<html" in reply.read(4096).lower()
        assert alive.wait("console", 10.0)
        assert alive.wait("master/console", 10.0)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
        rest = proc.stdout.read()
        assert rest == "", rest
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()  # reaps it and closes both pipes
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
