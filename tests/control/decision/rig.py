"""A closed loop for the pure Supervisor: an ideal arm in free space, or the PUMA in a cell.

`Rig.step()` runs one tick: it feeds the supervisor the current robot state and force,
applies the published target to the slave like the arm does (ignoring stale ones) and
records everything, each target with its motion since its engagement began (`Out.dp`,
`Out.dR`: p − p0 and R0ᵀ·R, p0 and R0 the supervisor's engagement pose).

The slave is either ideal (`cell=False`, the default: it goes to the target's pose at once,
in free space: the force is the test's push only) or the PUMA 560 in a MuJoCo cell of the
table (`cell=True`, `CellSlave`: the workcell's physics, services/world/workcell/engine.py,
each target through the arm's IK to its joint servos, 2 ms of physics per tick; the force
is what the solver computes at the wrist, the tool's weight removed as the force service
does, plus the push). Contact is the cell's alone: the gripper's fingertips, 35 mm below
the tool point (`FINGER_M`), touch the table first.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus.messages import ArmTarget, ForceSample, OperatorCommand, RobotState, mat3, vec
from services.control.decision.config import DecisionConfig
from services.control.decision.notices import Notice
from services.control.decision.supervisor import Inputs, Supervisor, TickResult
from services.world.workcell.mujoco_model import PhysicsParams
from services.world.workcell.scene import TABLE, Scene

TOOL_DOWN: NDArray[np.float64] = np.diag([-1.0, 1.0, -1.0])
"""The home orientation of the arm config: tool z axis pointing down."""
I3 = np.eye(3)
TICK_NS = 2_000_000
FINGER_M = PhysicsParams().finger_length_m
"""How far below the tool point the gripper's fingertips reach (m): they touch first."""
TABLE_SCENE = Scene(boxes=(TABLE,))
"""The cell of the contact tests: the table alone (cheap to step)."""


