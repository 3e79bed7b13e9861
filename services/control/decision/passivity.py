"""The slave side of time-domain passivity on the bus (docs/passivity.md).

The decision server runs on the robot host and sees the supervised command, robot/state and
robot/force, so it holds the slave port: the wrist force (tool frame → world by `tool_R`)
against the tool's measured motion, both taken at one instant from short timestamped
histories (`SlavePort`, `TimedHistory`). `SlaveTdpa.apply` observes that port, corrects the
supervised target so the robot never puts more energy into the workcell than the operator
put into the channel (energies from `robot/passivity/master`), and publishes its own on
`robot/passivity/slave`. Above the supervisor's contact limit the supervisor retracts the
target itself: the energy that brings in is not the channel's (excluded).

Engagements: a new operator engagement (master, engage) starts a new count, as the master
does; a new engagement of the arm (the supervisor's own `engage`, e.g. after a hold)
restarts the offset at zero (the supervisor starts it where the arm is told to be, so the
offset is already in it: nothing jumps). A hold passes unchanged and is not observed. The
correction only shortens motion into a contact or backs it out along the contact force (at
most 2 mm past the tool); the supervisor checked the uncorrected target.

Moments: while the operator's master runs a rotational port (its figures carry
`rot_e_in`), so does this side (`rot`): the wrist's moment about the tool point against the
tool's rotation, paired at the same instant as the force's, in `port_angles` /
`port_moment` coordinates, its energies of its own; the command's rotation is corrected
along the contact moment as its position is along the force. Otherwise rotations pass
unchanged (docs/passivity.md, "Rotations").
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from services.bus import keys
from services.bus.messages import ArmTarget, ForceSample, PassivityState, RobotState
from services.bus.node import Node
from services.control.passivity.rotation import (
    RotationTrack,
    angles_of,
    angles_towards,
    port_angles,
    port_moment,
    rotate_towards,
)
from services.control.passivity.roundtrip import RoundTrip
from services.control.passivity.slave import DEADBAND_N, SlavePort, TimedHistory
from services.control.passivity.wire import passivity_state
from services.geometry import m9, sub3

DT_MIN_S = 1e-4
DT_MAX_S = 0.1


class SlaveTdpa:
    """enabled: correct (true) or only observe and publish (false). drift_m_s: see
    `SlavePort`; deadband_n: see DEADBAND_N; contact_n: the supervisor's contact force
    limit (N): above it the supervisor moves the target itself (retraction), so the energy
    its motion brings in is not the operator channel's (excluded). yield_m_s_n,
    yield_max_rtt_s: see `SlavePort` (`[decision] passivity_yield_m_s_n`,
    `passivity_yield_max_rtt_ms`); the round trip is measured from the master's echoes
    (`link`, services/control/passivity/roundtrip.py)."""

    def __init__(
        self,
        node: Node,
        enabled: bool = True,
        drift_m_s: float = 0.03,
        deadband_n: float = DEADBAND_N,
        contact_n: float = math.inf,
        yield_m_s_n: float = 0.0,
        yield_max_rtt_s: float = math.inf,
    ) -> None:
        self.deadband_n = deadband_n
        self.contact_n = contact_n
        self.pc = SlavePort(
            enabled=enabled,
            drift_m_s=drift_m_s,
            yield_m_s_n=yield_m_s_n,
            yield_max_rtt_s=yield_max_rtt_s,
        )
        self.link = RoundTrip()
        """The round trip to the operator's master and back, from its echoes of ours (which
        ride on one message in many: every message is read, not only the newest)."""
        self.rot: SlavePort | None = None
        """The rotational port, while the operator's master runs one (None: it does not)."""
        self._enabled, self._drift_m_s = enabled, drift_m_s
        self._turn = RotationTrack()
        self._angles = TimedHistory()
        self._moment = TimedHistory()
        self._pub = node.publisher(keys.PASSIVITY_SLAVE)
        self._master_energy = node.latest(keys.PASSIVITY_MASTER, each=self._heard)
        self._seq = 0
        self._operator: tuple[str, int] | None = None
        self._arm_engage: int | None = None
        self._last_ns = 0
        self._tool = TimedHistory()
        self._force = TimedHistory()
        self._force_seq = -1
        self._state_seq = -1
        self._paired_ns = 0

    def apply(
        self,
        tgt: ArmTarget,
        operator: tuple[str, int] | None,
        state: RobotState | None,
        force: ForceSample | None,
        now_ns: int,
    ) -> ArmTarget:
        """The target to send to the arm in place of `tgt`.

        operator: (master id, engage) of the operator command being carried out, or None
        (no lease); force: None when there is none fresh. Energies are counted per operator
        engagement (the master counts the same way); the arm's own engagements (`tgt.engage`,
        renumbered by the supervisor, e.g. after a hold) only rebase the offset. A hold
        passes unchanged and is not observed (the supervisor's).
        """
        self._remember(state, force)
        if tgt.hold or operator is None:
            self.pc.restart()
            if self.rot is not None:
                self.rot.restart()
            return tgt
        if operator != self._operator:
            self._operator = operator
            self.pc.reset(operator[1])
            self.rot = None
            self._arm_engage = None
        if tgt.engage != self._arm_engage:
            self._arm_engage = tgt.engage
            self.pc.rebase()
            if self.rot is not None:
                self.rot.rebase()
        dt_s = min(max((now_ns - self._last_ns) * 1e-9, DT_MIN_S), DT_MAX_S)
        self._last_ns = now_ns
        got = self._master_energy.read()
        mono = time.monotonic_ns()
        if got is not None and got[0].master == operator[0] and got[0].side == "master":
            self.pc.remote.update(got[0].engage, got[0].e_in)
            ours = got[0].engage == operator[1]
            self.pc.asked_n = got[0].asked_n if ours else None
            self.pc.shown_n = got[0].shown_n if ours else None
            if ours and got[0].rot_e_in is not None:
                if self.rot is None:  # the master's runs one: so does ours, from now on
                    self.rot = SlavePort(enabled=self._enabled, drift_m_s=self._drift_m_s)
                    self.rot.reset(operator[1])
                    self._start_turning(state)
                self.rot.remote.update(got[0].engage, got[0].rot_e_in)
        self.pc.rtt_s = self.link.rtt_s(mono)
        f_now, c_now = self._observe()
        if state is None:
            return tgt
        target = self.pc.correct(list(tgt.p), list(state.tool_p), f_now.tolist(), dt_s)
        R = self._turned(tgt, state, c_now, dt_s)
        self._publish(operator)
        p = tuple(float(x) for x in target)
        return dataclasses.replace(tgt, p=p) if R is None else dataclasses.replace(tgt, p=p, R=R)

    def _heard(self, msg: PassivityState) -> None:
        """Each of the operator's master's figures as read (in `apply`): its echo of ours."""
        if self._operator is not None and (msg.master, msg.side) == (self._operator[0], "master"):
            self.link.heard(msg, time.time_ns(), time.monotonic_ns())

    def _turned(
        self, tgt: ArmTarget, state: RobotState, c_now: list[float], dt_s: float
    ) -> tuple[float, ...] | None:
        """The rotational port's correction of the target's rotation: the new `R`, or None
        when it is unchanged (no rotational port, or no offset in rotation)."""
        rot = self.rot
        if rot is None:
            return None
        theta = self._turn.theta
        R_now = m9(state.tool_R)
        goal = angles_towards(theta, R_now, m9(tgt.R))
        target = rot.correct(port_angles(goal), port_angles(theta), c_now, dt_s)
        if not any(rot.offset):
            return None
        return tuple(rotate_towards(R_now, sub3(angles_of(target), theta)))

    def _start_turning(self, state: RobotState | None) -> None:
        """The rotational port starts: its histories from now on, the tool's angles from its
        orientation now (none are kept while no rotational port runs)."""
        self._turn.reset()
        self._angles.clear()
        self._moment.clear()
        if state is not None:
            self._angles.add(state.t_ns, port_angles(self._turn.update(state.tool_R)))

    def _remember(self, state: RobotState | None, force: ForceSample | None) -> None:
        """Keep the tool positions and the wrist forces (world frame) with their own times;
        with a rotational port, the tool's angles and the wrist moments too."""
        turning = self.rot is not None
        if state is not None and state.seq != self._state_seq:
            self._state_seq = state.seq
            self._tool.add(state.t_ns, state.tool_p)
            if turning:
                self._angles.add(state.t_ns, port_angles(self._turn.update(state.tool_R)))
        if force is not None and state is not None and force.seq != self._force_seq:
            self._force_seq = force.seq
            R = np.asarray(state.tool_R, dtype=float).reshape(3, 3)
            f = R @ np.asarray(force.f, dtype=float)
            if float(np.linalg.norm(f)) < self.deadband_n:
                f = np.zeros(3)  # sensor noise: no contact, nothing to pay for
            self._force.add(force.t_ns, f.tolist())
            if turning:
                # The moment in the rotational port's coordinates, with the same dead band
                # there (1 N as 0.1 N·m).
                c = port_moment((R @ np.asarray(force.c, dtype=float)).tolist())
                if math.sqrt(sum(x * x for x in c)) < self.deadband_n:
                    c = [0.0, 0.0, 0.0]
                self._moment.add(force.t_ns, c)

    def _observe(self) -> tuple[np.ndarray, list[float]]:
        """Observe the ports at the newest instant both streams cover (force and position at
        that same time; the moment and the angles too, with a rotational port); returns the
        newest force (world, N) and moment (the rotational port's coordinates)."""
        t_f, t_p = self._force.newest_ns, self._tool.newest_ns
        if t_f is None or t_p is None:
            return np.zeros(3), [0.0, 0.0, 0.0]
        t = min(t_f, t_p)
        f = self._force.at(t)
        p = self._tool.at(t)
        assert f is not None and p is not None
        if t > self._paired_ns:
            self._paired_ns = t
            supervised = math.sqrt(sum(x * x for x in f)) > self.contact_n
            self.pc.observe(f, p, supervised)
            c, a = self._moment.at(t), self._angles.at(t)
            if self.rot is not None and c is not None and a is not None:
                self.rot.observe(c, a, supervised)
        f_new = self._force.at(t_f)
        c_new = self._moment.at(t_f)
        return (
            np.asarray(f_new if f_new is not None else f, dtype=float),
            list(c_new) if c_new is not None else [0.0, 0.0, 0.0],
        )

    def _publish(self, operator: tuple[str, int]) -> None:
        self._seq += 1
        echo, rtt_s = self.link.carry(time.monotonic_ns())
        self._pub.put(
            passivity_state(
                self._seq,
                operator[0],
                operator[1],
                "slave",
                self.pc,
                rot=self.rot,
                echo=echo,
                rtt_s=rtt_s,
            )
        )
