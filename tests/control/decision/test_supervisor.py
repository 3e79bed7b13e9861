"""The Supervisor driven tick by tick: each filter, the watchdogs, the lease, e-stop, rebase."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from services.bus.codec import to_fields
from services.bus.errors import RpcError
from services.control.decision.config import DecisionConfig
from services.control.decision.supervisor import Mode
from services.control.decision.target import HOLD_RESEND_NS, MAX_SPAN_S
from services.control.decision.tasks import TaskPlan, guarded_move_plan
from services.control.decision.watch import target_problem
from services.control.passivity.slave import DEADBAND_N
from services.geometry import angle_between, rot_z
from services.world.workcell.scene import TABLE
from tests.control.decision.rig import FINGER_M, TICK_NS, TOOL_DOWN, Rig

V_STEP = 0.25 * 0.002  # default speed limit per 2 ms tick (m)
W_STEP = 1.0 * 0.002  # default rotation limit per tick (rad)
CFG = DecisionConfig()


def engaged(rig: Rig, master: str = "m1", engage: int = 1, ticks: int = 3) -> None:
    for _ in range(ticks):
        rig.step([rig.cmd(master, engage)])
    assert rig.sup.mode is Mode.FOLLOW and rig.sup.lease == master


# --- mapping and the filters ---------------------------------------------------------------


def test_follows_the_operator_in_world_and_tool_frames() -> None:
    rig = Rig()
    start = rig.p.copy()
    engaged(rig)
    first = rig.outputs[0]
    assert first.master == "decision" and first.active
    assert np.allclose(first.dp, 0.0)  # rebased on the current pose: no jump
    rig.run(20, lambda i: [rig.cmd(dp=(0.0, 0.01, 0.0))])
    assert np.allclose(rig.p, start + np.array([0.0, 0.01, 0.0]), atol=1e-9)
    # a new engagement in tool mode: dp is along the tool axes (z down)
    rig.run(20, lambda i: [rig.cmd(engage=2, dp=(0.0, 0.0, 0.01), frame="tool")])
    assert np.allclose(rig.p, start + np.array([0.0, 0.01, -0.01]), atol=1e-9)
    assert rig.outputs[-1].engage == 2 and rig.sup.stats["engagements"] == 2


def test_every_published_command_is_valid_on_the_wire() -> None:
    rig = Rig()
    engaged(rig)
    rig.run(50, lambda i: [rig.cmd(dp=(0.001 * i, 0, 0), dR=rot_z(0.01 * i))])
    for c in rig.outputs:
        to_fields(c.target)  # raises ProtocolError if a rotation drifted or a field is bad
    seqs = [c.seq for c in rig.outputs]
    assert seqs == sorted(set(seqs))


def test_one_command_out_per_command_in_and_nothing_while_nothing_changes() -> None:
    rig = Rig()
    engaged(rig)
    n = len(rig.outputs)
    sent = [rig.cmd(dp=(0.0005 * i, 0, 0)) for i in range(10)]
    for cmd in sent:
        rig.step([cmd])
    assert len(rig.outputs) == n + 10  # each command at once, carrying its origin
    assert [c.origin_t_ns for c in rig.outputs[n:]] == [c.t_ns for c in sent]
    n = len(rig.outputs)
    rig.run(20)  # 40 ms without input (watchdog 100 ms): nothing to send
    assert len(rig.outputs) == n and rig.sup.mode is Mode.FOLLOW


def test_next_wake_is_a_watchdog_deadline_a_hold_resend_or_nothing() -> None:
    rig = Rig()
    assert rig.sup.next_wake_ns() is None  # idle: only inputs wake it
    engaged(rig)
    rig.step([rig.cmd()])
    wake = rig.sup.next_wake_ns()
    assert wake is not None and wake == rig.now_ns + int(CFG.watchdog_ms * 1e6) + 1
    rig.step([rig.cmd(active=False)])  # disengage: the hold went out at once
    assert not rig.outputs[-1].active
    assert rig.sup.next_wake_ns() == rig.now_ns + HOLD_RESEND_NS
    run = rig.sup.start_task(guarded_move_plan({"direction": [0, 0, 1]}, CFG), rig.now_ns)
    assert rig.sup.next_wake_ns() == rig.now_ns + int(CFG.period_s * 1e9)
    rig.sup.cancel_task(rig.now_ns)
    assert run.done


def test_with_passivity_on_a_contact_re_sends_the_target_every_period() -> None:
    """The slave's passivity port corrects the target only when a command goes out: with it
    on, teleoperation ticks every period, and while the wrist feels a contact (|f| at or
    above the port's dead band, or a moment at or above the rotational port's, 0.1 N·m)
    each tick re-sends the target; in free space nothing."""
    period_ns = int(CFG.period_s * 1e9)
    for passivity in (False, True):
        rig = Rig(DecisionConfig(passivity=passivity))
        engaged(rig)
        rig.step([rig.cmd()])
        wake = rig.sup.next_wake_ns()
        watchdog = rig.now_ns + int(CFG.watchdog_ms * 1e6) + 1
        assert wake == (rig.now_ns + period_ns if passivity else watchdog)
        n = len(rig.outputs)
        rig.run(10)  # free space: nothing to correct, nothing sent
        assert len(rig.outputs) == n
        rig.push_w = np.array([0.0, 0.0, 0.9 * DEADBAND_N])  # below the dead band: noise
        rig.run(10)
        assert len(rig.outputs) == n
        rig.push_c = np.array([0.0, 0.09, 0.0])  # a moment below the rotational band
        rig.run(10)
        assert len(rig.outputs) == n
        rig.push_c = np.array([0.0, 0.3, 0.0])  # a contact by its moment alone
        rig.run(5)
        assert len(rig.outputs) == n + (5 if passivity else 0)
        rig.push_c = np.zeros(3)
        n = len(rig.outputs)
        rig.push_w = np.array([0.0, 0.0, 5.0])  # a contact
        rig.run(10)
        sent = rig.outputs[n:]
        assert len(sent) == (10 if passivity else 0)
        # each a re-send of the target carrying out the operator's newest command
        assert all(c.active and c.origin_t_ns == rig.outputs[n - 1].origin_t_ns for c in sent)
        assert all(np.allclose(c.dp, rig.outputs[n - 1].dp) for c in sent)  # the same target
        # The force goes stale (no sample for stale_ms): no contact is known, nothing sent.
        rig.step([rig.cmd()], force=False, dt_ns=int(CFG.stale_ms * 1e6) + TICK_NS)
        m = len(rig.outputs)
        rig.run(10, force=False)
        assert len(rig.outputs) == m
        seqs = [c.seq for c in rig.outputs]
        assert seqs == sorted(set(seqs))


def test_an_engagement_waiting_for_the_force_stream_is_deferred_not_refused() -> None:
    """While the service brings robot/force up (force_warming) a new engagement waits, even
    with compliance on (which refuses one without force for good): the master's next
    command starts it once a sample is in. Without the flag the refusal stands."""
    rig = Rig(DecisionConfig(compliance=True))
    for _ in range(3):
        rig.step([rig.cmd()], force=False, force_warming=True)
    assert rig.sup.mode is Mode.IDLE and rig.outputs == []
    assert rig.sup.stats["deferred"] == 3 and "rejected" not in rig.kinds()
    rig.step([rig.cmd()], force_warming=True)  # a sample, but the stream not yet back
    assert rig.sup.mode is Mode.IDLE and rig.sup.stats["deferred"] == 4
    rig.step([rig.cmd()])  # the stream is back
    assert rig.sup.mode is Mode.FOLLOW and rig.sup.stats["engagements"] == 1
    assert rig.outputs[0].active and np.allclose(rig.outputs[0].dp, 0.0)
    cold = Rig(DecisionConfig(compliance=True))
    cold.step([cold.cmd()], force=False)
    assert cold.sup.mode is Mode.IDLE and "rejected" in cold.kinds()
    cold.step([cold.cmd()])
    assert cold.sup.mode is Mode.IDLE  # blocked for good: engage again to move


def test_a_100_hz_master_at_a_legal_speed_is_followed_without_a_limit() -> None:
    rig = Rig()
    engaged(rig)
    start = rig.p.copy()
    v = 0.9 * CFG.max_tool_speed_m_s
    for i in range(1, 31):  # 300 ms at 100 Hz: each step 10 ms of motion
        rig.step([rig.cmd(dp=(v * 0.01 * i, 0, 0))], dt_ns=10_000_000)
        assert np.allclose(rig.sup.target.p_sup, start + np.array([v * 0.01 * i, 0, 0]), atol=1e-12)
    assert not [n for n in rig.notices_of("limit") if n.data["reason"] == "speed"]
    assert rig.sup.notices.counters["limit"] == 0


def test_a_target_held_back_by_the_speed_limit_catches_up_on_the_timer() -> None:
    rig = Rig()
    engaged(rig)
    start = rig.p.copy()
    rig.step([rig.cmd(dp=(0.01, 0, 0))])  # 1 cm at once: 40 ms at the limit speed
    wake = rig.sup.next_wake_ns()
    assert wake == rig.now_ns + int(CFG.period_s * 1e9)  # catching up: every period
    n = len(rig.outputs)
    rig.run(25)  # 50 ms of timer ticks, no new command
    # each step still carries out that one command: its origin
    assert len(rig.outputs) > n
    assert all(c.origin_t_ns == rig.outputs[n - 1].origin_t_ns for c in rig.outputs[n:])
    assert np.allclose(rig.sup.target.p_sup, start + np.array([0.01, 0, 0]), atol=1e-12)
    rig.step()
    assert rig.sup.next_wake_ns() == rig.sup._cmd_rx_ns + int(CFG.watchdog_ms * 1e6) + 1


def test_speed_limit_spreads_a_jump_and_catches_up() -> None:
    rig = Rig()
    engaged(rig)
    start = rig.p.copy()
    path = []
    for _ in range(250):
        rig.step([rig.cmd(dp=(0.1, 0.0, 0.0))])
        path.append(rig.sup.target.p_sup.copy())
    steps = np.linalg.norm(np.diff(np.array([start, *path]), axis=0), axis=1)
    assert steps.max() <= V_STEP + 1e-12
    assert np.allclose(
        path[-1], start + np.array([0.1, 0.0, 0.0]), atol=1e-9
    )  # delayed, not dropped
    speed = [n for n in rig.notices_of("limit") if n.data["reason"] == "speed"]
    assert len(speed) == 1 and rig.sup.notices.counters["limit"] == 1


def test_the_approach_zone_slows_motion_towards_the_floor_and_only_that() -> None:
    """Within approach_zone_m of the box's floor (the table top) the target goes down at
    approach_speed at most; above it, and sideways or up inside it, at the full limit. The
    goal is reached late, not dropped, and the intervention is reported once."""
    cfg = DecisionConfig(approach_zone_m=0.02, approach_speed_m_s=0.01)
    floor = cfg.workspace_min[2]
    rig = Rig(cfg, p=(0.6, 0.0, floor + 0.05))
    engaged(rig)
    start = rig.p.copy()
    zs = [float(rig.sup.target.p_sup[2])]
    for _ in range(2000):  # 4 s of ticks towards 4.5 cm down (0.5 cm above the floor)
        rig.step([rig.cmd(dp=(0.0, 0.0, -0.045))])
        zs.append(float(rig.sup.target.p_sup[2]))
    down = -np.diff(zs)
    fast = V_STEP + 1e-12
    slow = 0.01 * 0.002 + 1e-12
    above = [d for z0, d in zip(zs, down, strict=False) if z0 - floor > 0.02 + V_STEP]
    inside = [d for z0, d in zip(zs, down, strict=False) if z0 - floor <= 0.02]
    assert max(above) == pytest.approx(V_STEP)  # above the zone: the speed limit alone
    assert inside and max(inside) <= slow and max(down) <= fast
    assert zs[-1] == pytest.approx(floor + 0.005, abs=1e-9)  # delayed, not dropped
    approach = [n for n in rig.notices_of("limit") if n.data["reason"] == "approach"]
    assert len(approach) == 1 and approach[0].data["approach_speed_m_s"] == 0.01
    # inside the zone: sideways at the full speed limit, then up at the full speed limit
    x0 = float(rig.sup.target.p_sup[0])
    rig.step([rig.cmd(dp=(0.02, 0.0, -0.045))])
    assert float(rig.sup.target.p_sup[0]) - x0 == pytest.approx(V_STEP)
    z0 = float(rig.sup.target.p_sup[2])
    rig.step([rig.cmd(dp=(V_STEP, 0.0, -0.025))])
    assert float(rig.sup.target.p_sup[2]) - z0 == pytest.approx(V_STEP)
    assert float(rig.sup.target.p_sup[0]) == pytest.approx(start[0] + V_STEP)


def test_after_a_long_silence_the_target_moves_on_at_the_speed_limit_not_in_a_leap() -> None:
    """A stream stalled for 1 s (TCP over a WAN, watchdogs widened to 2.4 s): the next
    command's step covers at most MAX_SPAN_S of speed; the rest follows on the timer."""
    cfg = DecisionConfig(watchdog_ms=2400.0, state_stale_ms=2400.0)
    rig = Rig(cfg)
    engaged(rig)
    start = rig.p.copy()
    rig.step([rig.cmd(dp=(0.0, 0.0, 0.0))])
    rig.run(500)  # 1 s of silence: no command
    rig.step([rig.cmd(dp=(0.1, 0.0, 0.0))])  # 10 cm further, after the silence
    x = float(rig.sup.target.p_sup[0]) - start[0]
    assert x == pytest.approx(cfg.max_tool_speed_m_s * MAX_SPAN_S)  # 2.5 cm, not 10
    xs = [x]
    for _ in range(300):
        rig.step()
        xs.append(float(rig.sup.target.p_sup[0]) - start[0])
    assert max(np.diff(xs)) <= V_STEP + 1e-12 and xs[-1] == pytest.approx(0.1)


