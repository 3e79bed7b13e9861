"""Force feedback: the wrist wrench measured at the slave's tool, shown on the operator's hand.

Inputs: a ForceSample (f, c at the tool point, tool frame) and the tool orientation
`tool_R` (world ← tool) from RobotState. The operator moves in the master frame, which A
maps onto the slave axes the command is expressed in: world axes in `world` mode, tool axes
in `tool` mode (PROTOCOL §2). The displayed wrench is mapped back the same way (A is a
rotation, so its inverse is Aᵀ), scaled, and saturated with its direction kept.

`ForceDisplay` is the one path from the wrist to the hand that the master service uses:
that mapping, then zero unless engaged, a ramp-in after each engagement, the contact's
friction shown scaled (`contact_tangential_gain`), a hook where a master-side controller
(passivity) can change the wrench before the device shows it, and a damper on the hand's
motion while a contact is shown (`contact_damping_ns_m`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from services.control.master.config import Frame, MasterConfig
from services.control.master.device import HandReading
from services.geometry import Array3, is_rotation


@dataclass(frozen=True, slots=True)
class DisplayWrench:
    """What to show the operator: force f (3,) N and moment c (3,) N·m in the master frame,
    and whether each was cut down to its limit."""

    f: Array3
    c: Array3
    force_saturated: bool
    torque_saturated: bool


def saturate(v: ArrayLike, max_norm: float) -> tuple[Array3, bool]:
    """v scaled down to norm max_norm when longer, direction kept; (v', was_saturated)."""
    x = np.asarray(v, dtype=float).reshape(3)
    norm = math.hypot(*x)  # no overflow for huge components, unlike a dot product
    if norm > max_norm:
        return x * (max_norm / norm), True
    return x, False


def operator_wrench(
    f_tool: ArrayLike,
    c_tool: ArrayLike,
    tool_R: ArrayLike,
    *,
    alignment: ArrayLike,
    frame: Frame,
    force_scale: float,
    max_force_n: float,
    max_torque_nm: float,
    hand_R: ArrayLike | None = None,
) -> DisplayWrench:
    """The wrench to display on the operator's hand.

    world mode: f_m = s · Aᵀ · tool_R · f_tool (tool → world → master frame);
    tool mode:  f_m = s · Aᵀ · f_tool (the operator's axes are mapped onto the tool's);
    either mode: c_m = s · M · c_tool, M = `hand_R` (the hand's orientation in the master
    frame; None: the identity). The moment goes where the rotation commands come from:
    eq. (5) turns the tool by the hand's own rotation, the hand's axes onto the tool's
    (R = R0·M0ᵀ·M at scale_r = 1, no alignment, in either mode), so the moment about the
    tool's axes is shown about the hand's as they stand, and the power it has against the
    hand's turn is the tool moment's against the tool's turn. Shown about the world's axes
    instead (as until 2026-11-27 in world mode), a tool pointing down turned the moment
    about z over: it pushed the hand along its turn, not against it (docs/master.md).
    Then |f_m| ≤ max_force_n and |c_m| ≤ max_torque_nm, direction kept.
    Raises ValueError on non-finite input or a tool_R or hand_R that is not a rotation.
    """
    f = np.asarray(f_tool, dtype=float).reshape(3)
    c = np.asarray(c_tool, dtype=float).reshape(3)
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(c))):
        raise ValueError("force and moment must be finite")
    A = np.asarray(alignment, dtype=float).reshape(3, 3)
    if frame == "world":
        R = np.asarray(tool_R, dtype=float).reshape(3, 3)
        if not is_rotation(R):
            raise ValueError("tool_R must be a rotation")
        to_master = A.T @ R
    elif frame == "tool":
        to_master = A.T
    else:
        raise ValueError("frame must be 'world' or 'tool'")
    if hand_R is not None:
        M = np.asarray(hand_R, dtype=float).reshape(3, 3)
        if not is_rotation(M):
            raise ValueError("hand_R must be a rotation")
        c = M @ c
    f_m, f_sat = saturate(force_scale * (to_master @ f), max_force_n)
    c_m, c_sat = saturate(force_scale * c, max_torque_nm)
    return DisplayWrench(f_m, c_m, f_sat, c_sat)


