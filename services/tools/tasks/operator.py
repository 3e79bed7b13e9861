"""A scripted operator: a closed-loop "person" at a master station.

The person drives the robot ONLY through the master, as a human would: they move their
hand (a `VirtualMaster`'s hand pose), press and release the master-shift (clutch) when the
hand reaches the edge of its comfortable workspace, change the motion scale for fine
positioning and the mapping frame, and open or close the grip. They watch what an operator
sees: `robot/state` (the tool, as the console mirrors it), `workcell/state` (the scene, as
the stereo video shows it) and their station's `master/state`.

Moving the tool to a goal is a reach-and-correct loop. From the current engagement's
references, the hand pose at engagement (E0, M0) and the tool pose (p0, R0), the person
inverts the master mapping (eq. 5, PROTOCOL.md §2):

    E = E0 + J⁻¹·(p_aim − p0),   J = s_t·A (world frame) or s_t·R0·A (tool frame)
    M = M0·Rxyz(Rxyz⁻¹(R0ᵀ·R_aim) / s_r)

moves the hand there at a bounded speed (re-clutching at the workspace edge), waits for
the tool to settle, looks at the error and aims off by it (p_aim += p_goal − p_tool,
R_aim ← R_aim·R_toolᵀ·R_goal) until the tool is within tolerance.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, Literal, Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.bus import keys
from services.bus.errors import RpcError, TelerobotError, Unavailable
from services.bus.messages import Event, MasterState, Message, RobotState, mat3, vec
from services.bus.node import Node
from services.bus.rate import RateLoop
from services.bus.streams import wait_latest
from services.control.master.devices.virtual import VirtualMaster
from services.geometry import (
    angle_between,
    exp_so3,
    orthonormalize,
    rotation_angle,
    rxyz,
    rxyz_inv,
    slerp,
)
from services.world.workcell.messages import WORKCELL_STATE, ObjectView, WorkcellState, objects_of

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]
Frame = Literal["world", "tool"]
M = TypeVar("M", bound=Message)

IDENTITY9: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
READY = ("ready", "moving")


CALL_TIMEOUT_S = 5.0
"""How long the person waits for the arm to answer a question (through the decision)."""


class TaskFailed(TelerobotError):
    """The person could not do what the script asked (with what they saw)."""


# --- the station: how the person's actions reach the master ---------------------------------
class MasterLink(Protocol):
    """What a person does at a master station. Hand pose in the master frame (m; R 3×3)."""

    def set_hand(self, p: Vec, R: Mat, clutch: bool, grip: float | None) -> None:
        """The hand is here; the master-shift is pressed (clutch) or not; the grip."""

    def set_scale(self, scale_t: float, scale_r: float) -> dict[str, Any]:
        """Turn the station's scale knobs (0 < s ≤ 1); the station's status."""

    def set_frame(self, frame: Frame) -> dict[str, Any]:
        """Switch the mapping frame; the station's status."""


class DeviceLink:
    """A person at an in-process `VirtualMaster`: the hand moves the device; the knobs are
    the master's methods (`robot/master/<id>/rpc/set_scale`, `set_frame`)."""

    def __init__(
        self, device: VirtualMaster, node: Node, master_id: str, timeout_s: float = 2.0
    ) -> None:
        self.device = device
        self.node = node
        self.service = f"master/{master_id}"
        self.timeout_s = timeout_s

    def set_hand(self, p: Vec, R: Mat, clutch: bool, grip: float | None) -> None:
        self.device.set_hand(p, R, clutch=clutch, grip=grip)

    def set_scale(self, scale_t: float, scale_r: float) -> dict[str, Any]:
        args = {"scale_t": scale_t, "scale_r": scale_r}
        return self.node.call(self.service, "set_scale", args, self.timeout_s)

    def set_frame(self, frame: Frame) -> dict[str, Any]:
        return self.node.call(self.service, "set_frame", {"frame": frame}, self.timeout_s)


