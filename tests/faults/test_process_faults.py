"""Faults against the REAL services in simulation, each a separate process (issue 11).

One cell for the module (tests/faults/cell.py): a router, arm (sim arm), force (sim
sensor), decision and a scripted master, spawned with subprocess; the observer is an
in-process peer connected throughout. The tests run in file order, and each first brings the
cell back to "every service up, the master's engagement followed, the arm moving", so a
test also passes on its own. The last test checks that no event published during all of it
was lost.

Every bound below is a deadline of a wait ("held within 2.5 s"), never a speed assertion;
the figures measured are printed and saved to artifacts/faults.json.
"""

from __future__ import annotations

import itertools
import json
import sys
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from services.bus.errors import RpcError, Unavailable
from services.bus.messages import RobotState
from services.control.arm.config import ArmConfig
from services.control.arm.fake_controller import FakeController
from services.control.arm.model import load_model
from services.tools.cell.procs import Child
from tests.conftest import BEST_EFFORT_LOSS, wait_until
from tests.faults.cell import MASTER_ID, FaultCell, path_length
from tests.faults.observe import (
    REST_TOL_RAD,
    Observer,
    count_between,
    event_continuity,
    record,
    tool_steps,
)
from tests.faults.rogue import MARK

HOME_Q_RAD = load_model().home
"""The default model's home (the PUMA 560's)."""

pytestmark = [pytest.mark.faults, pytest.mark.alone, pytest.mark.timeout(180)]

PUMA = ArmConfig()
MAX_TOOL_SPEED_M_S = PUMA.max_tool_speed_m_s
STATE_PERIOD_S = 1.0 / PUMA.state_rate_hz
READ_AGE_S = 1.0 / PUMA.control_rate_hz
"""A state's joints were read by the last control tick, at most one period before its stamp
(CI saw 2.60 mm against 2.49 allowed by the stamps while the arm caught up a late command
at its 0.5 m/s limit)."""
HOLD_DEADLINE_S = 2.5
"""The arm must be at rest this soon after the fault (watchdog 100 ms, lease ≤ 2 s)."""
LEASE_S = 2.0
QUIET_S = 1.0
"""Rest is confirmed by this long without motion."""
SERIAL_SAMPLE_PERIOD_S = PUMA.serial_cycle_ms / 1e3
"""robot/state's joints from a serial controller change once per controller cycle."""
REBASE_TOL_M = 1e-3
"""A new engagement starts where the arm holds: its first state is this close to the hold."""


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FaultCell]:
    c = FaultCell(tmp_path_factory.mktemp("faults"))
    try:
        yield c
    finally:
        c.close()


def _assert_rest(
    cell: FaultCell, start: int, t_fault_ns: int, deadline_s: float
) -> tuple[RobotState, list[RobotState], float]:
    """Wait for the arm to be at rest (within `deadline_s`, confirmed for QUIET_S); the
    first state at rest, the states since `start`, and the time to hold (ms)."""
    rest = cell.obs.wait_rest(start, QUIET_S, deadline_s)
    assert rest is not None, f"the arm did not come to rest within {deadline_s} s"
    r, states = rest
    held = states[r]
    return held, states, (held.t_ns - t_fault_ns) / 1e6


def _drift(states: list[RobotState], q: tuple[float, ...]) -> float:
    """The largest joint deviation (rad) of `states` from `q`."""
    if not states:
        return 0.0
    return float(np.max(np.abs(np.asarray([s.q for s in states]) - np.asarray(q))))


def _resume(cell: FaultCell, held: RobotState, start: int) -> tuple[list[RobotState], float]:
    """After a new engagement: the states from `start` and the offset (m) of the first
    state of that engagement from the hold point."""
    first = cell.obs.wait_state(lambda s: s.engage > held.engage, start, 30.0)
    assert first is not None, "no new engagement reached the arm"
    states = cell.obs.states(start)
    offset = float(np.linalg.norm(np.subtract(first.tool_p, held.tool_p)))
    before = [s for s in states if s.seq < first.seq and s.seq > held.seq]
    assert _drift(before, held.q) <= 2 * REST_TOL_RAD, "the arm moved while nobody engaged"
    return states, offset