class ForceFeedback:
    """`operator_wrench` with the settings of a MasterConfig."""

    def __init__(self, config: MasterConfig) -> None:
        self._A = config.alignment_matrix
        self._force_scale = config.force_scale
        self._max_force_n = config.max_force_n
        self._max_torque_nm = config.max_torque_nm

    def compute(
        self,
        f_tool: ArrayLike,
        c_tool: ArrayLike,
        tool_R: ArrayLike,
        frame: Frame,
        hand_R: ArrayLike | None = None,
    ) -> DisplayWrench:
        """The display wrench for a ForceSample (f, c) and RobotState.tool_R (9 or 3×3);
        `frame` is the teleoperation frame in use (Teleop.frame); `hand_R` the hand's
        orientation now (the moment is shown about its axes)."""
        return operator_wrench(
            f_tool,
            c_tool,
            tool_R,
            alignment=self._A,
            frame=frame,
            force_scale=self._force_scale,
            max_force_n=self._max_force_n,
            max_torque_nm=self._max_torque_nm,
            hand_R=hand_R,
        )

    @staticmethod
    def zero() -> DisplayWrench:
        """Nothing to display (no or stale force data)."""
        return DisplayWrench(np.zeros(3), np.zeros(3), False, False)


WrenchHook = Callable[[DisplayWrench, HandReading, float], DisplayWrench]
"""hook(wrench, hand, dt_s) -> wrench: changes the wrench about to be displayed (master
frame), knowing the hand reading of this tick and the time since the previous one. Called
by the loop thread, only while engaged; its output is saturated again."""


CONTACT_DAMPING_FULL_N = 1.0
"""The contact damper's gain ramps in with the force shown (after the hook), from 0 at no
force to `contact_damping_ns_m` at this force (N) and above: free motion is not damped, and
the damper never switches on at once under a moving hand."""
VELOCITY_CUTOFF_HZ = 100.0
"""The hand's velocity for the damper: its position differenced each tick, low-passed at
this cutoff (a first-order filter: position noise of a µm at 1 kHz is 1 mm/s raw)."""
MAX_DAMPED_DT_S = 0.05
"""A tick longer than this (a stalled loop) restarts the velocity estimate: a step over a
long gap is not the hand's velocity now."""


class HandVelocity:
    """The hand's velocity (m/s, master frame) from its positions tick by tick, low-passed
    at VELOCITY_CUTOFF_HZ; zero until two positions less than MAX_DAMPED_DT_S apart."""

    def __init__(self) -> None:
        self._p: Array3 | None = None
        self.v: Array3 = np.zeros(3)

    def reset(self) -> None:
        self._p = None
        self.v = np.zeros(3)

    def update(self, hand_p: ArrayLike, dt_s: float) -> Array3:
        p = np.asarray(hand_p, dtype=float).reshape(3)
        prev, self._p = self._p, p
        if prev is None or not 0.0 < dt_s <= MAX_DAMPED_DT_S:
            self.v = np.zeros(3)
            return self.v
        alpha = 1.0 - math.exp(-2.0 * math.pi * VELOCITY_CUTOFF_HZ * dt_s)
        self.v = self.v + alpha * ((p - prev) / dt_s - self.v)
        return self.v


def contact_damping(f_shown: ArrayLike, v_hand: ArrayLike, b_ns_m: float) -> Array3:
    """The damper's force (N, master frame) on a hand moving at `v_hand` while `f_shown` is
    shown: −b·v with b = `b_ns_m` × min(|f_shown| / CONTACT_DAMPING_FULL_N, 1). Passive: its
    power against the hand, −b·|v|², is never positive."""
    f = np.asarray(f_shown, dtype=float).reshape(3)
    gain = b_ns_m * min(math.hypot(*f) / CONTACT_DAMPING_FULL_N, 1.0)
    return -gain * np.asarray(v_hand, dtype=float).reshape(3)


CONTACT_NORMAL_N = 1.0
"""A contact begins when the wrist force reaches this (N); its normal is taken from the
forces of this size or more over its first NORMAL_WINDOW_S, while the force is mostly the
press and its friction not yet built up."""
CONTACT_LOST_N = 0.5
CONTACT_LOST_S = 0.1
"""Below CONTACT_LOST_N (N, the wrist force) for CONTACT_LOST_S the contact is over; the
next one takes its normal anew (a touch's bounces are one contact)."""
NORMAL_WINDOW_S = 0.1
"""The normal is the mean of the force's directions over the contact's first this many
seconds."""
FORCE_CAP_N = 1e6
"""The wrist force is bounded to this size (direction kept) before its normal is taken:
far above any display's limit, far below where its arithmetic could overflow."""


