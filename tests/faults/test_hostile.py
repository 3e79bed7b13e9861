"""Hostile input through the wire, against the real processes on a router: inputs that are
well-formed but absurd (1e308, 10 MB strings, a thousand nested lists, floods of names).

One cell for the module (router, arm, force, decision as separate processes; an in-process
observer and an attacker): every case must be refused with a contract error, move no joint
by more than 1e-6 rad, leave every process alive and answering, and keep the decision's
holds going out. The soak at the end sends the whole corpus three times and bounds each
service's memory growth after the first round.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.bus import codec, keys
from services.bus.config import NodeConfig
from services.bus.errors import RpcError, Unavailable
from services.bus.messages import IDENTITY_R, OperatorCommand
from services.bus.node import Node
from tests.conftest import wait_until
from tests.faults.observe import Observer, record
from tests.faults.procs import LOOPBACK_LISTEN, Cell

pytestmark = [pytest.mark.faults, pytest.mark.alone, pytest.mark.timeout(300)]

START_TIMEOUT_S = 60.0
CALL_TIMEOUT_S = 5.0
STILL_RAD = 1e-6
"""A case moved nothing: no joint changed by more than this."""
MAX_REPLY_CHARS = 400
MAX_EVENT_BYTES = 2_000
RSS_GROWTH_MB = 50.0
SERVICES = ("arm", "force", "decision")


class Attacker:
    """A peer on the router that publishes and calls whatever it likes."""

    def __init__(self, endpoint: str) -> None:
        self.node = Node("attacker", NodeConfig(connect=(endpoint,), listen=(LOOPBACK_LISTEN,)))
        self.cmd = self.node.publisher(keys.CMD)
        self.arm_cmds = self.node.subscribe(keys.ARM_TARGET)
        self.seq = time.time_ns() // 1000
        self.engage = time.time_ns() // 1_000_000

    def command(
        self, dp: tuple[float, float, float], frame: str = "world", master: str = "evil"
    ) -> None:
        self.seq += 1
        self.cmd.put(
            OperatorCommand(
                seq=self.seq,
                t_ns=time.time_ns(),
                master=master,
                engage=self.engage,
                active=True,
                frame=frame,  # type: ignore[arg-type]
                dp=dp,
                dR=IDENTITY_R,
            )
        )

    def call(self, service: str, method: str, args: dict[str, Any]) -> RpcError | dict[str, Any]:
        """The reply, or the RpcError it raised (a case asserts on either)."""
        try:
            return self.node.call(service, method, args, CALL_TIMEOUT_S)
        except RpcError as e:
            return e


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Cell, Observer, Attacker]]:
    tmp: Path = tmp_path_factory.mktemp("hostile")
    c = Cell(tmp / "logs")
    obs: Observer | None = None
    attacker: Attacker | None = None
    try:
        c.start_router()
        obs = Observer(c.endpoint, name="hostile-observer")
        c.add("arm", "arm", "--autostart").start()
        c.add("force", "force").start()
        c.add("decision", "decision").start()
        attacker = Attacker(c.endpoint)
        assert obs.node.alive.wait("decision", START_TIMEOUT_S), c.logs()
        assert obs.wait(
            lambda: (st := obs.latest_state()) is not None and st.status == "ready",
            START_TIMEOUT_S,
        ), c.logs()
        yield c, obs, attacker
    finally:
        if attacker is not None:
            attacker.node.close()
        if obs is not None:
            obs.node.close()
        c.close()


def joints(obs: Observer) -> np.ndarray:
    """The newest measured joints, after a few fresh states (the arm's latest word)."""
    n = obs.n_states()
    obs.wait_states(3, n, 10.0)
    st = obs.latest_state()
    assert st is not None
    return np.array(st.q)


def alive_and_answering(c: Cell, attacker: Attacker) -> None:
    assert not c.crashed(), c.logs()
    for service, method in (("arm", "status"), ("force", "sensor_status"), ("decision", "status")):
        reply = attacker.call(service, method, {})
        assert isinstance(reply, dict), f"{service}.{method}: {reply}"


def short_error(reply: RpcError | dict[str, Any], code: str = "bad_request") -> RpcError:
    assert isinstance(reply, RpcError), f"accepted: {reply}"
    assert reply.code == code, reply
    assert len(reply.message) < MAX_REPLY_CHARS, len(reply.message)
    return reply


def deep(n: int) -> Any:
    v: Any = []
    for _ in range(n):
        v = [v]
    return v


# --- the cases, each through the wire ------------------------------------------------


def test_absurd_commands_never_move_the_arm_and_the_holds_go_on(
    cell: tuple[Cell, Observer, Attacker],
) -> None:
    c, obs, attacker = cell
    for dp, frame in (
        ((1e308, 0.0, 0.0), "world"),
        ((0.0, 0.0, 1e300), "world"),
        ((1e308, 1e308, 1e308), "tool"),
    ):
        attacker.engage += 1

        def leads(frame: str = frame) -> bool:
            # A sane engagement first, kept streaming until the evil master leads (a master
            # that stops streaming loses the lease to the watchdog, as a loaded machine showed).
            attacker.command((0.0, 0.0, 0.0), frame)
            status = attacker.call("decision", "status", {})
            return isinstance(status, dict) and status.get("lease") == "evil"

        assert wait_until(leads, 10.0, 0.01, what="the evil master to lead")
        q0 = joints(obs)
        holds0 = attacker.arm_cmds.received
        for _ in range(20):  # then the absurd one, 20 times at 100 Hz
            attacker.command(dp, frame)
            time.sleep(0.01)
        time.sleep(0.3)  # not a synchronisation: the arm must not move meanwhile either
        q1 = joints(obs)
        moved = float(np.max(np.abs(q1 - q0)))
        assert moved <= STILL_RAD, f"dp={dp} ({frame}) moved a joint {moved} rad"
        status = attacker.call("decision", "status", {})
        assert isinstance(status, dict) and status["mode"] == "hold" and status["lease"] is None
        assert status["loop"]["publish_errors"] == 0 and status["loop"]["errors"] == 0
        holds = attacker.arm_cmds.received - holds0
        assert holds >= 3, "the decision stopped publishing its hold"
        latest = attacker.arm_cmds.get()
        assert latest is not None and latest.hold
        record(f"hostile_cmd_{frame}_{dp[0]:g}", moved_rad=moved, holds=holds)
    alive_and_answering(c, attacker)


def test_estop_latches_whatever_its_call_carries_and_initialize_waits(
    cell: tuple[Cell, Observer, Attacker],
) -> None:
    c, obs, attacker = cell
    attacker.call("decision", "estop", {"reason": deep(1000)})
    status = attacker.call("decision", "status", {})
    assert isinstance(status, dict) and status["estop"] is True
    assert isinstance(attacker.call("decision", "reset", {}), dict)
    # The arm's own e-stop (powers the arm off) with garbage: it halts, then recovers with
    # connect and a waiting initialize, which replies when the arm is ready.
    attacker.call("arm", "estop", {"x": "y" * 60_000, "z": deep(500)})
    assert wait_until(lambda: (st := obs.latest_state()) is not None and st.status == "error", 10.0)
    assert isinstance(attacker.call("arm", "connect", {}), dict)
    reply = attacker.call("arm", "initialize", {"wait": True, "timeout_s": 30.0})
    assert reply == {"status": "ready"}, reply
    moved = short_error(
        attacker.call(
            "arm",
            "move_relative",
            {"dp": [0, 0, 0.001], "wait": True, "timeout_s": 1e10, "supervised_by": "decision"},
        )
    )
    assert "timeout_s" in moved.message
    alive_and_answering(c, attacker)


def test_a_call_that_fails_starts_no_motion(cell: tuple[Cell, Observer, Attacker]) -> None:
    c, obs, attacker = cell
    q0 = joints(obs)
    target = [float(x) + 0.05 for x in q0]
    short_error(attacker.call("arm", "move_joints", {"q": target}), "busy")  # unsupervised
    for service, extra in (("decision", {}), ("arm", {"supervised_by": "decision"})):
        # the attacker forges the decision's mark: the arm still refuses absurd arguments
        err = short_error(
            attacker.call(
                service, "move_joints", {"q": target, "wait": True, "timeout_s": 1e10, **extra}
            )
        )
        assert "timeout_s" in err.message
        short_error(attacker.call(service, "move_relative", {"dp": [1e308, 0, 0], **extra}))
        short_error(
            attacker.call(
                service, "move_pose", {"p": [1e308, 0, 0], "R": list(IDENTITY_R), **extra}
            )
        )
        short_error(attacker.call(service, "set_tool", {"p": [1e308] * 3, "R": list(IDENTITY_R)}))
    short_error(attacker.call("force", "set_tool", {"p": [1e308] * 3, "R": list(IDENTITY_R)}))
    short_error(
        attacker.call("decision", "task", {"name": "guarded_move", "direction": [1e308] * 3})
    )
    short_error(attacker.call("decision", "supervisor", {"max_tool_speed_m_s": 1e308}))
    time.sleep(0.3)  # not a synchronisation: nothing may move meanwhile
    moved = float(np.max(np.abs(joints(obs) - q0)))
    assert moved <= STILL_RAD, f"a refused call moved a joint {moved} rad"
    alive_and_answering(c, attacker)


def test_huge_inputs_get_short_replies_and_short_events(
    cell: tuple[Cell, Observer, Attacker],
) -> None:
    c, obs, attacker = cell
    n0 = obs.n_events()
    big = "x" * 10_000_000
    for service, method in (
        ("decision", "supervisor"),
        ("decision", "move_relative"),
        ("arm", "set_tool"),
        ("force", "sensor_config"),
    ):
        short_error(attacker.call(service, method, {"dp": big, "p": big, "period_ms": big}))
    attacker.node.session.put(keys.CMD.key, codec.pack({"seq": 1, "junk": big}))
    attacker.node.session.put(keys.FORCE.key, b"\xc1" * 1_000_000)
    assert obs.wait(lambda: obs.n_events() > n0, 10.0)
    time.sleep(1.0)  # not a synchronisation: the window in which more events could come
    sizes = [len(codec.encode(e)) for e in obs.events(n0)]
    assert sizes and max(sizes) < MAX_EVENT_BYTES, max(sizes)
    alive_and_answering(c, attacker)


def test_a_flood_of_names_is_a_trickle_of_events(cell: tuple[Cell, Observer, Attacker]) -> None:
    c, obs, attacker = cell
    n0 = obs.n_events()
    t0 = time.monotonic()
    for i in range(1000):
        attacker.call("decision", f"method_{i}_{'z' * 100}", {})
    for i in range(1000):
        attacker.command((0.0, 0.0, 0.0), master=f"rogue-{i}")
    elapsed = time.monotonic() - t0
    time.sleep(1.0)  # not a synchronisation: let the last events arrive
    events = [e for e in obs.events(n0) if e.source == "decision"]
    allowed = (int(elapsed) + 2) * 2 * 5  # two kinds (rejected, lease), 5 a second each
    assert len(events) <= allowed, f"{len(events)} events in {elapsed:.1f} s"
    total = sum(len(codec.encode(e)) for e in events)
    record("hostile_flood", events=len(events), seconds=round(elapsed, 1), event_bytes=total)
    assert total < 200_000
    alive_and_answering(c, attacker)


def test_a_forwarded_call_that_times_out_is_unavailable(
    cell: tuple[Cell, Observer, Attacker],
) -> None:
    c, _obs, attacker = cell
    force = c["force"]
    force.signal(signal.SIGSTOP)
    try:
        reply = attacker.call("decision", "sensor_status", {})
        err = short_error(reply, code="unavailable")
        assert any(w in err.message for w in ("timed out", "gone", "not running"))
    finally:
        force.signal(signal.SIGCONT)

    def answers() -> bool:  # its session may have lapsed while stopped: back within seconds
        try:
            return isinstance(attacker.call("force", "sensor_status", {}), dict)
        except Unavailable:
            return False

    assert wait_until(answers, 20.0)
    alive_and_answering(c, attacker)


# --- memory: the whole corpus three times ---------------------------------------------------


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS")


def corpus(attacker: Attacker) -> None:
    """One round of everything hostile, with large inputs to every service."""
    big = "q" * 8_000_000
    for service, methods in (
        ("arm", ("set_tool", "move_joints", "fk", "ik", "status")),
        ("force", ("sensor_config", "set_tool", "sensor_compliance")),
        ("decision", ("supervisor", "task", "move_pose", "sensor_config")),
    ):
        for method in methods:
            attacker.call(service, method, {"p": big, "q": [1e308] * 6, "name": big})
            attacker.call(service, method, {"reason": deep(900), "R": [5e-324] * 9})
    for i in range(300):
        attacker.call("decision", f"unknown_{i}_{'u' * 200}", {})
        attacker.command((1e308, 0.0, 0.0), master=f"m{i}-{'n' * 100}")
    for key in (keys.CMD.key, keys.ARM_TARGET.key, keys.STATE.key, keys.FORCE.key):
        attacker.node.session.put(key, b"\x92" + b"\xff" * 500_000)
        attacker.node.session.put(key, codec.pack({"seq": 1, "t_ns": 1, "pad": big[:60_000]}))


def test_memory_stays_bounded_over_three_rounds(cell: tuple[Cell, Observer, Attacker]) -> None:
    c, _obs, attacker = cell
    corpus(attacker)
    after_first = {s: rss_mb(c[s].pid) for s in SERVICES}
    for _ in range(2):
        corpus(attacker)
    growth = {s: rss_mb(c[s].pid) - after_first[s] for s in SERVICES}
    record("hostile_rss_growth_mb", **{s: round(g, 1) for s, g in growth.items()})
    assert all(g < RSS_GROWTH_MB for g in growth.values()), growth
    alive_and_answering(c, attacker)
    st = attacker.call("decision", "status", {})
    assert isinstance(st, dict) and st["loop"]["errors"] == 0
    try:
        attacker.node.call("decision", "status", {}, CALL_TIMEOUT_S)
    except Unavailable:  # pragma: no cover - the assertion above already failed then
        pytest.fail("decision stopped answering")
    assert os.path.exists(f"/proc/{c['decision'].pid}")