def test_a_force_stream_that_stops_makes_the_target_wait_then_go_on() -> None:
    """The wrist force flowed in this engagement and stops (a stalled link: the contact
    filter cannot see): the target waits where it is, once reported; it goes on when
    samples are back, at the speed limit, no leap."""
    rig = Rig()
    engaged(rig)
    goal = (0.05, 0.0, 0.0)
    rig.run(20, lambda i: [rig.cmd(dp=goal)])
    xs = [float(rig.sup.target.p_sup[0])]
    for _ in range(60):  # 120 ms without a sample: stale after 50 ms
        rig.step([rig.cmd(dp=goal)], force=False)
        xs.append(float(rig.sup.target.p_sup[0]))
    steps = np.diff(xs)
    stale_from = int(CFG.stale_ms * 1e6 / TICK_NS) + 1
    assert all(d == pytest.approx(V_STEP) for d in steps[: stale_from - 1])  # still fresh
    assert not np.any(steps[stale_from:])  # waited
    (ev,) = [n for n in rig.notices_of("limit") if n.data["reason"] == "force_gap"]
    assert ev.data["stale_ms"] == CFG.stale_ms and rig.sup.mode is Mode.FOLLOW
    assert rig.sup.stats["force_gap_ticks"] >= 60 - stale_from
    for _ in range(10):
        rig.step([rig.cmd(dp=goal)])
        xs.append(float(rig.sup.target.p_sup[0]))
    assert max(np.diff(xs[-11:])) <= V_STEP + 1e-12 and xs[-1] > xs[-11]


