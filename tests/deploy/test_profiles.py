"""`telerobot up` runs the shipped robot and operator profiles as two hosts would.

The profiles are installed from deploy/ like in test_security.py (prefix and ports
rewritten), plus the edits a lab makes to try a cell without hardware: the simulated arm,
sensor and cameras on the robot host, the scripted master on the station, which dials the
router at localhost. Both launchers start every child; the station's master and console
and the robot's services see each other through the router's ACL (liveliness tokens,
`decision status`); SIGTERM stops each launcher cleanly.
"""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from services.bus.config import NodeConfig
from services.bus.node import Node
from tests.bus.test_router import ChildProcess, spawned, telerobot
from tests.conftest import free_port, wait_until
from tests.deploy.cell import install, without_hardware

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

DEADLINE_S = 45.0
STOP_S = 30.0
ROBOT_SERVICES = {"arm", "force", "decision", "vision"}
STATION = {"master/station1", "console", "master/console"}


def stop(launcher: ChildProcess) -> int:
    """SIGTERM, as systemd or Ctrl-C would; the launcher stops its children in turn (each
    within its `stop_timeout_s`), so allow it more than ChildProcess.stop's 5 s."""
    launcher.proc.send_signal(signal.SIGTERM)
    return launcher.wait(STOP_S)


def test_robot_and_operator_profiles_come_up_together(tmp_path: Path) -> None:
    """The station is switched on first, as an operator may: its services wait for the
    robot host's router (fresh-clone CI 2026-12-02: started together, the station's master
    and console found no router yet, exited, and the launcher gave up)."""
    cell = install(tmp_path, ports=(free_port(), free_port()))
    without_hardware(cell, free_port())
    with spawned(telerobot("up", str(cell.profile("operator")))) as station:
        for service in ("master", "console"):
            station.expect(lambda s, n=service: s.startswith(f"[{n}]") and "Trying again" in s)
        with spawned(telerobot("up", str(cell.profile("robot")))) as robot:
            cfg = NodeConfig(
                mode="client",
                connect=(f"tcp/127.0.0.1:{cell.tcp_port}",),
                zenoh_config=str(cell.client_file("robot-local")),
            )
            with Node("check", cfg) as node:
                want = ROBOT_SERVICES | STATION
                up = wait_until(lambda: want <= node.alive.names(), DEADLINE_S, poll_s=0.1)
                # Strings, so that pytest prints every line of both launchers on a miss.
                missing = f"missing {sorted(want - node.alive.names())}"
                assert up, "\n".join([missing, *station.so_far()[-40:], *robot.so_far()[-40:]])
                status = node.call("decision", "status", {}, DEADLINE_S)
                assert want <= set(status["alive"]), status["alive"]
            for service in ("master", "console"):
                station.expect(lambda s, n=service: s.startswith(f"[{n}]") and "connected to" in s)
            assert stop(robot) == 0, robot.rest()[-30:]
            lines = robot.rest()
        assert stop(station) == 0, station.rest()[-20:]
    for service in ROBOT_SERVICES | {"router"}:
        assert f"[{service}] stopped (exit 0)" in lines, (service, lines[-30:])
