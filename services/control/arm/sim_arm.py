"""A simulated joint controller for any arm model: the default `Arm`.

The simulated servo (`JointFollower`) tracks the streamed setpoint like a position loop
with the model's per-joint limits (positions, speeds, accelerations); it is stepped at 1 kHz,
either by its own thread (`SimArm()`, for the service) or by the caller through `step(dt_s)`
(`threaded=False`, deterministic, for tests). Calibration takes `calibration_s` of simulated
time. Faults can be injected to exercise the proxy's error paths.

The same follower also moves the fake serial controller (`fake_controller.py`), so both
backends behave alike under the contract test.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from typing import Literal

import numpy as np

from services.control.arm.arm_base import ArmBase, as_joint_vector
from services.control.arm.driver import ArmError, ArmStatus, Q
from services.control.arm.model import ArmModel, load_model

FaultKind = Literal["stall", "disconnect", "error"]

# Substep of the simulated servo (s): the 1 kHz of a joint servo board.
SERVO_DT_S = 1e-3
ARRIVED_RAD = 1e-9
"""The servo's exponential approach ends here: joints this close to the setpoint, and this
slow (rad/s), are at the setpoint and at rest (far below any encoder's resolution)."""
IDLE_WAIT_S = 1.0

Joints = tuple[float, ...]
"""The n joint values (rad or rad/s), joint 1 first."""


def _joints(value: Sequence[float] | Q, n: int) -> Joints:
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
        self._q: Joints = _joints(as_joint_vector(q, "q", n), n)
        self._rest: Joints = (0.0,) * n
        self._v: Joints = self._rest
        self._sp: Joints = self._q
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
    def q_rad(self) -> Joints:
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


class SimArm(ArmBase):
    """A simulated joint controller of an arm model (implements `Arm`; default: the PUMA 560).

    The servo's limits are the model's capabilities (the URDF's joint ranges and velocities,
    the model file's accelerations) unless given. `q_init` (rad) is where the joints are at
    power-on (default: the model's `home`). `calibration_s` is the simulated
    duration of `initialize()`. `threaded=True` steps the servo at 1 kHz of wall time in a
    thread started by `connect()` while anything moves, and sleeps while the joints rest at
    the setpoint (a new setpoint, a fault or a calibration wakes it); `threaded=False`
    leaves stepping to `step(dt_s)`.
    A setpoint further than `max_setpoint_step_rad` from the measured joints, or outside
    the joint limits, is refused and puts the arm in `error` (the controller never jumps).
    A joint whose servo position and actual position differ by more than
    `stall_threshold_rad` is stalled: `error`.
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
    ) -> None:
        if calibration_s < 0.0:
            raise ValueError("calibration_s must be ≥ 0")
        arm = model if model is not None else load_model()
        self.model = arm
        self.n = arm.n
        self._lock = threading.RLock()
        self._servo = JointFollower.of(
            arm, q_init, max_joint_speed_rad_s, max_joint_accel_rad_s2, q_lo, q_hi
        )
        self._lo: Joints = tuple(self._servo.q_lo.tolist())
        self._hi: Joints = tuple(self._servo.q_hi.tolist())
        q0 = self._servo.q_rad
        if any(q < lo or q > hi for q, lo, hi in zip(q0, self._lo, self._hi, strict=True)):
            raise ValueError("q_init is outside the joint limits")
        # The actual joints differ from the servo's model only when a joint stalls. Joint
        # tuples never change in place: they are shared, not copied.
        self._q_actual: Joints = q0
        self._q_read: Joints = q0
        self._calibration_s = float(calibration_s)
        self._cal_left_s = 0.0
        self._calibrated = False
        self._status: ArmStatus = "disconnected"
        self._last_error: str | None = None
        self._link_up = False
        self._stalled_joint: int | None = None
        self._max_step_rad = float(max_setpoint_step_rad)
        self._stall_threshold_rad = float(stall_threshold_rad)
        self._t_s = 0.0
        self._threaded = threaded
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._kick = threading.Event()
        self.setpoints_accepted = 0
        self.setpoints_ignored = 0

    # --- Arm ---------------------------------------------------------------------------

    def connect(self) -> None:
        with self._lock:
            # A simulated fault is one event: re-connecting is the recovery from it.
            self._stalled_joint = None
            self._link_up = True
            self._servo.hold()
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
            self._servo.hold()
            if self._calibration_s == 0.0:
                self._finish_calibration()
        self._kick.set()

    def read_joints(self) -> Q:
        with self._lock:
            if not self._calibrated:
                raise ArmError("joint angles unknown: the arm was never calibrated")
            if self._link_up:
                self._q_read = self._q_actual
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
            jump = [abs(x - q) for x, q in zip(sp, self._q_actual, strict=True)]
            worst = max(jump)
            if worst > self._max_step_rad:
                j = jump.index(worst)
                self._fail_locked(f"setpoint jump of {worst:.3f} rad on q{j + 1} refused")
                return
            self._servo.setpoint = sp
            self.setpoints_accepted += 1
        self._kick.set()

    def stop(self) -> None:
        with self._lock:
            self._servo.hold()
        self._kick.set()

    def estop(self) -> None:
        with self._lock:
            self._servo.halt()
            self._q_actual = self._servo.q_rad
            self._status = "error"
            self._last_error = "emergency stop"
        self._kick.set()

    def close(self) -> None:
        with self._lock:
            self._servo.hold()
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
            return np.array(self._q_actual)

    @property
    def qd_true(self) -> Q:
        """The actual joint velocities (rad/s): for tests."""
        with self._lock:
            v = self._servo.v
            if self._stalled_joint is not None:
                v[self._stalled_joint] = 0.0
            return v

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
                self._stalled_joint = joint - 1
            else:
                raise ValueError(f"unknown fault {kind!r}")
        self._kick.set()

    def step(self, dt_s: float) -> None:
        """Advance the simulation by `dt_s` (s), in servo substeps of at most 1 ms."""
        if not dt_s > 0.0:
            raise ValueError("dt_s must be > 0")
        with self._lock:
            n = max(1, math.ceil(dt_s / SERVO_DT_S - 1e-9))
            h = dt_s / n
            for _ in range(n):
                self._substep(h)

    def _substep(self, h: float) -> None:
        self._t_s += h
        if self._status == "initializing":
            self._cal_left_s -= h
            if self._cal_left_s <= 0.0:
                self._finish_calibration()
        self._servo.step(h)
        j = self._stalled_joint
        q_servo = self._servo.q_rad
        if j is None:
            self._q_actual = q_servo
            return
        q = list(q_servo)
        q[j] = self._q_actual[j]
        self._q_actual = tuple(q)
        if abs(q_servo[j] - q[j]) > self._stall_threshold_rad:
            self._fail_locked(
                f"joint {j + 1} stalled: following error above {self._stall_threshold_rad} rad"
            )

    def _finish_calibration(self) -> None:
        self._calibrated = True
        self._status = "ready"
        self._q_read = self._q_actual

    def _fail_locked(self, why: str) -> None:
        """Error: the servo holds where the joints really are and takes no setpoint."""
        self._servo.q = self._q_actual
        if self._stalled_joint is not None:
            self._servo.stop_joint(self._stalled_joint)
        self._servo.hold()
        if self._status != "error":
            self._last_error = why
        self._status = "error"

    def _resting(self) -> bool:
        with self._lock:
            return self._status != "initializing" and self._servo.at_rest()

    def _run(self) -> None:
        next_t = time.monotonic()
        while self._running.is_set():
            self.step(SERVO_DT_S)
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
            next_t += SERVO_DT_S
            delay = next_t - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            elif delay < -0.05:
                # Far behind (a paused process): resume from now rather than fast-forward.
                next_t = time.monotonic()