def test_with_no_force_sensor_or_a_lost_one_teleoperation_is_not_paused() -> None:
    """No wrist force ever (a deployment without a sensor), or the force service gone
    (its token lost): nothing to wait for, the target follows (compliance off)."""
    rig = Rig()
    for _ in range(3):
        rig.step([rig.cmd()], force=False)
    assert rig.sup.mode is Mode.FOLLOW
    x0 = float(rig.sup.target.p_sup[0])
    rig.run(40, lambda i: [rig.cmd(dp=(0.01, 0.0, 0.0))], force=False)
    assert float(rig.sup.target.p_sup[0]) - x0 == pytest.approx(0.01)
    lost = Rig()
    engaged(lost)
    lost.step([lost.cmd()], force=False, lost=("force",))
    x0 = float(lost.sup.target.p_sup[0])
    lost.run(40, lambda i: [lost.cmd(dp=(0.01, 0.0, 0.0))], force=False)
    assert float(lost.sup.target.p_sup[0]) - x0 == pytest.approx(0.01)
    assert not [n for n in lost.notices_of("limit") if n.data["reason"] == "force_gap"]


def test_without_an_approach_zone_the_floor_is_reached_at_the_speed_limit() -> None:
    floor = CFG.workspace_min[2]
    rig = Rig(p=(0.6, 0.0, floor + 0.05))
    engaged(rig)
    zs = [float(rig.sup.target.p_sup[2])]
    for _ in range(200):
        rig.step([rig.cmd(dp=(0.0, 0.0, -0.045))])
        zs.append(float(rig.sup.target.p_sup[2]))
    assert -min(np.diff(zs)) == pytest.approx(V_STEP)
    assert zs[-1] == pytest.approx(floor + 0.005, abs=1e-9)
    assert not [n for n in rig.notices_of("limit") if n.data["reason"] == "approach"]


