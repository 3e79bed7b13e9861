"""The robot host's router, started from the shipped profile and JSON5, enforces TLS,
user/password authentication and the access-control list by role.

The router is `telerobot router --config robot.toml` in a child process, configured from
the very files of deploy/ (installed into a temporary directory: only the /etc/telerobot/
prefix and the listen ports are rewritten). Clients are in-process client sessions on
loopback: the robot's own services log in as `robot` over `tcp/127.0.0.1`, the operator
and the observer over `tls/localhost` with the cell's CA.

Every denial is checked against an allowed flow of the same client at the same time (a key
the client may publish, delivered to the same subscriber), so a test cannot pass because
nothing flows at all. Denials are silent to the sender: a denied put simply never arrives.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from services.bus import codec, keys
from services.bus.config import NodeConfig
from services.bus.errors import ConnectFailed, RpcError, Unavailable
from services.bus.keys import ENCODING
from services.bus.messages import ArmTarget, OperatorCommand, RobotState
from services.bus.node import Node, Subscription
from tests.bus.test_node import wait_matched
from tests.bus.test_router import ChildProcess, spawned, telerobot
from tests.conftest import free_port, wait_until
from tests.deploy.cell import Cell, install

DEADLINE_S = 15.0
DELIVERED = 20
"""Allowed messages a test waits for before it judges the denied ones (all sent in between)."""
IDENTITY9 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def command(seq: int, master: str) -> OperatorCommand:
    return OperatorCommand(
        seq=seq,
        t_ns=time.time_ns(),
        master=master,
        engage=1,
        active=True,
        frame="world",
        dp=(0.0, 0.0, 0.0),
        dR=IDENTITY9,
    )


def target(seq: int, master: str) -> ArmTarget:
    now = time.time_ns()
    return ArmTarget(seq=seq, t_ns=now, origin_t_ns=now, master=master, engage=1,
                     p=(0.5, 0.0, 0.6), R=IDENTITY9)  # fmt: skip


def message(key: str, seq: int, master: str) -> OperatorCommand | ArmTarget:
    """What a sender puts on `key`: a target on robot/arm/target, else a command."""
    return target(seq, master) if key == keys.ARM_TARGET.key else command(seq, master)


def state(seq: int) -> RobotState:
    return RobotState(
        seq=seq,
        t_ns=time.time_ns(),
        status="ready",
        q=(0.0,) * 6,
        tool_p=(0.5, 0.0, 0.6),
        tool_R=IDENTITY9,
        flange_p=(0.5, 0.0, 0.8),
        flange_R=IDENTITY9,
        engage=0,
        cmd_seq=0,
    )


class Senders:
    """Counts, per `master` field, the commands a subscription received (Zenoh's thread
    writes, the test reads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}

    def __call__(self, msg: OperatorCommand | ArmTarget) -> None:
        with self._lock:
            self._counts[msg.master] = self._counts.get(msg.master, 0) + 1

    @property
    def by_master(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    def count(self, master: str) -> int:
        return self.by_master.get(master, 0)


def put(node: Node, key: str, msg: OperatorCommand) -> None:
    """A raw session put: unlike a declared publisher, it is sent even when the client knows
    no subscriber, so only the router's ACL can stop it (a hostile client skips the
    client-side matching too)."""
    node.session.put(key, codec.encode(msg), encoding=ENCODING)


def interleave(allowed: tuple[Node, str, Senders], denied: list[tuple[Node, str, str]]) -> int:
    """Put robot/cmd from the allowed client and each denied (client, key, name) in turn
    until the allowed one has delivered DELIVERED commands; the number of rounds sent."""
    node, name, seen = allowed
    rounds = 0
    deadline = time.monotonic() + DEADLINE_S
    while seen.count(name) < DELIVERED:
        assert time.monotonic() < deadline, f"allowed {name} delivered {seen.by_master}"
        rounds += 1
        for dnode, dkey, dname in denied:
            put(dnode, dkey, message(dkey, rounds, dname))
        put(node, keys.CMD.key, command(rounds, name))
        time.sleep(0.005)  # pacing: commands are sent at ≤ 1 kHz in service too
    return rounds


class Router:
    """The robot host's router in a child process, and the cell it was installed from."""

    def __init__(self, cell: Cell, child: ChildProcess) -> None:
        self.cell = cell
        self.child = child
        self.tcp = f"tcp/127.0.0.1:{cell.tcp_port}"
        self.tls = f"tls/localhost:{cell.tls_port}"
        # as deploy/operator-quic.toml dials it: the listener's `mixed_rel=1` too
        self.quic = f"quic/localhost:{cell.quic_port}?mixed_rel=1"

    def node(
        self, name: str, client_file: Path, endpoint: str, instance: str | None = None
    ) -> Node:
        cfg = NodeConfig(mode="client", connect=(endpoint,), zenoh_config=str(client_file))
        return Node(name, cfg, instance=instance)

    def station(self, client_file: Path, endpoint: str, master_id: str) -> Node:
        """A master's session as an operator station opens it, its token announced."""
        node = self.node("master", client_file, endpoint, master_id)
        node.announce()
        return node

    def robot(self, name: str) -> Node:
        """A robot-host service: the `robot` login over loopback TCP."""
        return self.node(name, self.cell.client_file("robot-local"), self.tcp)


def start_router(
    root: Path, router_file: str | None = None, clients: tuple[str, ...] = ()
) -> Iterator[Router]:
    cell = install(root, ports=(free_port(), free_port()), clients=clients)
    profile = cell.profile("robot")
    if router_file is not None:
        text = profile.read_text().replace("robot-router.json5", router_file)
        profile.write_text(text)
    with spawned(telerobot("router", "--config", str(profile))) as child:
        line = child.expect("router up")
        assert f"tls/127.0.0.1:{cell.tls_port}" in line, line
        assert f"quic/127.0.0.1:{cell.quic_port}?mixed_rel=1" in line, line
        yield Router(cell, child)


@pytest.fixture(scope="module")
def router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Router]:
    yield from start_router(tmp_path_factory.mktemp("cell"))


