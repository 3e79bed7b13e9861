"""Two hosts and a NAT in network namespaces: the operator drives the arm over TLS.

Three namespaces of our own, with addresses that exist only inside them:

    robot 10.201.0.1 ─veth─ 10.201.0.2 nat 10.202.0.1 ─veth─ 10.202.0.2 operator
                                     (nft masquerade)        (default route via the nat)

The robot namespace has no route to 10.202.0.0/24 and the nat lets no connection in from the
robot side, so only the operator can open connections, as behind a home or campus NAT; no
namespace routes anywhere else. The robot namespace runs the router and arm, force and
decision from deploy/robot.toml (simulated arm and sensor via flags); the operator namespace
runs the scripted master from deploy/operator.toml and a probe session that logs in as the
operator, calls the decision server to connect and initialize the arm, and then watches
robot/state and robot/force over TLS through the NAT. The probe also logs in with the robot
host's own password from off the host: the router's ACL, which wants the loopback interface
for that login, must not deliver its puts to robot/arm/target.

Needs root, iproute2 and nftables (`make system-deps`); skipped with the reason otherwise.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.bus.test_router import ChildProcess
from tests.deploy.cell import install

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

ROBOT_IP = "10.201.0.1"
NAT_ROBOT_SIDE_IP = "10.201.0.2"
NAT_OPERATOR_SIDE_IP = "10.202.0.1"
OPERATOR_IP = "10.202.0.2"
STEP_S = 30.0
MOVED_M = 0.02
FORCE_SAMPLES = 300

PROBE = r"""
import json, math, sys, threading, time
from dataclasses import replace
from services.bus import codec, keys
from services.bus.config import NodeConfig, load_deploy, section
from services.bus.messages import ArmTarget
from services.bus.node import Node

profile, endpoint, robot_login, robot_tcp = sys.argv[1:5]
deploy = load_deploy(profile)
cfg = replace(section(NodeConfig, deploy["zenoh"], "zenoh"), connect=(endpoint,))
by_master = {}
lock = threading.Lock()

def count(m):
    with lock:
        by_master[m.master] = by_master.get(m.master, 0) + 1

def counts():
    with lock:
        return dict(by_master)

def control():
    return sum(v for k, v in counts().items() if k != "intruder")

with Node("probe", cfg) as node:
    state = node.subscribe(keys.STATE)
    force = node.subscribe(keys.FORCE)
    node.subscribe(keys.ARM_TARGET, count)
    assert node.alive.wait("arm", 30) and node.alive.wait("force", 30), node.alive.names()
    print("connect", json.dumps(node.call("decision", "connect", {}, 10)), flush=True)
    print("initialize", json.dumps(node.call("decision", "initialize", {}, 10)), flush=True)
    s = state.wait_for(lambda m: m.status == "ready", 30)
    assert s is not None, state.latest
    p0 = s.tool_p
    print("ready", *p0, flush=True)

    def dist(m):
        return math.dist(m.tool_p, p0)

    moved = state.wait_for(lambda m: dist(m) > float(sys.argv[5]), 40)
    assert moved is not None, (state.latest, p0)
    print("moved", dist(moved), moved.cmd_seq, flush=True)

    # The robot's own password from off the robot host: it logs in, but matches no subject.
    intruder_cfg = NodeConfig(mode="client", connect=(robot_tcp,), zenoh_config=robot_login)
    with Node("intruder", intruder_cfg) as intruder:
        control0 = control()
        i = 0
        deadline = time.monotonic() + 20
        while control() < control0 + 50:
            assert time.monotonic() < deadline, counts()
            i += 1
            # a raw put is sent whether or not the client knows a subscriber: only the
            # router's ACL stands in its way
            now = time.time_ns()
            msg = ArmTarget(seq=i, t_ns=now, origin_t_ns=now, master="intruder", engage=1,
                            p=p0, R=(1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0))
            intruder.session.put(keys.ARM_TARGET.key, codec.encode(msg), encoding=keys.ENCODING)
            time.sleep(0.002)
        print("intruder", i, json.dumps(counts()), flush=True)

    n0 = force.received
    assert force.wait_count(n0 + int(sys.argv[6]), 30), force.received
    print("force", force.received - n0, force.latest.seq, flush=True)
"""


def run(*argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=30, check=False)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip()}")
    return done


@dataclass(frozen=True, slots=True)
class Namespaces:
    robot: str
    nat: str
    operator: str

    def all(self) -> tuple[str, str, str]:
        return (self.robot, self.nat, self.operator)


def netns_unavailable() -> str | None:
    """Why the NAT test cannot run here, or None."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "needs root to create network namespaces (CI runs it as root)"
    for tool, package in (("ip", "iproute2"), ("nft", "nftables")):
        if shutil.which(tool) is None:
            return f"no `{tool}` (apt-get install {package}; `make system-deps`)"
    return None


