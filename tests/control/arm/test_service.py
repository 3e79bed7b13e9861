"""The arm service over Zenoh: methods, the target stream, and bad input that never moves it."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest

from services.bus import keys
from services.bus.errors import RpcError
from services.bus.messages import ArmTarget, Event, RobotState
from services.control.arm.config import ArmConfig
from services.control.arm.service import ArmService


@pytest.fixture
def arm(net):  # type: ignore[no-untyped-def]
    node = net.node("arm")
    svc = ArmService(node, ArmConfig(sim_calibration_s=0.05))
    try:
        yield svc
    finally:
        svc.close()


def _ready(client, state) -> RobotState:  # type: ignore[no-untyped-def]
    client.call("arm", "connect", {}, timeout_s=30.0)
    client.call("arm", "initialize", {"wait": True}, timeout_s=30.0)
    st = state.wait_for(lambda s: s.status == "ready", 30.0)
    assert st is not None, "the arm never became ready"
    return st


def _repeat_until(put, state, pred, timeout_s: float = 10.0):  # type: ignore[no-untyped-def]
    """Re-send the newest target until the state shows it, as a master's stream does.

    `robot/arm/target` is best effort (latest wins): on a starved host a burst can lose its
    last sample, and a real master's next tick supersedes it. `put()` sends a fresh copy of the
    last target and returns its seq; `pred(state, seq)` says when it has been applied.
    """
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        seq = put()
        st = state.wait_for(lambda s, n=seq: pred(s, n), 0.05)
        if st is not None:
            return st
    return None


def test_status_machine_and_motion_methods(net, arm) -> None:
    client = net.node("operator")
    state = client.subscribe(keys.STATE)
    statuses: list[str] = []
    moved = threading.Event()

    def on_event(ev: Event) -> None:
        if ev.source == "arm" and ev.kind == "status" and ev.data:
            statuses.append(str(ev.data.get("status")))
        if ev.kind == "moved":
            moved.set()

    client.subscribe(keys.EVENTS, on_event)
    assert client.call("arm", "status", {}, timeout_s=5.0)["status"] == "disconnected"
    with pytest.raises(RpcError) as err:
        client.call("arm", "home", {}, timeout_s=5.0)
    assert err.value.code == "not_ready"
    st = _ready(client, state)
    reply = client.call(
        "arm", "move_relative", {"dp": [0.0, 0.0, -0.05], "wait": True}, timeout_s=20.0
    )
    assert reply["completed"] is True
    after = state.wait_for(lambda s: s.status == "ready" and s.seq > st.seq + 5, 5.0)
    assert after is not None
    assert after.tool_p[2] == pytest.approx(st.tool_p[2] - 0.05, abs=1e-3)
    assert moved.wait(5.0)
    assert statuses[:3] == ["connected", "initializing", "ready"]
    fk = client.call("arm", "fk", {"q": list(after.q)}, timeout_s=5.0)
    assert np.allclose(fk["tool_p"], after.tool_p, atol=1e-6)
    ik = client.call("arm", "ik", {"p": fk["tool_p"], "R": fk["tool_R"]}, timeout_s=5.0)
    assert len(ik["solutions"]) == 8


def test_target_stream_moves_the_tool_and_bad_targets_never_do(net, arm) -> None:
    client = net.node("master")
    state = client.subscribe(keys.STATE)
    rejected: list[Event] = []
    got_rejected = threading.Event()

    def on_event(ev: Event) -> None:
        if ev.kind == "rejected":
            rejected.append(ev)
            got_rejected.set()

    client.subscribe(keys.EVENTS, on_event)
    st0 = _ready(client, state)
    pub = client.publisher(keys.ARM_TARGET)
    seq = 0

    def send(dp: tuple[float, float, float], engage: int = 1) -> None:
        nonlocal seq
        seq += 1
        now = time.time_ns()
        p = tuple(a + b for a, b in zip(st0.tool_p, dp, strict=True))
        pub.put(
            ArmTarget(seq=seq, t_ns=now, origin_t_ns=now, master="decision", engage=engage,
                      p=p, R=st0.tool_R)
        )  # fmt: skip

    for i in range(1, 40):
        send((0.0, 0.001 * i, 0.0))

    def send_last() -> int:
        send((0.0, 0.04, 0.0))
        return seq

    moved = _repeat_until(
        send_last,
        state,
        lambda s, n: s.cmd_seq == n and abs(s.tool_p[1] - st0.tool_p[1] - 0.04) < 1e-7,
    )
    assert moved is not None, "the tool did not follow the target stream"
    q_before = np.array(moved.q)

    # Garbage on the target key: NaN, a reflected R, a huge step, not msgpack at all.
    raw = client.session
    good = {
        "seq": seq + 1,
        "t_ns": 1,
        "origin_t_ns": 1,
        "master": "decision",
        "engage": 1,
        "p": list(moved.tool_p),
        "R": list(st0.tool_R),
    }
    bad = [
        {**good, "p": [float("nan"), 0.0, 0.0]},
        {**good, "R": [1.0, 0, 0, 0, 1.0, 0, 0, 0, -1.0]},
        b"\xc1\xff not msgpack",
    ]
    for payload in bad:
        raw.put(
            keys.ARM_TARGET.key, payload if isinstance(payload, bytes) else msgpack.packb(payload)
        )
    deadline = time.monotonic() + 5.0
    while not got_rejected.is_set() and time.monotonic() < deadline:
        send((0.5, 0.04, 0.0))  # a valid message, but a 0.5 m jump: refused by the arm
        got_rejected.wait(0.05)
    assert got_rejected.is_set(), "no rejected event"
    later = state.wait_for(lambda s: s.seq > moved.seq + 50, 5.0)
    assert later is not None
    assert np.allclose(later.q, q_before, atol=1e-6), "bad targets moved the arm"
    assert any(ev.kind == "rejected" for ev in rejected)


def test_a_target_is_applied_on_arrival_and_its_times_are_in_the_state(net, arm) -> None:
    client = net.node("master")
    state = client.subscribe(keys.STATE)
    st0 = _ready(client, state)
    pub = client.publisher(keys.ARM_TARGET)
    sent: list[ArmTarget] = []
    for i in range(1, 21):
        now = time.time_ns()
        tgt = ArmTarget(
            seq=i,
            t_ns=now,
            origin_t_ns=now - 1_000,  # the operator sent it 1 µs earlier
            master="decision",
            engage=1,
            p=(st0.tool_p[0], st0.tool_p[1] + 0.0005 * i, st0.tool_p[2]),
            R=st0.tool_R,
        )
        sent.append(tgt)
        pub.put(tgt)
    last = sent[-1]

    def send_last() -> int:
        nonlocal last
        now = time.time_ns()
        last = ArmTarget(
            seq=last.seq + 1, t_ns=now, origin_t_ns=now - 1_000, master="decision", engage=1,
            p=last.p, R=last.R,
        )  # fmt: skip
        pub.put(last)
        return last.seq

    st = _repeat_until(send_last, state, lambda s, n: s.cmd_seq == n and s.setpoint_ns is not None)
    assert st is not None, "the last target was never applied"
    assert st.cmd_origin_t_ns == last.origin_t_ns
    assert st.cmd_rx_ns is not None and st.setpoint_ns is not None
    # one clock: sent, then received, then the first setpoint from it
    assert last.origin_t_ns < last.t_ns <= st.cmd_rx_ns <= st.setpoint_ns <= st.t_ns
    # the setpoint's tool position (what a new engagement starts from): left out at rest
    # (the measured one is it), on the way to the target while moving, ahead of the tool
    assert st0.tool_p_cmd is None
    assert st.tool_p_cmd is not None and st0.tool_p[1] < st.tool_p_cmd[1] <= st0.tool_p[1] + 0.01
    moving = state.wait_for(
        lambda s: s.tool_p_cmd is not None and s.tool_p_cmd[1] > s.tool_p[1] + 1e-4, 10.0
    )
    assert moving is not None, "the setpoint was never seen ahead of the measured tool"
    done = state.wait_for(lambda s: abs(s.tool_p[1] - st0.tool_p[1] - 0.01) < 1e-7, 10.0)
    assert done is not None, "the tool did not reach the last command's target"
    rest = state.wait_for(lambda s: s.seq > done.seq and s.tool_p_cmd is None, 10.0)
    assert rest is not None, "at rest the setpoint's position is still sent"


def test_at_rest_nothing_is_recomputed_and_the_state_keeps_flowing(net, arm) -> None:
    client = net.node("observer")
    state = client.subscribe(keys.STATE)
    _ready(client, state)
    settled = state.wait_for(lambda s: s.status == "ready", 10.0)
    assert settled is not None
    # Let a settle period pass: the servo's approach ends, the sim arm goes to sleep.
    first = state.wait_for(lambda s: s.seq > settled.seq + 50, 10.0)
    assert first is not None
    ticks0 = arm.proxy.counters["ticks"]
    setpoints0 = arm.arm.setpoints_accepted
    t0 = arm.arm.t_s
    n0 = state.received
    assert state.wait_count(n0 + 100, 10.0)  # ≥ 100 more states: the stream keeps flowing
    later = state.get()
    assert later is not None and later.status == "ready"
    # One watch tick per state published at rest (100 Hz), not the 500 Hz control rate.
    states = state.received - n0
    assert arm.proxy.counters["ticks"] - ticks0 <= states + 5
    assert arm.arm.setpoints_accepted == setpoints0  # nothing re-sent to a resting arm
    assert arm.arm.t_s >= t0  # the simulated clock still follows the wall clock
    assert later.q == first.q  # not a nanoradian of drift


def test_while_a_decision_server_runs_only_it_may_start_motions(net, arm) -> None:
    client = net.node("operator")
    state = client.subscribe(keys.STATE)
    _ready(client, state)
    move = {"dp": [0.0, 0.0, -0.01], "wait": True}
    assert client.call("arm", "move_relative", move, timeout_s=20.0)["completed"] is True
    decision = net.node("decision")
    decision.announce()  # alive/decision: a supervisor is there now
    assert client.alive.wait("decision", 10.0)
    # the arm's own view of the token counts, not the client's (they arrive apart)
    assert arm.node.alive.wait("decision", 10.0)
    sent = arm.arm.setpoints_accepted
    with pytest.raises(RpcError) as err:
        client.call("arm", "move_relative", move, timeout_s=20.0)
    assert err.value.code == "busy" and "robot/decision/rpc/move_relative" in err.value.message
    assert arm.arm.setpoints_accepted == sent  # refused before anything was planned or sent
    assert arm.proxy.rpc_status({})["motion"] is None
    via = {**move, "supervised_by": "decision"}
    assert client.call("arm", "move_relative", via, timeout_s=20.0)["completed"] is True
    assert client.call("arm", "status", {}, timeout_s=5.0)["status"] == "ready"


def test_a_retried_motion_with_its_request_id_never_moves_twice(net, arm) -> None:
    client = net.node("operator")
    state = client.subscribe(keys.STATE)
    st0 = _ready(client, state)
    move = {"dp": [0.0, 0.0, -0.02], "request_id": "retry-1"}
    first = client.call("arm", "move_relative", move, timeout_s=20.0)
    again = client.call("arm", "move_relative", {**move, "wait": True}, timeout_s=20.0)
    assert again["motion"] == first["motion"] and again["duplicate"] is True
    assert again["completed"] is True
    done = state.wait_for(lambda s: s.status == "ready" and s.seq > st0.seq + 20, 10.0)
    assert done is not None
    assert done.tool_p[2] == pytest.approx(st0.tool_p[2] - 0.02, abs=1e-3)  # once, not twice
    other = client.call("arm", "move_relative", {**move, "request_id": "retry-2"}, 20.0)
    assert other["motion"] != first["motion"] and "duplicate" not in other
    with pytest.raises(RpcError) as err:
        client.call("arm", "move_relative", {**move, "request_id": "x" * 65}, timeout_s=5.0)
    assert err.value.code == "bad_request"


def test_the_arm_takes_its_physics_from_the_command_line_over_the_file() -> None:
    from services.bus.lifecycle import service_parser
    from services.control.arm.__main__ import arguments, arm_table

    p = service_parser("arm", add_arguments=arguments)
    deploy = {"arm": {"driver": "sim", "sim_physics": "own", "model": "ur5e"}}
    table = arm_table(deploy, p.parse_args(["--sim-physics", "workcell"]))
    assert table == {"driver": "sim", "sim_physics": "workcell", "model": "ur5e"}
    from services.control.arm.config import ArmConfig

    assert ArmConfig.from_mapping(table).sim_physics == "workcell"
    assert arm_table(deploy, p.parse_args([]))["sim_physics"] == "own"
    with pytest.raises(SystemExit):
        p.parse_args(["--sim-physics", "elsewhere"])
