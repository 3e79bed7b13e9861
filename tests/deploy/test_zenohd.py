"""The robot and operator profiles through zenohd, the Rust router, with the deployment's JSON5.

zenohd is what labs run (and rmw_zenoh, and the eclipse/zenoh image of
deploy/compose/robot.yml); our Python router embeds the same Rust core, but this runs the
real binary: `zenohd -c robot-router.json5` (TLS, the usrpwd logins, the ACL, the QoS
rules), built by `make zenohd` for the installed eclipse-zenoh's release. Skipped, with the
reason, where that binary is absent.

The cell is installed as in test_profiles.py (prefix and ports rewritten, no hardware);
the robot profile's [up] runs everything but its own router. Checked: every service and
the station come up through zenohd; the operator, over TLS, initializes the arm through
the decision and moves it with the console's virtual master, and gets robot/force; the
ACL refuses the operator's raw robot/arm/target and a direct call to the arm; SIGTERM
stops both launchers cleanly, and zenohd with them.
"""

from __future__ import annotations

import math
import signal
import time
from pathlib import Path

import pytest

from services.bus import codec, keys
from services.bus.config import NodeConfig
from services.bus.errors import Unavailable
from services.bus.messages import ArmTarget
from services.bus.node import Node
from tests.bus.test_router import ChildProcess, spawned, telerobot
from tests.conftest import free_port, wait_until
from tests.deploy.cell import edit, install, without_hardware
from tests.deploy.probe import (
    EYE,
    ZENOH_VERSION,
    Watch,
    router_listens,
    sweep,
    take_lease,
    zenohd_binary,
)

pytestmark = [pytest.mark.system, pytest.mark.timeout(240)]

DEADLINE_S = 60.0
STOP_S = 30.0
WANT = {
    "arm",
    "force",
    "decision",
    "vision",
    "ros2",
    "master/station1",
    "console",
    "master/console",
}


def stop(launcher: ChildProcess) -> int:
    launcher.proc.send_signal(signal.SIGTERM)
    return launcher.wait(STOP_S)


def intrude(node: Node, p: tuple[float, ...]) -> None:
    """50 raw puts to robot/arm/target: sent whatever the client knows of subscribers, so
    only the router's ACL stands in their way."""
    for i in range(50):
        now = time.time_ns()
        msg = ArmTarget(
            seq=10**9 + i, t_ns=now, origin_t_ns=now, master="intruder", engage=10**6,
            p=p, R=tuple(EYE),
        )  # fmt: skip
        node.session.put(keys.ARM_TARGET.key, codec.encode(msg), encoding=keys.ENCODING)
        time.sleep(0.01)


def test_robot_and_operator_profiles_through_zenohd(tmp_path: Path) -> None:
    zenohd = zenohd_binary()
    if zenohd is None:
        pytest.skip(f"no zenohd {ZENOH_VERSION} (make zenohd builds it with cargo)")
    cell = install(tmp_path, ports=(free_port(), free_port()))
    without_hardware(cell, free_port(), 'device = "virtual"\nengage_on_start = false')
    edit(cell.profile("robot"), ('services = ["router", ', "services = ["))
    router_json5 = cell.client_file("robot-router")
    with spawned([str(zenohd), "-c", str(router_json5)]) as router:
        assert router_listens(cell.tcp_port, cell.tls_port, timeout_s=DEADLINE_S), router.lines
        with spawned(telerobot("up", str(cell.profile("robot")))) as robot:
            with spawned(telerobot("up", str(cell.profile("operator")))) as station:
                operator = NodeConfig(
                    mode="client",
                    connect=(f"tls/localhost:{cell.tls_port}",),
                    zenoh_config=str(cell.client_file("operator-client")),
                )
                with Node("zenohd-probe", operator) as node:
                    w = Watch()
                    w.subscribe(node)
                    up = wait_until(lambda: node.alive.names() >= WANT, DEADLINE_S, poll_s=0.1)
                    missing = f"missing {sorted(WANT - node.alive.names())}"
                    lines = [missing, *router.lines[-20:], *robot.lines[-30:], *station.lines[-20:]]
                    assert up, "\n".join(lines)
                    status = node.call("decision", "status", {}, DEADLINE_S)
                    assert WANT - {"decision"} <= set(status["alive"]), status["alive"]

                    # a supervised move through the console's master, over TLS
                    node.call("decision", "connect", {}, DEADLINE_S)
                    node.call("decision", "initialize", {}, DEADLINE_S)
                    ready = wait_until(lambda: w.state().status == "ready", DEADLINE_S)
                    assert ready, w.snapshot(w.states)[-1:]
                    p0 = w.state().tool_p
                    take_lease(node, (0.0, 0.0, 0.0))
                    sweep(node, 0.0, 0.04, 40)
                    moved = wait_until(lambda: math.dist(w.state().tool_p, p0) > 0.02, DEADLINE_S)
                    assert moved, "\n".join(
                        f"{e.source} {e.kind} {e.message} {e.data}" for e in w.snapshot(w.events)
                    )
                    lease = node.call("decision", "status", {}, DEADLINE_S)["lease"]
                    assert lease == "console", lease
                    n = len(w.snapshot(w.force))
                    assert wait_until(lambda: len(w.snapshot(w.force)) >= n + 500, DEADLINE_S)

                    # the ACL: an operator's raw arm target never reaches the robot host (a
                    # session there, the robot login on loopback), nor a call to the arm
                    local = NodeConfig(
                        mode="client",
                        connect=(f"tcp/127.0.0.1:{cell.tcp_port}",),
                        zenoh_config=str(cell.client_file("robot-local")),
                    )
                    robot_side = Watch()
                    with Node("zenohd-robot-side", local) as there:
                        there.subscribe(
                            keys.ARM_TARGET, lambda m: robot_side.add(robot_side.targets, m)
                        )
                        assert wait_until(lambda: len(robot_side.snapshot(robot_side.targets)) > 5)
                        intrude(node, p0)
                        # the decision's own targets (≥ 20 Hz holds or follows) keep arriving
                        t0 = len(robot_side.snapshot(robot_side.targets))
                        more = wait_until(
                            lambda: len(robot_side.snapshot(robot_side.targets)) >= t0 + 40,
                            DEADLINE_S,
                        )
                        assert more, len(robot_side.snapshot(robot_side.targets)) - t0
                        seen = {t.master for t in robot_side.snapshot(robot_side.targets)}
                        assert seen == {"decision"}, seen
                    with pytest.raises(Unavailable):
                        node.call("arm", "status", {}, 2.0)
                assert stop(station) == 0, station.rest()[-20:]
            assert stop(robot) == 0, robot.rest()[-30:]
            lines = robot.rest()
        # zenohd has no handler for SIGTERM (nor SIGINT): it ends by the signal
        router.proc.send_signal(signal.SIGTERM)
        assert router.wait(STOP_S) == -signal.SIGTERM, router.lines[-10:]
    for service in ("arm", "force", "decision", "vision", "ros2"):
        assert f"[{service}] stopped (exit 0)" in lines, (service, lines[-30:])
