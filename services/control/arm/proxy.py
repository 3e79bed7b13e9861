"""The arm's proxy: the paper's IProxyRobot component, for any arm model, free of the bus.

`ArmProxy` turns method calls (PROTOCOL.md §4) and the streamed supervised targets (§3)
into one joint setpoint per control cycle for an `Arm`, and reports status changes and
other events through `emit(kind, message, data)`. The pieces, each in a module of its own:
the control core (`control.ProxyControl`: tick, streamed commands, motions, status, events),
the safety filter (`safety`), time laws and paths (`trajectory`), planning (`planning`),
motion handles and generators (`motions`) and the methods' arguments (`arguments`).

Who calls what: `tick(dt_s)` is called by the service's fixed-rate loop and is the only
place that talks to the arm's setpoint stream; `rpc_*`, `on_target`, `state` and
`wait_motion` may be called from any thread (the bus's callbacks). One lock serialises
them; motion planning (many IK solves) runs outside it on a kinematics instance of its own.

Motions. A method that moves the robot (`move_joints`, `move_pose`, `move_relative`,
`home`) is accepted only when the robot is `ready` (at rest): `busy` while another motion
or the target stream is moving it. It returns `{"accepted": True, "motion": id}` at
once; `wait_motion(id, timeout_s)` blocks until that motion ends. A streamed target
pre-empts a running motion; `stop` brakes any motion to rest.

Safety, whatever the source of the motion (`safe_step`, applied every tick): a setpoint
never leaves the joint limits, no joint exceeds its speed limit, no joint its acceleration
limit (unless that is the only way to honour the other limits), and the tool point moves at
most `max_tool_speed_m_s` and the tool frame turns at most `max_tool_rot_speed_rad_s`
between two ticks. An arm error, a following error or a failed read puts the proxy in
`error`: the motion is abandoned, the arm holds, and nothing moves until `connect` and
`initialize`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from services.bus.bounds import check_each, check_norm, short
from services.bus.errors import RpcError
from services.control.arm.arguments import (
    RelFrame,
    arg_config,
    arg_fraction,
    arg_rotation,
    arg_vector,
    opt_frame,
    opt_rotation,
    opt_vector,
    too_long,
)
from services.control.arm.control import ProxyControl
from services.control.arm.driver import ArmError
from services.control.arm.kinematics import Kinematics, compose_floats
from services.control.arm.motions import Brake, Motion, Planned
from services.control.arm.planning import Plan, PlanFn, plan_joint, plan_pose

Vec = NDArray[np.float64]

SETPOINT_SHOWN_M = 1e-6
"""robot/state carries the setpoint's tool position (`tool_p_cmd`) while it is more than
this from the measured one on some axis: moving or settling. At rest the two agree and the
field is left out (each message costs ~0.3 µs more to decode with it)."""


class ArmProxy(ProxyControl):
    """The IProxyRobot of PROTOCOL.md §4 over an `Arm`; events go out through `emit`.

    `emit(kind, message, data)` is called outside the proxy's lock, in order, from whichever
    thread caused the event; kinds: `status`, `moved`, `error` (data `code`), `data`,
    `rejected`, `limit`, `estop`.
    """

    # --- methods (PROTOCOL §4, IProxyRobot) -----------------------------------------------

    def rpc_describe(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """The ArmDescription (PROTOCOL §1) of the model, with the tool in use."""
        with self._lock:
            tool_p, tool_R = self._eMt_floats
        out = self.model.description(tuple(tool_p), tuple(tool_R))  # type: ignore[arg-type]
        # What the arm holds the tool to (its `limits`): the decision supervises within them.
        out["max_tool_speed_m_s"] = self.limits.tool_speed_m_s
        out["max_tool_rot_speed_rad_s"] = self.limits.tool_rot_speed_rad_s
        out["max_target_step_m"] = self.config.max_target_step_m
        out["max_target_step_rad"] = self.config.max_target_step_rad
        return out

    def rpc_status(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """The robot state plus the proxy's settings and last error."""
        with self._lock:
            out = self._state_locked()
            out.update(
                {
                    "frame": self._frame,
                    "tool": self._tool_dict(),
                    "motion": self._motion.id if self._motion else None,
                    "estop": self._estopped,
                    "error": self._last_error,
                    "arm_status": self.arm.status,
                    "arm_error": self.arm.last_error,
                    "cmd_t_ns": self._last_cmd_t_ns,
                    "counters": dict(self.counters),
                }
            )
            return out

    def rpc_connect(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Connect to the arm (or reconnect after an error or e-stop). → `{status}`."""
        try:
            with self._lock:
                if self._status in ("connected", "initializing", "ready", "moving"):
                    return {"status": self._status}
                try:
                    self.arm.connect()
                except ArmError as e:
                    # the controller is absent or silent: not a fault of ours (`internal`)
                    self._fail("not_ready", f"connect failed: {e}")
                    raise RpcError("not_ready", f"connect failed: {e}") from None
                self._estopped = False
                self._last_error = None
                self._set_status("connected")
                return {"status": self._status}
        finally:
            self._flush()

    def rpc_initialize(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Calibrate the arm; `ready` follows when it is done. → `{status}`."""
        try:
            with self._lock:
                self._check_not_estopped()
                if self._status == "moving":
                    raise RpcError("busy", "the robot is moving; stop it first")
                if self._status == "initializing":
                    return {"status": self._status}
                if self._status not in ("connected", "ready"):
                    raise RpcError("not_ready", f"robot is {self._status}: connect first")
                try:
                    self.arm.initialize()
                except ArmError as e:
                    self._fail("internal", f"initialize failed: {e}")
                    raise RpcError("internal", f"initialize failed: {e}") from None
                self._set_status("initializing")
                return {"status": self._status}
        finally:
            self._flush()

    def rpc_set_tool(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Place the tool frame in the flange frame: `{p (m), R}` = eMt. Not while moving."""
        p = arg_vector(args, "p", 3)
        check_norm("p", p.tolist(), "tool_offset_m")  # a tool over 1 m is not an arm's tool
        R = arg_rotation(args, "R")
        with self._lock:
            if self._status == "moving":
                raise RpcError("busy", "cannot change the tool while moving")
            self._set_tool(pin.SE3(R, p))
            return self._tool_dict()

    def rpc_set_frame(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """The default frame of `move_relative`: world, wrist or tool."""
        frame = opt_frame(args)
        if frame is None:
            raise RpcError("bad_request", "frame: missing (world, wrist or tool)")
        with self._lock:
            self._frame = frame
            return {"frame": frame}

    def rpc_move_joints(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Joint-interpolated move to `q` (rad) at `speed` (fraction of the limits, default 1)."""
        q = arg_vector(args, "q", self.n)
        speed = arg_fraction(args, "speed")
        self._check_limits(q)
        return self._move(
            "move_joints", lambda kin, q0, eMt: plan_joint(kin, self.limits, q0, q, eMt, speed)
        )

    def rpc_home(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Joint-interpolated move to `home_q` of the configuration."""
        q = np.array(self.config.home_q, dtype=np.float64)
        return self._move(
            "home", lambda kin, q0, eMt: plan_joint(kin, self.limits, q0, q, eMt, 1.0)
        )

    def rpc_move_pose(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Move the tool frame to `{p, R}` (world) at `speed` (fraction of the limits, default
        1; an extension, docs/protocol-extensions.md). A straight line when the target is on the
        current branch and the line is clear of singularities, else joint-interpolated to the
        IK solution of branch `config` (default: the one nearest the current joints)."""
        p = arg_vector(args, "p", 3)
        check_each("p", p.tolist(), "position_m")
        R = arg_rotation(args, "R")
        config = arg_config(args)
        if config is not None and not self._plan_kin.analytic:
            raise RpcError(
                "bad_request", f"config: {self.model.name} has no analytic IK, hence no branches"
            )
        speed = arg_fraction(args, "speed")
        target = pin.SE3(R, p)
        return self._move(
            "move_pose",
            lambda kin, q0, eMt: plan_pose(kin, self.limits, q0, target, eMt, config, speed),
        )

    def rpc_move_relative(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Move the tool by `dp` (m) and turn it by `dR` about the tool point, both expressed
        in `frame` (world, wrist or tool; default: `set_frame`'s):
        p⁺ = p + R_f·dp, R⁺ = R_f·dR·R_fᵀ·R, with R_f = I, R_we or R_wt. In the tool frame this
        is PROTOCOL §2's tool mode (p + R0·dp, R0·dR)."""
        dp = arg_vector(args, "dp", 3)
        check_norm("dp", dp.tolist(), "displacement_m")
        if too_long(dp, self.config.max_dp_m):
            raise RpcError("bad_request", f"dp: |dp| above {self.config.max_dp_m} m")
        dR_arg = opt_rotation(args, "dR")
        dR = np.eye(3) if dR_arg is None else dR_arg
        speed = arg_fraction(args, "speed")
        frame_arg = opt_frame(args)
        with self._lock:
            frame: RelFrame = frame_arg or self._frame

        def plan(kin: Kinematics, q0: Vec, eMt: pin.SE3) -> Plan:
            oMe = kin.fk_flange(q0)
            oMt = oMe * eMt
            R_f = {"world": np.eye(3), "wrist": oMe.rotation, "tool": oMt.rotation}[frame]
            target = pin.SE3(R_f @ dR @ R_f.T @ oMt.rotation, oMt.translation + R_f @ dp)
            return plan_pose(kin, self.limits, q0, target, eMt, None, speed)

        return self._move("move_relative", plan)

    def rpc_stop(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Brake any motion to rest (within the acceleration limits). → `{status, motion}`.

        `now: true` (docs/protocol-extensions.md, the decision's contact stop): the arm
        holds where it measurably is at once, not after a braking distance; nothing latches.
        """
        now = args.get("now", False)
        if not isinstance(now, bool):
            raise RpcError("bad_request", "stop: now must be true or false")
        with self._lock:
            motion = self._motion
            if self._status == "moving":
                if now:
                    self._halt_here()
                elif not isinstance(self._gen, Brake):
                    self._gen = Brake()
            status = self._status
        self._flush()
        return {"status": status, "motion": motion.id if motion else None}

    def rpc_estop(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Emergency stop (an extension of IProxyRobot for the decision server's `estop`):
        the arm halts at once; `error` until `connect` and `initialize`."""
        with self._lock:
            self.arm.estop()
            self._estopped = True
            self._abandon("estop")
            self._event("estop", "emergency stop", {})
            self._set_status("error", "emergency stop")
            status = self._status
        self._flush()
        return {"status": status}

    def rpc_fk(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """Tool and flange poses (world) of joints `q` with the current tool."""
        q = arg_vector(args, "q", self.n)
        with self._lock:
            eMt = pin.SE3(self._eMt)
        with self._plan_lock:
            oMe = self._plan_kin.fk_flange(q)
        oMt = oMe * eMt
        return {
            "tool_p": _floats(oMt.translation),
            "tool_R": _floats(oMt.rotation.reshape(-1)),
            "flange_p": _floats(oMe.translation),
            "flange_R": _floats(oMe.rotation.reshape(-1)),
        }

    def rpc_ik(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """IK of the tool target `{p, R}` (world): every branch, in the limits or not, each
        with its `config`, for an analytic arm; the numerical solution nearest `seed`
        (default: the present joints) for any other (none when it does not converge)."""
        p = arg_vector(args, "p", 3)
        check_each("p", p.tolist(), "position_m")
        R = arg_rotation(args, "R")
        seed = opt_vector(args, "seed", self.n)
        if seed is not None:
            check_each("seed", seed.tolist(), "joint_rad")
        with self._lock:
            eMt = pin.SE3(self._eMt)
            q_ref = np.array(self._q_cmd) if seed is None else seed
        with self._plan_lock:
            sols = self._plan_kin.ik(pin.SE3(R, p), eMt, q_ref=q_ref)
        out = []
        for s in sols:
            sol: dict[str, Any] = {"q": _floats(s.q), "in_limits": bool(s.in_limits)}
            if s.config is not None:
                sol["config"] = s.config
            out.append(sol)
        return {"solutions": out}

    def rpc_limits(self, args: Mapping[str, Any]) -> dict[str, Any]:
        """The joint limits (rad) and the motion limits the proxy enforces."""
        lim = self.limits
        return {
            "q_lo": _floats(lim.q_lo),
            "q_hi": _floats(lim.q_hi),
            "max_joint_speed_rad_s": _floats(lim.vmax),
            "max_joint_accel_rad_s2": _floats(lim.amax),
            "max_tool_speed_m_s": lim.tool_speed_m_s,
            "max_tool_rot_speed_rad_s": lim.tool_rot_speed_rad_s,
        }

    def motion(self, motion_id: int) -> Motion:
        """The handle of a recent motion; RpcError("bad_request") if unknown."""
        with self._lock:
            m = self._motions.get(motion_id)
        if m is None:
            raise RpcError("bad_request", f"motion: no recent motion {motion_id!r}")
        return m

    def wait_initialized(self, timeout_s: float) -> dict[str, Any]:
        """Block until calibration ends: `{status: ready}`, or RpcError when it failed
        (`internal`) or took longer than `timeout_s` (`busy`: still initializing)."""
        with self._status_changed:
            done = self._status_changed.wait_for(lambda: self._status != "initializing", timeout_s)
            status, error = self._status, self._last_error
        if not done:
            raise RpcError("busy", f"still initializing after {timeout_s:g} s")
        if status != "ready":
            raise RpcError("internal", f"initialization ended {status}: {short(error)}")
        return {"status": status}

    def wait_motion(self, motion_id: int, timeout_s: float) -> dict[str, Any]:
        """Block until motion `motion_id` ends (or `timeout_s` passes): its result dict."""
        return self.motion(motion_id).wait(timeout_s)

    def state(self) -> dict[str, Any]:
        """RobotState of PROTOCOL §3 without seq/t_ns, as plain lists and floats.

        `q` is the measured joints (the last setpoint before the first reading); `engage` and
        `cmd_seq` are those of the last applied target (−1 before any).
        """
        with self._lock:
            return self._state_locked()

    def _state_locked(self) -> dict[str, Any]:
        out = dict(self._poses_locked())
        out["status"] = self._status
        out["engage"] = self._engage if self._engage is not None else -1
        out["cmd_seq"] = self._last_seq
        if self._grip is not None:
            out["grip"] = self._grip
        if self._cmd_rx_ns is not None:
            out["cmd_rx_ns"] = self._cmd_rx_ns
        if self._cmd_origin_t_ns is not None:
            out["cmd_origin_t_ns"] = self._cmd_origin_t_ns
        if self._setpoint_ns is not None:
            out["setpoint_ns"] = self._setpoint_ns
        p_cmd, p = self._pose_cmd[0], out["tool_p"]
        if max(abs(a - b) for a, b in zip(p_cmd, p, strict=True)) > SETPOINT_SHOWN_M:
            out["tool_p_cmd"] = list(p_cmd)
        return out

    def _poses_locked(self) -> dict[str, Any]:
        """Joints, tool and flange poses and manipulability of the measured joints; computed
        again only when the joints or the tool changed (an arm at rest costs nothing)."""
        q = self._q_meas if self._q_meas is not None else self._q_cmd
        cache = self._fk_cache
        if cache is not None and cache[0] == q and cache[1] == self._tool_version:
            return cache[2]
        oMe = self._kin.flange_pose_floats(q)
        tool_p, tool_R = compose_floats(oMe, self._eMt_floats)
        poses: dict[str, Any] = {
            "q": list(q),
            "tool_p": tool_p,
            "tool_R": tool_R,
            "flange_p": oMe[0],
            "flange_R": oMe[1],
            "manipulability": self._kin.manipulability(q),
        }
        self._fk_cache = (list(q), self._tool_version, poses)
        return poses

    def _tool_dict(self) -> dict[str, Any]:
        return {
            "tool_p": _floats(self._eMt.translation),
            "tool_R": _floats(self._eMt.rotation.reshape(-1)),
        }

    def _check_limits(self, q: Vec) -> None:
        for j in range(self.n):
            lo, hi = self.limits.q_lo[j], self.limits.q_hi[j]
            if not lo <= q[j] <= hi:
                raise RpcError("limit", f"q[{j}] = {q[j]:.6g} rad is outside [{lo:.4f}, {hi:.4f}]")

    def _check_not_estopped(self) -> None:
        if self._estopped:
            raise RpcError("estop", "the robot is e-stopped: connect and initialize to recover")

    def _check_can_move(self) -> None:
        self._check_not_estopped()
        if self._status == "moving":
            raise RpcError("busy", "the robot is moving: stop it or wait for the motion")
        if self._status != "ready":
            raise RpcError("not_ready", f"robot is {self._status}")

    def _move(self, kind: str, plan: PlanFn) -> dict[str, Any]:
        with self._lock:
            self._check_can_move()
            q0 = np.array(self._q_cmd)
            eMt = pin.SE3(self._eMt)
            tool_version = self._tool_version
        with self._plan_lock:
            path, law, goal, how = plan(self._plan_kin, q0, eMt)
        with self._lock:
            self._check_can_move()
            if q0.tolist() != self._q_cmd or self._tool_version != tool_version:
                raise RpcError("busy", "the robot moved while the motion was planned")
            # Right after a motion the setpoint may still carry its last step's velocity
            # (≤ amax·dt): start with one tick of hold so the acceleration stays in bounds.
            motion = Motion(self._new_id(), kind)
            self._start(motion, Planned(path, law, goal, hold_first=any(self._qd_cmd)))
        self._flush()
        return {
            "accepted": True,
            "motion": motion.id,
            "duration_s": law.duration_s,
            "path": how,
            "q": _floats(goal),
        }


def _floats(v: Any) -> list[float]:
    return [float(x) for x in np.asarray(v).reshape(-1)]