def test_kill_master_mid_motion_holds_and_a_restart_reengages_without_jump(
    cell: FaultCell,
) -> None:
    cell.ensure_following()
    obs = cell.obs
    i = obs.n_states()
    pre = obs.wait_states(125, i, 5.0)
    speed = path_length(pre) / ((pre[-1].t_ns - pre[0].t_ns) / 1e9)
    assert speed > 0.01, "the arm should be moving when the master dies"
    ev0 = obs.n_events()
    k = obs.n_states()
    t_fault = time.time_ns()
    cell.kill(MASTER_ID)
    held, _, hold_ms = _assert_rest(cell, k, t_fault, HOLD_DEADLINE_S)
    watchdog = obs.wait_event(
        lambda e: e.source == "decision" and e.kind == "watchdog", ev0, HOLD_DEADLINE_S
    )
    # Restart: a new master process, a new engagement, rebased where the arm holds.
    m = obs.n_states()
    cell.start(MASTER_ID)
    _, offset = _resume(cell, held, m)
    assert cell.wait_motion(0.005, 10.0), "the new engagement does not move the arm"
    full = obs.states(k)
    steps = tool_steps(full, MAX_TOOL_SPEED_M_S, STATE_PERIOD_S, read_age_s=READ_AGE_S)
    still = [s for s in full if s.seq >= held.seq and s.engage == held.engage]
    record(
        "kill_master",
        speed_before_m_s=round(speed, 4),
        decision_event_ms=round((watchdog.t_ns - t_fault) / 1e6, 1),
        time_to_hold_ms=round(hold_ms, 1),
        held_for_s=round((still[-1].t_ns - held.t_ns) / 1e9, 2),
        drift_while_held_rad=_drift(still, held.q),
        decision_event=watchdog.message,
        resume_offset_mm=round(offset * 1e3, 3),
        state_steps=steps.n,
        max_step_mm=round(steps.max_step_m * 1e3, 3),
        max_step_of_limit=round(steps.max_ratio, 3),
        jumps=steps.jumps,
    )
    assert _drift(still, held.q) <= 2 * REST_TOL_RAD
    assert offset < REBASE_TOL_M
    assert steps.jumps == 0
    cell.assert_no_crash()


def test_frozen_master_holds_within_the_lease_and_resumes_without_jump(cell: FaultCell) -> None:
    cell.ensure_following()
    obs = cell.obs
    assert cell.wait_motion(0.005, 5.0)
    master = cell[MASTER_ID]
    ev0 = obs.n_events()
    k = obs.n_states()
    t_fault = time.time_ns()
    t0 = time.monotonic()
    master.freeze()
    try:
        held, states, hold_ms = _assert_rest(cell, k, t_fault, LEASE_S)
        watchdog = obs.wait_event(
            lambda e: e.source == "decision" and e.kind == "watchdog", ev0, LEASE_S
        )
        # Frozen past the master's lease: every peer drops its session and token.
        gone = wait_until(lambda: not obs.node.alive.is_alive(f"master/{MASTER_ID}"), 5.0)
        token_gone_ms = (time.monotonic() - t0) * 1e3
        assert gone, "the frozen master's liveliness token never went away"
    finally:
        master.thaw()
    t_thaw = time.monotonic()
    back = obs.node.alive.wait(f"master/{MASTER_ID}", 15.0)
    token_back_ms = (time.monotonic() - t_thaw) * 1e3
    m = obs.n_states()
    after = obs.wait_states(int(1.5 / STATE_PERIOD_S), m, 10.0)
    steps = tool_steps(states + after, MAX_TOOL_SPEED_M_S, STATE_PERIOD_S, read_age_s=READ_AGE_S)
    drift = _drift([s for s in states + after if s.seq >= held.seq], held.q)
    record(
        "freeze_master",
        decision_event=watchdog.message,
        decision_event_ms=round((watchdog.t_ns - t_fault) / 1e6, 1),
        time_to_hold_ms=round(hold_ms, 1),
        token_gone_after_ms=round(token_gone_ms, 1),
        token_back_after_thaw_ms=round(token_back_ms, 1),
        drift_after_thaw_rad=drift,
        mode_after_thaw=cell.mode(),
        jumps=steps.jumps,
        max_step_mm=round(steps.max_step_m * 1e3, 3),
    )
    assert back, "the thawed master never came back on the bus"
    assert master.alive
    # The frozen engagement is blocked for good: the arm stays where it held, no jump.
    assert drift <= 2 * REST_TOL_RAD
    assert steps.jumps == 0
    cell.assert_no_crash()


