"""The simulated joint controller of any arm model (the default `Arm`): the arm in MuJoCo.

`SimArm` streams its joint setpoints to the arm's position servos in the cell's physics and
reads the joints back from it (services/world/workcell/engine.py, docs/sim.md). The physics
is either

- **the workcell's** (`node` given: the arm service's): setpoints on `sim/arm/cmd`, joints
  from `sim/arm/state`, both published by the one process that owns the physics (the
  `workcell` service), which also moves the objects the arm touches;
- **the workcell's in this process** (`channel` given: `sim_physics = "embedded"`, the sim
  profile's): the same messages through an `ArmChannel`, in memory; or
- **its own** (no node: the arm alone, for the contract suite, the proxy's tests and a
  standalone `telerobot arm`): a `CellPhysics` of the arm in an empty cell, stepped at 1 kHz
  by its own thread (`threaded=True`) or by the caller through `step(dt_s)`
  (`threaded=False`, deterministic).

Calibration takes `calibration_s` (simulated time with its own physics, wall time with the
workcell's). Faults can be injected to exercise the proxy's error paths.

`JointFollower`, below, is the servo of the fake PUMA serial controller
(`fake_controller.py`), the real controller's counterpart; the simulation does not use it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from services.control.arm.arm_base import ArmBase, as_joint_vector
from services.control.arm.driver import ArmError, ArmStatus, Q
from services.control.arm.model import ArmModel, load_model
from services.world.workcell.channel import ArmChannel
from services.world.workcell.engine import CellPhysics
from services.world.workcell.messages import SIM_ARM_CMD, SIM_ARM_STATE, SimArmCmd
from services.world.workcell.scene import Scene

if TYPE_CHECKING:
    from services.bus.node import Node

log = logging.getLogger(__name__)

FaultKind = Literal["stall", "disconnect", "error"]

# Substep of the simulated servo (s): the 1 kHz of a joint servo board.
SERVO_DT_S = 1e-3
ARRIVED_RAD = 1e-9
"""The servo's exponential approach ends here: joints this close to the setpoint, and this
slow (rad/s), are at the setpoint and at rest (far below any encoder's resolution)."""
IDLE_WAIT_S = 1.0
PHYSICS_LOST_S = 2.0
"""No `sim/arm/state` for this long (the workcell publishes at ≥ 20 Hz): the link to the
physics is lost, the arm errs (a lost link stops motion). Not shorter: at 0.5 s, on a
loaded 2-core host (nice-19 busy loops, another demo running), the demo's arm came up in
`error` in 6 of 11 runs: the workcell, starved while eight services start, was silent that
long. Nothing moves while the physics is silent (it is what moves the joints), so the wait
costs no safety; a real arm's link is its driver's."""

JointFloats = tuple[float, ...]
"""The n joint values (rad or rad/s), joint 1 first."""


def _joints(value: Sequence[float] | Q, n: int) -> JointFloats:
    """n joint values as a tuple of floats (ValueError unless n)."""
    if isinstance(value, np.ndarray):
        return tuple(np.asarray(value, dtype=np.float64).reshape(n).tolist())
    out = tuple(map(float, value))
    if len(out) != n:
        raise ValueError(f"expected {n} joint values, got {len(out)}")
    return out


class JointFollower:
    """The joint servo of the simulated controller: rad, rad/s, s.

    Each step the commanded joint velocity is `kp·e` (e = setpoint − q), capped so that
    each joint can still stop at the setpoint at its maximum deceleration (`√(2·a·|e|)`),
    then limited to ±`vmax` and to a change of at most `amax·dt` from the previous velocity.
    The joints never leave [q_lo, q_hi]. Not thread safe: the owner locks.

    The state is plain floats: it steps at 1 kHz, and on a few joints a numpy call costs more
    than the arithmetic. `q`, `v` and `setpoint` give (fresh) arrays and take any n floats;
    `q_rad` is the joints as a tuple, for an owner that copies them every step.
    """

    def __init__(
        self,
        q: Sequence[float],
        vmax: Sequence[float],
        amax: Sequence[float],
        q_lo: Sequence[float],
        q_hi: Sequence[float],
        kp_1_s: float = 50.0,
    ) -> None:
        n = self.n = len(q)
        self._q: JointFloats = _joints(as_joint_vector(q, "q", n), n)
        self._rest: JointFloats = (0.0,) * n
        self._v: JointFloats = self._rest
        self._sp: JointFloats = self._q
        self.vmax = as_joint_vector(vmax, "vmax", n)
        self.amax = as_joint_vector(amax, "amax", n)
        self.q_lo = as_joint_vector(q_lo, "q_lo", n)
        self.q_hi = as_joint_vector(q_hi, "q_hi", n)
        self.kp_1_s = float(kp_1_s)
        # Per joint (vmax, amax, q_lo, q_hi), as floats for the step.
        self._limits = tuple(
            zip(
                self.vmax.tolist(),
                self.amax.tolist(),
                self.q_lo.tolist(),
                self.q_hi.tolist(),
                strict=True,
            )
        )

    @classmethod
    def of(
        cls,
        model: ArmModel,
        q: Sequence[float] | None = None,
        vmax: Sequence[float] | None = None,
        amax: Sequence[float] | None = None,
        q_lo: Sequence[float] | None = None,
        q_hi: Sequence[float] | None = None,
    ) -> JointFollower:
        """The servo of `model`'s arm: its home, speeds, accelerations and joint limits,
        each unless given."""
        return cls(
            model.home if q is None else q,
            [j.max_speed for j in model.joints] if vmax is None else vmax,
            [j.max_accel for j in model.joints] if amax is None else amax,
            model.q_lo if q_lo is None else q_lo,
            model.q_hi if q_hi is None else q_hi,
        )

    @property
    def q(self) -> Q:
        """The joints (rad)."""
        return np.array(self._q)

    @q.setter
    def q(self, value: Sequence[float] | Q) -> None:
        self._q = _joints(value, self.n)

    @property
    def q_rad(self) -> JointFloats:
        """The joints (rad) as a tuple: no copy needed, it never changes in place."""
        return self._q

    @property
    def v(self) -> Q:
        """The joint velocities (rad/s)."""
        return np.array(self._v)

    @v.setter
    def v(self, value: Sequence[float] | Q) -> None:
        self._v = _joints(value, self.n)

    @property
    def setpoint(self) -> Q:
        """The joint setpoint the servo tracks (rad)."""
        return np.array(self._sp)

    @setpoint.setter
    def setpoint(self, value: Sequence[float] | Q) -> None:
        self._sp = _joints(value, self.n)

    def stop_joint(self, j: int) -> None:
        """Zero the velocity of joint `j` (0 … n − 1): it is blocked."""
        v = list(self._v)
        v[j] = 0.0
        self._v = tuple(v)

    def hold(self) -> None:
        """Stop at maximum deceleration and stay there (a controlled stop)."""
        sp = []
        for q, v, (_, a, lo, hi) in zip(self._q, self._v, self._limits, strict=True):
            x = q + v * abs(v) / (2.0 * a)
            sp.append(lo if x < lo else hi if x > hi else x)
        self._sp = tuple(sp)

    def halt(self) -> None:
        """Stop dead (brakes): velocity zero, setpoint where the joints are."""
        self._v = self._rest
        self._sp = self._q

    def _desired(self) -> list[float]:
        """The velocity the servo asks for this step, before the acceleration limit (rad/s)."""
        kp = self.kp_1_s
        out = []
        for q, sp, (vmax, a, _, _) in zip(self._q, self._sp, self._limits, strict=True):
            e = sp - q
            ae = abs(e)
            # sign(e)·min(kp·|e|, √(2·a·|e|)), then within ±vmax
            v = min(kp * ae, math.sqrt(2.0 * a * ae))
            v = v if e > 0.0 else -v if e < 0.0 else 0.0
            out.append(-vmax if v < -vmax else vmax if v > vmax else v)
        return out

    def step(self, dt_s: float) -> None:
        """Advance by `dt_s` (≤ a few ms for fidelity)."""
        q_new: list[float] = []
        v_new: list[float] = []
        arrived = True
        for v_des, q, v, sp, (_, a, lo, hi) in zip(
            self._desired(), self._q, self._v, self._sp, self._limits, strict=True
        ):
            dv = a * dt_s
            v_lo, v_hi = v - dv, v + dv
            v = v_lo if v_des < v_lo else v_hi if v_des > v_hi else v_des
            q = q + v * dt_s
            if q < lo:
                q, v = lo, 0.0
            elif q > hi:
                q, v = hi, 0.0
            q_new.append(q)
            v_new.append(v)
            if arrived and not (abs(sp - q) <= ARRIVED_RAD and abs(v) <= ARRIVED_RAD):
                arrived = False
        if arrived:
            # At the setpoint, but never past a limit: a setpoint less than ARRIVED_RAD
            # outside one is where the joint stops (and then the setpoint, so it rests).
            rest = _joints(
                [
                    lo if x < lo else hi if x > hi else x
                    for x, (_, _, lo, hi) in zip(self._sp, self._limits, strict=True)
                ],
                self.n,
            )
            self._sp = rest
            self._q, self._v = rest, self._rest
        else:
            self._q, self._v = tuple(q_new), tuple(v_new)

    def at_rest(self) -> bool:
        """Exactly at the setpoint with zero velocity: stepping changes nothing."""
        return not any(self._v) and self._q == self._sp


class _Link:
    """Where the joints are: the setpoint goes in, the joints come back."""

    stepping = False

    def command(self, q: JointFloats, halt: bool = False) -> None:
        raise NotImplementedError

    def joints(self) -> tuple[JointFloats, JointFloats] | None:
        """(q, qd) now, or None before the physics has said."""
        raise NotImplementedError

    def step(self, dt_s: float) -> float:
        """Advance the physics (own physics only); the simulated time it advanced (s)."""
        return 0.0

    def lost(self) -> bool:
        """The physics said something once and then nothing for PHYSICS_LOST_S."""
        return False

    def close(self) -> None:
        pass


class _OwnPhysics(_Link):
    """The arm alone in an empty cell, in this process."""

    stepping = True

    def __init__(self, model: ArmModel, q0: Sequence[float]) -> None:
        self.physics = CellPhysics(model, Scene(), q0=q0)
        self._dt = float(self.physics.model.opt.timestep)
        self._q: JointFloats = tuple(q0)
        self._sp: JointFloats = tuple(q0)
        self._read()

    def _read(self) -> None:
        self._q = tuple(self.physics.q.tolist())
        self._qd: JointFloats = tuple(self.physics.qd.tolist())

    def command(self, q: JointFloats, halt: bool = False) -> None:
        if halt:
            self.physics.brake()
            self._read()
        else:
            self.physics.command(q)
        self._sp = q

    def joints(self) -> tuple[JointFloats, JointFloats]:
        return self._q, self._qd

    def step(self, dt_s: float) -> float:
        n = max(1, round(dt_s / self._dt))
        if self._q == self._sp and not any(self._qd):
            return n * self._dt  # at rest exactly at the setpoint, alone: nothing to do
        self.physics.step(n)
        self._read()
        return n * self._dt

    def at_rest(self, sp: JointFloats) -> bool:
        return max(map(abs, self._qd)) < ARRIVED_RAD and all(
            abs(a - b) < 1e-9 for a, b in zip(sp, self._q, strict=True)
        )


class _WorkcellPhysics(_Link):
    """The workcell's physics: over the bus (`sim/arm/cmd` out, `sim/arm/state` in), or in
    memory through an `ArmChannel` when the workcell runs in this process (the same
    messages, not encoded)."""

    def __init__(self, n: int, node: Node | None = None, channel: ArmChannel | None = None) -> None:
        self._n = n
        if channel is not None:
            self._put: Callable[[SimArmCmd], None] = channel.cmd.put
            self._state: Any = channel.state
        else:
            assert node is not None
            self._put = node.publisher(SIM_ARM_CMD).put
            self._state = node.latest(SIM_ARM_STATE)
        self._seq = 0
        self._rx_ns = 0

    def command(self, q: JointFloats, halt: bool = False) -> None:
        self._seq += 1
        self._put(SimArmCmd(seq=self._seq, t_ns=time.time_ns(), q=q, halt=halt))

    def joints(self) -> tuple[JointFloats, JointFloats] | None:
        got = self._state.read()
        if got is None or len(got[0].q) != self._n:
            return None
        st = got[0]
        self._rx_ns = got[1]
        return tuple(st.q), tuple(st.qd)

    def lost(self) -> bool:
        self.joints()
        return self._rx_ns > 0 and time.monotonic_ns() - self._rx_ns > PHYSICS_LOST_S * 1e9


class SimArm(ArmBase):
    """The simulated joint controller of an arm model (implements `Arm`; default: the PUMA
    560): its joints are the physics' (see the module docstring).

    `q_init` (rad): where the joints are at power-on in its own physics (default: the
    model's `home`; the workcell's physics keeps the arm where it is). A setpoint further
    than `max_setpoint_step_rad` from the measured joints, or outside the joint limits, is
    refused and puts the arm in `error` (the controller never jumps). A joint whose setpoint
    and actual position differ by more than `stall_threshold_rad` while it is stalled is an
    error. `stop()` holds at the point the joints reach at their maximum deceleration;
    `estop()` brakes them where they are.
    """

    def __init__(
        self,
        q_init: Sequence[float] | None = None,
        *,
        model: ArmModel | None = None,
        calibration_s: float = 0.5,
        threaded: bool = True,
        max_joint_speed_rad_s: Sequence[float] | None = None,
        max_joint_accel_rad_s2: Sequence[float] | None = None,
        max_setpoint_step_rad: float = 0.5,
        stall_threshold_rad: float = 0.02,
        q_lo: Sequence[float] | None = None,
        q_hi: Sequence[float] | None = None,
        node: Node | None = None,
        channel: ArmChannel | None = None,
    ) -> None:
        if calibration_s < 0.0:
            raise ValueError("calibration_s must be ≥ 0")
        arm = model if model is not None else load_model()
        self.model = arm
        n = self.n = arm.n
        self._lock = threading.RLock()
        self._lo: JointFloats = tuple(
            as_joint_vector(arm.q_lo if q_lo is None else q_lo, "q_lo", n)
        )
        self._hi: JointFloats = tuple(
            as_joint_vector(arm.q_hi if q_hi is None else q_hi, "q_hi", n)
        )
        amax = (
            [j.max_accel for j in arm.joints]
            if max_joint_accel_rad_s2 is None
            else max_joint_accel_rad_s2
        )
        self._amax: JointFloats = tuple(as_joint_vector(amax, "amax", n).tolist())
        q0 = _joints(as_joint_vector(arm.home if q_init is None else q_init, "q", n), n)
        if any(q < lo or q > hi for q, lo, hi in zip(q0, self._lo, self._hi, strict=True)):
            raise ValueError("q_init is outside the joint limits")
        self._link: _Link = (
            _OwnPhysics(arm, q0)
            if node is None and channel is None
            else _WorkcellPhysics(n, node, channel)
        )
        self._q_read: JointFloats = q0
        self._sp: JointFloats = q0
        self._calibration_s = float(calibration_s)
        self._cal_left_s = 0.0
        self._calibrated = False
        self._status: ArmStatus = "disconnected"
        self._last_error: str | None = None
        self._link_up = False
        self._stalled: tuple[int, float] | None = None
        self._max_step_rad = float(max_setpoint_step_rad)
        self._stall_threshold_rad = float(stall_threshold_rad)
        self._t_s = 0.0
        self._threaded = threaded
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._kick = threading.Event()
        self.setpoints_accepted = 0
        self.setpoints_ignored = 0

    # --- the physics --------------------------------------------------------------------

    def _joints_now(self) -> tuple[JointFloats, JointFloats] | None:
        return self._link.joints()

    def _q_now(self) -> JointFloats:
        j = self._link.joints()
        return j[0] if j is not None else self._q_read

    def _send(self, sp: JointFloats, halt: bool = False) -> None:
        """The setpoint to the servos (a stalled joint stays where it stalled)."""
        self._sp = sp
        if self._stalled is not None:
            j, qj = self._stalled
            sp = tuple(qj if i == j else x for i, x in enumerate(sp))
        self._link.command(sp, halt)

    def _hold(self) -> None:
        """The setpoint where the joints stop at their maximum deceleration."""
        now = self._link.joints()
        if now is None:
            return
        q, qd = now
        sp = []
        for x, v, a, lo, hi in zip(q, qd, self._amax, self._lo, self._hi, strict=True):
            y = x + v * abs(v) / (2.0 * a)
            sp.append(lo if y < lo else hi if y > hi else y)
        self._send(tuple(sp))

    # --- Arm ---------------------------------------------------------------------------

    def connect(self) -> None:
        with self._lock:
            # A simulated fault is one event: re-connecting is the recovery from it.
            self._stalled = None
            self._link_up = True
            self._hold()
            self._status = "connected"
        if self._threaded and self._thread is None:
            self._running.set()
            self._thread = threading.Thread(target=self._run, name="sim-arm", daemon=True)
            self._thread.start()

    def initialize(self) -> None:
        with self._lock:
            self._check_can_initialize()
            self._status = "initializing"
            self._cal_left_s = self._calibration_s
            self._hold()
            if self._calibration_s == 0.0:
                self._finish_calibration()
        self._kick.set()

    def read_joints(self) -> Q:
        with self._lock:
            if not self._calibrated:
                raise ArmError("joint angles unknown: the arm was never calibrated")
            if self._link_up:
                self._q_read = self._q_now()
                self._check_stall()
            return np.array(self._q_read)

    def command(self, q_setpoint: Q) -> None:
        with self._lock:
            accepted = self._accept_setpoint(q_setpoint)
            if accepted is None:
                return
            sp = _joints(accepted, self.n)
            for j, (x, lo, hi) in enumerate(zip(sp, self._lo, self._hi, strict=True)):
                if x < lo or x > hi:
                    self._fail_locked(f"setpoint q{j + 1}={x:.4f} rad outside the joint limits")
                    return
            q = self._q_now()
            jump = [abs(x - y) for x, y in zip(sp, q, strict=True)]
            worst = max(jump)
            if worst > self._max_step_rad:
                j = jump.index(worst)
                self._fail_locked(f"setpoint jump of {worst:.3f} rad on q{j + 1} refused")
                return
            self._send(sp)
            self.setpoints_accepted += 1
        self._kick.set()

    def stop(self) -> None:
        with self._lock:
            self._hold()
        self._kick.set()

    def estop(self) -> None:
        with self._lock:
            self._send(self._q_now(), halt=True)
            self._status = "error"
            self._last_error = "emergency stop"
        self._kick.set()

    def close(self) -> None:
        with self._lock:
            if self._link_up:
                self._hold()
            self._link_up = False
            self._status = "disconnected"
        thread, self._thread = self._thread, None
        if thread is not None:
            self._running.clear()
            self._kick.set()
            thread.join(timeout=1.0)

    # --- simulation --------------------------------------------------------------------

    @property
    def t_s(self) -> float:
        """Simulated time since construction (s)."""
        with self._lock:
            return self._t_s

    @property
    def q_true(self) -> Q:
        """The actual joint angles (rad), whatever the link: for tests."""
        with self._lock:
            return np.array(self._q_now())

    @property
    def qd_true(self) -> Q:
        """The actual joint velocities (rad/s): for tests."""
        with self._lock:
            j = self._link.joints()
            return np.zeros(self.n) if j is None else np.array(j[1])

    @property
    def physics(self) -> CellPhysics | None:
        """Its own physics (None: the workcell's)."""
        return self._link.physics if isinstance(self._link, _OwnPhysics) else None

    def inject_fault(self, kind: FaultKind, joint: int = 2) -> None:
        """Inject a fault; `connect()` clears it.

        `error`: an amplifier fault, `error` at once. `disconnect`: the link drops, `error`
        at once, the readback freezes. `stall`: joint `joint` (1 … n) stops moving; the arm
        goes to `error` as soon as the servo asks it to move.
        """
        with self._lock:
            if kind == "error":
                self._fail_locked("amplifier fault (injected)")
            elif kind == "disconnect":
                self._link_up = False
                self._fail_locked("link lost (injected)")
            elif kind == "stall":
                if not 1 <= joint <= self.n:
                    raise ValueError(f"joint must be 1 … {self.n}")
                self._stalled = (joint - 1, self._q_now()[joint - 1])
                self._send(self._sp)
            else:
                raise ValueError(f"unknown fault {kind!r}")
        self._kick.set()

    def step(self, dt_s: float) -> None:
        """Advance the simulation by `dt_s` (s): its own physics in 1 ms steps."""
        if not dt_s > 0.0:
            raise ValueError("dt_s must be > 0")
        with self._lock:
            h = self._link.step(dt_s) if self._link.stepping else dt_s
            self._t_s += h
            if self._status == "initializing":
                self._cal_left_s -= h
                if self._cal_left_s <= 0.0 and self._link.joints() is not None:
                    self._finish_calibration()
            self._check_stall()

    def _check_stall(self) -> None:
        if self._status == "error":
            return
        if self._link_up and self._link.lost():
            self._fail_locked("the workcell's physics stopped answering (no sim/arm/state)")
            self._link_up = False  # the readback freezes where it was last heard
            return
        if self._stalled is None:
            return
        j = self._stalled[0]
        if abs(self._sp[j] - self._q_now()[j]) > self._stall_threshold_rad:
            self._fail_locked(
                f"joint {j + 1} stalled: following error above {self._stall_threshold_rad} rad"
            )

    def _finish_calibration(self) -> None:
        self._calibrated = True
        self._status = "ready"
        self._q_read = self._q_now()

    def _fail_locked(self, why: str) -> None:
        """Error: the servos hold where the joints really are and take no setpoint."""
        if self._link_up:
            self._hold()
        if self._status != "error":
            self._last_error = why
            log.error("arm error: %s", why)
        self._status = "error"

    def _resting(self) -> bool:
        with self._lock:
            link = self._link
            return (
                self._status != "initializing"
                and isinstance(link, _OwnPhysics)
                and link.at_rest(self._sp if self._stalled is None else link.joints()[0])
            )

    def _run(self) -> None:
        next_t = time.monotonic()
        period = SERVO_DT_S if self._link.stepping else 0.01
        while self._running.is_set():
            self.step(period)
            if self._resting():
                # Nothing moves: sleep until a setpoint, fault or calibration wakes us.
                slept = time.monotonic()
                self._kick.wait(IDLE_WAIT_S)
                self._kick.clear()
                now = time.monotonic()
                with self._lock:
                    self._t_s += now - slept
                next_t = now
                continue
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            elif delay < -0.05:
                # Far behind (a paused process): resume from now rather than fast-forward.
                next_t = time.monotonic()
