"""`FrankaArm`: a Franka FR3 (or Panda) through libfranka — the `libfranka` arm driver.

The arm service streams joint setpoints (its servo's, within the model's limits) to
`command`; they go into a block of shared memory, and the real-time process (rt.py, started
by `connect`) runs libfranka's 1 kHz loop: a Ruckig jerk-limited trajectory toward the
newest setpoint, so the robot's discontinuity reflexes never fire from our side. The same
block carries the robot's state back: `read_joints` is the robot's own measured `q`.

Status (driver.py): `connect` starts the process, connects (`franka::Robot`; the real-time
check off only where the kernel has no real-time policy, said at start-up) and checks the
robot's `O_T_EE` against our FK of its measured joints (beyond 1 mm the model or the flange
is wrong and `connect` refuses); `initialize` runs `automaticErrorRecovery`, sets the
collision thresholds and impedances of the model's franka.toml and starts the loop — `ready`
once the robot takes our commands. A reflex or a refused command (`ControlException`), a lost
link (no state for `watchdog_s`, or libfranka's `NetworkException`) or the process dying is
`error`, with `last_error` naming the reflex; after it, `connect` starts a fresh process.

The Franka Hand, when the model has a gripper, is a second process (gripper moves block in
libfranka): `grip(g)` sends the newest grip, 0 open … 1 closed, as a width.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from typing import IO, Any

import numpy as np
import pinocchio as pin

from services.control.arm.arm_base import ArmBase
from services.control.arm.driver import ArmError, ArmStatus, Q
from services.control.arm.franka.errors import fault_message
from services.control.arm.franka.frankysim import close_pipes
from services.control.arm.franka.params import FrankaParams, load_params
from services.control.arm.franka.shm import (
    S_CONTROLLING,
    S_T_ROBOT,
    S_WALL_NS,
    Shared,
    Snapshot,
    state_path,
)
from services.control.arm.model import ArmModel

log = logging.getLogger("telerobot.arm.franka")

FK_TOLERANCE_M = 1e-3
FK_TOLERANCE_RAD = 0.01
GRIP_STEP_M = 0.002
"""A new grip moves the hand only when it changes the width by more than this."""
EXIT_WAIT_S = 6.0


class _Child:
    """A real-time process and its request/reply pipes."""

    def __init__(self, args: list[str], on_event: Any, name: str) -> None:
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.control.arm.franka.rt", *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=None,
            env=env,
            text=True,
            bufsize=1,
        )
        self._on_event = on_event
        self._lock = threading.Lock()
        self._next = 1
        self._waiting: dict[int, tuple[threading.Event, list[dict[str, Any]]]] = {}
        self._reader = threading.Thread(target=self._read, name=f"franka-{name}", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        out: IO[str] = self.proc.stdout  # type: ignore[assignment]
        while True:
            try:
                line = out.readline()
            except (OSError, ValueError):
                break
            if not line:
                break
            try:
                msg = json.loads(line)
            except ValueError:
                continue
            rid = msg.get("id")
            with self._lock:
                waiter = self._waiting.pop(rid, None) if rid is not None else None
            if waiter is not None:
                waiter[1].append(msg)
                waiter[0].set()
            if "event" in msg:
                self._on_event(msg)
        with self._lock:
            waiting, self._waiting = self._waiting, {}
        for ev, box in waiting.values():
            box.append({"ok": False, "kind": "link", "error": "the real-time process ended"})
            ev.set()

    def send(self, op: str, **args: Any) -> tuple[threading.Event, list[dict[str, Any]]]:
        ev: threading.Event = threading.Event()
        box: list[dict[str, Any]] = []
        with self._lock:
            rid = self._next
            self._next += 1
            self._waiting[rid] = (ev, box)
        try:
            stdin: IO[str] = self.proc.stdin  # type: ignore[assignment]
            stdin.write(json.dumps({"id": rid, "op": op, **args}) + "\n")
            stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            with self._lock:
                self._waiting.pop(rid, None)
            box.append({"ok": False, "kind": "link", "error": "the real-time process is gone"})
            ev.set()
        return ev, box

    def call(self, op: str, timeout_s: float, **args: Any) -> dict[str, Any]:
        ev, box = self.send(op, **args)
        if not ev.wait(timeout_s):
            raise ArmError(f"libfranka: no answer to {op} within {timeout_s:g} s")
        reply = box[0]
        if not reply.get("ok"):
            raise ArmError(f"libfranka: {op} failed: {reply.get('error', '?')}")
        return reply

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def close(self, timeout_s: float) -> None:
        if self.alive:
            self.send("exit")
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(2.0)
        self._reader.join(timeout=2.0)
        close_pipes(self.proc)


class FrankaArm(ArmBase):
    """A Franka arm through libfranka (implements `Arm`); see the module docstring.

    `robot_ip`: the robot's FCI address (Desk's "shop floor" network, or franky-sim's loopback
    address). `realtime`: `auto` (libfranka's real-time check on where the kernel allows it,
    else off and said), `enforce`, `ignore`. `watchdog_s`: no robot state for this long is a
    lost link. A setpoint outside the joint limits or further than `max_setpoint_step_rad` from
    the measured joints is refused and puts the arm in `error`.
    """

    def __init__(
        self,
        robot_ip: str,
        *,
        model: ArmModel,
        params: FrankaParams | None = None,
        realtime: str = "auto",
        watchdog_s: float = 0.5,
        connect_timeout_s: float = 15.0,
        max_setpoint_step_rad: float = 0.5,
        gripper: bool = True,
    ) -> None:
        if model.n != 7:
            raise ArmError(f"libfranka drives 7-joint arms, {model.name} has {model.n}")
        self.model = model
        self.n = 7
        self.params = params if params is not None else load_params(model)
        self.robot_ip = robot_ip
        self.realtime_mode = realtime
        self.watchdog_s = float(watchdog_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self._max_step_rad = float(max_setpoint_step_rad)
        self._want_gripper = gripper and bool(model.grip_joints)
        self._lock = threading.RLock()
        self._status: ArmStatus = "disconnected"
        self._last_error: str | None = None
        self.setpoints_ignored = 0
        self.setpoints_accepted = 0
        self._lo = model.q_lo
        self._hi = model.q_hi
        self.shm = Shared.create(state_path(robot_ip))
        self._rt: _Child | None = None
        self._hand: _Child | None = None
        self._hand_width: float | None = None
        self._hand_max = self.params.gripper_max_width_m
        self._have_state = False
        self._calibrated = False
        self._init_thread: threading.Thread | None = None
        self._t_robot_last: float | None = None
        self._epoch = 0
        self.realtime = ""
        """How libfranka's real-time check went at the last connect, for people."""
        self.notes: list[str] = []
        """What `connect` found worth saying (the real-time check, the EE frame, the hand)."""
        self.faults: list[dict[str, Any]] = []
        """The faults the robot reported, oldest first (the last 32)."""
        kin = model.kinematics()
        self._pin = kin.model
        self._pin_data = kin.model.createData()
        fid = self._pin.getFrameId(model.joint_names[0])
        self._base_fid = self._pin.frames[fid].parentFrame
        self._flange_fid = self._pin.getFrameId(model.flange_frame)
        self._eMt = pin.SE3(np.array(model.tool_R).reshape(3, 3), np.array(model.tool_p))

    # --- Arm --------------------------------------------------------------------------
    @property
    def status(self) -> ArmStatus:
        with self._lock:
            st = self._status
            if st in ("connected", "initializing", "ready"):
                self._watch_locked()
            return self._status

    def connect(self) -> None:
        with self._lock:
            self._epoch += 1
            self._stop_children()
            self._status = "disconnected"
            self._have_state = False
            if not self.shm.path.exists():  # released by `close`: a fresh block
                old, self.shm = self.shm, Shared.create(self.shm.path)
                self.shm.a[:] = old.a
                old.close(unlink=False)
        rt = _Child(["--shm", str(self.shm.path)], self._on_event, "rt")
        try:
            reply = rt.call(
                "connect", self.connect_timeout_s, ip=self.robot_ip, realtime=self.realtime_mode
            )
        except ArmError as e:
            rt.close(1.0)
            with self._lock:
                self._fail_locked(f"connect to {self.robot_ip} failed: {_after(e)}")
            raise ArmError(f"cannot reach the robot at {self.robot_ip}: {_after(e)}") from None
        notes = [f"libfranka real-time check {reply.get('realtime', '?')}"]
        problem = self._cross_check(reply)
        if problem is not None:
            rt.close(2.0)
            with self._lock:
                self._fail_locked(problem)
            raise ArmError(problem)
        notes += self._ee_note(reply)
        hand = None
        if self._want_gripper:
            hand = _Child(["--gripper"], self._on_event, "hand")
            try:
                r = hand.call(
                    "connect",
                    self.connect_timeout_s,
                    ip=self.robot_ip,
                    speed=self.params.gripper_speed_m_s,
                )
                self._hand_width = float(r["width"])
                if r.get("max_width"):
                    self._hand_max = min(self._hand_max, float(r["max_width"]))
            except ArmError as e:
                hand.close(1.0)
                hand = None
                notes.append(f"no Franka Hand: {_after(e)}")
        with self._lock:
            self._rt, self._hand = rt, hand
            self._have_state = True
            self.notes = notes
            self.realtime = str(reply.get("realtime", ""))
            self._last_error = None
            self._status = "connected"
        for n in notes:
            log.info("%s: %s", self.robot_ip, n)

    def initialize(self) -> None:
        with self._lock:
            self._check_can_initialize()
            rt = self._rt
            if rt is None:
                raise ArmError("cannot initialize: not connected")
            self._status = "initializing"
            epoch = self._epoch
        t = threading.Thread(target=self._initialize, args=(rt, epoch), daemon=True)
        self._init_thread = t
        t.start()

    def _initialize(self, rt: _Child, epoch: int) -> None:
        p = self.params
        try:
            rt.call("finish", 10.0)  # a re-initialize from ready: end the running loop first
            rt.call("recover", 30.0)
            rt.call("configure", 10.0, **p.wire())
            rt.call(
                "start",
                10.0,
                velocity=list(p.velocity_rad_s),
                accel=list(p.accel_rad_s2),
                jerk=list(p.jerk_rad_s3),
            )
        except ArmError as e:
            with self._lock:
                if epoch == self._epoch:
                    self._fail_locked(f"initialize failed: {_after(e)}")
            return
        with self._lock:
            if epoch == self._epoch and self._status == "initializing":
                self._status = "ready"
                self._calibrated = True

    def read_joints(self) -> Q:
        """The robot's measured joints; as the contract says, only once `ready` has been
        reached (after an error: the last the robot sent)."""
        with self._lock:
            if not self._calibrated:
                raise ArmError("joint angles unknown: the arm was never initialized")
        return self.shm.snapshot().q

    def snapshot(self) -> Snapshot:
        """The robot's newest state as the real-time process published it."""
        return self.shm.snapshot()

    def command(self, q_setpoint: Q) -> None:
        with self._lock:
            if self._status == "ready":
                self._watch_locked()
            accepted = self._accept_setpoint(q_setpoint)
            if accepted is None:
                return
            sp = accepted.tolist()
            for j, (x, lo, hi) in enumerate(zip(sp, self._lo, self._hi, strict=True)):
                if x < lo or x > hi:
                    self._fail_locked(f"setpoint q{j + 1}={x:.4f} rad outside the joint limits")
                    return
            q = self.shm.snapshot().q.tolist()
            jump = [abs(x - y) for x, y in zip(sp, q, strict=True)]
            worst = max(jump)
            if worst > self._max_step_rad:
                j = jump.index(worst)
                self._fail_locked(f"setpoint jump of {worst:.3f} rad on q{j + 1} refused")
                return
            self.shm.put_setpoint(sp, time.monotonic_ns())
            self.setpoints_accepted += 1

    def stop(self) -> None:
        with self._lock:
            if self._rt is not None:
                self.shm.request_hold()

    def robot_elapsed_s(self, wall_dt_s: float) -> float:
        """The robot's clock since the last call (the sum of libfranka's `readOnce`
        durations), while the loop runs; the wall's otherwise (`Clocked`)."""
        a = self.shm.a
        if a[S_CONTROLLING] == 0.0:
            self._t_robot_last = None
            return wall_dt_s
        t = float(a[S_T_ROBOT])
        last, self._t_robot_last = self._t_robot_last, t
        if last is None or t < last:
            return wall_dt_s
        return t - last

    def estop(self) -> None:
        with self._lock:
            rt = self._rt
            self._epoch += 1
            self._status = "error"
            self._last_error = "emergency stop"
        if rt is not None:
            rt.send("estop")

    def close(self) -> None:
        """Hold (each process finishes its motion), end the processes, release the block's
        file (its last state stays readable here: `snapshot`)."""
        with self._lock:
            self._epoch += 1
            self._stop_children()
            self._status = "disconnected"
            self.shm.path.unlink(missing_ok=True)

    def grip(self, grip: float) -> None:
        """The hand to `grip` (0 open … 1 closed) as a width; the newest wins."""
        if not (isinstance(grip, int | float) and 0.0 <= grip <= 1.0):
            return
        width = self._hand_max * (1.0 - float(grip))
        with self._lock:
            hand = self._hand
            if hand is None or self._status != "ready":
                return
            if self._hand_width is not None and abs(width - self._hand_width) <= GRIP_STEP_M:
                return
            self._hand_width = width
        hand.send("move", width=width)

    # --- internals ---------------------------------------------------------------------
    def _stop_children(self) -> None:
        """End both processes (each finishes its motion first); the caller holds the lock.
        A process whose robot went silent is blocked in libfranka's read: it is not waited for."""
        rt, hand = self._rt, self._hand
        self._rt = self._hand = None
        age_s = (time.monotonic_ns() - self.shm.a[S_WALL_NS]) * 1e-9
        wait_s = EXIT_WAIT_S if age_s <= self.watchdog_s else 0.2
        for child in (rt, hand):
            if child is not None:
                child.close(wait_s)

    def close_shared(self) -> None:
        """Release the shared block (after `close`)."""
        self.shm.close()

    def _watch_locked(self) -> None:
        """A lost link or a dead process is an error within one watchdog period."""
        rt = self._rt
        if rt is None:
            return
        if not rt.alive:
            self._fail_locked("link lost: the libfranka process ended")
            return
        a = self.shm.a
        age_s = (time.monotonic_ns() - a[S_WALL_NS]) * 1e-9
        # Not while initializing: recovery and configuration block the loop, with their own
        # time-outs; a loop that starts and never publishes fails the watchdog when ready.
        if age_s > self.watchdog_s and self._status in ("ready", "connected"):
            self._fail_locked(
                f"link lost: no robot state for {age_s * 1e3:.0f} ms "
                f"(watchdog {self.watchdog_s * 1e3:.0f} ms)"
            )

    def _on_event(self, msg: dict[str, Any]) -> None:
        if msg.get("event") == "gripper":
            if msg.get("ok") and "width" in msg:
                with self._lock:
                    self._hand_width = float(msg["width"])
            elif not msg.get("ok"):
                log.warning("Franka Hand: %s", msg.get("error", "move failed"))
            return
        if msg.get("event") != "fault":
            return
        kind = str(msg.get("kind", "control"))
        errors = [str(e) for e in msg.get("errors", [])][:41]
        why = fault_message(kind, str(msg.get("message", ""))[:300], errors)
        with self._lock:
            self.faults.append({"kind": kind, "errors": errors, "message": why})
            del self.faults[:-32]
            self._fail_locked(why)

    def _fail_locked(self, why: str) -> None:
        if self._status != "error":
            self._last_error = why
        self._status = "error"
        if self._rt is not None:
            self.shm.request_hold()

    def _flange_in_base(self, q: list[float]) -> pin.SE3:
        pin.framesForwardKinematics(self._pin, self._pin_data, np.asarray(q, dtype=np.float64))
        oMb = self._pin_data.oMf[self._base_fid]
        oMf = self._pin_data.oMf[self._flange_fid]
        return oMb.inverse() * oMf

    def _cross_check(self, reply: dict[str, Any]) -> str | None:
        """None when the robot's flange (O_T_EE · F_T_EE⁻¹) is where our FK puts it."""
        q = [float(x) for x in reply["q"]]
        O_T_EE = _se3(reply["O_T_EE"])
        F_T_EE = _se3(reply["F_T_EE"])
        robot = O_T_EE * F_T_EE.inverse()
        ours = self._flange_in_base(q)
        d_m = float(np.linalg.norm(robot.translation - ours.translation))
        d_rad = float(np.linalg.norm(pin.log3(robot.rotation.T @ ours.rotation)))
        if d_m > FK_TOLERANCE_M or d_rad > FK_TOLERANCE_RAD:
            return (
                f"the robot's flange is {d_m * 1e3:.1f} mm / {d_rad:.3f} rad from where model "
                f"{self.model.name!r} puts it ({self.model.flange_frame}) at the measured joints: "
                "the model or the flange frame is wrong; refusing to run"
            )
        return None

    def _ee_note(self, reply: dict[str, Any]) -> list[str]:
        F_T_EE = _se3(reply["F_T_EE"])
        d = float(np.linalg.norm(F_T_EE.translation - self._eMt.translation))
        if d > FK_TOLERANCE_M:
            return [
                f"the robot's end effector (Desk) is {d * 1e3:.1f} mm from the model's tool: "
                "the arm moves the model's tool; the wrench estimate is at the robot's"
            ]
        return []


def _se3(m16: list[float]) -> pin.SE3:
    """libfranka's column-major 4×4 as an SE3."""
    T = np.asarray(m16, dtype=np.float64).reshape((4, 4), order="F")
    R = T[:3, :3]
    # float32 on the wire: re-orthonormalise so SE3 holds a rotation
    u, _, vt = np.linalg.svd(R)
    return pin.SE3(u @ vt, T[:3, 3].copy())


def _after(e: BaseException) -> str:
    s = str(e)
    return s.removeprefix("libfranka: ")