def test_rotation_speed_limit() -> None:
    rig = Rig()
    engaged(rig)
    Rs = [rig.R.copy()]
    for _ in range(600):
        rig.step([rig.cmd(dR=rot_z(1.0))])
        Rs.append(rig.sup.target.R_sup.copy())
    assert max(angle_between(a, b) for a, b in itertools.pairwise(Rs)) <= W_STEP + 1e-9
    assert angle_between(Rs[-1], TOOL_DOWN @ rot_z(1.0)) < 1e-6


def test_workspace_clamp_keeps_an_offset_not_a_jump() -> None:
    rig = Rig(p=(0.9, 0.0, 0.6))
    engaged(rig)
    rig.run(300, lambda i: [rig.cmd(dp=(0.2, 0.0, 0.0))])  # hand 15 cm beyond x = 0.95
    assert rig.sup.target.p_sup[0] == pytest.approx(0.95)
    assert rig.p[0] <= 0.95 + 1e-12
    limits = [n for n in rig.notices_of("limit") if n.data["reason"] == "workspace"]
    assert len(limits) == 1
    # the hand comes back 5 cm: the tool comes back 5 cm at once (the excess is forgotten)
    rig.run(200, lambda i: [rig.cmd(dp=(0.15, 0.0, 0.0))])
    assert rig.sup.target.p_sup[0] == pytest.approx(0.90)