def test_kill_force_with_compliance_holds_and_a_restart_resumes_streaming(
    cell: FaultCell,
) -> None:
    cell.ensure_following()
    obs = cell.obs
    reply = cell.call("supervisor", {"compliance": True})
    assert reply["settings"]["compliance"] is True
    try:
        assert cell.wait_motion(0.005, 5.0), "compliance on: the arm should still follow"
        ev0 = obs.n_events()
        k = obs.n_states()
        t_fault = time.time_ns()
        cell.kill("force")
        held, states, hold_ms = _assert_rest(cell, k, t_fault, HOLD_DEADLINE_S)
        hold_ev = obs.wait_event(
            lambda e: e.source == "decision" and e.kind == "watchdog", ev0, HOLD_DEADLINE_S
        )
        f0 = obs.n_force()
        t_restart = time.monotonic()
        cell.start("force")
        got = obs.wait_force(1000, f0, 30.0)
        first_ms = (obs.force_times()[f0] - t_restart) * 1e3 if got else float("nan")
        seqs = obs.force_seqs(f0)
        lost = int(seqs[-1] - seqs[0] + 1 - len(seqs)) if seqs else -1
        m = obs.n_states()
        later = obs.wait_states(100, m, 5.0)
        drift = _drift([s for s in states if s.seq >= held.seq] + later, held.q)
        record(
            "kill_force_compliance",
            decision_event_ms=round((hold_ev.t_ns - t_fault) / 1e6, 1),
            time_to_hold_ms=round(hold_ms, 1),
            decision_event=hold_ev.message,
            restart_to_first_sample_ms=round(first_ms, 1),
            samples_after_restart=got,
            seq_gaps_after_restart=lost,
            drift_while_held_rad=drift,
        )
        assert got >= 1000, "the restarted force service does not stream"
        steps = [b - a for a, b in itertools.pairwise(seqs)]
        assert min(steps) >= 1, "a force sample arrived twice or out of order"
        # robot/force is best effort (PROTOCOL §3): a sample lost in transit is one
        # millisecond of a continuous signal. On this VM with its host stealing half the
        # CPU, 3-51 of 1000 were (5 of 6 runs of the unchanged code, 2026-12-02); what the
        # restart owes is a stream in order with no more than that; the quiet machine's
        # loss is the bench's (0 in docs/bench.md).
        assert lost <= BEST_EFFORT_LOSS * got, (
            f"{lost} of {got + lost} force samples lost in transit"
        )
        assert drift <= 2 * REST_TOL_RAD, "the arm moved without a new engagement"
    finally:
        cell.call("supervisor", {"compliance": False})
    cell.assert_no_crash()


def _rogue(cell: FaultCell, seconds: float) -> Child:
    argv = [
        sys.executable,
        "-m",
        "tests.faults.rogue",
        "--connect",
        cell.cell.endpoint,
        "--rate-hz",
        "10000",
        "--seconds",
        str(seconds),
    ]
    return cell.cell.add_argv("rogue", argv)


def _rejected(cell: FaultCell) -> int:
    """The decision server's count of rejected robot/cmd payloads."""
    return int(cell.call("status")["interventions"].get("rejected", 0))


def _status_calls(cell: FaultCell, until: float) -> tuple[int, int, float]:
    """Call decision `status` back to back until the monotonic time `until`:
    (answered, failed, slowest reply in ms)."""
    ok = failed = 0
    slowest = 0.0
    while time.monotonic() < until:
        t = time.monotonic()
        try:
            cell.call("status")
            ok += 1
        except (RpcError, Unavailable):
            failed += 1
        slowest = max(slowest, (time.monotonic() - t) * 1e3)
    return ok, failed, slowest


