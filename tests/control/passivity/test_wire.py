"""TDPA on the bus: the PassivityState message, the master's display hook and the decision's
command correction, each talking to a peer over loopback Zenoh."""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import pytest

from services.bus import codec, keys
from services.bus.errors import ProtocolError
from services.bus.messages import (
    IDENTITY_R,
    ArmTarget,
    ForceSample,
    PassivityState,
    RobotState,
)
from services.control.decision.config import DecisionConfig
from services.control.decision.passivity import SlaveTdpa
from services.control.decision.service import DecisionService
from services.control.master.device import HandReading
from services.control.master.feedback import DisplayWrench
from services.control.master.passivity import MasterTdpa
from services.geometry import angle_between, m9, rot_y, rot_z
from tests.conftest import Net, wait_until


def state(side: str, engage: int, e_in: float, master: str = "m1") -> PassivityState:
    return PassivityState(
        seq=int(time.time_ns() // 1000),
        t_ns=time.time_ns(),
        master=master,
        engage=engage,
        side=side,  # type: ignore[arg-type]
        enabled=True,
        e_in=e_in,
        e_out=0.0,
        dissipated_j=0.0,
        gain=0.0,
        active_steps=0,
    )


def test_passivity_state_round_trips_and_refuses_absurd_energy() -> None:
    msg = state("slave", 3, 0.25)
    assert codec.decode(PassivityState, codec.encode(msg)) == msg
    bad = codec.to_fields(msg) | {"e_in": -1.0}
    with pytest.raises(ProtocolError, match="e_in"):
        codec.from_fields(PassivityState, bad)
    with pytest.raises(ProtocolError, match="side"):
        codec.from_fields(PassivityState, codec.to_fields(msg) | {"side": "both"})


def hand(x: float) -> HandReading:
    return HandReading(hand_p=np.array([x, 0.0, 0.0]), hand_R=np.eye(3), clutch=False)


def wrench(fx: float) -> DisplayWrench:
    return DisplayWrench(np.array([fx, 0.0, 0.0]), np.zeros(3), False, False)


def test_master_hook_damps_until_the_slave_has_put_energy_in(net: Net) -> None:
    a, b = net.node("master"), net.node("robot")
    tdpa = MasterTdpa(a, "m1", lambda: 7)
    seen: list[PassivityState] = []
    b.subscribe(keys.PASSIVITY_MASTER, seen.append)
    slave_pub = b.publisher(keys.PASSIVITY_SLAVE)
    # The force pushes the hand along its motion (+x): output, and no energy from the slave.
    x = 0.0
    tdpa.hook(wrench(10.0), hand(x), 0.001)
    shown = []
    for _ in range(5):
        x += 0.0005
        shown.append(tdpa.hook(wrench(10.0), hand(x), 0.001).f[0])
    assert shown[-1] == pytest.approx(0.0, abs=1e-9)

    def published() -> bool:  # the hand holds still, no force: nothing changes but the news
        tdpa.hook(wrench(0.0), hand(x), 0.001)
        return len(seen) > 0

    assert wait_until(published)
    assert seen[-1].engage == 7
    assert seen[-1].side == "master" and seen[-1].master == "m1"
    # The slave's energy of another engagement or master is ignored; of this one, spent.
    twin = a.subscribe(keys.PASSIVITY_SLAVE)  # the master's session: it has what tdpa has
    for n, other in enumerate((state("slave", 6, 100.0), state("slave", 7, 100.0, master="m2"))):
        slave_pub.put(other)
        assert twin.wait_count(n + 1, 10.0)
        x += 0.0005
        assert tdpa.hook(wrench(10.0), hand(x), 0.001).f[0] == pytest.approx(0.0, abs=1e-9)
        assert tdpa.pc.remote.e_in == 0.0
    slave_pub.put(state("slave", 7, 100.0))

    def passes() -> bool:
        nonlocal x
        x += 0.0005
        return bool(tdpa.hook(wrench(10.0), hand(x), 0.001).f[0] == pytest.approx(10.0))

    assert wait_until(passes)
    assert tdpa.pc.remote.e_in == 100.0
    assert wait_until(lambda: seen[-1].e_out > 0.0)


def test_the_master_shows_a_moment_only_through_a_rotational_port(net: Net) -> None:
    """A master for a device without moments (`passivity_moments` off) shows none. With
    `passivity_moments`, the moment goes through a rotational port of its own: shown while
    nothing turns, withheld while the hand turns along it with nothing from the slave (the
    force, the hand still, shown in full all along), and the master's figures carry the
    rotational port's energies; the slave's `rot_e_in` pays for the moment."""
    held = DisplayWrench(np.array([2.0, 0.0, 0.0]), np.array([0.0, 0.3, 0.0]), False, True)
    hidden = MasterTdpa(net.node("a"), "m1", lambda: 7).hook(held, hand(0.0), 0.001)
    assert hidden.c.tolist() == [0.0, 0.0, 0.0] and not hidden.torque_saturated
    assert hidden.f[0] == pytest.approx(2.0)
    robot = net.node("robot")
    seen: list[PassivityState] = []
    robot.subscribe(keys.PASSIVITY_MASTER, seen.append)
    slave_pub = robot.publisher(keys.PASSIVITY_SLAVE)
    tdpa = MasterTdpa(net.node("b"), "m2", lambda: 7, show_moments=True)

    def turned(angle: float) -> DisplayWrench:
        return tdpa.hook(held, HandReading(np.zeros(3), rot_y(angle), False), 0.001)

    shown = turned(0.0)
    assert shown.c.tolist() == pytest.approx([0.0, 0.3, 0.0]) and shown.torque_saturated
    turning = [turned(0.001 * k) for k in range(1, 40)]
    assert turning[-1].c[1] == pytest.approx(0.0, abs=1e-6)
    assert all(w.f[0] == pytest.approx(2.0) for w in turning)
    assert tdpa.rot is not None and tdpa.rot.observer.e_out > 0.0
    assert tdpa.pc.observer.e_out == 0.0  # the force's port: the hand did not move

    def published() -> bool:
        turned(0.039)
        return len(seen) > 0 and seen[-1].master == "m2"

    assert wait_until(published)
    assert seen[-1].rot_e_out == pytest.approx(tdpa.rot.observer.e_out)
    assert seen[-1].rot_e_in == 0.0
    paid = dataclasses.replace(state("slave", 7, 0.0, master="m2"), rot_e_in=1.0)
    slave_pub.put(paid)

    def moment_back() -> bool:
        return bool(turned(0.039).c[1] == pytest.approx(0.3))

    assert wait_until(moment_back)
    assert tdpa.pc.remote.e_in == 0.0  # the force's reservoir got nothing


def test_the_master_reports_the_force_asked_and_shown_at_the_tool_and_the_slave_takes_its_own(
    net: Net,
) -> None:
    """The master shows the hand 2 N of the 8 it is asked (its reservoir empty, the hand
    pushing 2 N) at a force scale of 0.5: 16 N asked and 4 N shown at the tool. The slave
    port takes them for its own engagement only."""
    a, b = net.node("master"), net.node("robot")
    tdpa = MasterTdpa(a, "m1", lambda: 7, force_scale=0.5)
    seen: list[PassivityState] = []
    b.subscribe(keys.PASSIVITY_MASTER, seen.append)
    slave = SlaveTdpa(b, drift_m_s=0.0, yield_m_s_n=5e-5)
    shown: list[float] = []

    def published() -> bool:  # the hand still: nothing to push it out with
        shown.append(tdpa.hook(wrench(-8.0), hand(0.0), 0.002).f[0])
        return bool(seen)

    assert wait_until(published)
    assert all(-8.0 < x < 0.0 for x in shown)  # held back, every step
    msg = seen[-1]
    assert msg.asked_n == pytest.approx(16.0)
    assert msg.shown_n is not None
    assert any(msg.shown_n == pytest.approx(-x / 0.5) for x in shown)
    st = robot_state()
    push = ForceSample(seq=1, t_ns=time.time_ns(), f=(0.0, 0.0, 20.0), c=(0.0, 0.0, 0.0))

    def taken(engage: int) -> bool:
        tdpa.hook(wrench(-8.0), hand(0.0), 0.002)  # the master goes on publishing
        slave.apply(command(1, 0.0), ("m1", engage), st, push, 0)
        return slave.pc.shown_n is not None

    assert wait_until(lambda: taken(7))
    assert slave.pc.asked_n == pytest.approx(16.0)
    assert not taken(6)  # another engagement's figures are not this one's
    assert slave.pc.asked_n is None
    # Without a force scale (a display that shows nothing) the figures are left out.
    quiet = MasterTdpa(a, "m2", lambda: 7, force_scale=0.0)

    def quiet_published() -> bool:
        quiet.hook(wrench(-8.0), hand(0.0), 0.002)
        return seen[-1].master == "m2"

    assert wait_until(quiet_published)
    assert seen[-1].asked_n is None and seen[-1].shown_n is None


def test_each_side_measures_the_round_trip_from_the_others_echo_and_the_decision_yields_on_it(
    net: Net,
) -> None:
    """The master and the decision exchange figures over loopback: each echoes the other's
    newest stamp, each measures the round trip (well under a second here) and sends it as
    `rtt_ms`; the decision's port takes it, and a short one lets it yield."""
    a, b = net.node("master"), net.node("robot")
    tdpa = MasterTdpa(a, "m1", lambda: 7, force_scale=1.0)
    at_robot: list[PassivityState] = []
    at_master: list[PassivityState] = []
    b.subscribe(keys.PASSIVITY_MASTER, at_robot.append)
    a.subscribe(keys.PASSIVITY_SLAVE, at_master.append)
    slave = SlaveTdpa(b, drift_m_s=0.0, yield_m_s_n=5e-5, yield_max_rtt_s=0.25)
    st = robot_state()
    push = ForceSample(seq=1, t_ns=time.time_ns(), f=(0.0, 0.0, 20.0), c=(0.0, 0.0, 0.0))

    def exchanged() -> bool:
        tdpa.hook(wrench(-8.0), hand(0.0), 0.002)
        slave.apply(command(1, 0.0), ("m1", 7), st, push, 0)
        return slave.pc.rtt_s is not None and tdpa.link.rtt_s(time.monotonic_ns()) is not None

    assert wait_until(exchanged)
    rtt = slave.pc.rtt_s
    assert rtt is not None and 0.0 <= rtt < 1.0
    # The round trip rides on a message every 20 ms at most: the exchange goes on meanwhile.
    assert wait_until(lambda: exchanged() and any(m.rtt_ms is not None for m in at_master))
    assert wait_until(lambda: exchanged() and any(m.rtt_ms is not None for m in at_robot))
    echoed = [m for m in at_robot if m.echo_t_ns is not None]
    sent = {m.t_ns for m in at_master}
    assert echoed and all(m.echo_t_ns in sent for m in echoed)  # ours, stamp for stamp
    assert all(m.echo_age_ns is not None and m.echo_age_ns >= 0 for m in echoed)
    assert slave.link.ignored == 0 and tdpa.link.ignored == 0
    # The contact began before any round trip was known: no yield for it; the next one,
    # begun on this short round trip, yields.
    assert slave.pc.yield_on is False
    free = dataclasses.replace(push, seq=2, t_ns=time.time_ns(), f=(0.0, 0.0, 0.0))
    slave.apply(command(1, 0.0), ("m1", 7), st, free, 0)
    again = dataclasses.replace(push, seq=3, t_ns=time.time_ns())
    slave.apply(command(1, 0.0), ("m1", 7), st, again, 0)
    assert slave.pc.yield_on is True


def robot_state(
    tool_R: tuple[float, ...] = IDENTITY_R,
    tool_p: tuple[float, ...] = (0.5, 0.0, 0.5),
    seq: int = 1,
    t_ns: int | None = None,
    tool_p_cmd: tuple[float, ...] | None = None,
) -> RobotState:
    return RobotState(
        seq=seq,
        t_ns=time.time_ns() if t_ns is None else t_ns,
        status="moving",
        q=(0.0,) * 6,
        tool_p=tool_p,
        tool_R=tool_R,
        flange_p=(0.5, 0.0, 0.7),
        flange_R=tool_R,
        engage=1,
        cmd_seq=1,
        tool_p_cmd=tool_p_cmd,
    )


P0 = (0.5, 0.0, 0.5)
"""Where `robot_state` puts the tool by default, and every engagement here starts."""


def command(
    engage: int,
    dz: float,
    seq: int = 1,
    p0: tuple[float, ...] = P0,
    along: tuple[float, ...] = (0.0, 0.0, 1.0),
) -> ArmTarget:
    """The supervised target `dz` along `along` (world) from `p0`, the engagement's start."""
    now = time.time_ns()
    p = tuple(a + dz * u for a, u in zip(p0, along, strict=True))
    return ArmTarget(
        seq=seq, t_ns=now, origin_t_ns=now, master="decision", engage=engage, p=p, R=IDENTITY_R
    )


def dz_of(out: ArmTarget, p0: tuple[float, ...] = P0) -> float:
    return float(out.p[2] - p0[2])


def test_decision_holds_back_motion_into_a_contact_until_paid_for(net: Net) -> None:
    a, b = net.node("decision"), net.node("master")
    tdpa = SlaveTdpa(a, drift_m_s=0.0)
    seen: list[PassivityState] = []
    b.subscribe(keys.PASSIVITY_SLAVE, seen.append)
    master_pub = b.publisher(keys.PASSIVITY_MASTER)
    push_up = ForceSample(seq=1, t_ns=time.time_ns(), f=(0.0, 0.0, 20.0), c=(0.0, 0.0, 0.0))
    op = ("m1", 4)
    arm = {"p0": np.array([0.5, 0.0, 0.5]), "p": np.array([0.5, 0.0, 0.5]), "engage": 9}
    clock = {"k": 0}

    def go(engage: int, dz: float) -> float:
        """One tick: the target (dz from where the engagement began) through the slave
        port, then an ideal arm (at the corrected target at once)."""
        clock["k"] += 1
        k = clock["k"]
        if engage != arm["engage"]:
            arm["engage"], arm["p0"] = engage, arm["p"].copy()
        # A state and a force sample of this instant (the force measured where the arm is).
        t = 1_000_000_000 + k * 2_000_000
        st = robot_state(tool_p=tuple(float(x) for x in arm["p"]), seq=k, t_ns=t)
        f = dataclasses.replace(push_up, seq=k, t_ns=t)
        p0 = tuple(float(x) for x in arm["p0"])
        out = tdpa.apply(command(engage, dz, seq=k, p0=p0), op, st, f, t)
        arm["p"] = np.asarray(out.p)
        return dz_of(out, p0)

    outs = [go(9, 0.0)] + [go(9, -0.001 * k) for k in range(1, 6)]
    # 1 mm a tick down into a surface pushing up with 20 N, no energy from the operator
    assert outs == pytest.approx([0.0] * 6, abs=1e-12)
    assert tdpa.pc.offset[2] == pytest.approx(0.005)

    def heard() -> bool:
        go(9, -0.005)  # the same depth again (no motion, no energy): one more state out,
        # since those sent before the subscription reached the decision's peer are lost
        return len(seen) > 0 and seen[-1].master == "m1" and seen[-1].engage == 4

    assert wait_until(heard)
    # The slave's figures carry what its overdraws were repaid and forgiven (none yet).
    assert (seen[-1].repaid_j, seen[-1].forgiven_j) == (0.0, 0.0)
    # The operator pays 0.05 J: 2.5 mm more are allowed (20 N × 2.5 mm), the rest waits.
    master_pub.put(state("master", 4, 0.05))

    def paid() -> bool:
        go(9, -0.005)
        return tdpa.pc.remote.e_in == 0.05

    assert wait_until(paid)
    outs = [go(9, -0.001 * depth_mm) for depth_mm in (6, 7, 8)]
    assert outs == pytest.approx([-0.001, -0.002, -0.0025])
    assert go(9, -0.008) == pytest.approx(-0.0025)
    # Moving back out of the contact is never held back.
    assert go(9, -0.0055) == pytest.approx(0.0)
    # A new arm engagement (a rebase) starts the offset from zero: the target is unchanged.
    assert go(10, 0.0) == 0.0
    # Holds pass unchanged.
    hold = dataclasses.replace(command(10, -0.3), hold=True)
    st = robot_state()
    assert tdpa.apply(hold, op, st, push_up, 0) is hold


def test_decision_holds_the_target_on_the_measured_tool_in_contact(net: Net) -> None:
    """The supervisor starts an engagement at the setpoint's pose; the measured tool trails
    it (here still 0.13 mm above it, settling after a move). In contact, with no energy from
    the operator, the port holds the target on the measured tool, not 0.13 mm into the
    wall where the setpoint is."""
    tdpa = SlaveTdpa(net.node("decision"), drift_m_s=0.0)
    op = ("m1", 1)
    t0 = 1_000_000_000
    setpoint, tool = (0.5, 0.0, 0.5), (0.5, 0.0, 0.50013)
    push = ForceSample(seq=1, t_ns=t0, f=(0.0, 0.0, 20.0), c=(0.0, 0.0, 0.0))
    st = robot_state(tool_p=tool, seq=1, t_ns=t0, tool_p_cmd=setpoint)
    out = tdpa.apply(command(1, 0.0, p0=setpoint), op, st, push, t0)
    assert out.p[2] == pytest.approx(tool[2], abs=1e-12)


def test_decision_ignores_forces_below_the_deadband(net: Net) -> None:
    tdpa = SlaveTdpa(net.node("decision"), drift_m_s=0.0)
    op = ("m1", 1)
    st = robot_state()
    noise = ForceSample(seq=1, t_ns=time.time_ns(), f=(0.3, 0.0, 0.5), c=(0.0, 0.0, 0.0))
    tdpa.apply(command(1, 0.0), op, st, noise, 0)
    out = tdpa.apply(command(1, -0.01, seq=2), op, st, noise, 2_000_000)
    assert dz_of(out) == pytest.approx(-0.01)
    assert tdpa.pc.telemetry.active_steps == 0


def test_decision_pairs_force_and_motion_at_one_instant(net: Net) -> None:
    """States at 100 Hz, forces at 500 Hz, each with its own time: the port is observed at
    the newest instant both cover, with the position interpolated there."""
    tdpa = SlaveTdpa(net.node("decision"), drift_m_s=0.0)
    op = ("m1", 1)
    t0 = 1_000_000_000
    # The tool goes 1 cm down in 10 ms (state at t0 and t0 + 10 ms), a 20 N contact force.
    s0 = robot_state(tool_p=(0.5, 0.0, 0.5), seq=1, t_ns=t0)
    s1 = robot_state(tool_p=(0.5, 0.0, 0.49), seq=2, t_ns=t0 + 10_000_000)
    f = ForceSample(seq=1, t_ns=t0, f=(0.0, 0.0, 20.0), c=(0.0, 0.0, 0.0))
    tdpa.apply(command(1, 0.0), op, s0, f, t0)
    # A force sample 4 ms later: observed over 4 ms of the state's motion (4 mm), not 10.
    f4 = dataclasses.replace(f, seq=2, t_ns=t0 + 4_000_000)
    tdpa.apply(command(1, 0.0, seq=2), op, s1, f4, t0 + 10_000_000)
    assert tdpa.pc.observer.e_out == pytest.approx(20.0 * 0.004)
    # A force newer than every state: observed up to the newest state (the rest waits).
    f12 = dataclasses.replace(f, seq=3, t_ns=t0 + 12_000_000)
    tdpa.apply(command(1, 0.0, seq=3), op, s1, f12, t0 + 12_000_000)
    assert tdpa.pc.observer.e_out == pytest.approx(20.0 * 0.01)


def test_decision_excludes_the_supervisors_retraction(net: Net) -> None:
    """Above the supervisor's contact limit the tool backing out under the force is the
    supervisor's doing: no energy for the master."""
    tdpa = SlaveTdpa(net.node("decision"), drift_m_s=0.0, contact_n=40.0)
    op = ("m1", 1)
    t0 = 1_000_000_000
    hard = ForceSample(seq=1, t_ns=t0, f=(0.0, 0.0, 60.0), c=(0.0, 0.0, 0.0))
    for k, z in enumerate((0.490, 0.491, 0.492), start=1):
        t = t0 + k * 2_000_000
        st = robot_state(tool_p=(0.5, 0.0, z), seq=k, t_ns=t)
        tdpa.apply(command(1, 0.0, seq=k), op, st, dataclasses.replace(hard, seq=k, t_ns=t), t)
    assert tdpa.pc.observer.e_in == 0.0
    assert tdpa.pc.excluded_j == pytest.approx(60.0 * 0.002)
    # Below the limit the same motion is the channel's (up to what the workcell was given:
    # here nothing, so it is clipped rather than credited).
    soft = SlaveTdpa(net.node("decision2"), drift_m_s=0.0, contact_n=40.0)
    for k, z in enumerate((0.490, 0.491), start=1):
        t = t0 + k * 2_000_000
        st = robot_state(tool_p=(0.5, 0.0, z), seq=k, t_ns=t)
        f = ForceSample(seq=k, t_ns=t, f=(0.0, 0.0, 20.0), c=(0.0, 0.0, 0.0))
        soft.apply(command(1, 0.0, seq=k), op, st, f, t)
    assert soft.pc.excluded_j == 0.0 and soft.pc.clipped_j == pytest.approx(0.02)


def test_decision_reads_the_wrist_force_in_the_tool_frame(net: Net) -> None:
    a = net.node("decision")
    tdpa = SlaveTdpa(a, drift_m_s=0.0)
    flip = (1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0)  # tool z points down (world −z)
    st = robot_state(flip)
    # the wall pushes along tool −z (world +z); the target moves along tool +z (world −z)
    push = ForceSample(seq=1, t_ns=time.time_ns(), f=(0.0, 0.0, -20.0), c=(0.0, 0.0, 0.0))
    op = ("m1", 1)
    down = (0.0, 0.0, -1.0)
    tdpa.apply(command(1, 0.0, along=down), op, st, push, 0)
    out = tdpa.apply(command(1, 0.002, seq=2, along=down), op, st, push, 2_000_000)
    assert out.p == pytest.approx(P0, abs=1e-12)
    free = ForceSample(seq=2, t_ns=time.time_ns(), f=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0))
    out = tdpa.apply(command(1, 0.003, seq=3, along=down), op, st, free, 4_000_000)
    assert dz_of(out) == pytest.approx(-0.001)