def test_engagement_outside_the_box_may_only_come_back() -> None:
    rig = Rig(p=(1.0, 0.0, 0.6))  # outside x ≤ 0.95
    engaged(rig)
    rig.run(20, lambda i: [rig.cmd(dp=(0.05, 0.0, 0.0))])
    assert rig.sup.target.p_sup[0] == pytest.approx(1.0)  # not further out
    # back by 10 cm from the hand's furthest point (the 5 cm out were dropped)
    rig.run(400, lambda i: [rig.cmd(dp=(-0.05, 0.0, 0.0))])
    assert rig.sup.target.p_sup[0] == pytest.approx(0.9)


def test_contact_stops_motion_into_the_table_but_not_along_or_away() -> None:
    """The PUMA in the MuJoCo cell (the rig's `cell`): its fingertips touch the table."""
    top = TABLE.top_z + FINGER_M  # the tool point's height when the fingertips touch
    rig = Rig(p=(0.6, 0.0, top + 0.02), cell=True)
    engaged(rig)
    # the hand goes down to 1.5 mm above the workspace floor (the table top), 33.5 mm
    # past the fingertips' contact
    down = -(0.02 + FINGER_M - 0.0015)
    rig.run(400, lambda i: [rig.cmd(dp=(0.0, 0.0, down))])
    assert rig.sup.notices.counters["contact"] == 1
    (ev,) = rig.notices_of("contact")
    assert ev.data["reason"] == "force" and ev.data["force_n"] > 40.0
    z_stop = rig.p[2]
    assert top - 0.002 < z_stop < top + 0.002  # the fingertips touch, the box floor is not hit
    assert not [n for n in rig.notices_of("limit") if n.data["reason"] == "workspace"]
    force_n = float(np.linalg.norm(rig.force_w()))
    # still touching, never above the limit by more than one step of the stiffest contact
    # (the impact's transient stops it: at rest the arm presses less than the limit)
    assert 1.0 < force_n < 40.0 + 20_000 * V_STEP + 1e-6
    # sliding along the table is allowed while in contact
    rig.run(200, lambda i: [rig.cmd(dp=(0.02, 0.0, down))])
    assert rig.p[0] == pytest.approx(0.62, abs=2e-3)  # the servo's lag against friction
    assert rig.p[2] == pytest.approx(z_stop, abs=1e-3)
    # lifting the hand lifts the tool at once (what went into the table was dropped)
    rig.run(100, lambda i: [rig.cmd(dp=(0.02, 0.0, down + 0.01))])
    assert rig.p[2] == pytest.approx(z_stop + 0.01, abs=2e-3)


def test_torque_filter_stops_rotation_into_a_moment() -> None:
    rig = Rig()
    engaged(rig)
    rig.push_c = np.array([0.0, 0.0, 5.0])  # a moment about the tool z axis (> 4 N·m)
    R_before = rig.R.copy()
    rig.run(50, lambda i: [rig.cmd(dR=rot_z(-0.05))])  # turning against it: refused
    assert angle_between(R_before, rig.R) < 1e-9
    assert [n.data["reason"] for n in rig.notices_of("contact")] == ["torque"]
    # turning back with it is allowed at once: the hand's 0.1 rad back move becomes 0.1 rad
    rig.run(100, lambda i: [rig.cmd(dR=rot_z(0.05))])
    assert angle_between(R_before, rig.R) == pytest.approx(0.1, abs=1e-6)


def test_admittance_yields_to_a_push_beyond_the_deadband() -> None:
    rig = Rig(DecisionConfig(compliance=True))
    engaged(rig)
    start = rig.p.copy()
    rig.push_w = np.array([1.5, 0.0, 0.0])  # inside the 2 N deadband
    rig.run(100, lambda i: [rig.cmd()])
    assert np.allclose(rig.p, start)
    rig.push_w = np.array([12.0, 0.0, 0.0])  # 10 N beyond the band: 0.02 m/s
    rig.run(500, lambda i: [rig.cmd()])  # 1 s
    assert rig.p[0] - start[0] == pytest.approx(0.02, rel=1e-6)
    rig.push_w = np.zeros(3)
    rig.run(100, lambda i: [rig.cmd()])  # released: the tool stays where it was pushed
    assert rig.p[0] - start[0] == pytest.approx(0.02, rel=1e-6)


