"""The slave side of time-domain passivity on the bus (docs/passivity.md).

The decision server runs on the robot host and sees the supervised command, robot/state and
robot/force, so it holds the slave port: the wrist force (tool frame → world by `tool_R`)
against the tool's measured motion, both taken at one instant from short timestamped
histories (`SlavePort`, `TimedHistory`). `SlaveTdpa.apply` observes that port, corrects the
command's target so the robot never puts more energy into the workcell than the operator
put into the channel (energies from `robot/passivity/master`), and publishes its own on
`robot/passivity/slave`. Above the supervisor's contact limit the supervisor retracts the
target itself: the energy that brings in is not the channel's (excluded).

Engagements: a new operator engagement (master, engage) starts a new count, as the master
does; a new engagement of the arm (the supervisor's own `engage`, e.g. after a hold) takes
the tool pose then as (p0, R0) and the offset restarts at zero (the puma records its start
pose at that command, so the offset is already in it: nothing jumps). A hold (inactive
command) passes unchanged and is not observed. The correction only shortens motion into a
contact or backs it out along the contact force (at most 2 mm past the tool); the
supervisor checked the uncorrected target.

Moments: while the master's port is the whole wrench (its PassivityState says `moments`),
so is this one: the wrist's moment about the tool point against the tool's rotation, in
`WrenchCoords.slave(ROTATION_LENGTH_M)` coordinates, and the command's rotation is corrected
along the contact moment as its position is along the force (docs/passivity.md,
"Rotations"). Otherwise rotations pass unchanged, as before.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from services.bus import keys
from services.bus.messages import ForceSample, OperatorCommand, RobotState
from services.bus.node import Node
from services.control.passivity.slave import DEADBAND_N, SlavePort, TimedHistory
from services.control.passivity.wire import passivity_state
from services.control.passivity.wrench import RotationTrack, WrenchCoords, rotate_towards
from services.geometry import M9, V3, log9, m9, mul9, mv9, sub3, tmul9

DT_MIN_S = 1e-4
DT_MAX_S = 0.1
ROTATION_LENGTH_M = 0.1
"""A rotation of 1 rad counts as this many metres in the slave port's geometry, a moment of
1 N·m as 1/this newtons (`WrenchCoords.slave`): the back-out of at most 2 mm is 0.02 rad
(1.1°) in rotation, the 1 N dead band 0.1 N·m, the drift's 3 cm/s 0.3 rad/s. Energies are
unchanged (joules either way)."""
ZERO3 = (0.0, 0.0, 0.0)


class SlaveTdpa:
    """enabled: correct (true) or only observe and publish (false). drift_m_s: see
    `SlavePort`; deadband_n: see DEADBAND_N; contact_n: the supervisor's contact force
    limit (N): above it the supervisor moves the target itself (retraction), so the energy
    its motion brings in is not the operator channel's (excluded). yield_m_s_n: see
    `SlavePort` (0: off; `[decision] passivity_yield_m_s_n`)."""

    def __init__(
        self,
        node: Node,
        enabled: bool = True,
        drift_m_s: float = 0.03,
        deadband_n: float = DEADBAND_N,
        contact_n: float = math.inf,
        yield_m_s_n: float = 0.0,
    ) -> None:
        self.deadband_n = deadband_n
        self.contact_n = contact_n
        self.pc = SlavePort(
            enabled=enabled, drift_m_s=drift_m_s, yield_m_s_n=yield_m_s_n, offset=[0.0] * 6
        )
        self.coords = WrenchCoords.slave(ROTATION_LENGTH_M)
        self.moments = False
        """The port counts the moment (the master's port does, for this engagement)."""
        self._turn = RotationTrack()
        self._pub = node.publisher(keys.PASSIVITY_SLAVE)
        self._master_energy = node.latest(keys.PASSIVITY_MASTER)
        self._seq = 0
        self._operator: tuple[str, int] | None = None
        self._arm_engage: int | None = None
        self._R0 = np.eye(3)
        self._p0 = np.zeros(3)
        self._last_ns = 0
        self._tool = TimedHistory()
        self._force = TimedHistory()
        self._force_seq = -1
        self._state_seq = -1
        self._paired_ns = 0

    def apply(
        self,
        cmd: OperatorCommand,
        operator: tuple[str, int] | None,
        state: RobotState | None,
        force: ForceSample | None,
        now_ns: int,
    ) -> OperatorCommand:
        """The command to send to the puma in place of `cmd`.

        operator: (master id, engage) of the operator command being carried out, or None
        (no lease); force: None when there is none fresh. Energies are counted per operator
        engagement (the master counts the same way); the arm's own engagements (`cmd.engage`,
        renumbered by the supervisor, e.g. after a hold) only rebase the offset. A hold
        (inactive command) passes unchanged and is not observed (the supervisor's).
        """
        self._remember(state, force)
        if not cmd.active or operator is None:
            self.pc.restart()
            return cmd
        if operator != self._operator:
            self._operator = operator
            self.pc.reset(operator[1])
            self._arm_engage = None
            self.moments = False
        if cmd.engage != self._arm_engage:
            self._arm_engage = cmd.engage
            self.pc.rebase()
            if state is not None:
                # The puma starts the engagement from its setpoint's pose, not the measured
                # one, which trails it by the servo's error: with the measured pose every
                # target was that far off what the puma aimed at (0.13 mm after the move to
                # the start pose), and the port, holding its target "at the tool", pressed
                # the tool in by that much at each correction (docs/passivity.md).
                p0 = state.tool_p_cmd if state.tool_p_cmd is not None else state.tool_p
                self._R0 = np.asarray(state.tool_R, dtype=float).reshape(3, 3)
                self._p0 = np.asarray(p0, dtype=float)
        d = np.asarray(cmd.dp, dtype=float)
        if cmd.frame == "tool":
            d = self._R0 @ d
        dt_s = min(max((now_ns - self._last_ns) * 1e-9, DT_MIN_S), DT_MAX_S)
        self._last_ns = now_ns
        got = self._master_energy.read()
        if got is not None and got[0].master == operator[0] and got[0].side == "master":
            self.pc.remote.update(got[0].engage, got[0].e_in)
            ours = got[0].engage == operator[1]
            self.pc.asked_n = got[0].asked_n if ours else None
            self.pc.shown_n = got[0].shown_n if ours else None
            if ours and got[0].moments:
                self.moments = True
        f_now = self._observe()
        if state is None:
            return cmd
        cs = self.coords
        theta = self._turn.theta
        if self.moments:
            # The target's angles: the tool's now, turned by what separates the target from it.
            R_target = mul9(m9(self._R0), m9(cmd.dR))
            ahead = log9(tmul9(m9(state.tool_R), R_target))  # tool frame
            turn = _spatial(m9(state.tool_R), ahead)
            rot_target = [t + w for t, w in zip(theta, turn, strict=True)]
        else:
            rot_target = list(theta)
        target = self.pc.correct(
            cs.motion((self._p0 + d).tolist(), rot_target),
            cs.motion(state.tool_p, theta),
            f_now,
            dt_s,
        )
        self._publish(operator)
        p_out, th_out = cs.split_motion(target)
        out = np.asarray(p_out) - self._p0
        if cmd.frame == "tool":
            out = self._R0.T @ out
        dp = tuple(float(x) for x in out)
        if not self.moments or not any(self.pc.offset[3:]):
            return dataclasses.replace(cmd, dp=dp)
        # Corrected in rotation: the tool's orientation now, turned to the corrected angles.
        R_out = rotate_towards(m9(state.tool_R), sub3(th_out, theta))
        return dataclasses.replace(cmd, dp=dp, dR=tmul9(m9(self._R0), R_out))

    def _remember(self, state: RobotState | None, force: ForceSample | None) -> None:
        """Keep the tool positions and the wrist forces (world frame) with their own times."""
        if state is not None and state.seq != self._state_seq:
            self._state_seq = state.seq
            theta = self._turn.update(state.tool_R)
            self._tool.add(state.t_ns, self.coords.motion(state.tool_p, theta))
        if force is not None and state is not None and force.seq != self._force_seq:
            self._force_seq = force.seq
            R = np.asarray(state.tool_R, dtype=float).reshape(3, 3)
            f = (R @ np.asarray(force.f, dtype=float)).tolist()
            c = (R @ np.asarray(force.c, dtype=float)).tolist() if self.moments else ZERO3
            w = self.coords.wrench(f, c)
            if math.sqrt(sum(x * x for x in w)) < self.deadband_n:
                w = [0.0] * 6  # sensor noise: no contact, nothing to pay for
            self._force.add(force.t_ns, w)

    def _observe(self) -> list[float]:
        """Observe the port at the newest instant both streams cover (wrench and motion at
        that same time); returns the newest wrench (world, `self.coords`)."""
        t_f, t_p = self._force.newest_ns, self._tool.newest_ns
        if t_f is None or t_p is None:
            return [0.0] * 6
        t = min(t_f, t_p)
        f = self._force.at(t)
        p = self._tool.at(t)
        assert f is not None and p is not None
        if t > self._paired_ns:
            self._paired_ns = t
            supervised = math.sqrt(sum(x * x for x in f[:3])) > self.contact_n
            self.pc.observe(f, p, supervised)
        f_new = self._force.at(t_f)
        return list(f_new if f_new is not None else f)

    def _publish(self, operator: tuple[str, int]) -> None:
        self._seq += 1
        self._pub.put(
            passivity_state(
                self._seq, operator[0], operator[1], "slave", self.pc, moments=self.moments
            )
        )


def _spatial(R: M9, w_body: V3) -> V3:
    """A rotation vector in the body frame of `R`, in the spatial frame: R·w."""
    return mv9(R, w_body)