class CellSlave:
    """The PUMA 560 in a MuJoCo cell of `scene` (the table): a target's pose goes through
    the arm's IK to its joint servos, and each tick steps the physics by its length."""

    def __init__(self, p: Sequence[float], R: ArrayLike, scene: Scene = TABLE_SCENE) -> None:
        import pinocchio as pin

        from services.control.arm.model import load_model
        from services.world.workcell.engine import CellPhysics

        self._se3 = pin.SE3
        arm = load_model("puma560")
        self.kin = arm.kinematics()
        q = np.array(arm.home, dtype=float)
        self.R_goal = np.asarray(R, dtype=float)
        self.p_goal = np.asarray(p, dtype=float)
        goal = pin.SE3(self.R_goal, self.p_goal)
        for _ in range(100):  # from home to the start, a streamed IK step at a time
            sol = self.kin.solve(q, goal)
            q = np.asarray(sol.q, dtype=float)
            if sol.pos_err_m < 1e-7 and sol.rot_err_rad < 1e-7:
                break
        self.q = q
        self.ph = CellPhysics(arm, scene, q0=self.q)
        self.m = self.ph.params.tool_mass_kg
        self.com = np.asarray(self.ph.params.tool_com_m, dtype=float)
        self.grip = 0.0
        self._solved = (self.p_goal.tobytes(), self.R_goal.tobytes())

    def goto(self, p: NDArray[np.float64], R: NDArray[np.float64], grip: float | None) -> None:
        self.p_goal, self.R_goal = p, R
        if grip is not None:
            self.grip = grip

    def step(self, dt_ns: int) -> None:
        goal = (self.p_goal.tobytes(), self.R_goal.tobytes())
        if goal != self._solved:  # a new target: its joints (the servos hold the last)
            self.q = np.asarray(self.kin.solve(self.q, self._se3(self.R_goal, self.p_goal)).q)
            self._solved = goal
        self.ph.command(self.q, self.grip, dt_ns * 1e-9)
        self.ph.step(max(1, round(dt_ns * 1e-9 / self.ph.params.timestep_s)))

    def pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.ph.tool_pose()

    def wrench_t(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The wrist's wrench (tool frame) with the tool's weight removed, as the force
        service's gravity compensation does."""
        f, c = self.ph.wrench_t()
        _, R = self.ph.tool_pose()
        w = R.T @ np.array([0.0, 0.0, -self.m * 9.81])
        return f - w, c - np.cross(self.com, w)


@dataclass(frozen=True)
class Out:
    """A published ArmTarget and its motion since its engagement began (world frame)."""

    target: ArmTarget
    dp: tuple[float, ...]
    dR: tuple[float, ...]

    @property
    def active(self) -> bool:
        """False for a hold (the supervisor re-sends the target it last sent)."""
        return not self.target.hold

    def __getattr__(self, name: str) -> Any:
        return getattr(self.target, name)


class Rig:
    """The supervisor, an ideal slave, a force model; time advances TICK_NS per step."""

    def __init__(
        self,
        config: DecisionConfig | None = None,
        p: Sequence[float] = (0.6, 0.0, 0.6),
        R: ArrayLike = TOOL_DOWN,
        cell: bool = False,
        status: str = "ready",
    ) -> None:
        self.config = config or DecisionConfig()
        self.sup = Supervisor(self.config, seq_start=0, engage_start=0)
        self.now_ns = 10_000_000_000
        self.p = np.asarray(p, dtype=float)
        self.R = np.asarray(R, dtype=float)
        self.cell = CellSlave(self.p, self.R) if cell else None
        if self.cell is not None:
            self.p, self.R = self.cell.pose()
        self.status = status
        self.push_w = np.zeros(3)
        self.push_c = np.zeros(3)
        self.state_seq = 0
        self.force_seq = 0
        self.slave_engage: int | None = None
        self.slave_seq = -1
        self.grip: float | None = None
        self.seqs: dict[str, int] = {}
        self.outputs: list[Out] = []
        self.notices: list[Notice] = []
        self.results: list[TickResult] = []
        self.state_rx_ns = 0
        self.force_rx_ns = 0
        self._state: RobotState | None = None
        self._force: ForceSample | None = None

    # --- inputs ----------------------------------------------------------------------------
    def robot_state(self) -> RobotState:
        self.state_seq += 1
        return RobotState(
            seq=self.state_seq,
            t_ns=self.now_ns,
            status=self.status,  # type: ignore[arg-type]
            q=(0.0,) * 6,
            tool_p=vec(self.p),
            tool_R=vec(self.R),
            flange_p=vec(self.p),
            flange_R=vec(self.R),
            engage=self.slave_engage or 0,
            cmd_seq=max(self.slave_seq, 0),
            grip=self.grip,
        )

    def force_w(self) -> NDArray[np.float64]:
        """The force on the tool (N, world): the cell's contact (with `cell`) and the push."""
        if self.cell is None:
            return self.push_w.copy()
        return self.R @ self.cell.wrench_t()[0] + self.push_w

    def force_sample(self) -> ForceSample:
        self.force_seq += 1
        f_t = self.R.T @ self.force_w()
        c_t = self.push_c if self.cell is None else self.cell.wrench_t()[1] + self.push_c
        return ForceSample(seq=self.force_seq, t_ns=self.now_ns, f=vec(f_t), c=vec(c_t))

    def cmd(
        self,
        master: str = "m1",
        engage: int = 1,
        active: bool = True,
        dp: Sequence[float] = (0.0, 0.0, 0.0),
        dR: ArrayLike = I3,
        frame: str = "world",
        grip: float | None = None,
        seq: int | None = None,
    ) -> OperatorCommand:
        """An operator command with the next seq of `master` (or `seq`)."""
        if seq is None:
            seq = self.seqs.get(master, 0) + 1
        self.seqs[master] = max(self.seqs.get(master, 0), seq)
        return OperatorCommand(
            seq=seq,
            t_ns=self.now_ns,
            master=master,
            engage=engage,
            active=active,
            frame=frame,  # type: ignore[arg-type]
            dp=vec(dp),
            dR=vec(np.asarray(dR, dtype=float)),
            grip=grip,
        )

    # --- the loop --------------------------------------------------------------------------
    def step(
        self,
        commands: Sequence[OperatorCommand] = (),
        lost: Sequence[str] = (),
        state: bool = True,
        force: bool = True,
        dt_ns: int = TICK_NS,
        force_warming: bool = False,
    ) -> TickResult:
        """One tick, `dt_ns` after the last. `state`/`force` False: that stream delivers
        nothing this tick."""
        self.now_ns += dt_ns
        if self.cell is not None:
            self.cell.step(dt_ns)
            self.p, self.R = self.cell.pose()
        if state:
            self._state, self.state_rx_ns = self.robot_state(), self.now_ns
        if force:
            self._force, self.force_rx_ns = self.force_sample(), self.now_ns
        inp = Inputs(
            now_ns=self.now_ns,
            wall_ns=self.now_ns,
            state=self._state,
            state_rx_ns=self.state_rx_ns,
            force=self._force,
            force_rx_ns=self.force_rx_ns,
            commands=tuple(commands),
            lost=tuple(lost),
            force_warming=force_warming,
        )
        res = self.sup.tick(inp)
        self.results.append(res)
        self.notices.extend(res.notices)
        if res.command is not None:
            t = self.sup.target
            p0 = t.p0 if t.p0 is not None else np.zeros(3)
            tgt = res.command
            dp = vec(np.asarray(tgt.p) - p0)
            dR = vec(t.R0.T @ mat3(tgt.R))
            self.outputs.append(Out(tgt, dp, dR))
            self._slave(tgt)
        return res

    def run(self, n: int, make: object = None, **kw: bool) -> None:
        """`n` ticks; `make(i)` (if given) returns the commands of tick i."""
        for i in range(n):
            cmds = make(i) if callable(make) else ()
            self.step(cmds, **kw)

    def _slave(self, c: ArmTarget) -> None:
        """The target as the arm applies it (ideal tracking)."""
        if c.seq <= self.slave_seq or (
            self.slave_engage is not None and c.engage < self.slave_engage
        ):
            return
        self.slave_seq = c.seq
        self.slave_engage = c.engage
        if c.grip is not None:
            self.grip = c.grip
        if self.cell is not None:
            self.cell.goto(np.asarray(c.p, dtype=float), mat3(c.R), c.grip)
            return
        self.p = np.asarray(c.p, dtype=float)
        self.R = mat3(c.R)

    # --- views -----------------------------------------------------------------------------
    def kinds(self) -> list[str]:
        return [n.kind for n in self.notices]

    def notices_of(self, kind: str) -> list[Notice]:
        return [n for n in self.notices if n.kind == kind]

    def targets(self) -> list[NDArray[np.float64]]:
        """Every published target's tool point relative to its engagement's start (dp)."""
        return [np.asarray(c.dp) for c in self.outputs]

    def with_config(self, **changes: object) -> None:
        self.config = replace(self.config, **changes)  # type: ignore[arg-type]
        self.sup.set_config(self.config)