def test_flood_of_commands_leaves_decision_responsive_and_force_streaming(
    cell: FaultCell,
) -> None:
    cell.ensure_following()
    obs = cell.obs
    flood_s = 3.0
    t_a = time.monotonic()
    pre_ok, pre_failed, _ = _status_calls(cell, t_a + 2.0)
    t_b = time.monotonic()
    stats0 = cell.call("status")["supervisor"]["stats"]
    rejected0 = _rejected(cell)
    rogue = _rogue(cell, flood_s).start()
    try:
        ok, failed, slowest = 0, 0, 0.0
        t_limit = time.monotonic() + 60.0
        while MARK not in rogue.tail(5) and rogue.alive and time.monotonic() < t_limit:
            o, f, s = _status_calls(cell, time.monotonic() + 0.25)
            ok, failed, slowest = ok + o, failed + f, max(slowest, s)
        lines = [ln for ln in rogue.tail(50).splitlines() if ln.startswith(MARK)]
        assert lines, f"the rogue did not finish its flood\n{rogue.tail()}"
        result = json.loads(lines[-1][len(MARK) :])
        # The decision takes robot/cmd through its intake (Node.batches): under a flood what
        # waits is bounded (64, the oldest dropped unread), so it counts what it read, never
        # more than was sent, and has nothing left to work through once the flood ends.
        t_end = time.monotonic()
        counts: list[int] = []

        def settled() -> bool:
            counts.append(_rejected(cell) - rejected0)
            return len(counts) >= 3 and counts[-1] == counts[-3]

        drained = wait_until(settled, 30.0, poll_s=0.1)
        status = cell.call("status")
    finally:
        cell.expected_down.add("rogue")
        rogue.stop()
    drain_ms = (time.monotonic() - t_end) * 1e3
    stats1 = status["supervisor"]["stats"]
    # The rogue's wall-clock window on this process's monotonic clock (one host, one clock).
    offset = time.time() - time.monotonic()
    w0, w1 = result["t0_ns"] / 1e9 - offset, result["t1_ns"] / 1e9 - offset
    force_t = obs.force_times()
    pre_rate = count_between(force_t, t_a, t_b) / (t_b - t_a)
    flood_rate = count_between(force_t, w0, w1) / (w1 - w0)
    record(
        "flood",
        rogue_sent=result["sent"],
        rogue_rate_hz=round(result["rate_hz"]),
        rogue_garbage=result["garbage"],
        rogue_time_in_put_s=round(result["put_s"], 2),
        decision_commands_received=stats1["commands"] - stats0["commands"],
        decision_backlog_settled_ms=round(drain_ms),
        status_before_ok=pre_ok,
        status_before_failed=pre_failed,
        status_during_ok=ok,
        status_during_failed=failed,
        status_slowest_ms=round(slowest, 1),
        force_rate_before_hz=round(pre_rate),
        force_rate_during_hz=round(flood_rate),
        force_fraction=round(flood_rate / pre_rate, 3),
        decision_rejected=status["interventions"].get("rejected", 0) - rejected0,
        decision_lease_refusals=status["interventions"].get("lease"),
    )
    # It aims at 10 kHz; on a loaded 2-core host Zenoh's back-pressure (robot/cmd blocks
    # rather than drops) and the CPU hold it lower. At least 10× a master's 100 Hz is a flood.
    assert result["sent"] >= 1000 * flood_s, "the rogue did not flood"
    assert drained, "the decision server was still working through the flood 30 s later"
    assert 0 < counts[-1] <= result["garbage"], (counts[-1], result["garbage"])
    assert failed == 0 and ok >= 3
    # The force stream keeps flowing through the flood. On a quiet 2-core host it keeps
    # 88–91 % of its rate (docs/faults.md); the bound is loose because CI machines are shared
    # (45 % was seen with a benchmark running beside the suite): it catches a stalled stream.
    assert flood_rate >= 0.3 * pre_rate
    cell.assert_no_crash()


