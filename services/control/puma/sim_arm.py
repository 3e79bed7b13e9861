"""A simulated PUMA 560 joint controller: the default `Arm`.

The simulated servo (`JointFollower`) tracks the streamed setpoint like a position loop
with per-joint speed and acceleration limits; it is stepped at 1 kHz, either by its own
thread (`SimArm()`, for the service) or by the caller through `step(dt_s)` (`threaded=False`,
deterministic, for tests). Calibration takes `calibration_s` of simulated time. Faults can
be injected to exercise the proxy's error paths.

The same follower also moves the fake serial controller (`fake_controller.py`), so both
backends behave alike under the contract test.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Literal

import numpy as np

from services.control.puma.arm import (
    ARM_MAX_JOINT_ACCEL_RAD_S2,
    ARM_MAX_JOINT_SPEED_RAD_S,
    Q_HI_RAD,
    Q_LO_RAD,
    QN_RAD,
    ArmError,
    ArmStatus,
    Q,
)
from services.control.puma.arm_base import ArmBase, as_joint_vector

FaultKind = Literal["stall", "disconnect", "error"]

# Substep of the simulated servo (s): the 1 kHz of a PUMA joint servo board.
SERVO_DT_S = 1e-3
ARRIVED_RAD = 1e-9
"""The servo's exponential approach ends here: joints this close to the setpoint, and this
slow (rad/s), are at the setpoint and at rest (far below any encoder's resolution)."""
IDLE_WAIT_S = 1.0


class JointFollower:
    """The joint servo of the simulated controller: rad, rad/s, s.

    Each step the commanded joint velocity is `kp·e` (e = setpoint − q), capped so that
    each joint can still stop at the setpoint at its maximum deceleration (`√(2·a·|e|)`),
    then limited to ±`vmax` and to a change of at most `amax·dt` from the previous velocity.
    The joints never leave [q_lo, q_hi]. Not thread safe: the owner locks.
    """

    def __init__(
        self,
        q: Sequence[float],
        vmax: Sequence[float],
        amax: Sequence[float],
        q_lo: Sequence[float] = Q_LO_RAD,
        q_hi: Sequence[float] = Q_HI_RAD,
        kp_1_s: float = 50.0,
    ) -> None:
        self.q = as_joint_vector(q).copy()
        self.v = np.zeros(6)
        self.setpoint = self.q.copy()
        self.vmax = as_joint_vector(vmax, "vmax")
        self.amax = as_joint_vector(amax, "amax")
        self.q_lo = as_joint_vector(q_lo, "q_lo")
        self.q_hi = as_joint_vector(q_hi, "q_hi")
        self.kp_1_s = float(kp_1_s)

    def hold(self) -> None:
        """Stop at maximum deceleration and stay there (a controlled stop)."""
        stop_dist = self.v * np.abs(self.v) / (2.0 * self.amax)
        self.setpoint = np.clip(self.q + stop_dist, self.q_lo, self.q_hi)

    def halt(self) -> None:
        """Stop dead (brakes): velocity zero, setpoint where the joints are."""
        self.v = np.zeros(6)
        self.setpoint = self.q.copy()

    def desired_velocity(self) -> Q:
        """The velocity the servo asks for this step, before the acceleration limit (rad/s)."""
        e = self.setpoint - self.q
        v_fb = np.sign(e) * np.minimum(
            self.kp_1_s * np.abs(e), np.sqrt(2.0 * self.amax * np.abs(e))
        )
        return np.clip(v_fb, -self.vmax, self.vmax)

    def step(self, dt_s: float) -> None:
        """Advance by `dt_s` (≤ a few ms for fidelity)."""
        v_des = self.desired_velocity()
        dv = self.amax * dt_s
        self.v = np.clip(v_des, self.v - dv, self.v + dv)
        q_next = self.q + self.v * dt_s
        at_stop = (q_next < self.q_lo) | (q_next > self.q_hi)
        self.q = np.clip(q_next, self.q_lo, self.q_hi)
        self.v[at_stop] = 0.0
        if (
            np.abs(self.setpoint - self.q).max() <= ARRIVED_RAD
            and np.abs(self.v).max() <= ARRIVED_RAD
        ):
            self.q = self.setpoint.copy()
            self.v[:] = 0.0

    def at_rest(self) -> bool:
        """Exactly at the setpoint with zero velocity: stepping changes nothing."""
        return not self.v.any() and np.array_equal(self.q, self.setpoint)

    def is_settled(self, tol_rad: float = 1e-4) -> bool:
        return bool(np.all(np.abs(self.setpoint - self.q) <= tol_rad) and np.all(self.v == 0.0))


class SimArm(ArmBase):
    """A simulated PUMA 560 controller (implements `Arm`).

    `q_init` (rad) is where the joints are at power-on. `calibration_s` is the simulated
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
        q_init: Sequence[float] = QN_RAD,
        *,
        calibration_s: float = 0.5,
        threaded: bool = True,
        max_joint_speed_rad_s: Sequence[float] = ARM_MAX_JOINT_SPEED_RAD_S,
        max_joint_accel_rad_s2: Sequence[float] = ARM_MAX_JOINT_ACCEL_RAD_S2,
        max_setpoint_step_rad: float = 0.5,
        stall_threshold_rad: float = 0.02,
        q_lo: Sequence[float] = Q_LO_RAD,
        q_hi: Sequence[float] = Q_HI_RAD,
    ) -> None:
        if calibration_s < 0.0:
            raise ValueError("calibration_s must be ≥ 0")
        self._lock = threading.RLock()
        self._servo = JointFollower(
            q_init, max_joint_speed_rad_s, max_joint_accel_rad_s2, q_lo, q_hi
        )
        if np.any(self._servo.q < self._servo.q_lo) or np.any(self._servo.q > self._servo.q_hi):
            raise ValueError("q_init is outside the joint limits")
        # The actual joints differ from the servo's model only when a joint stalls.
        self._q_actual = self._servo.q.copy()
        self._q_read = self._servo.q.copy()
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
                self._q_read = self._q_actual.copy()
            return self._q_read.copy()

    def command(self, q_setpoint: Q) -> None:
        with self._lock:
            sp = self._accept_setpoint(q_setpoint)
            if sp is None:
                return
            outside = np.flatnonzero((sp < self._servo.q_lo) | (sp > self._servo.q_hi))
            if outside.size:
                j = int(outside[0])
                self._fail_locked(f"setpoint q{j + 1}={sp[j]:.4f} rad outside the joint limits")
                return
            jump = np.abs(sp - self._q_actual)
            if np.any(jump > self._max_step_rad):
                j = int(np.argmax(jump))
                self._fail_locked(f"setpoint jump of {jump[j]:.3f} rad on q{j + 1} refused")
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
            self._q_actual = self._servo.q.copy()
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
            return self._q_actual.copy()

    @property
    def qd_true(self) -> Q:
        """The actual joint velocities (rad/s): for tests."""
        with self._lock:
            v = self._servo.v.copy()
            if self._stalled_joint is not None:
                v[self._stalled_joint] = 0.0
            return v

    def inject_fault(self, kind: FaultKind, joint: int = 2) -> None:
        """Inject a fault; `connect()` clears it.

        `error`: an amplifier fault, `error` at once. `disconnect`: the link drops, `error`
        at once, the readback freezes. `stall`: joint `joint` (1…6) stops moving; the arm
        goes to `error` as soon as the servo asks it to move.
        """
        with self._lock:
            if kind == "error":
                self._fail_locked("amplifier fault (injected)")
            elif kind == "disconnect":
                self._link_up = False
                self._fail_locked("link lost (injected)")
            elif kind == "stall":
                if not 1 <= joint <= 6:
                    raise ValueError("joint must be 1…6")
                self._stalled_joint = joint - 1
            else:
                raise ValueError(f"unknown fault {kind!r}")
        self._kick.set()

    def step(self, dt_s: float) -> None:
        """Advance the simulation by `dt_s` (s), in servo substeps of at most 1 ms."""
        if not dt_s > 0.0:
            raise ValueError("dt_s must be > 0")
        with self._lock:
            n = max(1, int(np.ceil(dt_s / SERVO_DT_S - 1e-9)))
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
        if j is None:
            self._q_actual = self._servo.q.copy()
            return
        q = self._servo.q.copy()
        q[j] = self._q_actual[j]
        self._q_actual = q
        if abs(self._servo.q[j] - self._q_actual[j]) > self._stall_threshold_rad:
            self._fail_locked(
                f"joint {j + 1} stalled: following error above {self._stall_threshold_rad} rad"
            )

    def _finish_calibration(self) -> None:
        self._calibrated = True
        self._status = "ready"
        self._q_read = self._q_actual.copy()

    def _fail_locked(self, why: str) -> None:
        """Error: the servo holds where the joints really are and takes no setpoint."""
        self._servo.q = self._q_actual.copy()
        if self._stalled_joint is not None:
            self._servo.v[self._stalled_joint] = 0.0
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