@pytest.fixture(scope="module")
def mtls_router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Router]:
    # `operator1` as the README makes it (make-certs.sh … -c operator1), beside the defaults
    yield from start_router(
        tmp_path_factory.mktemp("cell-mtls"),
        "robot-router-mtls.json5",
        clients=("operator", "observer", "operator1"),
    )


class RobotSide:
    """The robot host's decision and arm stand-ins: subscribers of robot/cmd and
    robot/arm/target, `status` methods that count their calls, and liveliness tokens."""

    def __init__(self, stack: ExitStack, router: Router) -> None:
        self.cmd, self.arm_target = Senders(), Senders()
        self.calls: dict[str, int] = {"decision": 0, "arm": 0}
        self.node = stack.enter_context(router.robot("decision"))
        self.node.subscribe(keys.CMD, self.cmd)
        self.node.subscribe(keys.ARM_TARGET, self.arm_target)
        self.node.serve("decision", {"status": self._status("decision")})
        self.node.announce()
        arm = stack.enter_context(router.robot("arm"))
        arm.serve("arm", {"status": self._status("arm")})
        arm.announce()

    def _status(self, who: str) -> Callable[[dict[str, Any]], dict[str, Any]]:
        def status(args: dict[str, Any]) -> dict[str, Any]:
            self.calls[who] += 1
            return {"who": who}

        return status


def denied_call(node: Node, service: str) -> None:
    """A call the router must not deliver: it fails (no reply, or Zenoh's timeout error)."""
    with pytest.raises((Unavailable, RpcError)):
        node.call(service, "status", {}, 1.0)


@pytest.mark.parametrize("link", ["tls", "quic"])
def test_operator_commands_through_decision_but_never_the_arm_directly(
    router: Router, link: str
) -> None:
    """Over TLS and over QUIC with mixed reliability (deploy/operator-quic.toml): the same
    login, the same CA, the same rights."""
    with ExitStack() as stack:
        side = RobotSide(stack, router)
        robot, cmd, arm_target = side.node, side.cmd, side.arm_target
        op_id = f"op1-{link}"
        op = stack.enter_context(
            router.station(router.cell.client_file("operator-client"), getattr(router, link), op_id)
        )
        assert op.alive.wait("decision", DEADLINE_S), "the operator sees the robot's services"
        assert robot.alive.wait(f"master/{op_id}", DEADLINE_S), "the robot sees its token"
        rounds = interleave((op, "operator", cmd), [(op, keys.ARM_TARGET.key, "op-to-arm")])
        assert rounds >= DELIVERED
        assert arm_target.by_master == {}, "a put to robot/arm/target from off the robot host"

        # The subscriber of robot/arm/target works: the robot host's own decision reaches it.
        local = robot.publisher(keys.ARM_TARGET)
        wait_matched(local, DEADLINE_S)
        for i in range(1, 6):
            local.put(target(i, "decision"))
        assert wait_until(lambda: arm_target.count("decision") == 5, DEADLINE_S)
        assert set(arm_target.by_master) == {"decision"}

        # Methods: the decision server answers the operator; the arm's methods do not,
        # although the arm is up and answers the robot host itself.
        assert op.call("decision", "status", {}, DEADLINE_S) == {"who": "decision"}
        assert robot.call("arm", "status", {}, DEADLINE_S) == {"who": "arm"}
        denied_call(op, "arm")
        assert side.calls == {"decision": 1, "arm": 1}