def build(ns: Namespaces) -> None:
    """The three namespaces, their veths, the routes and the masquerade."""
    tag = str(os.getpid() % 100000)
    r_if, n_r_if, n_o_if, o_if = (f"tr{tag}{s}" for s in ("r", "nr", "no", "o"))
    for name in ns.all():
        run("ip", "netns", "add", name)
    run(*f"ip link add {r_if} netns {ns.robot} type veth peer {n_r_if} netns {ns.nat}".split())
    run(*f"ip link add {o_if} netns {ns.operator} type veth peer {n_o_if} netns {ns.nat}".split())
    for name, ifname, cidr in (
        (ns.robot, r_if, f"{ROBOT_IP}/24"),
        (ns.nat, n_r_if, f"{NAT_ROBOT_SIDE_IP}/24"),
        (ns.nat, n_o_if, f"{NAT_OPERATOR_SIDE_IP}/24"),
        (ns.operator, o_if, f"{OPERATOR_IP}/24"),
    ):
        run("ip", "-n", name, "addr", "add", cidr, "dev", ifname)
        run("ip", "-n", name, "link", "set", ifname, "up")
    for name in ns.all():
        run("ip", "-n", name, "link", "set", "lo", "up")
    # Only the operator has a default route, and it ends at the nat, which has none.
    run("ip", "-n", ns.operator, "route", "add", "default", "via", NAT_OPERATOR_SIDE_IP)
    run("ip", "netns", "exec", ns.nat, "sh", "-c", "echo 1 > /proc/sys/net/ipv4/ip_forward")
    rules = f"""
table ip telerobot_nat {{
  chain forward {{
    type filter hook forward priority filter; policy drop;
    ct state established,related accept
    iifname "{n_o_if}" oifname "{n_r_if}" accept
  }}
  chain postrouting {{
    type nat hook postrouting priority srcnat; policy accept;
    oifname "{n_r_if}" masquerade
  }}
}}
"""
    done = subprocess.run(
        ["ip", "netns", "exec", ns.nat, "nft", "-f", "-"],
        input=rules,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"nft: {done.stderr.strip()}")


@contextlib.contextmanager
def namespaces() -> Iterator[Namespaces]:
    reason = netns_unavailable()
    if reason:
        pytest.skip(reason)
    tag = f"telerobot-{os.getpid()}"
    ns = Namespaces(f"{tag}-robot", f"{tag}-nat", f"{tag}-operator")
    try:
        try:
            build(ns)
        except RuntimeError as e:
            if "Operation not permitted" in str(e) or "Permission denied" in str(e):
                pytest.skip(f"network namespace setup refused: {e}")
            raise
        yield ns
    finally:
        # Deleting a namespace deletes its veth ends (and their peers) and its nft table.
        for name in ns.all():
            run("ip", "netns", "delete", name, check=False)


def in_ns(ns: str, *argv: str) -> list[str]:
    return ["ip", "netns", "exec", ns, sys.executable, *argv]


def telerobot_in(ns: str, *args: str) -> list[str]:
    return in_ns(ns, "-m", "services.tools.cli.main", *args)


def test_scripted_master_drives_the_arm_through_a_nat_over_tls(tmp_path: Path) -> None:
    with namespaces() as ns, contextlib.ExitStack() as stack:
        cell = install(tmp_path / "etc", hosts=(ROBOT_IP,))
        robot_profile, operator_profile = str(cell.profile("robot")), str(cell.profile("operator"))
        tls = f"tls/{ROBOT_IP}:7448"

        def start(argv: list[str]) -> ChildProcess:
            child = ChildProcess(argv)
            stack.callback(child.stop)
            return child

        router = start(telerobot_in(ns.robot, "router", "--config", robot_profile))
        line = router.expect("router up", STEP_S)
        assert "tls/0.0.0.0:7448" in line, line
        start(telerobot_in(ns.robot, "arm", "--config", robot_profile, "--driver", "sim"))
        start(
            telerobot_in(
                ns.robot,
                "force",
                "--config",
                robot_profile,
                "--sensor",
                "sim",
                "--priority",
                "normal",
            )
        )
        start(telerobot_in(ns.robot, "decision", "--config", robot_profile))

        probe = start(
            in_ns(
                ns.operator,
                "-c",
                PROBE,
                operator_profile,
                tls,
                str(cell.client_file("robot-local")),
                f"tcp/{ROBOT_IP}:7447",
                str(MOVED_M),
                str(FORCE_SAMPLES),
            )
        )
        probe.expect("ready", 60)
        master = start(
            telerobot_in(
                ns.operator,
                "master",
                "--config",
                operator_profile,
                "--device",
                "script",
                "--connect",
                tls,
            )
        )
        moved = probe.expect("moved", 60).split()
        assert float(moved[1]) > MOVED_M
        intruder = probe.expect("intruder", STEP_S)
        counts = json.loads(intruder.split(" ", 2)[2])
        assert counts.get("intruder", 0) == 0, intruder
        assert sum(counts.values()) >= 50, intruder
        force = probe.expect("force", STEP_S).split()
        assert int(force[1]) >= FORCE_SAMPLES
        assert probe.wait(STEP_S) == 0, probe.lines
        assert master.proc.poll() is None, master.lines