def test_compliance_with_a_stale_force_stream_holds() -> None:
    rig = Rig(DecisionConfig(compliance=True))
    engaged(rig)
    rig.run(30, lambda i: [rig.cmd()], force=False)  # 60 ms without a sample (stale: 50 ms)
    assert rig.sup.mode is Mode.HOLD
    (ev,) = rig.notices_of("watchdog")
    assert ev.data["reason"] == "force_stale"
    assert not rig.outputs[-1].active


def test_compliance_refuses_an_engagement_without_force() -> None:
    rig = Rig(DecisionConfig(compliance=True))
    rig.run(30, lambda i: [rig.cmd()], force=False)
    assert rig.sup.mode is Mode.IDLE and rig.outputs == []
    assert rig.sup.notices.counters["rejected"] >= 1


# --- watchdogs, hold, rebase -------------------------------------------------------------------


def test_a_watchdog_hold_names_the_master_and_its_own_engagement() -> None:
    """The hold's `data.engage` is the master's engagement (what it shows and must leave),
    not the decision's counter (`engage_out`); the `engagement_held` notice says what held
    it, so a master whose hold event was rate-limited away still knows (issue 42 item 5)."""
    rig = Rig()
    engaged(rig, engage=7)
    rig.run(60)  # 120 ms without commands
    (ev,) = rig.notices_of("watchdog")
    assert ev.data["master"] == "m1" and ev.data["engage"] == 7
    assert ev.data["engage_out"] == rig.sup.target.engage_out != 7
    rig.step([rig.cmd(engage=7)])
    held = rig.notices_of("lease")[-1]
    assert held.data["reason"] == "engagement_held" and held.data["held_by"] == "command_timeout"


def test_command_watchdog_holds_until_a_new_engagement_and_rebases() -> None:
    rig = Rig()
    engaged(rig)
    rig.run(20, lambda i: [rig.cmd(dp=(0.0, 0.005, 0.0))])
    rig.run(60)  # 120 ms without commands (watchdog 100 ms)
    assert rig.sup.mode is Mode.HOLD and rig.sup.lease is None
    (ev,) = rig.notices_of("watchdog")
    assert ev.data["reason"] == "command_timeout"
    n_active = sum(c.active for c in rig.outputs)
    rig.run(100)  # 200 ms of holding: the hold goes out at once, then at 20 Hz
    assert not any(c.active for c in rig.outputs[n_active:])
    held = [c for c in rig.outputs if not c.active]
    assert len(held) in (5, 6) and {c.engage for c in held} == {1}
    gaps = [b.t_ns - a.t_ns for a, b in itertools.pairwise(held)]
    assert min(gaps) >= HOLD_RESEND_NS
    assert all(np.allclose(c.dp, held[0].dp) for c in held)  # the last target, re-sent
    n = len(rig.outputs)
    # the same engagement resumes streaming: nothing moves
    rig.run(50, lambda i: [rig.cmd(dp=(0.0, 0.05, 0.0))])
    assert not any(c.active for c in rig.outputs[n:])
    assert rig.notices_of("lease")[-1].data["reason"] == "engagement_held"
    # a new engagement moves again, rebased on the current pose (first dp = 0)
    pose = rig.p.copy()
    rig.step([rig.cmd(engage=2)])
    new = rig.outputs[-1]
    assert new.active and new.engage == 2 and np.allclose(new.dp, 0.0)
    assert np.allclose(rig.p, pose)


def test_master_liveliness_lost_holds_at_once() -> None:
    rig = Rig()
    engaged(rig)
    rig.step([rig.cmd()], lost=["master/m1"])
    assert rig.sup.mode is Mode.HOLD and not rig.outputs[-1].active
    assert rig.notices_of("watchdog")[-1].data["reason"] == "master_lost"
    n = len(rig.outputs)
    # the token comes back and the same engagement keeps streaming: still held
    rig.run(30, lambda i: [rig.cmd(dp=(0.01, 0, 0))])
    assert len(rig.outputs) > n and not any(c.active for c in rig.outputs[n - 1 :])


def test_stale_robot_state_or_robot_error_holds() -> None:
    rig = Rig()
    engaged(rig)
    rig.run(110, lambda i: [rig.cmd()], state=False)  # 220 ms > state_stale_ms 200
    assert rig.notices_of("watchdog")[-1].data["reason"] == "state_stale"
    rig2 = Rig()
    engaged(rig2)
    rig2.status = "error"
    rig2.step([rig2.cmd()])
    assert rig2.notices_of("watchdog")[-1].data["reason"] == "robot_error"


def test_engagement_refused_when_the_robot_is_not_ready() -> None:
    rig = Rig(status="connected")
    rig.run(5, lambda i: [rig.cmd()])
    assert rig.sup.mode is Mode.IDLE and rig.outputs == []
    rig.status = "ready"
    rig.run(5, lambda i: [rig.cmd()])  # that engagement was refused for good
    assert rig.outputs == []
    engaged(rig, engage=2)