def test_observer_may_watch_but_not_command(router: Router) -> None:
    with ExitStack() as stack:
        side = RobotSide(stack, router)
        robot, cmd = side.node, side.cmd
        op = stack.enter_context(
            router.station(router.cell.client_file("operator-client"), router.tls, "op2")
        )
        observer_file = router.cell.client_file("observer-client")
        watchers: list[tuple[str, Node]] = [
            ("observer-tls", stack.enter_context(router.node("obs", observer_file, router.tls))),
            ("observer-tcp", stack.enter_context(router.node("obs", observer_file, router.tcp))),
        ]
        states: list[Subscription[RobotState]] = [n.subscribe(keys.STATE) for _, n in watchers]
        denied = [(n, keys.CMD.key, name) for name, n in watchers]
        assert wait_until(lambda: robot.alive.is_alive("master/op2"), DEADLINE_S)
        interleave((op, "operator", cmd), denied)
        assert cmd.count("observer-tls") == 0 and cmd.count("observer-tcp") == 0, cmd.by_master

        # Their subscriptions to the robot's state work: every state over plain TCP (a LAN
        # observer), at most 50 a second over TLS (the router's `state-to-stations`
        # downsampling); a state after a pause of a period gets through either way.
        state_pub = robot.publisher(keys.STATE)
        n = 30
        t0 = time.monotonic()
        for i in range(1, n + 1):
            state_pub.put(state(i))
            time.sleep(0.002)
        burst_s = time.monotonic() - t0
        time.sleep(0.05)
        state_pub.put(state(n + 1))
        for sub in states:
            assert sub.wait_for(lambda m: m.seq == n + 1, DEADLINE_S) is not None
        tls, tcp = states
        assert tcp.received == n + 1, "plain TCP: every state"
        assert 2 <= tls.received <= 50.0 * burst_s + 3, (tls.received, burst_s)

        # …and they call nothing, not even the decision server.
        for _, watcher in watchers:
            denied_call(watcher, "decision")
        assert side.calls == {"decision": 0, "arm": 0}


def test_operator_login_over_plain_tcp_commands_nothing(router: Router) -> None:
    """Command rights need TLS (`link_protocols`): the operator's login over the plain
    listener matches no subject."""
    with ExitStack() as stack:
        cmd = RobotSide(stack, router).cmd
        op_file = router.cell.client_file("operator-client")
        tls = stack.enter_context(router.node("master", op_file, router.tls, "tls"))
        tcp = stack.enter_context(router.node("master", op_file, router.tcp, "tcp"))
        interleave((tls, "over-tls", cmd), [(tcp, keys.CMD.key, "tcp")])
        assert cmd.count("tcp") == 0, cmd.by_master


def test_wrong_password_cannot_connect(router: Router) -> None:
    cell = router.cell
    bad = cell.variant(
        "operator-client.json5",
        lambda t: t.replace('password: "change-me-operator"', 'password: "guess"'),
        "bad-password.json5",
    )
    nobody = cell.variant(
        "operator-client.json5",
        lambda t: t.replace('user: "operator"', 'user: "intruder"'),
        "unknown-user.json5",
    )
    # `robot`'s password from the robot host's file: logs in, so the file itself is good
    router.robot("probe").close()
    for file, endpoint in ((bad, router.tls), (bad, router.tcp), (nobody, router.tls)):
        with pytest.raises(ConnectFailed, match="Unable to connect"):
            router.node("master", file, endpoint).close()
    no_login = cell.variant(
        "operator-client.json5",
        lambda t: re.sub(r"\s*auth: \{.*?\n    \},", "", t, flags=re.S),
        "no-login.json5",
    )
    with pytest.raises(ConnectFailed, match="Unable to connect"):
        router.node("master", no_login, router.tls).close()


def test_client_without_the_ca_cannot_connect_over_tls(router: Router) -> None:
    cell = router.cell
    no_ca = cell.variant(
        "operator-client.json5",
        lambda t: re.sub(r'\n\s*root_ca_certificate: "[^"]*",', "", t),
        "no-ca.json5",
    )
    with pytest.raises(ConnectFailed, match="Unable to connect"):
        router.node("master", no_ca, router.tls).close()
    # the same file with the CA (the shipped one) connects: the CA is what was missing
    router.node("master", cell.client_file("operator-client"), router.tls).close()