@pytest.mark.parametrize(
    ("passivity", "zone", "warned"), [(True, 0.0, True), (True, 0.02, False), (False, 0.0, False)]
)
def test_decision_warns_when_passivity_runs_without_a_guarded_approach(
    net: Net, caplog: pytest.LogCaptureFixture, passivity: bool, zone: float, warned: bool
) -> None:
    with caplog.at_level(logging.WARNING, logger="telerobot.decision"):
        dec = DecisionService(
            net.node("decision"), DecisionConfig(passivity=passivity, approach_zone_m=zone)
        )
    try:
        said = [r.getMessage() for r in caplog.records if "guarded approach" in r.getMessage()]
        assert len(said) == (1 if warned else 0)
        if warned:
            assert "approach_zone_m" in said[0]
    finally:
        dec.close()


def turn_command(engage: int, angle_rad: float, seq: int = 1) -> ArmTarget:
    """Stay where the engagement began and turn the tool by `angle_rad` about the world's z."""
    return dataclasses.replace(command(engage, 0.0, seq=seq), R=m9(rot_z(angle_rad)))


def test_decision_holds_back_a_turn_into_a_contact_moment_until_paid_for(net: Net) -> None:
    """The tool held still against a contact that resists turning about z with 2 N·m (a
    carried block's edge on the table). The operator's master runs a rotational port and
    has put no energy into it: a command to turn 0.01 rad into the moment (20 mJ) is held at
    the tool's orientation, with the offset in rotation (0.01 rad as 1 mm at 0.1 m a
    radian). Paid 10 mJ on the rotational port, a turn of 0.005 rad is allowed: 2 N·m ×
    0.005 rad. The force's port is untouched throughout."""
    a, b = net.node("decision"), net.node("master")
    tdpa = SlaveTdpa(a, drift_m_s=0.0)
    seen: list[PassivityState] = []
    b.subscribe(keys.PASSIVITY_SLAVE, seen.append)
    master_pub = b.publisher(keys.PASSIVITY_MASTER)
    op = ("m1", 4)
    t0 = 1_000_000_000
    resist = ForceSample(seq=1, t_ns=t0, f=(0.0, 0.0, 0.0), c=(0.0, 0.0, -2.0))
    tick = {"k": 0}
    arm = {"R": IDENTITY_R}

    def go(angle_rad: float) -> ArmTarget:
        """One tick, then an ideal arm: the tool turned to the target at once."""
        tick["k"] += 1
        k = tick["k"]
        t = t0 + k * 2_000_000
        st = robot_state(tool_R=arm["R"], seq=k, t_ns=t)
        f = dataclasses.replace(resist, seq=k, t_ns=t)  # about z: the same in either frame
        out = tdpa.apply(turn_command(9, angle_rad, seq=k), op, st, f, t)
        arm["R"] = out.R
        return out

    def rot_state(e_in: float) -> PassivityState:
        return dataclasses.replace(state("master", 4, 0.0), rot_e_in=e_in)

    announce = rot_state(0.0)

    def counting_moments() -> bool:
        master_pub.put(announce)
        go(0.0)
        return tdpa.rot is not None

    assert wait_until(counting_moments)
    out = go(0.01)
    assert angle_between(np.asarray(out.R).reshape(3, 3), np.eye(3)) == pytest.approx(0.0, abs=1e-9)
    assert tdpa.rot is not None and tdpa.rot.offset[2] == pytest.approx(-0.01 * 0.1)
    master_pub.put(rot_state(0.01))

    def paid() -> bool:
        go(0.01)  # the same turn again (no motion, no energy) until the payment arrives
        return tdpa.rot is not None and tdpa.rot.remote.e_in == 0.01

    assert wait_until(paid)
    # The master turns on to 0.015 rad: the tool, 0.01 behind it, turns 0.005 and no more.
    for angle, allowed in ((0.015, 0.005), (0.02, 0.005)):
        out = go(angle)
        assert np.asarray(out.R).reshape(3, 3) == pytest.approx(rot_z(allowed), abs=1e-9)
    assert out.p == P0
    assert tdpa.pc.telemetry.active_steps == 0 and tdpa.pc.observer.e_out == 0.0

    def reported() -> bool:  # figures sent before the turn may still be arriving
        go(0.02)
        out_j = seen[-1].rot_e_out if seen else None
        return out_j is not None and abs(out_j - 0.01) < 1e-8  # 2 N·m × 0.005 rad

    assert wait_until(reported)
    assert tdpa.rot.observer.e_out == pytest.approx(0.01, rel=1e-6)
    # A master without a rotational port: the turn passes unchanged, as before.
    plain = SlaveTdpa(net.node("decision2"), drift_m_s=0.0)
    cmd = turn_command(9, 0.01)
    st = robot_state(seq=1, t_ns=t0)
    assert plain.apply(cmd, op, st, resist, t0).R == cmd.R
    assert plain.rot is None