class ContactNormal:
    """The contact's normal (unit, in the frame of the forces it is given) tick by tick: the
    mean of the force's directions over the contact's first NORMAL_WINDOW_S (its samples of
    CONTACT_NORMAL_N or more, one vote each, so neither a touch's chatter and impact nor
    one absurd sample tilts it much), kept until the force has stayed below CONTACT_LOST_N
    for CONTACT_LOST_S; None out of contact and while the window fills (directions that
    mostly cancel, their mean under 0.5, name none: the window starts again)."""

    def __init__(self) -> None:
        self.n: Array3 | None = None
        self._sum = np.zeros(3)
        self._count = 0
        self._since_s: float | None = None
        self._low_since_s: float | None = None

    def reset(self) -> None:
        self.n = None
        self._sum = np.zeros(3)
        self._count = 0
        self._since_s = self._low_since_s = None

    def update(self, f_shown: ArrayLike, now_s: float) -> Array3 | None:
        f = np.asarray(f_shown, dtype=float).reshape(3)
        size = math.hypot(*f)
        if self._since_s is not None:
            if size < CONTACT_LOST_N:
                if self._low_since_s is None:
                    self._low_since_s = now_s
                elif now_s - self._low_since_s >= CONTACT_LOST_S:
                    self.reset()
                    return None
            else:
                self._low_since_s = None
        if size >= CONTACT_NORMAL_N and self.n is None:
            if self._since_s is None:
                self._since_s = now_s
            self._sum = self._sum + f / size  # each sample's direction, one vote each
            self._count += 1
            if now_s - self._since_s >= NORMAL_WINDOW_S:
                size_sum = math.hypot(*self._sum)
                if size_sum >= 0.5 * self._count:
                    self.n = self._sum / size_sum
                else:  # forces that cancel name no normal: the window starts again
                    self._sum, self._count, self._since_s = np.zeros(3), 0, now_s
        return self.n


def across_normal(f_shown: ArrayLike, n: ArrayLike, gain: float) -> Array3:
    """`f_shown` with its part across the unit normal `n` scaled by `gain`: (f·n)n +
    gain·(f − (f·n)n). Never longer than `f_shown` for a gain within 0 … 1."""
    f = np.asarray(f_shown, dtype=float).reshape(3)
    u = np.asarray(n, dtype=float).reshape(3)
    along = float(f @ u) * u
    return along + gain * (f - along)


def ramp_gain(since_engaged_s: float, ramp_s: float) -> float:
    """0 → 1 linearly over `ramp_s` after an engagement (1 at once when ramp_s is 0)."""
    if ramp_s <= 0.0:
        return 1.0
    return min(max(since_engaged_s / ramp_s, 0.0), 1.0)


