"""The libfranka real-time process: `python -m services.control.arm.franka.rt --shm PATH`.

Started and owned by `FrankaArm` (driver.py), one per connection; it is the only place that
imports pylibfranka. Its main thread is the 1 kHz control loop: each cycle it takes the
robot's state (`readOnce`), takes the newest setpoint from the shared block (shm.py), steps
a Ruckig jerk-limited trajectory one robot millisecond toward it, writes the result
(`writeOnce`) and publishes the state. Nothing else runs in the cycle but a poll of its
request pipe.

Requests come as JSON lines on stdin, one at a time, each answered by one JSON line on the
reply pipe (the process's original stdout; libfranka's own prints go to stderr):

    connect {ip, realtime}       Robot(ip, kEnforce | kIgnore); its state
    configure {...}              collision behaviour, joint and Cartesian impedance
    recover                      automaticErrorRecovery
    start {velocity, accel, jerk} joint position control (joint impedance) until finish
    finish                       brake to rest, end the motion (motion_finished)
    estop                        leave the loop at once and `stop()` the robot
    read                         the state, once
    exit                         finish, then end the process

A fault is a line `{"event": "fault", "kind": "reflex" | "control" | "link", ...}` naming
libfranka's error flags. stdin closing (the arm service gone) finishes the motion and ends
the process: the robot holds.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import select
import sys
import time
from collections.abc import Callable
from typing import IO, Any

from services.control.arm.franka.errors import error_names, fault_kind
from services.control.arm.franka.shm import (
    RING,
    S_CONTROLLING,
    S_CYCLES,
    S_DQ,
    S_EE_T_K,
    S_F_EXT,
    S_F_T_EE,
    S_LOST,
    S_MODE,
    S_O_T_EE,
    S_Q,
    S_QC,
    S_RING,
    S_RING_I,
    S_SP_SEQ,
    S_SP_T,
    S_T_ROBOT,
    S_WALL_NS,
    N,
    Shared,
)

IDLE_POLL_S = 0.01
"""Outside the control loop the state is read at ~100 Hz (the arm's idle state rate)."""
FINISH_MAX_S = 5.0
"""A brake to rest that takes longer than this (robot time) ends the motion anyway."""
AT_REST_RAD_S = 1e-4


class Lines:
    """Complete lines from a file descriptor, read without blocking (after `select`)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.buf = b""
        self.eof = False

    def poll(self, timeout_s: float) -> list[bytes]:
        r, _, _ = select.select([self.fd], [], [], timeout_s)
        if r:
            chunk = os.read(self.fd, 65536)
            if not chunk:
                self.eof = True
            self.buf += chunk
        *lines, self.buf = self.buf.split(b"\n")
        return [x for x in lines if x.strip()]


class RealTime:
    """The process's state: the robot, the shared block, the reply pipe."""

    def __init__(self, shm: Shared, out: IO[str], lines: Lines) -> None:
        import pylibfranka

        self.pf = pylibfranka
        self.shm = shm
        self.out = out
        self.lines = lines
        self.robot: Any = None
        self.link_lost = False
        self.queue: list[dict[str, Any]] = []

    def reply(self, msg: dict[str, Any]) -> None:
        self.out.write(json.dumps(msg) + "\n")
        self.out.flush()

    # --- state -----------------------------------------------------------------------------
    def publish(self, st: Any, q_cmd: list[float] | None, controlling: bool) -> None:
        a = self.shm.begin_state()
        a[S_Q : S_Q + N] = st.q
        a[S_DQ : S_DQ + N] = st.dq
        a[S_QC : S_QC + N] = st.q if q_cmd is None else q_cmd
        a[S_O_T_EE : S_O_T_EE + 16] = st.O_T_EE
        a[S_F_EXT : S_F_EXT + 6] = st.O_F_ext_hat_K
        a[S_EE_T_K : S_EE_T_K + 16] = st.EE_T_K
        a[S_F_T_EE : S_F_T_EE + 16] = st.F_T_EE
        a[S_MODE] = float(int(st.robot_mode.value))
        a[S_CONTROLLING] = 1.0 if controlling else 0.0
        a[S_WALL_NS] = float(time.monotonic_ns())
        self.shm.end_state()

    def describe(self, st: Any) -> dict[str, Any]:
        return {
            "q": list(st.q),
            "O_T_EE": list(st.O_T_EE),
            "F_T_EE": list(st.F_T_EE),
            "EE_T_K": list(st.EE_T_K),
            "mode": st.robot_mode.name,
            "errors": error_names(st.current_errors),
            "last_motion_errors": error_names(st.last_motion_errors),
        }

    # --- requests --------------------------------------------------------------------------
    def handle(self, req: dict[str, Any]) -> bool:
        """Answer one request outside the control loop; False to end the process."""
        op = req.get("op")
        rid = req.get("id")
        pf = self.pf
        try:
            if op == "exit":
                self.reply({"id": rid, "ok": True})
                return False
            if op == "connect":
                self.reply({"id": rid, "ok": True, **self.connect(req)})
                return True
            if self.robot is None:
                raise RuntimeError("not connected")
            if op == "read":
                self.reply({"id": rid, "ok": True, **self.describe(self.robot.read_once())})
            elif op == "configure":
                r = self.robot
                r.set_collision_behavior(
                    req["lower_torque"], req["upper_torque"], req["lower_force"], req["upper_force"]
                )
                r.set_joint_impedance(req["joint_impedance"])
                r.set_cartesian_impedance(req["cartesian_impedance"])
                self.reply({"id": rid, "ok": True})
            elif op == "recover":
                self.robot.automatic_error_recovery()
                self.reply({"id": rid, "ok": True, **self.describe(self.robot.read_once())})
            elif op == "start":
                return self.control(req)
            elif op in ("finish", "estop"):
                self.reply({"id": rid, "ok": True})  # not moving: nothing to end
            else:
                raise RuntimeError(f"unknown request {op!r}")
        except pf.NetworkException as e:
            self.link_lost = True
            self.reply({"id": rid, "ok": False, "kind": "link", "error": _short(e)})
        except Exception as e:  # every failure of a request is its reply, never a crash
            self.reply({"id": rid, "ok": False, "kind": "control", "error": _short(e)})
        return True

    def connect(self, req: dict[str, Any]) -> dict[str, Any]:
        pf = self.pf
        ip = str(req["ip"])
        mode = req.get("realtime", "auto")
        realtime = "enforced"
        if mode == "ignore":
            robot = pf.Robot(ip, pf.RealtimeConfig.kIgnore)
            realtime = "ignored (arm.franka_realtime = ignore)"
        else:
            try:
                robot = pf.Robot(ip, pf.RealtimeConfig.kEnforce)
            except pf.RealtimeException as e:
                if mode == "enforce":
                    raise
                robot = pf.Robot(ip, pf.RealtimeConfig.kIgnore)
                realtime = f"ignored: {_short(e)}"
        self.robot = robot
        self.link_lost = False
        st = robot.read_once()
        self.publish(st, None, False)
        return {"realtime": realtime, **self.describe(st)}

    # --- the control loop ------------------------------------------------------------------
    def control(self, req: dict[str, Any]) -> bool:
        """Joint position control until finish, estop, exit or a fault; False to end."""
        from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig

        pf = self.pf
        rid = req.get("id")
        otg = Ruckig(N, 0.001)
        inp = InputParameter(N)
        out = OutputParameter(N)
        inp.max_velocity = req["velocity"]
        inp.max_acceleration = req["accel"]
        inp.max_jerk = req["jerk"]
        shm = self.shm
        a = shm.a
        ctrl = self.robot.start_joint_position_control(pf.ControllerMode.JointImpedance)
        st, _ = ctrl.readOnce()
        q0 = list(st.q_d)
        inp.current_position = q0
        inp.current_velocity = [0.0] * N
        inp.current_acceleration = [0.0] * N
        inp.target_position = q0
        inp.target_velocity = [0.0] * N
        sp_seq, hold, _, _ = shm.get_command()
        q_cmd = q0
        ctrl.writeOnce(pf.JointPositions(q_cmd))
        self.publish(st, q_cmd, True)
        a[S_SP_SEQ] = float(sp_seq)
        self.reply({"id": rid, "ok": True, "q": q0})
        ending: str | None = None  # finish | exit | estop
        end_id: Any = None
        t_end = 0.0
        lost = int(a[S_LOST])
        cycles = int(a[S_CYCLES])
        t_robot = float(a[S_T_ROBOT])
        last_wall = time.monotonic()
        ring_i = int(a[S_RING_I])
        ok_results = (Result.Working, Result.Finished)
        try:
            while True:
                st, dur = ctrl.readOnce()
                wall = time.monotonic()
                a[S_RING + ring_i % RING] = wall - last_wall
                ring_i += 1
                a[S_RING_I] = float(ring_i)
                last_wall = wall
                k = round(dur.to_sec() * 1000.0)
                if k > 1:
                    lost += k - 1
                t_robot += dur.to_sec()
                cycles += 1
                for r in self.lines.poll(0.0) if cycles % 4 == 0 else ():
                    ending, end_id = self._in_loop(r, ending, end_id)
                if self.lines.eof and ending is None:
                    ending = "exit"
                if ending == "estop":
                    break
                s_seq, s_hold, sp, _ = shm.get_command()
                if s_seq != sp_seq and ending is None:
                    sp_seq = s_seq
                    inp.control_interface = ControlInterface.Position
                    inp.target_position = sp
                    inp.target_velocity = [0.0] * N
                    a[S_SP_SEQ] = float(sp_seq)
                    a[S_SP_T] = float(time.monotonic_ns())
                # A hold (or the end) wins over a setpoint that came in the same cycle.
                if ending is not None or s_hold != hold:
                    hold = s_hold
                    inp.control_interface = ControlInterface.Velocity
                    inp.target_velocity = [0.0] * N
                    inp.target_acceleration = [0.0] * N
                for _ in range(max(k, 1) if k else 0):
                    res = otg.update(inp, out)
                    if res not in ok_results:
                        raise RuntimeError(f"interpolator: {res.name}")
                    out.pass_to_input(inp)
                if k:
                    q_cmd = list(out.new_position)
                at_rest = max(map(abs, inp.current_velocity)) < AT_REST_RAD_S
                if ending is not None:
                    t_end += dur.to_sec()
                    if at_rest or t_end > FINISH_MAX_S:
                        jp = pf.JointPositions(q_cmd)
                        jp.motion_finished = True
                        ctrl.writeOnce(jp)
                        break
                ctrl.writeOnce(pf.JointPositions(q_cmd))
                a[S_CYCLES] = float(cycles)
                a[S_LOST] = float(lost)
                a[S_T_ROBOT] = t_robot
                self.publish(st, q_cmd, True)
        except pf.NetworkException as e:
            self.link_lost = True
            self._fault("link", f"link lost: {_short(e)}", None)
            return not self.lines.eof
        except pf.ControlException as e:
            self._fault_after(e)
            return not self.lines.eof
        except Exception as e:  # the interpolator or a bad command: hold, say why
            self._stop_robot()
            self._fault("control", _short(e), None)
            return not self.lines.eof
        a[S_CYCLES] = float(cycles)
        a[S_LOST] = float(lost)
        a[S_CONTROLLING] = 0.0
        if ending == "estop":
            self._stop_robot()
        if end_id is not None or ending == "estop":
            self.reply({"id": end_id, "ok": True})
        queued, self.queue = self.queue, []
        for q in queued:
            if not self.handle(q):
                return False
        return ending != "exit"

    def _in_loop(self, raw: bytes, ending: str | None, end_id: Any) -> tuple[str | None, Any]:
        try:
            req = json.loads(raw)
        except ValueError:
            return ending, end_id
        op = req.get("op")
        if op == "estop":
            return "estop", req.get("id")
        if op in ("finish", "exit"):
            if op == "exit":
                self.queue.append({"op": "exit", "id": None})
            return (ending or "finish"), req.get("id")
        if op == "read":
            self.reply({"id": req.get("id"), "ok": True, "controlling": True})
            return ending, end_id
        self.reply({"id": req.get("id"), "ok": False, "kind": "busy", "error": f"{op}: moving"})
        return ending, end_id

    def _stop_robot(self) -> None:
        # the robot may be gone; stopping is best effort here
        with contextlib.suppress(Exception):
            self.robot.stop()

    def _fault_after(self, e: Exception) -> None:
        """A ControlException: the robot stopped the motion (a reflex, or a bad command)."""
        errors: list[str] = []
        mode = ""
        try:
            st = self.robot.read_once()
            errors = error_names(st.last_motion_errors) or error_names(st.current_errors)
            mode = st.robot_mode.name
            self.publish(st, None, False)
        except Exception:  # the state is a detail of the report; the fault is what counts
            pass
        self._fault(fault_kind(mode, str(e)), _short(e), errors, mode)

    def _fault(self, kind: str, message: str, errors: list[str] | None, mode: str = "") -> None:
        a = self.shm.a
        a[S_CONTROLLING] = 0.0
        self.reply(
            {
                "event": "fault",
                "kind": kind,
                "message": message,
                "errors": errors or [],
                "mode": mode,
            }
        )

    def idle(self) -> bool:
        """One idle step: a request, or a state read. False to end the process."""
        for raw in self.lines.poll(IDLE_POLL_S):
            try:
                req = json.loads(raw)
            except ValueError:
                continue
            if not self.handle(req):
                return False
        if self.lines.eof:
            return False
        if self.robot is not None and not self.link_lost:
            try:
                self.publish(self.robot.read_once(), None, False)
            except self.pf.NetworkException as e:
                self.link_lost = True
                self._fault("link", f"link lost: {_short(e)}", None)
            except Exception as e:  # reported once; the arm service decides what next
                self.link_lost = True
                self._fault("control", _short(e), None)
        return True


def gripper_main(out: IO[str], lines: Lines) -> int:
    """`--gripper`: the Franka Hand, one blocking move at a time, the newest grip wins."""
    import pylibfranka as pf

    gripper: Any = None
    speed = 0.1

    def reply(msg: dict[str, Any]) -> None:
        out.write(json.dumps(msg) + "\n")
        out.flush()

    while not lines.eof:
        reqs = []
        for raw in lines.poll(1.0):
            try:
                reqs.append(json.loads(raw))
            except ValueError:
                continue
        # Moves coalesce: only the newest width of what waited is driven to.
        moves = [r for r in reqs if r.get("op") == "move"]
        others = [r for r in reqs if r.get("op") != "move"]
        todo = others + moves[-1:]
        for req in todo:
            rid = req.get("id")
            try:
                if req.get("op") == "connect":
                    gripper = pf.Gripper(str(req["ip"]))
                    speed = float(req.get("speed", speed))
                    st = gripper.read_once()
                    reply({"id": rid, "ok": True, "width": st.width, "max_width": st.max_width})
                elif req.get("op") == "exit":
                    reply({"id": rid, "ok": True})
                    return 0
                elif gripper is None:
                    reply({"id": rid, "ok": False, "error": "not connected"})
                elif req.get("op") == "move":
                    width = float(req["width"])
                    done = gripper.move(width, speed)
                    st = gripper.read_once()
                    reply({"event": "gripper", "ok": bool(done), "width": st.width, "goal": width})
            except Exception as e:  # a failed move is reported; the arm goes on
                reply({"id": rid, "event": "gripper", "ok": False, "error": _short(e)})
    return 0


def _short(e: BaseException, n: int = 300) -> str:
    s = str(e) or type(e).__name__
    return s if len(s) <= n else s[:n] + "…"


def _reply_pipe() -> IO[str]:
    """The original stdout for replies; fd 1 from now on is stderr (libfranka's prints)."""
    fd = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    return os.fdopen(fd, "w", buffering=1)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot-franka-rt", description=__doc__)
    p.add_argument("--shm", help="the shared block (shm.py)")
    p.add_argument("--gripper", action="store_true", help="drive the Franka Hand instead")
    args = p.parse_args(argv)
    out = _reply_pipe()
    lines = Lines(0)
    if args.gripper:
        return gripper_main(out, lines)
    shm = Shared.attach(args.shm)
    rt = RealTime(shm, out, lines)
    step: Callable[[], bool] = rt.idle
    while step():
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