class BusLink(DeviceLink):
    """A person at a virtual master in another process: the hand goes through
    `robot/master/<id>/rpc/set_hand` (docs/protocol-extensions.md)."""

    def __init__(self, node: Node, master_id: str, timeout_s: float = 2.0) -> None:
        super().__init__(VirtualMaster(), node, master_id, timeout_s)

    def set_hand(self, p: Vec, R: Mat, clutch: bool, grip: float | None) -> None:
        args: dict[str, Any] = {"p": list(vec(p)), "R": list(vec(R)), "clutch": clutch}
        if grip is not None:
            args["grip"] = float(grip)
        self.node.call(self.service, "set_hand", args, self.timeout_s)


class Abort(Protocol):
    """A stop flag (threading.Event, services.bus.lifecycle.Shutdown)."""

    def is_set(self) -> bool: ...


# --- the person's eyes ------------------------------------------------------------------------
class Latest(Generic[M]):
    """The newest message of a stream that passes `accept`, with a condition to wait on."""

    def __init__(self, accept: Callable[[M], bool] | None = None) -> None:
        self._cond = threading.Condition()
        self._accept = accept
        self.latest: M | None = None
        self.count = 0

    def put(self, msg: M) -> None:
        if self._accept is not None and not self._accept(msg):
            return
        with self._cond:
            self.latest = msg
            self.count += 1
            self._cond.notify_all()

    def wait(self, pred: Callable[[M], bool], timeout_s: float) -> M | None:
        return wait_latest(self._cond, lambda: self.latest, pred, timeout_s)


class Observer:
    """What the operator sees: the tool (robot/state), the scene (workcell/state) and their
    own station (master/state of `master_id`). Subscriptions only store."""

    def __init__(self, node: Node, master_id: str) -> None:
        self.node = node
        self.master_id = master_id
        self._home_R: Mat | None = None
        self.robot: Latest[RobotState] = Latest()
        self.scene: Latest[WorkcellState] = Latest()
        self.station: Latest[MasterState] = Latest(lambda m: m.master == master_id)
        self._lock = threading.Lock()
        self.engagements_lost = 0
        self.last_loss: str = ""
        node.subscribe(keys.STATE, self.robot.put)
        node.subscribe(WORKCELL_STATE, self.scene.put)
        node.subscribe(keys.MASTER_STATE, self.station.put)
        node.subscribe(keys.EVENTS, self._on_event)

    def _on_event(self, ev: Event) -> None:
        """The console's status line: the decision server ended our engagement for a reason
        other than our own master-shift (watchdog, stop, e-stop, …)."""
        d = ev.data or {}
        if (
            ev.source == "decision"
            and ev.kind == "lease"
            and d.get("action") == "released"
            and d.get("master") == self.master_id
            and d.get("reason") != "disengaged"
        ):
            with self._lock:
                self.engagements_lost += 1
                self.last_loss = str(d.get("reason", ""))

    def tool(self) -> tuple[Vec, Mat]:
        """The newest tool pose (world): (p, R)."""
        st = self.robot.latest
        if st is None:
            raise TaskFailed("no robot/state: the operator cannot see the arm")
        return np.asarray(st.tool_p, dtype=float), mat3(st.tool_R)

    def home_R(self) -> Mat:
        """The tool's orientation at the arm's home configuration (world): the arm's own
        answer (its description's `home`, then `fk` of it, through the decision server),
        asked once. The tasks hold the tool so, pointing down, whatever the arm model."""
        if self._home_R is None:
            try:
                desc = self.node.call("decision", "describe", {}, CALL_TIMEOUT_S)
                home = (desc.get("named") or {}).get("home")
                if not isinstance(home, list):
                    raise TaskFailed("the arm's description names no home configuration")
                fk = self.node.call("decision", "fk", {"q": home}, CALL_TIMEOUT_S)
            except (RpcError, Unavailable) as e:
                raise TaskFailed(f"cannot ask the arm where home is: {e}") from None
            self._home_R = mat3(fk["tool_R"])
        return self._home_R

    def objects(self) -> dict[str, ObjectView]:
        ws = self.scene.latest
        if ws is None:
            raise TaskFailed("no workcell/state: the operator cannot see the scene")
        return objects_of(ws)

    def object(self, name: str) -> ObjectView:
        objs = self.objects()
        if name not in objs:
            raise TaskFailed(f"there is no {name!r} in the scene")
        return objs[name]