def test_router_restart_every_service_reconnects_and_streams_resume(cell: FaultCell) -> None:
    cell.ensure_following()
    obs = cell.obs
    s0, f0 = obs.n_states(), obs.n_force()
    t_kill = time.monotonic()
    cell.router.kill()
    cell.expected_down.add("router")
    # The peers meshed through the router's gossip: they keep streaming without it.
    outage_states = len(obs.wait_states(250, s0, 5.0))
    outage_force = obs.wait_force(500, f0, 5.0)
    outage_s = time.monotonic() - t_kill
    cell.cell.start_router()
    cell.expected_down.discard("router")
    t_restart = time.monotonic()
    # A client sees only what the router routes: everything it sees came back through it.
    probe = Observer(cell.cell.endpoint, name="probe", mode="client")
    try:
        wanted = {"arm", "force", "decision", f"master/{MASTER_ID}"}
        back = wait_until(lambda: wanted <= probe.node.alive.names(), 30.0)
        tokens_ms = (time.monotonic() - t_restart) * 1e3
        probe.wait_states(1, 0, 15.0)
        state_ms = (time.monotonic() - t_restart) * 1e3
        probe.wait_force(1, 0, 15.0)
        force_ms = (time.monotonic() - t_restart) * 1e3
        states = len(probe.wait_states(250, 0, 15.0))
        force = probe.wait_force(1000, 0, 15.0)
        reply = probe.node.call("decision", "status", {}, 5.0)
        sessions = _router_sessions(probe)
    finally:
        probe.close()
    record(
        "router_restart",
        outage_s=round(outage_s, 2),
        states_during_outage=outage_states,
        force_during_outage=outage_force,
        tokens_back_ms=round(tokens_ms, 1),
        first_state_ms=round(state_ms, 1),
        first_force_ms=round(force_ms, 1),
        probe_states=states,
        probe_force=force,
        router_peer_sessions=sessions,
        mode_after=reply["mode"],
    )
    assert outage_states >= 250 and outage_force >= 500
    assert back, f"not every service's token came back through the router: {wanted}"
    assert states >= 250 and force >= 1000
    assert sorted(reply["alive"]) == sorted(["decision", "force", "arm", f"master/{MASTER_ID}"])
    assert sessions >= 5, "arm, force, decision, master and the observer reconnect"
    cell.assert_no_crash()


def _router_sessions(probe: Observer) -> int:
    """How many peers the router has a session with (its admin space)."""
    for reply in probe.node.session.get("@/*/router", timeout=5.0):
        if reply.ok is None:
            continue
        info = json.loads(reply.ok.payload.to_bytes())
        return sum(1 for s in info.get("sessions", []) if s.get("whatami") == "peer")
    return -1


def test_kill_arm_is_reported_calls_are_unavailable_and_nothing_else_crashes(
    cell: FaultCell,
) -> None:
    cell.ensure_following()
    obs = cell.obs
    ev0 = obs.n_events()
    t_kill = time.time_ns()
    cell.kill("arm")
    lost = obs.wait_event(
        lambda e: e.source == "decision" and e.kind == "watchdog", ev0, HOLD_DEADLINE_S
    )
    event_ms = (lost.t_ns - t_kill) / 1e6
    status = cell.call("status")
    with pytest.raises(RpcError) as err:
        cell.call("limits")
    with pytest.raises(RpcError) as err_move:
        cell.call("move_relative", {"dp": [0.0, 0.0, 0.01]})
    master_status = obs.node.call(f"master/{MASTER_ID}", "status", {}, 3.0)
    alive = {n: cell[n].alive for n in ("force", "decision", MASTER_ID)}
    record(
        "kill_arm",
        decision_event=lost.message,
        decision_event_ms=round(event_ms, 1),
        alive_in_status=status["alive"],
        arm_in_status=status["arm"],
        limits_error=err.value.code,
        move_error=err_move.value.code,
        other_processes_alive=alive,
    )
    assert "arm" not in status["alive"]
    assert status["arm"].get("error") == "unavailable"
    assert err.value.code == "unavailable"
    assert err_move.value.code == "unavailable"
    assert master_status["master"] == MASTER_ID
    assert all(alive.values()) and cell.router.alive
    cell.start("arm")
    cell.wait_ready()
    assert obs.node.alive.wait("arm", 30.0)
    cell.assert_no_crash()


def _more_setpoints(fake: FakeController, n: int, timeout_s: float) -> bool:
    start = len(fake.setpoints)
    return wait_until(lambda: len(fake.setpoints) >= start + n, timeout_s)


