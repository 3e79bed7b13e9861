"""The slave side of time-domain passivity on the bus (docs/passivity.md).

The decision server runs on the robot host and sees the supervised command, robot/state and
robot/force, so it holds the slave port: the commanded displacement of the tool point
(world frame) against the wrist force (tool frame → world by `tool_R`), and the tool's
measured motion (robot/state) beside it. `SlaveTdpa.apply` observes that port, corrects
the command's `dp` so the robot never puts more energy into the
workcell than the operator put into the channel (`SlavePassivity`, energies from
`robot/passivity/master`), and publishes its own on `robot/passivity/slave`.

Engagements: a new operator engagement (master, engage) starts a new count, as the master
does; a new engagement of the arm (the supervisor's own `engage`, e.g. after a hold) takes
the tool orientation then as R0 and the offset restarts at zero (the puma records its start
pose at that command, so the offset is already in it: nothing jumps). A hold (inactive
command) passes unchanged. The correction only shortens motion into a contact or backs it
out along the contact force; the supervisor checked the uncorrected target.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from services.bus import keys
from services.bus.messages import ForceSample, OperatorCommand, RobotState
from services.bus.node import Node
from services.passivity.controller import SlavePassivity
from services.passivity.wire import passivity_state

DEADBAND_N = 1.0
"""A wrist force below this is sensor noise, not contact: the slave port sees none (the
energy of a motion against less than 1 N goes unobserved; with noise counted instead, its
random direction would hold back free motion)."""
DT_MIN_S = 1e-4
DT_MAX_S = 0.1


class SlaveTdpa:
    """enabled: correct (true) or only observe and publish (false). drift_m_s, slack_m: see
    `SlavePassivity`; deadband_n: see DEADBAND_N."""

    def __init__(
        self,
        node: Node,
        enabled: bool = True,
        drift_m_s: float = 0.01,
        slack_m: float = 0.0,
        deadband_n: float = DEADBAND_N,
    ) -> None:
        self.deadband_n = deadband_n
        self.pc = SlavePassivity(enabled=enabled, drift_m_s=drift_m_s, slack_m=slack_m)
        self._pub = node.publisher(keys.PASSIVITY_SLAVE)
        self._master_energy = node.latest(keys.PASSIVITY_MASTER)
        self._seq = 0
        self._operator: tuple[str, int] | None = None
        self._arm_engage: int | None = None
        self._R0 = np.eye(3)
        self._last: np.ndarray | None = None
        self._last_ns = 0
        self._tool_p: np.ndarray | None = None

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
        renumbered by the supervisor, e.g. after a hold) only rebase the offset.
        """
        if not cmd.active or operator is None:
            self._last = None
            self._tool_p = None
            return cmd
        if operator != self._operator:
            self._operator = operator
            self.pc.reset(operator[1])
            self._arm_engage = None
            self._tool_p = None
        if cmd.engage != self._arm_engage:
            self._arm_engage = cmd.engage
            self.pc.rebase()
            self._R0 = np.eye(3) if state is None else np.asarray(state.tool_R).reshape(3, 3)
            self._last = None
        d = np.asarray(cmd.dp, dtype=float)
        if cmd.frame == "tool":
            d = self._R0 @ d
        dx = np.zeros(3) if self._last is None else d - self._last
        dt_s = min(max((now_ns - self._last_ns) * 1e-9, DT_MIN_S), DT_MAX_S)
        self._last, self._last_ns = d, now_ns
        f_world = np.zeros(3)
        if force is not None and state is not None:
            f_world = np.asarray(state.tool_R).reshape(3, 3) @ np.asarray(force.f, dtype=float)
            if float(np.linalg.norm(f_world)) < self.deadband_n:
                f_world = np.zeros(3)  # sensor noise: no contact, nothing to pay for
        # The arm limits its speed and the supervisor may change the target, so the command
        # is not all the workcell received: the observer also sees the measured motion.
        done = np.zeros(3)
        if state is not None:
            p = np.asarray(state.tool_p, dtype=float)
            if self._tool_p is not None:
                done = p - self._tool_p
            self._tool_p = p
        got = self._master_energy.read()
        if got is not None and got[0].master == operator[0] and got[0].side == "master":
            self.pc.remote.update(got[0].engage, got[0].e_in)
        self.pc.step(f_world.tolist(), dx.tolist(), dt_s, done.tolist())
        self._publish(operator)
        target = d + np.asarray(self.pc.offset)
        if cmd.frame == "tool":
            target = self._R0.T @ target
        return dataclasses.replace(cmd, dp=tuple(float(x) for x in target))

    def _publish(self, operator: tuple[str, int]) -> None:
        self._seq += 1
        self._pub.put(passivity_state(self._seq, operator[0], operator[1], "slave", self.pc))