def test_disengage_releases_the_lease_and_holds() -> None:
    rig = Rig()
    engaged(rig)
    rig.step([rig.cmd(active=False)])
    assert rig.sup.mode is Mode.HOLD and rig.sup.lease is None
    assert rig.notices_of("lease")[-1].data["action"] == "released"
    assert rig.sup.notices.counters["watchdog"] == 0  # a disengage is not an intervention
    n = len(rig.outputs)
    assert not rig.outputs[-1].active  # the hold, at once
    rig.run(30)
    assert len(rig.outputs) > n and all(not c.active for c in rig.outputs[n - 1 :])


def test_stale_seq_and_engage_are_ignored() -> None:
    rig = Rig()
    engaged(rig)
    rig.run(30, lambda i: [rig.cmd(dp=(0.0, 0.01, 0.0))])
    target = rig.p.copy()
    old = rig.cmd(dp=(0.0, 0.05, 0.0), seq=3)  # an old seq arriving late
    rig.step([old])
    rig.step([rig.cmd(engage=0, dp=(0.05, 0, 0))])  # a lower engage
    rig.step([rig.cmd(dp=(0.0, 0.01, 0.0))])
    assert np.allclose(rig.p, target)
    assert rig.sup.stats["stale_commands"] == 2
    assert rig.notices_of("rejected")[0].data["reason"] == "stale seq or engage"


def test_a_restarted_master_counting_from_one_is_accepted() -> None:
    rig = Rig()
    engaged(rig)
    rig.step([rig.cmd(active=False)])
    rig.now_ns += 1_000_000_000  # the master restarts a second later with seq 1, engage 1
    rig.seqs.clear()
    engaged(rig, engage=1)


# --- the lease ---------------------------------------------------------------------------------


def test_a_second_master_is_refused_with_rate_limited_events() -> None:
    rig = Rig()
    engaged(rig, "m1")
    rig.run(250, lambda i: [rig.cmd("m1"), rig.cmd("m2", dp=(0.05, 0, 0))])  # 0.5 s
    refused = [n for n in rig.notices_of("lease") if n.data.get("master") == "m2"]
    assert len(refused) == 1  # one event per second and master
    assert rig.sup.notices.counters["lease"] == 250  # every refused command is counted
    assert rig.sup.lease == "m1"
    rig.step([rig.cmd("m1", active=False)])
    rig.run(5, lambda i: [rig.cmd("m2", dp=(0.05, 0, 0))])  # m2's current engagement: blocked
    assert rig.sup.lease is None
    engaged(rig, "m2", engage=2)


# --- e-stop ------------------------------------------------------------------------------------


def test_estop_latches_holds_refuses_and_reset_needs_a_new_engagement() -> None:
    rig = Rig()
    engaged(rig)
    rig.sup.estop(rig.now_ns)
    n = len(rig.outputs)
    rig.run(10, lambda i: [rig.cmd(dp=(0.05, 0, 0))])
    assert rig.sup.mode is Mode.ESTOP and len(rig.outputs) > n
    assert all(not c.active for c in rig.outputs[n:])
    assert rig.sup.notices.counters["estop"] == 1 + 10  # the latch and every refused command
    assert rig.notices_of("estop")[0].data["latched"] is True
    with pytest.raises(RpcError) as e:
        rig.sup.claim("move_joints")
    assert e.value.code == "estop"
    with pytest.raises(RpcError) as e:
        rig.sup.start_task(TaskPlan("guarded_move", ()), rig.now_ns)
    assert e.value.code == "estop"
    assert rig.sup.reset(rig.now_ns)
    n = len(rig.outputs)
    rig.run(10, lambda i: [rig.cmd(dp=(0.05, 0, 0))])
    assert not any(c.active for c in rig.outputs[n:])
    engaged(rig, engage=2)


def test_claim_for_a_forwarded_motion() -> None:
    rig = Rig()
    rig.sup.claim("home")  # idle: fine
    engaged(rig)
    with pytest.raises(RpcError) as e:
        rig.sup.claim("move_pose")
    assert e.value.code == "busy"
    rig.step([rig.cmd(active=False)])
    assert rig.sup.mode is Mode.HOLD
    rig.sup.claim("move_pose")  # stops re-sending the hold
    n = len(rig.outputs)
    rig.run(5)
    assert len(rig.outputs) == n


def test_stop_holds_teleoperation() -> None:
    rig = Rig()
    engaged(rig)
    rig.sup.stop(rig.now_ns)
    rig.step([rig.cmd(dp=(0.02, 0, 0))])
    assert rig.sup.mode is Mode.HOLD and not rig.outputs[-1].active