class ForceDisplay:
    """The displayed wrench, tick by tick (the loop thread only).

    `update(measured, frame, engaged, hand, dt_s, now_s)`:
    1. `measured` = (f, c, tool_R) from the freshest ForceSample and RobotState, or None when
       there is none or it is stale: mapped by `operator_wrench` (scale, A, saturation);
       non-finite input counts a fault and shows zero;
    2. zero unless the master is engaged (master-shift, before the first engagement, after
       a device fault: the hand is not coupled to the slave, so it is not pushed);
    3. × `ramp_gain` since the tick the master engaged (a rebase while engaged does not
       restart it), so a contact force held through a re-clutch does not kick the hand;
       likewise since the force came back after a stale gap (the display was zero through
       it, and the wrist may press harder now: a stream that resumes does not kick either);
    4. with `contact_tangential_gain` < 1, the wrist force's part across the contact's
       normal (`ContactNormal`, in the world frame) × that gain (`across_normal`), before
       step 1's mapping: what the device shows, and so what a passivity port in the hook
       observes;
    5. `hook` (None: unchanged), then saturated again to max_force_n / max_torque_nm;
    6. with `contact_damping_ns_m` > 0, the contact damper on the hand's velocity
       (`contact_damping`, outside the hook: a passivity port observes the contact's force,
       not the damper's), the sum saturated again.
    """

    def __init__(self, config: MasterConfig, hook: WrenchHook | None = None) -> None:
        self.feedback = ForceFeedback(config)
        self.hook = hook
        self._ramp_s = config.force_ramp_s
        self._max_force_n = config.max_force_n
        self._max_torque_nm = config.max_torque_nm
        self._damping_ns_m = config.contact_damping_ns_m
        self._tangential_gain = config.contact_tangential_gain
        self._normal = ContactNormal()
        self._velocity = HandVelocity()
        self._engaged_since_s: float | None = None
        self._fresh_since_s: float | None = None
        self.faults = 0

    def _hide_friction(self, f_tool: ArrayLike, tool_R: ArrayLike, now_s: float) -> ArrayLike:
        """The wrist force (tool frame) with its part across the contact's normal × the
        gain. The normal is kept in the world frame (`ContactNormal` on the world force), so
        a tool that turns in contact, or the `tool` frame, does not turn it. Input that is
        not a finite force and a rotation is returned as it is, for `compute` to refuse."""
        f = np.asarray(f_tool, dtype=float)
        R = np.asarray(tool_R, dtype=float)
        if f.shape != (3,) or R.size != 9 or not np.all(np.isfinite(f)):
            return f_tool
        R = R.reshape(3, 3)
        if not is_rotation(R):
            return f_tool
        # Direction kept, size bounded: a finite but absurd force (1e308 N) must not
        # overflow the rotation or the normal's sum; the display saturates it anyway.
        f_world = R @ saturate(f, FORCE_CAP_N)[0]
        n = self._normal.update(f_world, now_s)
        if n is None:
            return f
        return R.T @ across_normal(f_world, n, self._tangential_gain)

    def update(
        self,
        measured: tuple[ArrayLike, ArrayLike, ArrayLike] | None,
        frame: Frame,
        engaged: bool,
        hand: HandReading,
        dt_s: float,
        now_s: float,
    ) -> DisplayWrench:
        """The wrench to display this tick (see the class docstring); now_s is monotonic."""
        if not engaged:
            self._engaged_since_s = None
            self._velocity.reset()
            self._normal.reset()
            return ForceFeedback.zero()
        v_hand = self._velocity.update(hand.hand_p, dt_s) if self._damping_ns_m > 0.0 else None
        if self._engaged_since_s is None:
            self._engaged_since_s = now_s
        if measured is None:
            self._fresh_since_s = None
            mapped = ForceFeedback.zero()
            if self._tangential_gain < 1.0:
                self._normal.update(np.zeros(3), now_s)  # no force: towards the contact's end
        else:
            if self._fresh_since_s is None:
                self._fresh_since_s = now_s
            f_tool, c_tool, tool_R = measured
            if self._tangential_gain < 1.0:
                f_tool = self._hide_friction(f_tool, tool_R, now_s)
            try:
                mapped = self.feedback.compute(f_tool, c_tool, tool_R, frame, hand.hand_R)
            except ValueError:
                self.faults += 1
                return ForceFeedback.zero()
        since = self._engaged_since_s
        if self._fresh_since_s is not None:
            since = max(since, self._fresh_since_s)
        gain = ramp_gain(now_s - since, self._ramp_s)
        shown = DisplayWrench(
            gain * mapped.f, gain * mapped.c, mapped.force_saturated, mapped.torque_saturated
        )
        if self.hook is not None:
            hooked = self.hook(shown, hand, dt_s)
            f, f_sat = saturate(hooked.f, self._max_force_n)
            c, c_sat = saturate(hooked.c, self._max_torque_nm)
            if not (np.all(np.isfinite(f)) and np.all(np.isfinite(c))):
                self.faults += 1
                return ForceFeedback.zero()
            shown = DisplayWrench(
                f, c, hooked.force_saturated or f_sat, hooked.torque_saturated or c_sat
            )
        if v_hand is None:
            return shown
        f, f_sat = saturate(
            shown.f + contact_damping(shown.f, v_hand, self._damping_ns_m), self._max_force_n
        )
        return DisplayWrench(f, shown.c, shown.force_saturated or f_sat, shown.torque_saturated)