# --- the person -------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class OperatorConfig:
    """How the scripted person behaves (units in the names; hand in the master frame).

    rate_hz: how often the hand pose reaches the master (the device's sampling).
    hand_speed_m_s, hand_rot_speed_rad_s: how fast the hand moves on a reach.
    return_speed_m_s: how fast it moves back with the master-shift pressed.
    tool_speed_m_s, tool_rot_speed_rad_s: the tool speeds the person keeps below (they watch
      the arm; the supervisor's limits are 0.25 m/s and 1 rad/s by default).
    workspace_radius_m: the hand's comfortable reach around its rest point (the origin).
    max_hand_angle_rad: how far the wrist turns from neutral before re-clutching.
    settle_window_s, settle_tol_m, settle_tol_rad: the tool is "still" when it moved less
      than this over the window.
    tremor_m, tremor_rad: the hand's physiological tremor (std of a first-order low-pass
      noise, 50 ms time constant): what the scale knob is for near a target.
    step_timeout_s: the longest any single wait may take before the person gives up.
    engage_wait_s, engage_attempts: how long the person waits for the arm to take a new
      engagement before pressing and releasing the master-shift again, and how often.
    max_corrections, max_clutches: per reach.
    miss_m, miss_rad: a tool farther than this from where the hand put it did not follow
      (the supervisor held it, or it lagged): the person engages anew instead of aiming off.
    alignment: the station's master→slave axis alignment A (9 floats, row-major).
    seed: of the tremor.
    """

    rate_hz: float = 100.0
    hand_speed_m_s: float = 0.2
    hand_rot_speed_rad_s: float = 0.8
    return_speed_m_s: float = 0.5
    tool_speed_m_s: float = 0.2
    tool_rot_speed_rad_s: float = 0.8
    workspace_radius_m: float = 0.12
    max_hand_angle_rad: float = 1.2
    settle_window_s: float = 0.1
    settle_tol_m: float = 5e-5
    settle_tol_rad: float = 2e-4
    tremor_m: float = 0.0002
    tremor_rad: float = 0.001
    step_timeout_s: float = 15.0
    engage_wait_s: float = 1.5
    engage_attempts: int = 5
    max_corrections: int = 8
    miss_m: float = 0.004
    miss_rad: float = 0.035
    max_clutches: int = 12
    alignment: tuple[float, ...] = IDENTITY9
    seed: int = 0

    def __post_init__(self) -> None:
        for key in (
            "rate_hz",
            "hand_speed_m_s",
            "hand_rot_speed_rad_s",
            "return_speed_m_s",
            "tool_speed_m_s",
            "tool_rot_speed_rad_s",
            "workspace_radius_m",
            "max_hand_angle_rad",
            "settle_window_s",
            "settle_tol_m",
            "settle_tol_rad",
            "step_timeout_s",
            "engage_wait_s",
            "miss_m",
            "miss_rad",
        ):
            v = getattr(self, key)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{key} must be > 0, got {v!r}")
        for key in ("tremor_m", "tremor_rad"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{key} must be ≥ 0, got {v!r}")
        A = np.asarray(self.alignment, dtype=float)
        if A.size != 9 or not np.allclose(A.reshape(3, 3).T @ A.reshape(3, 3), np.eye(3)):
            raise ValueError("alignment must be a rotation (9 floats, row-major)")


@dataclass(frozen=True, slots=True)
class Reference:
    """One engagement as the person knows it: their hand (E0, M0) when it began and the
    tool pose (p0, R0, world) it began at; the scales and frame in force."""

    E0: Vec
    M0: Mat
    p0: Vec
    R0: Mat
    scale_t: float
    scale_r: float
    frame: Frame


def hand_for_tool(
    ref: Reference, p_aim: ArrayLike, R_aim: ArrayLike, alignment: ArrayLike
) -> tuple[Vec, Mat]:
    """Eq. (5) and PROTOCOL.md §2 inverted: the hand pose (master frame) that puts the tool
    at (p_aim, R_aim) (world) within the engagement `ref`.

        dp = s_t·A·(E − E0), p = p0 + dp (world) or p0 + R0·dp (tool)  ⇒  E = E0 + J⁻¹(p − p0)
        R = R0·Rxyz(s_r·Rxyz⁻¹(M0ᵀM))                                  ⇒  M = M0·Rxyz(a / s_r),
                                                                          a = Rxyz⁻¹(R0ᵀR)
    """
    A = np.asarray(alignment, dtype=float).reshape(3, 3)
    J = ref.scale_t * (A if ref.frame == "world" else ref.R0 @ A)
    E = ref.E0 + np.linalg.solve(J, np.asarray(p_aim, dtype=float) - ref.p0)
    a = rxyz_inv(ref.R0.T @ np.asarray(R_aim, dtype=float))
    return E, ref.M0 @ rxyz(a / ref.scale_r)


def tool_for_hand(
    ref: Reference, E: ArrayLike, Mh: ArrayLike, alignment: ArrayLike
) -> tuple[Vec, Mat]:
    """Eq. (5) and PROTOCOL.md §2 forward: the tool pose (world) the hand pose (E, Mh) asks
    for within the engagement `ref` (principal Rxyz⁻¹ branch)."""
    A = np.asarray(alignment, dtype=float).reshape(3, 3)
    dp = ref.scale_t * (A @ (np.asarray(E, dtype=float) - ref.E0))
    p = ref.p0 + (dp if ref.frame == "world" else ref.R0 @ dp)
    a = rxyz_inv(ref.M0.T @ np.asarray(Mh, dtype=float))
    return p, ref.R0 @ rxyz(ref.scale_r * a)


def ball_fraction(start: Vec, goal: Vec, centre: Vec, radius: float) -> float:
    """The largest α ∈ [0, 1] with start + α(goal − start) inside the ball (centre, radius);
    0 when the start is already on or outside its boundary in the direction of travel."""
    d = goal - start
    if float(np.linalg.norm(goal - centre)) <= radius:
        return 1.0
    a = float(d @ d)
    if a < 1e-18:
        return 1.0
    s = start - centre
    b = 2.0 * float(s @ d)
    c = float(s @ s) - radius * radius
    disc = b * b - 4.0 * a * c
    if disc < 0.0:
        return 0.0
    alpha = (-b + math.sqrt(disc)) / (2.0 * a)
    return float(min(1.0, max(0.0, alpha)))


@dataclass
class OperatorStats:
    """What the person did: clutches (re-clutch cycles), scale and frame changes, corrective
    reaches, grips, reaches done, and engagements started again after the supervisor had
    ended one."""

    clutches: int = 0
    scale_changes: int = 0
    frame_changes: int = 0
    corrections: int = 0
    grips: int = 0
    reaches: int = 0
    reengagements: int = 0
    log: list[str] = field(default_factory=list)


class Operator:
    """The scripted person (module docstring). Call `engage()` first; every method blocks
    until done or raises `TaskFailed` (each wait has a deadline, and `abort`, when set,
    stops the person at the next tick). Single-threaded: call it from one thread."""

    def __init__(
        self,
        link: MasterLink,
        eyes: Observer,
        config: OperatorConfig | None = None,
        abort: Abort | None = None,
    ) -> None:
        self.link = link
        self.abort = abort
        self.eyes = eyes
        self.config = config or OperatorConfig()
        self.A = np.asarray(self.config.alignment, dtype=float).reshape(3, 3)
        self.stats = OperatorStats()
        self._rate = RateLoop(self.config.rate_hz)
        self._dt = 1.0 / self.config.rate_hz
        self._rng = np.random.default_rng(self.config.seed)
        self._tremor = np.zeros(6)
        self._tau_s = 0.05
        self.hand_p = np.zeros(3)
        self.hand_R = np.eye(3)
        self.clutch = False
        self.grip_value = 0.0
        self.scale_t = 1.0
        self.scale_r = 1.0
        self.frame: Frame = "world"
        self.ref: Reference | None = None
        # The tool as the arm reported it, one sample per tick (a new `robot/state` seq
        # only), over a few settle windows: (seq, the arm's t_s, p, R). What `settle` looks
        # at, by the arm's own clock: on a starved host states arrive late and in bursts,
        # and a stale state repeated at each tick is not a still tool.
        span = max(16, math.ceil(3.0 * self.config.settle_window_s * self.config.rate_hz))
        self._seen: deque[tuple[int, float, Vec, Mat]] = deque(maxlen=span)
        self._still_seq = -1  # the last robot/state seq seen when the hand came to rest
        self._losses_seen = 0
        self._engaged_at_change = False
        self._t0 = time.monotonic()

    # --- the hand at the device's rate ----------------------------------------------------
    def _tick(self) -> None:
        if self.abort is not None and self.abort.is_set():
            raise TaskFailed("stopped")
        a = math.exp(-self._dt / self._tau_s)
        self._tremor = a * self._tremor + math.sqrt(1.0 - a * a) * self._rng.standard_normal(6)
        p = self.hand_p + self.config.tremor_m * self._tremor[:3]
        R = self.hand_R @ exp_so3(self.config.tremor_rad * self._tremor[3:])
        try:
            self.link.set_hand(p, R, self.clutch, self.grip_value)
        except (RpcError, Unavailable) as e:
            raise TaskFailed(f"the master station does not respond: {e}") from None
        st = self.eyes.robot.latest
        if st is not None and (not self._seen or st.seq != self._seen[-1][0]):
            self._seen.append((st.seq, st.t_ns * 1e-9, np.asarray(st.tool_p), mat3(st.tool_R)))
        self._rate.sleep()

    def _hand_at_rest(self) -> None:
        """From now the hand holds still: `settle` judges the states the arm sends after."""
        st = self.eyes.robot.latest
        self._still_seq = -1 if st is None else st.seq

    def _say(self, text: str) -> None:
        self.stats.log.append(f"{time.monotonic() - self._t0:7.2f} s  {text}")

    def _until(self, pred: Callable[[], bool], what: str, timeout_s: float | None = None) -> None:
        deadline = time.monotonic() + (timeout_s or self.config.step_timeout_s)
        while not pred():
            if time.monotonic() > deadline:
                raise TaskFailed(f"gave up waiting for {what}")
            self._tick()

    def move_hand(self, p: ArrayLike, R: ArrayLike | None = None) -> None:
        """Move the hand to (p, R) in a straight line and along the geodesic, at the
        hand's speeds, capped so the tool stays below the person's tool speeds."""
        goal_p = np.asarray(p, dtype=float)
        goal_R = self.hand_R if R is None else np.asarray(R, dtype=float)
        cfg = self.config
        v = (
            cfg.return_speed_m_s
            if self.clutch
            else min(cfg.hand_speed_m_s, cfg.tool_speed_m_s / self.scale_t)
        )
        w = cfg.hand_rot_speed_rad_s
        if not self.clutch:
            w = min(w, cfg.tool_rot_speed_rad_s / self.scale_r)
        dist = float(np.linalg.norm(goal_p - self.hand_p))
        ang = angle_between(self.hand_R, goal_R)
        n = max(1, math.ceil(max(dist / v, ang / w) / self._dt))
        p0, R0 = self.hand_p.copy(), self.hand_R.copy()
        for i in range(1, n + 1):
            u = i / n
            self.hand_p = p0 + u * (goal_p - p0)
            self.hand_R = slerp(R0, goal_R, u)
            self._tick()
        self._hand_at_rest()

    # --- watching the tool ------------------------------------------------------------------
    def settle(self) -> tuple[Vec, Mat]:
        """Hold the hand still until the tool is still: over settle_window_s of the arm's
        clock, every state the arm sent after the hand came to rest is within the tolerance
        of the newest. Returns the tool's mean pose over that window (the tremor's and the
        servo's jitter averaged: what a person judges by eye)."""
        cfg = self.config
        tol_m = cfg.settle_tol_m + 4.0 * cfg.tremor_m * (0.0 if self.clutch else self.scale_t)
        tol_r = cfg.settle_tol_rad + 4.0 * cfg.tremor_rad * (0.0 if self.clutch else self.scale_r)
        settled: list[tuple[Vec, Mat]] = []

        def still() -> bool:
            st = self.eyes.robot.latest
            if st is None or st.status not in READY:
                return False
            after = [s for s in self._seen if s[0] > self._still_seq]
            if len(after) < 3 or after[-1][1] - after[0][1] < cfg.settle_window_s:
                return False
            _, t_new, p_new, R_new = after[-1]
            window = [(p, R) for _, t, p, R in after if t >= t_new - cfg.settle_window_s]
            if len(window) < 3 or not all(
                float(np.linalg.norm(p - p_new)) <= tol_m and angle_between(R, R_new) <= tol_r
                for p, R in window
            ):
                return False
            settled.append(
                (
                    np.mean([p for p, _ in window], axis=0),
                    orthonormalize(np.mean([R for _, R in window], axis=0)),
                )
            )
            return True

        self._until(still, "the tool to settle")
        return settled[-1]

    # --- the station's controls -----------------------------------------------------------
    def engage(self) -> None:
        """Press and release the master-shift: a new engagement at the tool's pose."""
        self.press_clutch()
        self.release_clutch()

    def press_clutch(self) -> None:
        """Press the master-shift (and keep it pressed): the arm holds; the hand is free."""
        self.clutch = True
        # Two station reports after the press: the master has read the pressed hand at
        # least once (it arms the next engagement only then).
        n0 = self.eyes.station.count
        self._until(
            lambda: self.eyes.station.count >= n0 + 2 and self._station_active() is False,
            "the master to disengage",
        )
        self.ref = None

    def release_clutch(self) -> None:
        """Release the master-shift: a new engagement; wait for the arm to take it and
        record the engagement's references. If the arm does not follow (the supervisor
        refused the engagement: a stale stream, another master's lease), press and
        release again, as a person would, up to `engage_attempts` times."""
        for attempt in range(1, self.config.engage_attempts + 1):
            before = self._robot_engage()
            station = self.eyes.station.latest
            self.clutch = False
            self._wait_station_engaged(station.engage if station is not None else -1)
            try:
                self._wait_arm_engage_change(before, self.config.engage_wait_s)
                break
            except TaskFailed:
                if attempt == self.config.engage_attempts:
                    raise
                self.stats.reengagements += 1
                self._say("the arm does not follow: master-shift again")
                self.press_clutch()
        self._rebase()

    def _wait_station_engaged(self, after: int) -> None:
        self._until(
            lambda: (s := self.eyes.station.latest) is not None and s.active and s.engage > after,
            "the master to engage",
        )

    def _wait_arm_engage_change(self, before: int, timeout_s: float | None = None) -> None:
        self._until(
            lambda: self._robot_engage() != before, "the arm to follow the engagement", timeout_s
        )

    def _ensure_engaged(self) -> None:
        """If the decision server ended our engagement (watchdog, …), engage again, as a
        person who sees the arm stop following would."""
        if self.ref is not None and self.eyes.engagements_lost != self._losses_seen:
            self._say(f"engagement lost ({self.eyes.last_loss}): engaging again")
            self.stats.reengagements += 1
            self.engage()

    def _rebase(self) -> None:
        self._losses_seen = self.eyes.engagements_lost
        self._hand_at_rest()
        p0, R0 = self.settle()
        self.ref = Reference(
            self.hand_p.copy(), self.hand_R.copy(), p0, R0, self.scale_t, self.scale_r, self.frame
        )

    def _station_active(self) -> bool | None:
        s = self.eyes.station.latest
        return None if s is None else bool(s.active)

    def _robot_engage(self) -> int:
        st = self.eyes.robot.latest
        return -1 if st is None else int(st.engage)

    def set_scale(self, scale_t: float, scale_r: float | None = None) -> None:
        """Turn the scale knobs (a new engagement starts where the tool is)."""
        scale_r = self.scale_r if scale_r is None else scale_r
        if (scale_t, scale_r) == (self.scale_t, self.scale_r):
            return
        self._change(lambda: self.link.set_scale(scale_t, scale_r))
        self.scale_t, self.scale_r = scale_t, scale_r
        self.stats.scale_changes += 1
        self._say(f"scale {scale_t:g}/{scale_r:g}")
        self._after_change()

    def set_frame(self, frame: Frame) -> None:
        """Switch the mapping frame (a new engagement starts where the tool is)."""
        if frame == self.frame:
            return
        self._change(lambda: self.link.set_frame(frame))
        self.frame = frame
        self.stats.frame_changes += 1
        self._say(f"frame {frame}")
        self._after_change()

    def _change(self, action: Callable[[], dict[str, Any]]) -> None:
        """Turn a knob the way a person does while engaged: press the master-shift, turn
        it, bring the hand back to its rest point, release (one new engagement)."""
        self._engaged_at_change = self.ref is not None
        if self._engaged_at_change:
            self._ensure_engaged()
            self.settle()
            self.press_clutch()
        try:
            action()
        except (RpcError, Unavailable) as e:
            raise TaskFailed(f"the station refused: {e}") from None

    def _after_change(self) -> None:
        if not self._engaged_at_change:
            return  # takes effect at the next engagement
        self.move_hand(np.zeros(3))
        self.release_clutch()

    def set_grip(self, value: float) -> None:
        """Close (1) or open (0) the gripper and wait until the arm reports it."""
        if self.ref is None:
            raise TaskFailed("the grip acts only while engaged")
        self._ensure_engaged()
        self.settle()
        self.grip_value = float(value)
        self.stats.grips += 1
        for attempt in range(1, self.config.engage_attempts + 1):
            try:
                self._until(self._grip_followed, "the gripper to follow", self.config.engage_wait_s)
                return
            except TaskFailed:
                # The grip travels with the engagement: one the supervisor ended does not
                # carry it. Engage again (if it was ended) and wait once more.
                if attempt == self.config.engage_attempts:
                    raise
                self._ensure_engaged()

    def _grip_followed(self) -> bool:
        st = self.eyes.robot.latest
        return st is not None and st.grip is not None and abs(st.grip - self.grip_value) < 1e-9

    def grasp(self, name: str) -> None:
        """Close the gripper on `name` and see it held."""
        self.set_grip(1.0)
        self._until(
            lambda: (ws := self.eyes.scene.latest) is not None and ws.held == name,
            f"{name} to be held",
            timeout_s=2.0,
        )
        self._say(f"grasped {name}")

    def release(self, name: str) -> None:
        """Open the gripper and see `name` come to rest."""
        self.set_grip(0.0)
        self._until(
            lambda: (
                (ws := self.eyes.scene.latest) is not None
                and ws.held == ""
                and self.eyes.object(name).phase in ("resting", "toppled")
            ),
            f"{name} to come to rest",
            timeout_s=3.0,
        )
        self._say(f"released {name} on {self.eyes.object(name).on}")

    # --- reaching -------------------------------------------------------------------------------
    def reach(
        self,
        p_goal: ArrayLike,
        R_goal: ArrayLike | None = None,
        tol_m: float = 0.002,
        tol_rad: float = math.radians(1.0),
    ) -> tuple[float, float]:
        """Bring the tool to (p_goal, R_goal) (world; R None: keep the orientation) within
        the tolerances, re-clutching at the hand workspace's edge and correcting what is
        left. Returns the final (position error m, angle error rad)."""
        if self.ref is None:
            raise TaskFailed("reach: not engaged")
        cfg = self.config
        goal_p = np.asarray(p_goal, dtype=float)
        goal_R = self.eyes.tool()[1] if R_goal is None else np.asarray(R_goal, dtype=float)
        aim_p, aim_R = goal_p.copy(), goal_R.copy()
        corrections = clutches = 0
        centre = np.zeros(3)
        while True:
            self._ensure_engaged()
            ref = self.ref
            assert ref is not None
            hand_p, hand_R = hand_for_tool(ref, aim_p, aim_R, self.A)
            alpha_p = ball_fraction(self.hand_p, hand_p, centre, 0.98 * cfg.workspace_radius_m)
            alpha_r = _angle_fraction(self.hand_R, hand_R, 0.98 * cfg.max_hand_angle_rad)
            alpha = min(alpha_p, alpha_r)
            if alpha >= 1.0:
                self.move_hand(hand_p, hand_R)
                p, R = self.settle()
                if self.eyes.engagements_lost != self._losses_seen:
                    aim_p, aim_R = goal_p.copy(), goal_R.copy()  # what it saw was a hold
                    continue
                err_p, err_r = float(np.linalg.norm(goal_p - p)), angle_between(R, goal_R)
                if err_p <= tol_m and err_r <= tol_rad:
                    self.stats.reaches += 1
                    self._say(
                        f"reached within {err_p * 1e3:.2f} mm, {math.degrees(err_r):.2f}° "
                        f"({corrections} corrections)"
                    )
                    return err_p, err_r
                corrections += 1
                self.stats.corrections += 1
                self._say(f"correcting {err_p * 1e3:.2f} mm, {math.degrees(err_r):.2f}°")
                if corrections > cfg.max_corrections:
                    raise TaskFailed(
                        f"could not bring the tool within {tol_m * 1e3:g} mm / "
                        f"{math.degrees(tol_rad):g}° of the goal "
                        f"(left: {err_p * 1e3:.2f} mm, {math.degrees(err_r):.2f}°)"
                    )
                if err_p > cfg.miss_m or err_r > cfg.miss_rad:
                    # Not a residual: the arm did not do what the hand asked (it held, or
                    # lagged). Start from where the tool is, with the aim on the goal.
                    self._say("the arm did not follow the hand: master-shift again")
                    self.stats.reengagements += 1
                    aim_p, aim_R = goal_p.copy(), goal_R.copy()
                    self.engage()
                    continue
                aim_p = aim_p + (goal_p - p)
                aim_R = aim_R @ R.T @ goal_R
                continue
            clutches += 1
            if clutches > cfg.max_clutches:
                raise TaskFailed("too many re-clutches: the goal seems out of reach")
            if alpha > 0.02:
                self.move_hand(
                    self.hand_p + alpha * (hand_p - self.hand_p), slerp(self.hand_R, hand_R, alpha)
                )
            way = hand_p - self.hand_p
            back = (
                -0.6 * cfg.workspace_radius_m * way / np.linalg.norm(way)
                if float(np.linalg.norm(way)) > 1e-9 and alpha_p < 1.0
                else self.hand_p.copy()
            )
            self.reclutch(back, np.eye(3) if alpha_r < 1.0 else None)

    def reclutch(self, hand_p: ArrayLike, hand_R: ArrayLike | None = None) -> None:
        """Press the master-shift, carry the hand to (hand_p, hand_R), release."""
        self.press_clutch()
        self.move_hand(hand_p, hand_R)
        self.stats.clutches += 1
        self._say("re-clutch")
        self.release_clutch()

    def let_go(self) -> None:
        """Press the master-shift and keep it pressed: the arm holds where it is."""
        self.press_clutch()
        self.settle()


def _angle_fraction(R_now: Mat, R_goal: Mat, limit_rad: float) -> float:
    """The largest α ∈ [0, 1] such that slerp(R_now, R_goal, α) stays within `limit_rad`
    of the neutral hand orientation (bisection; the angle is unimodal along a geodesic)."""
    if rotation_angle(R_goal) <= limit_rad:
        return 1.0
    if rotation_angle(R_now) >= limit_rad:
        return 0.0
    lo, hi = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if rotation_angle(slerp(R_now, R_goal, mid)) <= limit_rad else (lo, mid)
    return lo


__all__ = [
    "BusLink",
    "DeviceLink",
    "MasterLink",
    "Observer",
    "Operator",
    "OperatorConfig",
    "OperatorStats",
    "Reference",
    "TaskFailed",
    "ball_fraction",
    "hand_for_tool",
    "tool_for_hand",
]