@pytest.mark.parametrize("link", ["tls", "quic"])
def test_mutual_tls_needs_the_operator_certificate_and_login(
    mtls_router: Router, link: str
) -> None:
    """mTLS and the ACL hold on QUIC as on TLS: the authorised station commands, one with
    another role's certificate gets nothing through, one without a certificate no link."""
    cell = mtls_router.cell
    endpoint = getattr(mtls_router, link)
    with ExitStack() as stack:
        cmd = RobotSide(stack, mtls_router).cmd
        op = stack.enter_context(
            mtls_router.node("master", cell.client_file("operator-client-mtls"), endpoint)
        )
        # A client certificate of the cell, but the observer's: the operator's password
        # with it commands nothing (the ACL wants CN `operator` AND user `operator`).
        wrong_cn = cell.variant(
            "operator-client-mtls.json5",
            lambda t: t.replace("certs/operator.", "certs/observer."),
            "observer-cert.json5",
        )
        imp = stack.enter_context(mtls_router.node("master", wrong_cn, endpoint, "imp"))
        # and the operator's certificate over plain TCP: no TLS, no operator subject
        tcp = stack.enter_context(
            mtls_router.node(
                "master", cell.client_file("operator-client-mtls"), mtls_router.tcp, "tcp"
            )
        )
        interleave(
            (op, "operator", cmd), [(imp, keys.CMD.key, "imposter"), (tcp, keys.CMD.key, "tcp")]
        )
        assert cmd.count("imposter") == 0 and cmd.count("tcp") == 0, cmd.by_master
    # Without any client certificate the TLS handshake fails.
    with pytest.raises(ConnectFailed, match="Unable to connect"):
        mtls_router.node("master", cell.client_file("operator-client"), endpoint).close()


def test_the_readme_s_operator1_certificate_commands_over_mutual_tls(mtls_router: Router) -> None:
    """`make-certs.sh … -c operator1` (the README's step) makes a certificate the shipped
    mTLS router's ACL accepts with the `operator` login (its CN is the role)."""
    cell = mtls_router.cell
    station1 = cell.variant(
        "operator-client-mtls.json5",
        lambda t: t.replace("certs/operator.", "certs/operator1."),
        "operator1-mtls.json5",
    )
    with ExitStack() as stack:
        cmd = RobotSide(stack, mtls_router).cmd
        op = stack.enter_context(mtls_router.node("master", station1, mtls_router.quic, "s1"))
        assert interleave((op, "operator", cmd), []) >= DELIVERED


def test_stations_and_observers_read_the_arm_s_description_but_never_publish_one(
    router: Router,
) -> None:
    """The description is published once and kept (Zenoh's advanced publisher): a station
    that comes later asks for the cached one through the router, and gets republished ones
    as they come; none of them can publish a description of its own."""
    from services.bus.messages import ArmDescription
    from services.control.arm.model import load_model

    fields = load_model("fr3").description()
    with ExitStack() as stack:
        arm = stack.enter_context(router.robot("arm"))
        pub = arm.publisher(keys.ARM_DESCRIPTION, cache=1)
        pub.put(ArmDescription(seq=1, t_ns=time.time_ns(), **fields))
        op = stack.enter_context(
            router.node("console", router.cell.client_file("operator-client"), router.tls)
        )
        obs = stack.enter_context(
            router.node("obs", router.cell.client_file("observer-client"), router.tls)
        )
        subs = [n.subscribe(keys.ARM_DESCRIPTION, history=True) for n in (op, obs)]
        for sub in subs:  # the cached one, though published before they subscribed
            got = sub.wait_for(lambda d: d.seq == 1, DEADLINE_S)
            assert got is not None and got.model == "fr3" and got.n == 7
        # a hostile station's description never reaches the robot host's subscriber
        local = arm.subscribe(keys.ARM_DESCRIPTION)
        for seq in range(2, 12):
            for n in (op, obs):
                n.session.put(
                    keys.ARM_DESCRIPTION.key,
                    codec.encode(ArmDescription(seq=100 + seq, t_ns=1, **fields)),
                    encoding=ENCODING,
                )
            pub.put(ArmDescription(seq=seq, t_ns=time.time_ns(), **fields))
            time.sleep(0.005)
        for sub in (*subs, local):  # the newest (highest seq) of each is the arm's last
            assert sub.wait_for(lambda d: d.seq == 11, DEADLINE_S) is not None
        assert local.received == 10, "only the arm's own ten, none of the stations' twenty"