def test_tick_timing_uses_the_nominal_period() -> None:
    assert int(DecisionConfig().period_s * 1e9) == TICK_NS


# --- hostile input -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("dp", "frame"),
    [
        ((1e308, 0.0, 0.0), "world"),
        ((0.0, 0.0, 1e300), "world"),
        ((1e308, 1e308, 1e308), "tool"),  # R0·dp would overflow to inf, then NaN
        ((2.5, 0.0, 0.0), "world"),  # finite, sane-looking, but beyond any engagement
    ],
)
def test_an_absurd_command_is_refused_before_arithmetic_and_the_hold_goes_on(
    dp: tuple[float, float, float], frame: str
) -> None:
    rig = Rig()
    engaged(rig)
    rig.run(10, lambda i: [rig.cmd(dp=(0.0, 0.0002 * i, 0.0))])
    assert rig.sup.notices.counters["limit"] == 0
    target = rig.sup.target.p_sup.copy()
    n = len(rig.outputs)
    rig.run(20, lambda i: [rig.cmd(dp=dp, frame=frame)], dt_ns=10_000_000)  # 20 at 100 Hz
    assert rig.sup.mode is Mode.HOLD and rig.sup.lease is None
    assert np.array_equal(rig.sup.target.p_sup, target)  # not a nanometre
    out = rig.outputs[n:]
    assert out and not any(c.active for c in out)  # holds keep going out, finite
    for c in out:
        to_fields(c.target)
    assert rig.sup.notices.counters["limit"] == 20
    (ev,) = [e for e in rig.notices_of("limit") if e.data.get("reason", "").startswith("dp")]
    assert "exceeds 2 m" in ev.data["reason"]  # names the field and the bound


def test_a_flood_of_master_ids_stays_a_trickle_of_events_in_bounded_memory() -> None:
    rig = Rig()
    engaged(rig, "m1")
    n0 = len(rig.notices_of("lease"))
    for i in range(3000):  # 3000 masters, each refused once, within 60 ms
        rig.step([rig.cmd(f"rogue{i}", dp=(0.05, 0, 0))], dt_ns=20_000)
    refused = rig.notices_of("lease")[n0:]
    assert len(refused) <= 5  # NOTICES_PER_S over all of them
    assert rig.sup.notices.counters["lease"] == 3000  # every one counted
    assert rig.sup.notices.keys_remembered <= 1024 and len(rig.sup.masters) <= 64
    rig.run(600, lambda i: [rig.cmd("m1")])  # a second and more later, one says how many
    rig.step([rig.cmd("late", dp=(0.05, 0, 0))])
    assert rig.notices_of("lease")[-1].data.get("suppressed", 0) >= 2990


# --- forwarded motions ---------------------------------------------------------------------------


def test_a_forwarded_motion_is_watched_and_stopped_at_a_contact() -> None:
    rig = Rig()
    rig.sup.claim("move_relative", rig.now_ns)
    assert rig.sup.watch is not None and rig.sup.next_wake_ns() is not None
    rig.status = "moving"
    rig.run(5)
    assert rig.sup.watch is not None and not any(r.stop_arm for r in rig.results)
    rig.push_w = np.array([0.0, 0.0, 60.0])  # the table pushes back: 60 N > 40 N
    res = rig.step()
    assert res.stop_arm and rig.sup.watch is None
    (ev,) = rig.notices_of("contact")
    assert ev.data["method"] == "move_relative" and ev.data["force_n"] > 40.0
    assert rig.sup.notices.counters["contact"] == 1


def test_a_forwarded_motion_leaving_the_box_is_stopped_and_one_that_ends_is_not() -> None:
    rig = Rig()
    rig.sup.claim("move_joints", rig.now_ns)
    rig.status = "moving"
    rig.run(3)
    rig.p = np.array([0.6, 0.0, CFG.workspace_min[2] - 0.01])  # 1 cm under the box's floor
    assert rig.step().stop_arm
    assert rig.notices_of("limit")[-1].data["reason"] == "workspace"
    rig2 = Rig()
    rig2.sup.claim("home", rig2.now_ns)
    rig2.status = "moving"
    rig2.run(3)
    rig2.status = "ready"  # the motion is over
    rig2.step()
    assert rig2.sup.watch is None and rig2.sup.next_wake_ns() is None


def test_a_forwarded_target_outside_the_workspace_is_named() -> None:
    cfg = DecisionConfig()
    assert target_problem(cfg, "move_pose", (0.6, 0.0, 0.6)) is None
    why = target_problem(cfg, "move_relative", (0.6, 0.0, 0.3))
    assert why is not None and why.startswith("move_relative: target") and "workspace" in why