def _fake_q_still(fake: FakeController, quiet_s: float, timeout_s: float) -> np.ndarray | None:
    """Wait until the controller's joints stay put for `quiet_s`; those joints."""
    deadline = time.monotonic() + timeout_s
    q_ref, t_ref = fake.q, time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.02)
        q = fake.q
        if float(np.max(np.abs(q - q_ref))) > REST_TOL_RAD:
            q_ref, t_ref = q, time.monotonic()
        elif time.monotonic() - t_ref >= quiet_s:
            return q
    return None


def test_serial_controller_garbles_and_drops_bytes_error_reconnect_no_jump(
    cell: FaultCell,
) -> None:
    with FakeController(q_init=HOME_Q_RAD, calibration_s=0.2) as fake:
        cell.ensure_following()
        cell.replace("arm", "arm", "--driver", "serial", "--port", fake.url, "--autostart")
        cell.start("arm")
        try:
            _garble_and_drop(cell, fake)
        finally:
            # Back to the simulated arm before the fake controller goes away.
            cell.replace("arm", "arm", "--autostart")
    cell.start("arm")
    cell.wait_ready()
    cell.assert_no_crash()


def _garble_and_drop(cell: FaultCell, fake: FakeController) -> None:
    obs = cell.obs
    faults: dict[str, Callable[[], None]] = {
        "garble_reply": fake.garble_next_reply,
        "drop_reply_bytes": lambda: fake.drop_next_reply_bytes(3),
    }
    for name, inject in faults.items():
        cell.ensure_following()
        assert _more_setpoints(fake, 20, 10.0), "the controller gets no setpoints"
        ev0 = obs.n_events()
        k = obs.n_states()
        t0 = time.monotonic()
        inject()
        err = obs.wait_event(
            lambda e: e.source == "arm" and e.kind == "error", ev0, HOLD_DEADLINE_S
        )
        error_ms = (time.monotonic() - t0) * 1e3
        said = obs.wait_state(lambda s: s.status == "error", k, 5.0)
        assert said is not None, "robot/state never said error"
        q_held = _fake_q_still(fake, 0.5, HOLD_DEADLINE_S + 1.0)
        assert q_held is not None, "the controller's arm did not hold"
        # Recover through the operator's entry point, as an operator would.
        cell.call("connect")
        cell.call("initialize")
        ready = cell.wait_ready(30.0)
        offset = float(np.max(np.abs(np.asarray(ready.q) - q_held)))
        m = obs.n_states()
        cell.ensure_following()
        steps = tool_steps(
            obs.states(k), MAX_TOOL_SPEED_M_S, STATE_PERIOD_S, SERIAL_SAMPLE_PERIOD_S
        )
        record(
            f"serial_{name}",
            arm_error=err.message,
            error_reported_ms=round(error_ms, 1),
            ready_q_offset_rad=offset,
            max_setpoint_jump_rad=round(fake.max_setpoint_jump_rad, 5),
            controller_step_errors=fake.errors_sent["STEP"],
            controller_connections=fake.connections,
            jumps=steps.jumps,
            max_step_mm=round(steps.max_step_m * 1e3, 3),
            states_after=obs.n_states() - m,
        )
        assert offset < 1e-4, "the arm's joints changed across the fault"
        assert fake.max_setpoint_jump_rad < 0.1
        assert fake.errors_sent["STEP"] == 0
        assert steps.jumps == 0


def test_no_event_was_lost_during_all_the_faults(cell: FaultCell) -> None:
    """Every robot/events message of every source reached the observer, which was connected
    throughout: per source the seqs are 1, 2, 3, … again from 1 after each restart."""
    cell.ensure_following()
    events = cell.obs.events()
    per_source = event_continuity(events)
    record(
        "events",
        total=len(events),
        per_source={
            s: {"received": v.received, "segments": v.segments, "lost": v.lost}
            for s, v in sorted(per_source.items())
        },
        lost=sum(v.lost for v in per_source.values()),
        disorder=sum(v.disorder for v in per_source.values()),
        cell_recoveries=cell.recoveries,
    )
    assert {"arm", "force", "decision"} <= set(per_source)
    for source, v in per_source.items():
        assert v.lost == 0 and v.disorder == 0, f"{source}: {v}"
    cell.assert_no_crash()
